"""Accuracy figures against ground truth: exact answers on analytic curves."""

from __future__ import annotations

import dataclasses
import io
import json
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import rewrite_mcap
from mcap.reader import make_reader
from numpy.typing import NDArray

from pipeline.errors import EvaluationError, RecordingError
from pipeline.measure.evaluate import (
    TARGETS,
    EvaluationReport,
    centerline_distances,
    evaluate_centerlines,
    evaluate_recording,
    format_report,
    load_ground_truth,
    tip_jitter,
)
from pipeline.reconstruct.frame_result import FrameResult
from pipeline.record.load import load_recording


def line(
    n: int, *, length_mm: float = 100.0, offset_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
) -> NDArray[np.float64]:
    """(n, 3) points from offset up +z over ``length_mm``, uniform."""
    z = np.linspace(0.0, length_mm, n)
    return np.stack([np.zeros(n), np.zeros(n), z], axis=1) + np.asarray(offset_mm, dtype=np.float64)


# --- centerline_distances ------------------------------------------------------------


def test_parallel_lines_1mm_apart_are_1mm_apart_between_vertices() -> None:
    # b has vertices only at its ends: a vertex-only distance would be ~50 mm mid-way.
    a = np.stack([np.linspace(0.0, 10.0, 41), np.zeros(41), np.zeros(41)], axis=1)
    b = np.array([[-5.0, 1.0, 0.0], [15.0, 1.0, 0.0]])
    np.testing.assert_allclose(centerline_distances(a, b), 1.0, rtol=0, atol=1e-12)


def test_point_set_against_itself_is_zero() -> None:
    pts = np.random.default_rng(0).normal(0.0, 20.0, (50, 3))
    np.testing.assert_allclose(centerline_distances(pts, pts), 0.0, atol=1e-12)


def test_points_beyond_the_ends_measure_to_the_end_vertex() -> None:
    b = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [10.0, 10.0, 0.0]])
    a = np.array([[-3.0, 4.0, 0.0], [13.0, 14.0, 0.0], [5.0, 2.0, 0.0], [12.0, 5.0, 0.0]])
    np.testing.assert_allclose(centerline_distances(a, b), [5.0, 5.0, 2.0, 2.0], atol=1e-12)


def test_single_vertex_and_repeated_vertices() -> None:
    a = np.array([[3.0, 4.0, 0.0]])
    assert centerline_distances(a, np.zeros((1, 3)))[0] == pytest.approx(5.0, abs=1e-12)
    # A zero-length segment must not divide by zero.
    b = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    np.testing.assert_allclose(centerline_distances(a, b), [4.0], atol=1e-12)


# --- evaluate_centerlines ------------------------------------------------------------


def test_lateral_shift_gives_the_shift_everywhere() -> None:
    truth = np.stack([line(101)] * 6)
    pred = np.stack([line(64, offset_mm=(0.5, 0.0, 0.0))] * 6)
    report = evaluate_centerlines(pred, truth)
    for value in (
        report.mean_mm,
        report.p95_mm,
        report.tip_median_mm,
        report.tip_p95_mm,
        report.base_mean_mm,
    ):
        assert value == pytest.approx(0.5, abs=1e-12)
    assert report.length_error_pct == pytest.approx(0.0, abs=1e-12)
    assert report.failed_frames == 0 and report.failed_indices == ()


def test_a_longer_curve_gives_tip_and_length_errors() -> None:
    truth = np.stack([line(101)] * 3)
    pred = np.stack([line(64, length_mm=102.0)] * 3)
    report = evaluate_centerlines(pred, truth)
    assert report.tip_median_mm == pytest.approx(2.0, abs=1e-12)
    assert report.base_mean_mm == pytest.approx(0.0, abs=1e-12)
    assert report.length_error_pct == pytest.approx(2.0, abs=1e-9)
    # Only pred's points beyond the true tip are off the true curve, by up to 2 mm.
    assert report.mean_mm < 0.05 and report.p95_mm < 2.0


