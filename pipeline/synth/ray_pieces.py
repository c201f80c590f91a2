"""First hits of rays with the solid pieces a tube is built from: cone frustums, balls, flat discs.

Every function takes rays sharing one origin ``o`` (3,) mm with unit directions
``d`` (P, 3), and returns ``Hits``: the distance to the nearest entry (P,) mm (inf:
miss) and the unit outward normal there (P, 3). ``keep(points)`` says which candidate
surface points (..., 3) lie on the solid (the tube's flat ends cut its pieces).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

Hits = tuple[NDArray[np.float64], NDArray[np.float64]]  # distance (P,) (inf: miss), unit normal (P, 3)
Keep = Callable[[NDArray[np.float64]], NDArray[np.bool_]]


def keep_all(points: NDArray[np.float64]) -> NDArray[np.bool_]:
    """A ``Keep`` for pieces no end plane cuts."""
    return np.ones(points.shape[:-1], bool)


def nearest(t: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Per ray (row), the index and distance of the nearest of several pieces (columns)."""
    if t.shape[1] == 0:
        return np.zeros(len(t), np.intp), np.full(len(t), np.inf)
    k = np.argmin(t, axis=1)
    return k, t[np.arange(len(t)), k]


def unit(v: NDArray[np.float64]) -> NDArray[np.float64]:
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)


def cone_hits(
    o: NDArray[np.float64],
    d: NDArray[np.float64],
    start: NDArray[np.float64],
    axis: NDArray[np.float64],
    c0: NDArray[np.float64],
    c1: NDArray[np.float64],
    lo: NDArray[np.float64],
    hi: NDArray[np.float64],
    keep: Keep,
) -> Hits:
    """Nearest entry through the side of S cone frustums (a cylinder when c1 = 0).

    Frustum j is the surface at distance ``c0[j] + c1[j] * h`` from the line
    ``start[j] + h * axis[j]`` (unit ``axis``), for ``lo[j] <= h <= hi[j]``, where that
    distance is positive. start, axis : (S, 3); c0, c1, lo, hi : (S,).
    """
    w = o - start  # (S, 3): every ray starts at the camera centre
    du = d @ axis.T  # (P, S)
    wu = np.einsum("ij,ij->i", w, axis)  # (S,)
    rho0 = c0 + c1 * wu  # frustum radius at the ray origin's axial coordinate
    # |w_perp + t d_perp|^2 = (rho0 + c1 du t)^2, with the half-b form of the quadratic.
    # With c1 = 0 every extra term is an exact zero, so a cylinder gives the same bits
    # as the plain cylinder formula.
    A = 1.0 - du * du - (c1 * c1) * (du * du)
    B = d @ w.T - du * wu - (c1 * du) * rho0
    C = np.einsum("ij,ij->i", w, w) - wu * wu - rho0 * rho0
    disc = B * B - A * C
    with np.errstate(invalid="ignore", divide="ignore"):
        # For A > 0 this is the smaller root (entering); for A < 0 (a ray closer to the
        # axis direction than the cone's half-angle) the larger one, where the ray
        # enters the nappe the frustum lies on. The axial range rejects the other nappe.
        t = (-B - np.sqrt(disc)) / A
        h = wu + t * du  # axial coordinate of the entry point
        ok = (disc >= 0) & (np.abs(A) > 1e-12) & (t > 0) & (h >= lo) & (h <= hi)
        ok &= keep(o + t[..., None] * d[:, None, :])
    k, t_min = nearest(np.where(ok, t, np.inf))
    rows = np.arange(len(d))
    hit = o + t_min[:, None] * d
    radial = hit - (start[k] + h[rows, k][:, None] * axis[k])
    # The outward normal of rho = c0 + c1 h leans back along the axis by the cone's slope
    # (rays that miss carry NaN here and are never used).
    with np.errstate(invalid="ignore"):
        lean = (c1[k] * np.linalg.norm(radial, axis=1))[:, None] * axis[k]
        return t_min, unit(radial - lean)


def ball_hits(
    o: NDArray[np.float64],
    d: NDArray[np.float64],
    centers: NDArray[np.float64],
    radii: NDArray[np.float64],
    keep: Keep,
) -> Hits:
    """Nearest entry into balls, centers : (J, 3) mm, radii : (J,) mm."""
    w = o - centers  # (J, 3)
    b = d @ w.T  # (P, J)
    disc = b * b - (np.einsum("ij,ij->i", w, w) - radii * radii)
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
        ok = (disc >= 0) & (t > 0) & keep(o + t[..., None] * d[:, None, :])
    k, t_min = nearest(np.where(ok, t, np.inf))
    hit = o + t_min[:, None] * d
    return t_min, unit(hit - centers[k]) if len(centers) else np.zeros_like(hit)


def disc_hits(
    o: NDArray[np.float64],
    d: NDArray[np.float64],
    center: NDArray[np.float64],
    normal: NDArray[np.float64],
    r: float,
) -> Hits:
    """Hits on a flat disc of radius ``r`` mm (an end face) whose outward unit normal is ``normal`` (3,)."""
    dn = d @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((center - o) @ normal) / dn
        hit = o + t[:, None] * d
        ok = (np.abs(dn) > 1e-12) & (t > 0) & (np.linalg.norm(hit - center, axis=1) <= r)
    return np.where(ok, t, np.inf), np.broadcast_to(normal, d.shape)


def short_cylinder_hits(
    o: NDArray[np.float64],
    d: NDArray[np.float64],
    center: NDArray[np.float64],
    axis: NDArray[np.float64],
    radius: float,
    thickness: float,
) -> Hits:
    """Nearest hit on a closed cylinder (a spacer disk): side and both flat faces.

    center : (3,) mm, the middle of the disk; axis : (3,) unit; radius, thickness : mm.
    """
    half = 0.5 * thickness
    side = cone_hits(
        o,
        d,
        (center - half * axis)[None],
        axis[None],
        np.array([radius]),
        np.zeros(1),
        np.zeros(1),
        np.array([thickness]),
        keep_all,
    )
    faces = [disc_hits(o, d, center + sign * half * axis, sign * axis, radius) for sign in (1.0, -1.0)]
    pieces = [side, *faces]
    k, t = nearest(np.stack([p[0] for p in pieces], axis=1))
    normal = np.stack([p[1] for p in pieces], axis=1)[np.arange(len(d)), k]
    return t, normal
