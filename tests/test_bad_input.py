"""Bad input through the CLI: exit status 2, one line naming the culprit, nothing written.

Each test copies one small valid session and breaks exactly one thing in it.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import tomli_w
from conftest import build_session, grey16_video, rig_cameras, rod_image, write_video

from pipeline.cli import EXIT_BAD_INPUT, main
from pipeline.session.folder import load_session
from pipeline.session.video import read_frames


@pytest.fixture(scope="module")
def good_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_session(tmp_path_factory.mktemp("good") / "session", frames=3)


@pytest.fixture
def session(good_session: Path, tmp_path: Path) -> Path:
    """A fresh copy of the valid session, to break."""
    return Path(shutil.copytree(good_session, tmp_path / "session"))


def _process(video_dir: Path, out: Path, *extra: str) -> list[str]:
    return ["process", str(video_dir), "--out", str(out), "--jobs", "1", "--no-images", *extra]


def assert_rejected(video_dir: Path, capsys: pytest.CaptureFixture[str], *needles: str) -> str:
    """Run `process` on ``video_dir``; check exit 2, one error line holding ``needles``, no output."""
    out = video_dir.parent / "out"
    code = main(_process(video_dir, out))
    err = capsys.readouterr().err
    assert code == EXIT_BAD_INPUT, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for needle in needles:
        assert needle in lines[0], f"{needle!r} not in {lines[0]!r}"
    assert not out.exists() or not any(out.iterdir())
    return lines[0]


def _edit_toml(path: Path, edit: Callable[[dict[str, Any]], None]) -> None:
    data = tomllib.loads(path.read_text())
    edit(data)
    path.write_text(tomli_w.dumps(data))


# --- the session directory ---------------------------------------------------------


def test_missing_video_dir(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert_rejected(tmp_path / "nowhere", capsys, "nowhere", "no such session directory")


def test_a_missing_relative_session_says_where_it_was_looked_for(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # `make -C repo process VIDEO_DIR=s1`: a relative path is taken from the folder make runs in.
    monkeypatch.chdir(tmp_path)
    assert_rejected(Path("s1"), capsys, f"s1: no such session directory (looked for it in {tmp_path})")


def test_a_tilde_the_shell_did_not_expand_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # zsh leaves `make process VIDEO_DIR=~/s1` as it is, and so does a quoted "~/s1".
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    (tmp_path / "s1").mkdir()
    assert_rejected(
        Path("~/s1"), capsys, f"~/s1: no such session directory (~ is not expanded here: give {tmp_path}/s1)"
    )


def test_empty_video_dir(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "empty").mkdir()
    assert_rejected(tmp_path / "empty", capsys, "empty", "is empty")


def test_video_given_instead_of_its_directory(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert_rejected(session / "cam0.avi", capsys, "cam0.avi", "is a file", "session directory")


def test_no_calibration(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (session / "calibration.toml").unlink()
    assert_rejected(session, capsys, "calibration.toml", "not found")


# --- calibration.toml ------------------------------------------------------------


def test_calibration_toml_syntax_error_shows_the_line(
    session: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = session / "calibration.toml"
    lines = path.read_text().splitlines()
    lines[2] = "size = 320 x 240"  # not TOML, on line 3
    path.write_text("\n".join(lines))
    assert_rejected(session, capsys, "calibration.toml", "TOML syntax error", "line 3")


def _drop_matrix(d: dict[str, Any]) -> None:
    del d["cam_1"]["matrix"]


def _short_translation(d: dict[str, Any]) -> None:
    d["cam_1"]["translation"] = [1.0, 2.0]


def _matrix_2x3(d: dict[str, Any]) -> None:
    d["cam_1"]["matrix"] = d["cam_1"]["matrix"][:2]


def _nan_translation(d: dict[str, Any]) -> None:
    d["cam_1"]["translation"][0] = float("nan")


def _inf_distortion(d: dict[str, Any]) -> None:
    d["cam_1"]["distortions"][0] = float("inf")


def _zero_focal(d: dict[str, Any]) -> None:
    d["cam_1"]["matrix"][0][0] = 0.0  # singular K


def _negative_focal(d: dict[str, Any]) -> None:
    d["cam_1"]["matrix"][1][1] = -300.0


def _sheared_rotation(d: dict[str, Any]) -> None:
    d["cam_1"]["rotation"] = [[1.0, 0.2, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]


def _reflection(d: dict[str, Any]) -> None:
    d["cam_1"]["rotation"] = [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]


def _skewed_matrix(d: dict[str, Any]) -> None:
    d["cam_1"]["matrix"][0][1] = 5.0


def _fisheye(d: dict[str, Any]) -> None:
    d["cam_1"]["fisheye"] = True  # as anipose writes a fisheye calibration


def _folding_distortion(d: dict[str, Any]) -> None:
    d["cam_1"]["distortions"][0] = -50.0  # the radius stops growing a tenth of the way to the corners


def _text_size(d: dict[str, Any]) -> None:
    d["cam_1"]["size"] = ["320", "240"]


def _duplicate_name(d: dict[str, Any]) -> None:
    d["cam_1"]["name"] = "cam0"


def _copied_table(d: dict[str, Any]) -> None:
    d["cam_1"] = {**d["cam_0"], "name": "cam1"}  # cam0's table pasted, only renamed


@pytest.mark.parametrize(
    ("edit", "needles"),
    [
        (_drop_matrix, ("[cam_1]", "missing", "matrix")),
        (_short_translation, ("cam1", "translation", "shape")),
        (_matrix_2x3, ("cam1", "matrix", "shape")),
        (_nan_translation, ("cam1", "translation", "non-finite")),
        (_inf_distortion, ("cam1", "distortions", "non-finite")),
        (_zero_focal, ("cam1", "matrix", "fx, fy > 0")),
        (_negative_focal, ("cam1", "matrix", "fx, fy > 0")),
        (_sheared_rotation, ("cam1", "rotation", "not a rotation")),
        (_reflection, ("cam1", "rotation", "not a rotation")),
        (_skewed_matrix, ("cam1", "skew", "calibrate with zero skew")),
        (_fisheye, ("cam1", "fisheye", "standard lens model")),
        (
            _folding_distortion,
            (
                "camera 'cam1'",
                "distortion (k1 -50, k2 0.03, ",
                "folds the image before its corners",
                "(k1, k2, p1, p2, k3)",
            ),
        ),
        (_text_size, ("cam1", "size")),
        (_duplicate_name, ("'cam0'", "more than once")),
        (_copied_table, ("cameras 'cam0' and 'cam1' stand at the same place", "copied")),
    ],
    ids=lambda v: v.__name__.strip("_") if callable(v) else "",
)
def test_bad_camera_table(
    session: Path,
    capsys: pytest.CaptureFixture[str],
    edit: Callable[[dict[str, Any]], None],
    needles: tuple[str, ...],
) -> None:
    _edit_toml(session / "calibration.toml", edit)
    assert_rejected(session, capsys, "calibration.toml", *needles)


# --- videos against the calibration ------------------------------------------------


def test_one_cameras_video_copied_under_anothers_name(
    session: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    shutil.copy(session / "cam0.avi", session / "cam2.avi")
    assert_rejected(session, capsys, "cam2.avi", "is the same file as cam0.avi")


def test_video_without_calibration_entry(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    shutil.copy(session / "cam0.avi", session / "cam7.avi")
    assert_rejected(session, capsys, "cam7.avi", "no camera named 'cam7'")


def test_camera_without_video(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (session / "cam2.avi").unlink()
    assert_rejected(session, capsys, "camera 'cam2'", "has no video")


def test_a_camera_whose_video_is_of_a_kind_not_read_is_named_with_it(
    session: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (session / "cam2.avi").rename(session / "cam2.wmv")
    line = assert_rejected(session, capsys, "cam2.wmv: is not read as the video of camera 'cam2'")
    assert ".mp4, .avi, .mkv, .mov, .m4v, .webm, .ts, .mts, .m2ts" in line


def test_video_names_spelt_decomposed_match_the_calibrations_composed_ones(session: Path) -> None:
    # macOS copies keep an accented file name decomposed (NFD); the calibration spells it
    # composed (NFC), as typed.
    import unicodedata

    composed = unicodedata.normalize("NFC", "cámara")
    _edit_toml(session / "calibration.toml", lambda doc: doc["cam_0"].update(name=composed))
    (session / "cam0.avi").rename(session / (unicodedata.normalize("NFD", composed) + ".avi"))
    cameras = load_session(session).cameras
    assert cameras[0].name == composed


def test_a_webm_video_is_read(session: Path) -> None:
    (session / "cam2.avi").rename(session / "cam2.webm")
    assert load_session(session).video_paths[2].name == "cam2.webm"


def test_two_videos_for_one_camera(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_video(session / "cam1.mp4", [rod_image(rig_cameras()[1])] * 3)
    assert_rejected(session, capsys, "two videos for camera 'cam1'", "cam1.avi", "cam1.mp4")


def test_video_size_differs_from_calibration(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_video(session / "cam1.avi", [np.full((120, 160), 150, np.uint8)] * 3)
    assert_rejected(session, capsys, "cam1.avi", "160x120", "320x240", "'cam1'")


def test_fps_differs_between_videos(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    session = build_session(tmp_path / "s", frames=2, fps={"cam0": 30.0, "cam1": 25.0, "cam2": 30.0})
    assert_rejected(session, capsys, "cam1.avi", "25 fps", "30 fps")


def test_random_bytes_video(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (session / "cam0.avi").unlink()
    (session / "cam0.mp4").write_bytes(np.random.default_rng(0).bytes(20_000))
    assert_rejected(session, capsys, "cam0.mp4", "cannot be opened as a video")


@pytest.mark.parametrize("kind", ["png", "jpg", "gif"])
def test_a_still_image_as_a_video(session: Path, capsys: pytest.CaptureFixture[str], kind: str) -> None:
    # FFmpeg opens it as a one-frame video (at 25 fps, a GIF at 100): it is named for what
    # it is, and not taken for a camera recorded at another rate.
    if kind == "gif":  # OpenCV writes no GIF: the smallest one, a pixel
        encoded = bytes.fromhex(
            "4749463839610100010080000000000000ffffff21f90401000000002c00000000010001000002024401003b"
        )
    else:
        ok, array = cv2.imencode(f".{kind}", rod_image(rig_cameras()[1]))
        assert ok
        encoded = array.tobytes()
    (session / "cam0.avi").write_bytes(encoded)
    line = assert_rejected(session, capsys, "cam0.avi", "is a still", "image, not a video")
    assert "fps" not in line


@pytest.mark.parametrize("bits", [10, 12])
def test_a_16_bit_video_of_unscaled_camera_values_is_read_at_their_depth(
    session: Path, caplog: pytest.LogCaptureFixture, bits: int
) -> None:
    # A camera's 10- or 12-bit values stored in 16-bit samples as they are: read as 16-bit,
    # every frame would be black (and all tube); read at their depth, it is the scene.
    image = rod_image(rig_cameras()[0])
    (session / "cam0.avi").unlink()
    grey16_video(session / "cam0.mkv", [image.astype(np.uint16) << (bits - 8)] * 3)
    with caplog.at_level("WARNING"):
        assert len(load_session(session).cameras) == 3
    assert f"cam0.mkv: a 16-bit grey video whose first frame holds {bits}-bit values" in caplog.text
    ((_, read),) = read_frames(session / "cam0.mkv", 1, 2)
    assert read is not None and np.abs(read.astype(int) - image).max() <= 1


def test_zero_byte_video(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (session / "cam2.avi").write_bytes(b"")
    assert_rejected(session, capsys, "cam2.avi", "cannot be opened as a video")


def test_mp4_copied_half_way(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # mp4v writes its index (moov atom) last: the first half alone cannot be opened.
    (session / "cam1.avi").unlink()
    mp4 = write_video(session / "cam1.mp4", [rod_image(rig_cameras()[1])] * 3)
    data = mp4.read_bytes()
    mp4.write_bytes(data[: len(data) // 2])
    assert_rejected(session, capsys, "cam1.mp4", "cannot be opened as a video")


def test_video_without_frames(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_video(session / "cam0.avi", [], size=(320, 240))
    assert_rejected(session, capsys, "cam0.avi")


# --- session.toml ------------------------------------------------------------------


def test_session_toml_syntax_error(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (session / "session.toml").write_text("[workspace]\nvoxel_mm = 2.0\nsize_mm = 256 256 256\n")
    assert_rejected(session, capsys, "session.toml", "TOML syntax error", "line 3")


def test_session_toml_unknown_section(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (session / "session.toml").write_text("[workspaec]\nvoxel_mm = 2.0\n")
    assert_rejected(session, capsys, "session.toml", "'workspaec'", "workspace", "silhouette")


def test_session_toml_unknown_key(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (session / "session.toml").write_text("[workspace]\nvoxel = 2.0\n")
    assert_rejected(session, capsys, "session.toml", "'voxel'", "voxel_mm", "size_mm", "origin_mm")


@pytest.mark.parametrize("voxel", [0.0, -1.0])
def test_voxel_size_not_positive(session: Path, capsys: pytest.CaptureFixture[str], voxel: float) -> None:
    (session / "session.toml").write_text(f"[workspace]\nvoxel_mm = {voxel}\n")
    assert_rejected(session, capsys, "session.toml", "voxel_mm must be > 0")


def test_grid_too_large_says_how_much_memory(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (session / "session.toml").write_text("[workspace]\nvoxel_mm = 0.1\n")
    line = assert_rejected(session, capsys, "session.toml", "2560x2560x2560", "GiB", "voxel_mm")
    # 2560^3 voxels x (4 bytes x 3 cameras + 13) bytes = 390.625 GiB, printed to 0.1 GiB.
    assert "390.6 GiB" in line


def test_workspace_not_seen_by_a_camera(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # A box 3 m to the side of the rig, its base with it: every camera looks elsewhere.
    (session / "session.toml").write_text(
        "[workspace]\norigin_mm = [3000.0, 0.0, 0.0]\n[manipulator]\nbase_mm = [3128.0, 128.0, 0.0]\n"
    )
    assert_rejected(session, capsys, "does not see the workspace", "camera 'cam", "session.toml")


def test_a_smallest_blob_larger_than_the_images_is_refused(
    session: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (session / "session.toml").write_text("[silhouette]\nmin_area_px = 1000000000\n")
    assert_rejected(session, capsys, "session.toml", "min_area_px 1000000000", "320x240 = 76800 px")


def test_a_camera_that_sees_nothing_in_any_frame_is_named(
    session: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # cam1's video shows the scene without the rod (a camera pointed away, or a threshold on
    # the wrong side of its scene): no frame has a tube, and that camera is why.
    video = next(session.glob("cam1.*"))
    write_video(video, [np.full((240, 320), 200, np.uint8)] * 3)
    assert main(_process(session, session.parent / "out")) == 1
    err = capsys.readouterr().err
    assert (
        "no tube in any frame: a camera sees no silhouette (camera 'cam1' in 3 of the 3 empty frames)" in err
    )
    assert "check its picture" in err


def test_a_workspace_that_misses_the_tube_is_named(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Every camera sees the box and the rod, but the rod (x = 128 mm) stands beside the box.
    (session / "session.toml").write_text(
        "[workspace]\norigin_mm = [0.0, 0.0, 0.0]\nsize_mm = [100.0, 256.0, 256.0]\n"
        '[manipulator]\nbase_mm = "auto"\n'
    )
    assert main(_process(session, session.parent / "out")) == 1
    err = capsys.readouterr().err
    assert "no tube in any frame" in err and "meet nowhere in the workspace box" in err, err
    assert "origin_mm and size_mm" in err and "polarity" not in err


def test_frames_outside_the_session(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = session.parent / "out"
    assert main([*_process(session, out), "--frames", "10:20"]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "--frames 10:20 selects no frame" in err and "3 frames" in err
    assert not out.exists() or not any(out.iterdir())


# --- the CLI itself ----------------------------------------------------------------


def test_a_device_in_place_of_the_session_directory_is_named(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(_process(Path("/dev/null"), Path("/nonexistent/out"))) == EXIT_BAD_INPUT
    assert "/dev/null: is not a directory (a device or pipe)" in capsys.readouterr().err


def test_debug_shows_the_exception_and_keeps_the_exit_status(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["--debug", *_process(tmp_path / "nowhere", tmp_path / "out")]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "Traceback" in err and err.rstrip().endswith("no such session directory")


def test_subprocess_bad_input_is_one_line_without_traceback(session: Path) -> None:
    (session / "cam1.avi").unlink()
    mp4 = write_video(session / "cam1.mp4", [rod_image(rig_cameras()[1])] * 3)
    mp4.write_bytes(mp4.read_bytes()[:1000])  # copied half-way: OpenCV and FFmpeg complain natively
    out = session.parent / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "pipeline", *_process(session, out)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == EXIT_BAD_INPUT
    assert "Traceback" not in proc.stderr
    # Only our line: native OpenCV/FFmpeg warnings would bury it.
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()], proc.stderr
    assert proc.stderr.startswith("error: ") and "cam1.mp4" in proc.stderr
    assert not out.exists()


@pytest.mark.parametrize("stdout", ["full", "closed", "json-to-dev-stdout"])
def test_a_stdout_that_takes_nothing_costs_the_summary_not_the_run(session: Path, stdout: str) -> None:
    # `> /dev/full` (no room), `>&-` (closed by the caller) and `--json /dev/stdout` into a pipe
    # (read and waited on for good, once): the run's outputs and exit status stand.
    out = session.parent / "out"
    command = [sys.executable, "-m", "pipeline", *_process(session, out)]
    options: dict[str, Any] = {"stderr": subprocess.PIPE, "text": True, "timeout": 120, "check": False}
    if stdout == "full":
        with open("/dev/full", "w") as full:
            proc = subprocess.run(command, stdout=full, **options)
    elif stdout == "closed":
        proc = subprocess.run(command, preexec_fn=lambda: os.close(1), **options)
    else:
        proc = subprocess.run([*command, "--json", "/dev/stdout"], stdout=subprocess.PIPE, **options)
        assert json.loads(proc.stdout)["exit_code"] == 0
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr and "internal error" not in proc.stderr
    assert (out / "session.mcap").is_file() and (out / "session.rrd").is_file()


def test_a_json_summary_that_a_full_stdout_cannot_take_is_an_error(session: Path) -> None:
    # `--json > summary.json` on a full disk: the script that asked for it would read nothing.
    out = session.parent / "out"
    command = [sys.executable, "-m", "pipeline", *_process(session, out), "--json"]
    with open("/dev/full", "w") as full:
        proc = subprocess.run(
            command, stdout=full, stderr=subprocess.PIPE, text=True, timeout=120, check=False
        )
    assert proc.returncode == EXIT_BAD_INPUT, proc.stderr
    (line,) = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert line.startswith("error: stdout: cannot take the JSON summary (No space left on device)"), line
    assert "Traceback" not in proc.stderr
    assert (out / "session.mcap").is_file() and (out / "session.rrd").is_file()


def test_a_json_summary_to_a_stdout_the_caller_closed_is_refused_before_the_run(session: Path) -> None:
    # `--json >&-`: the summary a script asked for would go to the null device, exit 0.
    out = session.parent / "out"
    command = [sys.executable, "-m", "pipeline", *_process(session, out), "--json"]
    proc = subprocess.run(
        command,
        preexec_fn=lambda: os.close(1),
        stderr=subprocess.PIPE,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == EXIT_BAD_INPUT, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        "error: stdout: closed (>&-), so it cannot take the JSON summary; leave it open, or send it to a file"
    ]
    assert not out.exists()


def test_a_current_directory_that_no_longer_exists_is_named(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def gone() -> str:
        raise FileNotFoundError(2, "No such file or directory")

    monkeypatch.setattr(os, "getcwd", gone)
    assert main(["process", "/nowhere"]) == EXIT_BAD_INPUT
    assert (
        capsys.readouterr().err == "error: the current directory no longer exists; cd to a folder that does\n"
    )


# --- settings a real rig cannot have ----------------------------------------------------


@pytest.mark.parametrize(
    ("toml", "needles"),
    [
        ("[manipulator]\nradius_mm = 0.005\n", ("radius_mm", "0.1-100 (millimetres)", "got 0.005")),
        ("[silhouette]\nthreshold = 255\n", ("threshold", "1-254", "got 255")),
        ("[session]\nstart_time = 1969-07-20T20:17:00Z\n", ("start_time", "1969-07-20", "1970-01-01..2262")),
        ("[session]\nstart_time = 2300-01-01T00:00:00Z\n", ("start_time", "2300-01-01", "1970-01-01..2262")),
        # start_time itself fits, the last of the session's 3 frames (66 ms later) does not.
        (
            "[session]\nstart_time = 2262-04-11T23:47:16.8Z\n",
            ("start_time", "last frame", "earlier start_time"),
        ),
    ],
    ids=["radius-in-metres", "threshold-255", "start-1969", "start-2300", "last-frame-past-2262"],
)
def test_setting_out_of_a_real_rigs_range(
    session: Path, capsys: pytest.CaptureFixture[str], toml: str, needles: tuple[str, ...]
) -> None:
    (session / "session.toml").write_text(toml)
    assert_rejected(session, capsys, "session.toml", *needles)


@pytest.mark.parametrize("name", ["session.toml", "calibration.toml"])
def test_a_utf8_byte_order_mark_is_accepted(session: Path, name: str) -> None:
    (session / "session.toml").write_text("[workspace]\nvoxel_mm = 4.0\n")
    path = session / name
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())  # as Notepad saves UTF-8
    loaded = load_session(session)
    assert loaded.settings.workspace.voxel_mm == 4.0 and len(loaded.cameras) == 3


# --- paths ----------------------------------------------------------------------------


def test_a_dangling_symlink_video_is_named_as_such(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (session / "cam2.avi").unlink()
    (session / "cam2.avi").symlink_to(session.parent / "moved" / "cam2.avi")
    assert_rejected(session, capsys, "cam2.avi", "symbolic link to", "moved/cam2.avi", "does not exist")


@pytest.mark.parametrize("inside", [False, True], ids=["out", "a-folder-in-out"])
def test_an_out_folder_behind_a_dangling_symlink_is_named_as_such(
    session: Path, capsys: pytest.CaptureFixture[str], tmp_path: Path, inside: bool
) -> None:
    # A link to a drive that is not mounted: "cannot create the output directory (File
    # exists)" said nothing of the link.
    link = tmp_path / "drive"
    link.symlink_to(tmp_path / "not-mounted")
    out = link / "take1" if inside else link
    assert main(_process(session, out)) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    target = tmp_path / "not-mounted"
    assert err == (
        f"error: {link}: is a symbolic link to {target}, which does not exist; fix the link (mount the "
        "drive), or give --out another folder\n"
    )
    assert not (tmp_path / "not-mounted").exists()


def test_a_dangling_symlink_session_is_named_as_such(
    session: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    link = session.parent / "link"
    link.symlink_to(session.parent / "unmounted")
    assert_rejected(link, capsys, "link", "symbolic link to", "unmounted", "does not exist")


NOT_UTF8 = os.fsdecode(b"caf\xe9")  # Latin-1 bytes, as an old archive leaves them


def test_a_session_path_that_is_not_utf8_is_refused(
    session: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    odd = session.rename(session.parent / NOT_UTF8)
    line = assert_rejected(odd, capsys, "caf\ufffd", "not UTF-8", "rename the folder")
    assert "\udce9" not in line


def test_an_out_path_that_is_not_utf8_is_refused(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = session.parent / NOT_UTF8
    assert main(_process(session, out)) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "--out path in UTF-8" in err and len(err.splitlines()) == 1
    assert not out.exists()


# --- background images ------------------------------------------------------------------


@pytest.mark.parametrize(
    "scale", [1, 4095 / 255, 257], ids=["8-bit-values", "12-bit-values", "full-16-bit-range"]
)
def test_a_16_bit_background_is_read_at_the_videos_depth(session: Path, scale: float) -> None:
    (session / "session.toml").write_text('[silhouette]\nmethod = "background"\npolarity = "dark"\n')
    (session / "background").mkdir()
    grey = np.full((240, 320), 150, np.uint8)
    grey[100:140, 150:170] = 40
    for cam in ("cam0", "cam1", "cam2"):
        cv2.imwrite(str(session / "background" / f"{cam}.png"), grey)
    cv2.imwrite(
        str(session / "background" / "cam1.png"), np.round(grey.astype(np.float64) * scale).astype(np.uint16)
    )
    backgrounds = load_session(session).backgrounds
    for background in backgrounds:
        assert background is not None and background.dtype == np.uint8
        np.testing.assert_array_equal(background, grey)  # not black


# --- the command line --------------------------------------------------------------------


def test_a_stdout_that_cannot_spell_a_path_still_gets_every_line(session: Path, tmp_path: Path) -> None:
    # An ASCII locale and an output folder named in another script: the "wrote" lines come
    # out with escapes, not lost after the first one that cannot be encoded.
    out = tmp_path / "sortie über"
    run = subprocess.run(
        [sys.executable, "-m", "pipeline", *_process(session, out)],
        env={**os.environ, "PYTHONIOENCODING": "ascii"},
        capture_output=True,
        text=True,
        encoding="ascii",
    )
    assert run.returncode == 0, run.stderr
    wrote = [line for line in run.stdout.splitlines() if line.startswith("wrote ")]
    # The recordings, and the cameras moved to the mount (this rig's rod ends 2.7 mm from it).
    assert len(wrote) == 3 and all("sortie \\xfcber" in line for line in wrote)
    assert all(any(kind in line for line in wrote) for kind in (".mcap", ".rrd", ".calibration.toml"))


def test_a_refused_run_tells_a_json_reader_why(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # A script reading --json - gets the reason, not an empty stdout.
    (session / "cam2.avi").unlink()
    out = session.parent / "out"
    assert main([*_process(session, out), "--json", "-"]) == EXIT_BAD_INPUT
    captured = capsys.readouterr()
    (line,) = captured.err.strip().splitlines()
    assert json.loads(captured.out) == {"error": line.removeprefix("error: "), "exit_code": EXIT_BAD_INPUT}
    assert "camera 'cam2'" in line and not out.exists()


def test_an_out_folder_with_a_tilde_no_shell_expanded_is_refused(
    session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # --out=~/results reaches the run with its ~: it would make a folder named "~" here.
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert main([*_process(session, Path("~/results"))]) == EXIT_BAD_INPUT
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("error: ~/results: ~ is not expanded here (it would make a folder named ~)")
    assert line.endswith(f"; give --out {tmp_path}/home/results")
    assert not (tmp_path / "~").exists()
    # So is a render's folder (synth, synth-calib): the same check.
    assert main(["synth", "~/render", "--frames", "2"]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err.strip().endswith(f"; give synth {tmp_path}/home/render")
    assert not (tmp_path / "~").exists()


def test_negative_frames_say_what_is_wrong(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = session.parent / "out"
    with pytest.raises(SystemExit) as exited:  # argparse's own exit, with our one line
        main([*_process(session, out), "--frames", "-5:10"])
    assert exited.value.code == EXIT_BAD_INPUT
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "--frames" in line and "0 <= START < STOP" in line and "'-5:10'" in line


@pytest.mark.parametrize("address", ["notaurl", "http://localhost:8787", "tcp://host:port"])
def test_a_malformed_scheduler_address(
    session: Path, capsys: pytest.CaptureFixture[str], address: str
) -> None:
    out = session.parent / "out"
    assert main([*_process(session, out), "--backend", "dask", "--scheduler", address]) == EXIT_BAD_INPUT
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("error: --scheduler ") and "not a Dask scheduler address" in line
    assert "tcp://HOST:PORT" in line
    assert not out.exists()


def test_a_server_that_is_not_a_scheduler_is_an_error_not_a_hang(
    session: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from pipeline.run import runner

    monkeypatch.setattr(runner, "DASK_CONNECT_TIMEOUT_S", 1)
    # Accepts TCP connections and never says a word, as a stalled or foreign server does.
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        address = f"tcp://127.0.0.1:{server.getsockname()[1]}"
        out = session.parent / "out"
        assert main([*_process(session, out), "--backend", "dask", "--scheduler", address]) == EXIT_BAD_INPUT
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert f"cannot reach the Dask scheduler at {address} (no answer within 1 s)" in line
    assert not out.exists()


# --- inputs that are not files, outputs over inputs -----------------------------------


@pytest.mark.parametrize("name", ["calibration.toml", "session.toml"])
def test_a_named_pipe_for_a_toml_file_is_refused_not_waited_on(
    session: Path, name: str, capsys: pytest.CaptureFixture[str]
) -> None:
    (session / name).unlink(missing_ok=True)
    os.mkfifo(session / name)  # a read would block until something wrote to it
    assert_rejected(session, capsys, name, "not a regular file")


def test_arrays_nested_too_deeply_in_the_calibration(
    session: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with open(session / "calibration.toml", "a") as f:
        f.write("\n[deep]\nvalue = " + "[" * 100_000 + "]" * 100_000 + "\n")
    assert_rejected(session, capsys, "calibration.toml", "nested too deeply")


def test_a_rig_of_one_camera_is_refused(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    def one_camera(d: dict[str, Any]) -> None:
        for key in [k for k in d if k.startswith("cam_") and k != "cam_0"]:
            del d[key]

    _edit_toml(session / "calibration.toml", one_camera)
    for video in session.glob("cam[12].*"):
        video.unlink()
    assert_rejected(session, capsys, "calibration.toml", "1 camera", "two or more")


@pytest.mark.parametrize("target", ["calibration.toml", "cam0.avi"])
def test_the_json_summary_never_takes_the_place_of_an_input(
    session: Path, target: str, capsys: pytest.CaptureFixture[str]
) -> None:
    before = (session / target).read_bytes()
    out = session.parent / "out"
    code = main(_process(session, out, "--json", str(session / target)))
    err = capsys.readouterr().err
    assert code == EXIT_BAD_INPUT and "is not a JSON summary" in err, err
    assert (session / target).read_bytes() == before
    assert not out.exists() or not any(out.iterdir())


def test_the_json_summary_never_takes_the_place_of_the_recording(
    session: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = session.parent / "out"
    out.mkdir()
    code = main(_process(session, out, "--json", str(out / "session.mcap")))
    assert code == EXIT_BAD_INPUT and "is one of the files this run writes" in capsys.readouterr().err
    assert not any(out.iterdir())


def test_a_view_that_is_all_silhouette_fails_its_frames_at_once(
    session: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A black picture in one camera: every pixel passes a dark tube's threshold.
    video = next(session.glob("cam1.*"))
    n_frames = load_session(session).frame_count
    write_video(video, [np.zeros((240, 320), np.uint8)] * n_frames)
    out = session.parent / "out"
    code = main(_process(session, out))
    err = capsys.readouterr().err
    assert code == 1, err
    assert "camera 'cam1' sees 100 % of its image as tube" in err and "polarity and threshold" in err
    # Every such view is named at once, not one per run (a grey level apart: two videos of
    # the same bytes are refused before the run, as one video copied).
    write_video(next(session.glob("cam2.*")), [np.full((240, 320), 5, np.uint8)] * n_frames)
    code = main(_process(session, session.parent / "out2"))
    err = capsys.readouterr().err
    assert code == 1, err
    assert "cameras 'cam1' and 'cam2' see 100 and 100 % of their images as tube; check their pictures" in err


@pytest.mark.parametrize("kind", ["folder", "video", "session.toml"])
def test_calibrate_checks_its_output_before_calibrating(
    tmp_path: Path, kind: str, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "boards").mkdir()  # no images: calibrating would fail, later
    target = tmp_path / "out"
    content = {"video": b"\x00\x00\x00\x18ftypmp42", "session.toml": b"[workspace]\nvoxel_mm = 2.0\n"}
    if kind == "folder":
        target.mkdir()
    else:
        target.write_bytes(content[kind])
    # --force replaces an earlier calibration, never a file of another kind (a TOML file too).
    code = main(["calibrate", str(tmp_path / "boards"), "-o", str(target), "--force"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == EXIT_BAD_INPUT and len(err) == 1, err
    assert ("is a folder" if kind == "folder" else "is not a calibration") in err[0]
    assert str(target) in err[0]
    if kind != "folder":
        assert target.read_bytes() == content[kind]


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs /proc, where no file can be created")
@pytest.mark.parametrize("target", ["/proc/calibration.toml", "/proc/rig/calibration.toml"])
def test_calibrate_to_where_no_file_can_be_created_is_refused_before_any_image_is_read(
    target: str, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    def no_detection(*_args: object) -> None:
        raise AssertionError("the board images were read")

    monkeypatch.setattr("pipeline.calibrate.solve.detect_directory", no_detection)
    monkeypatch.setattr("pipeline.calibrate.solve.load_board", no_detection)
    (tmp_path / "boards").mkdir()
    code = main(["calibrate", str(tmp_path / "boards"), "-o", target])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == EXIT_BAD_INPUT and len(err) == 1, err
    assert err[0].startswith(f"error: {target}: cannot be written in /proc (")
    assert err[0].endswith("give -o a file in a folder you can write to")


def test_calibrate_keeps_an_existing_calibration_without_force(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "boards").mkdir()  # no images: calibrating would fail, later
    target = tmp_path / "calibration.toml"
    target.write_text('[cam_0]\nname = "cam0"\n')
    code = main(["calibrate", str(tmp_path / "boards"), "-o", str(target)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == EXIT_BAD_INPUT and err == [f"error: {target}: already exists; use --force to replace it"]
    assert target.read_text() == '[cam_0]\nname = "cam0"\n'
    # With --force the output is taken, and the run goes on to the (here empty) board images.
    code = main(["calibrate", str(tmp_path / "boards"), "-o", str(target), "--force"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == EXIT_BAD_INPUT and len(err) == 1 and "already exists" not in err[0], err


def test_a_folder_in_place_of_a_video_is_named(session: Path, capsys: pytest.CaptureFixture[str]) -> None:
    video = next(session.glob("cam1.*"))
    video.unlink()
    video.mkdir()
    assert_rejected(session, capsys, video.name, "is not a regular file", "video file")


def test_a_declared_radius_far_from_the_tubes_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from pipeline.synth import render_session

    render_session(tmp_path / "s", frames=3, radius_mm=6.0, progress=False, jobs=1)
    _edit_toml(tmp_path / "s" / "session.toml", lambda d: d["manipulator"].update(radius_mm=60.0))
    # Named once, before any frame: not a failed line for every estimate the frames give.
    code = main(_process(tmp_path / "s", tmp_path / "out"))
    err = capsys.readouterr().err.splitlines()
    assert code == EXIT_BAD_INPUT and len(err) == 1, err
    assert err[0].startswith(
        f"error: {tmp_path / 's' / 'session.toml'}: [manipulator] radius_mm = 60 mm, but the silhouettes "
        "show a tube of about"
    )
    assert err[0].endswith("mm; correct radius_mm, or leave it out to take the silhouettes'")
    assert not (tmp_path / "out").exists()
    # A frame started from the hull says so too (a live camera's, which has no sample frames).
    from pipeline.reconstruct.frame import reconstruct_frame
    from pipeline.reconstruct.frame_task import decode_frames
    from pipeline.reconstruct.model import build_model
    from pipeline.session.folder import load_session

    session = load_session(tmp_path / "s")
    ((_, images),) = decode_frames(session.video_paths, range(1))
    result = reconstruct_frame(0, images, build_model(session))
    assert result.status == "failed" and "radius_mm = 60 mm, but the silhouettes show" in result.reason


def test_a_video_link_that_leads_back_to_itself_is_named(
    session: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    video = next(session.glob("cam1.*"))
    video.unlink()
    video.symlink_to(video.name)
    assert_rejected(session, capsys, video.name, "leads back to itself")


def test_a_folder_in_place_of_the_runs_lock_is_named(
    session: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = session.parent / "out"
    (out / ".session.lock").mkdir(parents=True)
    code = main(_process(session, out))
    err = capsys.readouterr().err
    assert code == EXIT_BAD_INPUT and ".session.lock: is a folder where a run keeps its lock" in err, err
