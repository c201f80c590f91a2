"""Cameras refined from a session's silhouettes: a calibration that is off comes closer to
the true rig, an exact one is kept, a moved camera is named, the world frame stays."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import rig_cameras

from pipeline.calibrate.adjust import (
    N_PARAMS,
    Tube,
    aligned_by_images,
    moved_camera,
    nearest_to_given,
    parameter_jacobian,
    similar_camera,
)
from pipeline.calibrate.mount import mount_shift, moved_to_mount
from pipeline.calibrate.refine import (
    Refinement,
    distinct_poses,
    refine,
    refined_cameras,
    refitter,
    sample_session,
    sample_tubes,
)
from pipeline.errors import SettingsError
from pipeline.geometry.camera import Camera
from pipeline.reconstruct.frame_task import decode_frames
from pipeline.reconstruct.model import SessionModel, build_model
from pipeline.reconstruct.tip_shape import sample_frames
from pipeline.session.folder import load_session
from pipeline.session.settings import settings_from_dict
from pipeline.synth import render_session
from pipeline.synth.session_render import SceneOptions
from pipeline.synth.variety import draw_cases, render_case

FRAMES = 30
# Per calibration error: the session's model, the tubes of some of its frames, and those
# frames' tubes reconstructed with other cameras (refine's refit).
Sampled = dict[float, tuple[SessionModel, list[Tube], Callable[[Sequence[Camera]], list[Tube]]]]


def _true_cameras(session_dir: Path) -> list[Camera]:
    gt = np.load(session_dir / "ground_truth.npz")
    return [
        Camera(
            str(name),
            (int(gt["image_size"][0]), int(gt["image_size"][1])),
            gt["K"][i],
            gt["dist"][i],
            cv2.Rodrigues(gt["R"][i])[0].ravel(),
            gt["t"][i],
        )
        for i, name in enumerate(gt["camera_names"])
    ]


def _image_error_px(
    cameras: list[Camera] | tuple[Camera, ...], truth: list[Camera], points_mm: np.ndarray
) -> np.ndarray:
    """(C,) RMS distance (px) between each camera's and the true camera's images of the points."""
    return np.array(
        [
            np.sqrt(np.mean(np.sum((c.project(points_mm) - t.project(points_mm)) ** 2, axis=1)))
            for c, t in zip(cameras, truth, strict=True)
        ]
    )


@pytest.fixture(scope="module")
def sessions(tmp_path_factory: pytest.TempPathFactory) -> dict[float, Path]:
    """A random shape (seeded) filmed with the true cameras, its calibration exact or off."""
    root = tmp_path_factory.mktemp("refine")
    out = {}
    for error_deg in (0.0, 0.15):
        out[error_deg] = root / f"e{error_deg:g}"
        render_session(
            out[error_deg],
            shape="random",
            frames=FRAMES,
            seed=23,
            radius_mm=6.0,
            options=SceneOptions(calib_error_deg=error_deg),
            progress=False,
            jobs=1,
        )
    return out


@pytest.fixture(scope="module")
def sampled(sessions: dict[float, Path]) -> Sampled:
    """Per calibration error, the session's model and the tubes of 12 of its frames."""
    out = {}
    for error_deg, session_dir in sessions.items():
        session = load_session(session_dir)
        model = build_model(session)
        frames = decode_frames(session.video_paths, sample_frames(0, FRAMES, 12))
        out[error_deg] = (model, sample_tubes(model, frames), refitter(model, frames))
    return out


def _refined(
    sampled: Sampled, error_deg: float, mode: str | bool = "auto"
) -> tuple[SessionModel, tuple[tuple[Camera, ...], Refinement]]:
    model, tubes, refit = sampled[error_deg]
    return model, refine(model, tubes, mode, refit)


