"""The synthetic renderer is an oracle: check it against OpenCV and exact geometry only,
never against the reconstruction modules."""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import itertools
import logging
import math
import tomllib
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from pipeline.errors import PipelineError
from pipeline.session.calibration_io import read_calibration
from pipeline.session.settings import load_settings
from pipeline.session.video import video_fingerprint
from pipeline.synth.images import (
    FLICKER,
    THRESHOLD_DARK,
    background_texture,
    render_frame,
    threshold_for,
    tube_mask,
)
from pipeline.synth.names import ARRANGEMENT_NAMES, PROFILES, SHAPES, TIPS
from pipeline.synth.radius_profiles import RadiusProfile, disks_of, max_radius, radius_along
from pipeline.synth.random_shapes import (
    LENGTH_RANGE_MM,
    MAX_TIP_STEP_MM,
    PERIOD_FRAMES,
    draw_shape,
    shape_at,
)
from pipeline.synth.raycast import distort_normalized, ray_directions, undistort_pixels
from pipeline.synth.rig import ARRANGEMENTS, SynthCamera, make_rig
from pipeline.synth.session_render import (
    BASE_MM,
    SceneOptions,
    check_poses,
    render_session,
    session_centerlines,
)
from pipeline.synth.shapes import Segment, centerline, shape_centerlines
from pipeline.synth.variety import Case, draw_cases, render_case

FRAMES = 12
RADIUS_MM = 6.0
NAMES = ("cam0", "cam1", "cam2")
GT_KEYS = {
    "centerlines",
    "calib_error_deg",
    "bumped_camera",
    "timestamps_s",
    "radius_mm",
    "base_mm",
    "shape",
    "fps",
    "camera_names",
    "K",
    "dist",
    "R",
    "t",
    "image_size",
    "tip",
    "profile",
    "radius_profile_mm",
    "length_mm",
    "disk_arc_mm",
    "disk_radius_mm",
    "disk_thickness_mm",
    "distractor_camera",
    "flicker_gain",
    "video_fingerprints",
}


def _render(directory: Path, **kwargs: object) -> Path:
    render_session(directory, frames=FRAMES, progress=False, **kwargs)  # type: ignore[arg-type]
    return directory


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _render(tmp_path_factory.mktemp("synth") / "s")


@pytest.fixture(scope="module")
def same_seed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _render(tmp_path_factory.mktemp("synth") / "same")


@pytest.fixture(scope="module")
def other_seed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _render(tmp_path_factory.mktemp("synth") / "other", seed=1)


