"""Visual hull: coarse-to-fine carving equals brute-force carving, voxel for voxel."""

from __future__ import annotations

import pickle

import cv2
import numpy as np
import pytest
from conftest import COARSE_WS, random_masks, rig_cameras
from numpy.typing import NDArray

from pipeline.carve.hull import (
    build_grid,
    carve,
    carve_brute_force,
    pixel_indices,
    voxel_centers_mm,
)
from pipeline.geometry.camera import Camera
from pipeline.session.settings import Workspace
from pipeline.synth.images import tube_mask
from pipeline.synth.rig import make_rig
from pipeline.synth.shapes import centerline, pose_segments


def _four_cameras() -> list[Camera]:
    """The oblique rig plus one camera of the ninety rig, with a 400x300 image."""
    cams = rig_cameras("oblique")
    c = make_rig("ninety")[1]
    k = c.K.copy()
    k[0, 2], k[1, 2] = 199.5, 149.5
    cams.append(Camera("cam3", (400, 300), k, c.dist, cv2.Rodrigues(c.R)[0].ravel(), c.t))
    return cams


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_carve_equals_brute_force_on_random_silhouettes(seed: int) -> None:
    cams = rig_cameras()
    grid = build_grid(cams, COARSE_WS)
    masks = random_masks(cams, seed)
    expected = carve_brute_force(cams, COARSE_WS, masks)
    assert len(expected) > 0  # the comparison must not be trivially between two empty hulls
    np.testing.assert_array_equal(carve(grid, masks), expected)


@pytest.mark.parametrize("seed", [10, 11])
def test_carve_equals_brute_force_non_cubic_grid_four_cameras(seed: int) -> None:
    rng = np.random.default_rng(seed)
    # A box whose edges are not multiples of the cell size, shifted off the origin.
    ws = Workspace(
        tuple(rng.uniform(-20, 40, 3).tolist()),  # type: ignore[arg-type]
        tuple(rng.uniform(150, 260, 3).tolist()),  # type: ignore[arg-type]
        float(rng.uniform(4.5, 7.5)),
    )
    assert any(n % 16 for n in ws.shape)
    cams = _four_cameras()
    masks = random_masks(cams, seed, blobs=25)
    expected = carve_brute_force(cams, ws, masks)
    assert len(expected) > 0
    np.testing.assert_array_equal(carve(build_grid(cams, ws), masks), expected)


@pytest.mark.parametrize(
    "ws",
    [
        Workspace((127.0, 127.0, 100.0), (2.0, 2.0, 2.0), 2.0),  # a single voxel
        Workspace((100.0, 120.0, 50.0), (60.0, 3.0, 90.0), 3.0),  # one voxel thick
    ],
)
def test_carve_equals_brute_force_on_tiny_grids_with_two_cameras(ws: Workspace) -> None:
    cams = rig_cameras()[:2]
    masks = [np.ones((c.height, c.width), bool) for c in cams]
    masks[1][::3] = False  # every third row of camera 1 is background
    expected = carve_brute_force(cams, ws, masks)
    assert len(expected) > 0
    np.testing.assert_array_equal(carve(build_grid(cams, ws), masks), expected)


def test_carve_equals_brute_force_with_every_distortion_term() -> None:
    # Rational, thin-prism and tilted-sensor terms all go through Camera.normalized_to_pixels.
    cams = rig_cameras()
    dist = np.array(
        [-0.2, 0.05, 0.002, -0.001, 0.01, 0.02, -0.01, 0.005, 1e-3, -1e-3, 2e-3, 5e-4, 0.01, -0.02]
    )
    c = cams[1]
    cams[1] = Camera(c.name, c.size_px, c.matrix, dist, c.rotation, c.translation_mm)
    masks = random_masks(cams, 21, blobs=12)
    expected = carve_brute_force(cams, COARSE_WS, masks)
    assert len(expected) > 0
    np.testing.assert_array_equal(carve(build_grid(cams, COARSE_WS), masks), expected)


