"""Spacer disks: read from the widths along a tube, drawn into its outline and its mask."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from numpy.typing import NDArray

from pipeline.geometry.polyline import polyline_arclength, resample_polyline
from pipeline.reconstruct.disks import Disks, outline_along, read_disks, rims, spans_along
from pipeline.reconstruct.radius_profile import RadiusProfile

FloatArray = NDArray[np.float64]


def _widths(
    rng: np.random.Generator,
    radius_of: Callable[[FloatArray], FloatArray],
    disks: tuple[FloatArray, float, float] | None,
    *,
    frames: int = 16,
    length: float = 250.0,
) -> list[tuple[FloatArray, FloatArray]]:
    """Half-widths read along a tube by three views in each of ``frames`` frames, every
    ~1 mm from a random start: the tube's ``radius_of(arc)``, widened by each disk (arc
    lengths, radius, thickness) as its ellipse, seen at a random angle, reaches the line."""
    readings = []
    for _ in range(frames):
        arcs, halves = [], []
        for _ in range(3):
            arc = np.arange(rng.uniform(0.0, 1.0), length, 1.0)
            half = radius_of(arc) + rng.normal(0.0, 0.05, len(arc))
            if disks is not None:
                centres, big, thick = disks
                along = big * rng.uniform(0.05, 1.0)  # the ellipse's half-length along the tube
                for c in centres:
                    off = np.abs(arc - c)
                    inside = off < along + 0.5 * thick
                    reach = big * np.sqrt(
                        np.clip(1.0 - (np.maximum(off - 0.5 * thick, 0.0) / along) ** 2, 0, 1)
                    )
                    half = np.where(inside, np.maximum(half, reach), half)
            keep = rng.uniform(size=len(arc)) > 0.2  # crowded or unread samples
            arcs.append(arc[keep])
            halves.append(half[keep])
        readings.append((np.concatenate(arcs), np.concatenate(halves)))
    return readings


@pytest.mark.parametrize("seed", range(6))
def test_disks_are_read_where_they_are(seed: int) -> None:
    rng = np.random.default_rng(seed)
    r = rng.uniform(4.0, 8.0)
    spacing = rng.uniform(12.0, 36.0)
    big = r * rng.uniform(1.3, 2.0)
    centres = np.arange(spacing, 250.0 - 0.5 * spacing, spacing)
    found = read_disks(_widths(rng, lambda a: np.full(a.shape, r), (centres, big, rng.uniform(1.0, 4.0))))
    assert found is not None
    # Every disk found, each within a millimetre of its place, none that is not there.
    assert len(found.arc_mm) == len(centres)
    assert np.max(np.abs(found.arc_mm - centres)) < 1.0
    assert abs(found.radius_mm - big) < 0.05 * big


@pytest.mark.parametrize("seed", range(6))
def test_tubes_without_disks_have_none(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    r = rng.uniform(4.0, 8.0)
    step_at, ratio = rng.uniform(60.0, 190.0), rng.uniform(0.6, 1.5)
    profiles = [
        lambda a: np.full(a.shape, r),
        lambda a: r * (1.0 + (ratio - 1.0) * a / 250.0),  # tapered (or widening)
        lambda a: np.where(a < step_at, r, r * ratio),  # a step
    ]
    for radius_of in profiles:
        assert read_disks(_widths(rng, radius_of, None)) is None


@pytest.mark.parametrize("seed", range(4))
def test_a_step_read_short_here_and_there_is_no_disk(seed: int) -> None:
    # A tube 1.5 times wider over its first part, read short by a few millimetres in a few
    # places of it (another part's outline over it in most views): the wider part's
    # stretches between them are not disks.
    rng = np.random.default_rng(200 + seed)
    r = rng.uniform(4.0, 6.0)
    step_at = rng.uniform(100.0, 180.0)
    dips = rng.uniform(10.0, step_at - 10.0, size=3)

    def radius_of(a: FloatArray) -> FloatArray:
        wide = np.where(a < step_at, 1.5 * r, r)
        return np.where(np.min(np.abs(a[:, None] - dips[None]), axis=1) < 2.0, 1.25 * r, wide)

    assert read_disks(_widths(rng, radius_of, None)) is None


def test_too_few_frames_read_no_disks() -> None:
    rng = np.random.default_rng(3)
    readings = _widths(rng, lambda a: np.full(a.shape, 5.0), (np.arange(20.0, 240.0, 20.0), 9.0, 2.0))
    assert read_disks(readings[:2]) is None


def test_a_disk_seen_edge_on_spans_its_radius_at_its_place_only() -> None:
    from conftest import rig_cameras

    cam = rig_cameras()[0]
    # An axis across the view (perpendicular to the camera's optical axis, through the
    # point it looks at): a disk on it is seen edge-on, a bar 2 R long and its thickness wide.
    look = cam.camera_from_world.T @ np.array([0.0, 0.0, 1.0])
    point = cam.center_mm + 400.0 * look
    across = cam.camera_from_world.T @ np.array([1.0, 0.0, 0.0])
    axis = point[None] + np.linspace(-60.0, 60.0, 121)[:, None] * across[None]
    arc = polyline_arclength(axis)
    disks = Disks(np.array([60.0]), 10.0, 2.0)
    rim = rims(axis, arc, disks)
    assert rim.shape[0] == 1
    samples = np.array([57.0, 59.5, 60.0, 60.5, 63.0])  # arc lengths of the lines read
    pts = axis[0] + samples[:, None] * across[None]
    px = cam.project(pts)
    tangent_px = cam.project(pts + across) - px
    tangent_px /= np.linalg.norm(tangent_px, axis=1, keepdims=True)
    normal = np.column_stack([-tangent_px[:, 1], tangent_px[:, 0]])
    spans = spans_along([cam], rim, px[None], normal[None])[0, :, 0]  # (K, 2) px
    r_px = cam.focal_px * 10.0 / 400.0
    # Within half its thickness of the disk, the line crosses it from -R to R; farther, not.
    for k, s in enumerate(samples):
        if abs(s - 60.0) < 1.0:
            np.testing.assert_allclose(spans[k], [-r_px, r_px], rtol=0.03)
        else:
            assert np.isnan(spans[k]).all()


def test_the_outline_takes_the_spans_that_touch_the_tube() -> None:
    r = np.array([[5.0, 5.0, 5.0, 5.0]])
    spans = np.array(
        [
            [
                [[-9.0, 9.0], [np.nan, np.nan]],  # a disk across the line: both edges its
                [[3.0, 8.0], [7.5, 11.0]],  # two chained on one side
                [[5.3, 9.0], [np.nan, np.nan]],  # a gap of 0.3 px: within 0.5, one outline
                [[7.0, 9.0], [np.nan, np.nan]],  # clear of the tube: its edge is read first
            ]
        ]
    )
    lo, hi = outline_along(r, spans, gap_px=0.5)
    np.testing.assert_allclose(lo, [[-9.0, -5.0, -5.0, -5.0]])
    np.testing.assert_allclose(hi, [[9.0, 11.0, 9.0, 5.0]])


@pytest.fixture(scope="module")
def rendered_disk_tube() -> tuple[FloatArray, list, list, list, Disks]:
    """A bent r 5 tube with r 9 disks every 18 mm rendered with the synthetic renderer
    (its own disks): its axis, the cameras, the contrasts, the silhouettes, and the disks
    as the reconstruction takes them."""
    from conftest import rig_cameras

    from pipeline.reconstruct.tube_fit import foreground_contrast
    from pipeline.synth.images import background_texture, render_frame, threshold_for
    from pipeline.synth.radius_profiles import Disks as RenderedDisks
    from pipeline.synth.rig import make_rig

    s = np.linspace(0.0, 220.0, 441)
    curve = np.array([128.0, 128.0, 0.0]) + np.column_stack(
        [90.0 * (1 - np.cos(s / 90.0)), 25.0 * np.sin(s / 70.0), 90.0 * np.sin(s / 90.0)]
    )
    arcs = np.arange(18.0, 210.0, 18.0)
    backgrounds = [background_texture(320, 240, seed=5, camera_index=i) for i in range(3)]
    images = render_frame(make_rig(), curve, 5.0, backgrounds, seed=5, disks=RenderedDisks(arcs, 9.0, 2.0))
    contrasts = [foreground_contrast(im, polarity="dark") for im in images]
    silhouettes = [im < threshold_for("dark") for im in images]
    return curve, rig_cameras(), contrasts, silhouettes, Disks(arcs, 9.0)


def test_drawn_disks_put_the_sides_mid_points_on_the_axis(rendered_disk_tube: tuple) -> None:
    from pipeline.reconstruct.side_readings import read_sides

    curve, cameras, contrasts, _, disks = rendered_disk_tube
    pts = resample_polyline(curve, 56)
    offsets = {}
    for name, drawn in (("plain", None), ("drawn", RadiusProfile.of_disks(disks))):
        obs = read_sides(pts, cameras, contrasts, 5.0, 4.0, session_radii=drawn)
        centre, weight = obs.centres()
        offsets[name] = np.abs(centre[weight > 0])
        if name == "drawn":
            # The tube's own radius, read between the disks' outlines.
            assert abs(obs.radius_mm - 5.0) < 0.3
    # At the true axis, with the disks drawn the readings put it where it is (and read
    # more of the tube); without, the disks' ellipses put many a millimetre off.
    assert np.percentile(offsets["drawn"], 90) < 0.6
    assert np.percentile(offsets["plain"], 90) > 1.5 * np.percentile(offsets["drawn"], 90)
    assert len(offsets["drawn"]) > len(offsets["plain"])


def test_the_mask_drawn_holds_the_disks(rendered_disk_tube: tuple) -> None:
    from pipeline.reconstruct.quality import tube_masks

    curve, cameras, _, seen, disks = rendered_disk_tube
    plain = tube_masks(cameras, curve, 5.0)
    drawn = tube_masks(cameras, curve, 5.0, disks)
    for p, d, s in zip(plain, drawn, seen, strict=True):
        assert (d | p).sum() == d.sum()  # the tube is still drawn
        # The disks' pixels drawn are the silhouette's: most of what the plain tube misses.
        missed = s & ~p
        assert (missed & d).sum() > 0.7 * missed.sum()
        assert (d & ~s).sum() < 0.1 * d.sum()


@pytest.mark.parametrize("seed", range(3))
def test_a_start_from_the_hull_draws_the_disks(seed: int) -> None:
    """A start from the hull that draws the session's disks reads the tube's own radius
    between them, where one without reads the disks' outlines as the tube's."""
    from conftest import rig_cameras

    from pipeline.carve.hull import build_grid, carve, voxel_centers_mm
    from pipeline.reconstruct.centerline import fit_centerline
    from pipeline.reconstruct.tube_fit import foreground_contrast
    from pipeline.session.settings import Settings
    from pipeline.synth.images import background_texture, render_frame, threshold_for
    from pipeline.synth.radius_profiles import Disks as RenderedDisks
    from pipeline.synth.rig import make_rig

    rng = np.random.default_rng(seed)
    radius, spacing = rng.uniform(4.5, 6.5), rng.uniform(13.0, 18.0)
    disk_radius = radius * rng.uniform(1.5, 1.8)
    bend, sway, period = rng.uniform(60.0, 120.0), rng.uniform(15.0, 35.0), rng.uniform(50.0, 90.0)
    s = np.linspace(0.0, 220.0, 441)
    curve = np.array([128.0, 128.0, 0.0]) + np.column_stack(
        [bend * (1 - np.cos(s / bend)), sway * np.sin(s / period), bend * np.sin(s / bend)]
    )
    arcs = np.arange(spacing, 210.0, spacing)
    backgrounds = [background_texture(320, 240, seed=seed, camera_index=i) for i in range(3)]
    images = render_frame(
        make_rig(), curve, radius, backgrounds, seed=seed, disks=RenderedDisks(arcs, disk_radius, 2.0)
    )
    cameras = rig_cameras()
    contrasts = [foreground_contrast(im, polarity="dark") for im in images]
    masks = [im < threshold_for("dark") for im in images]
    workspace = Settings().workspace
    hull = voxel_centers_mm(workspace, carve(build_grid(tuple(cameras), workspace), masks))
    read = {}
    for name, drawn in (("plain", None), ("drawn", RadiusProfile.of_disks(Disks(arcs, disk_radius)))):
        _, fit = fit_centerline(
            hull,
            cameras,
            masks,
            contrasts,
            base_mm=curve[0],
            base_known=True,
            radius_mm=radius,
            voxel_mm=workspace.voxel_mm,
            session_radii=drawn,
        )
        read[name] = fit.radius_mm / radius
    # On twelve such tubes (seeds 0-11, 2026-12-07): 1.03-1.06 drawn, 1.24-1.72 not.
    assert abs(read["drawn"] - 1.0) < 0.1
    assert read["plain"] > 1.15


def test_a_profile_with_disks_goes_through_json() -> None:
    profile = RadiusProfile(np.array([1.0, 3.0]), np.array([5.0, 5.1]), Disks(np.array([20.0, 40.5]), 8.25))
    back = RadiusProfile.from_json(profile.to_json())
    assert back is not None and back.disks is not None
    np.testing.assert_allclose(back.disks.arc_mm, [20.0, 40.5])
    assert back.disks.radius_mm == 8.25
    alone = profile.disks_alone()
    assert alone is not None and len(alone.arc_mm) == 0
    assert np.isnan(alone.at(np.array([10.0]))).all()
    assert "2 spacer disks of radius 8.2 mm" in alone.describe()
    assert RadiusProfile.from_json('{"arc_mm": [], "radius_mm": []}') is None


def test_disks_from_the_tip_are_the_same_disks() -> None:
    # A tube 200 mm long, its axis run backwards: the disk 30 mm from the base is 170 mm
    # from the tip, and the order along the axis stays increasing.
    disks = Disks(np.array([30.0, 80.0, 150.0]), 9.0, 2.5)
    back = disks.from_tip(200.0)
    np.testing.assert_allclose(back.arc_mm, [50.0, 120.0, 170.0])
    assert (back.radius_mm, back.thickness_mm) == (9.0, 2.5)
    np.testing.assert_allclose(back.from_tip(200.0).arc_mm, disks.arc_mm)


def test_a_disk_projected_past_what_fixed_point_holds_is_not_drawn() -> None:
    from pipeline.reconstruct.tube_drawing import SUPERSAMPLE, draw_disks

    angle = np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False)
    ring = np.column_stack([np.cos(angle), np.sin(angle)])
    near = 10.0 + 4.0 * ring  # a disk of 4 px radius round pixel (10, 10)
    far = 5e7 + 4.0 * ring  # near a camera's plane: 5e7 px out, past int32 in fixed point
    canvas = np.zeros((20 * SUPERSAMPLE, 20 * SUPERSAMPLE), np.uint8)
    assert draw_disks(canvas, far[None], (0, 0)) == (0, 0, 0, 0)
    assert not canvas.any()
    x0, y0, x1, y1 = draw_disks(canvas, np.stack([near, far]), (0, 0))
    drawn = canvas > 0
    # pi 4^2 px of the image, SUPERSAMPLE^2 canvas pixels each.
    assert abs(drawn.sum() / SUPERSAMPLE**2 - np.pi * 16.0) < 3.0
    assert (
        not drawn[:y0].any() and not drawn[y1:].any() and not drawn[:, :x0].any() and not drawn[:, x1:].any()
    )