def test_synth_writes_a_calibration_off_by_the_error_asked_for(sessions: dict[float, Path]) -> None:
    truth = _true_cameras(sessions[0.15])
    given = load_session(sessions[0.15]).cameras
    centrelines = np.load(sessions[0.15] / "ground_truth.npz")["centerlines"].reshape(-1, 3)
    error = _image_error_px(given, truth, centrelines)
    assert np.all(error > 0.3) and np.all(error < 4.0)
    exact = _image_error_px(load_session(sessions[0.0]).cameras, _true_cameras(sessions[0.0]), centrelines)
    assert np.all(exact < 1e-6)


def test_a_calibration_that_is_off_comes_closer_to_the_true_rig(
    sessions: dict[float, Path], sampled: Sampled
) -> None:
    model, (cameras, report) = _refined(sampled, 0.15)
    truth = _true_cameras(sessions[0.15])
    points = np.load(sessions[0.15] / "ground_truth.npz")["centerlines"].reshape(-1, 3)
    before = _image_error_px(model.cameras, truth, points)
    after = _image_error_px(cameras, truth, points)
    assert report.applied
    assert report.after_px < 0.5 * report.before_px
    # Held to the mount, the refined rig itself (not only up to a similarity) nears the truth.
    assert report.mount_shift_mm is not None and "to the mount" in report.describe()
    assert np.sqrt(np.mean(after**2)) < 0.2 * np.sqrt(np.mean(before**2))
    # Up to a turn, scale and shift of the whole rig (which the silhouettes cannot
    # tell, and the given calibration anchors), the refined rig is the true one.
    rms = [
        np.sqrt(np.mean(_image_error_px(aligned_by_images(c, truth, points), truth, points) ** 2))
        for c in (model.cameras, cameras)
    ]
    assert rms[1] < 0.5 * rms[0]
    # The cameras named as moved are among those that are off by more than half a pixel.
    named = {c.name for c in model.cameras if any(f"camera {c.name} " in line for line in report.warnings())}
    assert named and named <= {c.name for c, e in zip(model.cameras, before, strict=True) if e > 0.5}


def test_a_camera_bumped_alone_is_refined_alone_and_the_others_kept(sessions: dict[float, Path]) -> None:
    # One camera of the exact rig turned about its centre, as a bump does (0.3-1 deg, a
    # random axis; at 0.8 deg its image of the tube lies off the silhouette by a radius or
    # two): it alone is corrected and named, the others are kept as they are. Where two
    # cameras alone explain the silhouettes alike, every camera is adjusted as before: never
    # another camera alone.
    session = load_session(sessions[0.0])
    truth = _true_cameras(sessions[0.0])
    points = np.load(sessions[0.0] / "ground_truth.npz")["centerlines"].reshape(-1, 3)
    frames = decode_frames(session.video_paths, sample_frames(0, FRAMES, 12))
    singled_out = 0
    for seed in (4, 9, 11):
        rng = np.random.default_rng(seed)
        bumped = int(rng.integers(len(session.cameras)))
        axis = rng.normal(size=3)
        turn = np.deg2rad(rng.uniform(0.3, 1.0)) * axis / np.linalg.norm(axis)
        camera = session.cameras[bumped]
        rotation = cv2.Rodrigues(turn)[0] @ camera.camera_from_world
        moved = replace(
            camera, rotation=cv2.Rodrigues(rotation)[0].ravel(), translation_mm=-rotation @ camera.center_mm
        )
        given = tuple(moved if k == bumped else c for k, c in enumerate(session.cameras))
        model = build_model(replace(session, cameras=given))
        cameras, report = refine(model, sample_tubes(model, frames), "auto", refitter(model, frames))
        assert report.applied and report.alone in ("", camera.name)
        if not report.alone:
            continue
        singled_out += 1
        before = _image_error_px(given, truth, points)[bumped]
        after = _image_error_px(cameras, truth, points)[bumped]
        kept = np.delete(_image_error_px(cameras, given, points), bumped)
        assert np.all(kept < 1e-6)
        assert after < 0.15 * before
        assert [line.split()[1] for line in report.warnings()] == [camera.name]
        assert f"{camera.name} " in report.describe() and "kept as given" in report.describe()
    assert singled_out >= 2


