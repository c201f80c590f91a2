"""The hand-off from capture to reconstruction: a short queue that drops its oldest.

Frame-sets wait here for the reconstruction. When it falls behind and the queue is
full, the oldest waiting set is dropped (and counted), never the newest: a live view
shows the latest shape, and memory stays bounded whatever the load.
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


class DroppingQueue:
    """A bounded queue of frame-sets, filled by the capture threads, emptied by the run."""

    def __init__(self, capacity: int = QUEUE_SETS) -> None:
        self._items: deque[FrameSet] = deque()
        self._capacity = capacity
        self._ready = threading.Condition()
        self.dropped = 0

    def put(self, item: FrameSet) -> None:
        with self._ready:
            if len(self._items) >= self._capacity:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self._ready.notify()

    @property
    def capacity(self) -> int:
        return self._capacity

    def get(self, timeout_s: float) -> FrameSet | None:
        """The oldest waiting set, or None if none came within ``timeout_s``."""
        with self._ready:
            if not self._items:
                self._ready.wait(timeout_s)
            return self._items.popleft() if self._items else None

    def __len__(self) -> int:
        with self._ready:
            return len(self._items)
