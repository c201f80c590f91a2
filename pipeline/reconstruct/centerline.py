"""The centreline: an ordered, smooth curve from the base to the tip.

Three steps, each its own module:

1. :mod:`pipeline.reconstruct.ordering` marches through the visual hull from the base and
   returns a rough polyline, base -> tip, that false bridges do not fool;
2. :mod:`pipeline.reconstruct.tube_fit` moves that polyline until the tube of radius r it
   describes projects onto every silhouette (the hull alone is wider than the
   tube, off-centre where the views are uneven, and overshoots the tip);
3. :func:`smooth_curve` (here) turns the fitted samples into a cubic spline,
   resampled uniformly in arc length, with unit tangents and curvature.

Where the hull is ambiguous (a loop whose tip crosses its stem in the views)
the march may choose wrong. A fitted tube that leaves part of a silhouette
unexplained (:func:`pipeline.reconstruct.quality.misfit_fractions`), or whose parts come
closer than a tube allows (a tip curled into its stem, which the stem hides in
most views), is therefore not taken as it is: other hypotheses are fitted (the
march coasting on its own course through the crowded hull; the fit without its
outlier rejection; the march resumed from the fitted end, or from where the
unexplained tube leaves the curve), and the one whose tube re-projects best
onto the silhouettes (IoU) wins, those whose parts come too close handicapped.
Where the hull was crowded and the tip's tube meets another part's in some
view (a loop's tip lying on its stem, whose edges the side readings can take
for the tip's), the tip is then bent to the pixels
(:func:`pipeline.reconstruct.tube_tip.bend_tip_to_pixels`), the stem under it fitted
again now that the tip is known (:func:`pipeline.reconstruct.tube_fit.refit_body`; also
from the stem bridged where it lies near the tip, which the tip's edges
pulled towards it), and the tip bent again against that stem. A tip lying
on its stem has no readings of its own, so the tip where the curve's own
course takes it (:func:`pipeline.reconstruct.tube_tip.continue_on_circle`) is bent too;
these last hypotheses are compared by how their tubes match the grey levels
(:func:`pipeline.reconstruct.tube_tip.coverage_mismatch`), which, unlike the IoU, tell a
tip lying on the stem from one beside it. A tip that then ends inside its
stem may be a loop the march ran the wrong way round (it took the tip's end,
lying beside the stem, for the loop's start): the loop run the other way is
fitted and bent too, and kept if it matches the grey levels clearly better
(:func:`_free_tip_from_stem`). Each frame stands alone.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import BSpline, make_lsq_spline
from scipy.spatial import cKDTree

from ..geometry.camera import Camera
from ..geometry.polyline import cut_polyline, polyline_arclength, resample_polyline, self_intersects
from .ordering import March, march_hull
from .quality import misfit_fractions, reprojection_iou, tube_mask
from .tube_fit import TubeFit, centre_across, fit_tube, refit_body, trim_unexplained_tail
from .tube_tip import (
    bend_tip_to_pixels,
    continue_on_circle,
    coverage_mismatch,
    pixel_coverages,
    tip_meets_tube,
)

__all__ = [
    "Centerline",
    "fit_centerline",
    "polyline_arclength",
    "radius_from_silhouettes",
    "resample_polyline",
    "self_intersects",
    "silhouette_score",
    "smooth_curve",
]

FloatArray = NDArray[np.float64]

# Spline knots every this many mm: fine enough for a loop of ~30 mm radius (the
# cubic's error on such a circle is < 0.01 mm), coarse enough to average the
# per-sample noise of the fit (samples are ~4 mm apart, so ~3 per knot span).
KNOT_SPACING_MM = 20.0
# A fitted tube whose worst view's misfit fraction (pipeline.reconstruct.quality) exceeds
# this leaves part of a silhouette unexplained: other hypotheses are tried.
# Measured on rendered sessions (radii 4-9 mm, both rigs): 0 on smooth shapes,
# <= 0.8 % where a loop's fit follows the tube, 2.8-12 % where it went astray.
MISFIT = 0.01
# Times a fit that stops short is carried on (see _carry_on).
_CARRY_ON_ROUNDS = 2
# How far back (in radii) a carried-on march may restart, coasting (see _carry_on).
_COAST_BACK_RADII = 8.0
# Two parts of a tube of radius r touch when their axes are 2 r apart; a fitted
# axis may stray from the true one by up to a quarter radius (the fit's outlier
# limit, pipeline.reconstruct.tube_fit._OUTLIER_RADII) on each part: a curve whose parts
# come closer than this many radii passes through itself and is not the tube.
# Measured on rendered loops (r 4-9 mm, both rigs): the true curves keep
# 2.1-4.2 r; the wrong hypotheses (a tip curled into the stem, a march run
# back along it) come to 0.5-1.4 r.
_CLOSEST_RADII = 1.5
# ... yet where the stem hides a tip in most views, a curve whose tip curled
# into the stem can still be the tube but for its end (the bend then moves the
# tip): it is not dropped, it ranks this much lower in mean re-projection IoU.
# Measured where the tip hides: right and wrong tips differ by 0.01-0.03 in
# IoU; a curve that stops short of a loop's last part loses 0.1-0.5.
_IMPLAUSIBLE = 0.05
# The tip's last this many radii, as the bend placed them (its longest span,
# see pipeline.reconstruct.tube_tip.bend_tip_to_pixels), are held when the stem is refitted.
_HELD_TIP_RADII = 4.0
# The stem under a bent tip is bridged (see _bridge_under_tip) where it comes
# within this many radii of the tip's last _HELD_TIP_RADII radii, at least
# _BRIDGE_APART_RADII radii before them along the curve.
_BRIDGE_REACH_RADII = 3.0
_BRIDGE_APART_RADII = 4.0
# Measured bulges of the stem under a loop's tip: up to 1.2 radii (r 9 ninety
# loop); a bridge that moves the stem farther is not correcting such a pull.
_BRIDGE_MOVE_RADII = 1.5
# A hypothesis under a bent tip replaces the one chosen by IoU only if its
# coverage mismatch is this fraction lower. Measured on 13 loop sessions (r 5-9,
# both rigs; 150-frame r 9 ninety loop): mean of per-session mean error 0.336
# mm as before, 0.316 by the least mismatch alone, 0.318 with a 2 % margin,
# 0.320 with 5 %; average median tip 0.753 / 0.748 / 0.743 / 0.750 mm; and
# the 12-frame r 9 ninety loop's median tip 0.65 / 0.74 / 0.65 / 0.65 mm.
_COVERAGE_MARGIN = 0.02
# Under a bent tip, the curve's last this many radii (one hypothesis each) are
# redone along the circle its _CIRCLE_FIT_RADII radii before follow, and the
# best matches to the grey levels bent (see _continue_tip). Measured on the
# 150-frame r 9 ninety loop: 13 frames with tips 6-27 mm off before, none
# after (the chosen curve's continuations alone: 1, frame 33 at 14 mm; 3, 5
# and 8 radii back each won on some frames); bending every continuation
# instead of the best ones cost ~170 ms more a frame.
_CONTINUE_RADII = (3.0, 5.0, 8.0)
_CIRCLE_FIT_RADII = 6.0
# A loop run the wrong way round (see _free_tip_from_stem): its tip ends inside a
# part at least this many radii before it along the curve (a tight loop of a
# tube cannot bring its tip back to itself in fewer), and the true tip is
# sought this many radii past the junction where the wrong course left the
# loop. Measured on the 150-frame r 7 ninety loop (seed 23): on its 3
# reversed frames, refitted and bent from 3, 4 and 6 radii past the junction
# the tips come to 0.2-1.2 mm (20-25 mm before) and their coverage mismatch
# to 25-30 % below the reversed curve's; from 1 or 2 radii, the wrong course
# is kept, from 8 the loop's start is cut.
_LOOP_APART_RADII = 8.0
_REVERSE_RADII = (3.0, 4.5, 6.0)
# The loop run the other way is another course for the whole loop, not a
# correction of its end: it must match the grey levels clearly better. Measured
# (r 7 ninety loop above; 13 other loop sessions, r 4-9, both rigs): the
# reversals that set a tip right matched them 15-37 % better; one that won
# only by a better-fitted stem (tip 0.3 -> 21 mm, an r 9 loop) 2.7 %.
_REVERSE_MARGIN = 0.10
# A tip inside its stem that left the loop for it (see _free_tip_from_stem):
# the last this many radii redone on the circle this many radii before follow.
# Measured on the r 7 ninety loop's frame 149 (tip 28.6 mm off, left the loop
# ~6.4 radii before its end): redone 8 radii on the circle of the 10 before,
# refitted and bent, the tip comes to 0.5 mm (coverage mismatch 28 against
# 150; the truth's 26); 5 or 11 radii, or a circle of 6, stay 13-47 mm off.
_REDO_RADII = 8.0
_REDO_FIT_RADII = 10.0
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
    cap: str = "flat",
) -> tuple[Centerline, TubeFit]:
    """The whole centreline step: hull -> ordered polyline -> tube fit -> spline.

    Parameters
    ----------
    points_mm : (P, 3) float64 occupied voxel centres, world frame, mm.
    cameras, masks, contrasts : per camera: the camera, its (H, W) bool silhouette
        and (H, W) float32 foreground contrast (:func:`pipeline.reconstruct.tube_fit.foreground_contrast`).
    base_mm : (3,) where the tube starts, world frame, mm.
    base_known : the base is the session's mount point (kept fixed by the fit),
        not an estimate.
    radius_mm : first guess of the tube radius, mm.
    voxel_mm : voxel edge, mm.
    n_points : samples of the resulting curve.
    cap : the tube's end, "flat" or "round" (a hemisphere around the axis' end).

    Returns
    -------
    The :class:`Centerline` and the :class:`~pipeline.reconstruct.tube_fit.TubeFit` it came
    from (radius and residual). ValueError if the hull gives no curve.
    """

    def refine(point: FloatArray, direction: FloatArray) -> FloatArray | None:
        return centre_across(point, direction, cameras, contrasts, radius_mm=radius_mm)

    def fit(march: March, robust: bool = True) -> TubeFit:
        return _fit_march(
            march.points_mm, cameras, masks, contrasts, radius_mm, voxel_mm, base_known, robust, cap
        )

    scores: dict[int, tuple[TubeFit, float]] = {}

    def standing(candidate: TubeFit) -> float:
        # Candidates are ranked more than once: each is drawn and scored once.
        # The candidate is kept with its score: a dropped one's id could be
        # given to a new candidate, which would inherit its score (the result
        # then depended on the frames processed before).
        if id(candidate) not in scores:
            scores[id(candidate)] = (candidate, _standing(candidate, cameras, masks))
        return scores[id(candidate)][1]

    march = march_hull(points_mm, base_mm, radius_mm=radius_mm, voxel_mm=voxel_mm, refine=refine)
    best = fit(march)
    if march.crowded.any() and (_misfit(best, cameras, masks) > MISFIT or _passes_through_itself(best)):
        # The march had to choose where the hull swelled (a crossing, a false
        # bridge), and its tube leaves parts of the silhouettes unexplained (or
        # strays off them), or passes through itself (a tip curled into the
        # stem explains the silhouettes as well as the tip beside it, where the
        # stem hides it in most views): try the other hypotheses. Coasting
        # keeps the curve's course through the crowd; without the outlier
        # rejection the fit keeps readings that a wrong curve would call
        # inconsistent. The tube that explains the silhouettes best
        # (re-projection IoU, see _standing) wins.
        coasted = march_hull(
            points_mm, base_mm, radius_mm=radius_mm, voxel_mm=voxel_mm, refine=refine, coast=True
        )
        candidates = [best, fit(coasted), fit(march, robust=False), fit(coasted, robust=False)]
        # A tube cannot pass through itself, but a curve that does (a tip curled
        # into the stem) may still be the tube but for its end, while one that
        # keeps apart may have stopped short: both are carried on, and the
        # better (a curve passing through itself handicapped) wins.
        seeds = [max(candidates, key=standing)]
        apart = [c for c in candidates if not _passes_through_itself(c)]
        if apart and max(apart, key=standing) is not seeds[0]:
            seeds.append(max(apart, key=standing))
        carried = [
            _carry_on(seed, fit, standing, points_mm, base_mm, cameras, masks, radius_mm, voxel_mm, refine)
            for seed in seeds
        ]
        best = max(carried, key=standing)
    if (
        march.crowded.any()
        and np.isfinite(best.radius_mm)
        and best.radius_mm > 0
        and tip_meets_tube(best.points_mm, cameras, best.radius_mm)
    ):
        # The tip lies against another part of the tube in some view, whose
        # edges can pull the tip's side readings off it: the tip is bent to
        # the pixels instead (see pipeline.reconstruct.tube_tip). The stem the tip lies on
        # was fitted while the tip was misplaced, and the tip's edges pulled
        # it too: with the tip placed, the stem under it is read again (the
        # views where the tip's tube touches it are now known, see
        # pipeline.reconstruct.tube_fit.refit_body), and the tip bent again against it.
        radius = best.radius_mm
        # The grey levels read as coverage once for every bend and comparison.
        coverages = pixel_coverages(contrasts, masks)

        def mismatch(axes_mm: Sequence[FloatArray]) -> list[float]:
            return coverage_mismatch(axes_mm, cameras, masks, contrasts, radius, coverages=coverages, cap=cap)

        def bend(axis_mm: FloatArray) -> FloatArray:
            # Only a bend that runs into the tube is refused, not one that comes
            # close (as candidates are, above): the search's path from a tip
            # against the stem to the right place can pass closer than 1.5 r.
            return bend_tip_to_pixels(
                axis_mm,
                cameras,
                masks,
                contrasts,
                radius,
                rejects=lambda axis: self_intersects(axis, radius),
                coverages=coverages,
                cap=cap,
            )

        bent = bend(best.points_mm)
        hold = float(polyline_arclength(bent)[-1]) - _HELD_TIP_RADII * radius
        # The stem may bulge towards the tip (see _bridge_under_tip): it is
        # refitted both as it is and bridged there, and the tube that explains
        # the silhouettes better is kept (bridging a stem that does bend there
        # loses its bend, where the readings near the tip are dropped); the tip
        # is then bent again against it. Measured on the 150-frame r 9 loop:
        # 0.405 / 1.308 / 0.833 mm mean / p95 / median tip without the bridge,
        # 0.372 / 1.133 / 0.867 with it.
        stems = [bent]
        bridged = _bridge_under_tip(bent, radius, hold_from_mm=hold)
        if bridged is not bent:
            stems.append(bridged)
        # The tip and a stem bulging towards it hold each other in place (each
        # explains pixels the other should), and the first bend, made against
        # the bulge, can take the tip farther off: the stem as the fit had it,
        # bridged, is a hypothesis too.
        others = []
        bridged = _bridge_under_tip(best.points_mm, radius, hold_from_mm=hold)
        if bridged is not best.points_mm:
            others.append(bridged)
        refits = [
            refit_body(start, cameras, contrasts, radius_mm=radius, hold_from_mm=hold, base_fixed=base_known)
            for start in stems + others
        ]
        first = 0
        if len(stems) > 1:
            standings = [_standing(replace(best, points_mm=r), cameras, masks) for r in refits[: len(stems)]]
            first = int(np.argmax(standings))
        # Measured (12-frame r 9 ninety loop; 150 frames of it): the second
        # bend takes mean / p95 / median tip / length from 0.44 / 1.61 / 2.11 /
        # 1.10 to 0.40 / 1.30 / 1.92 / 0.86 (0.43 / 1.47 / 1.90 / 1.05 to 0.42
        # / 1.42 / 1.77 / 0.94), for ~25 ms more on such a frame.
        bents = [bend(refit) for refit in refits]
        if len(bents) > 1:
            # With their tips bent, the hypotheses are compared by how they
            # match the grey levels (pipeline.reconstruct.tube_tip.coverage_mismatch): the
            # silhouettes' IoU cannot tell a tip lying on the stem from one
            # beside it (on the wrong-tip frames of the 150-frame r 9 ninety
            # loop, the true curve's IoU was below the chosen one's on 5 of
            # 13, its coverage mismatch below on all 13). Another hypothesis
            # replaces the one the IoU chose only if its mismatch is
            # _COVERAGE_MARGIN lower: between near-equal tubes, the IoU's
            # choice held the median tip better (see the constant).
            costs = mismatch(bents)
            other = int(np.argmin(costs))
            if costs[other] < (1.0 - _COVERAGE_MARGIN) * costs[first]:
                first = other
        best = replace(best, points_mm=bents[first])
        # A tip lying on the stem has no side readings of its own, and the bend
        # searches near where the fit left it: the tip where the curve's own
        # course takes it is tried too (see _continue_tip).
        ordered = [bents[first]] + [b for n, b in enumerate(bents) if n != first]
        best = replace(best, points_mm=_continue_tip(ordered, bend, mismatch, radius))

        def refit(axis_mm: FloatArray) -> FloatArray:
            track = robust_track(axis_mm)
            tube = fit_tube(
                track, cameras, contrasts, radius_mm=radius, base_fixed=base_known, masks=masks, cap=cap
            )
            return tube.points_mm

        # A tip that ends inside the stem may be a loop run the wrong way
        # round, or one that left its loop for the stem where they cross.
        axis = _free_tip_from_stem(best.points_mm, refit, bend, mismatch, radius)
        best = replace(best, points_mm=axis)
    return smooth_curve(best.points_mm, n_points=n_points), best


def _free_tip_from_stem(
    points_mm: FloatArray,
    refit: Callable[[FloatArray], FloatArray],
    bend: Callable[[FloatArray], FloatArray],
    mismatch: Callable[[Sequence[FloatArray]], list[float]],
    radius_mm: float,
) -> FloatArray:
    """The axis (M, 3), or, if its tip ends inside its stem, a course that keeps
    it out, if that matches the grey levels better.

    Where a loop's tip comes back beside its stem, the march can take the
    tip's end for the loop's start where they meet: the curve then jumps from
    the stem to the tip, runs the loop backwards, and ends where the loop
    starts, inside the stem (its tube passes through itself there). That tube
    covers nearly the same pixels as the true one (the silhouettes' IoU cannot
    tell them apart) but for where the ends meet. So when the tip ends within
    ``_CLOSEST_RADII`` radii of a part at least ``_LOOP_APART_RADII`` radii
    before it, the loop is also run the other way: the curve up to that part
    (the junction), then the loop backwards from its end to a sample
    ``_REVERSE_RADII`` radii past the junction (where the wrong course left
    the loop for the tip: the new tip), each refitted (``refit``) and bent
    (``bend``). Where the loop crosses the stem in the views that see it
    edge-on, the march can also leave the loop for the stem: the curve's last
    ``_REDO_RADII`` radii are then redone along the circle the
    ``_REDO_FIT_RADII`` radii before follow
    (:func:`pipeline.reconstruct.tube_tip.continue_on_circle`), refitted and bent too. The
    axis that matches the grey levels best (``mismatch``, the frame's
    :func:`pipeline.reconstruct.tube_tip.coverage_mismatch`), by ``_REVERSE_MARGIN``, wins.
    """
    pts = np.asarray(points_mm, dtype=np.float64)
    arc = polyline_arclength(pts)
    before = arc < arc[-1] - _LOOP_APART_RADII * radius_mm
    if not before.any():
        return pts
    gap = np.linalg.norm(pts[before] - pts[-1], axis=1)
    j = int(np.argmin(gap))
    if gap[j] >= _CLOSEST_RADII * radius_mm:
        return pts
    axes = [pts]
    for k in _REVERSE_RADII:
        i = int(np.searchsorted(arc, arc[j] + k * radius_mm))
        # The loop is at least _LOOP_APART_RADII long, more than any cut: this
        # holds the last samples, which may be few where the junction is near.
        if i >= len(arc) - 2:
            break
        try:
            axes.append(bend(refit(np.vstack([pts[: j + 1], pts[i:][::-1]]))))
        except (ValueError, np.linalg.LinAlgError):
            continue
    redone = continue_on_circle(pts, redo_mm=_REDO_RADII * radius_mm, fit_mm=_REDO_FIT_RADII * radius_mm)
    try:
        axes.append(bend(refit(redone)))
    except (ValueError, np.linalg.LinAlgError):
        pass
    if len(axes) == 1:
        return pts
    costs = mismatch(axes)
    other = int(np.argmin(costs))
    return axes[other] if costs[other] < (1.0 - _REVERSE_MARGIN) * costs[0] else pts


def _continue_tip(
    curves_mm: Sequence[FloatArray],
    bend: Callable[[FloatArray], FloatArray],
    mismatch: Callable[[Sequence[FloatArray]], list[float]],
    radius_mm: float,
) -> FloatArray:
    """The chosen curve (``curves_mm[0]``), or one whose tip follows its own course, bent.

    Each curve's last few radii (``_CONTINUE_RADII``) are redone along the
    circle the part before follows (:func:`pipeline.reconstruct.tube_tip.continue_on_circle`);
    of these continuations, of the chosen curve and of the other hypotheses'
    curves (each (M_i, 3), bent, world frame, mm), the one that best matches
    the grey levels (``mismatch``, the frame's
    :func:`pipeline.reconstruct.tube_tip.coverage_mismatch`) is bent, and
    the chosen curve's best too if that is another (a continuation's match
    before its bend ranks it only roughly); the axis, (M, 3), that matches them
    best is returned, the chosen curve's own included.
    """
    continued = [
        continue_on_circle(curve, redo_mm=k * radius_mm, fit_mm=_CIRCLE_FIT_RADII * radius_mm)
        for curve in curves_mm
        for k in _CONTINUE_RADII
    ]
    costs = mismatch(continued)
    own = int(np.argmin(costs[: len(_CONTINUE_RADII)]))
    tries = sorted({own, int(np.argmin(costs))})
    axes = [curves_mm[0]] + [bend(continued[j]) for j in tries]
    costs = mismatch(axes)
    # No margin here (unlike between the stems, see fit_centerline): where the
    # tip hides, the matches differ by ~1 %, and the least one was the nearer
    # tip more often. Measured, 150-frame r 9 ninety loop: 0.281 / 0.801 /
    # 0.757 mm mean / p95 / median tip with a 2 % margin, 0.270 / 0.752 / 0.663
    # without (smoothed tip jitter 2.8 -> 1.9 times the truth's); the 11 other
    # loops' median tips equal or lower.
    return axes[int(np.argmin(costs))]


def _bridge_under_tip(points_mm: FloatArray, radius_mm: float, *, hold_from_mm: float) -> FloatArray:
    """(M, 3) axis with the part of the stem that lies near its tip replaced by a
    spline through the stem around it.

    The tip's edges, taken for the stem's while the tip was misplaced, pull the
    stem towards it (a bulge of up to a radius over a few radii); refitting
    the stem cannot undo it where the views that see both have their readings
    dropped as crowded (the corrections there follow their neighbours', so the
    bulge stays): bridged first, the stem there is what its neighbours say,
    and the views that do see it move it.
    """
    pts = np.asarray(points_mm, dtype=np.float64)
    arc = polyline_arclength(pts)
    tip = pts[arc >= hold_from_mm]
    stem = arc < hold_from_mm - _BRIDGE_APART_RADII * radius_mm
    if len(tip) == 0 or stem.sum() < 8:
        return pts
    gap = np.sqrt(((pts[:, None, :] - tip[None, :, :]) ** 2).sum(-1)).min(axis=1)
    near = stem & (gap < _BRIDGE_REACH_RADII * radius_mm)
    near[0] = False  # the base stays where it is
    if not near.any():
        return pts
    keep = ~near
    weights = np.ones(int(keep.sum()))
    weights[[0, -1]] = 10.0
    # The knots of smooth_curve's spline, but none over the bridged part: the
    # bridge is one cubic piece, as stiff as the stem it stands for (with
    # knots there, the pieces over it are held by the samples beyond, and
    # swing; over a long bridge some are held by none, and are undefined).
    # Measured on the r 9 ninety loop, 150 frames: 0.405 / 1.308 mm mean / p95
    # with knots over the bridge (or none only where it is undefined), 0.363 /
    # 1.118 mm without.
    total = float(arc[-1])
    inner = np.linspace(0.0, total, int(total / KNOT_SPACING_MM) + 2)[1:-1]
    inner = inner[(inner < arc[near].min()) | (inner > arc[near].max())]
    knots = np.concatenate([np.zeros(4), inner, np.full(4, total)])
    try:
        with np.errstate(invalid="ignore", divide="ignore"):
            bridge = make_lsq_spline(arc[keep], pts[keep], knots, k=3, w=weights)(arc[near])
    except (ValueError, np.linalg.LinAlgError):
        return pts
    # No bridge that moves the stem farther than the tip's pull can have (see
    # _BRIDGE_MOVE_RADII).
    if not np.isfinite(bridge).all():
        return pts
    if np.linalg.norm(bridge - pts[near], axis=1).max() > _BRIDGE_MOVE_RADII * radius_mm:
        return pts
    out = pts.copy()
    out[near] = bridge
    return out


def _carry_on(
    best: TubeFit,
    fit: Callable[[March], TubeFit],
    standing: Callable[[TubeFit], float],
    points_mm: FloatArray,
    base_mm: FloatArray,
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.bool_]],
    radius_mm: float,
    voxel_mm: float,
    refine: Callable[[FloatArray, FloatArray], FloatArray | None],
) -> TubeFit:
    """``best`` marched on again towards the tube its silhouettes still show.

    A march can stop where the hull is fat (two parts of a loop merged in most
    views), or follow the wrong branch where the tip meets the stem, though the
    fitted curve is on the tube up to there. The hull points that project onto
    silhouette pixels the fitted tube leaves unexplained are where the rest of
    the tube is: march again from the curve's sample nearest to them (in its
    second half: the first is held by the base), towards them, never back onto
    the curve before it, and fit again (also from the end, and coasting from a
    few diameters back); keep the result that ranks best by ``standing``
    (:func:`_standing`) if it ranks above ``best``. A ``best`` that passes
    through itself is carried on too, however well it explains the silhouettes.
    """
    score = standing(best)
    for _ in range(_CARRY_ON_ROUNDS):
        if _misfit(best, cameras, masks) <= MISFIT and not _passes_through_itself(best):
            break
        lost = _unexplained_points(points_mm, best, cameras, masks)
        # Fewer than half a radius of tube's worth of voxels is no tube.
        if len(lost) < 0.5 * np.pi * radius_mm**3 / voxel_mm**3:
            break
        curve = best.points_mm
        arc = polyline_arclength(curve)
        tree = cKDTree(lost)
        gap, nearest = tree.query(curve)
        gap = np.where(arc < 0.5 * arc[-1], np.inf, gap)
        j = int(np.argmin(gap))
        near = lost[tree.query_ball_point(lost[np.asarray(nearest, dtype=np.intp)[j]], 3.0 * radius_mm)]
        # From the end in its own direction; from the sample nearest the
        # unexplained tube, towards it (the same when the curve stopped short);
        # and from a few diameters back, coasting on the curve's own course
        # through the crowd (a tip pulled onto the stem it runs along).
        starts = [(len(curve) - 1, None, False)]
        if j < len(curve) - 1:
            starts.append((j, near.mean(axis=0) - curve[j], False))
        back = int(np.searchsorted(arc, arc[-1] - _COAST_BACK_RADII * radius_mm))
        if back > len(curve) // 2:
            starts.append((back, None, True))
        candidates = []
        for k, heading, coast in starts:
            march = march_hull(
                points_mm,
                base_mm,
                radius_mm=radius_mm,
                voxel_mm=voxel_mm,
                refine=refine,
                resume_mm=curve[: k + 1],
                heading=heading,
                coast=coast,
            )
            if polyline_arclength(march.points_mm)[-1] >= arc[k] + 2.0 * radius_mm:
                other = fit(march)
                candidates.append((standing(other), other))
        if not candidates or max(c[0] for c in candidates) <= score:
            break
        score, best = max(candidates, key=lambda c: c[0])
    return best


def _unexplained_points(
    points_mm: FloatArray, fit: TubeFit, cameras: Sequence[Camera], masks: Sequence[NDArray[np.bool_]]
) -> FloatArray:
    """(U, 3) hull points that project, in some view, onto silhouette pixels more
    than a pixel away from the fitted tube's re-projection."""
    pts = np.asarray(points_mm, dtype=np.float64)
    lost = np.zeros(len(pts), dtype=bool)
    grow = np.ones((3, 3), np.uint8)
    for cam, mask in zip(cameras, masks, strict=True):
        tube = cv2.dilate(tube_mask(cam, fit.points_mm, fit.radius_mm).view(np.uint8), grow).view(bool)
        free = mask & ~tube
        px = np.round(cam.project(pts)).astype(np.int64)
        h, w = mask.shape
        ok = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        lost[ok] |= free[px[ok, 1], px[ok, 0]]
    return pts[lost]


