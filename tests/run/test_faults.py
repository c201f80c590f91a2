"""Faults during a run: the run finishes, bad frames are data, outputs are never half-written.

Most tests replace the per-frame computation (``frame_fn``) by :class:`StraightRod`,
a cheap stand-in that returns a fixed curve, so that they exercise the runner's
fault handling and not the reconstruction.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import av
import numpy as np
import psutil
import pytest
from conftest import build_session
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader, breakup_chunk

from pipeline.cli import EXIT_FRAMES_FAILED, EXIT_OK, main
from pipeline.errors import Interrupted, OutputError, RecordingError, SettingsError, WorkersError
from pipeline.reconstruct.frame_result import FrameResult
from pipeline.record.load import load_recording
from pipeline.record.mcap_log import METRICS_TOPIC
from pipeline.run import output_target, outputs, runner, workers
from pipeline.session.folder import load_session
from pipeline.session.settings import Settings

# As many points as session.toml's default, which a recording without curves falls back on.
CURVE_POINTS = Settings().centerline.points


@dataclass(frozen=True)
class StraightRod:
    """A stand-in frame function: the rod of conftest, as an "ok" result with ``points`` voxels."""

    points: int = 50

    def __call__(self, index: int, images: Sequence[Any], model: Any) -> tuple[FrameResult, None]:
        z = np.linspace(0.0, 160.0, CURVE_POINTS)
        curve = np.column_stack([np.full_like(z, 128.0), np.full_like(z, 128.0), z])
        voxels = np.random.default_rng(index).uniform(100, 156, (self.points, 3)).astype(np.float32)
        result = FrameResult(index=index, status="ok", points_mm=voxels, centerline_mm=curve, length_mm=160.0)
        return result, None


straight_rod = StraightRod()


def dies_at_frame_5(index: int, images: Sequence[Any], model: Any) -> tuple[FrameResult, None]:
    """Kill the worker process on frame 5, as the OOM killer would; note each attempt."""
    if index == 5:
        marker = Path(os.environ["FAULTS_ATTEMPTS_DIR"]) / f"attempt-{os.getpid()}"
        marker.touch()
        os._exit(9)
    return straight_rod(index, images, model)


def _run(session_dir: Path, out: Path, **options: Any) -> runner.RunSummary:
    kwargs: dict[str, Any] = {"jobs": 1, "images": False, "progress": False, "frame_fn": straight_rod}
    kwargs.update(options)
    return runner.process_session(load_session(session_dir), out_dir=out, **kwargs)


def _leftovers(out: Path) -> list[str]:
    """Temporary files a run left behind."""
    return sorted(p.name for p in out.iterdir() if p.name.startswith("."))


def _cut(path: Path, fraction: float) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])


# --- damaged videos ------------------------------------------------------------------------


def test_avi_cut_short_fails_the_frames_past_the_cut(tmp_path: Path) -> None:
    session = build_session(tmp_path / "cut", frames=10)
    _cut(session / "cam1.avi", 0.55)  # the AVI header still says 10 frames
    out = tmp_path / "out"
    summary = _run(session, out)
    failed = dict(summary.frames_failed)
    assert summary.exit_code == 1
    assert summary.frames_ok + len(failed) == 10
    # The first frames survive the cut; from the first lost frame on, every frame is lost.
    first = min(failed)
    assert 0 < first < 10 and sorted(failed) == list(range(first, 10))
    # Each says why: the frame the cut runs through is rejected, the ones after are gone.
    assert all(reason.startswith("camera cam1: ") for reason in failed.values())
    assert failed[9] == "camera cam1: not in the file (cut short?)"
    rec = load_recording(out / "cut.mcap")
    assert list(rec.frame_indices) == list(range(10))
    assert list(rec.statuses).count("failed") == len(failed)


def test_cameras_that_lose_a_frame_for_one_reason_share_its_line(tmp_path: Path) -> None:
    session = build_session(tmp_path / "cut2", frames=10)
    for name in ("cam1.avi", "cam2.avi"):
        _cut(session / name, 0.55)
    failed = dict(_run(session, tmp_path / "out").frames_failed)
    assert failed[9] == "cameras cam1, cam2: not in the file (cut short?)"


def _chunks_hit(video: Path, start: int, stop: int) -> set[int]:
    """Frames of an AVI whose chunk (8-byte header and data, where idx1 puts it) meets bytes [start, stop)."""
    with av.open(str(video)) as container:
        entries = container.streams.video[0].index_entries
        return {e.timestamp for e in entries if e.pos < stop and e.pos + 8 + e.size > start}


def test_damaged_packet_fails_frames_of_that_camera_only(tmp_path: Path) -> None:
    session = build_session(tmp_path / "dmg", frames=10)
    video = session / "cam2.avi"
    data = bytearray(video.read_bytes())
    middle = len(data) // 2
    hit = _chunks_hit(video, middle, middle + 800)
    # Mid-file: the last frame is intact, so a failure there (the cut case) would not do.
    assert hit and max(hit) < 9
    data[middle : middle + 800] = np.random.default_rng(1).bytes(800)
    video.write_bytes(bytes(data))
    summary = _run(session, tmp_path / "out")
    # Exactly the frames whose bytes were hit fail (one chunk loses its header, one its
    # picture data); the frames after them are read at their own positions and are ok.
    assert sorted(i for i, _ in summary.frames_failed) == sorted(hit)
    assert all("camera cam2" in reason for _, reason in summary.frames_failed)
    assert summary.frames_ok == 10 - len(hit)
    assert summary.exit_code == 1


def test_videos_of_different_lengths_process_the_common_frames(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    session = build_session(tmp_path / "len", frame_counts={"cam0": 6, "cam1": 4, "cam2": 5})
    with caplog.at_level(logging.WARNING):
        summary = _run(session, tmp_path / "out")
    assert "cam0: 6, cam1: 4, cam2: 5" in caplog.text
    assert (summary.frames_ok, summary.frames_failed, summary.exit_code) == (4, [], 0)


# --- the real reconstruction, through the command line ----------------------------------------

# 4 mm voxels: a 64^3 grid, plenty for a 7 px rod and quick to build.
COARSE = {"workspace": {"voxel_mm": 4.0}}


def _cli_process(session: Path, out: Path) -> int:
    return main(["process", str(session), "--out", str(out), "--jobs", "1", "--no-images"])


def test_a_video_much_shorter_than_the_others_is_named_and_ends_the_run_with_status_1(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    session = build_session(tmp_path / "short", frame_counts={"cam1": 1}, frames=8, settings=COARSE)
    assert _cli_process(session, tmp_path / "out") == EXIT_FRAMES_FAILED
    captured = capsys.readouterr()
    assert "1 processed, 1 ok" in captured.out
    assert (
        f"  {session / 'cam1.avi'} has 1 frame, the others 8: only the first frame was processed; "
        "check the recording"
    ) in captured.err.splitlines()
    assert load_recording(tmp_path / "out" / "short.mcap").centerlines_m.shape[0] == 1
    # Frames every video holds: the shorter one cut none of them.
    code = main(
        ["process", str(session), "-o", str(tmp_path / "part"), "-j", "1", "--no-images", "--frames", ":1"]
    )
    assert code == EXIT_OK and "only the first" not in capsys.readouterr().err


def test_manipulator_out_of_view_is_empty_not_a_crash(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    session = build_session(tmp_path / "gone", frames=4, empty_frames={1, 2}, settings=COARSE)
    assert _cli_process(session, tmp_path / "out") == EXIT_OK
    assert "2 ok, 2 empty, 0 failed" in capsys.readouterr().out
    rec = load_recording(tmp_path / "out" / "gone.mcap")
    assert list(rec.statuses) == ["ok", "empty", "empty", "ok"]
    assert np.isnan(rec.centerlines_m[1:3]).all() and not np.isnan(rec.centerlines_m[[0, 3]]).any()


def test_truncated_video_run_exits_1_and_names_the_frames(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    session = build_session(tmp_path / "cut", frames=8, settings=COARSE)
    _cut(session / "cam2.avi", 0.6)
    assert _cli_process(session, tmp_path / "out") == EXIT_FRAMES_FAILED
    err = capsys.readouterr().err
    rec = load_recording(tmp_path / "out" / "cut.mcap")
    failed = np.flatnonzero(rec.statuses == "failed")
    assert len(failed) and (rec.statuses[: failed[0]] == "ok").all()
    # One line per span and reason on stderr, in frame order, the last one the frames past the cut.
    lines = [line for line in err.splitlines() if line.startswith("  failed ")]
    assert lines and all(": camera cam2: " in line for line in lines)
    assert lines[-1].endswith(f"{failed[-1]}: camera cam2: not in the file (cut short?)")


# --- a worker that dies ----------------------------------------------------------------------


@pytest.mark.slow
def test_worker_that_dies_is_retried_then_its_frames_fail(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    session = build_session(tmp_path / "die", frames=3 * runner.MIN_RANGE_FRAMES)
    attempts = tmp_path / "attempts"
    attempts.mkdir()
    monkeypatch.setenv("FAULTS_ATTEMPTS_DIR", str(attempts))  # inherited by the loky workers
    summary = _run(session, tmp_path / "out", jobs=2, backend="loky", frame_fn=dies_at_frame_5)
    assert len(list(attempts.iterdir())) >= 2  # tried, then tried again in a fresh worker
    failed = dict(summary.frames_failed)
    assert 5 in failed and "worker died" in failed[5]
    # Only the dead range is lost (three ranges of MIN_RANGE_FRAMES).
    assert sorted(failed) == list(range(0, runner.MIN_RANGE_FRAMES))
    assert summary.frames_ok == 2 * runner.MIN_RANGE_FRAMES and summary.exit_code == 1


def always_dies(index: int, images: Sequence[Any], model: Any) -> tuple[FrameResult, None]:
    """Kill the worker on every frame: a worker that cannot run at all (the scheduler's only one)."""
    os._exit(9)


@pytest.mark.slow
def test_workers_that_die_on_every_range_leave_the_outputs_there(tmp_path: Path) -> None:
    # A recording of nothing but failed frames would replace a good pair under --force.
    session = build_session(tmp_path / "die", frames=2 * runner.MIN_RANGE_FRAMES)
    out = tmp_path / "out"
    _run(session, out, frames=(0, 2))
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    no_frame = (
        r"no frame was reconstructed: worker died on frames 0-\d+, also when retried "
        r".*\(as on all \d+ ranges of the run\)"
    )
    with pytest.raises(WorkersError, match=no_frame):
        _run(session, out, force=True, jobs=2, backend="loky", frame_fn=always_dies)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


# --- outputs: existing, unwritable, disk full, interrupted -----------------------------------


def test_existing_outputs_are_kept_without_force(tmp_path: Path) -> None:
    session = build_session(tmp_path / "take", frames=2)
    out = tmp_path / "out"
    _run(session, out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    with pytest.raises(OutputError, match=r"take\.mcap: already exists; use --force"):
        _run(session, out)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


@pytest.mark.parametrize("which", ["mcap", "rrd"])
def test_a_folder_where_a_recording_goes_is_refused_even_with_force(tmp_path: Path, which: str) -> None:
    # --force replaces recordings; a folder under a recording's name is not one. Before any
    # work, with nothing written and the folder as it was.
    session = build_session(tmp_path / "take", frames=2)
    out = tmp_path / "out"
    (out / f"take.{which}").mkdir(parents=True)
    (out / f"take.{which}" / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match=rf"take\.{which}: is not a file but is where the recording goes"):
        _run(session, out, force=True)
    assert sorted(p.name for p in out.iterdir()) == [f"take.{which}"]
    assert (out / f"take.{which}" / "notes.txt").read_text() == "mine"


class _Recorder:
    """Frame function that checks, while the run goes on, that the old outputs are intact."""

    def __init__(self, path: Path) -> None:
        self.path, self.original = path, path.read_bytes()
        self.intact: list[bool] = []

    def __call__(self, index: int, images: Sequence[Any], model: Any) -> tuple[FrameResult, None]:
        self.intact.append(self.path.read_bytes() == self.original)
        return straight_rod(index, images, model)


def test_force_replaces_outputs_atomically(tmp_path: Path) -> None:
    session = build_session(tmp_path / "take", frames=3)
    out = tmp_path / "out"
    _run(session, out, frames=(0, 1))
    watch = _Recorder(out / "take.mcap")
    # Threads: the frame function runs in this process and can look at the files mid-run.
    summary = _run(session, out, force=True, backend="threading", frame_fn=watch)
    assert watch.intact == [True, True, True]  # the old file stayed whole until the end
    assert summary.frames_ok == 3 and len(load_recording(out / "take.mcap")) == 3
    assert _leftovers(out) == []


class _Interrupt:
    def __call__(self, index: int, images: Sequence[Any], model: Any) -> tuple[FrameResult, None]:
        if index == 2:
            raise KeyboardInterrupt
        return straight_rod(index, images, model)


def test_interrupted_force_run_leaves_old_outputs(tmp_path: Path) -> None:
    session = build_session(tmp_path / "take", frames=4)
    out = tmp_path / "out"
    _run(session, out, frames=(0, 1))
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    stopped = r"interrupted with \d of 4 frames written; temporary files removed"
    with pytest.raises(Interrupted, match=stopped):
        _run(session, out, force=True, backend="threading", frame_fn=_Interrupt())
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_output_path_under_a_file_is_an_error_before_any_work(tmp_path: Path) -> None:
    session = build_session(tmp_path / "take", frames=2)
    (tmp_path / "file").write_text("not a directory")
    # Tests run as root, so chmod cannot make a directory unwritable: a path under a file can't exist.
    with pytest.raises(OutputError, match=r"file: is a file, not a directory \(in .*file/out\); give --out"):
        _run(session, tmp_path / "file" / "out")
    with pytest.raises(OutputError, match=r"file: is a file, not a directory; give --out a directory"):
        _run(session, tmp_path / "file")


def test_output_path_in_a_folder_this_user_may_not_open_is_an_error_before_any_work(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    session = build_session(tmp_path / "take", frames=2)
    closed = tmp_path / "closed"
    closed.mkdir()
    real_exists = Path.exists

    def exists(self: Path) -> bool:  # what stat says of a path in a folder without x permission
        if self.parent == closed:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(self))
        return real_exists(self)

    monkeypatch.setattr(Path, "exists", exists)
    with pytest.raises(OutputError, match=r"closed/out: cannot be opened \(permission denied\); give --out"):
        _run(session, closed / "out")


def test_a_session_name_too_long_for_the_output_files_is_refused_before_any_work(tmp_path: Path) -> None:
    # 240 characters fit a folder's name, not ".<name>.mcap.<run>.partial" (255 bytes at most).
    session = build_session(tmp_path / ("s" * 240), frames=2)
    out = tmp_path / "out"
    with pytest.raises(OutputError, match=r"name is too long for its output files' names \(26\d bytes"):
        _run(session, out)
    assert not out.exists()
    shorter = session.rename(tmp_path / ("s" * 200))
    _run(shorter, out)
    assert (out / f"{shorter.name}.mcap").is_file()


class _FullDisk:
    """A file object that accepts ``room`` bytes and then raises ENOSPC, like a full disk."""

    def __init__(self, real: IO[bytes], room: int) -> None:
        self.real, self.room = real, room

    def write(self, data: Any) -> int:
        if len(data) > self.room:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.room -= len(data)
        return self.real.write(data)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.real, name)


@pytest.mark.parametrize("room", [0, 2000], ids=["at-open", "mid-run"])
def test_disk_full_is_a_clear_error_and_leaves_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, room: int
) -> None:
    session = build_session(tmp_path / "take", frames=6)
    real_open = outputs._open_partial
    monkeypatch.setattr(outputs, "_open_partial", lambda path: _FullDisk(real_open(path), room))
    out = tmp_path / "out"
    with pytest.raises(OutputError, match=r"disk full while writing the recordings; free space"):
        _run(session, out)
    assert not out.exists()  # the run created it, and removes it with the rest


