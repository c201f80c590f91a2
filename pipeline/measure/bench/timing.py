"""Per-frame wall-clock samples per stage, and their median / 95th / 99th percentile.

Used by ``make bench`` only; the pipeline itself records its per-stage times in
:attr:`FrameResult.timings_s`, which the bench adds sample by sample.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class StageStats:
    """Summary of one stage's per-frame times.

    Attributes
    ----------
    median_ms : median time per frame, milliseconds.
    p95_ms : 95th percentile per frame, milliseconds.
    count : number of per-frame samples.
    p99_ms : 99th percentile per frame, milliseconds (the per-frame speed target's
        figure: with 300 frames, about the third slowest).
    """

    median_ms: float
    p95_ms: float
    count: int
    p99_ms: float = float("nan")

    @classmethod
    def from_seconds(cls, samples_s: list[float] | np.ndarray) -> StageStats:
        """Summarise per-frame samples given in seconds (NaN statistics when there are none)."""
        ms = np.asarray(samples_s, dtype=np.float64) * 1e3
        if ms.size == 0:
            return cls(float("nan"), float("nan"), 0)
        p95, p99 = np.percentile(ms, [95, 99])
        return cls(float(np.median(ms)), float(p95), int(ms.size), float(p99))


class StageTimer:
    """Collects one wall-clock sample per stage and frame (``time.perf_counter``)."""

    def __init__(self) -> None:
        self.samples_s: dict[str, list[float]] = {}

    @contextmanager
    def time(self, stage: str) -> Iterator[None]:
        """Time the ``with`` block as one sample of ``stage``."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self.add(stage, time.perf_counter() - start)

    def add(self, stage: str, seconds: float) -> None:
        self.samples_s.setdefault(stage, []).append(float(seconds))

    def stats(self) -> dict[str, StageStats]:
        """Stage -> median / p95 / p99 of its samples, in the order stages were first seen."""
        return {stage: StageStats.from_seconds(s) for stage, s in self.samples_s.items()}