def test_an_exact_calibration_is_kept(sampled: Sampled) -> None:
    model, (cameras, report) = _refined(sampled, 0.0)
    assert not report.applied and report.reason
    assert cameras is model.cameras
    assert report.warnings() == [] and report.problems() == []


def test_cameras_kept_whose_rig_sees_the_base_millimetres_off_are_moved_to_the_mount(
    sampled: Sampled,
) -> None:
    """A rig off as a whole (turned or shifted by the calibration's error, which no
    silhouette shows) sees the tube's base away from base_mm: the given cameras are kept
    as they are, and the world frame moved to the mount. A bend whose calibration is
    0.15 deg off (`synth --frames 60 --calib-error 0.15 --seed 3`) is 3.1 mm off on every
    frame with its cameras kept as they are, 0.24 mm moved (2026-12-05)."""
    model, tubes, refit = sampled[0.0]
    base = np.asarray(model.settings.manipulator.base_mm, dtype=np.float64)
    manipulator = replace(model.settings.manipulator, base_mm=tuple(base + np.array([0.0, 2.5, 0.0])))
    moved = replace(model, settings=replace(model.settings, manipulator=manipulator))
    cameras, report = refine(moved, tubes, "auto", refit)
    assert not report.applied and report.changed and report.mount_shift_mm is not None
    np.testing.assert_allclose(report.mount_shift_mm, (0.0, -2.5, 0.0), atol=0.6)
    assert report.describe().startswith("given (") and "to the mount" in report.describe()
    (line,) = report.warnings()
    assert line.startswith("the cameras see the tube's base 2.") and "or base_mm is off" in line
    expected = moved_to_mount(model.cameras, np.asarray(report.mount_shift_mm))
    for got, want in zip(cameras, expected, strict=True):
        np.testing.assert_allclose(got.project(base[None]), want.project(base[None]))
    # Where they see it at the mount, they are kept as they are (the test above).
    assert refine(model, tubes, "auto", refit)[0] is model.cameras


@pytest.mark.parametrize("off_mm", [(15.0, 0.0, 0.0), (0.0, 0.0, -15.0)])
def test_a_mount_set_far_from_the_base_is_named_where_the_cameras_are_kept(
    sampled: Sampled, off_mm: tuple[float, float, float]
) -> None:
    """An exact calibration is kept, and a base_mm 15 mm from where its cameras see the
    tube's base is named: every frame would be fitted to start there."""
    model, tubes, refit = sampled[0.0]
    base = np.asarray(model.settings.manipulator.base_mm, dtype=np.float64) + off_mm
    manipulator = replace(model.settings.manipulator, base_mm=tuple(base))
    moved = replace(model, settings=replace(model.settings, manipulator=manipulator))
    for frames in (tubes, [tubes[0]] * 6):  # kept for agreeing, and for one pose
        cameras, report = refine(moved, frames, "auto", refit)
        assert cameras is model.cameras and not report.applied
        (line,) = report.problems()
        assert "the tube's base is seen 1" in line and "check base_mm" in line
        assert report.warnings() == []


@pytest.mark.parametrize("kept_by", ["two cameras", "refine = false"])
def test_a_mount_set_far_from_the_base_is_named_where_nothing_is_refined(
    sessions: dict[float, Path], tmp_path: Path, kept_by: str
) -> None:
    """Cameras that are not refined (two of them, or ``[calibration] refine = false``) are
    still read for where they see the tube's base: a base_mm 15 mm off is named."""
    if kept_by == "two cameras":
        session_dir = tmp_path / "two"
        render_session(
            session_dir,
            shape="random",
            frames=FRAMES,
            seed=29,
            radius_mm=6.0,
            options=SceneOptions(cameras=2),
            progress=False,
            jobs=1,
        )
    else:
        session_dir = sessions[0.0]
    session = load_session(session_dir)
    frames = decode_frames(session.video_paths, sample_frames(0, FRAMES, 12))
    for off_mm in (0.0, 15.0):
        base = np.add(session.settings.manipulator.base_mm, [off_mm, 0.0, 0.0])
        settings = replace(
            session.settings,
            manipulator=replace(session.settings.manipulator, base_mm=tuple(base)),
            calibration=replace(session.settings.calibration, refine=kept_by == "two cameras"),
        )
        model = build_model(replace(session, settings=settings))
        cameras, report, _, _ = refined_cameras(model, frames)
        assert cameras is model.cameras and report is not None and not report.applied
        assert report.describe().startswith("given (") and report.warnings() == []
        if off_mm:
            (line,) = report.problems()
            assert "the tube's base is seen 1" in line and "check base_mm" in line
        else:
            assert report.problems() == []