def test_carve_equals_brute_force_when_cameras_sit_inside_the_box() -> None:
    # Voxels behind a camera and far outside its image must never be occupied.
    ws = Workspace((-700.0, -700.0, -300.0), (1700.0, 1700.0, 1100.0), 25.0)
    cams = rig_cameras()
    assert all(np.all(c.center_mm > ws.origin_mm) for c in cams)
    masks = [np.ones((c.height, c.width), bool) for c in cams]
    masks[0][:, :40] = False
    expected = carve_brute_force(cams, ws, masks)
    assert len(expected) > 0
    np.testing.assert_array_equal(carve(build_grid(cams, ws), masks), expected)


@pytest.fixture(scope="module")
def tube_frame() -> tuple[list[Camera], Workspace, list[NDArray[np.bool_]]]:
    """Exact silhouettes of the synthetic tube (a C bend, radius 6 mm) at 4 mm voxels."""
    truth = make_rig()
    curve = centerline(pose_segments("bend_rotate", 0.3), base_mm=np.array([128.0, 128.0, 0.0]), points=120)
    masks = [tube_mask(c, curve, 6.0) for c in truth]
    return rig_cameras(), Workspace(voxel_mm=4.0), masks


def test_carve_equals_brute_force_on_a_rendered_tube(tube_frame) -> None:
    cams, ws, masks = tube_frame
    expected = carve_brute_force(cams, ws, masks)
    # A 250 mm tube of radius 6 mm fills ~28 cm^3, i.e. ~440 voxels of 64 mm^3; the hull is larger.
    assert len(expected) > 400
    np.testing.assert_array_equal(carve(build_grid(cams, ws), masks), expected)


def test_empty_silhouette_carves_nothing(tube_frame) -> None:
    cams, ws, masks = tube_frame
    grid = build_grid(cams, ws)
    empty = [masks[0], np.zeros_like(masks[1]), masks[2]]
    assert carve(grid, empty).size == 0
    assert carve_brute_force(cams, COARSE_WS, empty).size == 0


def test_grid_survives_pickling(tube_frame) -> None:
    # The runner ships the grid to worker processes.
    cams, ws, masks = tube_frame
    grid = build_grid(cams, ws)
    clone = pickle.loads(pickle.dumps(grid))
    np.testing.assert_array_equal(carve(clone, masks), carve(grid, masks))


def test_uint8_masks_carve_like_bool_masks(tube_frame) -> None:
    cams, ws, masks = tube_frame
    grid = build_grid(cams, ws)
    as_uint8 = [m.astype(np.uint8) * 255 for m in masks]
    np.testing.assert_array_equal(carve(grid, as_uint8), carve(grid, masks))


def test_pixel_rule_rounds_half_up_and_rejects_outside() -> None:
    u = np.array([2.5, 2.49, -0.5, -0.51, 9.49, 9.5, np.nan, 0.0])
    v = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 4.5])
    # Pixel centres sit at integers: [-0.5, 0.5) is column 0, and the image is 10x5.
    np.testing.assert_array_equal(pixel_indices(u, v, 10, 5), [3, 2, 0, -1, 9, -1, -1, -1])


def test_voxel_centers_are_cell_midpoints() -> None:
    ws = Workspace((10.0, 20.0, 30.0), (40.0, 20.0, 10.0), 2.0)  # shape (20, 10, 5)
    flat = np.ravel_multi_index((np.array([0, 19]), np.array([0, 9]), np.array([0, 4])), ws.shape)
    centres = voxel_centers_mm(ws, flat)
    assert centres.dtype == np.float32
    np.testing.assert_array_equal(centres, [[11.0, 21.0, 31.0], [49.0, 39.0, 39.0]])


def test_mask_of_the_wrong_size_is_refused(tube_frame) -> None:
    cams, ws, masks = tube_frame
    grid = build_grid(cams, ws)
    with pytest.raises(ValueError, match="mask 1 has shape"):
        carve(grid, [masks[0], masks[1][:-1], masks[2]])
    with pytest.raises(ValueError, match="2 masks for 3 cameras"):
        carve(grid, masks[:2])
