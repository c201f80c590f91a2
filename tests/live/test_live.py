"""pipeline live: frame matching, the hand-off queue, sources, and whole runs.

Whole runs replay a short rendered session (its videos played at 30 fps as if they
were cameras), stream it over UDP on 127.0.0.1, stream to a Rerun gRPC server the
test starts, and are stopped by a signal; each checks the recordings it leaves.
"""

from __future__ import annotations

import base64
import contextlib
import dataclasses
import io
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tomli_w

import pipeline
from pipeline.errors import OutputError, SessionError, SettingsError
from pipeline.live import run as live_run
from pipeline.live.capture import CameraReader
from pipeline.live.handoff import DroppingQueue
from pipeline.live.restarts import RestartWorker
from pipeline.live.run import CameraSummary, LiveSummary, run_live
from pipeline.live.sources import V4L2_FORMAT, Source, open_rig, parse_source
from pipeline.live.stream import check_viewer, grpc_url, parse_host_port
from pipeline.live.sync import (
    MAX_WAITING_FRAMES,
    CapturedFrame,
    FrameMatcher,
    FrameSet,
    half_period_ns,
    head_action,
)
from pipeline.measure.bench.live import mean_gap_mm
from pipeline.session.settings import settings_from_dict

RERUN = Path(sys.executable).parent / "rerun"  # the CLI installed with rerun-sdk
RERUN_ENV = {**os.environ, "RERUN_ANALYTICS": "off"}
FRAMES = 20  # a short session, within one tracking segment
PERIOD_NS = 33_333_333  # 30 fps
TOLERANCE_NS = PERIOD_NS // 2


def _frame(camera: int, arrived_ns: int) -> CapturedFrame:
    return CapturedFrame(camera, arrived_ns, np.full((2, 2), camera, np.uint8))


# --- matching frames into frame-sets -----------------------------------------------------------


def test_heads_within_half_a_period_form_a_set_else_the_earliest_goes() -> None:
    assert head_action([100, 110, 105], tolerance_ns=10) is None
    assert head_action([100, 111, 105], tolerance_ns=10) == 0
    assert head_action([130, 100, 125], tolerance_ns=10) == 1


def test_jittered_cameras_are_matched_frame_for_frame() -> None:
    matcher = FrameMatcher(3, TOLERANCE_NS)
    rng = np.random.default_rng(0)
    sets: list[FrameSet] = []
    for k in range(10):
        # Each camera's frame k arrives within 5 ms of the tick, in any order.
        for camera in rng.permutation(3):
            jitter = int(rng.integers(-5_000_000, 5_000_000))
            sets += matcher.add(_frame(int(camera), k * PERIOD_NS + jitter))
    assert [s.index for s in sets] == list(range(10))
    for k, frame_set in enumerate(sets):
        assert [int(im[0, 0]) for im in frame_set.images] == [0, 1, 2]  # camera order
        assert all(abs(t - k * PERIOD_NS) <= 5_000_000 for t in frame_set.arrived_ns)
    assert matcher.unmatched == [0, 0, 0]


