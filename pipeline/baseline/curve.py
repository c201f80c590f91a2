"""BASELINE ONLY: the original method's centreline, kept for side-by-side comparison.

This is not the pipeline's centreline (that is :mod:`pipeline.reconstruct.centerline`); it is
the method this project replaces, reimplemented faithfully so its accuracy can be
measured on the same sessions (``--curve polyfit``, ``python -m
pipeline.measure.accuracy_table``). As described by the original work:

1. fit a sphere to the hull points (linear least squares);
2. parameterise every point by its angle around the sphere's centre, in the
   bending plane, measured from the base;
3. fit an order-2 polynomial per axis, x(angle), y(angle), z(angle), to all points;
4. sample the polynomials from the base's angle to the largest angle (the tip).

Known limits, by construction, and shown in tests/baseline/test_curve.py: an
order-2 polynomial per axis cannot follow an S or a multi-segment pose; the
angle wraps past 180 degrees, so a loop (the tip curling back past the base) is
ordered wrongly and its curve is far off; and a nearly straight pose has no
sphere to speak of (its centre runs off to infinity and the angles all shrink
towards zero). The hull's overshoot at the tip is kept too: the curve ends at
the hull's last point, not at the tube's end.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..geometry.polyline import resample_polyline

FloatArray = NDArray[np.float64]

# The polynomials are sampled this many times more densely than the output, and
# the dense polyline is resampled uniformly in arc length (the FrameResult contract).
_DENSE = 16


def fit_sphere(points_mm: ArrayLike) -> tuple[FloatArray, float]:
    """Least-squares sphere through points (the algebraic fit: linear in centre and radius).

    Parameters
    ----------
    points_mm : (P, 3) float64, mm; P >= 4.

    Returns
    -------
    center_mm : (3,) float64, mm.
    radius_mm : float, mm.
    """
    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    # |p|^2 = 2 c.p + (r^2 - |c|^2): linear in (c, r^2 - |c|^2).
    a = np.column_stack([2.0 * pts, np.ones(len(pts))])
    b = np.einsum("ij,ij->i", pts, pts)
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    center = sol[:3]
    radius = float(np.sqrt(max(sol[3] + center @ center, 0.0)))
    return center, radius


def polyfit_centerline(points_mm: ArrayLike, base_mm: ArrayLike | None, *, n_points: int = 64) -> FloatArray:
    """The original method's centreline (BASELINE, for comparison only).

    Parameters
    ----------
    points_mm : (P, 3) float64 occupied voxel centres of the visual hull, world
        frame, mm; P >= 4.
    base_mm : (3,) float64 mount point, world frame, mm. None: the hull point
        lowest in z (the original rig stands on the floor); callers that know the
        workspace should pass :func:`pipeline.reconstruct.ordering.infer_base` instead.
    n_points : N, samples of the result (both ends included).

    Returns
    -------
    (N, 3) float64 curve ordered base -> tip, uniform in arc length, mm.
    """
    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    if len(pts) < 4:
        raise ValueError(f"polyfit_centerline needs at least 4 hull points, got {len(pts)}")
    base = pts[np.argmin(pts[:, 2])] if base_mm is None else np.asarray(base_mm, dtype=np.float64)
    angles = bending_angles(pts, base)

    # Fit against the angle scaled to [0, 1]: the same polynomial, better conditioned.
    span = float(angles.max())
    if not span > 0:
        raise ValueError("polyfit_centerline: the hull does not extend away from the base")
    u = angles / span
    coeffs = [np.polyfit(u, pts[:, axis], 2) for axis in range(3)]
    dense_u = np.linspace(0.0, 1.0, _DENSE * n_points)
    dense = np.column_stack([np.polyval(c, dense_u) for c in coeffs])
    return resample_polyline(dense, n_points)


def bending_angles(points_mm: FloatArray, base_mm: FloatArray) -> FloatArray:
    """Each point's angle (rad) around the fitted sphere's centre, in the bending plane,
    from the base; positive towards the bulk of the points. (P,) float64 in (-pi, pi]."""
    center, _ = fit_sphere(points_mm)
    rel = points_mm - center
    # The bending plane: the hull's two directions of largest spread (its normal is
    # the direction of least spread, the tube's thickness for a planar bend).
    _, _, vt = np.linalg.svd(points_mm - points_mm.mean(axis=0), full_matrices=False)
    normal = vt[2]
    to_base = base_mm - center
    e1 = to_base - (to_base @ normal) * normal
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    angles = np.arctan2(rel @ e2, rel @ e1)
    # Orient so the angle grows from the base towards the tip.
    return angles if np.median(angles) >= 0 else -angles