def _fit_march(
    track: FloatArray,
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.bool_]],
    contrasts: Sequence[NDArray[np.float32]],
    radius_mm: float,
    voxel_mm: float,
    base_known: bool,
    robust: bool = True,
    cap: str = "flat",
) -> TubeFit:
    """A march's polyline -> trimmed, cut before the hull's overshoot, fitted tube."""
    if len(track) < 3:
        raise ValueError("the hull holds no tube near the base")
    # The tube lies inside the hull, and the march stops within a step (< a
    # radius) of the hull's end: the tip cannot be farther along than that.
    hull_end = float(polyline_arclength(track)[-1]) + radius_mm
    track = trim_unexplained_tail(track, cameras, masks, radius_mm=radius_mm)
    # The hull of a tube overshoots its end by up to a radius (more from steep
    # views), and the march's last steps drift in it: start the fit from before
    # that; the fit finds the end from the images.
    length = float(polyline_arclength(track)[-1])
    track = cut_polyline(track, max(length - 1.5 * radius_mm - voxel_mm, 0.5 * length))
    if len(track) >= 8:
        track = robust_track(track)
    return fit_tube(
        track,
        cameras,
        contrasts,
        radius_mm=radius_mm,
        base_fixed=base_known,
        masks=masks,
        max_length_mm=hull_end,
        robust=robust,
        cap=cap,
    )


