"""BASELINE ONLY: the original method's big-cube carving heuristic, kept for comparison.

Not used by the pipeline. The original split the grid into big cubes and looked at
the small cubes (voxels) on each big cube's surface: if any of them projected into all
silhouettes, the big cube was kept and its inner voxels tested too; otherwise the whole
big cube was discarded. Every voxel it looked at was projected anew each frame (no
lookup table). A part of the object that lies inside a big cube without reaching its
surface, such as a thin tip ending inside it, is lost: the heuristic can only miss
voxels, never add any, relative to exact carving (:func:`pipeline.carve.hull.carve`).

It uses the package's pixel rule (:func:`pipeline.carve.hull.pixel_indices`) so that, where
it does keep a big cube, its voxels agree exactly with exact carving.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from ..carve.hull import occupied_by_projection
from ..geometry.camera import Camera
from ..session.settings import Workspace


def carve_original(
    cameras: Sequence[Camera],
    workspace: Workspace,
    masks: Sequence[NDArray[np.bool_]],
    *,
    big_cube_voxels: int = 8,
) -> NDArray[np.int64]:
    """The original's carving: big cubes screened by their surface voxels.

    Parameters
    ----------
    cameras, workspace : the rig and the carving box.
    masks : one (H, W) bool silhouette per camera.
    big_cube_voxels : edge of a big cube in voxels; cubes at the far faces of the grid
        are cut short where the grid ends.

    Returns
    -------
    (P,) int64 sorted flat voxel indices (C order over ``workspace.shape``): the
    occupied voxels of the big cubes kept.
    """
    if big_cube_voxels < 1:
        raise ValueError(f"big_cube_voxels must be >= 1, got {big_cube_voxels}")
    cube_of, on_surface = _big_cubes(workspace.shape, big_cube_voxels)
    surface = np.flatnonzero(on_surface)
    hit = surface[occupied_by_projection(cameras, workspace, masks, surface)]
    kept = np.zeros(int(cube_of.max()) + 1, dtype=bool)
    kept[cube_of[hit]] = True
    inner = np.flatnonzero(kept[cube_of] & ~on_surface)
    inner_hit = inner[occupied_by_projection(cameras, workspace, masks, inner)]
    return np.sort(np.concatenate([hit, inner_hit]))


def _big_cubes(shape: tuple[int, int, int], edge: int) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Per voxel (flat, C order): its big cube's number and whether it lies on that cube's surface."""
    cube = []
    surface = []
    counts = [math.ceil(n / edge) for n in shape]
    for a, n in enumerate(shape):
        i = np.arange(n)
        c = i // edge
        last = np.minimum((c + 1) * edge, n) - 1  # the far face of a cut-short cube
        axis_shape = [1, 1, 1]
        axis_shape[a] = n
        cube.append(c.reshape(axis_shape))
        surface.append(((i % edge == 0) | (i == last)).reshape(axis_shape))
    cube_of = (cube[0] * counts[1] + cube[1]) * counts[2] + cube[2]
    on_surface = surface[0] | surface[1] | surface[2]
    return cube_of.ravel().astype(np.int64), on_surface.ravel()
