"""Half-widths read along the tube on several frames, pooled in bins of arc length.

Each frame's two-edge readings (:func:`pipeline.reconstruct.side_readings.side_widths`)
are placed by their arc length from the base; a bin's value is the median of every
reading in it, kept only where enough frames read it that one frame's stray readings
(another part's outline taken for an edge) do not make it. The session's radius profile
(:mod:`.radius_profile`) and its spacer disks (:mod:`.disks`) are read from such bins.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def binned_medians(
    readings: Sequence[tuple[FloatArray, FloatArray]], bin_mm: float, min_frames: int
) -> FloatArray | None:
    """(B,) the median half-width (mm) of the readings in each bin ``bin_mm`` long from the
    base, NaN where fewer than ``min_frames`` frames read it; None where fewer frames than
    that read anything. ``readings``: each frame's (arc lengths (R,) mm, half-widths (R,) mm)."""
    frames = [(np.asarray(a, dtype=np.float64), np.asarray(h, dtype=np.float64)) for a, h in readings]
    frames = [(a, h) for a, h in frames if len(a)]
    if len(frames) < min_frames:
        return None
    arc = np.concatenate([a for a, _ in frames])
    half = np.concatenate([h for _, h in frames])
    frame = np.concatenate([np.full(len(a), k) for k, (a, _) in enumerate(frames)])
    bins = np.floor(np.maximum(arc, 0.0) / bin_mm).astype(np.int64)
    profile = np.full(int(bins.max()) + 1, np.nan)
    for b in np.unique(bins):
        mine = bins == b
        if len(np.unique(frame[mine])) >= min_frames:
            profile[b] = float(np.median(half[mine]))
    return profile