def test_failed_frames_are_counted_and_named_and_skipped() -> None:
    truth = np.stack([line(101)] * 8)
    pred = np.stack([line(64, offset_mm=(0.0, 0.3, 0.0))] * 8)
    pred[[2, 5]] = np.nan
    report = evaluate_centerlines(pred, truth, frame_indices=np.arange(100, 108))
    assert report.failed_frames == 2
    assert report.failed_indices == (102, 105)
    assert report.mean_mm == pytest.approx(0.3, abs=1e-12)


def test_all_frames_failed_gives_nan_figures_not_an_error() -> None:
    report = evaluate_centerlines(np.full((4, 8, 3), np.nan), np.stack([line(10)] * 4))
    assert report.failed_frames == 4
    assert np.isnan(report.mean_mm) and np.isnan(report.tip_median_mm) and np.isnan(report.jitter_ratio)


def sine_tips(amplitude_mm: float, frames: int = 91) -> tuple[NDArray[np.float64], float]:
    """Tip tracks x = A sin(w k) at 0.5 Hz and 30 fps, and w (rad per frame)."""
    w = 2 * np.pi * 0.5 / 30.0
    x = amplitude_mm * np.sin(w * np.arange(frames))
    return np.stack([x, np.zeros(frames), np.full(frames, 100.0)], axis=1), w


def test_jitter_of_a_sine_is_its_analytic_second_difference() -> None:
    tips, w = sine_tips(20.0)
    # x[k+1] - 2 x[k] + x[k-1] = -4 sin^2(w/2) x[k] exactly, for every interior k.
    expected = 4 * np.sin(w / 2) ** 2 * np.sqrt(np.mean(tips[1:-1, 0] ** 2))
    assert tip_jitter(tips) == pytest.approx(expected, rel=1e-12)


def test_jitter_ratio_compares_with_the_true_tip() -> None:
    truth_tips, _ = sine_tips(20.0)
    pred_tips, _ = sine_tips(40.0)
    truth = np.stack([line(5)] * len(truth_tips))
    pred = truth.copy()
    truth[:, -1], pred[:, -1] = truth_tips, pred_tips
    report = evaluate_centerlines(pred, truth, timestamps_s=np.arange(len(truth)) / 30.0)
    assert report.jitter_ratio == pytest.approx(2.0, rel=1e-12)


def test_uneven_timestamps_use_the_non_uniform_second_difference() -> None:
    # x = a t^2 has second difference 2 a step^2 at any spacing (step = median step).
    t = np.cumsum(np.random.default_rng(2).uniform(0.03, 0.045, 30))
    tips = np.stack([3.0 * t**2, np.zeros_like(t), np.zeros_like(t)], axis=1)
    step = np.median(np.diff(t))
    assert tip_jitter(tips, timestamps_s=t) == pytest.approx(2 * 3.0 * step**2, rel=1e-9)


def test_no_second_difference_across_missing_frames() -> None:
    # The tip holds still, then (while frames 10-19 were not recorded) moves 10 mm.
    t = np.concatenate([np.arange(10), np.arange(20, 30)]) / 30.0
    tips = np.zeros((20, 3))
    tips[10:, 0] = 10.0
    assert tip_jitter(tips, timestamps_s=t) == 0.0
    assert tip_jitter(tips) > 1.0  # without timestamps the jump looks like jitter


# --- report output -------------------------------------------------------------------


def small_report() -> EvaluationReport:
    truth = np.stack([line(101)] * 5)
    pred = np.stack([line(64, offset_mm=(0.2, 0.0, 0.0))] * 5)
    pred[3] = np.nan
    return evaluate_centerlines(pred, truth)


def test_json_is_strict_and_round_trips() -> None:
    report = small_report()
    data = json.loads(report.to_json())
    assert data["failed_indices"] == [3]
    assert data["mean_mm"] == pytest.approx(0.2)
    # A still tip has zero jitter: the ratio is undefined and must be null, not NaN.
    assert data["jitter_ratio"] is None
    assert data["smoothed"] is None


