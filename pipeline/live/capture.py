"""One reader thread per camera: open its source with PyAV, decode, stamp each frame on arrival.

A reader hands every frame, as an (H, W) uint8 grey image with its arrival time, to
a callback (the frame matcher). A camera that stalls (no frame within ``stall_s``),
ends or cannot be opened is reported once per outage and opened again every
``retry_s`` until the run stops; the other cameras go on meanwhile. A replayed
video is paced at its frame rate from the run's common start, stamped with the time
it is due (when a camera would have delivered it), and ends with its last frame.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import stat
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import av
import numpy as np
from numpy.typing import NDArray

from ..errors import VideoError
from ..session.video import Greyer
from .reasons import ffmpeg_text, outage_reason, unresolved_host
from .sources import V4L2_FORMAT, Source
from .sync import CapturedFrame

log = logging.getLogger(__name__)

# No frame for this long: the camera has stalled (reported, then opened again).
STALL_S = 2.0
# Opening a source may take this long (a stream's first packets, a device's start).
OPEN_TIMEOUT_S = 5.0
# FFmpeg options for a network stream: probe as little as will find the stream, and
# pass packets on as they come.
LOW_DELAY_OPTIONS = {"fflags": "nobuffer", "probesize": "32768", "analyzeduration": "0"}
# Packets a stream may fail to decode before its first frame, passed over: a stream joined
# between two keyframes, or opened with ``nobuffer`` (which drops the packets FFmpeg
# probed), starts with packets that refer to ones the decoder never had. H.264's decoder
# passes over them itself; FFV1's raises. Ten seconds at 30 fps.
JOIN_PACKETS = 300
# A camera that is down is tried again this often.
RETRY_S = 1.0
# A named pipe is waited on in slices this long, each ending with a look at the run's stop.
PIPE_POLL_S = 0.1
# What a source that cannot be read, or stops being read, raises: FFmpeg's errors (refused,
# timed out, no such device, damaged data), the system's (a named pipe's), and the pipeline's.
SOURCE_ERRORS = (av.error.FFmpegError, OSError, VideoError)


@dataclass
class CameraStats:
    """What a camera delivered: frames, first and last arrival (monotonic ns), outages."""

    frames: int = 0
    first_ns: int | None = None
    last_ns: int | None = None
    outages: list[str] = field(default_factory=list)

    def add(self, arrived_ns: int) -> None:
        self.frames += 1
        if self.first_ns is None:
            self.first_ns = arrived_ns
        self.last_ns = arrived_ns

    @property
    def fps(self) -> float:
        """Frames per second between its first and last frame (NaN with fewer than two)."""
        if self.frames < 2 or self.first_ns is None or self.last_ns is None or self.last_ns <= self.first_ns:
            return float("nan")
        return (self.frames - 1) * 1e9 / (self.last_ns - self.first_ns)


class SourceFault(Exception):
    """A camera's frames cannot be used as they are (wrong size): the run stops, named."""


class PipeStalled(OSError):
    """A named pipe's writer holds it open but has written nothing for the stall time."""


class PipeFile:
    """A named pipe's reading end as a file for FFmpeg, whose reads see the run's stop.

    FFmpeg reads a pipe in blocking reads that nothing but data or the writer's close
    ends, so a writer that stalls with the pipe open would hold the reader past the run.
    Here the pipe is opened without waiting for a writer, and each read waits for data in
    slices of ``poll_s``: it returns nothing (the stream's end) once ``stop`` is set, and
    raises :class:`PipeStalled` where data came once and then none for ``stall_s``. Before
    any data it waits for a writer as long as the run goes on, as FFmpeg's open would.
    """

    def __init__(self, path: str, stop: threading.Event, stall_s: float, poll_s: float = PIPE_POLL_S) -> None:
        self._fd: int | None = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
        self._poll = select.poll()
        self._poll.register(self._fd, select.POLLIN)
        self._stop, self._stall_s, self._poll_s = stop, stall_s, poll_s
        self._started = False  # data has come

    def read(self, size: int) -> bytes:
        """Up to ``size`` bytes, b"" at the stream's end or the run's stop."""
        assert self._fd is not None, "read after close"
        waited_s = 0.0
        while not self._stop.is_set():
            if self._started and waited_s >= self._stall_s:
                raise PipeStalled(f"no data for {self._stall_s:g} s: its writer stalled")
            if self._poll.poll(self._poll_s * 1e3):
                try:
                    data = os.read(self._fd, size)
                except BlockingIOError:  # another reader of the pipe took the data
                    continue
                self._started = self._started or bool(data)
                return data  # b"": every writer closed it
            waited_s += self._poll_s
        return b""

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


