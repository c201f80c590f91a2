"""The per-frame path: statuses, the FrameResult it fills, and the curve on a rendered tube."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import ROD_MM, rig_cameras

from pipeline.carve.hull import build_grid, carve, voxel_centers_mm
from pipeline.measure.evaluate import centerline_distances
from pipeline.reconstruct import frame
from pipeline.reconstruct.frame import (
    SessionModel,
    build_model,
    frame_silhouettes,
    reconstruct_frame,
    reconstruct_from_silhouettes,
    tube_blobs,
)
from pipeline.reconstruct.frame_result import STATUSES
from pipeline.reconstruct.quality import BARELY_MEET_SHARE, SILHOUETTES_APART, hull_shares, tube_width_px
from pipeline.session.folder import load_session
from pipeline.session.settings import ManipulatorSettings, Settings, SilhouetteSettings
from pipeline.session.video import read_frames
from pipeline.synth.images import THRESHOLD_DARK, background_texture, render_frame
from pipeline.synth.radius_profiles import RadiusProfile
from pipeline.synth.random_shapes import draw_shape, shape_at
from pipeline.synth.rig import make_rig
from pipeline.synth.shapes import shape_centerlines

BASE = np.array([128.0, 128.0, 0.0])
RADIUS = 6.0


@pytest.fixture(scope="module")
def model() -> SessionModel:
    cams = tuple(rig_cameras())
    settings = Settings(silhouette=SilhouetteSettings(threshold=THRESHOLD_DARK))
    return SessionModel(cams, settings, build_grid(cams, settings.workspace), (None, None, None))


@pytest.fixture(scope="module")
def tube() -> tuple[np.ndarray, list[np.ndarray]]:
    """A rendered bent tube (the synthetic renderer, textured background, noise)."""
    curve = shape_centerlines("bend_rotate", 12, base_mm=BASE)[5]
    backgrounds = [background_texture(320, 240, seed=3, camera_index=i) for i in range(3)]
    return curve, render_frame(make_rig(), curve, RADIUS, backgrounds, seed=3, frame_index=5)


def test_a_rendered_tube_is_reconstructed(model: SessionModel, tube: tuple) -> None:
    curve, images = tube
    result = reconstruct_frame(7, images, model)
    assert result.status == "ok" and result.reason == "" and result.index == 7
    assert result.centerline_mm is not None and result.tangents is not None
    assert result.curvature_per_mm is not None
    assert result.centerline_mm.shape == (64, 3)
    # The known mount (the spline holds its ends with 100x weight: ~1e-6 mm).
    np.testing.assert_allclose(result.centerline_mm[0], BASE, atol=1e-3)
    dist = np.concatenate(
        [centerline_distances(result.centerline_mm, curve), centerline_distances(curve, result.centerline_mm)]
    )
    # The accuracy targets (mean 0.4, p95 1.0, tip 1.0 mm, length 1 %); measured on
    # this frame: mean ~0.15, tip ~0.4 mm.
    assert dist.mean() < 0.4
    assert np.percentile(dist, 95) < 1.0
    assert np.linalg.norm(result.centerline_mm[-1] - curve[-1]) < 1.0
    assert result.length_mm == pytest.approx(250.0, rel=0.01)
    np.testing.assert_allclose(np.linalg.norm(result.tangents, axis=1), 1.0, atol=1e-9)
    # The bend is 0.7 rad over 250 mm at this phase: curvature ~0.003 /mm, far
    # below the tube's own 1/r.
    assert np.median(result.curvature_per_mm) < 0.02
    # Radius from the silhouette widths: measured 6.1 mm (the rim's anti-aliasing).
    assert result.radius_mm == pytest.approx(RADIUS, abs=0.3)
    assert 0 < result.fit_residual_mm < 0.5
    # The tube's width in each view, at its radius: what the writers count thin tubes by.
    np.testing.assert_allclose(
        result.tube_width_px, tube_width_px(model.cameras, result.centerline_mm, result.radius_mm)
    )
    assert all(4.0 < w < 12.0 for w in result.tube_width_px)  # 12 mm across at ~0.6 px/mm
    assert len(result.iou) == 3 and min(result.iou) > 0.85
    assert result.voxel_count > 500
    assert set(result.timings_s) == {"silhouette", "carve", "centerline", "quality"}


def test_without_a_base_it_is_inferred_at_the_floor(model: SessionModel, tube: tuple) -> None:
    curve, images = tube
    settings = replace(model.settings, manipulator=ManipulatorSettings(base_mm=None, radius_mm=None))
    result = reconstruct_frame(0, images, replace(model, settings=settings))
    assert result.status == "ok" and result.centerline_mm is not None
    # Inferred from the hull's end on the floor: within a voxel of the mount.
    assert np.linalg.norm(result.centerline_mm[0] - BASE) < 2.0
    assert centerline_distances(result.centerline_mm, curve).mean() < 0.5
    assert result.radius_mm == pytest.approx(RADIUS, abs=0.3)


def test_polyfit_method_gives_the_baseline_curve(model: SessionModel, tube: tuple) -> None:
    _, images = tube
    settings = replace(model.settings, centerline=replace(model.settings.centerline, method="polyfit"))
    result = reconstruct_frame(0, images, replace(model, settings=settings))
    assert result.status == "ok" and result.centerline_mm is not None
    assert result.centerline_mm.shape == (64, 3)
    assert np.isnan(result.fit_residual_mm)  # the baseline fits no tube


def test_nothing_in_view_is_empty(model: SessionModel, tube: tuple) -> None:
    images = [np.full((240, 320), 170, np.uint8) for _ in range(3)]
    result = reconstruct_frame(3, images, model)
    assert result.status == "empty"
    # Every camera that sees nothing is named: the user mends them all at once.
    assert result.index == 3 and result.unseen_by == ("cam0", "cam1", "cam2")
    assert result.reason == "nothing seen by cameras 'cam0', 'cam1' and 'cam2'"
    assert result.centerline_mm is None and np.isnan(result.length_mm)
    seen = list(tube[1])
    seen[2] = images[2]  # cam2 alone sees nothing
    result = reconstruct_frame(3, seen, model)
    assert result.status == "empty" and result.unseen_by == ("cam2",)
    assert result.reason == "nothing seen by camera 'cam2'"


def test_silhouettes_that_share_no_voxel_are_empty(model: SessionModel) -> None:
    masks = [np.zeros((240, 320), bool) for _ in range(3)]
    # A blob in a corner of every view: the three corners' rays never meet.
    masks[0][:10, :10] = masks[1][-10:, :10] = masks[2][:10, -10:] = True
    images = [np.full((240, 320), 170, np.uint8) for _ in range(3)]
    result = reconstruct_from_silhouettes(4, images, masks, model)
    assert result.status == "empty" and "no voxel" in result.reason and result.unseen_by == ()


def test_an_undecodable_image_fails_naming_the_camera(model: SessionModel, tube: tuple) -> None:
    _, images = tube
    result = reconstruct_frame(9, [images[0], None, images[2]], model)
    assert result.status == "failed"
    assert result.index == 9 and "'cam1'" in result.reason  # the index says which frame


def test_noise_never_raises(model: SessionModel) -> None:
    rng = np.random.default_rng(0)
    for _ in range(3):
        images = [rng.integers(0, 256, (240, 320), dtype=np.uint8) for _ in range(3)]
        result = reconstruct_frame(0, images, model)
        assert result.status in STATUSES
        assert result.status == "ok" or result.reason


def test_a_drawing_that_fails_while_the_blobs_are_kept_fails_the_frame(
    tmp_path: Path, make_session: Callable[..., Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    session = load_session(make_session(tmp_path / "s", frames=1))
    model = build_model(session)
    images = [image for p in session.video_paths for _, image in read_frames(p, 0, 1)]

    def impossible_disc(*_: object) -> None:
        raise cv2.error("OpenCV(4) circle: radius >= 0")

    monkeypatch.setattr(frame, "tube_blobs", impossible_disc)
    result = reconstruct_frame(0, images, model)
    assert result.status == "failed" and "circle: radius >= 0" in result.reason
    assert SILHOUETTES_APART not in result.reason  # the rendered session's cameras agree


def test_a_session_directory_round_trip(tmp_path: Path, make_session: Callable[..., Path]) -> None:
    # The conftest rod: a dark 7 px line from the base straight up, 160 mm.
    session = load_session(make_session(tmp_path / "s", frames=2, empty_frames={1}))
    model = build_model(session)
    frames = [list(read_frames(p, 0, 2)) for p in session.video_paths]
    first = reconstruct_frame(0, [f[0][1] for f in frames], model)
    second = reconstruct_frame(1, [f[1][1] for f in frames], model)
    assert first.status == "ok" and first.centerline_mm is not None
    # A 7 px line drawn without anti-aliasing, through lossy MJPG: its axis is
    # found within about a pixel (~2 mm at this range), its radius is ~3.5 px.
    assert centerline_distances(first.centerline_mm, ROD_MM).mean() < 1.0
    assert second.status == "empty"
    decoded = [f[0][1] for f in frames]
    assert all(im is not None for im in decoded)
    masks = frame_silhouettes([im for im in decoded if im is not None], model)
    assert all(m.dtype == bool and m.any() for m in masks)


def test_a_blob_no_other_view_confirms_is_not_the_tube(model: SessionModel, tube: tuple) -> None:
    import cv2

    from pipeline.carve.hull import carve, voxel_centers_mm

    _, images = tube
    masks = frame_silhouettes(images, model)
    points = voxel_centers_mm(model.settings.workspace, carve(model.grid, masks))
    # A dark object in camera 0's corner, apart from the tube; and a thin spur joined
    # to the tube's silhouette that no voxel projects into (a tip thinner than a voxel).
    seen = masks[0].copy()
    cv2.circle(seen.view(np.uint8), (12, 12), 8, 1, -1)
    ys, xs = np.nonzero(masks[0])
    spur = (int(xs[np.argmax(ys)]), int(ys.max()))
    cv2.line(seen.view(np.uint8), spur, (spur[0], min(spur[1] + 6, seen.shape[0] - 1)), 1, 1)
    kept = tube_blobs([seen, *masks[1:]], points, model)
    assert not kept[0][:21, :21].any()  # the object is dropped
    assert (kept[0] == (seen & ~_disc(seen.shape, (12, 12), 8))).all()  # everything else kept
    assert all((k == m).all() for k, m in zip(kept[1:], masks[1:], strict=True))


def test_a_tracked_frame_keeps_the_blobs_along_its_prediction(model: SessionModel, tube: tuple) -> None:
    from pipeline.carve.hull import carve, voxel_centers_mm

    curve, images = tube
    masks = frame_silhouettes(images, model)
    points = voxel_centers_mm(model.settings.workspace, carve(model.grid, masks))
    # A dark object in camera 0, 80 mm from the tube, that a voxel confirms (as two
    # views' hull may: its cone crosses the other view's tube).
    ghost = curve[len(curve) // 2] + np.array([80.0, 0.0, 0.0])
    u, v = np.round(model.cameras[0].project(ghost[None])[0]).astype(int)
    assert 8 <= u < masks[0].shape[1] - 8 and 8 <= v < masks[0].shape[0] - 8
    seen = masks[0] | _disc(masks[0].shape, (int(u), int(v)), 8)
    assert not (masks[0] & _disc(masks[0].shape, (int(u), int(v)), 10)).any()
    confirmed = np.vstack([points, ghost[None]])
    views = [seen, *masks[1:]]
    # The hull alone keeps it; along the track's prediction, it is dropped and the
    # tube's blob kept whole.
    assert (tube_blobs(views, confirmed, model)[0] == seen).all()
    kept = tube_blobs(views, confirmed, model, curve, RADIUS)
    assert (kept[0] == masks[0]).all()
    assert all((k == m).all() for k, m in zip(kept[1:], masks[1:], strict=True))
    # A prediction that reaches none of a view's blobs (a tube far from it) leaves the
    # hull's; so does a prediction without a radius.
    away = curve + np.array([0.0, 0.0, 400.0])
    assert (tube_blobs(views, confirmed, model, away, RADIUS)[0] == seen).all()
    assert (tube_blobs(views, confirmed, model, curve, float("nan"))[0] == seen).all()


def _disc(shape: tuple[int, ...], centre: tuple[int, int], radius: int) -> np.ndarray:
    import cv2

    canvas = np.zeros(shape, np.uint8)
    cv2.circle(canvas, centre, radius, 1, -1)
    return canvas.view(bool)


def _random_tube_hidden_in_one_view(
    seed: int, model: SessionModel, hidden: slice
) -> tuple[np.ndarray, list[np.ndarray]]:
    """A random shape (the synthetic variety's) rendered in the rig, its ``hidden`` samples
    painted over in view ``seed % 3`` with the scene behind them, as an object of the tube's
    own grey level would, or a threshold that breaks a thin tube there: (curve (N, 3) mm,
    per camera grey image)."""
    rng = np.random.default_rng(seed)
    shape = draw_shape(
        seed,
        profile=RadiusProfile(radius_mm=RADIUS),
        tip="flat",
        base_mm=BASE,
        box_lo_mm=np.zeros(3),
        box_hi_mm=np.full(3, 256.0),
    )
    curve = shape_at(shape, np.array([float(rng.integers(60))]), base_mm=BASE)[0]
    backgrounds = [background_texture(320, 240, seed=seed, camera_index=i) for i in range(3)]
    images = render_frame(make_rig(), curve, RADIUS, backgrounds, seed=seed, frame_index=0)
    view, cam = seed % 3, model.cameras[seed % 3]
    part = curve[hidden]
    width = 2 * cam.focal_px * RADIUS / float(cam.to_camera(part)[:, 2].min()) + 6
    band = cv2.polylines(
        np.zeros((240, 320), np.uint8), [cam.project(part).round().astype(np.int32)], False, 255, int(width)
    )
    images[view] = np.where(band > 0, np.clip(backgrounds[view], 0, 255).astype(np.uint8), images[view])
    return curve, images


@pytest.mark.parametrize(
    ("part", "seed"), [("middle", 0), ("middle", 1), ("middle", 2), ("start", 3), ("start", 4), ("start", 5)]
)
def test_a_part_one_view_does_not_show_is_found_from_the_others(
    model: SessionModel, part: str, seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The middle fifth: a start from the hull does not find every such stretch: on seeds
    # 0-11 (2026-12-05) 6 of 12 curves came within 0.5 mm and 2 % of the length, 6 of 12
    # with a twentieth hidden. The first 30 mm: the hull holds nothing near the base, and
    # the march starts in the voxels every view but one sees; two views place that part: on
    # seeds 3-8 (2026-12-06) the curves came within 0.13-0.50 mm (mean).
    hidden = slice(80, 120) if part == "middle" else slice(0, 25)
    curve, images = _random_tube_hidden_in_one_view(seed, model, hidden)
    truth_mm = float(np.linalg.norm(np.diff(curve, axis=0), axis=1).sum())

    result = reconstruct_frame(0, images, model)
    assert result.status == "ok" and result.centerline_mm is not None
    dist = np.concatenate(
        [centerline_distances(result.centerline_mm, curve), centerline_distances(curve, result.centerline_mm)]
    )
    within_mm = 0.5 if part == "middle" else 0.6
    assert dist.mean() < within_mm and result.length_mm == pytest.approx(truth_mm, rel=0.02), (
        dist.mean(),
        result.length_mm,
    )
    # The hull, which needs every view, stops where the one view loses the tube (so does the
    # tube fitted through it alone), or holds no start.
    monkeypatch.setattr(frame, "hull_but_one_view", lambda *_: np.zeros((0, 3)))
    alone = reconstruct_frame(0, images, model)
    if part == "middle":
        assert alone.length_mm < 0.8 * truth_mm
    else:
        assert alone.status == "failed" and "the hull holds no tube near the base" in alone.reason


@pytest.mark.parametrize("seed", range(3))
def test_the_hull_explains_each_silhouette_where_the_cameras_agree(
    model: SessionModel, tube: tuple, seed: int
) -> None:
    """Cameras that agree see all of each silhouette within a voxel of the hull; a view whose
    silhouette lies elsewhere sees little of its own there."""
    _, images = tube
    masks = frame_silhouettes(images, model)
    voxel = model.settings.workspace.voxel_mm
    points = voxel_centers_mm(model.settings.workspace, carve(model.grid, masks))
    assert np.all(hull_shares(points, masks, model.cameras, voxel) > 0.9)
    # A view whose silhouette lies elsewhere (a camera that has turned): the others' cones
    # meet around their tube, and its silhouette is not there.
    rng = np.random.default_rng(seed)
    moved = list(masks)
    moved[seed] = np.roll(masks[seed], tuple(rng.integers(40, 60, 2)), axis=(0, 1))
    points = voxel_centers_mm(model.settings.workspace, carve(model.grid, moved))
    shares = hull_shares(points, moved, model.cameras, voxel)
    assert shares[seed] < BARELY_MEET_SHARE


def test_a_frame_that_fails_where_the_silhouettes_barely_meet_names_the_cameras(
    model: SessionModel, tube: tuple, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A fit that fails on silhouettes whose cones meet only at their fringes (one view's
    silhouette elsewhere, as a camera turned since calibration puts it) says that the
    cameras are the cause; on silhouettes that agree it does not."""
    _, images = tube
    masks = frame_silhouettes(images, model)
    moved = list(masks)
    moved[0] = np.roll(masks[0], 16, axis=1)  # 16 px across the tube's middle, in cam0
    assert len(carve(model.grid, moved)) >= frame.MIN_VOXELS  # the cones still meet somewhere

    no_tube_reason = "the hull holds no tube near the base"

    def no_tube(*_: object) -> None:
        raise ValueError(no_tube_reason)

    monkeypatch.setattr(frame, "tube_blobs", no_tube)
    result = reconstruct_from_silhouettes(6, images, moved, model)
    assert result.status == "failed"
    assert result.reason == f"centreline fit failed: {no_tube_reason}; {SILHOUETTES_APART}"
    result = reconstruct_from_silhouettes(6, images, masks, model)
    assert result.status == "failed" and SILHOUETTES_APART not in result.reason


def test_a_start_from_the_hull_draws_the_disks_on_three_cameras_only(
    model: SessionModel, tube: tuple, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pipeline.reconstruct.disks import Disks
    from pipeline.reconstruct.radius_profile import RadiusProfile as SessionRadii

    disks = Disks(np.array([40.0, 80.0, 120.0]), 9.0)
    drawn: list[object] = []
    fit_centerline = frame.fit_centerline

    def spy(*args: object, **kwargs: object) -> object:
        drawn.append(kwargs.get("session_radii"))
        return fit_centerline(*args, **kwargs)

    monkeypatch.setattr(frame, "fit_centerline", spy)
    _, images = tube
    with_disks = replace(model, radius_profile=SessionRadii.of_disks(disks))
    cameras = with_disks.cameras[:2]
    two = replace(
        with_disks,
        cameras=cameras,
        grid=build_grid(cameras, with_disks.settings.workspace),
        backgrounds=with_disks.backgrounds[:2],
    )
    reconstruct_frame(0, images, with_disks)
    reconstruct_frame(0, images[:2], two)
    # Two views' readings are exactly the two numbers that place each sample: the disks
    # stay out of their start (they go into the track's fit on both rigs).
    assert len(drawn) == 2 and drawn[1] is None
    assert isinstance(drawn[0], SessionRadii) and drawn[0].disks is disks
