"""A live run: cameras in, each frame's shape out as it happens, recordings at the stop.

One reader thread per camera (:mod:`.capture`) stamps frames on arrival; the
matcher (:mod:`.sync`) pairs them into frame-sets; a short queue (:mod:`.handoff`)
hands those to this thread, which reconstructs each with the tracked core of ``process``
(:class:`pipeline.reconstruct.frame_task.Tracker`; tracks started from the hull after the
first frame run in a process of their own, :mod:`.restarts`) and writes it at once to the
MCAP and Rerun writers of ``process`` (the Rerun stream also to a viewer, the MCAP's
messages also to a Foxglove server). The run stops at Ctrl-C, SIGTERM or SIGHUP,
after ``duration_s``, or at the end of a replay; the recordings are then finished
and renamed into place as ``process`` does, holding every frame written. A run that
no frame-set reached writes nothing.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import OutputError, SessionError
from ..reconstruct.frame_task import Tracker
from ..run.interrupts import deferred_signals, signals_interrupt
from ..run.output_target import OutputTarget, prepare_outputs
from ..run.outputs import Writers
from ..run.summary import RunSummary
from ..session.folder import SHORT_VIDEO_FRACTION, SHORT_VIDEO_FRAMES, Session
from .capture import CameraReader
from .handoff import QUEUE_SETS, DroppingQueue
from .restarts import RestartWorker
from .sources import Source
from .stream import check_foxglove
from .sync import CapturedFrame, FrameMatcher, half_period_ns

log = logging.getLogger(__name__)

# How often the run looks up from an empty queue (stop requests, the end of a replay).
POLL_S = 0.05
# The restart worker gets this long to start before the cameras do (it takes ~1 s).
RESTARTS_READY_S = 30.0
# Readers blocked in a read get this long, together, to notice the stop (their reads time out).
JOIN_S = 3.0
# The cameras a live run reconstructs with, as its summary and recordings say: a refinement
# needs a session's frames spread over the run, which a live run does not have ahead.
LIVE_CAMERAS = "given (a live run does not refine them from the silhouettes)"
# A live run stops while the disk that holds its recordings still has room to finish them,
# rather than lose every frame when it fills (its cameras cannot film the take again).
# Finishing writes the smoothed curves and their flags (2.7 KiB a frame-set in the demo's
# recordings, 2026-12-05), the MCAP's index and what Rerun still holds.
FINISH_ROOM_BYTES = 32 << 20
FINISH_ROOM_PER_SET_BYTES = 8 << 10
STOPPED_FOR_ROOM = "the disk filling up"
STOPPED_BY_FAULT = "a camera's fault"


@dataclass(frozen=True)
class CameraSummary:
    """How one camera of a live run went.

    name : the camera's name in calibration.toml.
    fps : frames per second it delivered (NaN with fewer than two frames).
    delivered : frames it delivered.
    unmatched : its frames that no frame of every other camera matched.
    outages : why it stopped, each time it did (retried).
    down_at_end : it was still down (an outage not over) as the run ended.
    cut_short : a replayed camera's: why its frames ended before its video did ("" where
        not); None for a camera.
    """

    name: str
    fps: float
    delivered: int
    unmatched: int = 0
    outages: tuple[str, ...] = ()
    down_at_end: bool = False
    cut_short: str | None = None

    @property
    def is_replay(self) -> bool:
        return self.cut_short is not None

    @property
    def silent(self) -> bool:
        """It delivered no frame, where one was due: a camera, or a replay that failed."""
        return not self.delivered and (bool(self.outages) or not self.is_replay)

    def rate(self) -> str:
        """Its name and frames per second, or why it has none (a rate needs two frames)."""
        if np.isfinite(self.fps):
            return f"{self.name} {self.fps:.1f}"
        return (
            f"{self.name} no frames"
            if not self.delivered
            else f"{self.name} {self.delivered} frame(s), no rate"
        )


@dataclass(frozen=True)
class LiveSummary:
    """How a live run went: the run's summary plus the live figures.

    latencies_ms : (F,) per frame written, from the capture of its last image to its
        result being written, ms.
    dropped : frame-sets dropped because the reconstruction fell behind.
    stopped_by : "a signal" (Ctrl-C, SIGTERM, SIGHUP), "--duration", "the end of the replay",
        "the cameras ending", ``STOPPED_FOR_ROOM`` or ``STOPPED_BY_FAULT``.
    cameras : per camera, in calibration order, how it went.
    stop_line : where the run stopped early for a problem (room on its disk, a camera's
        fault after frames were written), the line that says so ("" otherwise).
    """

    run: RunSummary
    latencies_ms: np.ndarray
    dropped: int
    stopped_by: str = ""
    cameras: tuple[CameraSummary, ...] = ()
    stop_line: str = ""

    def camera(self, name: str) -> CameraSummary:
        """The camera named ``name``."""
        return next(c for c in self.cameras if c.name == name)

    @property
    def lost_cameras(self) -> list[CameraSummary]:
        """The cameras down at the end of a run in which another was not: the rig lost them
        (all down together is the cameras' end, not a fault)."""
        down = [c for c in self.cameras if c.down_at_end]
        return down if len(down) < len(self.cameras) else []

    @property
    def exit_code(self) -> int:
        """The run's; 1 at least where a camera delivered nothing or was lost for good, a
        replay ended short, the run stopped early for a problem or dropped frame-sets."""
        silent = any(c.silent for c in self.cameras) or bool(self.lost_cameras)
        early = bool(self.stop_line) or self.dropped > 0
        return max(self.run.exit_code, int(silent or bool(self.replay_lines()) or early))

    def latency_ms(self, percentile: float) -> float:
        return float(np.percentile(self.latencies_ms, percentile)) if len(self.latencies_ms) else float("nan")

    def outage_lines(self) -> list[str]:
        lines = [self.stop_line] if self.stop_line else []
        if self.dropped:
            lines.append(
                f"  dropped: {self.dropped} frame-sets: the reconstruction fell behind the cameras "
                "(docs/live.md; --no-images lightens each frame)"
            )
        if not self.run.frames_total:
            by_stop = self.stopped_by in ("--duration", "a signal")
            when = f" before the run was stopped by {self.stopped_by}" if by_stop else ""
            lines.append(f"  no frame-set arrived{when}; nothing written")
        for cam in self.cameras:
            if cam.silent:
                why = cam.outages[0] if cam.outages else "its source opened no stream before the run ended"
                lines.append(
                    f"  camera {cam.name}: delivered no frame ({why}); check its source in [live] in "
                    "session.toml, and that the camera is on or its stream is sent"
                )
            elif cam.outages:
                state = "down at the end" if cam.down_at_end else "picked up again"
                stopped = f"stopped {len(cam.outages)} time(s), {state}"
                line = f"  camera {cam.name}: {stopped} (first: {cam.outages[0]})"
                if cam in self.lost_cameras:
                    line += (
                        f"; the other cameras' frames after it stopped had no set ({cam.delivered} of "
                        "its frames delivered): check the camera and its connection"
                    )
                lines.append(line)
        return lines

    def replay_lines(self) -> list[str]:
        """A replayed camera whose frames ended well before the others' (its video cut short,
        by more than ``process`` lets videos differ) or that is damaged past them: the
        others' later frames had no set."""
        if not self.cameras or not all(c.is_replay for c in self.cameras):
            return []  # not a replay
        if self.stopped_by != "the end of the replay":
            return []  # stopped before the videos' ends: they are not known to end short
        most = max(c.delivered for c in self.cameras)
        allowed = max(SHORT_VIDEO_FRAMES, SHORT_VIDEO_FRACTION * most)  # as process allows
        lines = []
        for cam in self.cameras:
            if most - cam.delivered > allowed or cam.cut_short:
                ends = (
                    f"it is damaged there: {cam.cut_short}"
                    if cam.cut_short
                    else "its video ends there: cut short?"
                )
                lines.append(
                    f"  camera {cam.name}: its replay ended after {cam.delivered} of the {most} frames the "
                    f"others gave ({ends}); the frames after had no set: re-export the video"
                )
        return lines

    def problem_lines(self) -> list[str]:
        """The run's failure and warning lines, then the cameras that stopped or ended short."""
        return self.run.problem_lines() + self.outage_lines() + self.replay_lines()

    def live_lines(self) -> list[str]:
        rates = ", ".join(c.rate() for c in self.cameras)
        unmatched = sum(c.unmatched for c in self.cameras)
        latency = (
            f"latency p50 {self.latency_ms(50):.1f} ms, p99 {self.latency_ms(99):.1f} ms"
            if len(self.latencies_ms)
            else "no frame-set written, so no latency"
        )
        return [
            f"live: stopped by {self.stopped_by}; {latency}; {self.dropped} frame-sets dropped, "
            f"{unmatched} frames unmatched",
            f"  cameras (frames/s): {rates}",
        ]

    def lines(self) -> list[str]:
        """The run's summary with the cameras that stopped and the live lines before its time
        and files."""
        lines = self.run.lines()
        at = next((i for i, line in enumerate(lines) if line.startswith("time:")), len(lines))
        return lines[:at] + self.outage_lines() + self.replay_lines() + self.live_lines() + lines[at:]

    def to_dict(self) -> dict[str, Any]:
        """:meth:`RunSummary.to_dict` with the live figures under "live" (null where unknown)."""
        return self.run.to_dict() | {
            "exit_code": self.exit_code,
            "problems": [line.strip() for line in self.problem_lines()],
            "live": {
                "stopped_by": self.stopped_by,
                "latency_ms": {"p50": _finite(self.latency_ms(50)), "p99": _finite(self.latency_ms(99))},
                "frames_dropped": self.dropped,
                "frames_unmatched": {c.name: c.unmatched for c in self.cameras},
                "camera_fps": {c.name: _finite(c.fps) for c in self.cameras},
                "outages": {c.name: list(c.outages) for c in self.cameras},
            },
        }


def _finite(value: float) -> float | None:
    return value if np.isfinite(value) else None  # JSON has no NaN


def run_live(
    rig: Session,
    sources: Sequence[Source],
    *,
    out_dir: Path,
    viewer_url: str | None = None,
    foxglove: tuple[str, int] | None = None,
    duration_s: float | None = None,
    images: bool = True,
    force: bool = False,
    queue_sets: int = QUEUE_SETS,
) -> LiveSummary:
    """Reconstruct ``rig``'s cameras live into ``out_dir/<rig name>.mcap`` and ``.rrd``.

    Parameters
    ----------
    rig : the rig's cameras and settings (:func:`pipeline.session.folder.load_rig`, or a
        session when replaying it).
    sources : per camera of ``rig``, in its order, where its frames come from.
    out_dir : output directory, created if needed.
    viewer_url : also stream the Rerun recording to this viewer's gRPC URL.
    foxglove : (host, port) of a Foxglove WebSocket server to publish the MCAP's topics on.
    duration_s : stop after this many seconds (None: at Ctrl-C, or the end of a replay).
    images : store (and stream) the camera images.
    force : replace existing outputs (when the run stops).
    queue_sets : frame-sets that may wait for the reconstruction before the oldest is
        dropped, once the run has settled (a replay that must keep every frame, as the
        tests', passes many; see :mod:`.handoff`).

    Raises
    ------
    OutputError, SettingsError : before any frame, as ``process``.
    SessionError : a camera's frames do not fit its calibration, or a replay cannot be
        read; nothing is left behind.

    A run that no frame-set reached writes no recording (its summary lists no output,
    and exits 1), and removes the folders it made for them.
    """
    if foxglove is not None:
        check_foxglove(*foxglove)  # not seconds into the run, once the model is built
    with signals_interrupt():
        target = prepare_outputs(Path(out_dir), rig.name, force)
        written = False
        try:
            summary = _run(rig, sources, target, viewer_url, foxglove, duration_s, images, queue_sets)
            written = bool(summary.run.outputs)
        finally:
            target.release(failed=not written)
    return summary


def _model(rig: Session, sources: Sequence[Source]) -> tuple[Any, str, str]:
    """The per-session model; a replay chooses its tube end and reads the tube's radius along
    it from its videos, as ``process`` does where it keeps the given cameras. With it, why
    every frame's tip is in doubt ("" where it is not: see
    :attr:`pipeline.reconstruct.tip_shape.TipChoice.doubt`), and the end assumed and how it
    was chosen (for the recordings' metadata)."""
    from ..calibrate.refine import sample_evidence, sample_session
    from ..calibrate.video_order import check_video_order
    from ..reconstruct.frame import check_declared_radius
    from ..reconstruct.model import build_model
    from ..reconstruct.tip_shape import end_assumed, with_session_tip

    model = build_model(rig)
    if rig.settings.manipulator.tip == "auto" and not all(s.is_replay for s in sources):
        log.warning(
            '[manipulator] tip = "auto" is chosen from a session\'s frames; a live rig assumes a '
            'flat end: set tip = "flat" or "round" in %s',
            rig.directory / "session.toml",
        )
    if sources and all(s.is_replay for s in sources):
        from ..session.video import probe_video

        paths = [Path(s.url) for s in sources]
        frames = min(probe_video(p).frame_count for p in paths)
        samples = sample_session(paths, 0, frames)
        check_video_order(model, samples, paths)
        check_declared_radius(model, samples, rig.directory / "session.toml")
        read, radii = sample_evidence(model, samples)
        model, choice = with_session_tip(model, paths, 0, frames, read=read, session_radii=radii)
        return model, choice.doubt if choice is not None else "", end_assumed(model, choice)
    return model, "", end_assumed(model, None)


def _run(
    rig: Session,
    sources: Sequence[Source],
    target: OutputTarget,
    viewer_url: str | None,
    foxglove: tuple[str, int] | None,
    duration_s: float | None,
    images: bool,
    queue_sets: int,
) -> LiveSummary:
    t0 = time.perf_counter()
    names = [c.name for c in rig.cameras]
    free = free_bytes(target.out_dir)
    if free < finish_room_bytes(0):
        raise OutputError(
            f"{target.out_dir}: its disk has {_mib(free)} free, and a live run keeps "
            f"{_mib(finish_room_bytes(0))} to finish its recordings in; free space or choose another --out"
        )
    model, doubt, tube_end = _model(rig, sources)
    server = None
    writer: Writers | None = None
    stop = threading.Event()
    readers: list[CameraReader] = []
    restarts = RestartWorker(model)
    try:
        if foxglove is not None:
            from .stream import FoxgloveServer

            server = FoxgloveServer(*foxglove, name=f"pipeline live {rig.name}")
            log.info("Foxglove: %s (in Foxglove: Open connection, Foxglove WebSocket)", server.address)
        writer = Writers(
            rig,
            target,
            images=images,
            viewer_url=viewer_url,
            mirror=server,
            cameras_used=LIVE_CAMERAS,
            tube_end=tube_end,
            radius_profile=model.radius_profile,
            frame_doubt=doubt,
        )
        queue = DroppingQueue(queue_sets)
        matcher = FrameMatcher(len(sources), half_period_ns(rig.fps))
        lock = threading.Lock()

        def deliver(frame: CapturedFrame) -> None:
            with lock:
                # Half a period of the slowest camera, from the rates the streams declare
                # once open (a replay's: its videos'); the rig's nominal rate until then.
                rates = [r.rate_fps for r in readers if r.rate_fps]
                matcher.tolerance_ns = half_period_ns(min(rates) if rates else rig.fps)
                for frame_set in matcher.add(frame):
                    queue.put(frame_set)

        restarts.wait_ready(RESTARTS_READY_S)
        start_ns = time.monotonic_ns()
        readers = [
            CameraReader(k, s, rig.cameras[k].size_px, deliver, stop, start_ns=start_ns)
            for k, s in enumerate(sources)
        ]
        for reader in readers:
            reader.start()
        log.info(
            "capturing %s; Ctrl-C (or SIGTERM) stops and writes %s and %s",
            ", ".join(s.describe() for s in sources),
            target.mcap_path,
            target.rrd_path,
        )
        latencies, stopped_by, fault = _loop(
            readers, queue, writer, model, names, images, duration_s, restarts
        )
        stop_line = ""
        if stopped_by == STOPPED_BY_FAULT:
            stop_line = f"  {fault}; the run stopped there, after {len(latencies)} frame-sets, and kept them"
        if stopped_by == STOPPED_FOR_ROOM:
            stop_line = (
                f"  {target.out_dir}: its disk had {_mib(free_bytes(target.out_dir))} left: the run stopped "
                f"after {len(latencies)} frame-sets to finish its recordings with them; free space or "
                "choose another --out"
            )
        try:
            with deferred_signals():  # from here a signal waits for the recordings to be complete
                _stop_readers(stop, readers)
                if latencies:  # one per frame-set written
                    writer.finish()
                else:  # an empty recording would only stand in the way of the next run's
                    writer.abort()
        except KeyboardInterrupt:
            if not writer.committed:
                raise
            # A signal while finishing: the run was ending anyway, and its recordings are complete.
    except BaseException as exc:
        if not stop.is_set():  # not stopped already on the way out
            # Bad input, named in one line (a camera's source that never opens): the other
            # readers, still waiting on their sources, are not blamed for it.
            _stop_readers(stop, readers, warn=not isinstance(exc, SessionError))
        if writer is not None and not writer.committed:
            writer.abort()
        raise
    finally:
        restarts.close()
        if server is not None:
            server.stop()
    return LiveSummary(
        run=dataclasses.replace(writer.summary(time.perf_counter() - t0), tip=tube_end, cameras=LIVE_CAMERAS),
        latencies_ms=np.asarray(latencies, dtype=np.float64),
        dropped=queue.dropped,
        stopped_by=stopped_by,
        stop_line=stop_line,
        cameras=tuple(
            CameraSummary(
                name=name,
                fps=reader.stats.fps,
                delivered=reader.stats.frames,
                unmatched=unmatched,
                outages=tuple(reader.stats.outages),
                down_at_end=reader.down,
                cut_short=reader.cut_short if reader.source.is_replay else None,
            )
            for name, reader, unmatched in zip(names, readers, matcher.unmatched_at_end, strict=True)
        ),
    )


def _loop(
    readers: Sequence[CameraReader],
    queue: DroppingQueue,
    writer: Writers,
    model: Any,
    names: Sequence[str],
    images: bool,
    duration_s: float | None,
    restarts: RestartWorker,
) -> tuple[list[float], str, str]:
    """Reconstruct and write frame-sets until the run stops; (latencies in ms, why it stopped,
    and a camera's fault that stopped it after frames were written, "" for none: before any,
    the fault is raised, a SessionError, and nothing is written)."""
    # A frame whose track is lost waits for its start from the hull as long as a frame-set
    # can still wait in the queue behind it: its result is then process's.
    tracker = Tracker(
        model, names, images=images, restarts=restarts, may_wait=lambda: len(queue) + 1 < queue.capacity
    )
    # Frame times in the recordings: the arrival of the frame's last image, on the wall clock.
    wall_from_monotonic_ns = time.time_ns() - time.monotonic_ns()
    deadline = None if duration_s is None else time.monotonic() + duration_s
    latencies: list[float] = []
    try:
        while True:
            if deadline is not None and time.monotonic() >= deadline:
                return latencies, "--duration", ""
            frame_set = queue.get(POLL_S)
            if frame_set is None:
                for reader in readers:
                    if reader.fault is not None:
                        # A camera that turns faulty mid-run (restarted at another size) ends
                        # the run, its frames so far kept: they cannot be filmed again.
                        if latencies:
                            return latencies, STOPPED_BY_FAULT, reader.fault
                        raise SessionError(reader.fault)
                    if reader.crash is not None:
                        raise reader.crash
                if all(r.finished.is_set() for r in readers) and not len(queue):
                    replay = all(r.source.is_replay for r in readers)
                    return latencies, "the end of the replay" if replay else "the cameras ending", ""
                continue
            # A signal waits for the frame to be written whole: the recordings stay consistent.
            with deferred_signals():
                out = tracker.step(frame_set.index, frame_set.images)
                latency_ms = (time.monotonic_ns() - frame_set.last_arrival_ns) * 1e-6
                writer.write(
                    out,
                    time_ns=frame_set.last_arrival_ns + wall_from_monotonic_ns,
                    extra_metrics={"latency_ms": latency_ms},
                )
                latencies.append(latency_ms)
                queue.settle()
            if free_bytes(writer.target.out_dir) < finish_room_bytes(len(latencies)):
                return latencies, STOPPED_FOR_ROOM, ""
    except KeyboardInterrupt:
        return latencies, "a signal", ""


def finish_room_bytes(frame_sets: int) -> int:
    """The room (bytes) a live run keeps on its disk to finish recordings of ``frame_sets``."""
    return FINISH_ROOM_BYTES + FINISH_ROOM_PER_SET_BYTES * frame_sets


def free_bytes(directory: Path) -> int:
    """The bytes this user may still write on the disk that holds ``directory`` (as many as
    can be where the disk cannot be asked: the folder removed under the run, whose writes
    then fail on their own)."""
    try:
        return shutil.disk_usage(directory).free
    except OSError:
        return sys.maxsize


def _mib(size_bytes: int) -> str:
    return f"{size_bytes / (1 << 20):.1f} MiB"


def _stop_readers(stop: threading.Event, readers: Sequence[CameraReader], *, warn: bool = True) -> None:
    """Stop the readers and wait for them (``JOIN_S`` at most), warning (``warn``) of each
    still blocked in its source."""
    stop.set()
    # One wait for all of them: readers that stay blocked (daemon threads) cost the run
    # JOIN_S once, not once each.
    deadline = time.monotonic() + JOIN_S
    for reader in readers:
        reader.join(max(0.0, deadline - time.monotonic()))
    for reader in readers:
        if warn and reader.alive:  # blocked inside its source (a device or stream that hangs)
            log.warning(
                "%s: its reader was still waiting on the source %g s after the run stopped; "
                "the run ended without it (check the camera and its connection)",
                reader.source.describe(),
                JOIN_S,
            )
