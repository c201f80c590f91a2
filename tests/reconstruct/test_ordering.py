"""The march's start: from the hull around the base itself, whatever the grid.

(The march through whole tubes is tested in test_centerline.py.)
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from pipeline.reconstruct.ordering import _HullIndex, _initial_direction, march_hull

FloatArray = NDArray[np.float64]
VOXEL = 2.0
RADIUS = 6.0


def _column(centre_xy: tuple[float, float], height_mm: float = 80.0) -> FloatArray:
    """Centres of the 2 mm voxels (on the grid of the default workspace, centres at
    odd mm) within RADIUS + 1 of the vertical axis through ``centre_xy``."""
    axis = np.arange(1.0, 256.0, VOXEL)
    x, y, z = np.meshgrid(axis, axis, axis[axis < height_mm], indexing="ij")
    pts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    keep = np.hypot(pts[:, 0] - centre_xy[0], pts[:, 1] - centre_xy[1]) <= RADIUS + 1.0
    return pts[keep]


@pytest.mark.parametrize("order", ["as_built", "reversed", "shuffled"])
def test_a_base_on_a_grid_corner_starts_straight_up_the_tube(order: str) -> None:
    # (128, 128, 0) is a corner of the voxel grid: four voxel centres are
    # equally near it. The start must not hang on which of them a tie-break picks.
    base = np.array([128.0, 128.0, 0.0])
    pts = _column((128.0, 128.0))
    if order == "reversed":
        pts = pts[::-1].copy()
    elif order == "shuffled":
        pts = pts[np.random.default_rng(1).permutation(len(pts))]
    reach = RADIUS + VOXEL
    direction = _initial_direction(_HullIndex.build(pts, VOXEL), base, reach)
    assert direction is not None
    # The hull around the base is symmetric about the axis: the direction is
    # the axis, to float summation error.
    np.testing.assert_allclose(direction, [0.0, 0.0, 1.0], atol=1e-12)
    track = march_hull(pts, base, radius_mm=RADIUS, voxel_mm=VOXEL).points_mm
    # Every centroid of a symmetric cross-section is on the axis.
    np.testing.assert_allclose(track[:, :2], np.broadcast_to(base[:2], track[:, :2].shape), atol=1e-9)


def test_a_base_off_the_hull_starts_from_the_nearest_hull() -> None:
    # A base 40 mm below the hull (an inferred or misplaced mount): nothing of
    # the hull lies within reach of it, so the march starts from its nearest voxel.
    pts = _column((128.0, 128.0))
    pts = pts[pts[:, 2] > 40.0]
    base = np.array([128.0, 128.0, 0.0])
    direction = _initial_direction(_HullIndex.build(pts, VOXEL), base, RADIUS + VOXEL)
    assert direction is not None
    # Pointing up into the hull (within the tilt a corner voxel's neighbourhood
    # gives: its ball's mean is ~1 mm off the axis, 40+ mm up: < 0.1 rad).
    assert direction[2] > np.cos(0.1)


def test_a_base_amid_the_hull_gives_no_direction() -> None:
    pts = _column((128.0, 128.0))
    index = _HullIndex.build(pts, VOXEL)
    # A base on the axis halfway up the hull: the hull around it is balanced,
    # its mean is the base itself, and no way is the way in.
    middle = np.array([128.0, 128.0, 40.0])
    assert _initial_direction(index, middle, RADIUS + VOXEL) is None


@pytest.mark.parametrize("gap_mm", [6.0, 16.0, 22.0])
def test_the_march_crosses_a_gap_in_the_hull_straight_ahead(gap_mm: float) -> None:
    # A part of the tube lost from one view's silhouette for a few pixels cuts its
    # hull: the march goes on across the gap, straight ahead, to the tube's end.
    pts = _column((128.0, 128.0), height_mm=200.0)
    pts = pts[(pts[:, 2] < 90.0) | (pts[:, 2] > 90.0 + gap_mm)]
    track = march_hull(pts, np.array([128.0, 128.0, 0.0]), radius_mm=RADIUS, voxel_mm=VOXEL).points_mm
    assert track[-1, 2] > 190.0


def test_the_march_stops_at_a_gap_longer_than_it_looks_across() -> None:
    pts = _column((128.0, 128.0), height_mm=200.0)
    pts = pts[(pts[:, 2] < 90.0) | (pts[:, 2] > 140.0)]
    track = march_hull(pts, np.array([128.0, 128.0, 0.0]), radius_mm=RADIUS, voxel_mm=VOXEL).points_mm
    assert 80.0 < track[-1, 2] < 92.0