def _misfit(fit: TubeFit, cameras: Sequence[Camera], masks: Sequence[NDArray[np.bool_]]) -> float:
    """The worst view's :func:`.quality.misfit_fractions` of a fitted tube (1 if no radius)."""
    if not (np.isfinite(fit.radius_mm) and fit.radius_mm > 0):
        return 1.0
    return max(misfit_fractions(cameras, masks, fit.points_mm, fit.radius_mm))


def _passes_through_itself(fit: TubeFit) -> bool:
    """Whether a fitted tube's parts come closer than ``_CLOSEST_RADII`` radii: not a tube."""
    return self_intersects(fit.points_mm, fit.radius_mm, closest_radii=_CLOSEST_RADII)


def _standing(fit: TubeFit, cameras: Sequence[Camera], masks: Sequence[NDArray[np.bool_]]) -> float:
    """How a candidate ranks: its :func:`silhouette_score`, less ``_IMPLAUSIBLE`` if
    its parts come closer than a tube allows (:func:`_passes_through_itself`)."""
    penalty = _IMPLAUSIBLE if _passes_through_itself(fit) else 0.0
    return silhouette_score(fit, cameras, masks) - penalty


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
            focal = cam.focal_px
            radii.append(np.count_nonzero(mask) / perimeter * depth / focal)
    return float(np.median(radii)) if radii else float("nan")
