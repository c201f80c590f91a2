"""Quality figures: the re-projected tube mask and its IoU with the silhouettes."""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest
from conftest import rig_cameras

from pipeline.carve.silhouette import extract_silhouette
from pipeline.reconstruct import quality
from pipeline.reconstruct.frame_result import FrameResult
from pipeline.reconstruct.quality import (
    misfit_fractions,
    off_smoothed,
    reprojection_iou,
    silhouette_iou,
    tube_mask,
    tube_masks,
    tube_width_px,
)
from pipeline.reconstruct.tracking import USUAL_MISFIT_MAX, usual_misfit
from pipeline.session.settings import SilhouetteSettings, Workspace
from pipeline.synth.images import THRESHOLD_DARK, render_frame
from pipeline.synth.rig import make_rig
from pipeline.synth.shapes import shape_centerlines

BASE = np.array([128.0, 128.0, 0.0])


def test_iou_of_simple_masks() -> None:
    a = np.zeros((10, 10), bool)
    b = np.zeros((10, 10), bool)
    assert silhouette_iou(a, b) == 1.0  # both empty: nothing to disagree on
    a[:, :4] = True
    assert silhouette_iou(a, b) == 0.0
    b[:, 2:6] = True  # overlap 2 columns, union 6
    assert silhouette_iou(a, b) == pytest.approx(2 / 6)
    assert silhouette_iou(a, a) == 1.0


def test_a_perfect_tube_has_iou_one_in_every_view() -> None:
    cams = rig_cameras()
    curve = shape_centerlines("s_curve", 12, base_mm=BASE)[4]
    masks = [tube_mask(cam, curve, 6.0) for cam in cams]
    assert all(m.sum() > 200 for m in masks)
    assert reprojection_iou(cams, masks, curve, 6.0) == (1.0, 1.0, 1.0)


def test_tube_mask_area_matches_the_projected_tube() -> None:
    cam = rig_cameras()[0]
    # A 150 mm rod through the workspace centre, across camera 0's line of sight.
    centre = np.array([128.0, 128.0, 128.0])
    across = np.cross(cam.camera_from_world[2], [0.0, 0.0, 1.0])
    across /= np.linalg.norm(across)
    rod = centre + np.outer(np.linspace(-75.0, 75.0, 20), across)
    depth = cam.to_camera(centre[None])[0, 2]
    px_per_mm = cam.matrix[0, 0] / depth
    expected = (2 * 6.0 * 150.0 + np.pi * 36.0) * px_per_mm**2  # sides + two round ends
    # Rasterising a ~6 px wide strip: the edge pixels make it +-1/2 px per side,
    # i.e. about +-8 % of the area; supersampling halves that.
    assert tube_mask(cam, rod, 6.0).sum() == pytest.approx(expected, rel=0.08)
    assert tube_mask(cam, rod, 6.0, supersample=4).sum() == pytest.approx(expected, rel=0.04)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_tubes_width_in_pixels_is_its_drawn_masks_area_over_its_length(seed: int) -> None:
    rng = np.random.default_rng(seed)
    cams = rig_cameras(["oblique", "ninety"][seed % 2])
    radius = float(rng.uniform(1.0, 8.0))
    centre = rng.uniform(100.0, 156.0, 3)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    rod = centre + np.outer(np.linspace(-40.0, 40.0, 20), direction)
    widths = tube_width_px(cams, rod, radius)
    for cam, width in zip(cams, widths, strict=True):
        a, b = cam.project(rod[[0, -1]])
        length_px = float(np.linalg.norm(b - a))
        # The drawn tube: its sides over the rod's image, plus its two round ends.
        area = tube_mask(cam, rod, radius, supersample=4).sum()
        drawn = (area - np.pi * width**2 / 4) / length_px
        assert width == pytest.approx(drawn, rel=0.15, abs=0.3)
    behind = tube_width_px(cams, rod - 1e4 * cams[0].camera_from_world[2], radius)
    assert np.isnan(behind[0])