def _frames(path: Path) -> NDArray[np.uint8]:
    """Every frame of a video, read with plain OpenCV, as (F, H, W) grey."""
    cap = cv2.VideoCapture(str(path))
    out = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        out.append(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
    cap.release()
    return np.stack(out)


def _project(table: dict, points_mm: NDArray[np.float64]) -> NDArray[np.float64]:
    """cv2.projectPoints with the numbers of one calibration.toml table, (N, 2) px."""
    uv, _ = cv2.projectPoints(
        points_mm,
        np.array(table["rotation"], dtype=np.float64),
        np.array(table["translation"], dtype=np.float64),
        np.array(table["matrix"], dtype=np.float64),
        np.array(table["distortions"], dtype=np.float64),
    )
    return uv.reshape(-1, 2)


def _rim(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Pixels within one pixel of the mask's edge (the anti-aliased band)."""
    m = mask.astype(np.uint8)
    kernel = np.ones((3, 3), np.uint8)
    return cv2.dilate(m, kernel) != cv2.erode(m, kernel)


def _iou(a: NDArray[np.bool_], b: NDArray[np.bool_], keep: NDArray[np.bool_]) -> float:
    return float((a & b & keep).sum() / ((a | b) & keep).sum())


# --- the session directory -------------------------------------------------------------


def test_session_opens_with_plain_opencv(session: Path) -> None:
    for name in NAMES:
        cap = cv2.VideoCapture(str(session / f"{name}.mp4"))
        assert cap.isOpened()
        assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(30.0)
        cap.release()
        frames = _frames(session / f"{name}.mp4")
        assert frames.shape == (FRAMES, 240, 320)
        background = cv2.imread(str(session / "background" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        assert background.shape == (240, 320) and background.dtype == np.uint8


def test_calibration_and_settings_parse(session: Path) -> None:
    with (session / "calibration.toml").open("rb") as f:
        calib = tomllib.load(f)
    tables = [calib[f"cam_{i}"] for i in range(3)]
    assert [t["name"] for t in tables] == list(NAMES)
    for table in tables:
        assert table["size"] == [320, 240]
        assert np.array(table["matrix"]).shape == (3, 3)
        assert len(table["distortions"]) == 5
        assert len(table["rotation"]) == 3 and len(table["translation"]) == 3
    settings = load_settings(session / "session.toml")
    assert settings.silhouette.method == "threshold"
    assert settings.silhouette.polarity == "dark"
    assert settings.manipulator.base_mm == (128.0, 128.0, 0.0)
    assert settings.manipulator.radius_mm == RADIUS_MM
    assert settings.workspace.size_mm == (256.0, 256.0, 256.0)


def test_ground_truth_arrays(session: Path) -> None:
    gt = np.load(session / "ground_truth.npz")
    assert set(gt.files) == GT_KEYS
    # The videos the truth is of, as evaluate fingerprints them, wherever the file is copied.
    assert list(gt["video_fingerprints"]) == [
        f"{name}.mp4={video_fingerprint(session / f'{name}.mp4')}" for name in NAMES
    ]
    assert gt["centerlines"].shape == (FRAMES, 200, 3) and gt["centerlines"].dtype == np.float64
    np.testing.assert_allclose(gt["timestamps_s"], np.arange(FRAMES) / 30.0)
    assert float(gt["radius_mm"]) == RADIUS_MM and float(gt["fps"]) == 30.0
    assert str(gt["shape"]) == "bend_rotate"
    np.testing.assert_array_equal(gt["base_mm"], [128.0, 128.0, 0.0])
    np.testing.assert_array_equal(gt["centerlines"][:, 0], np.broadcast_to(BASE_MM, (FRAMES, 3)))
    assert list(gt["camera_names"]) == list(NAMES)
    assert gt["K"].shape == (3, 3, 3) and gt["dist"].shape == (3, 5)
    assert gt["R"].shape == (3, 3, 3) and gt["t"].shape == (3, 3)
    np.testing.assert_array_equal(gt["image_size"], [320, 240])
    # The calibration file and the ground truth describe the same cameras.
    with (session / "calibration.toml").open("rb") as f:
        calib = tomllib.load(f)
    for i in range(3):
        R, _ = cv2.Rodrigues(np.array(calib[f"cam_{i}"]["rotation"]))
        np.testing.assert_allclose(R, gt["R"][i], atol=1e-12)
        np.testing.assert_allclose(calib[f"cam_{i}"]["translation"], gt["t"][i])


def test_short_session_shows_varied_poses(session: Path) -> None:
    tips = np.load(session / "ground_truth.npz")["centerlines"][:, -1]
    # 12 frames cover a whole bending cycle: the tip travels tens of millimetres.
    assert np.ptp(tips, axis=0).max() > 50.0


# --- the images are right ----------------------------------------------------------------


def test_projected_centerline_lands_on_tube_pixels(session: Path) -> None:
    gt = np.load(session / "ground_truth.npz")
    with (session / "calibration.toml").open("rb") as f:
        calib = tomllib.load(f)
    threshold = threshold_for("dark")
    for i, name in enumerate(NAMES):
        frames = _frames(session / f"{name}.mp4")
        for f in range(FRAMES):
            # Leave out the last 6 mm: at the flat tip the centre is near the cap's edge.
            uv = np.rint(_project(calib[f"cam_{i}"], gt["centerlines"][f, :-5])).astype(int)
            values = frames[f][uv[:, 1], uv[:, 0]]
            assert values.max() < threshold, f"{name} frame {f}"


def test_threshold_matches_analytic_mask(session: Path) -> None:
    gt = np.load(session / "ground_truth.npz")
    cams = make_rig()
    backgrounds = [background_texture(320, 240, seed=0, camera_index=i) for i in range(3)]
    f = 5
    line = gt["centerlines"][f]
    rendered = render_frame(cams, line, RADIUS_MM, backgrounds, frame_index=f)
    for i, cam in enumerate(cams):
        truth = tube_mask(cam, line, RADIUS_MM)
        keep = ~_rim(truth)
        # Away from the 1-px anti-aliased rim the grey levels are ~20 grey levels from the
        # threshold (several noise sigmas), so the masks should agree nearly everywhere.
        assert _iou(rendered[i] < threshold_for("dark"), truth, keep) > 0.95
        # The same after mp4v compression, from the video itself.
        decoded = _frames(session / f"{cam.name}.mp4")[f]
        assert _iou(decoded < threshold_for("dark"), truth, keep) > 0.95


def test_bright_polarity_is_the_negative() -> None:
    cams = make_rig()[:1]
    backgrounds = [background_texture(320, 240, seed=0, camera_index=0)]
    line = shape_centerlines("loop", 20, base_mm=BASE_MM)[7]
    dark = render_frame(cams, line, RADIUS_MM, backgrounds, noise_sigma=0.0)[0]
    bright = render_frame(cams, line, RADIUS_MM, backgrounds, noise_sigma=0.0, polarity="bright")[0]
    # Rounding of x and of 255 - x can differ by one grey level.
    assert np.abs(dark.astype(int) + bright.astype(int) - 255).max() <= 1
    truth = tube_mask(cams[0], line, RADIUS_MM)
    assert _iou(bright > threshold_for("bright"), truth, ~_rim(truth)) > 0.95


def test_tube_mask_matches_brute_force_distance() -> None:
    """A pixel centre is in the mask exactly when its ray passes within the radius of the
    polyline (the capsule chain), away from the flat end caps."""
    cam = make_rig()[1]
    line = np.ascontiguousarray(shape_centerlines("s_curve", 10, base_mm=BASE_MM)[3][::4])  # 50 points
    mask = tube_mask(cam, line, RADIUS_MM)
    rvec = cv2.Rodrigues(cam.R)[0]
    line_px = cv2.projectPoints(line, rvec, cam.t, cam.K, cam.dist)[0].reshape(-1, 2)
    # The tube is < 10 px wide here: a 15 px margin around the projected centreline holds it.
    u0, v0 = np.floor(line_px.min(axis=0) - 15).astype(int)
    u1, v1 = np.ceil(line_px.max(axis=0) + 15).astype(int)
    box = (slice(v0, v1), slice(u0, u1))
    outside = np.ones_like(mask)
    outside[box] = False
    assert not mask[outside].any()
    v, u = np.mgrid[box]
    dirs = ray_directions(cam, np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64))
    o = cam.center
    # Closest approach between each ray (o + s d) and each segment [a, b], sampled finely.
    dist = np.full(len(dirs), np.inf)
    for a_k, b_k in itertools.pairwise(line):
        samples = np.linspace(0.0, 1.0, 41)[:, None] * (b_k - a_k) + a_k
        rel = samples - o  # (41, 3)
        along = dirs @ rel.T  # (Q, 41)
        perp2 = np.einsum("ij,ij->i", rel, rel)[None, :] - along**2
        dist = np.minimum(dist, np.sqrt(np.clip(perp2, 0.0, None)).min(axis=1))
    near = (dist <= RADIUS_MM).reshape(u.shape)
    # Sampling overestimates the distance by at most (spacing / 2)^2 / (2 r) < 1 micron,
    # so only the 1-px rim and the pixels near the flat caps may disagree.
    far_from_ends = (
        np.hypot(u[..., None] - line_px[[0, -1], 0], v[..., None] - line_px[[0, -1], 1]).min(axis=-1) > 8
    )
    keep = ~_rim(mask)[box] & far_from_ends
    assert np.array_equal(mask[box][keep], near[keep])
    assert mask[box][keep].sum() > 150  # the comparison covered the tube (~200 interior pixels)


def test_ray_directions_invert_opencv_projection() -> None:
    rng = np.random.default_rng(0)
    points = rng.uniform(0.0, 256.0, (200, 3))
    for cam in make_rig("oblique") + make_rig("ninety"):
        uv, _ = cv2.projectPoints(points, cv2.Rodrigues(cam.R)[0], cam.t, cam.K, cam.dist)
        dirs = ray_directions(cam, uv.reshape(-1, 2))
        expected = points - cam.center
        expected /= np.linalg.norm(expected, axis=1, keepdims=True)
        # 1e-9 rad is ~1e-6 px at f = 300 px: only floating-point error is allowed.
        np.testing.assert_allclose(dirs, expected, atol=1e-9)


def test_undistort_inverts_distort_at_the_corners() -> None:
    cam = make_rig()[2]  # the strongest distortion
    corners = np.array([[0.0, 0.0], [319.0, 0.0], [0.0, 239.0], [319.0, 239.0]])
    xy = undistort_pixels(cam, corners)
    back = distort_normalized(cam, xy)
    uv = back * [cam.K[0, 0], cam.K[1, 1]] + cam.K[:2, 2]
    np.testing.assert_allclose(uv, corners, atol=1e-8)


# --- determinism -----------------------------------------------------------------------


def test_same_seed_same_outputs(session: Path, same_seed: Path) -> None:
    assert (session / "ground_truth.npz").read_bytes() == (same_seed / "ground_truth.npz").read_bytes()
    for name in ("calibration.toml", "session.toml", "background/cam1.png"):
        assert (session / name).read_bytes() == (same_seed / name).read_bytes()
    for name in NAMES:
        np.testing.assert_array_equal(_frames(session / f"{name}.mp4"), _frames(same_seed / f"{name}.mp4"))


def test_other_seed_other_noise_same_motion(session: Path, other_seed: Path) -> None:
    a, b = np.load(session / "ground_truth.npz"), np.load(other_seed / "ground_truth.npz")
    np.testing.assert_array_equal(a["centerlines"], b["centerlines"])
    frames_a, frames_b = _frames(session / "cam0.mp4"), _frames(other_seed / "cam0.mp4")
    assert np.abs(frames_a.astype(int) - frames_b.astype(int)).mean() > 5.0


def test_frame_renders_the_same_alone() -> None:
    """Noise is drawn per frame, so chunked parallel rendering cannot change a frame."""
    cams = make_rig()
    backgrounds = [background_texture(320, 240, seed=3, camera_index=i) for i in range(3)]
    line = shape_centerlines("helix", 4, base_mm=BASE_MM)[2]
    a = render_frame(cams, line, RADIUS_MM, backgrounds, seed=3, frame_index=2)
    b = render_frame(cams, line, RADIUS_MM, backgrounds, seed=3, frame_index=2)
    c = render_frame(cams, line, RADIUS_MM, backgrounds, seed=3, frame_index=3)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert not np.array_equal(a[0], c[0])


# --- geometry of the shapes ------------------------------------------------------------


@pytest.mark.parametrize("shape", SHAPES)
def test_every_shape_stays_inside_workspace_and_views(shape: str) -> None:
    for frames, arrangement in ((900, "oblique"), (15, "oblique"), (300, "ninety")):
        lines = shape_centerlines(shape, frames, base_mm=BASE_MM)
        # Raises if any frame leaves a view or the cube.
        check_poses(lines, RADIUS_MM, make_rig(arrangement))
        # Independently: centre points keep a radius from the cube's walls; the base is on the floor.
        assert lines[..., :2].min() >= RADIUS_MM and lines[..., :2].max() <= 256 - RADIUS_MM
        assert lines[..., 2].min() >= 0.0 and lines[..., 2].max() <= 256.0


def test_check_poses_refuses_a_tube_outside() -> None:
    cams = make_rig()
    lines = shape_centerlines("straight", 3, base_mm=np.array([3.0, 128.0, 0.0]))
    with pytest.raises(PipelineError, match="frame 0: the tube leaves the 256 mm workspace"):
        check_poses(lines, RADIUS_MM, cams)


def test_check_poses_refuses_a_tube_that_runs_into_itself() -> None:
    # The loop's tip passes ~20 mm from its stem: a 12 mm radius tube would cut into it.
    lines = shape_centerlines("loop", 3, base_mm=BASE_MM)
    with pytest.raises(PipelineError, match="the tube runs into itself"):
        check_poses(lines, 12.0, make_rig())


def test_check_poses_refuses_a_tube_out_of_view() -> None:
    cam = make_rig()[0]
    zoomed = dataclasses.replace(cam, K=cam.K * [[4.0], [4.0], [1.0]])  # 4x focal length
    lines = shape_centerlines("straight", 3, base_mm=BASE_MM)
    with pytest.raises(PipelineError, match="frame 0: the tube leaves the image of camera cam0"):
        check_poses(lines, RADIUS_MM, [zoomed])


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("length_mm", [250.0, 180.0])
def test_uniform_arc_length_and_requested_length(shape: str, length_mm: float) -> None:
    lines = shape_centerlines(shape, 30, base_mm=BASE_MM, length_mm=length_mm)
    steps = np.linalg.norm(np.diff(lines, axis=1), axis=2)
    # Chords of a curve sampled every h mm fall short of h by (kappa h)^2 / 24: < 1e-4 relative here.
    np.testing.assert_allclose(steps, length_mm / 199, rtol=2e-4)
    np.testing.assert_allclose(steps.sum(axis=1), length_mm, rtol=0.005)


def test_shape_motion_varies_and_tube_never_touches_itself() -> None:
    for shape in SHAPES:
        lines = shape_centerlines(shape, 900, base_mm=BASE_MM)[::10]
        assert np.ptp(lines[:, -1], axis=0).max() > 10.0, shape  # the tip moves
        # Points more than 40 mm apart along the tube keep a tube diameter between them.
        sub = lines[:, ::2]
        d = np.linalg.norm(sub[:, :, None] - sub[:, None], axis=3)
        idx = np.arange(sub.shape[1])
        far = np.abs(idx[:, None] - idx[None]) * (250.0 / 199 * 2) > 40.0
        assert d[:, far].min() > 2 * RADIUS_MM, shape


def test_loop_curls_back_near_its_body() -> None:
    lines = shape_centerlines("loop", 900, base_mm=BASE_MM)
    tip = lines[:, -1]
    body = lines[:, :-60]  # farther than 75 mm from the tip along the tube
    gap = np.linalg.norm(body - tip[:, None], axis=2).min(axis=1)
    # The tip comes back within two diameters of the stem, never into it.
    assert gap.max() < 4 * RADIUS_MM and gap.min() > 2 * RADIUS_MM


def test_straight_stays_nearly_straight() -> None:
    lines = shape_centerlines("straight", 900, base_mm=BASE_MM)
    offset = np.linalg.norm(lines[..., :2] - BASE_MM[:2], axis=2)
    assert offset.max() < 15.0
    assert lines[:, -1, 2].min() > 0.99 * 250.0


def test_constant_curvature_segment_is_a_circular_arc() -> None:
    kappa = 1.0 / 80.0
    line = centerline([Segment(200.0, kappa, 0.0, math.pi / 2)], base_mm=BASE_MM)
    # Bending direction phi = pi/2 is the base frame's binormal, world +y.
    center = BASE_MM + np.array([0.0, 80.0, 0.0])
    np.testing.assert_allclose(np.linalg.norm(line - center, axis=1), 80.0, atol=1e-9)
    np.testing.assert_allclose(line[:, 0], BASE_MM[0], atol=1e-9)  # stays in the y-z plane


def test_helix_segment_has_constant_radius_about_its_axis() -> None:
    kappa, tau = 0.02, 0.03
    line = centerline([Segment(250.0, kappa, tau, 0.0)], base_mm=BASE_MM, points=400)
    rho = kappa / (kappa**2 + tau**2)
    # The axis runs along the Darboux vector tau T + kappa B (base frame: T = +z,
    # B = +y) and passes rho from the start along the principal normal N = +x.
    axis = np.array([0.0, kappa, tau]) / math.hypot(kappa, tau)
    on_axis = BASE_MM + rho * np.array([1.0, 0.0, 0.0])
    rel = line - on_axis
    radial = rel - (rel @ axis)[:, None] * axis
    np.testing.assert_allclose(np.linalg.norm(radial, axis=1), rho, atol=1e-9)


def test_bright_ninety_session(tmp_path: Path) -> None:
    render_session(tmp_path, frames=2, polarity="bright", arrangement="ninety", progress=False)
    settings = load_settings(tmp_path / "session.toml")
    assert (settings.silhouette.polarity, settings.silhouette.threshold) == (
        "bright",
        threshold_for("bright"),
    )
    with (tmp_path / "calibration.toml").open("rb") as f:
        assert tomllib.load(f)["metadata"]["arrangement"] == "ninety"
    frame = _frames(tmp_path / "cam1.mp4")[0]
    # A light tube on a dark scene: most pixels are background, below the threshold.
    assert np.median(frame) < threshold_for("bright") < frame.max()


def test_bad_arguments_raise_pipeline_errors(tmp_path: Path) -> None:
    with pytest.raises(PipelineError, match="unknown synthetic shape 'spiral'"):
        render_session(tmp_path, shape="spiral", frames=2, progress=False)
    with pytest.raises(PipelineError, match=r"--frames must be in \[1, 108000\]"):
        render_session(tmp_path, frames=0, progress=False)
    with pytest.raises(PipelineError, match="an hour at 30 fps"):
        render_session(tmp_path, frames=10**9, progress=False)
    with pytest.raises(PipelineError, match=r"--seed must be 0 or more, got -1"):
        render_session(tmp_path / "seeded", frames=2, seed=-1, progress=False)
    assert not (tmp_path / "seeded").exists()  # refused before anything is written


def test_synth_renders_into_a_new_or_empty_folder_or_over_a_render_only(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "calibration.toml").write_text("my own cameras\n")
    with pytest.raises(PipelineError, match="is not a synthetic session"):
        render_session(mine, frames=2, progress=False)
    assert (mine / "calibration.toml").read_text() == "my own cameras\n"
    render_session(tmp_path / "new", frames=2, progress=False, jobs=1)
    render_session(tmp_path / "new", frames=3, progress=False, jobs=1)  # over its own render
    assert len(np.load(tmp_path / "new" / "ground_truth.npz")["centerlines"]) == 3
    # A render of two cameras refused for its poses leaves the earlier render whole.
    from pipeline.synth import session_render

    def refused(*_: object, **__: object) -> None:
        raise PipelineError("synthetic frame 0: the tube runs into itself")

    monkeypatch.setattr(session_render, "check_poses", refused)
    with pytest.raises(PipelineError, match="runs into itself"):
        render_session(tmp_path / "new", frames=2, progress=False, jobs=1, options=SceneOptions(cameras=2))
    assert (tmp_path / "new" / "cam2.mp4").is_file() and (
        tmp_path / "new" / "background" / "cam2.png"
    ).is_file()
    monkeypatch.undo()
    # Two cameras over three: the third camera's video and background go with the render.
    render_session(tmp_path / "new", frames=2, progress=False, jobs=1, options=SceneOptions(cameras=2))
    assert sorted(p.name for p in (tmp_path / "new").glob("*.mp4")) == ["cam0.mp4", "cam1.mp4"]
    assert sorted(p.name for p in (tmp_path / "new" / "background").iterdir()) == ["cam0.png", "cam1.png"]
    with pytest.raises(PipelineError, match="unknown arrangement"):
        render_session(tmp_path, frames=2, arrangement="square", progress=False)


# --- the variety: tube ends, radius profiles, rigs, scenes, random shapes ---------------


def _zoomed(cam: SynthCamera, target_mm: NDArray[np.float64], zoom: float = 4.0) -> SynthCamera:
    """``cam`` with a ``zoom`` x longer lens whose image centre looks at ``target_mm``
    (distortion acts on normalised coordinates, so only K changes)."""
    x_cam = cam.R @ target_mm + cam.t
    xd = distort_normalized(cam, (x_cam[:2] / x_cam[2])[None])[0]
    f = zoom * cam.K[0, 0]
    K = np.array([[f, 0.0, 159.5 - f * xd[0]], [0.0, f, 119.5 - f * xd[1]], [0.0, 0.0, 1.0]])
    return dataclasses.replace(cam, K=K)


def _straight_across(
    cam: SynthCamera, through_mm: NDArray[np.float64], before_mm: float, after_mm: float
) -> NDArray[np.float64]:
    """(101, 3) straight centreline from ``before_mm`` before ``through_mm`` to ``after_mm`` past it,
    perpendicular to the camera's line of sight there, so that lengths along and across it
    show in the image unforeshortened."""
    sight = through_mm - cam.center
    along = np.cross(sight, [0.0, 0.0, 1.0])
    along /= np.linalg.norm(along)
    s = np.linspace(-before_mm, after_mm, 101)
    return through_mm + s[:, None] * along


def _on_mask(cam: SynthCamera, mask: NDArray[np.bool_], points_mm: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Whether each point (P, 3) projects (OpenCV) onto a mask pixel."""
    uv, _ = cv2.projectPoints(points_mm, cv2.Rodrigues(cam.R)[0], cam.t, cam.K, cam.dist)
    iu, iv = np.rint(uv.reshape(-1, 2)).astype(int).T
    return mask[iv, iu]


def _width_mm(cam: SynthCamera, mask: NDArray[np.bool_], line: NDArray[np.float64], s_index: int) -> float:
    """The silhouette's width across a straight centreline at sample ``s_index``, in mm at the
    tube's depth: the extent of points on the across-direction that land on the mask."""
    along = line[-1] - line[0]
    across = np.cross(along, line[s_index] - cam.center)
    across /= np.linalg.norm(across)
    u = np.arange(-15.0, 15.0, 0.05)
    hits = _on_mask(cam, mask, line[s_index] + u[:, None] * across)
    return float(u[hits].max() - u[hits].min()) if hits.any() else 0.0


ZOOM_TARGET_MM = np.array([128.0, 128.0, 150.0])


@pytest.fixture(scope="module")
def zoom_cam() -> SynthCamera:
    return _zoomed(make_rig()[0], ZOOM_TARGET_MM)


def test_round_tip_reaches_a_radius_past_the_backbone_end(zoom_cam: SynthCamera) -> None:
    line = _straight_across(zoom_cam, ZOOM_TARGET_MM, 60.0, 0.0)
    tangent = (line[-1] - line[-2]) / np.linalg.norm(line[-1] - line[-2])
    beyond = ZOOM_TARGET_MM + np.array([0.4, 0.8, 1.25])[:, None] * RADIUS_MM * tangent
    flat = tube_mask(zoom_cam, line, RADIUS_MM, tip="flat")
    round_ = tube_mask(zoom_cam, line, RADIUS_MM, tip="round")
    # At 4x zoom a pixel is ~0.5 mm here: 0.4 r and 0.8 r beyond the end lie 5 and 10 px
    # inside the cap's outline, 1.25 r lies 7 px outside it; the flat end stops at 0.
    np.testing.assert_array_equal(_on_mask(zoom_cam, round_, beyond), [True, True, False])
    np.testing.assert_array_equal(_on_mask(zoom_cam, flat, beyond), [False, False, False])
    # Farther than 2.5 r (30 px) from the end's image the two tubes are the same, pixel for pixel.
    end_px = cv2.projectPoints(
        ZOOM_TARGET_MM[None], cv2.Rodrigues(zoom_cam.R)[0], zoom_cam.t, zoom_cam.K, zoom_cam.dist
    )[0].ravel()
    v, u = np.mgrid[0:240, 0:320]
    away = np.hypot(u - end_px[0], v - end_px[1]) > 30.0
    assert np.array_equal(round_[away], flat[away]) and flat[away].sum() > 1000
    assert round_[~away].sum() > flat[~away].sum()


@pytest.mark.parametrize(
    ("profile", "samples"),
    [("tapered", (10, 50, 90)), ("step", (30, 45, 70)), ("disks", (40, 50, 60))],
)
def test_radius_profile_sets_the_silhouette_width(
    zoom_cam: SynthCamera, profile: str, samples: tuple
) -> None:
    line = _straight_across(zoom_cam, ZOOM_TARGET_MM, 50.0, 50.0)  # sample i at arc i mm
    prof = RadiusProfile(profile, RADIUS_MM, disk_spacing_mm=20.0)
    radii = radius_along(prof, np.linspace(0.0, 100.0, len(line)))
    disks = disks_of(prof, 100.0)
    mask = tube_mask(zoom_cam, line, radii, disks=disks)
    for i in samples:
        expected = 2.0 * radii[i]
        if disks is not None and np.min(np.abs(disks.arc_mm - i)) < 0.5:
            expected = 2.0 * disks.radius_mm  # sample i sits at arc i mm: on a disk
        # Widths are read to the nearest pixel at each rim, ~0.5 mm at 4x zoom.
        assert _width_mm(zoom_cam, mask, line, i) == pytest.approx(expected, abs=1.0), (profile, i)


def test_disks_and_taper_change_the_width_as_described(zoom_cam: SynthCamera) -> None:
    line = _straight_across(zoom_cam, ZOOM_TARGET_MM, 50.0, 50.0)
    arc = np.linspace(0.0, 100.0, len(line))
    uniform = tube_mask(zoom_cam, line, RADIUS_MM)
    disks = disks_of(RadiusProfile("disks", RADIUS_MM), 100.0)
    assert disks is not None and list(disks.arc_mm) == [20.0, 40.0, 60.0, 80.0]
    with_disks = tube_mask(zoom_cam, line, RADIUS_MM, disks=disks)
    tapered = tube_mask(zoom_cam, line, radius_along(RadiusProfile("tapered", RADIUS_MM), arc))
    # On a disk 1.5x wider, between disks as wide as the plain tube; the taper ends at 0.6 r.
    assert _width_mm(zoom_cam, with_disks, line, 40) > 1.4 * _width_mm(zoom_cam, uniform, line, 40)
    assert _width_mm(zoom_cam, with_disks, line, 50) == pytest.approx(_width_mm(zoom_cam, uniform, line, 50))
    assert _width_mm(zoom_cam, tapered, line, 95) < 0.7 * _width_mm(zoom_cam, uniform, line, 95)
    assert with_disks.sum() > uniform.sum() > tapered.sum()


def test_varying_radius_mask_matches_brute_force_swept_balls() -> None:
    """A pixel centre is in the mask exactly when its ray passes within r(u) of some point
    q(u) of the polyline, r varying linearly between vertices (the swept balls), with a
    round tip; away from the flat base."""
    cam = make_rig()[1]
    line = np.ascontiguousarray(
        shape_centerlines("s_curve", 10, base_mm=BASE_MM)[3][::4]
    )  # 50 points, 5 mm apart
    radii = 5.0 + 2.0 * np.sin(np.arange(len(line)) / 3.0)  # slopes up to 0.13
    radii[30:] -= 1.5  # and a step down over one segment (slope 0.3)
    mask = tube_mask(cam, line, radii, tip="round")
    v, u = np.mgrid[0:240, 0:320]
    line_px = cv2.projectPoints(line, cv2.Rodrigues(cam.R)[0], cam.t, cam.K, cam.dist)[0].reshape(-1, 2)
    box = (
        (u > line_px[:, 0].min() - 15)
        & (u < line_px[:, 0].max() + 15)
        & (v > line_px[:, 1].min() - 15)
        & (v < line_px[:, 1].max() + 15)
    )
    assert not mask[~box].any()
    dirs = ray_directions(cam, np.stack([u[box], v[box]], axis=1).astype(np.float64))
    o = cam.center
    margin = np.full(len(dirs), np.inf)  # min over q(u) of distance(ray, q(u)) - r(u)
    for k in range(len(line) - 1):
        w = np.linspace(0.0, 1.0, 41)[:, None]
        q = line[k] + w * (line[k + 1] - line[k])
        r = radii[k] + w[:, 0] * (radii[k + 1] - radii[k])
        rel = q - o
        along = dirs @ rel.T
        perp = np.sqrt(np.clip(np.einsum("ij,ij->i", rel, rel)[None] - along**2, 0.0, None))
        margin = np.minimum(margin, (perp - r[None]).min(axis=1))
    near = margin <= 0.0
    far_from_base = np.hypot(u[box] - line_px[0, 0], v[box] - line_px[0, 1]) > 8
    keep = ~_rim(mask)[box] & far_from_base
    # Sampling 41 points per 5 mm segment overestimates the margin by < 0.02 mm (0.01 px):
    # only the anti-aliasing rim may disagree.
    assert np.array_equal(mask[box][keep], near[keep])
    assert mask[box][keep].sum() > 100


def test_uniform_radius_array_renders_like_one_radius() -> None:
    """A constant per-point radius goes through the frustum formulas and must give the
    cylinder's bits exactly: named-shape sessions render as they always have."""
    cams = make_rig()
    backgrounds = [background_texture(320, 240, seed=1, camera_index=i) for i in range(3)]
    line = shape_centerlines("loop", 10, base_mm=BASE_MM)[4]
    a = render_frame(cams, line, RADIUS_MM, backgrounds, seed=1)
    b = render_frame(cams, line, np.full(len(line), RADIUS_MM), backgrounds, seed=1)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_two_camera_session(tmp_path: Path) -> None:
    render_session(tmp_path, frames=2, options=SceneOptions(cameras=2), progress=False)
    with (tmp_path / "calibration.toml").open("rb") as f:
        calib = tomllib.load(f)
    assert sorted(k for k in calib if k.startswith("cam_")) == ["cam_0", "cam_1"]
    assert sorted(p.name for p in tmp_path.glob("*.mp4")) == ["cam0.mp4", "cam1.mp4"]
    gt = np.load(tmp_path / "ground_truth.npz")
    assert gt["K"].shape == (2, 3, 3) and list(gt["camera_names"]) == ["cam0", "cam1"]


def test_large_images_show_the_same_scene_finer(tmp_path: Path) -> None:
    render_session(
        tmp_path,
        shape="straight",
        frames=1,
        options=SceneOptions(cameras=2, size=(1280, 960)),
        progress=False,
    )
    with (tmp_path / "calibration.toml").open("rb") as f:
        assert tomllib.load(f)["cam_1"]["size"] == [1280, 960]
    frame = _frames(tmp_path / "cam1.mp4")[0]
    assert frame.shape == (960, 1280)
    line = np.load(tmp_path / "ground_truth.npz")["centerlines"][0]
    small = tube_mask(make_rig()[1], line, RADIUS_MM)
    # 4x the width and height: 16x the tube's pixels, within its rim's share.
    assert (frame < threshold_for("dark")).sum() == pytest.approx(16 * small.sum(), rel=0.1)
    # The same lens: a world point lands at 4x its pixel position (pixel corners scale).
    big, base = make_rig(size=(1280, 960))[1], make_rig()[1]
    uv_big = cv2.projectPoints(line, cv2.Rodrigues(big.R)[0], big.t, big.K, big.dist)[0].reshape(-1, 2)
    uv = cv2.projectPoints(line, cv2.Rodrigues(base.R)[0], base.t, base.K, base.dist)[0].reshape(-1, 2)
    np.testing.assert_allclose(uv_big + 0.5, 4.0 * (uv + 0.5), atol=1e-9)


def test_distractor_is_dark_in_one_background_only(tmp_path: Path) -> None:
    render_session(tmp_path, frames=2, seed=4, options=SceneOptions(distractor=True), progress=False)
    gt = np.load(tmp_path / "ground_truth.npz")
    which = int(gt["distractor_camera"])
    dark = [
        int(
            (
                cv2.imread(str(tmp_path / "background" / f"{n}.png"), cv2.IMREAD_GRAYSCALE) < THRESHOLD_DARK
            ).sum()
        )
        for n in NAMES
    ]
    # A blob 10-22 px in semi-axes: hundreds of pixels below the threshold, in that view only.
    assert dark[which] > 200 and sum(dark) == dark[which]
    # It is apart from the tube: the view's thresholded frame has two blobs.
    frame = _frames(tmp_path / f"cam{which}.mp4")[0]
    count, _ = cv2.connectedComponents((frame < THRESHOLD_DARK).astype(np.uint8))
    assert count - 1 == 2


def test_flicker_scales_each_frame_by_its_gain(tmp_path: Path) -> None:
    render_session(tmp_path, frames=6, options=SceneOptions(flicker=True), progress=False)
    gains = np.load(tmp_path / "ground_truth.npz")["flicker_gain"]
    assert np.all(np.abs(gains - 1.0) <= FLICKER) and np.ptp(gains) > 0.02
    background = cv2.imread(str(tmp_path / "background" / "cam0.png"), cv2.IMREAD_GRAYSCALE).astype(float)
    frames = _frames(tmp_path / "cam0.mp4").astype(float)
    # Pixel by pixel the scene is the background times the gain; the median leaves out the
    # tube (~1 % of the view). The codec darkens every frame alike (by ~1 %), so frames are
    # compared with their mean; noise and compression leave a few tenths of a percent.
    ratio = np.median(frames / background, axis=(1, 2))
    np.testing.assert_allclose(ratio / ratio.mean(), gains / gains.mean(), atol=0.004)


def test_round_tip_and_profile_in_ground_truth(tmp_path: Path) -> None:
    render_session(
        tmp_path,
        shape="s_curve",
        frames=2,
        options=SceneOptions(tip="round", profile="tapered"),
        progress=False,
    )
    gt = np.load(tmp_path / "ground_truth.npz")
    assert set(gt.files) == GT_KEYS
    assert (str(gt["tip"]), str(gt["profile"])) == ("round", "tapered")
    assert gt["radius_profile_mm"].shape == (2, 200)
    np.testing.assert_allclose(gt["radius_profile_mm"][:, [0, -1]], [[6.0, 3.6]] * 2)
    assert float(gt["radius_mm"]) == 6.0  # the nominal radius, as session.toml says
    np.testing.assert_allclose(
        np.linalg.norm(np.diff(gt["centerlines"][0], axis=0), axis=1).sum(), 250.0, rtol=1e-3
    )


# --- random shapes ----------------------------------------------------------------------


def _turning(lines: NDArray[np.float64]) -> NDArray[np.float64]:
    """Turning angle (rad) at each interior sample, (F, N - 2)."""
    t = np.diff(lines, axis=1)
    t /= np.linalg.norm(t, axis=2, keepdims=True)
    return np.arccos(np.clip(np.einsum("fij,fij->fi", t[:, 1:], t[:, :-1]), -1.0, 1.0))


@pytest.fixture(scope="module")
def random_motions() -> list[tuple[RadiusProfile, str, NDArray[np.float64]]]:
    """A period of motion of random shapes for several seeds, profiles and tips."""
    out = []
    for seed, (kind, radius, tip) in enumerate(
        [("uniform", 6.0, "flat"), ("disks", 5.0, "round"), ("tapered", 8.0, "round"), ("step", 4.0, "flat")]
        * 2
    ):
        profile = RadiusProfile(kind, radius)
        shape = draw_shape(
            seed,
            profile=profile,
            tip=tip,
            base_mm=BASE_MM,
            box_lo_mm=np.zeros(3),
            box_hi_mm=np.full(3, 256.0),
        )
        lines = shape_at(shape, np.arange(PERIOD_FRAMES, dtype=np.float64), base_mm=BASE_MM)
        out.append((profile, tip, lines))
    return out


def test_random_shapes_stay_in_the_box_and_off_themselves(random_motions: list) -> None:
    for profile, tip, lines in random_motions:
        widest = max_radius(profile)
        np.testing.assert_array_equal(lines[:, 0], np.broadcast_to(BASE_MM, (len(lines), 3)))
        # The rim of the cross-section at each sample: a ring of radius r(s) across the tangent.
        length = np.linalg.norm(np.diff(lines[0], axis=0), axis=1).sum()
        radii = radius_along(profile, np.linspace(0.0, length, lines.shape[1]))
        tangent = np.gradient(lines, axis=1, edge_order=2)
        tangent /= np.linalg.norm(tangent, axis=2, keepdims=True)
        n1 = np.cross(tangent, [0.3, 0.5, 0.8])
        n1 /= np.linalg.norm(n1, axis=2, keepdims=True)
        n2 = np.cross(tangent, n1)
        for a in np.linspace(0.0, 2.0 * np.pi, 16, endpoint=False):
            rim = lines + radii[:, None] * (np.cos(a) * n1 + np.sin(a) * n2)
            # 0.01 mm: finite-difference tangents tilt the base's rim below the floor by ~(kappa h)^2.
            assert rim.min() >= -0.01 and rim.max() <= 256.01, profile
        if tip == "round":
            end = lines[:, -1]
            assert (end - radii[-1]).min() >= 0.0 and (end + radii[-1]).max() <= 256.0
        # Parts more than 4 widest radii apart along the backbone keep 2.5 of them apart
        # (less 0.3 mm: only every other sample of every third frame is compared here).
        sub = lines[::3, ::2]
        arc = np.linspace(0.0, length, sub.shape[1])
        far = np.abs(arc[:, None] - arc[None]) > 4.0 * widest
        gaps = np.linalg.norm(sub[:, :, None] - sub[:, None], axis=-1)
        assert gaps[:, far].min() > 2.5 * widest - 0.3, profile


def test_random_shapes_respect_the_bending_limit(random_motions: list) -> None:
    for profile, _, lines in random_motions:
        h = np.linalg.norm(lines[0, 1] - lines[0, 0])
        bend_radius = h / _turning(lines).max()
        assert bend_radius >= 3.0 * profile.radius_mm * 0.98, profile


def test_random_shapes_include_loops(random_motions: list) -> None:
    # Over the draws some turn by more than a full circle within 200 mm of their length, some do not.
    def max_turn(lines: NDArray[np.float64]) -> float:
        turning = np.cumsum(_turning(lines[::30]), axis=1)
        h = np.linalg.norm(lines[0, 1] - lines[0, 0])
        window = int(200.0 / h)
        return float((turning[:, window:] - turning[:, :-window]).max()) if turning.shape[1] > window else 0.0

    turns = [max_turn(lines) / (2.0 * math.pi) for _, _, lines in random_motions]
    assert max(turns) > 1.0 and min(turns) < 0.8


def test_random_motion_is_smooth_and_periodic(random_motions: list) -> None:
    for _, _, lines in random_motions:
        tips = lines[:, -1]
        steps = np.linalg.norm(np.diff(tips, axis=0, append=tips[:1]), axis=1)
        assert steps.max() <= MAX_TIP_STEP_MM
        # Smooth: the tip's acceleration stays small (mm per frame^2), across the period's wrap too.
        accel = np.linalg.norm(np.roll(tips, -1, axis=0) - 2.0 * tips + np.roll(tips, 1, axis=0), axis=1)
        assert accel.max() < 0.5
        # The whole shape moves: the tip travels tens of mm over a period.
        assert np.ptp(tips, axis=0).max() > 20.0


def test_random_shape_session_is_deterministic_and_in_arc_length(tmp_path: Path) -> None:
    a = session_centerlines("random", 40, seed=11, length_mm=250.0, profile=RadiusProfile(), tip="flat")
    b = session_centerlines("random", 40, seed=11, length_mm=250.0, profile=RadiusProfile(), tip="flat")
    c = session_centerlines("random", 40, seed=12, length_mm=250.0, profile=RadiusProfile(), tip="flat")
    np.testing.assert_array_equal(a[0], b[0])
    assert not np.allclose(a[0], c[0])
    steps = np.linalg.norm(np.diff(a[0], axis=1), axis=2)
    # Exact arcs between samples: chords fall short of h by (kappa h)^2 / 24 < 1e-4 of h.
    np.testing.assert_allclose(steps, a[1] / 199, rtol=1e-4)
    assert LENGTH_RANGE_MM[0] <= a[1] <= LENGTH_RANGE_MM[1]


# --- the variety draws ------------------------------------------------------------------


def test_draw_cases_is_deterministic_and_covers_every_option() -> None:
    cases = draw_cases(3, 40)
    assert draw_cases(3, 40) == cases
    assert draw_cases(4, 40) != cases
    assert len({c.name for c in cases}) == 40
    assert {c.shape for c in cases} == {*SHAPES, "random"}
    # Three whole rounds of 12 (6 random) and 4 of a fourth.
    assert 18 <= sum(c.shape == "random" for c in cases) <= 22
    assert {c.tip for c in cases} == set(TIPS)
    assert {c.profile for c in cases} == set(PROFILES)
    assert {c.arrangement for c in cases} == {"oblique", "ninety"}
    assert {c.cameras for c in cases} == {2, 3}
    assert {c.distractor for c in cases} == {c.flicker for c in cases} == {False, True}
    assert {c.polarity for c in cases} == {"dark", "bright"}
    assert {c.size for c in cases} == {(320, 240)}
    assert {c.size for c in draw_cases(3, 2, size=(1280, 960))} == {(1280, 960)}
    radii = [c.radius_mm for c in cases]
    assert min(radii) >= 4.0 and max(radii) <= 8.0 and len(set(radii)) > 4


def test_render_case_writes_what_the_case_says(tmp_path: Path) -> None:
    case = next(c for c in draw_cases(5, 20) if c.cameras == 2 and c.shape != "random")
    render_case(case, tmp_path, 2)
    gt = np.load(tmp_path / "ground_truth.npz")
    assert str(gt["shape"]) == case.shape and str(gt["tip"]) == case.tip
    assert str(gt["profile"]) == case.profile and len(gt["camera_names"]) == 2
    assert (int(gt["distractor_camera"]) >= 0) == case.distractor
    assert load_settings(tmp_path / "session.toml").silhouette.polarity == case.polarity
    assert float(gt["calib_error_deg"]) == 0.0


def test_drawn_spacer_disks_vary_and_are_rendered_as_drawn(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cases = draw_cases(3, 40)
    disks = [c for c in cases if c.profile == "disks"]
    assert len({(c.disk_spacing_mm, c.disk_ratio, c.disk_thickness_mm) for c in disks}) == len(disks) > 3
    assert all(12.0 <= c.disk_spacing_mm <= 36.0 and 1.3 <= c.disk_ratio <= 2.0 for c in disks)
    # The disks are drawn apart from the rest: with other disks, every other option of
    # every case is the same (but the radius of a named shape that wider disks would take
    # out of the workspace, drawn thinner to fit).
    import pipeline.synth.variety as variety

    monkeypatch.setattr(variety, "_disks", lambda seed, index: {"disk_spacing_mm": 50.0})
    others = draw_cases(3, 40)

    def rest(case: Case) -> Case:
        return dataclasses.replace(
            case, radius_mm=0.0, disk_spacing_mm=0.0, disk_ratio=0.0, disk_thickness_mm=0.0
        )

    assert [rest(c) for c in others] == [rest(c) for c in cases]
    assert [c.disk_spacing_mm for c in others if c.profile == "disks"] == [50.0] * len(disks)
    monkeypatch.undo()
    case = disks[0]
    render_case(case, tmp_path, 2)
    gt = np.load(tmp_path / "ground_truth.npz")
    assert str(gt["profile"]) == "disks"
    np.testing.assert_allclose(np.diff(gt["disk_arc_mm"]), case.disk_spacing_mm)
    assert float(gt["disk_radius_mm"]) == pytest.approx(case.disk_ratio * case.radius_mm)
    assert float(gt["disk_thickness_mm"]) == case.disk_thickness_mm


def test_a_drawn_case_with_a_calibration_error_says_so_and_renders_it(tmp_path: Path) -> None:
    case = dataclasses.replace(draw_cases(5, 1)[0], calib_error_deg=0.05)
    assert case.name.endswith("-calib0.05") and "0.05 deg off" in case.describe()
    assert case.name != draw_cases(5, 1)[0].name
    render_case(case, tmp_path, 2)
    gt = np.load(tmp_path / "ground_truth.npz")
    assert float(gt["calib_error_deg"]) == 0.05
    given = read_calibration(tmp_path / "calibration.toml")
    assert all(not np.allclose(cam.matrix, k) for cam, k in zip(given, gt["K"], strict=True))


@pytest.mark.parametrize("bumped", [0, 2])
def test_a_bumped_camera_alone_is_off_turned_about_its_centre(tmp_path: Path, bumped: int) -> None:
    options = SceneOptions(calib_error_deg=0.6, bumped_camera=bumped)
    render_session(tmp_path, frames=2, seed=3, options=options, progress=False, jobs=1)
    gt = np.load(tmp_path / "ground_truth.npz")
    assert int(gt["bumped_camera"]) == bumped
    for k, cam in enumerate(read_calibration(tmp_path / "calibration.toml")):
        np.testing.assert_allclose(cam.matrix, gt["K"][k])
        np.testing.assert_allclose(cam.center_mm, -gt["R"][k].T @ gt["t"][k], atol=1e-9)
        turn = cam.camera_from_world @ gt["R"][k].T
        angle = np.rad2deg(np.linalg.norm(cv2.Rodrigues(turn)[0]))
        assert angle == pytest.approx(0.6 if k == bumped else 0.0, abs=1e-6)


def test_bad_variety_options_raise_pipeline_errors(tmp_path: Path) -> None:
    with pytest.raises(PipelineError, match="unknown tip 'pointy'"):
        render_session(tmp_path, frames=2, options=SceneOptions(tip="pointy"), progress=False)
    with pytest.raises(PipelineError, match="unknown radius profile 'wavy'"):
        render_session(tmp_path, frames=2, options=SceneOptions(profile="wavy"), progress=False)
    with pytest.raises(PipelineError, match="2 or 3 cameras, got 4"):
        render_session(tmp_path, frames=2, options=SceneOptions(cameras=4), progress=False)
    with pytest.raises(PipelineError, match="image size must be one of 320x240, 1280x960, got 640x480"):
        render_session(tmp_path, frames=2, options=SceneOptions(size=(640, 480)), progress=False)
    with pytest.raises(PipelineError, match="--bumped-camera needs --calib-error DEG"):
        render_session(tmp_path, frames=2, options=SceneOptions(bumped_camera=1), progress=False)
    bumped = SceneOptions(cameras=2, calib_error_deg=0.5, bumped_camera=2)
    with pytest.raises(PipelineError, match="a camera's index, 0-1, got 2"):
        render_session(tmp_path, frames=2, options=bumped, progress=False)


def test_the_arrangements_the_command_line_offers_are_the_rigs_placements() -> None:
    assert ARRANGEMENT_NAMES == tuple(ARRANGEMENTS)


def test_a_full_disk_leaves_no_half_made_session(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import errno
    import os

    from pipeline.synth import session_render

    def full(*args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with monkeypatch.context() as m:
        m.setattr(session_render, "write_npz_deterministic", full)
        with pytest.raises(
            PipelineError, match=r"new: cannot write the session \(No space left on device\); nothing"
        ):
            render_session(tmp_path / "new", frames=2, progress=False, jobs=1)
    assert not (tmp_path / "new").exists()

    real_writer = cv2.VideoWriter

    class LosingFrames:
        """OpenCV's writer on a full disk: it takes every frame and writes none, silently."""

        fourcc = real_writer.fourcc

        def __init__(self, path: str, *args: object) -> None:
            self.real = real_writer(path, *args)
            self.lose = path.endswith("cam2.mp4")

        def write(self, image: np.ndarray) -> None:
            if not self.lose:
                self.real.write(image)

        def __getattr__(self, name: str) -> object:
            return getattr(self.real, name)

    monkeypatch.setattr(session_render.cv2, "VideoWriter", LosingFrames)
    with pytest.raises(PipelineError, match=r"cam2\.mp4 holds 0 of its 2 frames \(a full disk\?\)"):
        render_session(tmp_path / "new", frames=2, progress=False, jobs=1)
    assert not (tmp_path / "new").exists()


def test_an_interrupted_render_leaves_no_half_made_session_or_says_so(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pipeline.errors import Interrupted
    from pipeline.synth import session_render

    render_session(tmp_path / "earlier", frames=2, progress=False, jobs=1)

    def interrupted(*args: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(session_render, "_write_videos", interrupted)
    with pytest.raises(Interrupted, match=r"^interrupted; nothing written$"):
        render_session(tmp_path / "new", frames=2, progress=False, jobs=1)
    assert not (tmp_path / "new").exists()
    with pytest.raises(Interrupted, match=r"earlier is incomplete: render it again"):
        render_session(tmp_path / "earlier", frames=2, progress=False, jobs=1)
    # What it left is neither render: the readers refuse it, and a render finishes it.
    from pipeline.errors import EvaluationError, SessionError
    from pipeline.measure.evaluate import load_ground_truth
    from pipeline.session.folder import load_session

    unfinished = r"earlier: a synthetic render stopped part-way here \(UNFINISHED-RENDER\.txt\); render it"
    with pytest.raises(SessionError, match=unfinished):
        load_session(tmp_path / "earlier")
    with pytest.raises(EvaluationError, match=unfinished):
        load_ground_truth(tmp_path / "earlier")
    monkeypatch.undo()
    render_session(tmp_path / "earlier", frames=2, progress=False, jobs=1)
    assert len(load_session(tmp_path / "earlier").cameras) == 3
    assert not (tmp_path / "earlier" / "UNFINISHED-RENDER.txt").exists()


def test_synth_draws_no_progress_bar_into_a_log(tmp_path: Path) -> None:
    # stderr a file or a pipe, not a terminal: a bar's redraws would fill it with lines.
    import subprocess
    import sys

    proc = subprocess.run(
        [sys.executable, "-m", "pipeline", "synth", str(tmp_path / "s"), "--frames", "2"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    assert "\r" not in proc.stderr and "rendering" not in proc.stderr
    assert proc.stderr.strip().endswith("(bend_rotate, 2 frames)")


def test_a_background_opencv_does_not_write_is_named_and_leaves_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # OpenCV returns False, raising nothing, where it cannot write (a full disk).
    monkeypatch.setattr("pipeline.synth.out_dir.cv2.imwrite", lambda *_: False)
    with pytest.raises(
        PipelineError,
        match=r"new: cannot write the session \(OpenCV wrote no image: a full disk.*; nothing written",
    ):
        render_session(tmp_path / "new", frames=2, progress=False, jobs=1)
    assert not (tmp_path / "new").exists()


def test_an_earlier_render_on_a_read_only_file_system_is_left_as_it_was(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The folder takes no file (a read-only mount): the render stops before marking the
    # earlier one unfinished, which is unchanged, and says so (not "free space").
    earlier = tmp_path / "earlier"
    render_session(earlier, frames=2, progress=False, jobs=1)
    before = {p: p.read_bytes() for p in earlier.rglob("*") if p.is_file()}

    @contextlib.contextmanager
    def read_only(out_dir: Path) -> Iterator[None]:
        raise OSError(errno.EROFS, "Read-only file system", str(out_dir / "UNFINISHED-RENDER.txt"))
        yield

    monkeypatch.setattr("pipeline.synth.session_render.unfinished", read_only)
    with pytest.raises(
        PipelineError,
        match=r"\(Read-only file system\); the earlier render in .*earlier is unchanged; give a directory",
    ):
        render_session(earlier, frames=2, progress=False, jobs=1)
    assert {p: p.read_bytes() for p in earlier.rglob("*") if p.is_file()} == before


def test_a_thin_tubes_session_has_voxels_fine_enough_for_process(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # A silhouette two or three pixels wide needs voxels of at most the tube's radius
    # (docs/troubleshooting.md): a session synth writes for a thin tube must have them.
    from pipeline.errors import PipelineError
    from pipeline.session.folder import load_session

    with caplog.at_level(logging.WARNING):
        render_session(tmp_path / "thin", frames=2, radius_mm=1.5, progress=False, jobs=1)
    assert load_session(tmp_path / "thin").settings.workspace.voxel_mm == pytest.approx(1.5)
    assert "too thin" not in caplog.text
    # Under a pixel and a half wide in every view: warned of, with what to do.
    with caplog.at_level(logging.WARNING):
        render_session(tmp_path / "thinner", frames=2, radius_mm=0.7, progress=False, jobs=1)
    assert "a tube of radius 0.7 mm is about 0." in caplog.text
    assert "px wide at its narrowest in these 320x240 images: too thin for process" in caplog.text
    render_session(tmp_path / "usual", frames=2, radius_mm=6.0, progress=False, jobs=1)
    assert load_session(tmp_path / "usual").settings.workspace.voxel_mm == 2.0
    with pytest.raises(PipelineError, match=r"radius_mm must be in 0\.5-20 mm, got 0\.05"):
        render_session(tmp_path / "thinnest", frames=2, radius_mm=0.05, progress=False, jobs=1)
    assert not (tmp_path / "thinnest").exists()
