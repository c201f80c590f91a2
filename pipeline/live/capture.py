"""One reader thread per camera: open its source with PyAV, decode, stamp each frame on arrival.

A reader hands every frame, as an (H, W) uint8 grey image with its arrival time, to
a callback (the frame matcher). A camera that stalls (no frame within ``stall_s``),
ends or cannot be opened is reported once per outage and opened again every
``retry_s`` until the run stops; the other cameras go on meanwhile. A replayed
video is paced at its frame rate from the run's common start, stamped with the time
it is due (when a camera would have delivered it), and ends with its last frame.
"""

from __future__ import annotations

import logging
import os
import stat
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..session.video import Greyer
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
# A camera that is down is tried again this often.
RETRY_S = 1.0


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
        # Why a replay's frames ended before its video did (damaged past them): "" where not.
        self.cut_short = ""
        self.down = False  # an outage was reported and no frame has come since
        self._thread = threading.Thread(target=self._run, name=f"camera-{source.camera}", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def join(self, timeout_s: float) -> None:
        self._thread.join(timeout_s)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def wake(self) -> None:
        """Let a reader waiting to open a named pipe that nothing writes to see the stop.

        FFmpeg opens a named pipe blocking, until a writer opens it too: no timeout reaches
        it there. Opening the pipe's writing end and closing it at once ends that wait (the
        stream is then empty, and the reader, seeing the stop, returns). Called after the
        stop is set; a reader doing anything else is left alone.
        """
        if self.source.is_replay or not self._thread.is_alive():
            return
        try:
            if stat.S_ISFIFO(os.stat(self.source.url).st_mode):
                # Fails (ENXIO) where no reader has the pipe open: nothing waits on it then.
                os.close(os.open(self.source.url, os.O_WRONLY | os.O_NONBLOCK))
        except OSError:  # not a path, or no reader waiting on it
            pass

    def _run(self) -> None:
        reported_at: int | None = None  # frames delivered when the last outage was reported
        try:
            while not self._stop.is_set():
                try:
                    self._read()
                    why = "the stream ended"
                except SourceFault as exc:
                    self.fault = str(exc)
                    return
                except Exception as exc:  # FFmpeg's errors: refused, timed out, no such device
                    why = " ".join(str(exc).split())[:200] or type(exc).__name__
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
                        "%s: %s; the other cameras go on, retrying every %g s",
                        self.source.describe(),
                        why,
                        self._retry_s,
                    )
                self._stop.wait(self._retry_s)
        finally:
            self.finished.set()

    def _open(self) -> Any:
        import av

        options = {}
        if self.source.format == V4L2_FORMAT:
            options["video_size"] = f"{self.size_px[0]}x{self.size_px[1]}"
        elif not self.source.is_replay:
            # A stream's frames are stamped as they arrive: FFmpeg's probing would hold the
            # first ones back and hand them over at once, stamped alike.
            options.update(LOW_DELAY_OPTIONS)
        timeout = None if self.source.is_replay else (OPEN_TIMEOUT_S, self._stall_s)
        try:
            return av.open(self.source.url, format=self.source.format, options=options, timeout=timeout)
        except av.error.ProtocolNotFoundError:
            # Never opens, however often it is tried: a typo (rtps://) or another program's URL.
            scheme = self.source.url.partition(":")[0]
            raise SourceFault(
                f"{self.source.describe()}: FFmpeg reads no {scheme}: URLs; fix the camera's source "
                "in [live] in session.toml (rtsp://, udp://, tcp://, http://, srt://, ...)"
            ) from None

    def _read(self) -> None:
        container = self._open()
        try:
            stream = container.streams.video[0]
            rate = stream.average_rate or stream.guessed_rate
            if rate and not self.source.is_replay:
                self.rate_fps = float(rate)
            greyer = Greyer()
            for k, frame in enumerate(container.decode(stream)):
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
        finally:
            container.close()

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