@pytest.mark.parametrize("seed", range(3))
def test_a_frame_whose_edges_lie_off_its_tube_beyond_both_bars_is_unexplained(seed: int) -> None:
    rng = np.random.default_rng(seed)
    cams = rig_cameras(["oblique", "ninety"][seed % 2])
    radius = float(rng.uniform(2.0, 8.0))
    rod = rng.uniform(100.0, 156.0, 3) + np.outer(np.linspace(-40.0, 40.0, 20), [0.0, 0.0, 1.0])

    def widths_at(radius_mm: float) -> np.ndarray:
        return tube_width_px(cams, rod, radius_mm)

    # The residual at which each bar is met: in pixels (by the tube's mean width) and radii.
    width_px = float(np.mean(widths_at(radius)))
    at_px = quality.UNEXPLAINED_FRAME_PX * 2.0 * radius / width_px
    at_radii = quality.UNEXPLAINED_RADII * radius
    bar = max(at_px, at_radii)
    assert quality.unexplained_reason(widths_at(radius), radius, 0.98 * bar) == ""
    reason = quality.unexplained_reason(widths_at(radius), radius, 1.02 * bar)
    px, radii = (float(v) for v in re.findall(r"([\d.]+) (?:px|radii)", reason))
    assert px == pytest.approx(1.02 * bar * width_px / (2.0 * radius), abs=0.006)
    assert radii == pytest.approx(1.02 * bar / radius, abs=0.006)
    # Beyond one bar alone, nothing: a thin tube's fraction of a pixel, a thick one's sliver.
    assert quality.unexplained_reason(widths_at(radius), radius, (at_px + at_radii) / 2.0) == ""
    assert quality.unexplained_reason(widths_at(radius), radius, np.nan) == ""
    assert quality.unexplained_reason(widths_at(np.nan), np.nan, 1.0) == ""


def test_a_tube_thinner_than_a_pixel_draws_at_most_a_line() -> None:
    cam = rig_cameras()[0]
    rod = np.array([[128.0, 128.0, 60.0], [128.0, 128.0, 200.0]])
    # A radius far under half a pixel (a reading of nothing): no error, a thin mask.
    for supersample in (1, 4):
        mask = tube_mask(cam, rod, 0.01, supersample=supersample)
        assert mask.sum() < tube_mask(cam, rod, 3.0, supersample=supersample).sum() / 2


def test_true_curve_reprojects_onto_rendered_silhouettes() -> None:
    cams = rig_cameras()
    curve = shape_centerlines("bend_rotate", 12, base_mm=BASE)[3]
    backgrounds = [np.full((240, 320), 170.0) for _ in cams]
    images = render_frame(make_rig(), curve, 6.0, backgrounds, noise_sigma=0.0)
    settings = SilhouetteSettings(threshold=THRESHOLD_DARK)
    masks = [extract_silhouette(im, settings) for im in images]
    iou = reprojection_iou(cams, masks, curve, 6.0)
    # A ~6 px wide tube: one pixel of rasterisation disagreement along each edge
    # costs ~0.1 of IoU; measured 0.93-0.98 for the truth.
    assert min(iou) > 0.88
    # The same curve moved sideways by one radius is clearly worse.
    shifted = curve + np.array([6.0, 0.0, 0.0])
    assert max(reprojection_iou(cams, masks, shifted, 6.0)) < min(iou) - 0.2
    # The rendered tube's ends are flat, the drawn one's round: the round ends
    # are not counted as misfit, so the truth misfits by (almost) nothing (the
    # centre-line gate is 1 %), the shifted curve by far more.
    assert max(misfit_fractions(cams, masks, curve, 6.0)) < 0.005
    assert min(misfit_fractions(cams, masks, shifted, 6.0)) > 0.05