def test_format_report_shows_figures_targets_and_failed_frames() -> None:
    text = format_report(small_report())
    assert "centreline mean (mm)" in text and "0.200" in text
    assert f"<= {TARGETS['mean_mm']}" in text
    assert "failed frames: 3" in text


# --- files ---------------------------------------------------------------------------


def test_ground_truth_from_a_session_directory(tmp_path: Path) -> None:
    centerlines = np.stack([line(20)] * 3)
    np.savez(tmp_path / "ground_truth.npz", centerlines=centerlines, timestamps_s=np.arange(3) / 30.0)
    loaded = load_ground_truth(tmp_path)
    np.testing.assert_array_equal(loaded.centerlines_mm, centerlines)
    assert loaded.timestamps_s is not None and len(loaded.timestamps_s) == 3
    assert loaded.video_fingerprints == {} and loaded.radius_mm is None


def test_missing_inputs_are_user_errors(tmp_path: Path) -> None:
    with pytest.raises(EvaluationError, match=r"holds no ground_truth\.npz"):
        load_ground_truth(tmp_path)
    with pytest.raises(EvaluationError, match="does not exist"):
        load_ground_truth(tmp_path / "nope.npz")
    (tmp_path / "bad.npz").write_text("not a zip")
    with pytest.raises(EvaluationError, match=r"bad\.npz: is not a ground_truth\.npz \(a NumPy \.npz"):
        load_ground_truth(tmp_path / "bad.npz")
    (tmp_path / "cut.npz").write_bytes(b"PK\x03\x04 and then nothing")
    with pytest.raises(EvaluationError, match=r"cut\.npz: not a readable \.npz"):
        load_ground_truth(tmp_path / "cut.npz")
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(EvaluationError, match="no 'centerlines' array"):
        load_ground_truth(tmp_path / "other.npz")
    with pytest.raises(EvaluationError, match=r"missing\.mcap does not exist"):
        evaluate_recording(tmp_path / "missing.mcap", tmp_path / "other.npz")


@pytest.mark.parametrize("where", ["file", "in-session", "recording"])
def test_a_link_that_leads_back_to_itself_is_named_as_such(tmp_path: Path, where: str) -> None:
    # A loop of links is no missing file: "does not exist" would send the user looking for one.
    np.savez(tmp_path / "truth.npz", centerlines=np.stack([line(20)] * 3))
    (tmp_path / "session").mkdir()
    loop = {"file": tmp_path / "gt.npz", "in-session": tmp_path / "session" / "ground_truth.npz"}.get(
        where, tmp_path / "run.mcap"
    )
    loop.symlink_to(loop.name)
    with pytest.raises(EvaluationError, match=rf"{loop}: is a symbolic link that leads back to itself"):
        if where == "recording":
            evaluate_recording(loop, tmp_path / "truth.npz")
        else:
            load_ground_truth(loop if where == "file" else loop.parent)


# --- a recording made by the runner -------------------------------------------------

RUN_FRAMES = 8


def rod_truth(index: int) -> NDArray[np.float64]:
    """(20, 3) the true curve of frame ``index``: a vertical rod moved ``index`` mm along x."""
    return line(20, length_mm=160.0, offset_mm=(128.0 + index, 128.0, 0.0))


def shifted_rod(index: int, images: object, model: object) -> tuple[FrameResult, None]:
    """Stand-in frame function: the true rod 0.5 mm off along y; frame 4 sees no tube, 5 fails."""
    if index == 4:
        return FrameResult(index=index, status="empty", reason="no silhouette"), None
    if index == 5:
        return FrameResult.failed(index, "test failure"), None
    curve = line(16, length_mm=160.0, offset_mm=(128.0 + index, 128.5, 0.0))
    points = curve.astype(np.float32)
    return FrameResult(index=index, status="ok", points_mm=points, centerline_mm=curve, length_mm=160.0), None