class _FullDiskOnClose(_FullDisk):
    """A full disk's temporary file: it takes nothing, and fails its flush on close too."""

    def close(self) -> None:
        self.real.close()
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_disk_full_for_the_frame_log_too_is_a_clear_error_and_leaves_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The disk fills while a frame is written: the run's own temporary files fail as they
    # are closed, which must not stop the clean-up nor hide the first error.
    from pipeline.run import frame_log

    session = build_session(tmp_path / "take", frames=6)
    real_temporary = frame_log.tempfile.TemporaryFile
    monkeypatch.setattr(
        frame_log.tempfile, "TemporaryFile", lambda **kw: _FullDiskOnClose(real_temporary(**kw), 0)
    )
    out = tmp_path / "out"
    with pytest.raises(OutputError, match=r"disk full while writing the recordings; free space"):
        _run(session, out)
    assert not out.exists()


def test_disk_full_at_rename_leaves_no_half_output(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    session = build_session(tmp_path / "take", frames=2)

    def replace(src: Any, dst: Any) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(outputs.os, "replace", replace)
    out = tmp_path / "out"
    with pytest.raises(OutputError, match="disk full"):
        _run(session, out)
    assert not out.exists()


# --- a recording cut short --------------------------------------------------------------------


@pytest.fixture(scope="module")
def big_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real output with several zstd chunks: 40 frames of 30k points (360 kB each)."""
    base = tmp_path_factory.mktemp("rec")
    session = build_session(base / "rec", frames=40)
    _run(session, base / "out", frame_fn=StraightRod(points=30_000))
    return base / "out" / "rec.mcap"


def _frames_by_chunk(path: Path) -> list[tuple[int, int]]:
    """(end offset of the chunk record, frames whose metrics message it holds), in file order."""
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
        assert summary is not None
        f.seek(0)
        chunks = [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]
    indexes = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    metrics = next(c.id for c in summary.channels.values() if c.topic == METRICS_TOPIC)
    return [
        (
            index.chunk_start_offset + index.chunk_length,
            sum(isinstance(r, Message) and r.channel_id == metrics for r in breakup_chunk(chunk)),
        )
        for index, chunk in zip(indexes, chunks, strict=True)
    ]


def test_recording_cut_short_is_read_to_its_last_complete_chunk(
    big_recording: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    full = load_recording(big_recording)
    assert full.complete and len(full) == 40
    by_chunk = _frames_by_chunk(big_recording)
    assert len(by_chunk) >= 4, "the fixture should span several chunks"
    data = big_recording.read_bytes()
    ends = [end for end, _ in by_chunk]
    # Inside the first chunk, one byte short of a chunk's end, exactly at its end, in the middle
    # of a later chunk, and in the summary after the last chunk.
    cuts = [ends[0] // 2, ends[1] - 1, ends[1], (ends[2] + ends[3]) // 2, len(data) - 100]
    cut_path = tmp_path / "cut.mcap"
    for cut in cuts:
        cut_path.write_bytes(data[:cut])
        expected = sum(n for end, n in by_chunk if end <= cut)
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            rec = load_recording(cut_path)
        assert not rec.complete
        assert len(rec) == expected, f"cut at {cut}"
        # One warning, naming the last frame read (frame indices count from 0 here), or none.
        (warning,) = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        if expected:
            assert f"cut short after frame {expected - 1} (the run did not finish); read" in warning
        else:
            assert warning.endswith("cut short before its first frame (the run did not finish)")
        np.testing.assert_array_equal(rec.frame_indices, full.frame_indices[:expected])
        np.testing.assert_array_equal(rec.centerlines_m, full.centerlines_m[:expected])
        for got, want in zip(rec.points_m, full.points_m, strict=False):
            np.testing.assert_array_equal(got, want)


# --- SIGTERM to the command line --------------------------------------------------------------


def _hook_path(hook: Path) -> str:
    """PYTHONPATH for a run with ``hook``/sitecustomize.py: the hook, then this source tree,
    which sitecustomize imports from before ``-m`` puts the current folder on the path (an
    installed pipeline elsewhere, such as another work tree's, would be tested instead)."""
    return os.pathsep.join([str(hook), str(Path(__file__).resolve().parents[2])])


# Installed as sitecustomize in every Python process of the run (the CLI and its loky workers):
# the CLI's process_session gets a slow stand-in frame function, so that a short session lasts
# long enough to be stopped mid-run.
_SLOW_RUN_HOOK = """
import os, sys, time

def slow_frame(index, images, model):
    from pipeline.reconstruct.frame_result import FrameResult

    time.sleep(float(os.environ["FAULTS_FRAME_S"]))
    return FrameResult(index=index, status="empty", reason="slow stand-in"), None

# In the command line's process only: workers that imported the pipeline as they start would
# lengthen the moment when a signal finds them starting.
if os.environ.get("FAULTS_FRAME_S") and sys.orig_argv[1:3] == ["-m", "pipeline"]:
    import pipeline.run.runner as runner

    _process_session = runner.process_session

    def process_session(session, **options):
        return _process_session(session, **options, frame_fn=slow_frame)

    runner.process_session = process_session
"""


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=lambda s: s.name)
def test_a_signal_stops_the_run_and_keeps_previous_outputs(tmp_path: Path, sig: signal.Signals) -> None:
    session = build_session(tmp_path / "take", frames=60)
    out = tmp_path / "out"
    out.mkdir()
    previous = {"take.mcap": b"previous mcap", "take.rrd": b"previous rrd"}
    for name, data in previous.items():
        (out / name).write_bytes(data)
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(_SLOW_RUN_HOOK)
    env = {**os.environ, "PYTHONPATH": _hook_path(hook), "FAULTS_FRAME_S": "0.2"}
    command = [sys.executable, "-m", "pipeline", "process", str(session), "--out", str(out)]
    proc = subprocess.Popen(
        [*command, "--jobs", "2", "--no-images", "--force"],
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        preexec_fn=_as_from_a_terminal,
    )
    try:
        # Wait until the run is under way (its temporary MCAP exists), then a little more:
        # 60 frames of 0.2 s on 2 workers last 6 s, so the signal lands mid-run.
        for _ in range(1200):
            if any(p.name.endswith(".partial") for p in out.iterdir()):
                break
            time.sleep(0.05)
        time.sleep(1.0)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert {p.name: p.read_bytes() for p in out.iterdir()} == previous
    _assert_interrupted_in_one_line(proc, err)


def test_an_interrupted_wait_lets_the_call_finish_before_the_clean_up() -> None:
    # A signal while a Rerun stream opens its file (in _within's thread): the clean-up that
    # follows must not run before the file is open, or the file appears after it, complete.
    finished = threading.Event()

    def opening() -> None:
        time.sleep(0.5)
        finished.set()

    # A real SIGINT, which wakes the waiting main thread (SIGINT may be inherited ignored).
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        threading.Timer(0.1, os.kill, (os.getpid(), signal.SIGINT)).start()
        with pytest.raises(KeyboardInterrupt):
            outputs._within(5.0, opening)
        assert finished.is_set()
    finally:
        signal.signal(signal.SIGINT, previous)


def _start_slow_run(tmp_path: Path, backend: str, frame_s: float) -> tuple[subprocess.Popen[str], Path]:
    """The CLI in a group of its own on 60 frames of ``frame_s`` each (_SLOW_RUN_HOOK), two
    workers of ``backend``; returns once the run is under way (its temporary MCAP exists)."""
    session = build_session(tmp_path / "take", frames=60)
    out = tmp_path / "out"
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(_SLOW_RUN_HOOK)
    env = {**os.environ, "PYTHONPATH": _hook_path(hook), "FAULTS_FRAME_S": str(frame_s)}
    command = [sys.executable, "-m", "pipeline", "process", str(session), "--out", str(out), "--no-images"]
    proc = _popen_in_a_group([*command, "--jobs", "2", "--backend", backend], env)
    for _ in range(1200):
        if proc.poll() is not None or (out.exists() and any(p.suffix == ".partial" for p in out.iterdir())):
            break
        time.sleep(0.05)
    time.sleep(1.0)  # the workers are in their first ranges
    return proc, out


@pytest.mark.slow
# Each signal and each backend once: the parent treats SIGINT, SIGTERM and SIGHUP alike.
@pytest.mark.parametrize(
    ("sig", "backend"), [(signal.SIGINT, "loky"), (signal.SIGHUP, "dask")], ids=["SIGINT-loky", "SIGHUP-dask"]
)
def test_a_terminals_signal_to_every_process_ends_the_run_in_one_line(
    tmp_path: Path, backend: str, sig: signal.Signals
) -> None:
    proc, out = _start_slow_run(tmp_path, backend, 0.5)
    try:
        children = psutil.Process(proc.pid).children(recursive=True)
        _signal(proc, sig, "group")  # Ctrl-C, or the terminal closed: the workers get it too
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    # Not the workers' tracebacks, the resource tracker's KeyErrors nor distributed's logs.
    _assert_interrupted_in_one_line(proc, err)
    assert not out.exists()
    _assert_no_process_left(proc.pid, children)


@pytest.mark.slow
def test_dask_workers_exit_when_the_run_is_killed(tmp_path: Path) -> None:
    proc, _ = _start_slow_run(tmp_path, "dask", 30.0)  # each worker in a frame for 30 s
    try:
        children = psutil.Process(proc.pid).children(recursive=True)
        assert len([p for p in children if "spawn_main" in " ".join(p.cmdline())]) == 2, children
        proc.kill()  # SIGKILL, as the OOM killer ends a run: no clean-up of its own
        proc.wait(timeout=60)
    finally:
        proc.kill()
    _assert_no_process_left(proc.pid, children)


@pytest.mark.slow
def test_dask_run_keeps_stderr_to_the_projects_own_lines(tmp_path: Path) -> None:
    # The cameras as given: the test rig's rod, round at its base, is seen 2.7 mm from base_mm,
    # which "auto" would move the rig by, and say so.
    settings = {**COARSE, "calibration": {"refine": False}}
    session = build_session(tmp_path / "take", frames=6, settings=settings)
    command = [sys.executable, "-m", "pipeline", "process", str(session), "--out", str(tmp_path / "out")]
    done = subprocess.run(
        [*command, "--backend", "dask", "--jobs", "2"], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == EXIT_OK, done.stderr
    # No INFO lines from distributed as the cluster starts and stops, no warnings: a run
    # where every frame is ok has nothing to say on stderr.
    assert done.stderr == ""
    assert "6 processed, 6 ok" in done.stdout


_WORKER_LOG_LEVELS = """
import logging
from distributed import default_client
from pipeline.run.backends import parallel_backend
names = ("distributed", "distributed.client", "tornado", "tornado.application")
levels = lambda: sorted({logging.getLogger(n).getEffectiveLevel() for n in names})
with parallel_backend("dask", None, 2, None):
    print(levels(), *default_client().run(levels).values())
"""


@pytest.mark.slow
def test_dask_workers_keep_distributeds_logs_to_themselves(tmp_path: Path) -> None:
    # joblib opens a client in every worker: when the scheduler dies under it (the terminal
    # closed on the run), that client's error must not reach the run's stderr.
    env = {k: v for k, v in os.environ.items() if not k.startswith("DASK_")}
    done = subprocess.run(
        [sys.executable, "-c", _WORKER_LOG_LEVELS], capture_output=True, text=True, timeout=120, env=env
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == [f"[{logging.CRITICAL}]"] * 3


# --- two runs, dead runs, the pair of outputs ------------------------------------------------


def test_a_second_run_into_the_same_folder_is_refused_while_one_writes(tmp_path: Path) -> None:
    session = build_session(tmp_path / "take", frames=2)
    out = tmp_path / "out"
    writing = output_target.prepare_outputs(out, "take", False)  # a run under way holds the lock
    try:
        with pytest.raises(OutputError, match=r"^another run is writing take in .*out; wait for it"):
            _run(session, out)
        _run(build_session(tmp_path / "other", frames=2), out)  # another session is not held up
    finally:
        writing.release(failed=False)
    assert sorted(p.name for p in out.iterdir()) == ["other.mcap", "other.rrd"]
    assert _run(session, out).frames_ok == 2  # the lock is gone with its run
    assert _leftovers(out) == []


def test_temporary_files_of_dead_runs_are_removed_by_the_next_run(tmp_path: Path) -> None:
    session = build_session(tmp_path / "take", frames=2)
    out = tmp_path / "out"
    out.mkdir()
    dead = [".take.mcap.4242-0badf00d.partial", ".take.rrd.4242-0badf00d.partial", ".take.mcap.partial"]
    kept = [".other.mcap.4242-0badf00d.partial", ".takeover.mcap.1-2.partial"]  # not this session's
    for name in dead + kept:
        (out / name).write_bytes(b"half a recording")
    _run(session, out)
    assert _leftovers(out) == sorted(kept)
    assert load_recording(out / "take.mcap").complete


def test_a_failed_second_rename_puts_the_old_pair_back(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    session = build_session(tmp_path / "take", frames=3)
    out = tmp_path / "out"
    _run(session, out, frames=(0, 1))
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    real_replace = os.replace

    def replace(src: Any, dst: Any) -> None:
        if Path(dst).name == "take.rrd":  # the .mcap is in place already
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        real_replace(src, dst)

    monkeypatch.setattr(outputs.os, "replace", replace)
    with pytest.raises(OutputError, match=r"cannot write the recordings"):
        _run(session, out, force=True)
    # Neither a new .mcap beside the old .rrd, nor a temporary file: the old pair, whole.
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


# A run (of StraightRod, in one process) killed outright between its two renames: the new
# .mcap is in place, the .rrd is still under its temporary name.
_KILLED_BETWEEN_RENAMES = """
import os, signal, sys
from pathlib import Path

sys.path[:0] = ["tests", "tests/run"]
from pipeline.run import runner
from pipeline.session.folder import load_session
from test_faults import straight_rod

real_replace = os.replace

def replace(src, dst):
    if Path(dst).name == "take.rrd" and str(src).endswith(".partial"):
        os.kill(os.getpid(), signal.SIGKILL)
    real_replace(src, dst)

os.replace = replace
runner.process_session(
    load_session(Path(sys.argv[1])), out_dir=Path(sys.argv[2]), jobs=1, images=False,
    progress=False, frame_fn=straight_rod, force=True,
)
"""


def test_a_pair_split_by_a_kill_between_the_renames_is_told_and_put_together(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    session = build_session(tmp_path / "take", frames=3)
    out = tmp_path / "out"
    _run(session, out, frames=(0, 1))  # the old pair: one frame
    old_rrd = (out / "take.rrd").read_bytes()
    killed = subprocess.run(
        [sys.executable, "-c", _KILLED_BETWEEN_RENAMES, str(session), str(out)],
        cwd=Path(__file__).resolve().parents[2],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    assert (out / "take.rrd").read_bytes() == old_rrd  # split: the old .rrd ...
    (partial,) = out.glob(".take.rrd.*.partial")  # ... the new one beside it, complete
    new_rrd = partial.read_bytes()
    with caplog.at_level(logging.WARNING):
        assert len(load_recording(out / "take.mcap")) == 3  # ... and the new .mcap
    assert "take.mcap: the run that wrote it was killed while putting its outputs in place" in caplog.text
    assert "take.rrd may be an earlier run's" in caplog.text
    caplog.clear()
    # The next run of the session there puts the rest in place first (and then, without
    # --force, refuses to replace the pair).
    with caplog.at_level(logging.WARNING), pytest.raises(OutputError, match="already exists"):
        _run(session, out)
    assert "the run that wrote them was killed while putting them in place; put in place now" in caplog.text
    assert (out / "take.rrd").read_bytes() == new_rrd
    assert len(load_recording(out / "take.mcap")) == 3
    assert _leftovers(out) == []


def test_a_run_that_fails_removes_the_output_folder_it_created(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    session = build_session(tmp_path / "take", frames=2)
    monkeypatch.setenv("JOBLIB_TEMP_FOLDER", str(tmp_path / "no-such-folder"))
    with pytest.raises(SettingsError, match=r"JOBLIB_TEMP_FOLDER=.*no-such-folder: is not a writable folder"):
        _run(session, tmp_path / "new" / "out", jobs=2, backend="loky")
    assert not (tmp_path / "new").exists()


def test_jobs_beyond_the_cores_are_capped_with_a_note(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    session = build_session(tmp_path / "take", frames=2)
    cores = workers.available_cores()
    with caplog.at_level(logging.WARNING):
        summary = _run(session, tmp_path / "out", jobs=1000, backend="threading")
    assert summary.frames_ok == 2
    assert f"--jobs 1000 is more than the {cores} cores available; using {cores}" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        summary = _run(session, tmp_path / "out2", jobs=-100, backend="threading")
    assert summary.frames_ok == 2
    assert f"--jobs -100 leaves none of the {cores} cores; using 1" in caplog.text


def test_no_workers_at_all_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    from pipeline.cli import EXIT_BAD_INPUT, main

    with pytest.raises(SystemExit) as stopped:  # argparse's usage error
        main(["process", "anywhere", "--jobs", "0"])
    assert stopped.value.code == EXIT_BAD_INPUT
    assert "0 workers cannot run" in capsys.readouterr().err


# --- a signal at any moment -------------------------------------------------------------------

# As _SLOW_RUN_HOOK, for the moment the session is loaded: the CLI's load_session marks that it
# has begun and then takes a minute.
_SLOW_LOAD_HOOK = """
import os, sys, time

if os.environ.get("FAULTS_LOADING_MARK") and sys.orig_argv[1:3] == ["-m", "pipeline"]:
    import pipeline.session.folder

    def load_session(directory):
        open(os.environ["FAULTS_LOADING_MARK"], "w").close()
        # A minute of loading, as Python runs it: a signal that the kernel hands another of
        # the run's threads (the workers' manager, the watch) is taken by the main thread at
        # its next instruction. One C-level sleep of 60 s would hold it that long, which no
        # real loading does.
        for _ in range(600):
            time.sleep(0.1)

    pipeline.session.folder.load_session = load_session
"""


def _as_from_a_terminal() -> None:
    """In a child about to run the pipeline: SIGINT and SIGHUP as a terminal's job has them.
    A run started from a background job inherits SIGINT ignored, one under ``nohup`` SIGHUP
    ignored, and honours that (:mod:`pipeline.run.interrupts`): the test suite may itself
    run under either."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGHUP, signal.SIG_DFL)


def _popen_in_a_group(command: list[str], env: dict[str, str]) -> subprocess.Popen[str]:
    """Start ``command`` as a terminal starts a job: a process group of its own (which
    :func:`_signal` can signal whole, as Ctrl-C does), SIGINT and SIGHUP not ignored
    (:func:`_as_from_a_terminal`)."""
    return subprocess.Popen(
        command,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        start_new_session=True,
        preexec_fn=_as_from_a_terminal,
    )


def _signal(proc: subprocess.Popen[str], sig: signal.Signals, to: str) -> None:
    """``sig`` to the process alone (``kill PID``), or to its whole group (a terminal's Ctrl-C
    or hang-up, which reach the workers too)."""
    if to == "group":
        os.killpg(proc.pid, sig)
    else:
        proc.send_signal(sig)


# A signal to the run's process alone, or to its process group as a terminal sends it.
_SIGNALS_AND_TARGETS = [
    (signal.SIGINT, "process"),
    (signal.SIGTERM, "process"),
    (signal.SIGHUP, "group"),
]


@pytest.mark.slow
@pytest.mark.parametrize(("sig", "to"), _SIGNALS_AND_TARGETS, ids=lambda v: getattr(v, "name", v))
def test_a_signal_while_loading_ends_the_run_cleanly(tmp_path: Path, sig: signal.Signals, to: str) -> None:
    session = build_session(tmp_path / "take", frames=2)
    out = tmp_path / "new" / "out"
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(_SLOW_LOAD_HOOK)
    mark = tmp_path / "loading"
    env = {**os.environ, "PYTHONPATH": _hook_path(hook), "FAULTS_LOADING_MARK": str(mark)}
    command = [sys.executable, "-m", "pipeline", "process", str(session), "--out", str(out), "--jobs", "2"]
    proc = _popen_in_a_group(command, env)
    try:
        for _ in range(1200):
            if mark.exists() or proc.poll() is not None:
                break
            time.sleep(0.05)
        # The workers started ahead, still starting: a terminal's signal finds them importing.
        children = psutil.Process(proc.pid).children(recursive=True)
        _signal(proc, sig, to)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert err.strip().splitlines() == ["interrupted; nothing written"]
    assert not (tmp_path / "new").exists()
    _, alive = psutil.wait_procs(children, timeout=30)
    for p in alive:
        p.kill()
    assert not alive


def test_a_rerun_writer_that_does_not_finish_is_an_error_not_a_hang(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import rerun as rr

    session = build_session(tmp_path / "take", frames=2)
    bounds: list[float] = []

    def stuck_flush(self: Any, *, timeout_sec: float = 1e38) -> None:
        bounds.append(timeout_sec)
        raise RuntimeError("Flush timed out - not all log messages were sent")  # Rerun's words

    monkeypatch.setattr(rr.RecordingStream, "flush", stuck_flush)
    out = tmp_path / "out"
    with pytest.raises(OutputError, match=r"take\.rrd: the Rerun recording was not written within 60 s"):
        _run(session, out)
    assert bounds == [outputs.FLUSH_TIMEOUT_S]  # the wait had a bound
    assert not out.exists()


def test_a_rerun_writer_that_stops_on_a_full_disk_is_named_as_such(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import rerun as rr

    session = build_session(tmp_path / "take", frames=2)

    def stopped_flush(self: Any, *, timeout_sec: float = 1e38) -> None:
        raise RuntimeError("File-writer thread shut down prematurely")  # Rerun's words (was exit 3)

    monkeypatch.setattr(rr.RecordingStream, "flush", stopped_flush)
    out = tmp_path / "out"
    with pytest.raises(OutputError, match=r"take\.rrd: the Rerun recording could not be written completely"):
        _run(session, out)
    assert not out.exists()


def test_a_rerun_writer_stuck_on_a_full_disk_does_not_hold_up_another_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import rerun as rr

    session = build_session(tmp_path / "take", frames=6)
    # The MCAP meets the full disk first; Rerun's writer is stuck on it, and closing its
    # stream waits for the writer (for good, on a real full disk: the run hung, deaf to Ctrl-C).
    real_open = outputs._open_partial
    monkeypatch.setattr(outputs, "_open_partial", lambda path: _FullDisk(real_open(path), 2000))
    stuck = threading.Event()
    monkeypatch.setattr(rr.RecordingStream, "disconnect", lambda self: stuck.wait(60))
    left_to_exit: list[bool] = []
    monkeypatch.setattr(rr, "unregister_shutdown", lambda: left_to_exit.append(True))
    monkeypatch.setattr(outputs, "RERUN_WAIT_S", 0.5)
    out = tmp_path / "out"
    try:
        with pytest.raises(OutputError, match=r"disk full while writing the recordings; free space"):
            _run(session, out)
    finally:
        stuck.set()
    assert left_to_exit == [True]  # nor does Rerun's own handler hold up the exit
    assert not out.exists()


def test_a_rerun_file_that_cannot_be_started_is_an_error_not_a_hang(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import rerun as rr

    session = build_session(tmp_path / "take", frames=2)
    stuck = threading.Event()
    # On a full disk, Rerun's save() (which writes the layout first) waited for good.
    monkeypatch.setattr(rr.RecordingStream, "save", lambda self, path, **options: stuck.wait(60))
    left_to_exit: list[bool] = []
    monkeypatch.setattr(rr, "unregister_shutdown", lambda: left_to_exit.append(True))
    monkeypatch.setattr(outputs, "RERUN_WAIT_S", 0.5)
    out = tmp_path / "out"
    expected = r"take\.rrd: the Rerun recording was not started within 0\.5 s \(disk full"
    try:
        with pytest.raises(OutputError, match=expected):
            _run(session, out)
    finally:
        stuck.set()
    assert left_to_exit == [True]
    assert not out.exists()


def test_a_recording_cut_in_its_smoothed_curves_has_none(big_recording: Path, tmp_path: Path) -> None:
    data = big_recording.read_bytes()
    by_chunk = _frames_by_chunk(big_recording)
    cut_path = tmp_path / "cut.mcap"
    cut_path.write_bytes(data[: by_chunk[-1][0]])  # every frame's chunk, not the footer
    rec = load_recording(cut_path)
    assert not rec.complete and len(rec) == 40
    assert rec.smoothed_centerlines_m is None  # as documented, not a partly NaN array


def test_loading_the_rrd_says_to_pass_the_mcap(big_recording: Path) -> None:
    with pytest.raises(
        RecordingError, match=r"rec\.rrd: is a Rerun recording .*read the \.mcap written beside it"
    ):
        load_recording(big_recording.with_suffix(".rrd"))


# --- a worker killed while handing back its results ---------------------------------------

# As _SLOW_RUN_HOOK: the CLI's runs get a frame function whose worker, on frame 5, sends half
# of its range's results and dies (the OOM killer at the wrong moment: a message cut short in
# the pipe, which loky's manager thread then waits on for good). The first time only, unless
# FAULTS_HANDBACK_ALWAYS is set; the watch's bound is FAULTS_HANDBACK_S.
_DIES_HANDING_BACK_HOOK = """
import os, struct, sys, time

def dies_handing_back(index, images, model):
    from multiprocessing import connection
    from pipeline.reconstruct.frame_result import FrameResult

    mark = os.environ["FAULTS_HANDBACK_MARK"]
    if index == 5 and (os.environ.get("FAULTS_HANDBACK_ALWAYS") or not os.path.exists(mark)):
        def half(self, buf):
            data = bytes(buf)
            self._send(struct.pack("!i", len(data)) + data[: len(data) // 2])
            open(mark, "w").close()
            os._exit(9)

        connection.Connection._send_bytes = half
    time.sleep(float(os.environ.get("FAULTS_FRAME_S", "0")))
    return FrameResult(index=index, status="empty", reason="stand-in"), None

if os.environ.get("FAULTS_HANDBACK_S") and sys.orig_argv[1:3] == ["-m", "pipeline"]:
    import pipeline.run.runner as runner
    import pipeline.run.workers as workers

    workers.HANDBACK_TIMEOUT_S = float(os.environ["FAULTS_HANDBACK_S"])
    _process_session = runner.process_session

    def process_session(session, **options):
        return _process_session(session, **options, frame_fn=dies_handing_back)

    runner.process_session = process_session
"""


def _start_dying_run(tmp_path: Path, frames: int, **env: str) -> tuple[subprocess.Popen[str], Path, Path]:
    """The CLI on a session of ``frames`` with _DIES_HANDING_BACK_HOOK; (process, out, mark)."""
    session = build_session(tmp_path / "take", frames=frames)
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(_DIES_HANDING_BACK_HOOK)
    out, mark = tmp_path / "out", tmp_path / "died"
    variables = {"PYTHONPATH": _hook_path(hook), "FAULTS_HANDBACK_S": "2", "FAULTS_HANDBACK_MARK": str(mark)}
    command = [sys.executable, "-m", "pipeline", "process", str(session), "--out", str(out), "--no-images"]
    proc = subprocess.Popen(
        [*command, "--jobs", "2"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, **variables, **env},
        preexec_fn=_as_from_a_terminal,
    )
    return proc, out, mark


def _assert_interrupted_in_one_line(proc: subprocess.Popen[str], err: str) -> None:
    """Exit status 130 and one line on stderr: what was done, and that nothing is left behind."""
    assert proc.returncode == 130, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert re.fullmatch(
        r"interrupted with \d+ of 60 frames written; temporary files removed, existing outputs untouched",
        lines[0],
    )


def _assert_no_process_left(pid: int, children: list[psutil.Process]) -> None:
    # Generous: the workers are killed as the run ends; this only guards against them staying.
    _, alive = psutil.wait_procs(children, timeout=30)
    for p in alive:
        p.kill()
    assert not alive, [p.cmdline() for p in alive]
    assert not [p for p in Path("/dev/shm").glob(f"pipeline-model-{pid}-*")]


@pytest.mark.slow
def test_a_worker_killed_while_handing_back_its_results_is_retried_not_waited_for(tmp_path: Path) -> None:
    frames = 2 * runner.MIN_RANGE_FRAMES
    proc, out, mark = _start_dying_run(tmp_path, frames)
    children: list[psutil.Process] = []
    try:
        while proc.poll() is None and not mark.exists():
            with contextlib.suppress(psutil.Error):
                children = psutil.Process(proc.pid).children(recursive=True)
            time.sleep(0.05)
        # Without a bound the run would wait here for good; 2 s and a fresh pool are enough.
        summary, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert mark.exists(), "the worker should have died handing back its results"
    assert proc.returncode == 1, err  # every frame is "empty" (the stand-in), none failed
    assert re.search(
        r"a worker failed on frames 0 onwards \(a worker died while handing back its results\); "
        r"retrying in a fresh pool",
        err,
    ), err
    assert f"{frames} processed, 0 ok, {frames} empty, 0 failed" in summary  # the range retried whole
    assert load_recording(out / "take.mcap").complete and len(load_recording(out / "take.mcap")) == frames
    _assert_no_process_left(proc.pid, children)


@pytest.mark.slow
def test_a_signal_while_the_pool_waits_on_a_dead_worker_ends_the_run(tmp_path: Path) -> None:
    sig = signal.SIGINT
    # The watch's bound is long (60 s): the signal, not the watch, has to end the wait.
    proc, out, mark = _start_dying_run(
        tmp_path, 60, FAULTS_HANDBACK_S="60", FAULTS_HANDBACK_ALWAYS="1", FAULTS_FRAME_S="0.1"
    )
    children: list[psutil.Process] = []
    try:
        while proc.poll() is None and not mark.exists():
            with contextlib.suppress(psutil.Error):
                children = psutil.Process(proc.pid).children(recursive=True)
            time.sleep(0.05)
        time.sleep(1.0)  # the pool is stuck now
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    _assert_interrupted_in_one_line(proc, err)
    assert not out.exists()
    _assert_no_process_left(proc.pid, children)
