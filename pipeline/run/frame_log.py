"""What a run keeps of each frame for its finish, on disk rather than in memory.

The finish smooths every frame's curve and writes again the metrics of the frames that
lie far from their smoothed curves (:class:`pipeline.run.outputs.Writers`). Held in
memory, those cost ~3 KB a frame: a live run's memory grew by ~10 MiB a minute. Here each
frame's curve and metrics message go to anonymous temporary files beside the outputs
(gone when closed, or when the process ends), and only their indices stay in memory
(16 bytes a frame).
"""

from __future__ import annotations

import contextlib
import tempfile
from array import array
from pathlib import Path
from typing import IO

import numpy as np
from numpy.typing import NDArray


class FrameLog:
    """Each frame's index, time, curve and metrics message, in the order written; the
    files are opened in ``directory`` at the first frame (OSError there, as a write's)."""

    def __init__(self, directory: Path) -> None:
        self.frames = array("q")
        self.times_ns = array("q")
        self._directory = directory
        self._files: tuple[IO[bytes], IO[bytes]] | None = None  # curves, metrics
        self._points = 0  # samples per curve, from the first curve (0: none yet)
        self._uneven = False  # curves of more than one length: no stack of them
        self._metric_ends = array("q")

    def _opened(self) -> tuple[IO[bytes], IO[bytes]]:
        if self._files is None:
            curves = tempfile.TemporaryFile(prefix=".curves-", dir=self._directory)
            try:
                metrics = tempfile.TemporaryFile(prefix=".metrics-", dir=self._directory)
            except BaseException:
                curves.close()
                raise
            self._files = curves, metrics
        return self._files

    def __len__(self) -> int:
        return len(self.frames)

    def add(self, frame: int, time_ns: int, curve_mm: NDArray[np.float64] | None, metrics: bytes) -> None:
        """One frame: its (N, 3) mm curve (None without one) and its metrics message."""
        curves, metrics_file = self._opened()
        self.frames.append(frame)
        self.times_ns.append(time_ns)
        if curve_mm is not None and not self._points:
            self._points = len(curve_mm)
            # Frames before the first curve had none: their rows of NaN, now that N is known.
            curves.write(np.full((len(self.frames) - 1, self._points, 3), np.nan).tobytes())
        if curve_mm is not None and len(curve_mm) != self._points:
            self._uneven = True
        if self._points and not self._uneven:
            row = np.full((self._points, 3), np.nan) if curve_mm is None else curve_mm
            curves.write(np.ascontiguousarray(row, dtype=np.float64).tobytes())
        metrics_file.write(metrics)
        self._metric_ends.append(metrics_file.tell())

    def stacked_curves(self) -> NDArray[np.float64] | None:
        """(F, N, 3) mm: the frames' curves, NaN rows where a frame has none; None where
        they differ in length (or there are none)."""
        if not self._points or self._uneven:
            return None
        curves, _ = self._opened()
        curves.flush()
        curves.seek(0)
        data = np.frombuffer(curves.read(), dtype=np.float64)
        return data.reshape(len(self.frames), self._points, 3).copy()

    def metrics(self, row: int) -> bytes:
        """Frame ``row``'s metrics message (rows in the order written)."""
        _, metrics_file = self._opened()
        start = self._metric_ends[row - 1] if row else 0
        metrics_file.flush()
        metrics_file.seek(start)
        message = metrics_file.read(self._metric_ends[row] - start)
        metrics_file.seek(0, 2)  # back to the end, for the next frame
        return message

    def close(self) -> None:
        """Close (and so remove) the files; each is closed even where another's close fails."""
        if self._files is not None:
            files, self._files = self._files, None
            with contextlib.ExitStack() as stack:
                for file in files:
                    stack.callback(file.close)
