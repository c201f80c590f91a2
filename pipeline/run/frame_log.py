"""What a run keeps of each frame for its finish, on disk rather than in memory.

The finish smooths every frame's curve and writes again the metrics of the frames that
lie far from their smoothed curves (:class:`pipeline.run.outputs.Writers`). Held in
memory, those cost ~3 KB a frame: a live run's memory grew by ~10 MiB a minute. Here each
frame's curve and metrics message go to anonymous temporary files (gone when closed, or
when the process ends), and only their indices stay in memory (16 bytes a frame).
"""

from __future__ import annotations

import tempfile
from array import array

import numpy as np
from numpy.typing import NDArray


class FrameLog:
    """Each frame's index, time, curve and metrics message, in the order written."""

    def __init__(self) -> None:
        self.frames = array("q")
        self.times_ns = array("q")
        self._curves = tempfile.TemporaryFile(prefix="pipeline-curves-")
        self._points = 0  # samples per curve, from the first curve (0: none yet)
        self._uneven = False  # curves of more than one length: no stack of them
        self._has_curve = bytearray()
        self._metrics = tempfile.TemporaryFile(prefix="pipeline-metrics-")
        self._metric_ends = array("q")

    def __len__(self) -> int:
        return len(self.frames)

    def add(self, frame: int, time_ns: int, curve_mm: NDArray[np.float64] | None, metrics: bytes) -> None:
        """One frame: its (N, 3) mm curve (None without one) and its metrics message."""
        self.frames.append(frame)
        self.times_ns.append(time_ns)
        if curve_mm is not None and not self._points:
            self._points = len(curve_mm)
            # Frames before the first curve had none: their rows of NaN, now that N is known.
            self._curves.write(np.full((len(self._has_curve), self._points, 3), np.nan).tobytes())
        if curve_mm is not None and len(curve_mm) != self._points:
            self._uneven = True
        self._has_curve.append(curve_mm is not None)
        if self._points and not self._uneven:
            row = np.full((self._points, 3), np.nan) if curve_mm is None else curve_mm
            self._curves.write(np.ascontiguousarray(row, dtype=np.float64).tobytes())
        self._metrics.write(metrics)
        self._metric_ends.append(self._metrics.tell())

    def stacked_curves(self) -> NDArray[np.float64] | None:
        """(F, N, 3) mm: the frames' curves, NaN rows where a frame has none; None where
        they differ in length (or there are none)."""
        if not self._points or self._uneven:
            return None
        self._curves.flush()
        self._curves.seek(0)
        data = np.frombuffer(self._curves.read(), dtype=np.float64)
        return data.reshape(len(self.frames), self._points, 3).copy()

    def metrics(self, row: int) -> bytes:
        """Frame ``row``'s metrics message (rows in the order written)."""
        start = self._metric_ends[row - 1] if row else 0
        self._metrics.flush()
        self._metrics.seek(start)
        message = self._metrics.read(self._metric_ends[row] - start)
        self._metrics.seek(0, 2)  # back to the end, for the next frame
        return message

    def close(self) -> None:
        self._curves.close()
        self._metrics.close()
