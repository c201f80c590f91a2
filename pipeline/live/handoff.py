"""The hand-off from capture to reconstruction: a short queue that drops its oldest.

Frame-sets wait here for the reconstruction. When it falls behind and the queue is
full, the oldest waiting set is dropped (and counted), never the newest: a live view
shows the latest shape, and memory stays bounded whatever the load. Until the run has
settled (its first frame out, the sets that waited for it taken), the queue holds more:
the first frame starts its track from the hull, which takes longer than a frame period.
"""

from __future__ import annotations

import threading
from collections import deque

from .sync import FrameSet

# Frame-sets that may wait: 67 ms at 30 fps, enough to ride out a slow frame (one that
# starts its track from the hull). Replaying the demo on a loaded machine, 2 dropped as
# few sets as 3 (60 and 64-86 in 20 s) at two thirds of the latency (p50 69 ms, not 114);
# 1 halved the latency again but dropped 99-151.
QUEUE_SETS = 2
# Frame-sets that may wait until the run has settled: half a second at 30 fps. The first
# frame starts its track from the hull on the run's own thread, 140-160 ms on the bench's
# loop (up to ~350 ms on others); held to QUEUE_SETS, the loop's replay dropped the 2-3
# sets that came meanwhile. Holding them, it dropped none, at latency p99 36-39 ms
# instead of 30-32 ms (two replays each, 2026-12-04).
SETTLING_SETS = 15


class DroppingQueue:
    """A bounded queue of frame-sets, filled by the capture threads, emptied by the run."""

    def __init__(self, capacity: int = QUEUE_SETS, *, settling: int = SETTLING_SETS) -> None:
        self._items: deque[FrameSet] = deque()
        self._capacity, self._settling = capacity, max(settling, capacity)
        self._settled = False
        self._ready = threading.Condition()
        self.dropped = 0

    def put(self, item: FrameSet) -> None:
        with self._ready:
            if len(self._items) >= self.capacity:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self._ready.notify()

    @property
    def capacity(self) -> int:
        """The sets that may wait now: more until the run has settled (see :meth:`settle`)."""
        return self._capacity if self._settled else self._settling

    def settle(self) -> None:
        """A frame is out (called after each): once fewer sets wait than the capacity, the
        run has settled, and the queue holds only that many from then on."""
        with self._ready:
            self._settled = self._settled or len(self._items) < self._capacity

    def get(self, timeout_s: float) -> FrameSet | None:
        """The oldest waiting set, or None if none came within ``timeout_s``."""
        with self._ready:
            if not self._items:
                self._ready.wait(timeout_s)
            return self._items.popleft() if self._items else None

    def __len__(self) -> int:
        with self._ready:
            return len(self._items)
