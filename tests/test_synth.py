"""The synthetic renderer is an oracle: check it against OpenCV and exact geometry only,
never against the reconstruction modules."""

from __future__ import annotations

import dataclasses
import itertools
import math
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from pipeline.errors import PipelineError
from pipeline.settings import load_settings
from pipeline.synth.images import background_texture, render_frame, threshold_for, tube_mask
from pipeline.synth.raycast import distort_normalized, ray_directions, undistort_pixels
from pipeline.synth.rig import make_rig
from pipeline.synth.session_render import BASE_MM, check_poses, render_session
from pipeline.synth.shapes import Segment, centerline, shape_centerlines
from pipeline.synth_names import SHAPES

FRAMES = 12
RADIUS_MM = 6.0
NAMES = ("cam0", "cam1", "cam2")
GT_KEYS = {
    "centerlines",
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
    with pytest.raises(PipelineError, match="--frames must be at least 1"):
        render_session(tmp_path, frames=0, progress=False)
    with pytest.raises(PipelineError, match="unknown arrangement"):
        render_session(tmp_path, frames=2, arrangement="square", progress=False)