class CameraReader:
    """Reads one camera's source in a thread of its own.

    Parameters
    ----------
    camera : the camera's index in calibration order.
    source : what to open.
    size_px : (width, height) the calibration gives the camera.
    deliver : called, in this reader's thread, with each frame.
    stop : set by the run to stop every reader.
    start_ns : the run's common start (monotonic ns): a replay is paced from it.
    """

    def __init__(
        self,
        camera: int,
        source: Source,
        size_px: tuple[int, int],
        deliver: Callable[[CapturedFrame], None],
        stop: threading.Event,
        *,
        start_ns: int,
        stall_s: float = STALL_S,
        retry_s: float = RETRY_S,
    ) -> None:
        self.camera, self.source, self.size_px = camera, source, size_px
        self._deliver, self._stop = deliver, stop
        self._start_ns, self._stall_s, self._retry_s = start_ns, stall_s, retry_s
        self.stats = CameraStats()
        self.rate_fps: float | None = source.replay_fps  # the stream's declared rate, once open
        self.finished = threading.Event()  # a replay ended, or the reader stopped
        self.fault: str | None = None  # why the run must stop (set with ``finished``)
        # An error that is no source's (a bug): the run raises it again (set with ``finished``).
        self.crash: Exception | None = None
        # Why a replay's frames ended before its video did (damaged past them): "" where not.
        self.cut_short = ""
        self.down = False  # an outage was reported and no frame has come since
        self._opened = False  # the source of the current attempt opened
        self._thread = threading.Thread(target=self._run, name=f"camera-{source.camera}", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def join(self, timeout_s: float) -> None:
        """Wait up to ``timeout_s`` for the reader to stop; at once if it never started (a
        signal while the run started its readers)."""
        if self._thread.ident is not None:
            self._thread.join(timeout_s)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def _run(self) -> None:
        reported_at: int | None = None  # frames delivered when the last outage was reported
        try:
            while not self._stop.is_set():
                check = ""  # what to check, for the warning
                try:
                    self._read()
                    why = "the stream ended"
                except SourceFault as exc:
                    self.fault = str(exc)
                    return
                except SOURCE_ERRORS as exc:
                    if self.source.is_replay:
                        why = ffmpeg_text(exc)
                    elif host := unresolved_host(self.source.url):
                        why = f"cannot resolve the host {host!r}"
                        check = "check the URL's host name and the network"
                    else:
                        why, check = outage_reason(
                            exc, opened=self._opened, open_timeout_s=OPEN_TIMEOUT_S, stall_s=self._stall_s
                        )
                except Exception as exc:  # no source's error: handed to the run, which raises it
                    self.crash = exc
                    return
                if self._stop.is_set():
                    return
                if self.source.is_replay:
                    if why != "the stream ended" and not self.stats.frames:
                        self.fault = f"{self.source.describe()}: cannot be replayed ({why})"
                    elif why != "the stream ended":
                        # Damaged part-way: the frames before stand, as in ``process``.
                        self.cut_short = why
                    return
                if reported_at != self.stats.frames:  # a new outage, not the same one again
                    reported_at = self.stats.frames
                    self.stats.outages.append(why)
                    self.down = True
                    log.warning(
                        "%s: %s%s; the other cameras go on, retrying every %g s",
                        self.source.describe(),
                        why,
                        f" ({check})" if check else "",
                        self._retry_s,
                    )
                self._stop.wait(self._retry_s)
        finally:
            self.finished.set()

    def _open(self, pipe: PipeFile | None) -> Any:
        """The source opened by FFmpeg, read through ``pipe`` where it is a named pipe."""
        options = {}
        if self.source.format == V4L2_FORMAT:
            options["video_size"] = f"{self.size_px[0]}x{self.size_px[1]}"
        elif not self.source.is_replay:
            # A stream's frames are stamped as they arrive: FFmpeg's probing would hold the
            # first ones back and hand them over at once, stamped alike.
            options.update(LOW_DELAY_OPTIONS)
        # The pipe's reads see the stop and time out themselves (FFmpeg's cannot).
        timeout = None if self.source.is_replay or pipe is not None else (OPEN_TIMEOUT_S, self._stall_s)
        try:
            return av.open(
                pipe or self.source.url, format=self.source.format, options=options, timeout=timeout
            )
        except av.error.ProtocolNotFoundError:
            # Never opens, however often it is tried: a typo (rtps://) or another program's URL.
            scheme = self.source.url.partition(":")[0]
            raise SourceFault(
                f"{self.source.describe()}: FFmpeg reads no {scheme}: URLs; fix the camera's source "
                "in [live] in session.toml (rtsp://, udp://, tcp://, http://, srt://, ...)"
            ) from None

    def _read(self) -> None:
        self._opened = False
        with contextlib.ExitStack() as held:  # closed in reverse: the container, then the pipe
            pipe = None
            if not self.source.is_replay and _is_pipe(self.source.url):
                pipe = held.enter_context(
                    contextlib.closing(PipeFile(self.source.url, self._stop, self._stall_s))
                )
            container = held.enter_context(self._open(pipe))
            self._opened = True
            if not container.streams.video:
                raise VideoError("it holds no video stream")
            stream = container.streams.video[0]
            rate = stream.average_rate or stream.guessed_rate
            if rate and not self.source.is_replay:
                self.rate_fps = float(rate)
            greyer = Greyer()
            frames = container.decode(stream) if self.source.is_replay else _joined(container, stream)
            for k, frame in enumerate(frames):
                # Stamped before anything else is done with it: the grey conversion waits for
                # the interpreter's lock, for longer when the run is busy.
                arrived_ns = time.monotonic_ns()
                if self._stop.is_set():
                    return
                if (frame.width, frame.height) != self.size_px:
                    raise SourceFault(
                        f"{self.source.describe()}: frames are {frame.width}x{frame.height} but "
                        f"calibration.toml gives {self.size_px[0]}x{self.size_px[1]}; set the camera "
                        "to the calibrated resolution, or use this resolution's calibration"
                    )
                self._hand_over(k, arrived_ns, greyer(frame))

    def _hand_over(self, k: int, arrived_ns: int, image: NDArray[np.uint8]) -> None:
        if self.source.replay_fps is not None:
            # A replayed frame arrives when a camera would have delivered it: frame k of
            # every camera at the same moment from the common start.
            due_ns = self._start_ns + round(k * 1e9 / self.source.replay_fps)
            wait_s = (due_ns - time.monotonic_ns()) * 1e-9
            if wait_s > 0 and self._stop.wait(wait_s):
                return
            arrived_ns = due_ns
        if self.down:
            self.down = False
            log.warning("%s: frames again", self.source.describe())
        self.stats.add(arrived_ns)
        self._deliver(CapturedFrame(self.camera, arrived_ns, image))


def _joined(container: Any, stream: Any) -> Iterator[Any]:
    """``stream``'s frames, passing over the packets that fail to decode before the first
    frame (at most :data:`JOIN_PACKETS`); a failure after it is raised."""
    decoded = passed = 0
    for packet in container.demux(stream):
        try:
            frames = packet.decode()
        except av.error.InvalidDataError:
            if decoded or passed >= JOIN_PACKETS:
                raise
            passed += 1
            continue
        decoded += len(frames)
        yield from frames


def _is_pipe(path: str) -> bool:
    """``path`` is a named pipe (False where it is not a path, or not there)."""
    try:
        return stat.S_ISFIFO(os.stat(path).st_mode)
    except (OSError, ValueError):
        return False