@pytest.mark.parametrize("other_fps", [15, 60])
def test_a_camera_at_another_rate_is_matched_with_the_nearest_frames(other_fps: int) -> None:
    # Two cameras at 30 fps and one at half or twice that, each frame 2 ms off its tick: the
    # oldest frames within the tolerance are often a period apart while the simultaneous
    # frame waits behind one of them.
    matcher = FrameMatcher(3, half_period_ns(min(30, other_fps)))
    rng = np.random.default_rng(1)
    events = [(int(k * 1e9 / 30 + rng.normal(0, 2e6)), c) for k in range(120) for c in (0, 1)]
    events += [(int(k * 1e9 / other_fps + rng.normal(0, 2e6)), 2) for k in range(120 * other_fps // 30)]
    sets: list[FrameSet] = []
    for arrived_ns, camera in sorted(events):
        sets += matcher.add(_frame(camera, arrived_ns))
    assert len(sets) >= 119 * min(30, other_fps) // 30
    apart_ms = [abs(s.arrived_ns[2] - s.arrived_ns[0]) / 1e6 for s in sets]
    # Paired oldest-first, a third of the sets would be a period apart.
    assert sum(apart > 10 for apart in apart_ms) <= len(sets) // 100


def test_a_frame_one_camera_lost_drops_the_others_frames_of_that_tick() -> None:
    matcher = FrameMatcher(3, TOLERANCE_NS)
    sets: list[FrameSet] = []
    for k in range(4):
        for camera in range(3):
            if (k, camera) != (1, 2):  # camera 2 loses its frame 1
                sets += matcher.add(_frame(camera, k * PERIOD_NS))
    assert [s.arrived_ns for s in sets] == [(k * PERIOD_NS,) * 3 for k in (0, 2, 3)]
    assert matcher.unmatched == [1, 1, 0]


def test_a_stalled_camera_keeps_the_others_waiting_frames_bounded() -> None:
    matcher = FrameMatcher(2, TOLERANCE_NS)
    for k in range(50):
        assert matcher.add(_frame(0, k * PERIOD_NS)) == []
    assert matcher.unmatched == [50 - MAX_WAITING_FRAMES, 0]
    # Stopped now, the frames still waiting for it are unmatched too: every frame is counted.
    assert matcher.unmatched_at_end == [50, 0]
    # When the other camera comes back, the waiting frames it cannot match are dropped too.
    (frame_set,) = matcher.add(_frame(1, 49 * PERIOD_NS))
    assert frame_set.arrived_ns == (49 * PERIOD_NS, 49 * PERIOD_NS)
    assert frame_set.last_arrival_ns == 49 * PERIOD_NS


def test_the_queue_drops_its_oldest_set_when_full_and_counts_it() -> None:
    queue = DroppingQueue(capacity=2, settling=2)
    for k in range(5):
        queue.put(FrameSet(k, (), (k,)))
    assert queue.dropped == 3
    got = [queue.get(0.0) for _ in range(3)]
    assert [s.index if s is not None else None for s in got] == [3, 4, None]


def test_the_queue_holds_more_until_the_run_has_settled() -> None:
    # The first frame starts its track from the hull, longer than a frame period: the sets
    # that come meanwhile wait, up to ``settling``; once the run has settled and taken them
    # down below the capacity, the queue holds two again, and stays so.
    queue = DroppingQueue(capacity=2, settling=6)
    for k in range(8):
        queue.put(FrameSet(k, (), (k,)))
    assert queue.dropped == 2 and queue.capacity == 6
    first = queue.get(0.0)
    assert first is not None and first.index == 2
    queue.settle()  # the first frame is out, but 5 sets still wait: not yet
    assert queue.capacity == 6
    for _ in range(4):
        queue.get(0.0)
        queue.settle()
    assert len(queue) == 1 and queue.capacity == 2
    for k in range(8, 12):
        queue.put(FrameSet(k, (), (k,)))
    queue.settle()  # falling behind later does not bring the larger queue back
    assert queue.dropped == 5 and queue.capacity == 2 and len(queue) == 2


# --- sources, settings, addresses --------------------------------------------------------------


def test_sources_devices_indices_and_urls() -> None:
    assert parse_source("cam0", "0") == Source("cam0", "/dev/video0", V4L2_FORMAT)
    assert parse_source("cam1", "/dev/video3") == Source("cam1", "/dev/video3", V4L2_FORMAT)
    by_id = "/dev/v4l/by-id/usb-rig-cam1-video-index0"
    assert parse_source("cam1", by_id) == Source("cam1", by_id, V4L2_FORMAT)
    assert parse_source("cam2", "udp://127.0.0.1:5002") == Source("cam2", "udp://127.0.0.1:5002")


def test_live_table_takes_device_indices_and_refuses_other_values() -> None:
    settings = settings_from_dict({"live": {"cam0": 2, "cam1": "rtsp://rig/1"}})
    assert settings.live.sources == (("cam0", "2"), ("cam1", "rtsp://rig/1"))
    with pytest.raises(SettingsError, match=r"\[live\] cam0 must be a device path.*got 1.5"):
        settings_from_dict({"live": {"cam0": 1.5}})


def test_two_names_for_one_source_are_one_source(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from pipeline.live.sources import source_identity

    # A device and a link to it (as udev's /dev/v4l/by-id/... links are): one device number.
    link = tmp_path / "usb-rig-cam0-video-index0"
    link.symlink_to("/dev/null")
    assert (
        source_identity(str(link)) == source_identity("/dev/null") == ("device", os.stat("/dev/null").st_rdev)
    )
    # A named pipe by its relative and its absolute path; two pipes are two sources.
    os.mkfifo(tmp_path / "cam1.pipe")
    os.mkfifo(tmp_path / "cam2.pipe")
    monkeypatch.chdir(tmp_path)
    assert source_identity("cam1.pipe") == source_identity(str(tmp_path / "cam1.pipe"))
    assert source_identity("cam1.pipe") != source_identity("cam2.pipe")
    # Paths not there yet (a camera unplugged) by where they lead; URLs by their text.
    assert source_identity("./gone/../cam3") == source_identity(str(tmp_path / "cam3"))
    assert source_identity("udp://127.0.0.1:5002") != source_identity("udp://127.0.0.1:5003")


def _rig(directory: Path, session: Path, live: dict[str, str | int] | None) -> Path:
    """A rig directory: the session's calibration and settings, with ``[live]``."""
    import tomllib

    directory.mkdir()
    (directory / "calibration.toml").write_bytes((session / "calibration.toml").read_bytes())
    settings = tomllib.loads((session / "session.toml").read_text())
    if live is not None:
        settings["live"] = live
    (directory / "session.toml").write_text(tomli_w.dumps(settings))
    return directory


def test_live_paths_are_taken_from_the_rigs_folder_with_home_expanded(
    tmp_path: Path, session: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    rig = _rig(tmp_path / "rig", session, {"cam0": "cam0.pipe", "cam1": "~/cam1.pipe", "cam2": 2})
    os.mkfifo(rig / "cam0.pipe")
    os.mkfifo(home / "cam1.pipe")
    monkeypatch.chdir(tmp_path)  # not the rig's folder
    _, sources = open_rig(rig, None)
    assert [s.url for s in sources] == [str(rig / "cam0.pipe"), str(home / "cam1.pipe"), "/dev/video2"]


def test_a_replay_of_another_rigs_session_is_warned_of(
    tmp_path: Path, session: Path, caplog: pytest.LogCaptureFixture
) -> None:
    import tomllib

    rig = _rig(tmp_path / "rig", session, None)
    with caplog.at_level(logging.WARNING):
        open_rig(rig, session)  # the rig's own session: said nothing
    assert caplog.text == ""
    # The rig's first camera turned by a degree: its sessions are no longer this rig's.
    doc = tomllib.loads((rig / "calibration.toml").read_text())
    first = next(iter(k for k in doc if k != "metadata"))
    doc[first]["rotation"] = [v + 0.02 for v in doc[first]["rotation"]]
    (rig / "calibration.toml").write_text(tomli_w.dumps(doc))
    with caplog.at_level(logging.WARNING):
        open_rig(rig, session)
    assert f"{session}: camera 'cam0' of its calibration.toml sees the workspace up to" in caplog.text
    assert "replay a session filmed with this rig" in caplog.text


def test_a_rig_whose_live_table_misses_or_misnames_a_camera_is_refused(tmp_path: Path, session: Path) -> None:
    rig = _rig(tmp_path / "a", session, {"cam0": 0, "cam1": 1})
    with pytest.raises(SettingsError, match=r"\[live\] gives no source for camera 'cam2'; add cam2 ="):
        open_rig(rig, None)
    rig = _rig(tmp_path / "b", session, {"cam0": 0, "cam1": 1, "cam2": 2, "cam9": 3})
    with pytest.raises(SettingsError, match=r"\[live\] names camera 'cam9', which calibration.toml"):
        open_rig(rig, None)
    rig = _rig(tmp_path / "c", session, None)
    with pytest.raises(SettingsError, match=r"no \[live\] table; add one naming each camera's source"):
        open_rig(rig, None)
    # A folder and a file are not cameras (a file is read as fast as it decodes).
    rig = _rig(tmp_path / "e", session, {"cam0": str(tmp_path), "cam1": 1, "cam2": 2})
    with pytest.raises(SettingsError, match=r"\[live\] cam0 = '.*' is a folder; give a device"):
        open_rig(rig, None)
    video = str(session / "cam1.mp4")
    rig = _rig(tmp_path / "f", session, {"cam0": 0, "cam1": video, "cam2": 2})
    with pytest.raises(
        SettingsError, match=r"\[live\] cam1 = .*cam1.mp4. is a file, not a camera .*--replay"
    ):
        open_rig(rig, None)
    # So is one named by FFmpeg's file: URL, and that URL and the path are one source.
    for n, url in enumerate((f"file://{video}", f"file:{video}")):
        rig = _rig(tmp_path / f"f{n}", session, {"cam0": 0, "cam1": url, "cam2": 2})
        with pytest.raises(SettingsError, match=r"\[live\] cam1 = 'file:.*cam1.mp4. is a file, not a camera"):
            open_rig(rig, None)
    rig = _rig(tmp_path / "f2", session, {"cam0": "file:///dev/null", "cam1": 1, "cam2": "/dev/null"})
    with pytest.raises(
        SettingsError, match=r"cameras 'cam0' and 'cam2' the same source \(file:///dev/null and"
    ):
        open_rig(rig, None)
    # Two names of one device (a link to it, as udev's by-id links are) are one source.
    link = tmp_path / "by-id-cam0"
    link.symlink_to("/dev/null")
    rig = _rig(tmp_path / "g", session, {"cam0": "/dev/null", "cam1": 1, "cam2": str(link)})
    with pytest.raises(
        SettingsError,
        match=r"cameras 'cam0' and 'cam2' the same source \(/dev/null and .*by-id-cam0, one device\)",
    ):
        open_rig(rig, None)
    # A device index and its path are the same device.
    rig = _rig(tmp_path / "d", session, {"cam0": 0, "cam1": "udp://127.0.0.1:5002", "cam2": "/dev/video0"})
    with pytest.raises(
        SettingsError, match=r"\[live\] gives cameras 'cam0' and 'cam2' the same source \(/dev/video0\)"
    ):
        open_rig(rig, None)
    # A UDP port is received on once, whatever the address is spelled (the second camera's
    # reader found it in use, and the run wrote nothing); multicast groups share ports.
    for n, other in enumerate(("udp://localhost:5002", "udp://0.0.0.0:5002?fifo_size=100", "UDP://@:5002")):
        rig = _rig(tmp_path / f"u{n}", session, {"cam0": "udp://127.0.0.1:5002", "cam1": 1, "cam2": other})
        with pytest.raises(
            SettingsError,
            match=r"cameras 'cam0' and 'cam2' the same source \(udp://127.0.0.1:5002 and .*one udp port",
        ):
            open_rig(rig, None)
    groups = {"cam0": "udp://239.0.0.1:5002", "cam1": "udp://239.0.0.2:5002", "cam2": "udp://127.0.0.1:5003"}
    assert [s.url for s in open_rig(_rig(tmp_path / "m", session, groups), None)[1]] == list(groups.values())


def test_viewer_and_foxglove_addresses() -> None:
    assert grpc_url("9876") == "rerun+http://127.0.0.1:9876/proxy"
    assert grpc_url("rig:9000") == "rerun+http://rig:9000/proxy"
    assert grpc_url("rerun+http://10.0.0.2:9876/proxy") == "rerun+http://10.0.0.2:9876/proxy"
    with pytest.raises(SettingsError, match="not a Rerun viewer address"):
        grpc_url("http://rig")
    for port in ("99999", "127.0.0.1:99999", "rig:x"):
        with pytest.raises(SettingsError, match=f"--viewer connect '{port}': not a Rerun viewer address"):
            grpc_url(port)
    assert parse_host_port("0.0.0.0:8766") == ("0.0.0.0", 8766)
    assert parse_host_port("8766") == ("127.0.0.1", 8766)
    assert parse_host_port("[::1]:8766") == ("::1", 8766)  # an IPv6 host, bracketed as in URLs
    with pytest.raises(SettingsError, match="expected HOST:PORT"):
        parse_host_port("rig:port")


def test_spawn_falls_back_to_no_viewer_where_no_window_can_open(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    from pipeline.live import stream

    monkeypatch.setattr(stream.sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert stream.viewer_from_choice([]) is None and stream.viewer_from_choice(["none"]) is None
    assert "no display to open a Rerun viewer on" in caplog.text
    with pytest.raises(SettingsError, match="expected spawn, none, or connect ADDRESS"):
        stream.viewer_from_choice(["connect"])


# --- whole runs --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from pipeline.synth import render_session

    directory = tmp_path_factory.mktemp("live") / "take"
    render_session(directory, frames=FRAMES, progress=False, jobs=1)
    return directory


@pytest.fixture(scope="module")
def processed(session: Path, tmp_path_factory: pytest.TempPathFactory) -> pipeline.record.load.Recording:
    """The session through ``process``, for comparison."""
    out = tmp_path_factory.mktemp("processed")
    pipeline.process_session(
        pipeline.load_session(session), out_dir=out, jobs=1, backend="threading", progress=False
    )
    return pipeline.load_recording(out / "take.mcap")


def test_the_restart_worker_starts_a_track_and_follows_it_as_this_process_would(session: Path) -> None:
    from pipeline.reconstruct.frame import reconstruct_with_silhouettes
    from pipeline.reconstruct.frame_task import decode_frames
    from pipeline.reconstruct.model import build_model

    model = build_model(pipeline.load_session(session))
    frames = decode_frames(pipeline.load_session(session).video_paths, [5, 6, 7, 8])
    before, _ = reconstruct_with_silhouettes(*frames[0], model)
    here = [before]
    for index, images in frames[1:]:
        here.append(reconstruct_with_silhouettes(index, images, model, here)[0])
    worker = RestartWorker(model)
    try:
        worker.wait_ready(60.0)
        assert worker.available and not worker.under_way
        assert worker.caught_up(lambda: True) is None  # nothing started
        assert worker.start(*frames[1], [before])
        assert not worker.start(*frames[1], [before])  # one start at a time
        for index, images in frames[2:]:
            worker.follow(index, images)
        # Not done at once (a start takes > 0.1 s), nor nearly (the start is not done).
        assert worker.behind >= 1 and not worker.nearly_caught_up
        assert worker.caught_up(lambda: False) is None
        deadline = time.monotonic() + 60.0
        track = worker.caught_up(lambda: time.monotonic() < deadline)
        assert not worker.under_way and worker.behind == 0  # taken over
    finally:
        worker.close()
    assert track is not None and [r.index for r in track] == [5, 6, 7, 8]
    for a, b in zip(here, track, strict=True):
        assert a.centerline_mm is not None and b.centerline_mm is not None
        np.testing.assert_array_equal(a.centerline_mm, b.centerline_mm)


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads a process's signal mask in /proc")
def test_the_restart_worker_leaves_ctrl_c_and_a_hang_up_to_the_run() -> None:
    # A terminal's Ctrl-C reaches every process of its group: a worker still importing as it
    # starts would print a traceback under the run's one line. It starts with them blocked.
    worker = RestartWorker({})
    try:
        worker.wait_ready(60.0)
        (pid,) = [process.pid for process in worker._pool._processes.values()]
        status = Path(f"/proc/{pid}/status").read_text()
        blocked = int(next(line for line in status.splitlines() if line.startswith("SigBlk:")).split()[1], 16)
    finally:
        worker.close()
    for sig in (signal.SIGINT, signal.SIGHUP):
        assert blocked & (1 << (sig - 1)), f"{sig.name} is not blocked in the restart worker"


# A run killed outright (SIGKILL, the OOM killer) with its restart worker started.
_KILLED_RUN = """
import os, signal
from pipeline.live.restarts import RestartWorker
worker = RestartWorker({})
worker.wait_ready(60.0)
print(" ".join(str(p.pid) for p in worker._pool._processes.values()), flush=True)
os.kill(os.getpid(), signal.SIGKILL)
"""


@pytest.mark.slow
def test_the_restart_worker_exits_when_the_run_is_killed() -> None:
    # Left behind, it held the run's stdout and stderr open: a pipe reading them never ended.
    import psutil

    proc = subprocess.run([sys.executable, "-c", _KILLED_RUN], capture_output=True, text=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    (pid,) = [int(pid) for pid in proc.stdout.split()]
    orphan = [psutil.Process(pid)] if psutil.pid_exists(pid) else []
    _, alive = psutil.wait_procs(orphan, timeout=30)  # it notices within about a second
    for p in alive:
        p.kill()
    assert not alive


def test_a_restart_worker_that_ends_as_it_starts_does_not_hold_the_run() -> None:
    # A terminal's SIGTERM to the whole group can end the worker before it has read what it
    # is spawned with. The run must not wait for it: the model, far larger than a pipe
    # holds, is not written to the worker's pipe. Spawned as /bin/false, it ends at once.
    import multiprocessing.spawn

    model = {"tables": np.zeros(8_000_000)}  # 64 MB
    made: list[RestartWorker] = []
    python = multiprocessing.spawn.get_executable()
    multiprocessing.spawn.set_executable("/bin/false")
    try:
        starting = threading.Thread(target=lambda: made.append(RestartWorker(model)), daemon=True)
        starting.start()
        starting.join(30.0)
    finally:
        multiprocessing.spawn.set_executable(python)
    assert not starting.is_alive(), "the run waits on a worker that has ended"
    (worker,) = made
    try:
        worker.wait_ready(30.0)
        assert not worker.available  # the run goes on without it
    finally:
        worker.close()


def _verify_rrd(path: Path) -> None:
    verify = subprocess.run(
        [str(RERUN), "rrd", "verify", str(path)], env=RERUN_ENV, capture_output=True, text=True
    )
    assert verify.returncode == 0, verify.stderr


def test_a_replay_of_swapped_videos_is_refused_naming_them(session: Path, tmp_path: Path) -> None:
    # As process refuses them: the videos in other cameras' places, named before any frame.
    swapped = tmp_path / "take"
    swapped.mkdir()
    for item in session.iterdir():
        (swapped / {"cam1.mp4": "cam2.mp4", "cam2.mp4": "cam1.mp4"}.get(item.name, item.name)).symlink_to(
            item
        )
    rig, sources = open_rig(None, swapped)
    with pytest.raises(SessionError, match=r"cam2\.mp4 looks like cam1's view"):
        run_live(rig, sources, out_dir=tmp_path / "out", duration_s=5.0)
    assert not (tmp_path / "out").exists()


def test_a_replay_damaged_part_way_keeps_the_frames_before_and_says_why(
    session: Path, tmp_path: Path
) -> None:
    from pipeline.live.capture import CameraReader

    video = tmp_path / "cam1.mp4"
    data = bytearray((session / "cam1.mp4").read_bytes())
    at = int(0.6 * len(data))
    data[at : at + 2000] = np.random.default_rng(0).bytes(2000)
    video.write_bytes(bytes(data))
    delivered: list[CapturedFrame] = []
    source = Source("cam1", str(video), replay_fps=300.0)  # paced ten times faster: a quick test
    reader = CameraReader(
        1, source, (320, 240), delivered.append, threading.Event(), start_ns=time.monotonic_ns()
    )
    reader.start()
    assert reader.finished.wait(60)
    # Not a fault that stops the run: the frames before the damage stand, and why it ended is kept.
    assert reader.fault is None and 0 < len(delivered) < FRAMES
    assert "Invalid data" in reader.cut_short


def test_a_replay_reader_that_fails_other_than_on_its_video_raises_that_error_in_the_run(
    session: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pipeline.live import capture

    class BrokenGreyer:
        def __call__(self, frame: object) -> None:
            raise TypeError("a bug in the reader")

    # Not taken for a damaged video (a replay "that cannot be replayed"): a bug, raised as such.
    monkeypatch.setattr(capture, "Greyer", BrokenGreyer)
    rig, sources = open_rig(None, session)
    with pytest.raises(TypeError, match="a bug in the reader"):
        run_live(rig, sources, out_dir=tmp_path / "out", duration_s=10.0)
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_a_replay_records_what_process_records(
    session: Path, processed: pipeline.record.load.Recording, tmp_path: Path
) -> None:
    rig, sources = open_rig(None, session)
    assert [s.replay_fps for s in sources] == [30.0] * 3
    # A queue long enough that no frame-set is dropped however loaded the machine is.
    summary = run_live(rig, sources, out_dir=tmp_path, queue_sets=FRAMES)
    assert isinstance(summary, LiveSummary)
    assert summary.stopped_by == "the end of the replay" and summary.dropped == 0
    assert summary.run.frames_ok == FRAMES and summary.exit_code == 0
    assert len(summary.latencies_ms) == FRAMES and (summary.latencies_ms > 0).all()
    live = pipeline.load_recording(tmp_path / "take.mcap")
    assert live.complete and live.frame_indices.tolist() == list(range(FRAMES))
    assert all(m["latency_ms"] > 0 for m in live.metrics)
    # The same core on the same frames: the bar is 0.05 mm mean; within one
    # tracking segment (20 frames) the two runs fit the same frames from the same track.
    assert mean_gap_mm(live, processed) < 0.05
    # The replay chooses its tube end from its videos as process does, and says so.
    assert live.tube_end == processed.tube_end != ""
    # ... and which cameras it used: the given ones, in the summary and the recording alike.
    assert f"  tube end: {live.tube_end}" in summary.lines()
    # ... and reads the tube's radius along it from the same sample frames.
    assert live.radius_profile is not None and processed.radius_profile is not None
    np.testing.assert_allclose(live.radius_profile.radius_mm, processed.radius_profile.radius_mm)
    assert f"  tube radius: {live.radius_profile.describe()}" in summary.lines()
    assert live.cameras.startswith("given") and f"  cameras: {live.cameras}" in summary.lines()
    assert live.smoothed_centerlines_m is not None
    _verify_rrd(tmp_path / "take.rrd")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["take.mcap", "take.rrd"]


def test_a_disk_filling_up_stops_the_run_with_the_frames_so_far_recorded(
    session: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The disk's free space as the run asks for it: plenty before the first frame-set and
    # after each of the next four, then, after the fifth, less than the run keeps to finish
    # its recordings.
    asked: list[Path] = []

    def free_bytes(directory: Path) -> int:
        asked.append(directory)
        room = live_run.finish_room_bytes(FRAMES)
        return 10 * room if len(asked) <= 5 else room // 2

    monkeypatch.setattr(live_run, "free_bytes", free_bytes)
    rig, sources = open_rig(None, session)
    summary = run_live(rig, sources, out_dir=tmp_path, queue_sets=FRAMES)
    assert set(asked) == {tmp_path}
    assert summary.stopped_by == live_run.STOPPED_FOR_ROOM and summary.exit_code == 1
    assert summary.run.frames_total == 5
    (line,) = [line for line in summary.problem_lines() if "free space" in line]
    assert f"{tmp_path}: its disk had" in line and "stopped after 5 frame-sets" in line
    recording = pipeline.load_recording(tmp_path / "take.mcap")
    assert recording.complete and recording.frame_indices.tolist() == [0, 1, 2, 3, 4]
    _verify_rrd(tmp_path / "take.rrd")


def test_a_camera_turning_faulty_mid_run_ends_it_with_the_frames_so_far_kept(
    session: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A camera restarted at another size after 5 frames: its frames are refused from there,
    # and the run stops, keeping what it wrote (exit 1), not throwing it away.
    from pipeline.live import capture

    hand_over = capture.CameraReader._hand_over

    def restarted(reader: CameraReader, k: int, arrived_ns: int, image: np.ndarray) -> None:
        if reader.source.camera == "cam2" and k >= 5:
            raise capture.SourceFault(
                "camera 'cam2' (test): frames are 640x480 but calibration.toml gives 320x240"
            )
        hand_over(reader, k, arrived_ns, image)

    monkeypatch.setattr(capture.CameraReader, "_hand_over", restarted)
    rig, sources = open_rig(None, session)
    summary = run_live(rig, sources, out_dir=tmp_path, queue_sets=FRAMES)
    assert summary.stopped_by == live_run.STOPPED_BY_FAULT and summary.exit_code == 1
    (line,) = [line for line in summary.problem_lines() if "640x480" in line]
    assert "the run stopped there, after" in line and "and kept them" in line
    recording = pipeline.load_recording(tmp_path / "take.mcap")
    assert recording.complete and 0 < len(recording) <= 5
    _verify_rrd(tmp_path / "take.rrd")


def test_dropped_frame_sets_are_a_problem_of_the_run() -> None:
    run = pipeline.run.summary.RunSummary(
        frames_ok=10, frames_empty=0, frames_failed=[], wall_s=1.0, fps=10.0
    )
    kept = LiveSummary(run=run, latencies_ms=np.ones(10), dropped=0, stopped_by="--duration")
    assert kept.exit_code == 0 and not any("dropped:" in line for line in kept.problem_lines())
    behind = dataclasses.replace(kept, dropped=3)
    (line,) = [line for line in behind.problem_lines() if "dropped:" in line]
    assert (
        line.startswith("  dropped: 3 frame-sets: the reconstruction fell behind") and behind.exit_code == 1
    )


def test_a_disk_without_room_to_finish_is_refused_before_the_run(
    session: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(live_run, "free_bytes", lambda directory: live_run.finish_room_bytes(0) - 1)
    rig, sources = open_rig(None, session)
    with pytest.raises(OutputError, match=r"out: its disk has 32\.0 MiB free, and a live run keeps 32\.0"):
        run_live(rig, sources, out_dir=tmp_path / "out", duration_s=5.0)
    assert not (tmp_path / "out").exists()


def _free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.slow
# The server saves what it receives as it comes, without the footer a finished file has.
@pytest.mark.filterwarnings("ignore:RRD file has no footer")
def test_a_rerun_grpc_server_receives_the_stream(session: Path, tmp_path: Path) -> None:
    from rerun.chunk import RrdReader

    port = _free_port()
    received = tmp_path / "received.rrd"
    # The Rerun CLI as a gRPC server that saves what it receives, in a process group of its own.
    server = subprocess.Popen(
        [str(RERUN), "--serve-grpc", "--port", str(port), "--save", str(received)],
        env=RERUN_ENV | {"TMPDIR": str(tmp_path)},  # its scratch folder, not /tmp's
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        _wait_for_port(port)
        check_viewer(grpc_url(str(port)))  # a viewer, as `--viewer connect PORT` asks it
        rig, sources = open_rig(None, session)
        summary = run_live(
            rig, sources, out_dir=tmp_path / "out", viewer_url=grpc_url(str(port)), queue_sets=FRAMES
        )
        assert summary.run.frames_ok == FRAMES
        time.sleep(0.5)  # the server writes what it got
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        server.wait(timeout=10)
    table = RrdReader(received).stream().collect().reader(index="frame", contents="/world/centerline")
    frames = table.to_arrow_table().column("frame").to_pylist()
    assert sorted(frames) == list(range(FRAMES))


def test_a_viewer_that_takes_the_connection_but_never_answers_does_not_hold_the_run(
    session: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # A hung viewer, or another service on its port: the connection is taken (the listen
    # queue's), nothing is ever read. Closing the viewer's stream would wait for it, in
    # native code, for as long as it stays.
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        rig, sources = open_rig(None, session)
        url = grpc_url(str(listener.getsockname()[1]))
        done: list[Any] = []
        run = threading.Thread(
            # A queue long enough that no frame-set is dropped however loaded the machine is.
            target=lambda: done.append(
                run_live(rig, sources, out_dir=tmp_path / "out", viewer_url=url, queue_sets=FRAMES)
            ),
            daemon=True,
        )
        run.start()
        run.join(120.0)  # a bound on a hang, not a speed target: the run takes seconds
        assert not run.is_alive(), "the run waits for the viewer"
    assert done[0].run.frames_ok == FRAMES
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        f"{session.name}.mcap",
        f"{session.name}.rrd",
    ]
    assert "the Rerun viewer did not close its connection" in caplog.text


def _wait_for_port(port: int) -> None:
    for _ in range(200):
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.1).close()
            return
        except OSError:
            time.sleep(0.05)
    raise AssertionError(f"nothing listens on {port}")


_UDP_SENDER = """
import sys, time
from fractions import Fraction
import av

start = float(sys.argv[1])  # wall-clock time of frame 0: senders started apart stay in step
pairs = [arg.split("=") for arg in sys.argv[2:]]
outputs, encoded = [], []
for video, port in pairs:
    container = av.open(f"udp://127.0.0.1:{port}?pkt_size=1316", mode="w", format="mpegts")
    stream = container.add_stream("mpeg2video", rate=30)
    stream.width, stream.height = 320, 240
    stream.pix_fmt = "yuv420p"
    stream.gop_size = 5  # a reader that joins late decodes from the next keyframe
    stream.max_b_frames = 0
    stream.bit_rate = 2_000_000
    # Encoded once, before sending: sending frame k of the three cameras takes microseconds.
    packets = []
    for frame in av.open(video).decode(video=0):
        packets += [(bytes(p), p.is_keyframe) for p in stream.encode(frame.reformat(format="yuv420p"))]
    packets += [(bytes(p), p.is_keyframe) for p in stream.encode(None)]
    outputs.append((container, stream))
    encoded.append(packets)
k = max(0, int((time.time() - start) * 30) + 1)
k += (-k) % 5  # from a keyframe
while True:
    time.sleep(max(0.0, start + k / 30 - time.time()))
    for packets, (container, stream) in zip(encoded, outputs):
        data, key = packets[k % len(packets)]
        packet = av.Packet(data)
        packet.stream = stream
        packet.time_base = Fraction(1, 30)
        packet.pts = packet.dts = k
        packet.is_keyframe = key
        container.mux(packet)
    k += 1
"""


def udp_sender(
    videos: list[Path], ports: list[int], *, start: float | None = None
) -> subprocess.Popen[bytes]:
    """Stream ``videos`` to the ``ports`` as MPEG-TS over UDP at 30 fps, over and over, until
    killed: a process of its own, as cameras are, so that the run does not hold it up.
    ``start``: the wall-clock time of frame 0 (default now)."""
    pairs = [f"{video}={port}" for video, port in zip(videos, ports, strict=True)]
    when = time.time() if start is None else start
    return subprocess.Popen(
        [sys.executable, "-c", _UDP_SENDER, repr(when), *pairs], stderr=subprocess.DEVNULL
    )


@pytest.fixture
def udp_rig(session: Path, tmp_path: Path) -> Iterator[tuple[Path, list[int]]]:
    ports = [_free_port(socket.SOCK_DGRAM) for _ in range(3)]
    live = {f"cam{k}": f"udp://127.0.0.1:{port}" for k, port in enumerate(ports)}
    yield _rig(tmp_path / "rig", session, live), ports


@pytest.mark.slow
def test_cameras_streaming_over_udp_are_reconstructed(
    session: Path, processed: pipeline.record.load.Recording, udp_rig: tuple[Path, list[int]], tmp_path: Path
) -> None:
    rig_dir, ports = udp_rig
    rig, sources = open_rig(rig_dir, None)
    assert [s.url for s in sources] == [f"udp://127.0.0.1:{p}" for p in ports]
    sender = udp_sender([session / f"cam{k}.mp4" for k in range(3)], ports)
    try:
        summary = run_live(rig, sources, out_dir=tmp_path / "out", duration_s=4.0)
    finally:
        sender.kill()
        sender.wait()
    assert summary.stopped_by == "--duration"
    live = pipeline.load_recording(tmp_path / "out" / "rig.mcap")
    # The frames whose track held: where it is lost (often, in this fast-moving session), a
    # frame that cannot wait for its start from the hull keeps the lost fit, flagged.
    held = np.array(
        [
            status == "ok" and "track was lost" not in metrics["suspect_reason"]
            for status, metrics in zip(live.statuses, live.metrics, strict=True)
        ]
    )
    # A few frames at least, however loaded the machine.
    assert held.sum() >= 3, summary.lines()
    # Each frame-set holds the same moment from the three cameras: its curve is one that
    # process found on some frame of the session (the re-encoding costs a little: 1 mm).
    # Three cameras' frames from different moments would fit no tube this well: the
    # tube moves 5-10 mm a frame in this short session.
    # A frame stamped late on a starved core can still pair with a neighbour's: most, not all
    # (alone or beside busy cores every held frame matched; under the whole suite on two
    # cores, 2026-12-06, three quarters). Frames paired across moments match none.
    reference_mm = processed.centerlines_m * 1000.0
    found = [
        np.linalg.norm(reference_mm - curve_mm, axis=-1).mean(axis=-1).min() < 1.0
        for curve_mm in live.centerlines_m[held] * 1000.0
    ]
    assert np.mean(found) >= 2 / 3, found


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=lambda s: s.name)
def test_a_signal_stops_the_run_with_complete_recordings(
    session: Path, udp_rig: tuple[Path, list[int]], tmp_path: Path, sig: signal.Signals
) -> None:
    rig_dir, ports = udp_rig
    out = tmp_path / "out"
    # Cameras that never end: only the signal stops the run.
    sender = udp_sender([session / f"cam{k}.mp4" for k in range(3)], ports)
    command = [sys.executable, "-m", "pipeline", "live", str(rig_dir), "--out", str(out), "--viewer", "none"]
    proc = subprocess.Popen(
        command,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # A run started from a background job inherits SIGINT ignored, and honours it.
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        # Wait until the run is capturing (it says so), then let it reconstruct for a while.
        assert proc.stderr is not None
        said: list[str] = []
        for line in iter(proc.stderr.readline, ""):
            said.append(line)
            if "capturing camera 'cam0'" in line:
                break
        assert said and "capturing" in said[-1], said
        time.sleep(2.0)
        proc.send_signal(sig)
        stdout, rest = proc.communicate(timeout=60)
        stderr = "".join(said) + rest
    finally:
        proc.kill()
        sender.kill()
        sender.wait()
    # A signal is no error: the status is the run's own, 1 only where it dropped frame-sets
    # (a loaded machine's UDP cameras outrun the reconstruction), and said so.
    assert proc.returncode == (1 if "\n  dropped: " in stderr else 0), stderr
    assert "live: stopped by a signal;" in stdout
    assert sorted(p.name for p in out.iterdir()) == ["rig.mcap", "rig.rrd"]
    rec = pipeline.load_recording(out / "rig.mcap")
    assert rec.complete and len(rec) > 0 and rec.smoothed_centerlines_m is not None
    assert (np.diff(rec.frame_indices) > 0).all()  # in order, each once
    _verify_rrd(out / "rig.rrd")


# --- the Foxglove server -----------------------------------------------------------------------


class _WebSocket:
    """The least of a WebSocket client (RFC 6455) to read what a Foxglove server sends."""

    def __init__(self, port: int, protocol: str) -> None:
        self._sock = socket.create_connection(("127.0.0.1", port), timeout=5)
        key = base64.b64encode(os.urandom(16)).decode()
        self._sock.sendall(
            f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
            f"Sec-WebSocket-Protocol: {protocol}\r\n\r\n".encode()
        )
        self._buf = b""
        while b"\r\n\r\n" not in self._buf:
            self._buf += self._sock.recv(4096)
        head, self._buf = self._buf.split(b"\r\n\r\n", 1)
        assert head.startswith(b"HTTP/1.1 101"), head

    def _need(self, n: int) -> None:
        while len(self._buf) < n:
            self._buf += self._sock.recv(65536)

    def receive(self) -> tuple[int, bytes]:
        """(opcode, payload) of the next frame: 1 text, 2 binary."""
        self._need(2)
        opcode, size, at = self._buf[0] & 0x0F, self._buf[1] & 0x7F, 2
        if size >= 126:
            width = 2 if size == 126 else 8
            self._need(2 + width)
            size, at = int.from_bytes(self._buf[2 : 2 + width], "big"), 2 + width
        self._need(at + size)
        payload, self._buf = self._buf[at : at + size], self._buf[at + size :]
        return opcode, payload

    def send_text(self, text: str) -> None:
        data, mask = text.encode(), os.urandom(4)
        assert len(data) < 126
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(data))
        self._sock.sendall(bytes([0x81, 0x80 | len(data)]) + mask + masked)

    def close(self) -> None:
        self._sock.close()


def test_the_foxglove_server_publishes_the_mcaps_topics_and_its_statics_to_late_subscribers() -> None:
    from conftest import rig_cameras
    from mcap.reader import make_reader

    from pipeline.live.stream import FoxgloveServer
    from pipeline.reconstruct.frame_result import FrameResult
    from pipeline.record.mcap_log import McapRecorder

    server = FoxgloveServer("127.0.0.1", 0, name="test")
    try:
        sink = io.BytesIO()
        recorder = McapRecorder(sink, rig_cameras(), mirror=server)
        curve_mm = np.column_stack([np.full(5, 100.0), np.linspace(0.0, 40.0, 5), np.linspace(10.0, 50.0, 5)])
        result = FrameResult(index=0, status="ok", centerline_mm=curve_mm, length_mm=40.0, radius_mm=6.0)
        recorder.write_frame(result, 1_700_000_000_000_000_000, jpegs=[b"\xff\xd8jpeg"] * 3)
        recorder.finish()
        mcap_topics = {
            channel.topic
            for channel in make_reader(io.BytesIO(sink.getvalue())).get_summary().channels.values()
        }

        client = _WebSocket(int(server.address.rsplit(":", 1)[1]), "foxglove.sdk.v1")
        advertised: dict[str, int] = {}
        while set(advertised) != mcap_topics:
            opcode, payload = client.receive()
            message = json.loads(payload) if opcode == 1 else {}
            if message.get("op") == "advertise":
                advertised |= {c["topic"]: c["id"] for c in message["channels"]}
        assert set(advertised) == mcap_topics
        # /tf was written once, before this client came: subscribing sends it again.
        client.send_text(
            json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": advertised["/tf"]}]})
        )
        opcode, payload = client.receive()
        while opcode != 2:
            opcode, payload = client.receive()
        assert payload[0] == 1 and int.from_bytes(payload[1:5], "little") == 7  # message data, subscription 7
        client.close()
    finally:
        server.stop()


# --- the command line --------------------------------------------------------------------------


def test_live_without_sources_is_one_line_and_exit_2(
    session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from pipeline.cli import main

    rig = _rig(tmp_path / "rig", session, None)
    # RIG_DIR after --viewer's words is the rig, not a third word of --viewer.
    assert main(["live", "--out", str(tmp_path / "out"), "--viewer", "none", str(rig)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and len(err.splitlines()) == 1 and "no [live] table" in err
    assert not (tmp_path / "out").exists()
    # So is RIG_DIR after --foxglove, whose address may be left out ("give RIG_DIR" before).
    assert main(["live", "--out", str(tmp_path / "out"), "--foxglove", str(rig)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no [live] table" in err


def test_live_to_a_viewer_nobody_runs_is_refused_before_the_run(
    session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from pipeline.cli import main

    port = _free_port()  # nothing listens there
    code = main(
        ["live", "--replay", str(session), "--out", str(tmp_path / "out"), "--viewer", "connect", str(port)]
    )
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert f"--viewer connect rerun+http://127.0.0.1:{port}/proxy: no Rerun viewer answers there" in err
    assert len(err.splitlines()) == 1 and not (tmp_path / "out").exists()


def test_a_viewer_address_where_something_else_listens_is_refused_naming_it() -> None:
    import http.server

    # A web server on the port (another tool's, or the viewer's web port for its gRPC one).
    web = http.server.HTTPServer(("127.0.0.1", 0), http.server.BaseHTTPRequestHandler)
    threading.Thread(target=web.serve_forever, daemon=True).start()
    try:
        url = grpc_url(str(web.server_port))
        with pytest.raises(SettingsError) as refused:
            check_viewer(url)
    finally:
        web.shutdown()
        web.server_close()
    line = str(refused.value)
    assert line.startswith(f"--viewer connect {url}: the server there answers as a web server (")
    assert "so it is no Rerun viewer; give the viewer's gRPC port (rerun's is 9876)" in line
    # A service that takes the connection and never answers (a hung viewer).
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        with pytest.raises(SettingsError, match="took the connection but did not answer within 2 s"):
            check_viewer(grpc_url(str(listener.getsockname()[1])))


def test_a_foxglove_subscriber_gets_the_messages_written_just_before_the_stop() -> None:
    # The SDK's stop drops what is still queued for a client: the last frames of a run.
    from pipeline.live.stream import FoxgloveServer
    from pipeline.record.mcap_log import ChannelSchema

    server = FoxgloveServer("127.0.0.1", 0, name="test")
    schema = ChannelSchema(name="blob", encoding="jsonschema", data=b"{}", message_encoding="json")
    server("/blob", schema, b"{}", 0)
    client = _WebSocket(int(server.address.rsplit(":", 1)[1]), "foxglove.sdk.v1")
    channel_id = None
    while channel_id is None:
        opcode, payload = client.receive()
        message = json.loads(payload) if opcode == 1 else {}
        if message.get("op") == "advertise":
            channel_id = next((c["id"] for c in message["channels"] if c["topic"] == "/blob"), None)
    client.send_text(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": channel_id}]}))
    while server.subscribed == 0:
        time.sleep(0.01)
    received: list[bytes] = []

    def read() -> None:
        with contextlib.suppress(OSError, IndexError):
            while True:
                opcode, payload = client.receive()
                if opcode == 8:  # the server's close
                    return
                if opcode == 2:
                    received.append(payload)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    # 300 messages of 200 kB (fewer than the SDK's queue of 1,024 a client), then the stop.
    for i in range(300):
        server("/blob", schema, b"{" + b" " * 200_000 + b"}", i + 1)
    server.stop()
    reader.join(5)
    client.close()
    assert len(received) >= 300  # (and /blob's first message, if it came after the subscription)


def test_a_foxglove_client_that_stopped_reading_does_not_hold_the_run(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    # The SDK's stop waits for every client to close; one that stopped reading never does
    # (until its own timeout, a minute or more), and the wait is in native code.
    from pipeline.live import stream

    server = stream.FoxgloveServer("127.0.0.1", 0, name="test")
    real_stop, released = server._server.stop, threading.Event()

    class Stalled:
        def stop(self) -> None:
            released.wait()  # a client that never closes
            real_stop()

    server._server = Stalled()
    monkeypatch.setattr(stream, "STOP_TIMEOUT_S", 0.2)
    started = time.monotonic()
    with caplog.at_level(logging.WARNING):
        server.stop()
    assert time.monotonic() - started < 5.0  # not held until the client goes
    assert "Foxglove: a client did not close within 0.2 s" in caplog.text
    released.set()


def test_a_foxglove_port_already_taken_is_refused_before_the_run(
    session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from pipeline.cli import main
    from pipeline.live import run

    def began(*args: object) -> None:
        raise AssertionError("the run began")

    monkeypatch.setattr(run, "_model", began)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        out = ["--out", str(tmp_path / "out"), "--viewer", "none", "--foxglove", f"127.0.0.1:{port}"]
        assert main(["live", "--replay", str(session), *out]) == 2
        err = capsys.readouterr().err.strip()
        assert f"--foxglove 127.0.0.1:{port}: port {port} is taken (" in err and "another --foxglove" in err
        assert len(err.splitlines()) == 1 and not (tmp_path / "out").exists()
        rig, sources = open_rig(None, session)
        with pytest.raises(SettingsError, match=f"port {port} is taken"):
            run_live(rig, sources, out_dir=tmp_path / "out", foxglove=("127.0.0.1", port))
    with pytest.raises(SettingsError, match=r"--foxglove no-such-host\.invalid:8765: cannot serve there"):
        run_live(rig, sources, out_dir=tmp_path / "out", foxglove=("no-such-host.invalid", 8765))
    assert not (tmp_path / "out").exists()


def test_a_camera_that_does_not_answer_is_reported_and_the_run_still_stops_cleanly(
    session: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    ports = [_free_port() for _ in range(3)]  # nothing listens: each connection is refused
    rig_dir = _rig(
        tmp_path / "rig", session, {f"cam{k}": f"tcp://127.0.0.1:{p}" for k, p in enumerate(ports)}
    )
    rig, sources = open_rig(rig_dir, None)
    with caplog.at_level("WARNING", logger="pipeline.live.capture"):
        summary = run_live(rig, sources, out_dir=tmp_path / "out", duration_s=2.0)
    # Every camera is refused, reported once and retried each second; no frame, exit 1.
    assert summary.stopped_by == "--duration" and summary.run.frames_total == 0 and summary.exit_code == 1
    for k in range(3):
        assert any(f"camera 'cam{k}' (tcp://127.0.0.1:{ports[k]})" in r.message for r in caplog.records)
        assert summary.camera(f"cam{k}").outages == ("connection refused",)  # the same outage, reported once
    assert not any("Errno" in r.message for r in caplog.records)
    # No frame-set: no recording, no temporary file, and not the folder made for them.
    assert summary.run.outputs == [] and not (tmp_path / "out").exists()
    assert summary.problem_lines()[0] == (
        "  no frame-set arrived before the run was stopped by --duration; nothing written"
    )
    # Into a folder holding an earlier recording, even with force: it stays as it was.
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "rig.mcap").write_bytes(b"earlier")
    summary = run_live(rig, sources, out_dir=tmp_path / "out", duration_s=0.5, force=True)
    assert summary.run.outputs == [] and summary.exit_code == 1
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["rig.mcap"]
    assert (tmp_path / "out" / "rig.mcap").read_bytes() == b"earlier"


def test_ffmpegs_errors_are_worded_for_the_camera_without_its_error_numbers() -> None:
    import errno

    import av

    from pipeline.live.reasons import ffmpeg_text, outage_reason

    def reason(exc: BaseException, *, opened: bool = False) -> tuple[str, str]:
        return outage_reason(exc, opened=opened, open_timeout_s=5.0, stall_s=2.0)

    cut_off = av.error.ExitError(1414092869, "Immediate exit requested", "udp://0.0.0.0:5002")
    assert reason(cut_off) == (
        "no stream within 5 s",
        "check that the camera sends its stream to this address",
    )
    assert reason(cut_off, opened=True) == ("no frame for 2 s", "check the camera's cable, power or stream")
    refused = av.error.ConnectionRefusedError(errno.ECONNREFUSED, "Connection refused", "tcp://rig:5000")
    assert reason(refused)[0] == "connection refused" and "runs at this address" in reason(refused)[1]
    busy = av.error.OSError(-errno.EBUSY, "Device or resource busy", "/dev/video0")  # a negative code
    assert reason(busy) == ("the device is busy", "close the other program that uses the camera")
    invalid = av.error.InvalidDataError(1094995529, "Invalid data found when processing input", "x")
    assert reason(invalid)[0] == "FFmpeg cannot read the stream (invalid data)"
    # FFmpeg's own text, where it has no better word, without its number or the URL again.
    bug = av.error.BugError(558323010, "Internal bug, should not have happened", "rtsp://rig/1")
    assert reason(bug)[0] == "FFmpeg: Internal bug, should not have happened"
    assert ffmpeg_text(bug) == "Internal bug, should not have happened"
    for exc in (cut_off, refused, busy, invalid, bug):
        text = " ".join(reason(exc))
        assert "Errno" not in text and str(abs(exc.errno)) not in text, text


def test_a_host_the_system_cannot_resolve_is_named_not_taken_for_a_cable() -> None:
    from pipeline.live.reasons import unresolved_host

    # .invalid never resolves (RFC 2606): no network is asked for an answer that could change.
    assert unresolved_host("http://nosuchhost.invalid/x.mp4") == "nosuchhost.invalid"
    for url in (
        "udp://127.0.0.1:5002",
        "rtsp://localhost:8554/cam",
        "/dev/video0",
        "pipe.ts",
        "http://[::1]:80/",
    ):
        assert unresolved_host(url) == "", url


def test_a_source_of_a_scheme_ffmpeg_does_not_read_stops_the_run_named(
    session: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # A typo for rtsp://: it would never open, however often it was tried. The other cameras'
    # readers, waiting on streams nothing sends yet, are not blamed for it.
    live = {
        "cam0": f"tcp://127.0.0.1:{_free_port()}",
        "cam1": "rtps://127.0.0.1:1/x",
        "cam2": f"udp://127.0.0.1:{_free_port()}",
    }
    rig, sources = open_rig(_rig(tmp_path / "rig", session, live), None)
    with (
        caplog.at_level(logging.WARNING, logger="pipeline.live"),
        pytest.raises(
            SessionError, match=r"camera 'cam1' \(rtps://127.0.0.1:1/x\): FFmpeg reads no rtps: URLs"
        ),
    ):
        run_live(rig, sources, out_dir=tmp_path / "out", duration_s=30.0)
    assert not (tmp_path / "out").exists()
    assert "still waiting on the source" not in caplog.text
    for thread in threading.enumerate():  # cam2's, until its open times out: not into the next test
        if thread.name.startswith("camera-"):
            thread.join(30.0)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes")
@pytest.mark.parametrize("duration_s", [0.5, 0.001], ids=["waiting", "stopped-at-once"])
def test_named_pipes_nothing_writes_to_end_with_the_run(
    session: Path, tmp_path: Path, duration_s: float
) -> None:
    # Stopped at once, the stop may land before the readers have opened their pipes.
    pipes = [tmp_path / f"cam{k}.pipe" for k in range(3)]
    for pipe in pipes:
        os.mkfifo(pipe)
    rig_dir = _rig(tmp_path / "rig", session, {f"cam{k}": str(pipe) for k, pipe in enumerate(pipes)})
    rig, sources = open_rig(rig_dir, None)
    try:
        summary = run_live(rig, sources, out_dir=tmp_path / "out", duration_s=duration_s)
        # Each reader waited for its pipe's first data: the run's stop reached it there, and it ended.
        waiting = [t.name for t in threading.enumerate() if t.name.startswith("camera-cam")]
    finally:
        for pipe in pipes:  # a reader still waiting on its pipe (a failure above) reads its end
            with contextlib.suppress(OSError):
                os.close(os.open(pipe, os.O_WRONLY | os.O_NONBLOCK))
    assert waiting == []
    assert summary.stopped_by == "--duration" and summary.exit_code == 1 and not (tmp_path / "out").exists()
    lines = summary.problem_lines()
    for k in range(3):
        assert lines[k + 1].startswith(f"  camera cam{k}: delivered no frame (its source opened no stream")


def _mpegts(video: Path) -> bytes:
    """``video`` as an MPEG-TS stream, as a camera's writer would send it down a pipe."""
    import av

    out = io.BytesIO()
    with av.open(out, mode="w", format="mpegts") as container:
        stream = container.add_stream("mpeg2video", rate=30)
        stream.width, stream.height, stream.pix_fmt = 320, 240, "yuv420p"
        for frame in av.open(video).decode(video=0):
            container.mux(stream.encode(frame.reformat(format="yuv420p")))
        container.mux(stream.encode(None))
    return out.getvalue()


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes")
def test_a_lossless_ffv1_stream_is_read_from_its_first_keyframe(session: Path, tmp_path: Path) -> None:
    # FFV1's frames between keyframes refer to the ones before: FFmpeg's low-delay open drops
    # the first packets it probed, and the decoder raised on the next ones.
    import av

    stream_bytes = io.BytesIO()
    with av.open(stream_bytes, mode="w", format="nut") as container:
        stream = container.add_stream("ffv1", rate=30)
        stream.width, stream.height, stream.pix_fmt = 320, 240, "gray"
        stream.gop_size = 10
        for frame in av.open(session / "cam1.mp4").decode(video=0):
            container.mux(stream.encode(frame.reformat(format="gray")))
        container.mux(stream.encode(None))
    pipe = tmp_path / "cam1.pipe"
    os.mkfifo(pipe)

    stop = threading.Event()

    def write() -> None:
        with open(pipe, "wb") as fifo:
            fifo.write(stream_bytes.getvalue())
            fifo.flush()
            stop.wait()  # a camera that goes on: the pipe stays open until the run stops

    threading.Thread(target=write, daemon=True).start()
    delivered: list[CapturedFrame] = []
    reader = CameraReader(
        1, Source("cam1", str(pipe)), (320, 240), delivered.append, stop, start_ns=time.monotonic_ns()
    )
    reader.start()
    deadline = time.monotonic() + 20
    while len(delivered) < FRAMES - 10 and time.monotonic() < deadline and reader.fault is None:
        time.sleep(0.05)
    stop.set()
    reader.join(5)
    assert reader.fault is None and reader.stats.outages == []
    # From the first keyframe the probe left on: every frame of the video from there on.
    assert FRAMES - 10 <= len(delivered) <= FRAMES


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes")
def test_named_pipes_whose_writers_stall_open_are_reported_and_end_with_the_run(
    session: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pipeline.live import capture

    opened: list[capture.PipeFile] = []

    class KeptPipeFile(capture.PipeFile):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            opened.append(self)

    monkeypatch.setattr(capture, "PipeFile", KeptPipeFile)
    pipes = [tmp_path / f"cam{k}.pipe" for k in range(3)]
    # Five times over: more than FFmpeg probes before the first frame.
    streams = [_mpegts(session / f"cam{k}.mp4") * 5 for k in range(3)]
    writers: list[int] = []

    def write_and_stall(pipe: Path, data: bytes) -> None:
        fd = os.open(pipe, os.O_WRONLY)  # waits for the run's reader
        writers.append(fd)
        os.write(fd, data)  # then writes nothing more, and keeps the pipe open

    for pipe, data in zip(pipes, streams, strict=True):
        os.mkfifo(pipe)
        threading.Thread(target=write_and_stall, args=(pipe, data), daemon=True).start()
    rig, sources = open_rig(
        _rig(tmp_path / "rig", session, {f"cam{k}": str(p) for k, p in enumerate(pipes)}), None
    )
    try:
        summary = run_live(rig, sources, out_dir=tmp_path / "out", duration_s=4.0)
        # Every reader saw the stop, though its writer still holds its pipe open.
        blocked = [t.name for t in threading.enumerate() if t.name.startswith("camera-cam")]
    finally:
        for fd in writers:
            os.close(fd)
    assert blocked == []
    # Each pipe's reading end is closed with its stream (after the stall, and after the stop).
    assert len(opened) >= 3 and all(pipe._fd is None for pipe in opened)
    assert summary.stopped_by == "--duration"
    for k in range(3):
        assert summary.camera(f"cam{k}").delivered > 0
        assert summary.camera(f"cam{k}").outages == ("no data for 2 s: its writer stalled",)
        assert f"  camera cam{k}: stopped 1 time(s), down at the end (first: no data for 2 s" in "\n".join(
            summary.problem_lines()
        )


@pytest.mark.slow
def test_a_camera_that_stalls_is_reported_and_picked_up_again_while_the_others_go_on(
    session: Path, udp_rig: tuple[Path, list[int]], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    rig_dir, ports = udp_rig
    rig, sources = open_rig(rig_dir, None)
    videos = [session / f"cam{k}.mp4" for k in range(3)]
    start = time.time()
    # One sender per camera, all on one clock; cam2's stops 2 s after the run starts capturing
    # and starts again 2 s later (margins for a loaded machine, where opening and decoding lag).
    senders = [udp_sender([videos[k]], [ports[k]], start=start) for k in range(3)]
    stalled: list[float] = []  # when cam2 stopped and started again, wall clock

    def stall_cam2() -> None:
        while not any("capturing" in r.getMessage() for r in caplog.records):
            time.sleep(0.05)
        time.sleep(2.0)
        senders[2].kill()
        stalled.append(time.time())
        time.sleep(2.0)
        senders[2] = udp_sender([videos[2]], [ports[2]], start=start)
        stalled.append(time.time())

    stall = threading.Thread(target=stall_cam2, daemon=True)
    try:
        with caplog.at_level("INFO"):
            stall.start()
            summary = run_live(rig, sources, out_dir=tmp_path / "out", duration_s=8.0)
    finally:
        stall.join(30)
        for sender in senders:
            sender.kill()
            sender.wait()
    assert [len(c.outages) for c in summary.cameras] == [0, 0, 1]
    assert any("camera 'cam2'" in r.message and "retrying" in r.message for r in caplog.records)
    assert any("camera 'cam2'" in r.message and "frames again" in r.message for r in caplog.records)
    # Frames before the stall and after it, none while cam2 was away.
    times_s = pipeline.load_recording(tmp_path / "out" / "rig.mcap").timestamps_ns * 1e-9
    stopped, restarted = stalled
    assert (times_s < stopped).any() and (times_s > restarted).any()
    # No frame-set for most of the 2 s cam2 was away: the longest gap between frame-sets, and
    # after the kill. Where it lies to the second depends on the machine's load: frames in
    # flight at the kill, or queued behind a reader that a loaded machine slows, are decoded
    # and stamped later (frame-sets 0.5 and 1.0 s after the kill were seen when the suite
    # ran on 2 cores beside other work).
    order = np.sort(times_s)
    gaps = np.diff(order)
    longest = int(np.argmax(gaps))
    resumed = order[longest + 1]
    assert gaps[longest] >= 1.0 and resumed > stopped, (gaps[longest], resumed - stopped)


def test_the_summary_gives_latency_drops_rates_and_outages() -> None:
    from pipeline.run.summary import RunSummary

    run = RunSummary(frames_ok=4, frames_empty=0, frames_failed=[], wall_s=2.0, fps=2.0)
    summary = LiveSummary(
        run=run,
        latencies_ms=np.array([10.0, 20.0, 30.0, 40.0, 50.0]),
        dropped=3,
        stopped_by="a signal",
        cameras=(
            CameraSummary("cam0", fps=30.0, delivered=60, unmatched=1),
            CameraSummary("cam1", fps=float("nan"), delivered=1, outages=("Connection refused",)),
        ),
    )
    lines = summary.lines()
    assert lines[0] == "frames: 4 processed, 4 ok, 0 empty, 0 failed"
    # numpy's linear interpolation: p50 of 10..50 is 30, p99 is 10 + 0.99 * 40 = 49.6.
    live = "live: stopped by a signal; latency p50 30.0 ms, p99 49.6 ms; 3 frame-sets dropped"
    assert f"{live}, 1 frames unmatched" in lines
    assert "  cameras (frames/s): cam0 30.0, cam1 1 frame(s), no rate" in lines
    outage = "  camera cam1: stopped 1 time(s), picked up again (first: Connection refused)"
    assert outage in summary.problem_lines() and lines.index(outage) < lines.index(
        "time: 2.0 s wall, 2.0 frames/s"
    )
    data = json.loads(json.dumps(summary.to_dict(), allow_nan=False))  # no NaN in the JSON
    assert data["live"]["latency_ms"] == {"p50": 30.0, "p99": pytest.approx(49.6)}
    assert data["live"]["camera_fps"] == {"cam0": 30.0, "cam1": None}
    # Dropped frame-sets are data lost: a problem of the run (exit 1), on stderr.
    assert data["live"]["frames_dropped"] == 3 and data["exit_code"] == 1
    assert any(line.startswith("  dropped: 3 frame-sets") for line in summary.problem_lines())


def test_the_summary_of_a_run_without_frames_says_so_rather_than_nan() -> None:
    from pipeline.run.summary import RunSummary

    run = RunSummary(frames_ok=0, frames_empty=0, frames_failed=[], wall_s=2.0, fps=0.0)
    summary = LiveSummary(
        run=run,
        latencies_ms=np.array([]),
        dropped=0,
        stopped_by="--duration",
        cameras=(
            CameraSummary("cam0", fps=float("nan"), delivered=0),
            CameraSummary("cam1", fps=float("nan"), delivered=1, unmatched=1),  # one frame gives no rate
        ),
    )
    lines = summary.lines()
    assert not any("nan" in line for line in lines), lines
    assert (
        "live: stopped by --duration; no frame-set written, so no latency; 0 frame-sets dropped, "
        in "\n".join(lines)
    )
    assert "  cameras (frames/s): cam0 no frames, cam1 1 frame(s), no rate" in lines


def test_the_summary_names_a_camera_that_delivered_nothing_or_whose_replay_ended_short() -> None:
    from pipeline.run.summary import RunSummary

    run = RunSummary(frames_ok=21, frames_empty=0, frames_failed=[], wall_s=2.0, fps=10.0)
    common = {
        "run": run,
        "latencies_ms": np.array([10.0]),
        "dropped": 0,
        "stopped_by": "the end of the replay",
    }
    names = ("cam0", "cam1", "cam2")

    def replayed(
        delivered: tuple[int, int, int], cut_short: tuple[str, str, str] = ("", "", "")
    ) -> tuple[CameraSummary, ...]:
        return tuple(
            CameraSummary(name, fps=30.0, delivered=n, unmatched=40 - n, cut_short=why)
            for name, n, why in zip(names, delivered, cut_short, strict=True)
        )

    short = LiveSummary(**common, cameras=replayed((40, 21, 40)))
    (line,) = short.problem_lines()
    assert line.startswith("  camera cam1: its replay ended after 21 of the 40 frames the others gave")
    assert "cut short?" in line and short.exit_code == 1
    assert short.to_dict()["exit_code"] == 1  # the JSON summary's status is the process's
    # Cameras started by hand stop a few frames apart: as process, that is no problem.
    close = dataclasses.replace(short, cameras=replayed((40, 38, 40)))
    assert close.problem_lines() == [] and close.exit_code == 0
    damaged = dataclasses.replace(short, cameras=replayed((40, 21, 40), ("", "Invalid data", "")))
    assert "it is damaged there: Invalid data" in damaged.problem_lines()[0]
    whole = dataclasses.replace(short, cameras=replayed((40, 40, 40)))
    assert whole.problem_lines() == [] and whole.exit_code == 0
    # Stopped by --duration before the replay's first frame: not the videos' fault.
    none = RunSummary(frames_ok=0, frames_empty=0, frames_failed=[], wall_s=0.1, fps=0.0)
    early = dataclasses.replace(short, run=none, stopped_by="--duration", cameras=replayed((1, 0, 0)))
    assert early.problem_lines() == [
        "  no frame-set arrived before the run was stopped by --duration; nothing written"
    ]
    assert early.exit_code == 1  # no tube in any frame, as for process
    stopped = dataclasses.replace(short, stopped_by="--duration")  # the others' later frames were not due yet
    assert stopped.problem_lines() == []
    silent = LiveSummary(
        **common,
        cameras=(
            CameraSummary("cam0", fps=float("nan"), delivered=0, outages=("No such file or directory",)),
            CameraSummary("cam1", fps=float("nan"), delivered=0),
            CameraSummary(
                "cam2", fps=float("nan"), delivered=12, outages=("Connection refused",), down_at_end=True
            ),
        ),
    )
    assert silent.problem_lines() == [
        "  camera cam0: delivered no frame (No such file or directory); check its source in [live] in "
        "session.toml, and that the camera is on or its stream is sent",
        "  camera cam1: delivered no frame (its source opened no stream before the run ended); check its "
        "source in [live] in session.toml, and that the camera is on or its stream is sent",
        "  camera cam2: stopped 1 time(s), down at the end (first: Connection refused); the other "
        "cameras' frames after it stopped had no set (12 of its frames delivered): check the camera and "
        "its connection",
    ]
    assert silent.exit_code == 1


def test_a_camera_lost_while_the_others_went_on_is_a_problem_all_ending_together_is_not() -> None:
    from pipeline.run.summary import RunSummary

    run = RunSummary(frames_ok=26, frames_empty=0, frames_failed=[], wall_s=10.0, fps=2.6)

    def ended(down: tuple[bool, bool, bool]) -> LiveSummary:
        cameras = tuple(
            CameraSummary(
                f"cam{k}",
                fps=30.0,
                delivered=45 if lost else 300,
                outages=("no frame for 2 s",) if lost else (),
                down_at_end=lost,
            )
            for k, lost in enumerate(down)
        )
        return LiveSummary(
            run=run, latencies_ms=np.array([10.0]), dropped=0, stopped_by="a signal", cameras=cameras
        )

    lost = ended((False, False, True))
    (line,) = lost.problem_lines()
    assert line.startswith(
        "  camera cam2: stopped 1 time(s), down at the end (first: no frame for 2 s); the other"
    )
    assert "(45 of its frames delivered): check the camera" in line
    assert lost.exit_code == 1 and lost.to_dict()["exit_code"] == 1
    # Every stream stopped before the run was: the session's end, said, but no fault.
    together = ended((True, True, True))
    assert all(
        line.endswith("down at the end (first: no frame for 2 s)") for line in together.problem_lines()
    )
    assert together.exit_code == 0


def test_a_camera_whose_frames_do_not_fit_its_calibration_stops_the_run_named(session: Path) -> None:
    from pipeline.live.capture import CameraReader

    delivered: list[CapturedFrame] = []
    source = Source("cam1", str(session / "cam1.mp4"), replay_fps=30.0)
    reader = CameraReader(
        1, source, (640, 480), delivered.append, threading.Event(), start_ns=time.monotonic_ns()
    )
    reader.start()
    assert reader.finished.wait(10)
    assert reader.fault is not None and delivered == []
    assert reader.fault.startswith(f"camera 'cam1' ({session / 'cam1.mp4'}): frames are 320x240 but")
    assert "calibration.toml gives 640x480" in reader.fault


def _rig_at_640x480(directory: Path, session: Path, live: dict[str, str | int] | None) -> Path:
    rig_dir = _rig(directory, session, live)
    calibration = rig_dir / "calibration.toml"
    text = calibration.read_text()
    assert "320,\n    240," in text
    calibration.write_text(text.replace("320,\n    240,", "640,\n    480,"))
    return rig_dir


def test_a_replay_at_another_resolution_than_the_rig_is_refused(session: Path, tmp_path: Path) -> None:
    from pipeline.errors import SessionError

    rig_dir = _rig_at_640x480(tmp_path / "rig", session, None)
    with pytest.raises(
        SessionError, match=r"cam0.mp4: frames are 320x240 but the rig's calibration.toml gives"
    ):
        open_rig(rig_dir, session)


@pytest.mark.slow
def test_a_run_stopped_by_a_camera_of_the_wrong_size_leaves_nothing_behind(
    session: Path, tmp_path: Path
) -> None:
    from pipeline.errors import SessionError

    ports = [_free_port(socket.SOCK_DGRAM) for _ in range(3)]
    live = {f"cam{k}": f"udp://127.0.0.1:{port}" for k, port in enumerate(ports)}
    rig, sources = open_rig(_rig_at_640x480(tmp_path / "rig", session, live), None)
    sender = udp_sender([session / f"cam{k}.mp4" for k in range(3)], ports)  # 320x240
    try:
        with pytest.raises(SessionError, match=r"camera 'cam\d' \(udp://.*\): frames are 320x240 but"):
            run_live(rig, sources, out_dir=tmp_path / "out")
    finally:
        sender.kill()
        sender.wait()
    assert not (tmp_path / "out").exists()


class _HangingReader(CameraReader):
    """A camera whose source never returns (a device or stream that hangs in its read)."""

    def __init__(self, release: threading.Event, stop: threading.Event) -> None:
        source = Source("cam0", "/dev/video9", V4L2_FORMAT)
        super().__init__(0, source, (320, 240), lambda _: None, stop, start_ns=0)
        self._release = release

    def _read(self) -> None:
        self._release.wait()


def test_a_reader_still_blocked_in_its_source_after_the_stop_is_named(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(live_run, "JOIN_S", 0.2)
    stop, release = threading.Event(), threading.Event()
    reader = _HangingReader(release, stop)
    reader.start()
    try:
        live_run._stop_readers(stop, [reader])
        (line,) = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert line.startswith("camera 'cam0' (/dev/video9): its reader was still waiting on the source")
        assert "0.2 s after the run stopped" in line
        assert "check the camera and its connection" in line
    finally:
        release.set()
        reader.join(5.0)
    caplog.clear()
    live_run._stop_readers(stop, [reader])  # a reader that has ended is not named
    assert not caplog.records


def test_ctrl_c_while_the_readers_start_stops_the_run_and_removes_its_files(
    session: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The signal lands after the first reader has started, before the others have.
    start = CameraReader.start
    started: list[int] = []

    def start_then_interrupt(self: CameraReader) -> None:
        if started:
            raise KeyboardInterrupt
        started.append(1)
        start(self)

    monkeypatch.setattr(CameraReader, "start", start_then_interrupt)
    rig, sources = open_rig(None, session)
    with pytest.raises(KeyboardInterrupt):
        run_live(rig, sources, out_dir=tmp_path / "out", viewer_url=None)
    assert started == [1]
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_a_run_whose_recordings_fail_to_finish_stops_its_readers_once(
    session: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def fail(self: Any) -> None:
        raise OSError("disk full")

    calls: list[int] = []
    stop_readers = live_run._stop_readers

    def counted(stop: threading.Event, readers: Any) -> None:
        calls.append(len(readers))
        stop_readers(stop, readers)

    monkeypatch.setattr(live_run.Writers, "finish", fail)
    monkeypatch.setattr(live_run, "_stop_readers", counted)
    rig, sources = open_rig(None, session)
    with pytest.raises(OSError, match="disk full"):
        run_live(rig, sources, out_dir=tmp_path / "out", duration_s=1.0)
    # A reader still blocked in its source would be waited for, and named, once.
    assert calls == [3]
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