@pytest.fixture(scope="module")
def partial_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A recording of frames 2..7 of an 8-frame session, and the session's ground truth."""
    from conftest import build_session

    from pipeline.run.runner import process_session
    from pipeline.session.folder import load_session

    root = tmp_path_factory.mktemp("evaluate_run")
    session_dir = build_session(root / "rod", frames=RUN_FRAMES)
    truth = np.stack([rod_truth(i) for i in range(RUN_FRAMES)])
    np.savez(session_dir / "ground_truth.npz", centerlines=truth, timestamps_s=np.arange(RUN_FRAMES) / 30.0)
    process_session(
        load_session(session_dir),
        out_dir=root / "out",
        jobs=1,
        frames=(2, RUN_FRAMES),
        images=False,
        progress=False,
        frame_fn=shifted_rod,
    )
    return root / "out" / "rod.mcap", session_dir


def test_recording_is_matched_to_the_truth_by_frame_index(partial_run: tuple[Path, Path]) -> None:
    recording, session_dir = partial_run
    report = evaluate_recording(recording, session_dir)
    assert report.frames == RUN_FRAMES - 2
    assert report.failed_indices == (5,)
    # A frame with no tube seen is not a failure, as process's summary has it.
    assert report.empty_frames == 1 and report.empty_indices == (4,)
    assert report.good_frames == RUN_FRAMES - 2 - 2
    # Matched frame for frame, only the 0.5 mm shift remains; a frame off would add 1 mm.
    assert report.mean_mm == pytest.approx(0.5, abs=1e-6)  # metres and back: rounding only
    assert report.tip_median_mm == pytest.approx(0.5, abs=1e-6)
    assert report.length_error_pct == pytest.approx(0.0, abs=1e-6)
    # The runner smooths after the last frame: a uniform motion passes through unchanged.
    assert report.smoothed is not None
    assert report.smoothed.failed_indices == (5,) and report.smoothed.empty_indices == (4,)
    assert report.smoothed.mean_mm == pytest.approx(0.5, abs=1e-6)


