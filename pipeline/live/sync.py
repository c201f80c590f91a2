"""Frames of several cameras matched into frame-sets by their arrival times.

Each camera's frames are stamped as they arrive (monotonic ns). A frame-set is one
frame per camera, all within half a frame period of each other; a frame that no
frame of every other camera comes close enough to is dropped. Pure bookkeeping:
no threads, no clocks (the caller stamps the frames and holds the lock).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

# Frames a camera may have waiting for the others: a camera whose partners stall for
# longer loses its oldest (counted), so that waiting never grows memory.
MAX_WAITING_FRAMES = 8
# A head this share of the tolerance or more before the latest camera's waits for the frame
# behind it before it is matched (see FrameMatcher.add): more than the jitter of cameras
# at one rate (a set's frames 10 ms apart at 30 fps stay prompt), less than a camera at
# twice the others' rate puts a stale head (a whole tolerance) before the latest.
_LOOSE_SHARE = 0.75


@dataclass(frozen=True, eq=False)
class CapturedFrame:
    """One camera's frame as it arrived.

    camera : the camera's index in calibration order.
    arrived_ns : monotonic clock at arrival (``time.monotonic_ns``).
    image : (H, W) uint8 grey image.
    """

    camera: int
    arrived_ns: int
    image: NDArray[np.uint8]


@dataclass(frozen=True, eq=False)
class FrameSet:
    """One frame per camera (calibration order), matched.

    index : the frame-set's number in the run, from 0 (frame-sets dropped later keep theirs).
    arrived_ns : per camera, the monotonic arrival time of its frame.
    """

    index: int
    images: tuple[NDArray[np.uint8], ...]
    arrived_ns: tuple[int, ...]

    @property
    def last_arrival_ns(self) -> int:
        """When the last of its images arrived: where its latency counts from."""
        return max(self.arrived_ns)


def head_action(heads_ns: Sequence[int], tolerance_ns: int) -> int | None:
    """What to do with the oldest frame of each camera, ``heads_ns`` (arrival, ns).

    Returns None when they all lie within ``tolerance_ns`` of each other (they form
    a set), else the camera whose head to drop: the earliest, which no later frame
    of the camera with the latest head can come closer to.
    """
    earliest = int(np.argmin(heads_ns))
    if max(heads_ns) - heads_ns[earliest] <= tolerance_ns:
        return None
    return earliest


class FrameMatcher:
    """Per camera, the frames waiting for the others'; :meth:`add` returns the sets it completes.

    tolerance_ns : frames of one set arrive within this of each other (half a frame period).
    """

    def __init__(self, cameras: int, tolerance_ns: int) -> None:
        self.tolerance_ns = tolerance_ns
        self._waiting: list[deque[CapturedFrame]] = [deque() for _ in range(cameras)]
        self._next_index = 0
        self.unmatched = [0] * cameras  # per camera, frames dropped without a set

    @property
    def unmatched_at_end(self) -> list[int]:
        """Per camera, its frames in no set once the run has stopped: those dropped, and
        those still waiting for a camera that sent no more (a replay's shorter video)."""
        pairs = zip(self.unmatched, self._waiting, strict=True)
        return [dropped + len(waiting) for dropped, waiting in pairs]

    def add(self, frame: CapturedFrame) -> list[FrameSet]:
        waiting = self._waiting[frame.camera]
        waiting.append(frame)
        if len(waiting) > MAX_WAITING_FRAMES:
            waiting.popleft()
            self.unmatched[frame.camera] += 1
        sets = []
        while all(self._waiting):
            heads = [w[0].arrived_ns for w in self._waiting]
            drop = head_action(heads, self.tolerance_ns)
            if drop is not None:
                self._waiting[drop].popleft()
                self.unmatched[drop] += 1
                continue
            # A head well before the latest may have a nearer frame behind it (a camera at
            # twice the others' rate, or the others at twice its): decided once that frame
            # has come, and dropped for it where it is nearer.
            latest = max(heads)
            early = [c for c, head in enumerate(heads) if latest - head > _LOOSE_SHARE * self.tolerance_ns]
            if any(len(self._waiting[c]) < 2 for c in early):
                break
            nearer = [c for c in early if abs(self._waiting[c][1].arrived_ns - latest) < latest - heads[c]]
            if nearer:
                for c in nearer:
                    self._waiting[c].popleft()
                    self.unmatched[c] += 1
                continue
            frames = [w.popleft() for w in self._waiting]
            sets.append(
                FrameSet(
                    self._next_index, tuple(f.image for f in frames), tuple(f.arrived_ns for f in frames)
                )
            )
            self._next_index += 1
        return sets


def half_period_ns(fps: float) -> int:
    """Half a frame period at ``fps`` frames/s, in ns: the matching tolerance."""
    return round(0.5e9 / fps)