def test_misfit_is_zero_for_the_tube_itself_and_counts_what_a_short_curve_misses() -> None:
    from pipeline.geometry.polyline import cut_polyline, polyline_arclength

    cams = rig_cameras()
    curve = shape_centerlines("s_curve", 12, base_mm=BASE)[4]
    masks = [tube_mask(cam, curve, 6.0) for cam in cams]
    assert all(f == 0.0 for f in misfit_fractions(cams, masks, curve, 6.0))
    # A sixth of the tube missing leaves its share of each silhouette (a sixth
    # of the length, more or less foreshortened in each view: measured 17-30 %)
    # unexplained: far above a misfit of a few %. A third missing, more still.
    length = polyline_arclength(curve)[-1]
    sixth = misfit_fractions(cams, masks, cut_polyline(curve, length * 5 / 6), 6.0)
    third = misfit_fractions(cams, masks, cut_polyline(curve, length * 2 / 3), 6.0)
    assert all(0.1 < a < b < 1.0 for a, b in zip(sixth, third, strict=True)), (sixth, third)
    # Drawn a pixel wider or narrower than the silhouette: still no misfit.
    assert misfit_fractions(cams[:1], masks[:1], curve, 6.5) == (0.0,)
    assert misfit_fractions(cams[:1], [np.zeros_like(masks[0])], curve, 6.0) == (0.0,)  # nothing seen