def test_cli_evaluate_prints_the_table_and_json(
    partial_run: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    from pipeline.cli import main

    recording, session_dir = partial_run
    assert main(["evaluate", str(recording), str(session_dir / "ground_truth.npz")]) == 0
    assert "centreline mean (mm)" in capsys.readouterr().out
    assert main(["evaluate", str(recording), str(session_dir), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["failed_indices"] == [5] and data["empty_indices"] == [4] and data["exit_code"] == 0
    # The recording's own fields once, at the top level: not as "" again in the smoothed report.
    assert "other_session" in data and "other_session" not in data["smoothed"]
    assert data["smoothed"]["empty_frames"] == 1


def failed_rod(index: int, images: object, model: object) -> tuple[FrameResult, None]:
    """Stand-in frame function: every frame fails."""
    return FrameResult.failed(index, "test failure"), None


def test_a_recording_without_a_curve_measures_nothing_and_exits_1(
    partial_run: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A script's `evaluate && ...` must not take a run that found no tube for a pass.
    from pipeline.cli import EXIT_FRAMES_FAILED, main
    from pipeline.run.runner import process_session
    from pipeline.session.folder import load_session

    _, session_dir = partial_run
    process_session(
        load_session(session_dir), out_dir=tmp_path, jobs=1, images=False, progress=False, frame_fn=failed_rod
    )
    assert main(["evaluate", str(tmp_path / "rod.mcap"), str(session_dir)]) == EXIT_FRAMES_FAILED
    err = capsys.readouterr().err
    assert f"warning: {tmp_path / 'rod.mcap'}: no frame holds a curve to compare ({RUN_FRAMES} frames" in err


def test_a_truncated_recording_is_evaluated_as_far_as_it_goes_and_says_so(
    partial_run: tuple[Path, Path],
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    capsys: pytest.CaptureFixture[str],
) -> None:
    from pipeline.cli import EXIT_FRAMES_FAILED, main

    recording, session_dir = partial_run
    whole = evaluate_recording(recording, session_dir)
    assert whole.complete
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recording.read_bytes()[: recording.stat().st_size - 64])  # the footer lost
    assert main(["evaluate", str(cut), str(session_dir), "--json"]) == EXIT_FRAMES_FAILED
    assert json.loads(capsys.readouterr().out)["exit_code"] == EXIT_FRAMES_FAILED  # said in the JSON too
    # One line names it, the reading's: the report is of the frames before the cut.
    (line,) = [r.getMessage() for r in caplog.records if "cut.mcap" in r.getMessage()]
    assert "(the run did not finish)" in line and "damaged" not in line
    assert not evaluate_recording(cut, session_dir).complete


def test_a_recording_damaged_inside_is_evaluated_as_far_as_it_goes_and_named_damaged(
    partial_run: tuple[Path, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from pipeline.cli import EXIT_FRAMES_FAILED, main

    recording, session_dir = partial_run
    # A chunk every few messages: damage in the middle of its data leaves frames before it.
    data = bytearray(rewrite_mcap(recording, tmp_path / "chunked.mcap", chunk_size=500).read_bytes())
    summary = make_reader(io.BytesIO(data)).get_summary()
    assert summary is not None and len(summary.chunk_indexes) > 2
    chunk = summary.chunk_indexes[len(summary.chunk_indexes) // 2]
    middle = chunk.chunk_start_offset + chunk.chunk_length // 2  # inside the middle chunk
    data[middle : middle + 64] = bytes(64)
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(data)
    assert main(["evaluate", str(damaged), str(session_dir)]) == EXIT_FRAMES_FAILED
    (line,) = [r.getMessage() for r in caplog.records if str(damaged) in r.getMessage()]
    assert f"{damaged}: damaged after frame " in line and "cut short" not in line
    assert "run `pipeline process` on its session again" in line
    # The command says it once: the reading's line, its report of the frames before it, exit 1.
    run = subprocess.run(
        [sys.executable, "-m", "pipeline", "evaluate", str(damaged), str(session_dir)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert run.returncode == EXIT_FRAMES_FAILED and "centreline mean" in run.stdout
    said = [s for s in run.stderr.splitlines() if "damaged after" in s or "is damaged" in s]
    assert said == [f"WARNING: {line}"]
    report = evaluate_recording(damaged, session_dir)
    assert report.damaged and not report.complete


def test_another_sessions_ground_truth_is_warned_of(
    partial_run: tuple[Path, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    recording, session_dir = partial_run
    other = tmp_path / "other"
    other.mkdir()
    (other / "ground_truth.npz").write_bytes((session_dir / "ground_truth.npz").read_bytes())
    with caplog.at_level(logging.WARNING):
        evaluate_recording(recording, session_dir)
    assert "recording of session" not in caplog.text
    with caplog.at_level(logging.WARNING):
        report = evaluate_recording(recording, other)
    assert "is a recording of session 'rod', the ground truth that of 'other'" in caplog.text
    assert report.other_session == "rod" and not evaluate_recording(recording, session_dir).other_session
    # The report is given, and the exit status says it may compare two sessions.
    from pipeline.cli import EXIT_FRAMES_FAILED, main

    assert main(["evaluate", str(recording), str(other)]) == EXIT_FRAMES_FAILED
    assert main(["evaluate", str(recording), str(session_dir)]) == 0


def test_a_session_filmed_again_since_its_recording_is_warned_of(
    partial_run: tuple[Path, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # The same folder (so the same session name), its videos replaced: a render again.
    recording, session_dir = partial_run
    again = tmp_path / "rod"
    shutil.copytree(session_dir, again)
    video = next(p for p in sorted(again.iterdir()) if p.name.startswith("cam1."))
    with caplog.at_level(logging.WARNING):
        assert not evaluate_recording(recording, again).other_videos  # a copy is the same session
    assert "other videos" not in caplog.text
    data = bytearray(video.read_bytes())
    data[-100] ^= 0xFF  # one byte of its last frame
    video.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING):
        report = evaluate_recording(recording, again / "ground_truth.npz")
    assert report.other_videos == video.name and not report.other_session
    assert f"was made from other videos than {video.name} beside the ground truth" in caplog.text
    from pipeline.cli import EXIT_FRAMES_FAILED, main

    assert main(["evaluate", str(recording), str(again)]) == EXIT_FRAMES_FAILED


def test_a_ground_truth_copied_from_another_render_is_warned_of(
    partial_run: tuple[Path, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # Copied away from its videos, under the recording's session name: only the videos it
    # names as rendered with it tell it is another session's.
    recording, session_dir = partial_run
    videos = load_recording(recording).videos
    truth = dict(np.load(session_dir / "ground_truth.npz"))
    results = tmp_path / "rod"
    results.mkdir()

    def truth_of(fingerprints: dict[str, str]) -> Path:
        named = np.array([f"{name}={fingerprint}" for name, fingerprint in fingerprints.items()])
        np.savez(results / "ground_truth.npz", **truth, video_fingerprints=named)
        return results / "ground_truth.npz"

    with caplog.at_level(logging.WARNING):
        assert not evaluate_recording(recording, truth_of(videos)).other_videos  # its own
    assert "other videos" not in caplog.text
    other = {
        name: ("0" * 16 if name.startswith("cam1.") else fingerprint) for name, fingerprint in videos.items()
    }
    with caplog.at_level(logging.WARNING):
        report = evaluate_recording(recording, truth_of(other))
    assert report.other_videos == next(name for name in videos if name.startswith("cam1."))
    assert "other videos than those the ground truth was rendered with" in caplog.text
    # A camera's video rendered under another name (cam1.mkv for the recording's cam1 video:
    # re-encoded) is another video too.
    renamed = {name: fp for name, fp in videos.items() if not name.startswith("cam1.")} | {
        "cam1.mkv": "1" * 16
    }
    assert evaluate_recording(recording, truth_of(renamed)).other_videos == "cam1.mkv"
    from pipeline.cli import EXIT_FRAMES_FAILED, main

    assert main(["evaluate", str(recording), str(results)]) == EXIT_FRAMES_FAILED


def test_a_folder_given_as_the_recording_is_named(partial_run: tuple[Path, Path]) -> None:
    recording, session_dir = partial_run
    with pytest.raises(EvaluationError, match=r"is a folder; give the recording's \.mcap file"):
        evaluate_recording(recording.parent, session_dir)
    with pytest.raises(
        EvaluationError, match=r"a recording: give the recording first, then the ground truth"
    ):
        evaluate_recording(session_dir, recording)  # the two the other way round
    with pytest.raises(
        EvaluationError, match=r"is a ground truth \(\.npz\), not a recording: give the recording first"
    ):
        evaluate_recording(session_dir / "ground_truth.npz", recording)


def test_a_ground_truth_with_non_finite_centrelines_is_a_user_error(
    partial_run: tuple[Path, Path], tmp_path: Path
) -> None:
    recording, _ = partial_run
    truth = np.stack([rod_truth(i) for i in range(RUN_FRAMES)])
    truth[3, 0, 0] = np.nan
    np.savez(tmp_path / "nan.npz", centerlines=truth)
    with pytest.raises(EvaluationError, match="holds non-finite values"):
        evaluate_recording(recording, tmp_path / "nan.npz")


def test_a_ground_truth_far_beyond_any_workspace_is_a_user_error(
    partial_run: tuple[Path, Path], tmp_path: Path
) -> None:
    # Finite, but 1e300 mm: the distances to it overflow, and every figure would be empty.
    recording, _ = partial_run
    truth = np.stack([rod_truth(i) for i in range(RUN_FRAMES)]) * 1e300
    np.savez(tmp_path / "far.npz", centerlines=truth)
    with pytest.raises(EvaluationError, match=r"'centerlines' reach .*e\+30\d mm from the origin"):
        evaluate_recording(recording, tmp_path / "far.npz")


def test_a_recording_cut_before_its_first_frame_is_one_line(
    partial_run: tuple[Path, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    recording, session_dir = partial_run
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recording.read_bytes()[:600])  # the header and metadata, no frame
    with caplog.at_level(logging.WARNING), pytest.raises(EvaluationError) as info:
        evaluate_recording(cut, session_dir)
    assert "holds no frames (cut short before its first frame" in str(info.value)
    assert not caplog.records  # the reason is in the error's line, not in a warning above it
    rrd = tmp_path / "run.rrd"
    rrd.write_bytes(b"RRF2" + bytes(60))
    with pytest.raises(RecordingError, match=r"is a Rerun recording .*; read the \.mcap written beside it"):
        evaluate_recording(rrd, session_dir)


def test_a_recording_damaged_before_its_first_frame_is_one_line(
    partial_run: tuple[Path, Path], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    recording, session_dir = partial_run
    data = bytearray(recording.read_bytes())
    data[700:764] = bytes(64)  # past the header and metadata, inside the first chunk
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(data)
    with caplog.at_level(logging.WARNING), pytest.raises(EvaluationError) as info:
        evaluate_recording(damaged, session_dir)
    message = str(info.value)
    assert message.startswith(f"{damaged}: the recording holds no frames (damaged before its first frame: ")
    assert "a disk or copy error" in message and "run `pipeline process` on its session again" in message
    assert not caplog.records  # the reason is in the error's line, not in a warning above it


def test_recording_beyond_the_truth_is_a_user_error(partial_run: tuple[Path, Path], tmp_path: Path) -> None:
    recording, _ = partial_run
    np.savez(tmp_path / "short.npz", centerlines=np.stack([rod_truth(0)] * 4))
    with pytest.raises(EvaluationError, match="frame 4 is beyond the ground truth's 4 frames"):
        evaluate_recording(recording, tmp_path / "short.npz")


# --- the accuracy table (docs/accuracy.md) (pipeline.measure.accuracy_table) ---------------------------


def test_accuracy_table_covers_every_shape_and_an_unseen_set() -> None:
    from pipeline.measure.accuracy_table import default_cases
    from pipeline.synth.names import SHAPES

    cases = default_cases()
    assert {c.shape for c in cases if not c.unseen} == set(SHAPES)
    unseen = [c for c in cases if c.unseen]
    assert {c.arrangement for c in unseen} == {"ninety", "oblique"}
    assert {4.0, 9.0} <= {c.radius_mm for c in unseen}
    assert {c.polarity for c in unseen} == {"dark", "bright"}
    assert {c.shape for c in unseen} == set(SHAPES)
    assert len({c.name for c in cases}) == len(cases)


def test_accuracy_table_is_markdown_with_ours_smoothed_and_polyfit() -> None:
    from pipeline.measure.accuracy_table import COLUMNS, Case, CaseResult, format_table, results_json

    ours = dataclasses.replace(small_report(), smoothed=dataclasses.replace(small_report(), label="smoothed"))
    results = [
        CaseResult(Case("loop", "loop"), 5, ours, small_report()),
        CaseResult(Case("ninety-helix-r4", "helix", "ninety", 4.0, unseen=True), 5, small_report(), None),
    ]
    lines = format_table(results).splitlines()
    assert lines[1] == "|" + "---|" * len(COLUMNS)
    first = [cell.strip() for cell in lines[2].strip("|").split("|")]
    assert len(first) == len(COLUMNS)
    assert first[:4] == ["loop", "oblique", "6", "0.20"]
    assert first[7] == "1/5"  # failed / frames
    assert first[8:10] == ["0 (-)", "-"]  # frames off (flagged), good frames flagged: not known here
    assert first[11] == "0.20" and first[15] == "0.20"  # smoothed and polyfit means
    second = [cell.strip() for cell in lines[3].strip("|").split("|")]
    assert second[0] == "ninety-helix-r4 (unseen)" and second[11] == "-" and second[-1] == "-"
    assert json.loads(results_json(results))[1]["polyfit"] is None


@pytest.mark.parametrize(
    ("centerlines", "message"),
    [
        (np.zeros((0, 20, 3)), r"'centerlines' holds no frames"),
        (np.zeros((RUN_FRAMES, 0, 3)), r"'centerlines' holds no points"),
        (np.ones((RUN_FRAMES, 20, 3), dtype=bool), r"'centerlines' holds bool values"),
        (np.ones((RUN_FRAMES, 20, 3), dtype=complex), r"'centerlines' holds complex128 values"),
        (np.ones((RUN_FRAMES, 1, 3)), r"'centerlines' holds 1 point a frame; a centreline needs 2"),
        (
            np.stack([rod_truth(i) for i in range(RUN_FRAMES)]) / 1000.0,
            r"its centrelines are 0\.\d+ mm long .*is this one in metres\?",
        ),
    ],
    ids=["no-frames", "no-points", "bool", "complex", "one-point", "metres"],
)
def test_a_ground_truth_without_usable_centrelines_is_named(
    partial_run: tuple[Path, Path], tmp_path: Path, centerlines: NDArray[np.generic], message: str
) -> None:
    recording, _ = partial_run
    np.savez(tmp_path / "odd.npz", centerlines=centerlines)
    with pytest.raises(EvaluationError, match=rf"odd\.npz: {message}"):
        evaluate_recording(recording, tmp_path / "odd.npz")


def test_a_recording_without_any_curve_counts_every_frame_failed() -> None:
    # N = 0: a recording that holds frames but no curve points.
    truth = np.stack([line(20)] * 4)
    report = evaluate_centerlines(np.zeros((4, 0, 3)), truth)
    assert report.failed_frames == 4 and report.failed_indices == (0, 1, 2, 3)
    assert np.isnan(report.mean_mm) and np.isnan(report.tip_jitter_mm)


@pytest.mark.timeout(20)
def test_a_named_pipe_is_refused_not_waited_on_nor_called_missing(
    partial_run: tuple[Path, Path], tmp_path: Path
) -> None:
    recording, session_dir = partial_run
    pipe = tmp_path / "pipe"
    os.mkfifo(pipe)  # a read would block until something wrote to it
    with pytest.raises(RecordingError, match=r"pipe: cannot read: is not a regular file"):
        evaluate_recording(pipe, session_dir)
    with pytest.raises(EvaluationError, match=r"pipe: is not a regular file"):
        evaluate_recording(recording, pipe)


def test_a_report_to_a_stdout_the_caller_closed_is_refused(
    partial_run: tuple[Path, Path], capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # `evaluate ... >&-`: the report is all the command makes.
    from pipeline.cli import EXIT_BAD_INPUT, commands, main

    recording, session_dir = partial_run
    monkeypatch.setattr(commands, "_CLOSED_BY_CALLER", {"stdout"})
    assert main(["evaluate", str(recording), str(session_dir)]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err.splitlines() == [
        "error: stdout: closed (>&-), so it cannot take the report of rod.mcap; leave it open, "
        "or send it to a file"
    ]


@pytest.mark.parametrize("as_json", [False, True], ids=["table", "json"])
def test_a_report_that_stdout_cannot_take_is_an_error_not_a_success(
    partial_run: tuple[Path, Path],
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    as_json: bool,
) -> None:
    # `evaluate ... --json > report.json` on a full disk: the report is all the command makes.
    from pipeline.cli import EXIT_BAD_INPUT, main

    recording, session_dir = partial_run
    with open("/dev/full", "w", encoding="utf-8") as full:
        monkeypatch.setattr(sys, "stdout", full)
        code = main(["evaluate", str(recording), str(session_dir), *(["--json"] if as_json else [])])
    err = capsys.readouterr().err
    assert code == EXIT_BAD_INPUT, err
    assert err.startswith("error: stdout: cannot take the report of rod.mcap (No space left on device)"), err
