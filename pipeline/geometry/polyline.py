"""Small helpers on ordered 3-D polylines (arc length, uniform resampling)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def polyline_arclength(points_mm: FloatArray) -> FloatArray:
    """(M,) cumulative chord length along an (M, 3) polyline, starting at 0 (mm)."""
    pts = np.asarray(points_mm)
    if pts.dtype != np.float64:  # summed in its own precision, then widened
        return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    out = np.empty(len(pts))
    out[0] = 0.0
    np.cumsum(vector_norms(pts[1:] - pts[:-1]), out=out[1:])
    return out


def vector_norms(vectors: FloatArray) -> FloatArray:
    """(...,) Euclidean norms of (..., D) ``vectors`` along the last axis.

    ``np.linalg.norm(vectors, axis=-1)``'s own arithmetic (the sum of squares
    reduced, then its root), so the same values, without its per-call overhead:
    it runs a few dozen times per frame on small arrays.
    """
    return np.sqrt(np.add.reduce(vectors * vectors, axis=-1))


def resample_polyline(
    points_mm: FloatArray, n_points: int, *, arclength_mm: FloatArray | None = None
) -> FloatArray:
    """(M, 3) polyline -> (n_points, 3) points uniform in chord length (linear interpolation).

    ``arclength_mm`` (M,): its :func:`polyline_arclength`, if the caller has it.
    """
    pts = np.asarray(points_mm, dtype=np.float64)
    s = polyline_arclength(pts) if arclength_mm is None else arclength_mm
    u = np.linspace(0.0, s[-1], n_points)
    return np.column_stack([np.interp(u, s, pts[:, i]) for i in range(3)])


def cut_polyline(points_mm: FloatArray, length_mm: float) -> FloatArray:
    """The first ``length_mm`` of an (M, 3) polyline (at least its first segment's start)."""
    pts = np.asarray(points_mm, dtype=np.float64)
    s = polyline_arclength(pts)
    if length_mm >= s[-1]:
        return pts
    keep = s < length_mm
    at = np.interp(length_mm, s, np.arange(len(pts), dtype=np.float64))
    i = int(np.floor(at))
    end = pts[i] + (at - i) * (pts[min(i + 1, len(pts) - 1)] - pts[i])
    return np.vstack([pts[keep], end])


def self_intersects(points_mm: FloatArray, radius_mm: float, *, closest_radii: float = 1.0) -> bool:
    """Whether an (M, 3) axis comes back within ``closest_radii`` radii of itself (mm, world frame).

    Two parts of a tube of radius r cannot have axes closer than 2 r (the
    default, half that, leaves room for a fit a few mm off where they nearly
    touch); parts closer than 4 r along the curve (a bend) are not compared.
    NaN radius: False.
    """
    if not np.isfinite(radius_mm):
        return False
    pts = np.asarray(points_mm, dtype=np.float64)
    s = polyline_arclength(pts)
    apart = np.abs(s[:, None] - s[None, :]) > 4.0 * radius_mm
    gap = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=-1)
    return bool((apart & (gap < closest_radii * radius_mm)).any())


def axis_gap_mm(a_mm: FloatArray, b_mm: FloatArray, n_points: int = 64) -> float:
    """Largest distance (mm) between two (M, 3) axes at the same arc length from their
    bases, over the shorter one's length (a longer or shorter tip is not a gap)."""
    length = min(polyline_arclength(a_mm)[-1], polyline_arclength(b_mm)[-1])
    gap = resample_polyline(cut_polyline(a_mm, length), n_points) - resample_polyline(
        cut_polyline(b_mm, length), n_points
    )
    return float(np.max(np.linalg.norm(gap, axis=1)))


def by_fraction(values: FloatArray, n: int) -> FloatArray:
    """(n,) ``values`` (M,), given at M samples spread evenly along a curve, at n such samples
    (linear interpolation by the fraction of the way along)."""
    return np.interp(np.linspace(0.0, 1.0, n), np.linspace(0.0, 1.0, len(values)), values)


def unit_tangents(pts: FloatArray) -> FloatArray:
    """(N, 3) unit tangents of the polyline ``pts`` (N, 3), by central differences."""
    # np.gradient's own arithmetic (central differences / 2, one-sided at the
    # ends), without its per-call overhead.
    d = np.empty_like(pts)
    d[1:-1] = (pts[2:] - pts[:-2]) / 2.0
    d[0] = pts[1] - pts[0]
    d[-1] = pts[-1] - pts[-2]
    return d / np.maximum(vector_norms(d)[:, None], 1e-12)