def test_a_part_the_threshold_lost_but_the_grey_levels_show_is_no_misfit() -> None:
    from pipeline.reconstruct.tube_fit import foreground_contrast

    cams = rig_cameras()
    curve = shape_centerlines("bend_rotate", 12, base_mm=BASE)[3]
    backgrounds = [np.full((240, 320), 170.0) for _ in cams]
    images = render_frame(make_rig(), curve, 6.0, backgrounds, noise_sigma=0.0)
    masks = [extract_silhouette(im, SilhouetteSettings(threshold=THRESHOLD_DARK)) for im in images]
    contrasts = [foreground_contrast(im, polarity="dark") for im in images]
    # One view's silhouette loses a third of the tube (a faint part over a background as
    # dark, say); its image still shows it.
    rows = np.nonzero(masks[0].any(axis=1))[0]
    gap = masks[0].copy()
    gap[rows[0] : rows[0] + len(rows) // 3] = False
    gapped = [gap, *masks[1:]]
    assert misfit_fractions(cams, gapped, curve, 6.0)[0] > 0.1
    assert max(misfit_fractions(cams, gapped, curve, 6.0, contrasts)) < 0.005
    # Where the image shows background, the drawn tube strays as before.
    shifted = curve + np.array([6.0, 0.0, 0.0])
    plain = misfit_fractions(cams, masks, shifted, 6.0)
    assert misfit_fractions(cams, masks, shifted, 6.0, contrasts) == pytest.approx(plain, abs=0.01)
    assert min(plain) > 0.05


def test_masks_in_all_views_equal_the_per_view_ones() -> None:
    cams = rig_cameras()
    curve = shape_centerlines("helix", 12, base_mm=BASE)[7]
    # The same discs projected the same way (project_in_views is OpenCV's
    # arithmetic): identical masks, no tolerance.
    # ~100 and ~25 discs: over and under project_in_views' array threshold (48 points).
    for axis in (curve, curve[: len(curve) // 4]):
        for batched, cam in zip(tube_masks(cams, axis, 5.0), cams, strict=True):
            np.testing.assert_array_equal(batched, tube_mask(cam, axis, 5.0))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_windowed_mask_is_the_whole_masks_pixels_there(seed: int) -> None:
    rng = np.random.default_rng(seed)
    cam = rig_cameras()[seed % 3]
    curve = shape_centerlines("helix", 12, base_mm=BASE)[int(rng.integers(12))]
    w, h = cam.size_px
    for supersample in (1, 4):
        whole = tube_mask(cam, curve, 5.0, supersample=supersample)
        for _ in range(5):
            x0, y0 = int(rng.integers(0, w - 1)), int(rng.integers(0, h - 1))
            x1, y1 = int(rng.integers(x0 + 1, w + 1)), int(rng.integers(y0 + 1, h + 1))
            part = tube_mask(cam, curve, 5.0, supersample=supersample, window=((x0, y0), (x1, y1)))
            np.testing.assert_array_equal(part, whole[y0:y1, x0:x1])
        assert whole.any()


def test_a_hull_against_a_wall_other_than_the_bases_is_reported() -> None:
    box = Workspace(origin_mm=(-50.0, 0.0, 10.0), size_mm=(100.0, 100.0, 100.0), voxel_mm=2.0)
    base = np.array([0.0, 50.0, 10.0])  # on the floor
    column = np.column_stack([np.zeros(40), np.full(40, 50.0), 11.0 + 2.0 * np.arange(40)])  # z 11..89
    assert not quality.reaches_walls(column, box, base)  # on the base's wall only
    assert quality.reaches_walls(np.vstack([column, [[0.0, 50.0, 109.0]]]), box, base)  # the ceiling
    assert quality.reaches_walls(np.vstack([column, [[-49.0, 50.0, 60.0]]]), box, base)  # a side
    assert not quality.reaches_walls(np.vstack([column, [[-47.0, 50.0, 60.0]]]), box, base)  # a voxel in
    # A base on a side wall makes that wall the mount's, and the floor a wall like the others.
    side_base = np.array([-50.0, 50.0, 60.0])
    assert not quality.reaches_walls(np.array([[-49.0, 50.0, 60.0]]), box, side_base)
    assert quality.reaches_walls(np.array([[0.0, 50.0, 11.0]]), box, side_base)


# --- the suspect flag ----------------------------------------------------------------------------


def _arc_mm(n: int = 60) -> np.ndarray:
    """(n, 3) a quarter circle of radius 100 mm rising from the default base, mm."""
    angle = np.linspace(0.0, np.pi / 2, n)
    return np.column_stack([128.0 + 100.0 * (1 - np.cos(angle)), np.full(n, 128.0), 100.0 * np.sin(angle)])


def test_a_tube_that_matches_its_silhouettes_and_its_track_is_not_suspect() -> None:
    cams = rig_cameras()
    axis = _arc_mm()
    masks = quality.tube_masks(cams, axis, 6.0)
    iou, misfit = quality.tube_figures(cams, masks, axis, 6.0)
    length = float(np.linalg.norm(np.diff(axis, axis=0), axis=1).sum())
    reason = quality.suspect_reason(
        cams, masks, axis, 6.0, iou=iou, misfit=misfit, jump_mm=0.5, expected_length_mm=length + 2
    )
    assert reason == ""


def test_a_jump_is_judged_beyond_what_the_track_keeps_missing_its_predictions_by() -> None:
    cams = rig_cameras()
    axis = _arc_mm()
    masks = quality.tube_masks(cams, axis, 6.0)
    iou, misfit = quality.tube_figures(cams, masks, axis, 6.0)

    def reason(miss_mm: float) -> str:  # the prediction missed by 10 mm: more than a radius
        return quality.suspect_reason(
            cams, masks, axis, 6.0, iou=iou, misfit=misfit, jump_mm=10.0, prediction_miss_mm=miss_mm
        )

    # A track that steadily accelerates misses each frame's prediction by about as much.
    assert reason(0.0) == "10.0 mm from its track's prediction"
    assert reason(5.0) == ""
    assert "prediction" in reason(3.0)


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        ("silhouette", "the tube drawn in it differ by"),
        ("prediction", "from its track's prediction"),
        ("length", "length"),
        ("crossing", "passes through itself"),
    ],
)
def test_each_sign_of_a_wrong_curve_makes_it_suspect(change: str, expected: str) -> None:
    cams = rig_cameras()
    axis = _arc_mm()
    length = float(np.linalg.norm(np.diff(axis, axis=0), axis=1).sum())
    masks = quality.tube_masks(cams, axis, 6.0)
    jump, expected_length = 0.0, length
    if change == "silhouette":  # another part of the tube the curve does not explain
        masks = [
            m | o
            for m, o in zip(
                masks, quality.tube_masks(cams, axis + np.array([0.0, 60.0, 0.0]), 6.0), strict=True
            )
        ]
    elif change == "prediction":  # 3 radii from where the track said
        jump = 18.0
    elif change == "length":  # 5 mm longer than its track has it
        expected_length = length - 5.0
    else:  # the curve comes back through its own start
        axis = np.vstack([axis, axis[::-1][1:20] + np.array([0.0, 2.0, 0.0])])
    iou, misfit = quality.tube_figures(cams, masks, axis, 6.0)
    reason = quality.suspect_reason(
        cams,
        masks,
        axis,
        6.0,
        iou=iou,
        misfit=misfit,
        jump_mm=jump,
        expected_length_mm=expected_length,
    )
    assert expected in reason


@pytest.mark.parametrize("seed", range(3))
def test_a_silhouette_left_unexplained_counts_beyond_what_the_track_usually_leaves(seed: int) -> None:
    # Spacer disks (wider rings on the tube) that the drawn tube does not have: every
    # frame leaves their pixels unexplained, and that alone is not a wrong curve.
    rng = np.random.default_rng(seed)
    cams = rig_cameras()
    axis = _arc_mm()
    masks = quality.tube_masks(cams, axis, 6.0)
    for k in rng.choice(np.arange(8, len(axis) - 4), 4, replace=False):
        disk = quality.tube_masks(cams, axis[k - 1 : k + 2], 9.0)
        masks = [m | d for m, d in zip(masks, disk, strict=True)]
    iou, misfit = quality.tube_figures(cams, masks, axis, 6.0)
    share = max(misfit)
    assert share > quality.SUSPECT_MISFIT, share
    judged = [
        quality.suspect_reason(cams, masks, axis, 6.0, iou=iou, misfit=misfit, usual_misfit=usual)
        for usual in (0.0, share - 0.005, share - quality.SUSPECT_MISFIT - 0.005)
    ]
    assert ["differ by" in reason for reason in judged] == [True, False, True]
    # The track's usual share: the median of its last 30 frames' worst views, capped; a
    # frame without figures (failed) says nothing.
    frames = [
        FrameResult(index=i, status="ok", misfits=(0.001, m, 0.002))
        for i, m in enumerate(rng.uniform(0.01, 0.02, 40))
    ]
    frames.append(FrameResult.failed(40, "camera 'cam0' image could not be decoded"))
    worst = [max(f.misfits) for f in frames[-30:] if f.misfits]
    assert usual_misfit(frames) == pytest.approx(np.median(worst))
    assert usual_misfit([replace(f, misfits=(0.2,)) for f in frames[:5]]) == USUAL_MISFIT_MAX
    assert usual_misfit([]) == 0.0


@pytest.mark.parametrize("seed", range(4))
def test_a_length_is_judged_against_the_runs_where_the_run_agrees_on_one(seed: int) -> None:
    rng = np.random.default_rng(seed)
    frames = 60
    length = rng.uniform(100.0, 300.0)
    lengths = length + rng.normal(0.0, 0.5, frames)
    off = rng.choice(frames, 5, replace=False)
    lengths[off] += rng.choice([-1.0, 1.0], 5) * rng.uniform(4.0, 20.0, 5)
    lengths[off[0]] = np.nan  # a frame without a curve is no distance off
    gaps = quality.off_length(lengths)
    median = np.nanmedian(lengths)
    np.testing.assert_allclose(gaps[off[1:]], lengths[off[1:]] - median)
    assert gaps[off[0]] == 0.0
    flagged = np.flatnonzero(np.abs(gaps) > quality.SUSPECT_LENGTH_MM)
    assert sorted(flagged) == sorted(off[1:])
    # A robot that extends through the run has no one length: nothing is judged.
    extending = np.linspace(length, 1.3 * length, frames)
    assert not quality.off_length(extending).any()
    assert len(quality.off_length(np.full(3, np.nan))) == 3


@pytest.mark.parametrize("seed", range(4))
def test_a_curve_is_as_far_from_its_smoothed_one_as_its_farthest_sample(seed: int) -> None:
    rng = np.random.default_rng(seed)
    frames, n = 12, 64
    smoothed = np.cumsum(rng.normal(0.0, 2.0, (frames, n, 3)), axis=1)
    curves = smoothed.copy()
    moved = rng.choice(frames, 3, replace=False)
    shift = rng.uniform(0.5, 6.0, 3)
    for frame, by in zip(moved, shift, strict=True):
        direction = rng.normal(size=3)
        curves[frame, rng.integers(n) :] += by * direction / np.linalg.norm(direction)
    curves[moved[0], :, 0] = np.nan  # a frame without a curve is no distance off
    gaps = off_smoothed(curves, smoothed)
    expected = np.zeros(frames)
    expected[moved[1:]] = shift[1:]
    np.testing.assert_allclose(gaps, expected, atol=1e-9)
