"""The original big-cube heuristic (baseline): what it keeps, and what it misses."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import COARSE_WS, random_masks, rig_cameras
from numpy.typing import NDArray

from pipeline.baseline.carving import carve_original
from pipeline.carve.hull import carve_brute_force, pixel_indices, voxel_centers_mm
from pipeline.geometry.camera import Camera
from pipeline.session.settings import Workspace


def _masks_of_voxels(
    cameras: list[Camera], ws: Workspace, flat: NDArray[np.int64]
) -> list[NDArray[np.bool_]]:
    """Silhouettes holding exactly the pixels that the given voxel centres fall on."""
    centres = voxel_centers_mm(ws, flat).astype(np.float64)
    masks = []
    for cam in cameras:
        px = cam.project(centres)
        idx = pixel_indices(px[:, 0], px[:, 1], cam.width, cam.height)
        assert (idx >= 0).all()
        mask = np.zeros(cam.width * cam.height, bool)
        mask[idx] = True
        masks.append(mask.reshape(cam.height, cam.width))
    return masks


def test_an_object_inside_a_big_cube_is_missed() -> None:
    # A 2x2x2-voxel object (16 mm) in the middle of the big cube spanning voxels 16-23 in
    # x and y and 8-15 in z: it touches no voxel on that cube's surface.
    cams = rig_cameras()
    ix, iy, iz = np.meshgrid([19, 20], [19, 20], [11, 12], indexing="ij")
    block = np.sort(np.ravel_multi_index((ix.ravel(), iy.ravel(), iz.ravel()), COARSE_WS.shape))
    masks = _masks_of_voxels(cams, COARSE_WS, block)
    exact = carve_brute_force(cams, COARSE_WS, masks)
    assert np.isin(block, exact).all()
    assert carve_original(cams, COARSE_WS, masks, big_cube_voxels=8).size == 0


@pytest.mark.parametrize("edge", [1, 2])
def test_cubes_that_are_all_surface_reproduce_exact_carving(edge: int) -> None:
    # With edges of 1 or 2 voxels every voxel lies on its cube's surface: nothing is skipped.
    cams = rig_cameras()
    masks = random_masks(cams, 7)
    expected = carve_brute_force(cams, COARSE_WS, masks)
    assert len(expected) > 0
    np.testing.assert_array_equal(carve_original(cams, COARSE_WS, masks, big_cube_voxels=edge), expected)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_heuristic_only_ever_loses_voxels(seed: int) -> None:
    # Non-cubic grid whose far big cubes are cut short (shape not a multiple of 8).
    ws = Workspace((5.0, 0.0, -3.0), (250.0, 230.0, 210.0), 7.0)
    assert any(n % 8 for n in ws.shape)
    cams = rig_cameras()
    masks = random_masks(cams, seed)
    exact = carve_brute_force(cams, ws, masks)
    original = carve_original(cams, ws, masks)
    assert len(original) > 0
    assert np.isin(original, exact).all()
    assert np.all(np.diff(original) > 0)  # sorted, no duplicates


def test_big_cube_edge_must_be_positive() -> None:
    with pytest.raises(ValueError, match="big_cube_voxels"):
        carve_original(rig_cameras(), COARSE_WS, random_masks(rig_cameras(), 0), big_cube_voxels=0)