def test_a_tube_that_stands_still_is_not_refined_on(sampled: Sampled) -> None:
    """Frames of one pose repeat one view of the tube: "auto" keeps the given cameras (moved
    to the mount where, 0.15 deg off, they see the tube's base away from it)."""
    model, tubes, refit = sampled[0.15]
    assert distinct_poses(tubes) >= 2
    cameras, report = refine(model, [tubes[0]] * 6, "auto", refit)
    assert not report.applied and report.changes == ()
    assert "1 distinct pose in the 6 frames" in report.describe()
    kept = (
        model.cameras
        if report.mount_shift_mm is None
        else moved_to_mount(model.cameras, np.asarray(report.mount_shift_mm))
    )
    for got, want in zip(cameras, kept, strict=True):
        np.testing.assert_allclose(got.matrix, want.matrix)
        np.testing.assert_allclose(got.center_mm, want.center_mm)


def test_the_world_frame_is_the_given_rigs() -> None:
    """A rig turned, scaled and moved with its scene is brought back to the given one."""
    given = rig_cameras()
    rng = np.random.default_rng(4)
    points = np.array([128.0, 128.0, 128.0]) + rng.uniform(-60, 60, (200, 3))
    rotation = cv2.Rodrigues(np.array([0.004, -0.003, 0.005]))[0]
    moved = [similar_camera(cam, rotation, 1.004, np.array([0.8, -0.5, 0.6])) for cam in given]
    assert np.max(_image_error_px(moved, given, points)) > 0.5
    back = nearest_to_given(moved, given).cameras(moved)
    assert np.max(_image_error_px(back, given, points)) < 1e-3


def test_the_given_cameras_errors_average_out_in_the_world_frame() -> None:
    """Cameras each off by their own error place the true rig, moved as a whole, nearer
    the truth than the rig as seen through their images would be."""
    truth = rig_cameras()
    rng = np.random.default_rng(11)
    points = np.array([128.0, 128.0, 128.0]) + rng.uniform(-60, 60, (200, 3))
    by_poses, by_images = [], []
    for _ in range(12):
        given = [
            moved_camera(cam, rng.normal(0.0, [np.deg2rad(0.1)] * 3 + [0.7] * 3 + [0.002] + [0.7] * 2))
            for cam in truth
        ]
        # The true rig as an adjustment finds it: in a frame of its own.
        turn = cv2.Rodrigues(rng.normal(0.0, 0.003, 3))[0]
        adjusted = [similar_camera(cam, turn, 1.003, rng.normal(0.0, 1.0, 3)) for cam in truth]
        by_poses.append(
            np.mean(_image_error_px(nearest_to_given(adjusted, given).cameras(adjusted), truth, points))
        )
        by_images.append(np.mean(_image_error_px(aligned_by_images(adjusted, given, points), truth, points)))
    assert np.mean(by_poses) < 0.85 * np.mean(by_images)


