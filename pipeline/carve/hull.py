"""The visual hull: exact voxel carving, coarse-to-fine, from per-session lookup tables.

A voxel is occupied iff its centre projects inside the image and onto a silhouette
pixel in EVERY camera. A centre projecting to pixel coordinates (u, v) (OpenCV: pixel
centres at integer coordinates) falls on pixel (floor(u + 0.5), floor(v + 0.5));
:func:`pixel_indices` is that rule, used by every carving function in the package so
that they agree voxel for voxel.

The cameras are fixed, so :func:`build_grid` projects every voxel centre once per
session, into a voxel -> pixel lookup, and groups voxels into a two-level hierarchy:
coarse cells of 16^3 voxels holding fine cells of 4^3 voxels. For every cell and
camera it stores the bounding rectangle of the pixels the cell's voxel centres fall on
(exactly, from the lookup). Per frame, :func:`carve` sums each rectangle's silhouette
pixels with an integral image: a cell whose rectangle holds no silhouette pixel in
some camera cannot contain an occupied voxel, so skipping it is conservative by
construction and the result equals brute-force carving (:func:`carve_brute_force`).
Only the voxels of surviving fine cells are looked up, and the tables are stored
cell-major so that those voxels are contiguous.

Flat voxel indices are C order over ``Workspace.shape``:
``np.ravel_multi_index((ix, iy, iz), shape)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import Camera
from ..session.settings import Workspace

FloatArray = NDArray[np.float64]
IndexArray = NDArray[np.int64]

# Fine cells are FINE^3 voxels; coarse cells are COARSE^3 fine cells. Smaller cells
# mean more rectangle tests, larger ones more voxel look-ups in the hull's empty
# corners; (4, 4) was within 10 % of the best of (2-8, 2-8) on 210 synthetic tube frames
# at both 128^3 and 256^3.
FINE = 4
COARSE = 4


@dataclass(frozen=True, eq=False)
class HullGrid:
    """Per-session carving tables: built once by :func:`build_grid`, read by :func:`carve`.

    Plain NumPy attributes so that joblib memory-maps them when it ships the grid to
    worker processes. Cells are numbered coarse-major: fine cell ``f`` lies in coarse
    cell ``f // COARSE^3``; voxels are numbered fine-cell-major. The grid is padded
    to whole coarse cells; padding voxels fall outside every image.

    Attributes
    ----------
    workspace : the carving box.
    shape : (nx, ny, nz) voxels.
    image_sizes : (width, height) per camera, camera order.
    pixel_offsets : (K,) int64, start of each camera's mask in the concatenated, flattened
        masks of one frame; one always-False sentinel pixel follows the last camera's.
    integral_offsets : (K,) int64, likewise for the (H + 1, W + 1) integral images.
    coarse_corners : (K, 4, C) int32 flat indices into the concatenated integral images:
        corners (top-left, top-right, bottom-left, bottom-right) of each coarse cell's
        pixel rectangle per camera; all 0 where the cell is outside the image.
    fine_corners : (K, 4, C * COARSE^3) int32, the same for fine cells.
    voxel_pixels : (K, C * COARSE^3, FINE^3) int32 index of each voxel's pixel in
        the concatenated masks, the sentinel where the centre is outside the image.
        Camera-major: per-camera gathers and ANDs of contiguous rows are several times
        faster than reducing over a short camera axis.
    coarse_offsets, fine_offsets, voxel_offsets : (C,), (COARSE^3,), (FINE^3,)
        int64; a voxel's flat grid index is the sum of its three offsets.
    """

    workspace: Workspace
    shape: tuple[int, int, int]
    image_sizes: tuple[tuple[int, int], ...]
    pixel_offsets: IndexArray
    integral_offsets: IndexArray
    coarse_corners: NDArray[np.int32]
    fine_corners: NDArray[np.int32]
    voxel_pixels: NDArray[np.int32]
    coarse_offsets: IndexArray
    fine_offsets: IndexArray
    voxel_offsets: IndexArray

    @property
    def sentinel(self) -> int:
        """Index of the always-False pixel in the concatenated masks."""
        w, h = self.image_sizes[-1]
        return int(self.pixel_offsets[-1]) + w * h

    @property
    def nbytes(self) -> int:
        """Memory held by the tables, bytes."""
        arrays = (self.coarse_corners, self.fine_corners, self.voxel_pixels)
        return sum(a.nbytes for a in arrays)


def pixel_indices(u: FloatArray, v: FloatArray, width: int, height: int) -> IndexArray:
    """Pixel coordinates -> flat pixel index ``row * width + col``; -1 outside the image.

    Parameters
    ----------
    u, v : float64 arrays of one shape, pixels; NaN (a point behind the camera) is outside.

    Returns
    -------
    int64 array of that shape.
    """
    iu, iv, inside = _round_pixels(u, v, width, height)
    return np.where(inside, iv * width + iu, -1).astype(np.int64)


def _round_pixels(
    u: FloatArray, v: FloatArray, width: int, height: int
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """The pixel rule: (floor(u + 0.5), floor(v + 0.5)) and whether it lies in the image."""
    with np.errstate(invalid="ignore"):
        iu = np.floor(u + 0.5)
        iv = np.floor(v + 0.5)
        inside = (iu >= 0) & (iu < width) & (iv >= 0) & (iv < height)
    return iu, iv, inside


def voxel_centers_mm(workspace: Workspace, flat_indices: IndexArray) -> NDArray[np.float32]:
    """(P,) flat voxel indices -> (P, 3) float32 voxel centres, world frame, mm."""
    return _centers_f64(workspace, flat_indices).astype(np.float32)


def _centers_f64(workspace: Workspace, flat_indices: IndexArray) -> FloatArray:
    """(P,) flat voxel indices -> (P, 3) float64 centres: origin + (i + 0.5) * voxel."""
    ijk = np.stack(np.unravel_index(np.asarray(flat_indices, dtype=np.int64), workspace.shape), axis=1)
    return np.asarray(workspace.origin_mm) + (ijk + 0.5) * workspace.voxel_mm


# --------------------------------------------------------------------------- reference


def occupied_by_projection(
    cameras: Sequence[Camera],
    workspace: Workspace,
    masks: Sequence[NDArray[np.bool_]],
    flat_indices: IndexArray,
) -> NDArray[np.bool_]:
    """(P,) flat voxel indices -> (P,) bool occupancy, projecting each centre with
    :meth:`Camera.project` (cv2.projectPoints). The slow, obvious way; no lookup."""
    _check_masks(cameras, masks)
    centres = _centers_f64(workspace, flat_indices)
    occupied = np.ones(len(centres), dtype=bool)
    for cam, mask in zip(cameras, masks, strict=True):
        px = cam.project(centres)
        idx = pixel_indices(px[:, 0], px[:, 1], cam.width, cam.height)
        on_mask = np.ravel(np.asarray(mask, dtype=np.bool_))[np.maximum(idx, 0)]
        occupied &= (idx >= 0) & on_mask
    return occupied


def carve_brute_force(
    cameras: Sequence[Camera],
    workspace: Workspace,
    masks: Sequence[NDArray[np.bool_]],
    *,
    chunk_voxels: int = 1 << 18,
) -> IndexArray:
    """Reference carving: every voxel centre projected with cv2.projectPoints, every mask tested.

    Returns sorted (P,) int64 flat indices of the occupied voxels. Seconds per camera
    at 128^3; for tests and benchmarks only.
    """
    found = []
    for start in range(0, workspace.voxel_count, chunk_voxels):
        ids = np.arange(start, min(start + chunk_voxels, workspace.voxel_count), dtype=np.int64)
        found.append(ids[occupied_by_projection(cameras, workspace, masks, ids)])
    return np.concatenate(found)


# --------------------------------------------------------------------------- tables


def build_grid(cameras: Sequence[Camera], workspace: Workspace) -> HullGrid:
    """Project every voxel centre of ``workspace`` into every camera, once, and build the
    coarse-to-fine tables :func:`carve` uses.

    Instead of projecting 2 M points per camera with cv2.projectPoints (seconds), the
    camera-frame coordinates are sums of three per-axis terms (the grid is regular), and
    the distortion is applied by :meth:`Camera.normalized_to_pixels` in float64, one
    row of coarse cells at a time so that temporaries stay small (~0.1 s at 128^3,
    ~1 s at 256^3 for three cameras).

    Memory: 4 bytes per voxel and camera (``HullGrid.nbytes``), the grid padded to
    whole coarse cells of 16^3 voxels.
    """
    if len(cameras) < 1:
        raise ValueError("build_grid needs at least one camera")
    shape = workspace.shape
    side = FINE * COARSE
    ncx, ncy, ncz = (math.ceil(n / side) for n in shape)
    n_coarse = (ncx, ncy, ncz)
    fine_per_coarse = COARSE**3
    sizes = tuple((c.width, c.height) for c in cameras)
    pixel_offsets = np.cumsum([0] + [w * h for w, h in sizes[:-1]]).astype(np.int64)
    integral_offsets = np.cumsum([0] + [(w + 1) * (h + 1) for w, h in sizes[:-1]]).astype(np.int64)
    sentinel = int(pixel_offsets[-1]) + sizes[-1][0] * sizes[-1][1]
    if sentinel >= 2**31:
        raise ValueError("images too large for int32 pixel tables")

    _prime_allocator()
    n_cells = ncx * ncy * ncz
    k = len(cameras)
    coarse_corners = np.zeros((k, 4, n_cells), dtype=np.int32)
    fine_corners = np.zeros((k, 4, n_cells * fine_per_coarse), dtype=np.int32)
    voxel_pixels = np.empty((k, n_cells * fine_per_coarse, FINE**3), dtype=np.int32)

    # Per axis a, voxel index i = (cell * COARSE + fine) * FINE + vox as a (n_cells_a,
    # COARSE, FINE) array; its centre coordinate and whether it is real (not padding).
    axis_mm: list[FloatArray] = []
    axis_real: list[NDArray[np.bool_]] = []
    for a in range(3):
        i = np.arange(n_coarse[a] * side).reshape(n_coarse[a], COARSE, FINE)
        axis_mm.append(np.asarray(workspace.origin_mm[a] + (i + 0.5) * workspace.voxel_mm, np.float64))
        axis_real.append(i < shape[a])
    poses = [(cam.camera_from_world, np.asarray(cam.translation_mm, dtype=np.float64)) for cam in cameras]
    # One chunk = one row of coarse cells along z (fixed cx, cy): its temporaries stay
    # in cache (0.25-0.5 MB) and its fine cells are contiguous in the tables.
    row_fine = ncz * fine_per_coarse
    for cx in range(ncx):
        for cy in range(ncy):
            row = cx * ncy + cy
            coarse_rows = slice(row * ncz, (row + 1) * ncz)
            fine_rows = slice(row * row_fine, (row + 1) * row_fine)
            centres = _chunk_layout(axis_mm[0][cx], axis_mm[1][cy], axis_mm[2])
            rx, ry, rz = _chunk_layout(axis_real[0][cx], axis_real[1][cy], axis_real[2])
            real = ((rx & ry) & rz).reshape(FINE**3, row_fine)
            for c, cam in enumerate(cameras):
                w = sizes[c][0]
                iu, iv, inside = _project_chunk(cam, *poses[c], centres)
                pix, fine_rect = _chunk_tables(iu, iv, inside & real, w, int(pixel_offsets[c]), sentinel)
                voxel_pixels[c, fine_rows] = pix
                g = fine_rect.reshape(ncz, fine_per_coarse, 4)
                coarse_rect = np.concatenate(
                    [np.fmin.reduce(g[:, :, :2], 1), np.fmax.reduce(g[:, :, 2:], 1)], axis=1
                )
                fine_corners[c, :, fine_rows] = _corners(fine_rect, w, int(integral_offsets[c])).T
                coarse_corners[c, :, coarse_rows] = _corners(coarse_rect, w, int(integral_offsets[c])).T

    strides = np.array([shape[1] * shape[2], shape[2], 1], dtype=np.int64)

    def offsets(counts: tuple[int, int, int], step: int) -> IndexArray:
        ijk = np.stack(np.unravel_index(np.arange(math.prod(counts)), counts), axis=1)
        return (ijk * step) @ strides

    return HullGrid(
        workspace=workspace,
        shape=shape,
        image_sizes=sizes,
        pixel_offsets=pixel_offsets,
        integral_offsets=integral_offsets,
        coarse_corners=coarse_corners,
        fine_corners=fine_corners,
        voxel_pixels=voxel_pixels,
        coarse_offsets=offsets(n_coarse, side),
        fine_offsets=offsets((COARSE,) * 3, FINE),
        voxel_offsets=offsets((FINE,) * 3, 1),
    )


def _prime_allocator() -> None:
    """Allocate and free one 16 MiB block so that the chunks' temporaries are recycled.

    glibc serves blocks above its mmap threshold (128 KiB at start) with fresh mmaps and
    trims the heap when more than twice that is free, so a loop allocating and freeing
    MB-sized temporaries page-faults on every new array: measured, 1.1 M faults and 3x
    the CPU time of a warm build at 256^3. Freeing an mmapped block raises both
    thresholds to its size (glibc's own adaptive rule), after which the temporaries come
    from a heap that stays put. A no-op elsewhere, and harmless once raised.
    """
    block = np.empty(16 * 2**20, dtype=np.uint8)  # never touched: costs no page faults
    del block


def _chunk_layout(
    x: NDArray[Any], y: NDArray[Any], z: NDArray[Any]
) -> tuple[NDArray[Any], NDArray[Any], NDArray[Any]]:
    """Per-axis values of one chunk, reshaped to broadcast into its layout.

    x, y : (COARSE, FINE) [fine, voxel] along the chunk's single coarse cell in x and y;
    z : (ncz, COARSE, FINE) [cell, fine, voxel] along z. The layout is
    (vx, vy, vz, cz, fx, fy, fz): voxel axes first, so that reducing over a fine cell's
    voxels is an element-wise operation across contiguous rows.
    """
    ncz = z.shape[0]
    return (
        x.T.reshape(FINE, 1, 1, 1, COARSE, 1, 1),
        y.T.reshape(1, FINE, 1, 1, 1, COARSE, 1),
        z.transpose(2, 0, 1).reshape(1, 1, FINE, ncz, 1, 1, COARSE),
    )


def _project_chunk(
    cam: Camera, rot: FloatArray, t: FloatArray, centres: tuple[FloatArray, FloatArray, FloatArray]
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """Pixel (col, row) under the pixel rule, and inside-flag, of every voxel centre of a
    chunk whose x, y, z coordinates are given as broadcastable per-axis arrays (mm).

    rot, t : the camera's (3, 3) camera_from_world and (3,) translation, mm. Returns
    (FINE^3, fine cells) arrays: voxel-major, see :func:`_chunk_layout`.
    """
    px, py, pz = centres
    # x_cam = R @ (x e_x + y e_y + z e_z) + t: small per-axis terms, one full-size add
    # each. order="C": the broadcast would otherwise pick a strided layout, and every
    # later reshape would copy.
    x_cam, y_cam, z_cam = (
        np.add(t[j] + rot[j, 0] * px + rot[j, 1] * py, rot[j, 2] * pz, order="C") for j in range(3)
    )
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        inv_z = 1.0 / z_cam
        x_cam *= inv_z
        y_cam *= inv_z
        u, v = cam.normalized_to_pixels(x_cam, y_cam)
    iu, iv, inside = _round_pixels(u, v, cam.width, cam.height)
    inside &= z_cam > 0  # behind the camera: Camera.project gives NaN, i.e. outside
    n = FINE**3
    return iu.reshape(n, -1), iv.reshape(n, -1), inside.reshape(n, -1)


def _chunk_tables(
    iu: FloatArray, iv: FloatArray, inside: NDArray[np.bool_], width: int, offset: int, sentinel: int
) -> tuple[NDArray[np.int32], FloatArray]:
    """One camera's tables for one chunk, from its (FINE^3, F) pixel columns, rows and
    inside-flags (voxel-major).

    Returns
    -------
    pixels : (F, FINE^3) int32 index into the concatenated masks (``offset`` = this
        camera's start), ``sentinel`` where outside the image.
    rect : (F, 4) float64 inclusive pixel rectangle (u0, v0, u1, v1) of each fine cell,
        NaN where none of its voxels is inside the image.
    """
    outside = ~inside
    pix = iv * width
    pix += iu
    pix += offset
    pix[outside] = sentinel
    # NaN marks voxels outside the image; fmin/fmax skip them.
    iu[outside] = np.nan
    iv[outside] = np.nan
    rect = np.stack(
        [np.fmin.reduce(iu, 0), np.fmin.reduce(iv, 0), np.fmax.reduce(iu, 0), np.fmax.reduce(iv, 0)], axis=1
    )
    return pix.T.astype(np.int32), rect  # pix holds exact integers in float64


def _corners(rect: FloatArray, width: int, offset: int) -> NDArray[np.int32]:
    """(N, 4) inclusive pixel rectangles (u0, v0, u1, v1), NaN when empty -> (N, 4) flat
    integral-image indices of the corners (top-left, top-right, bottom-left, bottom-right);
    all 0 (a zero sum) for empty ones."""
    empty = np.isnan(rect[:, 0])
    r = np.where(empty[:, None], 0.0, rect).astype(np.int64)
    u0, v0, u1, v1 = r.T
    stride = width + 1
    corners = np.stack(
        [v0 * stride + u0, v0 * stride + u1 + 1, (v1 + 1) * stride + u0, (v1 + 1) * stride + u1 + 1],
        axis=1,
    )
    corners += offset
    # Index 0 is camera 0's integral-image corner, always 0: an empty rectangle sums to 0.
    corners[empty] = 0
    return corners.astype(np.int32)


# --------------------------------------------------------------------------- per frame


def carve(grid: HullGrid, masks: Sequence[NDArray[np.bool_]]) -> IndexArray:
    """Occupied voxels of one frame, identical to :func:`carve_brute_force`.

    Parameters
    ----------
    grid : the session's tables from :func:`build_grid`.
    masks : one (H, W) bool silhouette per camera, camera order.

    Returns
    -------
    (P,) int64 sorted flat indices (C order over ``grid.shape``) of occupied voxels.
    """
    if len(masks) != len(grid.image_sizes):
        raise ValueError(f"carve got {len(masks)} masks for {len(grid.image_sizes)} cameras")
    pixels = np.zeros(grid.sentinel + 1, dtype=np.bool_)  # the last one is the sentinel
    w_last, h_last = grid.image_sizes[-1]
    integrals = np.empty(int(grid.integral_offsets[-1]) + (w_last + 1) * (h_last + 1), dtype=np.int32)
    for c, mask in enumerate(masks):
        w, h = grid.image_sizes[c]
        if mask.shape != (h, w):
            raise ValueError(f"mask {c} has shape {mask.shape}, camera {c} images are {h}x{w}")
        m = np.ascontiguousarray(mask, dtype=np.bool_)  # no copy for a bool mask
        m8 = m.view(np.uint8)
        start = int(grid.integral_offsets[c])
        table = integrals[start : start + (w + 1) * (h + 1)].reshape(h + 1, w + 1)
        cv2.integral(m8, sum=table, sdepth=cv2.CV_32S)
        if table[h, w] == 0:  # an empty silhouette carves everything away
            return np.zeros(0, dtype=np.int64)
        pixels[grid.pixel_offsets[c] : grid.pixel_offsets[c] + w * h] = m.ravel()

    # Each level keeps the cells whose rectangle holds silhouette pixels in every camera,
    # camera by camera, so that later cameras test only what the earlier ones kept.
    per_coarse = len(grid.fine_offsets)
    per_fine = len(grid.voxel_offsets)
    cells = _nonempty_cells(integrals, grid.coarse_corners, np.arange(grid.coarse_corners.shape[2]))
    fine = (cells[:, None] * per_coarse + np.arange(per_coarse)).ravel()
    fine = _nonempty_cells(integrals, grid.fine_corners, fine)
    # Voxel slots (fine cell * per_fine + voxel) that hit the silhouette in camera 0, then
    # in each further camera.
    hit = np.flatnonzero(pixels[grid.voxel_pixels[0][fine]])
    slots = fine[hit // per_fine] * per_fine + hit % per_fine
    for lookup in grid.voxel_pixels[1:]:
        slots = slots[pixels[lookup.reshape(-1)[slots]]]
    f, v = np.divmod(slots, per_fine)
    ids = grid.coarse_offsets[f // per_coarse] + grid.fine_offsets[f % per_coarse] + grid.voxel_offsets[v]
    ids.sort()
    return ids


def _nonempty_cells(
    integrals: NDArray[np.int32], corners: NDArray[np.int32], cells: IndexArray
) -> IndexArray:
    """The ``cells`` whose pixel rectangle holds a silhouette pixel in every camera.

    corners : (K, 4, N) int32 flat integral-image indices (see :class:`HullGrid`).
    """
    for table in corners:
        g = integrals[np.take(table, cells, axis=1)]
        # Rectangle sum = br - tr - bl + tl > 0, i.e. br + tl > tr + bl.
        cells = cells[g[3] + g[0] > g[1] + g[2]]
    return cells


def _check_masks(cameras: Sequence[Camera], masks: Sequence[NDArray[np.bool_]]) -> None:
    if len(masks) != len(cameras):
        raise ValueError(f"got {len(masks)} masks for {len(cameras)} cameras")
    for cam, mask in zip(cameras, masks, strict=True):
        if mask.shape != (cam.height, cam.width):
            raise ValueError(
                f"mask for camera {cam.name!r} has shape {mask.shape}, expected {(cam.height, cam.width)}"
            )
