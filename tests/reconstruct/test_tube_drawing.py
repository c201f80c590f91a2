"""The views' grey levels read as coverage, where the tube is and where it is not."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import rig_cameras

from pipeline.reconstruct.tube_drawing import drawn_coverage, pixel_coverages, view_window


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


@pytest.mark.parametrize(
    ("arrangement", "seed"), [("oblique", 0), ("ninety", 1), ("oblique", 2), ("ninety", 3)]
)
def test_a_window_with_reach_holds_every_pixel_of_the_tube_moved_that_far(
    arrangement: str, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    radius = float(rng.uniform(3.0, 9.0))
    reach = float(rng.uniform(1.0, 3.0))
    # A short piece of tube (its window hugs it), somewhere in the workspace.
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    axis = rng.uniform(80.0, 176.0, size=3) + np.linspace(0.0, 4.0, 5)[:, None] * direction
    for cam in rig_cameras(arrangement):
        window = view_window(cam, axis, radius, reach_radii=reach)
        assert window is not None
        (x0, y0), (x1, y1) = window
        whole = ((0, 0), cam.size_px)
        sight = axis[0] - cam.center_mm
        sight /= np.linalg.norm(sight)
        for _ in range(8):
            # Moved by the whole reach: across the line of sight (where it moves farthest in
            # the image), or partly toward the camera (where it looks wider).
            shift = rng.normal(size=3)
            shift -= (shift @ sight) * sight * float(rng.uniform(0.5, 1.0))
            shift *= reach * radius / np.linalg.norm(shift)
            drawn = drawn_coverage(cam, axis + shift, radius, whole, cap=str(rng.choice(["flat", "round"])))
            assert drawn.any()
            drawn[y0:y1, x0:x1] = 0.0
            assert not drawn.any()
