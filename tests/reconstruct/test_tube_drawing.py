"""The views' grey levels read as coverage, where the tube is and where it is not."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.reconstruct.tube_drawing import pixel_coverages


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_window_without_silhouette_reads_no_tube(seed: int) -> None:
    rng = np.random.default_rng(seed)
    h, w = 240, 320
    # A textured view whose silhouette lies in one corner; a window far from it (a tracked
    # tip where this view lost the tube) and one over it.
    contrast = rng.uniform(0.0, 60.0, size=(h, w)).astype(np.float32)
    mask = np.zeros((h, w), dtype=bool)
    y, x = int(rng.integers(10, 40)), int(rng.integers(10, 40))
    mask[y : y + 20, x : x + 60] = True
    contrast[mask] += 150.0
    far = ((200, 150), (300, 220))
    near = ((0, 0), (120, 80))
    empty, seen = pixel_coverages([contrast, contrast], [mask, mask], [far, near])
    assert not empty.any()
    (x0, y0), (x1, y1) = near
    inside = mask[y0:y1, x0:x1]
    assert seen[y0:y1, x0:x1][inside].mean() > 0.9
