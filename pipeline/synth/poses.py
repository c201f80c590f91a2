"""Which synthetic poses a real tube could take: inside the workspace, in view, not through itself.

Pure functions of centrelines (F, N, 3) mm, world frame, base -> tip, and of the tube's
radius along them; each returns a per-frame verdict so that a shape generator can
redraw and a renderer can name the first bad frame.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .radius_profiles import Disks
from .raycast import project_points
from .rig import SynthCamera


def unit_tangents(centerlines_mm: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit tangents of polylines, (..., N, 3) -> (..., N, 3); second-order at the ends."""
    tangent = np.gradient(centerlines_mm, axis=-2, edge_order=2)
    return tangent / np.linalg.norm(tangent, axis=-1, keepdims=True)


def _normals(tangent: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Two unit vectors perpendicular to each unit tangent (..., 3) and to each other."""
    helper = np.where(np.abs(tangent[..., 2:3]) < 0.9, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    n1 = np.cross(tangent, helper)
    n1 /= np.linalg.norm(n1, axis=-1, keepdims=True)
    return n1, np.cross(tangent, n1)


def tube_surface_points(
    centerlines_mm: NDArray[np.float64], radius_mm: float | NDArray[np.float64], *, ring: int = 16
) -> NDArray[np.float64]:
    """Points on the rims of the tube's cross-section discs (perpendicular to the tangent).

    centerlines_mm : (..., N, 3) float64; radius_mm : one radius or (N,) per sample
    -> (..., N * ring, 3) float64 mm.
    """
    n1, n2 = _normals(unit_tangents(centerlines_mm))
    a = np.linspace(0.0, 2.0 * np.pi, ring, endpoint=False)[:, None]
    offsets = np.cos(a) * n1[..., None, :] + np.sin(a) * n2[..., None, :]  # (..., N, ring, 3)
    radius = np.asarray(radius_mm, dtype=np.float64)
    points = centerlines_mm[..., None, :] + (radius[..., None, None] if radius.ndim else radius) * offsets
    return points.reshape(*centerlines_mm.shape[:-2], -1, 3)


def _disk_frames(
    centerlines_mm: NDArray[np.float64], disks: Disks
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Centres and unit axes of the disks in every frame, each (F, D, 3), from the polylines."""
    seg = np.diff(centerlines_mm, axis=1)
    length = np.linalg.norm(seg, axis=2)
    arc = np.concatenate([np.zeros((len(seg), 1)), np.cumsum(length, axis=1)], axis=1)
    # Samples are uniform in arc length, so every frame's segments are alike.
    k = np.clip(np.searchsorted(arc[0], disks.arc_mm, side="right") - 1, 0, seg.shape[1] - 1)
    axis = seg[:, k] / length[:, k, None]
    centers = centerlines_mm[:, k] + (disks.arc_mm - arc[:, k])[..., None] * axis
    return centers, axis


def outside_box(
    centerlines_mm: NDArray[np.float64],
    radius_mm: float | NDArray[np.float64],
    lo_mm: NDArray[np.float64],
    hi_mm: NDArray[np.float64],
    *,
    tip: str = "flat",
    disks: Disks | None = None,
) -> NDArray[np.bool_]:
    """Per frame (F,), whether any part of the tube leaves the box [lo_mm, hi_mm] (each (3,)).

    A disc of radius r perpendicular to the unit tangent T reaches r * sqrt(1 - T_i^2)
    along axis i; the discs (with the flat end faces) sweep the tube, a round tip adds a
    ball of the tip's radius, and a disk of radius R and thickness e reaches
    R * sqrt(1 - T_i^2) + e / 2 * |T_i|: all exact bounds.
    """
    radius = np.asarray(radius_mm, dtype=np.float64)
    radius = radius[:, None] if radius.ndim else radius
    tangent = unit_tangents(centerlines_mm)
    across = np.sqrt(np.clip(1.0 - tangent**2, 0.0, None))
    reach = radius * across
    # 1e-3 mm: the base disc lies exactly on the floor z = 0, and finite-difference
    # tangents tilt it by ~(kappa h)^2, far below 1e-3 mm at its rim.
    lo, hi = lo_mm - 1e-3, hi_mm + 1e-3
    out = np.any((centerlines_mm - reach < lo) | (centerlines_mm + reach > hi), axis=(1, 2))
    if tip == "round":
        end = centerlines_mm[:, -1]
        r_tip = float(np.ravel(radius)[-1])
        out |= np.any((end - r_tip < lo) | (end + r_tip > hi), axis=1)
    if disks is not None and len(disks.arc_mm):
        centers, axis = _disk_frames(centerlines_mm, disks)
        d_reach = disks.radius_mm * np.sqrt(np.clip(1.0 - axis**2, 0.0, None))
        d_reach = d_reach + 0.5 * disks.thickness_mm * np.abs(axis)
        out |= np.any((centers - d_reach < lo) | (centers + d_reach > hi), axis=(1, 2))
    return out


def self_contact(
    centerlines_mm: NDArray[np.float64], *, min_gap_mm: float, min_arc_mm: float, step: int = 4
) -> NDArray[np.bool_]:
    """Per frame (F,), whether two backbone points more than ``min_arc_mm`` apart along it
    come closer than ``min_gap_mm``; every ``step``-th sample is compared."""
    sub = centerlines_mm[:, ::step]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(sub[0], axis=0), axis=1))])
    apart = np.abs(arc[:, None] - arc[None]) > min_arc_mm
    out = np.zeros(len(sub), bool)
    # Blocks of frames keep the (F, M, M) distance array small.
    for first in range(0, len(sub), 64):
        block = sub[first : first + 64]
        gaps = np.linalg.norm(block[:, :, None] - block[:, None], axis=-1)
        out[first : first + 64] = np.any(apart & (gaps < min_gap_mm), axis=(1, 2))
    return out


def out_of_view(
    centerlines_mm: NDArray[np.float64],
    radius_mm: float | NDArray[np.float64],
    camera: SynthCamera,
    *,
    tip: str = "flat",
    disks: Disks | None = None,
) -> NDArray[np.bool_]:
    """Per frame (F,), whether the tube leaves ``camera``'s image: rims of every other
    disc (about 2.5 mm apart) at 12 points, for a round tip the cap's farthest point, and
    the rims of both faces of every disk. The workspace itself projects 30 px or more
    inside every image, so this sampling is ample."""
    radius = np.asarray(radius_mm, dtype=np.float64)
    pts = tube_surface_points(centerlines_mm[:, ::2], radius[::2] if radius.ndim else radius, ring=12)
    if tip == "round":
        end_radius = float(np.ravel(radius)[-1])
        cap = centerlines_mm[:, -1] + end_radius * unit_tangents(centerlines_mm)[:, -1]
        pts = np.concatenate([pts, cap[:, None]], axis=1)
    if disks is not None and len(disks.arc_mm):
        centers, axis = _disk_frames(centerlines_mm, disks)
        faces = [centers + side * 0.5 * disks.thickness_mm * axis for side in (-1.0, 1.0)]
        n1, n2 = _normals(axis)
        a = np.linspace(0.0, 2.0 * np.pi, 12, endpoint=False)[:, None]
        ring = disks.radius_mm * (np.cos(a) * n1[..., None, :] + np.sin(a) * n2[..., None, :])
        rims = [(face[..., None, :] + ring).reshape(len(face), -1, 3) for face in faces]
        pts = np.concatenate([pts, *rims], axis=1)
    uv = project_points(camera, pts)
    return np.any((uv < 0) | (uv > [camera.width - 1, camera.height - 1]), axis=(1, 2))
