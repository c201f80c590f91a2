"""A lost track started again from the hull on another core, while the live frames go on.

A start from the hull (the march and its hypotheses,
:func:`pipeline.reconstruct.centerline.fit_centerline`) takes 150-350 ms on a loop: ten
frames at 30 fps. Where a live run's track is lost, the frame is computed here, in a
process of its own, as ``process`` computes it (started again from the hull), and the
run's thread waits for it only while no frame-set would be dropped for it. If it is not
done by then, the run's frames go on from the lost track, flagged suspect, while the
started track follows them here, frame after frame (a tracked frame costs a fraction of
a camera's period, so it catches up); once it has, it takes over
(:class:`~pipeline.reconstruct.frame_task.Tracker`). A lost track costs flagged frames, not
dropped ones, and from the take-over on the track is the one ``process`` would have.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import signal
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, wait
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..reconstruct.frame_result import FrameResult
from ..reconstruct.tracking import LENGTH_FRAMES
from ..run.interrupts import deferred_signals, signals_blocked_in_children
from ..run.workers import exit_with_parent, shared_file

log = logging.getLogger(__name__)

# How often a frame waiting for the started track looks up whether it can go on waiting.
WAIT_POLL_S = 0.002
# A started track this many frames behind the run's is given up (a machine too slow for it
# to catch up): the run's track starts again the next time it is lost.
MAX_BEHIND_FRAMES = 60

# In the worker: the session's model (set once, as it starts) and the started track.
_model: Any = None
_track: list[FrameResult] = []


def _take_model(path: str, parent_pid: int) -> None:
    import joblib

    exit_with_parent(parent_pid)  # a run killed outright leaves no worker behind
    global _model
    try:
        _model = joblib.load(path, mmap_mode="r")
    except FileNotFoundError:  # the run ended (and removed it) before this worker started
        os._exit(0)
    # Ctrl-C reaches the whole process group: the run, not this worker, decides what it means.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from ..reconstruct import frame  # noqa: F401  (imported now, not at the first start)


def _ready() -> None:
    """Nothing: submitted first, so that the worker starts and imports at once."""


def _step(
    index: int, images: Sequence[NDArray[np.uint8]], previous: Sequence[FrameResult] | None
) -> FrameResult:
    """Frame ``index`` of the started track, as ``process`` computes it, in the worker:
    ``previous`` (the run's track before it) starts the track, None goes on with it."""
    from ..reconstruct.frame import reconstruct_with_silhouettes

    global _track
    if previous is not None:
        _track = list(previous)
    try:
        result = reconstruct_with_silhouettes(index, images, _model, _track)[0]
    except Exception as exc:  # the frame's failure, not the worker's
        result = FrameResult.failed(index, f"{type(exc).__name__}: {exc}")
    _track = [*_track, result][-LENGTH_FRAMES:]
    return result


class RestartWorker:
    """One worker process that starts a lost track again from the hull and follows it
    until it has caught up (a :class:`~pipeline.reconstruct.frame_task.Restarts`).
    ``model``: the session's (:func:`pipeline.reconstruct.model.build_model`), written once
    to a file the worker maps (:func:`pipeline.run.workers.shared_file`)."""

    def __init__(self, model: Any) -> None:
        # The model goes to the worker as a file it maps, not through the pipe it is spawned
        # with: multiprocessing writes that pipe while it still holds the worker's end, so a
        # worker killed before it has read a model larger than the pipe (a terminal's signal
        # to the whole group) would leave the run waiting on the write for good.
        # What close() undoes, last first: the model's file, then the pool.
        self._resources = contextlib.ExitStack()
        path = self._resources.enter_context(shared_file(model))
        try:
            # The worker is spawned here, and the resource tracker with the pool's first
            # semaphore. A signal waits until the worker is under way, and both start with
            # Ctrl-C and a hang-up blocked, which a terminal sends its whole group: the run
            # handles them (the worker, still importing, would print a traceback; a tracker
            # killed by the hang-up would be started again by the run's exit, and its
            # successor print a KeyError per semaphore it is asked to forget).
            with deferred_signals(), signals_blocked_in_children():
                self._pool = ProcessPoolExecutor(
                    max_workers=1,
                    # Not forked: the run's capture threads hold locks a fork would copy held.
                    mp_context=multiprocessing.get_context("spawn"),
                    initializer=_take_model,
                    initargs=(str(path), os.getpid()),
                )
                self._resources.callback(self._pool.shutdown, wait=False, cancel_futures=True)
                self._warm: Future[None] = self._pool.submit(_ready)
        except BaseException:
            self._resources.close()
            raise
        # The started track: the run's track before it, and its own frames, in order.
        self._before: list[FrameResult] = []
        self._frames: list[Future[FrameResult]] = []
        self._started_at = -1
        self._failed = False

    @property
    def available(self) -> bool:
        return not self._failed

    @property
    def under_way(self) -> bool:
        return bool(self._frames)

    @property
    def behind(self) -> int:
        """Frames given to the started track that it has yet to fit."""
        return sum(not f.done() for f in self._frames)

    @property
    def nearly_caught_up(self) -> bool:
        return len(self._frames) > 1 and self._frames[-2].done()

    def wait_ready(self, timeout_s: float) -> None:
        """Wait until the worker has started (spawned and imported, ~1 s), so that it does
        not compete with the first frames for the cores."""
        try:
            self._warm.result(timeout_s)
        except Exception as exc:  # a worker that cannot start: the run goes on without it
            self._fail(exc)

    def start(self, index: int, images: Sequence[NDArray[np.uint8]], previous: Sequence[FrameResult]) -> bool:
        if self._failed or self._frames:
            return False
        self._before, self._started_at = list(previous), index
        return self._submit(index, images, self._before)

    def follow(self, index: int, images: Sequence[NDArray[np.uint8]]) -> None:
        if not self._frames:
            return
        if self.behind >= MAX_BEHIND_FRAMES:
            log.warning(
                "the track started again from the hull at frame %d fell %d frames behind; given up",
                self._started_at,
                MAX_BEHIND_FRAMES,
            )
            self._give_up()
            return
        self._submit(index, images, None)

    def caught_up(self, may_wait: Callable[[], bool]) -> list[FrameResult] | None:
        """The started track's results (the run's before it first, oldest first, at most
        ``LENGTH_FRAMES``) once it has every frame given to it, waiting for that as long as
        ``may_wait()`` says the caller can; None until then. Its last result is the last
        frame given to it. Once returned, the start is over."""
        if not self._frames:
            return None
        last = self._frames[-1]
        while not last.done() and may_wait():
            wait([last], timeout=WAIT_POLL_S)
        if not last.done():
            return None
        try:
            results = [f.result() for f in self._frames]
        except Exception as exc:  # the worker died
            self._fail(exc)
            return None
        track = [*self._before, *results][-LENGTH_FRAMES:]
        self._before, self._frames = [], []
        return track

    def _submit(
        self, index: int, images: Sequence[NDArray[np.uint8]], previous: Sequence[FrameResult] | None
    ) -> bool:
        try:
            self._frames.append(self._pool.submit(_step, index, [np.asarray(im) for im in images], previous))
        except RuntimeError as exc:  # the pool broke (its process died) or was shut down
            self._fail(exc)
            return False
        return True

    def _give_up(self) -> None:
        for frame in self._frames:
            frame.cancel()
        self._before, self._frames = [], []

    def _fail(self, exc: BaseException) -> None:
        log.warning(
            "the restart worker stopped (%s): lost tracks start again from the hull in the run's "
            "own thread from here on",
            " ".join(str(exc).split()) or type(exc).__name__,
        )
        self._give_up()
        self._failed = True

    def close(self) -> None:
        """Stop the worker, without waiting for a start under way, and remove its model's
        file (a worker still running keeps its mapping)."""
        self._resources.close()
