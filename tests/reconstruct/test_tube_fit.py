"""The tube fit's parts: held samples, the crowding test's margin, the stem refitted.

(fit_tube on rendered tubes is tested in test_centerline.py.)
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from pipeline.geometry.polyline import polyline_arclength, resample_polyline
from pipeline.measure.evaluate import centerline_distances
from pipeline.reconstruct.side_readings import SideReadings, _crowded, consistent_readings
from pipeline.reconstruct.tube_fit import _solve_corrections, refit_body

FloatArray = NDArray[np.float64]
RADIUS = 6.0


def _sides_along_x(k: int, offset: FloatArray) -> tuple[FloatArray, SideReadings]:
    """K samples 4 mm apart along x, each read by two views (one along y, one
    along z) that put the axis ``offset`` (K, 2) mm off it."""
    pts = np.column_stack([np.arange(k) * 4.0, np.zeros(k), np.zeros(k)])
    rows = np.zeros((k, 2, 3))
    rows[:, 0, 1] = 1.0
    rows[:, 1, 2] = 1.0
    sides = SideReadings(
        rows,
        offset - RADIUS,
        offset + RADIUS,
        np.ones((k, 2, 2), dtype=bool),
        RADIUS,
        np.full((k, 2), RADIUS),
        np.full(k, RADIUS),
    )
    return pts, sides


def test_held_samples_stay_and_their_neighbours_join_them() -> None:
    k = 20
    offset = np.full((k, 2), 1.0)  # every view says: 1 mm over, in y and z
    pts, sides = _sides_along_x(k, offset)
    held = np.arange(k) >= 15
    step = _solve_corrections(pts, sides, base_fixed=True, smoothness=0.5, held=held)
    np.testing.assert_array_equal(step[held], 0.0)
    np.testing.assert_array_equal(step[0], 0.0)
    # Away from both held ends the readings win (the smoothness ties the
    # corrections only near them): within 0.05 mm of the 1 mm they ask for.
    np.testing.assert_allclose(step[6:10, 1:], 1.0, atol=0.05)
    # The join is smooth: the corrections fall towards the held part.
    assert step[14, 1] < step[10, 1]
    # Holding the first sample is the same as base_fixed.
    first = np.zeros(k, dtype=bool)
    first[0] = True
    np.testing.assert_array_equal(
        _solve_corrections(pts, sides, base_fixed=False, smoothness=0.5, held=first),
        _solve_corrections(pts, sides, base_fixed=True, smoothness=0.5),
    )


def test_crowding_margin_is_how_close_another_part_may_come() -> None:
    # One view: a part along +x at y = 0, and another coming back along -x at
    # y = 2 r + 3 px (60 mm later along the curve): their silhouettes are 3 px
    # apart. Within a 2 px margin they do not touch; within 4 px they do.
    r_px = 5.0
    x = np.arange(0.0, 40.0, 2.0)
    out = np.column_stack([x, np.zeros_like(x)])
    back = np.column_stack([x[::-1], np.full_like(x, 2 * r_px + 3.0)])
    px = np.concatenate([out, back])[None]
    t_hat = np.concatenate([np.tile([1.0, 0.0], (len(x), 1)), np.tile([-1.0, 0.0], (len(x), 1))])[None]
    arc = np.concatenate([x, 100.0 + x])
    radii = np.full((1, len(arc)), r_px)
    apart = 20.0
    loose = _crowded(px, t_hat, radii, arc, apart, margin_px=2.0)
    strict = _crowded(px, t_hat, radii, arc, apart, margin_px=4.0)
    assert not loose.any()
    # The normal of the outgoing part, (-t_y, t_x) = (0, 1), points at the other
    # part: its positive side is touched, its negative side is not; and the
    # other way round for the part coming back.
    assert strict[0, : len(x), 1].all() and not strict[0, : len(x), 0].any()
    assert strict[0, len(x) :, 1].all() and not strict[0, len(x) :, 0].any()


@pytest.fixture(scope="module")
def rendered_arc() -> tuple[FloatArray, list, list]:
    """A C-shaped tube (200 mm, bend radius 110 mm) rendered with the demo rig:
    its axis, the cameras, the foreground contrasts."""
    from conftest import rig_cameras

    from pipeline.reconstruct.tube_fit import foreground_contrast
    from pipeline.synth.images import background_texture, render_frame
    from pipeline.synth.rig import make_rig

    s = np.linspace(0.0, 200.0, 400)
    curve = np.array([128.0, 128.0, 0.0]) + np.column_stack(
        [110.0 * (1 - np.cos(s / 110.0)), 0 * s, 110.0 * np.sin(s / 110.0)]
    )
    backgrounds = [background_texture(320, 240, seed=3, camera_index=i) for i in range(3)]
    images = render_frame(make_rig(), curve, RADIUS, backgrounds, seed=3)
    return curve, rig_cameras(), [foreground_contrast(im, polarity="dark") for im in images]


def test_refit_body_brings_a_bumped_stem_back_and_holds_the_tip(rendered_arc: tuple) -> None:
    curve, cams, contrasts = rendered_arc
    pts = resample_polyline(curve, 51)  # 4 mm apart
    arc = polyline_arclength(pts)
    # A 3 mm bump sideways (y) mid-curve, as a tip's edges leave on the stem.
    bumped = pts + (3.0 * np.exp(-(((arc - 80.0) / 15.0) ** 2)))[:, None] * np.array([0.0, 1.0, 0.0])
    hold = float(arc[-1]) - 4.0 * RADIUS
    out = refit_body(bumped, cams, contrasts, radius_mm=RADIUS, hold_from_mm=hold)
    # Back on the axis: sub-pixel edges at ~0.5 px/mm, as fit_tube (~0.1 mm).
    assert centerline_distances(out, curve).max() < 0.5
    # The part past ``hold`` (in the input's arc length) is where it was,
    # resampled as the fit resamples it; the tip and the base are exactly kept.
    before = resample_polyline(bumped, len(out))
    held = polyline_arclength(before) >= hold
    assert held.sum() >= 6
    np.testing.assert_allclose(out[held], before[held], atol=1e-9)
    np.testing.assert_allclose(out[[0, -1]], bumped[[0, -1]], atol=1e-9)


def test_consistent_drops_the_reading_the_solution_disagrees_with() -> None:
    k = 20
    offset = np.random.default_rng(0).normal(0.0, 0.05, (k, 2))  # edge noise, mm
    offset[10, 0] = 4.0  # another part of the tube in view 0 at sample 10
    pts, sides = _sides_along_x(k, offset)
    step = _solve_corrections(pts, sides, base_fixed=False, smoothness=0.5)
    kept = consistent_readings(sides, step)
    assert not kept.use[10, 0].any()
    # Everything else stays: its residuals are noise, far under a quarter radius.
    assert kept.readings == sides.readings - 2
    again = _solve_corrections(pts, kept, base_fixed=False, smoothness=0.5)
    # Without the outlier, sample 10 sits where its neighbours and the noise say.
    assert abs(again[10, 1]) < 0.3 < abs(step[10, 1])
    assert consistent_readings(kept, again) is kept


def test_the_radius_profile_follows_a_step_and_ignores_disks() -> None:
    from pipeline.reconstruct.side_readings import _radius_profile

    k = 50
    arc = np.arange(k) * 4.0
    # Two views; the tube steps from 6 to 4 mm half way; every fifth sample reads a
    # spacer disk (9 mm) in both views; the last samples have no reading (the tip zone).
    truth = np.where(arc < 100.0, 6.0, 4.0)
    half = np.repeat(truth[:, None], 2, axis=1)
    half[::5] = 9.0
    both = np.ones((k, 2), dtype=bool)
    both[-3:] = False
    radii = _radius_profile(arc, half, both, np.full(k, 6.0))
    far_from_step = np.abs(arc - 100.0) > 20.0
    np.testing.assert_allclose(radii[far_from_step], truth[far_from_step])
    assert radii[-1] == 4.0  # the tip takes the thin end's radius
    # Without readings, the expected radius stands.
    np.testing.assert_array_equal(_radius_profile(arc, half, np.zeros((k, 2), bool), np.full(k, 6.0)), 6.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_views_width_is_read_against_the_radius_where_it_read_it(seed: int) -> None:
    from pipeline.reconstruct.side_readings import width_ratios

    rng = np.random.default_rng(seed)
    k = 40
    # A tube stepped from 6 to 4 mm half way; view 0 reads it 10 % wider (blur), view 1
    # as it is; view 2 too, but only its wider part has two edges there (the thinner part
    # crowded in that view), view 3 has too few two-edge readings to say.
    radii = np.where(np.arange(k) < k // 2, 6.0, 4.0)
    scale = np.array([1.1, 1.0, 1.0, 1.3])
    half = radii[:, None] * scale[None, :] + rng.normal(0.0, 0.02, size=(k, 4))
    both = np.ones((k, 4), dtype=bool)
    both[k // 2 :, 2] = False
    both[4:, 3] = False
    median = float(np.median(half[both]))
    np.testing.assert_allclose(width_ratios(half, both, radii, median), [1.1, 1.0, 1.0, 1.0], atol=0.02)
    # A uniform tube (its radius read within a few % along it): each view's readings
    # pooled against the tube's median radius.
    flat = 6.0 + rng.normal(0.0, 0.05, size=k)
    half = flat[:, None] * scale[None, :] + rng.normal(0.0, 0.02, size=(k, 4))
    median = float(np.median(half[both]))
    expected = [np.median(half[both[:, j], j]) / median if both[:, j].sum() >= 5 else 1.0 for j in range(4)]
    np.testing.assert_allclose(width_ratios(half, both, flat, median), expected)


def test_the_end_radius_is_the_tubes_where_disks_widen_most_readings() -> None:
    from pipeline.reconstruct.side_readings import _end_radius, _radius_profile

    rng = np.random.default_rng(7)
    k, views = 30, 3
    arc = np.arange(k) * 4.0
    half = 8.0 + rng.normal(0.0, 0.05, size=(k, views))
    # Disks seen at an angle: their ellipses widen four samples of every five in two views.
    disk = (np.arange(k) % 5 < 4)[:, None] & (np.arange(views) < 2)[None, :]
    half[disk] = 11.0 + rng.normal(0.0, 0.2, size=int(disk.sum()))
    both = np.ones((k, views), dtype=bool)
    both[-3:] = False  # the tip zone has no reading
    assert abs(_end_radius(arc, half, both) - 8.0) < 0.15
    # The profile there is the disks' (its median), the cap would be 2-3 mm too wide.
    assert _radius_profile(arc, half, both, np.full(k, 8.0))[-1] > 10.0
    # Fewer than three samples read: no end radius.
    assert np.isnan(_end_radius(arc, half, np.zeros((k, views), dtype=bool)))


@pytest.mark.parametrize("seed", range(4))
def test_the_end_radius_of_a_tapered_tube_is_its_end_s(seed: int) -> None:
    from pipeline.reconstruct.side_readings import _end_radius

    rng = np.random.default_rng(seed)
    k, views = 60, 3
    arc = np.arange(k) * 4.0
    end, slope = rng.uniform(2.5, 6.0), rng.uniform(0.005, 0.02)  # mm, mm a mm towards the base
    # The readings stop a few samples before the tip, as the tip zone's do.
    half = end + slope * (arc[-1] - arc)[:, None] + rng.normal(0.0, 0.03, size=(k, views))
    both = np.ones((k, views), dtype=bool)
    both[-2:] = False
    assert abs(_end_radius(arc, half, both) - end) < 0.02 * end + 0.03
    # A uniform tube's reading is its radius; one widening towards its end is read at its
    # window's lower quartile, not carried wider.
    uniform = end + rng.normal(0.0, 0.03, size=(k, views))
    assert abs(_end_radius(arc, uniform, both) - end) < 0.05
    widening = end - slope * (arc[-1] - arc)[:, None] + rng.normal(0.0, 0.03, size=(k, views))
    assert _end_radius(arc, widening, both) < end


@pytest.mark.parametrize("seed", range(8))
def test_an_end_radius_carried_along_scattered_readings_is_never_below_nothing(seed: int) -> None:
    from pipeline.reconstruct.side_readings import _end_radius

    # A lost fit's few readings, wide then narrow: no taper carries them below zero.
    rng = np.random.default_rng(seed)
    k, views = 11, 3
    arc = np.arange(k) * 4.0
    half = np.full((k, views), np.nan)
    both = np.zeros((k, views), dtype=bool)
    both[5:9] = True
    half[5:9] = np.repeat(rng.uniform([8.0, 8.0, 0.5, 0.5], [12.0, 12.0, 1.5, 1.5])[:, None], views, axis=1)
    radius = _end_radius(arc, half, both)
    assert np.isnan(radius) or radius > 0


@pytest.mark.parametrize(
    "far_mm", [(-15000.0, 300.0, -15000.0), (15000.0, -300.0, 15000.0), (-3000.0, 128.0, 2000.0)]
)
def test_a_diverged_curve_is_read_without_an_error(far_mm: tuple[float, float, float]) -> None:
    """A curve run off kilometres away passes by the cameras, where a sample projects to a
    tube wider than any image: that view has nothing to read there, and the rest is read."""
    from conftest import rig_cameras

    from pipeline.reconstruct.side_readings import read_sides

    cameras = rig_cameras("ninety")
    pts = np.linspace(np.array([128.0, 128.0, 60.0]), np.array(far_mm), 400)
    contrasts = [np.zeros((c.size_px[1], c.size_px[0]), np.float32) for c in cameras]
    obs = read_sides(pts, cameras, contrasts, np.full(len(pts), 6.0), 4.0)
    assert obs.rows.shape[:2] == (len(pts), len(cameras))