def test_the_base_end_is_seen_where_the_rig_puts_it(sampled: Sampled) -> None:
    """With the true cameras the tubes' base ends are at the mount (0.30 mm off here); a
    rig moved by a known shift sees them moved by it, up to a calibration's error (farther
    where the cameras were refined); a mount set far from where the tube is, is not
    followed."""
    model, tubes, _ = sampled[0.0]
    base = np.asarray(model.settings.manipulator.base_mm, dtype=np.float64)
    shift, note = mount_shift(model.cameras, tubes, base)
    assert shift is not None and not note
    assert np.linalg.norm(shift) < 0.5
    moved_by = np.array([1.5, -1.0, 2.0])
    moved = moved_to_mount(model.cameras, moved_by)
    moved_tubes = [replace(t, points_mm=t.points_mm - moved_by) for t in tubes]
    seen, _ = mount_shift(moved, moved_tubes, base)
    assert seen is not None
    np.testing.assert_allclose(seen, shift - moved_by, atol=0.3)
    # A rig 8 mm off, as three cameras 0.3 deg off put it, is still a calibration's error
    # where the silhouettes showed the cameras off (refined); cameras they agree with are
    # not taken to be that far off: base_mm is.
    off_by = np.array([5.0, -4.0, 5.0])
    seen, _ = mount_shift(model.cameras, tubes, base - off_by, refined=True)
    assert seen is not None
    np.testing.assert_allclose(seen, shift + off_by, atol=0.3)
    kept, why = mount_shift(model.cameras, tubes, base - off_by)
    assert kept is None and "check base_mm" in why
    far, why = mount_shift(model.cameras, tubes, base + np.array([0.0, 20.0, 0.0]))
    assert far is None and "check base_mm" in why
    report = Refinement(True, 12, 0.3, 0.1, (), mount_note=why)
    assert any("check base_mm" in line for line in report.problems())


def test_the_base_of_a_tube_with_spacer_disks_is_seen_at_the_mount(tmp_path: Path) -> None:
    # Disks seen at an angle widen the radius profile near the base: read from it, this
    # case's base end came out 2.9 mm along the tube from the mount (0.5 read as a tip's
    # radius is), and exact cameras were moved there (beyond 1 mm, refine's bar).
    case = next(c for c in draw_cases(5, 14) if c.profile == "disks" and c.cameras == 3)
    session_dir = render_case(replace(case, disk_spacing_mm=20.0), tmp_path, 20, jobs=1)
    session = load_session(session_dir)
    model = build_model(session)
    tubes = sample_tubes(model, decode_frames(session.video_paths, sample_frames(0, 20, 8)))
    shift, note = mount_shift(model.cameras, tubes, np.asarray(model.settings.manipulator.base_mm))
    assert shift is not None and not note
    assert np.linalg.norm(shift) < 1.0


