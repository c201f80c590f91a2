"""The centreline: an ordered, smooth curve from the base to the tip.

Three steps, each its own module:

1. :mod:`pipeline.ordering` marches through the visual hull from the base and
   returns a rough polyline, base -> tip, that false bridges do not fool;
2. :mod:`pipeline.tube_fit` moves that polyline until the tube of radius r it
   describes projects onto every silhouette (the hull alone is wider than the
   tube, off-centre where the views are uneven, and overshoots the tip);
3. :func:`smooth_curve` (here) turns the fitted samples into a cubic spline,
   resampled uniformly in arc length, with unit tangents and curvature.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import make_lsq_spline

FloatArray = NDArray[np.float64]

# Spline knots every this many mm: fine enough for a loop of ~30 mm radius (the
# cubic's error on such a circle is < 0.01 mm), coarse enough to average the
# per-sample noise of the fit (samples are ~4 mm apart, so ~3 per knot span).
KNOT_SPACING_MM = 12.0
# Dense evaluation factor used to invert arc length.
_DENSE = 16


@dataclass(frozen=True, eq=False)
class Centerline:
    """A curve ordered base -> tip, uniform in arc length.

    Attributes
    ----------
    points_mm : (N, 3) float64, world frame, mm; points_mm[0] is the base end.
    tangents : (N, 3) float64 unit tangents (towards the tip).
    curvature_per_mm : (N,) float64 curvature, 1/mm.
    length_mm : arc length, mm.
    """

    points_mm: FloatArray
    tangents: FloatArray
    curvature_per_mm: FloatArray
    length_mm: float

    @property
    def tip_mm(self) -> FloatArray:
        return self.points_mm[-1]


def polyline_arclength(points_mm: FloatArray) -> FloatArray:
    """(M,) cumulative chord length along an (M, 3) polyline, starting at 0 (mm)."""
    seg = np.linalg.norm(np.diff(points_mm, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)])


def resample_polyline(points_mm: FloatArray, n_points: int) -> FloatArray:
    """(M, 3) polyline -> (n_points, 3) points uniform in chord length (linear interpolation)."""
    pts = np.asarray(points_mm, dtype=np.float64)
    s = polyline_arclength(pts)
    u = np.linspace(0.0, s[-1], n_points)
    return np.column_stack([np.interp(u, s, pts[:, i]) for i in range(3)])


def smooth_curve(
    polyline_mm: FloatArray, *, n_points: int = 64, knot_spacing_mm: float = KNOT_SPACING_MM
) -> Centerline:
    """Least-squares cubic spline through an ordered polyline, resampled by arc length.

    Parameters
    ----------
    polyline_mm : (M, 3) float64 ordered base -> tip, world frame, mm; M >= 2.
    n_points : N, samples of the result (both ends included).
    knot_spacing_mm : distance between interior knots along the curve.

    Returns
    -------
    :class:`Centerline` with N points. The ends are held (weighted 100x) so the
    curve starts and stops where the polyline does.
    """
    pts = np.asarray(polyline_mm, dtype=np.float64)
    s = polyline_arclength(pts)
    keep = np.concatenate([[True], np.diff(s) > 1e-9])  # repeated points break the spline
    pts, s = pts[keep], s[keep]
    total = float(s[-1])
    if len(pts) < 2 or total <= 0:
        raise ValueError("smooth_curve needs at least two distinct points")
    k = min(3, len(pts) - 1)
    # At least k + 1 data points per knot span (Schoenberg-Whitney, with room).
    n_inner = int(min(total / knot_spacing_mm, (len(pts) - k - 1) / 2.0))
    inner = np.linspace(0.0, total, n_inner + 2)[1:-1] if n_inner > 0 else np.zeros(0)
    knots = np.concatenate([np.zeros(k + 1), inner, np.full(k + 1, total)])
    weights = np.ones(len(s))
    weights[[0, -1]] = 100.0
    spline = make_lsq_spline(s, pts, knots, k=k, w=weights)

    dense_u = np.linspace(0.0, total, _DENSE * max(n_points, len(pts)))
    dense_s = polyline_arclength(spline(dense_u))
    u = np.interp(np.linspace(0.0, dense_s[-1], n_points), dense_s, dense_u)
    points = spline(u)
    d1 = spline(u, 1)
    d2 = spline(u, 2) if k >= 2 else np.zeros_like(d1)
    speed = np.linalg.norm(d1, axis=1)
    tangents = d1 / speed[:, None]
    curvature = np.linalg.norm(np.cross(d1, d2), axis=1) / speed**3
    return Centerline(
        points_mm=points, tangents=tangents, curvature_per_mm=curvature, length_mm=float(dense_s[-1])
    )
