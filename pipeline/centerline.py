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

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import BSpline, make_lsq_spline

from .camera import Camera
from .ordering import March, march_hull
from .polyline import cut_polyline, polyline_arclength, resample_polyline
from .quality import reprojection_iou
from .tube_fit import TubeFit, centre_across, fit_tube, trim_unexplained_tail

__all__ = [
    "Centerline",
    "fit_centerline",
    "polyline_arclength",
    "radius_from_silhouettes",
    "resample_polyline",
    "smooth_curve",
]

FloatArray = NDArray[np.float64]

# Spline knots every this many mm: fine enough for a loop of ~30 mm radius (the
# cubic's error on such a circle is < 0.01 mm), coarse enough to average the
# per-sample noise of the fit (samples are ~4 mm apart, so ~3 per knot span).
KNOT_SPACING_MM = 20.0
# A fitted tube whose mean re-projection IoU reaches this explains the
# silhouettes as well as a correct one does (measured: 0.90-0.95 on every
# correct frame of the rendered shapes, radii 4-9 mm, against 0.3-0.88 where a
# loop's march went astray); below it, other hypotheses are tried.
GOOD_SCORE = 0.9
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
    knots = np.concatenate([np.zeros(k + 1), inner, np.full(k + 1, total)])
    return make_lsq_spline(s, pts, knots, k=k, w=weights)


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


def fit_centerline(
    points_mm: FloatArray,
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.bool_]],
    contrasts: Sequence[NDArray[np.float32]],
    *,
    base_mm: FloatArray,
    base_known: bool,
    radius_mm: float,
    voxel_mm: float,
    n_points: int = 64,
) -> tuple[Centerline, TubeFit]:
    """The whole centreline step: hull -> ordered polyline -> tube fit -> spline.

    Parameters
    ----------
    points_mm : (P, 3) float64 occupied voxel centres, world frame, mm.
    cameras, masks, contrasts : per camera: the camera, its (H, W) bool silhouette
        and (H, W) float32 foreground contrast (:func:`pipeline.tube_fit.foreground_contrast`).
    base_mm : (3,) where the tube starts, world frame, mm.
    base_known : the base is the session's mount point (kept fixed by the fit),
        not an estimate.
    radius_mm : first guess of the tube radius, mm.
    voxel_mm : voxel edge, mm.
    n_points : samples of the resulting curve.

    Returns
    -------
    The :class:`Centerline` and the :class:`~pipeline.tube_fit.TubeFit` it came
    from (radius and residual). ValueError if the hull gives no curve.
    """

    def refine(point: FloatArray, direction: FloatArray) -> FloatArray | None:
        return centre_across(point, direction, cameras, contrasts, radius_mm=radius_mm)

    def fit(march: March) -> TubeFit:
        return _fit_march(march.points_mm, cameras, masks, contrasts, radius_mm, voxel_mm, base_known)

    march = march_hull(points_mm, base_mm, radius_mm=radius_mm, voxel_mm=voxel_mm, refine=refine)
    best = fit(march)
    if march.crowded.any() and (score := silhouette_score(best, cameras, masks)) < GOOD_SCORE:
        # The march had to choose where the hull swelled (a crossing, a false
        # bridge), and its tube leaves the silhouettes poorly explained: the other
        # hypothesis keeps the curve's course through the crowd. The one whose
        # tube explains the silhouettes better wins.
        coasted = march_hull(
            points_mm, base_mm, radius_mm=radius_mm, voxel_mm=voxel_mm, refine=refine, coast=True
        )
        other = fit(coasted)
        if silhouette_score(other, cameras, masks) > score:
            best = other
    return smooth_curve(best.points_mm, n_points=n_points), best


def _fit_march(
    track: FloatArray,
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.bool_]],
    contrasts: Sequence[NDArray[np.float32]],
    radius_mm: float,
    voxel_mm: float,
    base_known: bool,
) -> TubeFit:
    """A march's polyline -> trimmed, cut before the hull's overshoot, fitted tube."""
    if len(track) < 3:
        raise ValueError("the hull holds no tube near the base")
    track = trim_unexplained_tail(track, cameras, masks, radius_mm=radius_mm)
    # The hull of a tube overshoots its end by up to a radius (more from steep
    # views), and the march's last steps drift in it: start the fit from before
    # that; the fit finds the end from the images.
    length = float(polyline_arclength(track)[-1])
    track = cut_polyline(track, max(length - 1.5 * radius_mm - voxel_mm, 0.5 * length))
    if len(track) >= 8:
        track = robust_track(track)
    # The tube lies inside the hull, and the march stops within a step (< a
    # radius) of the hull's end: the tip cannot be farther along than that.
    return fit_tube(
        track,
        cameras,
        contrasts,
        radius_mm=radius_mm,
        base_fixed=base_known,
        masks=masks,
        max_length_mm=length + radius_mm,
    )


def silhouette_score(fit: TubeFit, cameras: Sequence[Camera], masks: Sequence[NDArray[np.bool_]]) -> float:
    """How well a fitted tube explains the silhouettes: its mean re-projection IoU."""
    radius = fit.radius_mm if np.isfinite(fit.radius_mm) else 0.0
    if radius <= 0:
        return 0.0
    return float(np.mean(reprojection_iou(cameras, masks, fit.points_mm, radius)))


def radius_from_silhouettes(
    cameras: Sequence[Camera], masks: Sequence[NDArray[np.bool_]], centre_mm: FloatArray
) -> float:
    """Rough tube radius (mm) from the silhouettes' area / perimeter, NaN if none.

    A long strip of width w has area ~ w L and perimeter ~ 2 L, so w/2 ~
    area / perimeter (px), converted at the depth of ``centre_mm`` (3,). Only a
    first guess: the tube fit measures the radius properly.
    """
    radii = []
    for cam, mask in zip(cameras, masks, strict=True):
        contours, _ = cv2.findContours(mask.view(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        perimeter = sum(cv2.arcLength(c, True) for c in contours)
        depth = float(cam.to_camera(np.asarray(centre_mm, dtype=np.float64)[None])[0, 2])
        if perimeter > 0 and depth > 0:
            focal = float(np.mean(np.diag(cam.matrix)[:2]))
            radii.append(np.count_nonzero(mask) / perimeter * depth / focal)
    return float(np.median(radii)) if radii else float("nan")