def test_zero_parameters_leave_a_camera_as_it_is() -> None:
    cam = rig_cameras()[1]
    points = np.array([[128.0, 128.0, 100.0], [90.0, 150.0, 40.0]])
    np.testing.assert_allclose(moved_camera(cam, np.zeros(9)).project(points), cam.project(points), atol=1e-9)
    turned = moved_camera(cam, np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0, -1.0]))
    np.testing.assert_allclose(turned.project(points) - cam.project(points), [[2.0, -1.0]] * 2, atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_parameter_jacobian_is_the_projections_derivative(seed: int) -> None:
    rng = np.random.default_rng(seed)
    cam = rig_cameras(["oblique", "ninety"][seed % 2])[seed % 3]
    cam = replace(cam, distortions=rng.normal(0.0, [0.1, 0.05, 0.002, 0.002, 0.01]))
    points = rng.uniform([40.0, 40.0, 0.0], [220.0, 220.0, 200.0], (40, 3))
    # Turns of 1e-4 rad: the ninety rig's cam1 is turned ~180 deg, where Rodrigues vectors
    # (moved_camera's) lose a smaller turn's digits.
    steps = np.array([1e-4] * 3 + [1e-3] * 3 + [1e-6] + [1e-3] * 2)
    differences = np.stack(
        [
            (moved_camera(cam, step).project(points) - moved_camera(cam, -step).project(points)) / (2 * size)
            for step, size in zip(np.diag(steps), steps, strict=True)
        ],
        axis=-1,
    )
    jacobian = parameter_jacobian(cam, points)
    assert jacobian.shape == (len(points), 2, N_PARAMS)
    np.testing.assert_allclose(jacobian, differences, rtol=1e-5, atol=1e-4 * np.abs(differences).max())


@pytest.mark.parametrize("value", ["sometimes", 1, 0.5])
def test_refine_setting_takes_auto_true_or_false(value: object) -> None:
    with pytest.raises(SettingsError, match=r"\[calibration\] refine"):
        settings_from_dict({"calibration": {"refine": value}})
    for ok in ("auto", True, False):
        assert settings_from_dict({"calibration": {"refine": ok}}).calibration.refine == ok


def test_process_writes_the_refined_calibration_beside_the_outputs(
    sessions: dict[float, Path], tmp_path: Path
) -> None:
    from pipeline import process_session
    from pipeline.session.calibration_io import read_calibration

    session = load_session(sessions[0.15])
    summary = process_session(session, out_dir=tmp_path, jobs=1, progress=False, frames=(0, 12))
    written = tmp_path / f"{session.name}.calibration.toml"
    assert written in [path for path, _ in summary.outputs]
    assert summary.cameras.startswith("refined")
    refined = read_calibration(written)
    assert [c.name for c in refined] == [c.name for c in session.cameras]
    # The cameras written are those the frames were reconstructed with, not the user's.
    given = session.cameras
    assert any(
        not np.allclose(r.translation_mm, g.translation_mm) for r, g in zip(refined, given, strict=True)
    )


def test_a_run_whose_mount_is_set_elsewhere_says_so_and_exits_1(
    sessions: dict[float, Path], tmp_path: Path
) -> None:
    from pipeline import process_session

    session = load_session(sessions[0.0])
    base = np.asarray(session.settings.manipulator.base_mm) + np.array([0.0, 15.0, 0.0])
    manipulator = replace(session.settings.manipulator, base_mm=tuple(base))
    moved = replace(session, settings=replace(session.settings, manipulator=manipulator))
    summary = process_session(moved, out_dir=tmp_path, jobs=1, progress=False, frames=(0, 12))
    assert summary.exit_code == 1 and summary.frames_ok == 12
    (line,) = [line for line in summary.problem_lines() if "check base_mm" in line]
    assert "the tube's base is seen 1" in line


def test_two_cameras_are_kept_and_the_summary_says_why(tmp_path: Path) -> None:
    from pipeline.calibrate.refine import refined_cameras

    render_session(
        tmp_path / "two",
        shape="random",
        frames=4,
        seed=5,
        options=SceneOptions(cameras=2, calib_error_deg=0.15),
        progress=False,
        jobs=1,
    )
    session = load_session(tmp_path / "two")
    model = build_model(session)
    cameras, report, _, _ = refined_cameras(model, sample_session(session.video_paths, 0, 4))
    assert cameras is model.cameras
    assert report is not None and not report.applied
    assert "three or more" in report.describe()


def test_two_cameras_are_kept_where_they_see_the_base_millimetres_off(tmp_path: Path) -> None:
    """Two views read the base end less surely than three: a two-camera rig is neither
    refined nor moved to the mount, and a base_mm a few mm off is left to the frames' fit
    (15 mm off is named, test_a_mount_set_far_from_the_base_is_named_where_nothing_is_refined)."""
    from pipeline.calibrate.refine import refined_cameras

    render_session(
        tmp_path / "two",
        shape="bend_rotate",
        frames=8,
        seed=4,
        options=SceneOptions(cameras=2),
        progress=False,
        jobs=1,
    )
    session = load_session(tmp_path / "two")
    model = build_model(session)
    base = np.asarray(model.settings.manipulator.base_mm, dtype=np.float64)
    manipulator = replace(model.settings.manipulator, base_mm=tuple(base + np.array([2.5, 0.0, 0.0])))
    off = replace(model, settings=replace(model.settings, manipulator=manipulator))
    cameras, report, _, _ = refined_cameras(off, sample_session(session.video_paths, 0, 8))
    assert cameras is model.cameras and report is not None and not report.changed
    assert "three or more" in report.describe() and "to the mount" not in report.describe()
    assert report.warnings() == [] and report.problems() == []


def test_the_tube_end_is_read_on_the_frames_of_cameras_kept(sessions: dict[float, Path]) -> None:
    from pipeline.calibrate.refine import SAMPLE_FRAMES, refined_cameras, sample_evidence
    from pipeline.reconstruct.tip_shape import with_session_tip

    session = load_session(sessions[0.0])
    model = build_model(session)
    assert model.settings.manipulator.tip == "auto"
    samples = sample_session(session.video_paths, 0, FRAMES)
    cameras, report, read, radii = refined_cameras(model, samples)
    assert cameras is model.cameras and report is not None and not report.applied
    assert read is not None and list(read.frames) == sample_frames(0, FRAMES, SAMPLE_FRAMES)
    assert 3 <= len(read.tips) <= len(read.frames)
    # Read alone (a live replay keeps its cameras as given), the same frames, ends and radii.
    alone, alone_radii = sample_evidence(model, samples)
    assert alone is not None and alone.frames == read.frames
    for a, b in zip(alone.tips, read.tips, strict=True):
        np.testing.assert_array_equal(a.axis_mm, b.axis_mm)
    assert radii is not None and alone_radii is not None
    np.testing.assert_array_equal(alone_radii.radius_mm, radii.radius_mm)
    # The radius along the tube, read on those frames: the uniform tube's 6 mm.
    assert np.all(np.abs(radii.radius_mm - 6.0) < 0.3), radii.radius_mm
    unrefined = replace(model.settings, calibration=replace(model.settings.calibration, refine=False))
    assert sample_evidence(replace(model, settings=unrefined), samples) == (None, None)
    settled, choice = with_session_tip(model, session.video_paths, 0, FRAMES, read=read)
    # The synthetic tube's end is flat, and the frames read settle it: none is read again.
    assert choice is not None and settled.tip == choice.tip == "flat"
    assert choice.clear and choice.frames <= len(read.tips), choice.describe()
    # Cameras refined see the frames otherwise: the end is left to be read with them.
    moved = load_session(sessions[0.15])
    off = build_model(moved)
    calibration = replace(off.settings.calibration, refine=True)
    forced = replace(off, settings=replace(off.settings, calibration=calibration))
    cameras, report, read, _ = refined_cameras(forced, sample_session(moved.video_paths, 0, FRAMES))
    assert report is not None and report.applied and cameras is not forced.cameras
    assert read is None


def test_the_sample_frames_on_two_workers_give_the_same_tubes(sessions: dict[float, Path]) -> None:
    from pipeline.run.workers import local_frame_map, release_local_workers

    session = load_session(sessions[0.15])
    model = build_model(session)
    frames = decode_frames(session.video_paths, sample_frames(0, FRAMES, 5))
    here = sample_tubes(model, frames)
    try:
        there = sample_tubes(model, frames, local_frame_map(2))
    finally:
        release_local_workers()
    # Every frame's tube, in the frames' order, bit for bit.
    assert len(there) == len(here) == 5
    for a, b in zip(here, there, strict=True):
        np.testing.assert_array_equal(a.points_mm, b.points_mm)
        np.testing.assert_array_equal(a.radii_mm, b.radii_mm)


def test_too_few_sample_frames_with_a_tube_keep_the_cameras_and_say_why(sessions: dict[float, Path]) -> None:
    """Where the sample frames hold too few tubes to refine on (the tube out of view, or
    cameras too far off for their cones to meet), the cameras are kept, and the summary's
    line says why."""
    session = load_session(sessions[0.15])
    model = build_model(session)
    frames = decode_frames(session.video_paths, sample_frames(0, FRAMES, 12))
    # All but two frames show nothing: a uniform grey at each camera's median level leaves
    # no silhouette.
    blank = [np.full_like(image, int(np.median(image))) for image in frames[0][1]]
    frames = [frames[0], frames[1]] + [(index, blank) for index, _ in frames[2:]]
    cameras, report, _, _ = refined_cameras(model, frames)
    assert cameras is model.cameras and report is not None and not report.applied
    assert report.describe() == (
        "given (only 2 of the 12 sample frames were reconstructed with them, too few to refine on)"
    )
