"""The centreline as a spline in arc length: fitted samples to a smooth, ordered curve.

:func:`smooth_curve` turns a fit's samples (base -> tip) into a cubic least-squares
spline, resampled uniformly in arc length, with unit tangents and curvature
(:class:`Centerline`); :func:`robust_track` smooths a polyline with outliers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import BSpline, make_lsq_spline

from ..geometry.polyline import polyline_arclength

FloatArray = NDArray[np.float64]

# Spline knots every this many mm: fine enough for a loop of ~30 mm radius (the
# cubic's error on such a circle is < 0.01 mm), coarse enough to average the
# per-sample noise of the fit (samples are ~4 mm apart, so ~3 per knot span).
KNOT_SPACING_MM = 20.0
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
    pts, s = _distinct(polyline_mm)
    total = float(s[-1])
    weights = np.ones(len(s))
    weights[[0, -1]] = 100.0
    spline = _lsq_spline(pts, s, weights, knot_spacing_mm)
    k = spline.k
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


def _distinct(polyline_mm: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Points (M, 3) without repeats (they break a spline) and their arc length (M,)."""
    pts = np.asarray(polyline_mm, dtype=np.float64)
    s = polyline_arclength(pts)
    keep = np.concatenate([[True], np.diff(s) > 1e-9])
    pts, s = pts[keep], s[keep]
    if len(pts) < 2 or s[-1] <= 0:
        raise ValueError("smooth_curve needs at least two distinct points")
    return pts, s


def _lsq_spline(pts: FloatArray, s: FloatArray, weights: FloatArray, knot_spacing_mm: float) -> BSpline:
    """Weighted least-squares cubic B-spline x(s), knots every ``knot_spacing_mm``."""
    total = float(s[-1])
    k = min(3, len(pts) - 1)
    # At least k + 1 data points per knot span (Schoenberg-Whitney, with room).
    n_inner = int(min(total / knot_spacing_mm, (np.count_nonzero(weights) - k - 1) / 2.0))
    inner = np.linspace(0.0, total, n_inner + 2)[1:-1] if n_inner > 0 else np.zeros(0)
    inner = _spans_with_data(inner, s[weights > 0], 2)
    knots = np.concatenate([np.zeros(k + 1), inner, np.full(k + 1, total)])
    return make_lsq_spline(s, pts, knots, k=k, w=weights)


def _spans_with_data(inner: FloatArray, s_kept: FloatArray, least: int) -> FloatArray:
    """The inner knots (I,) less those that leave a span between knots (the ends
    included) with fewer than ``least`` of the weighed points ``s_kept``.

    A span without data leaves the spline free there: across a gap in a track (the
    march across a break in the hull, its points beside the break dropped as
    outliers) it can run off by kilometres. Two points a span are enough for the
    tracks' smooth courses, and leave every track with data all along unchanged.
    """
    knots = list(inner)
    while knots:
        edges = np.concatenate([[-np.inf], knots, [np.inf]])
        counts = np.diff(np.searchsorted(s_kept, edges))
        short = np.flatnonzero(counts < least)
        if not len(short):
            break
        # The span's right knot, or its left one for the last span.
        span = int(short[0])
        del knots[min(span, len(knots) - 1)]
    return np.asarray(knots, dtype=np.float64)


def robust_track(
    track_mm: FloatArray, *, knot_spacing_mm: float = 15.0, outlier_mm: float = 2.5, rounds: int = 3
) -> FloatArray:
    """A march's polyline with its sideways excursions removed, (M, 3) -> (M', 3).

    Where the hull is crowded the march can wander a few mm off the axis for a
    few steps before the images pull it back. A spline fitted to the track, then
    refitted without the points farther than ``outlier_mm`` from it (``rounds``
    times), follows the axis through such excursions; the result is that spline
    sampled every ~2 mm, ends included.
    """
    pts, s = _distinct(track_mm)
    weights = np.ones(len(s))
    weights[[0, -1]] = 10.0
    for _ in range(rounds):
        spline = _lsq_spline(pts, s, weights, knot_spacing_mm)
        far = np.linalg.norm(spline(s) - pts, axis=1) > outlier_mm
        far[[0, -1]] = False
        if np.count_nonzero(~far) < 8:
            break
        weights = np.where(far, 0.0, weights)
    return np.asarray(spline(np.linspace(0.0, s[-1], max(int(s[-1] / 2.0), 2) + 1)))
