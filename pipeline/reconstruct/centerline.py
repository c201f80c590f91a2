"""The centreline: an ordered, smooth curve from the base to the tip.

Three steps, each its own module:

1. :mod:`pipeline.reconstruct.ordering` marches through the visual hull from the base and
   returns a rough polyline, base -> tip, that false bridges do not fool;
2. :mod:`pipeline.reconstruct.tube_fit` moves that polyline until the tube of radius r it
   describes projects onto every silhouette (the hull alone is wider than the
   tube, off-centre where the views are uneven, and overshoots the tip);
3. :func:`pipeline.reconstruct.spline.smooth_curve` turns the fitted samples into a cubic spline,
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
A tube may stop where one view loses it (in front of something of its own grey
level, or behind something), where the hull, which needs every view, stops too: a
march carried on from the end through the voxels that every view but one sees is
one of those hypotheses, and a tube that still leaves part of a silhouette
unexplained is carried on through them alone.
Where the hull was crowded and the tip's tube meets another part's in some
view (a loop's tip lying on its stem, whose edges the side readings can take
for the tip's), the tip is then bent to the pixels
(:func:`pipeline.reconstruct.tip_bend.bend_tip_to_pixels`), the stem under it fitted
again now that the tip is known (:func:`pipeline.reconstruct.tube_fit.refit_body`; also
from the stem bridged where it lies near the tip, which the tip's edges
pulled towards it), and the tip, now near its place, fitted again against that stem
(:func:`pipeline.reconstruct.tip_bend.refine_tip_to_pixels`). A tip lying
on its stem has no readings of its own, so the tip where the curve's own
course takes it (:func:`pipeline.reconstruct.tip_bend.continue_on_circle`) is bent too;
these last hypotheses are compared by how their tubes match the grey levels
(:func:`pipeline.reconstruct.tube_drawing.coverage_mismatch`), which, unlike the IoU, tell a
tip lying on the stem from one beside it. A tip that then ends inside its
stem may be a loop the march ran the wrong way round (it took the tip's end,
lying beside the stem, for the loop's start): the loop run the other way is
fitted and bent too, and kept if it matches the grey levels clearly better
(:func:`pipeline.reconstruct.loop_tip.free_tip_from_stem`). Each frame stands alone.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import replace

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from ..geometry.camera import Camera
from ..geometry.polyline import cut_polyline, polyline_arclength, self_intersects
from .loop_tip import HELD_TIP_RADII, bridge_under_tip, continue_tip, free_tip_from_stem
from .ordering import March, march_hull
from .quality import tube_mask
from .radius_profile import RadiusProfile
from .side_readings import centre_across
from .spline import Centerline, robust_track, smooth_curve
from .tip_bend import BEND_SPANS_RADII, bend_tip_to_pixels, refine_tip_to_pixels, tip_meets_tube
from .tube_drawing import coverage_mismatch, pixel_coverages
from .tube_fit import TubeFit, fit_tube, refit_body, trim_unexplained_tail
from .tube_scores import MISFIT, passes_through_itself, ranked_score, worst_misfit

FloatArray = NDArray[np.float64]

# Times a fit that stops short is carried on (see _carry_on).
_CARRY_ON_ROUNDS = 2
# How far back (in radii) a carried-on march may restart, coasting (see _carry_on).
_COAST_BACK_RADII = 8.0
# A hypothesis under a bent tip replaces the one chosen by IoU only if its
# coverage mismatch is this fraction lower. Measured on 13 loop sessions (r 5-9,
# both rigs; 150-frame r 9 ninety loop): mean of per-session mean error 0.336
# mm as before, 0.316 by the least mismatch alone, 0.318 with a 2 % margin,
# 0.320 with 5 %; average median tip 0.753 / 0.748 / 0.743 / 0.750 mm; and
# the 12-frame r 9 ninety loop's median tip 0.65 / 0.74 / 0.65 / 0.65 mm.
_COVERAGE_MARGIN = 0.02


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
    wider_hull: Callable[[], FloatArray] | None = None,
    session_radii: RadiusProfile | None = None,
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
    wider_hull : () -> (Q, 3) mm, the voxel centres that every view but one sees
        (:func:`pipeline.reconstruct.frame.hull_but_one_view`), asked for only where the
        fitted tube leaves part of a silhouette unexplained.
    session_radii : the spacer disks (and the radius along the tube) read on the session's
        frames (:mod:`pipeline.reconstruct.radius_profile`), drawn in every fit.

    Returns
    -------
    The :class:`Centerline` and the :class:`~pipeline.reconstruct.tube_fit.TubeFit` it came
    from (radius and residual). ValueError if the hull gives no curve.
    """

    def refine(point: FloatArray, direction: FloatArray) -> FloatArray | None:
        return centre_across(point, direction, cameras, contrasts, radius_mm=radius_mm)

    def fit(march: March, robust: bool = True) -> TubeFit:
        return _fit_march(
            march.points_mm,
            cameras,
            masks,
            contrasts,
            radius_mm,
            voxel_mm,
            base_known,
            robust,
            cap,
            session_radii,
        )

    scores: dict[int, tuple[TubeFit, float]] = {}

    def standing(candidate: TubeFit) -> float:
        # Candidates are ranked more than once: each is drawn and scored once.
        # The candidate is kept with its score: a dropped one's id could be
        # given to a new candidate, which would inherit its score (the result
        # then depended on the frames processed before).
        if id(candidate) not in scores:
            scores[id(candidate)] = (candidate, ranked_score(candidate, cameras, masks))
        return scores[id(candidate)][1]

    # The voxels every view but one sees: carved once, if a start or a march carried on needs them.
    wider = functools.cache(wider_hull) if wider_hull is not None else None
    if wider is not None:
        points_mm = _bridged_to_base(points_mm, wider, base_mm, radius_mm + voxel_mm)
    march = march_hull(points_mm, base_mm, radius_mm=radius_mm, voxel_mm=voxel_mm, refine=refine)
    best = fit(march)
    if march.crowded.any() and (worst_misfit(best, cameras, masks) > MISFIT or passes_through_itself(best)):
        # The march had to choose where the hull swelled (a crossing, a false
        # bridge), and its tube leaves parts of the silhouettes unexplained (or
        # strays off them), or passes through itself (a tip curled into the
        # stem explains the silhouettes as well as the tip beside it, where the
        # stem hides it in most views): try the other hypotheses. Coasting
        # keeps the curve's course through the crowd; without the outlier
        # rejection the fit keeps readings that a wrong curve would call
        # inconsistent. The tube that explains the silhouettes best
        # (re-projection IoU, see standing) wins.
        coasted = march_hull(
            points_mm, base_mm, radius_mm=radius_mm, voxel_mm=voxel_mm, refine=refine, coast=True
        )
        candidates = [best, fit(coasted), fit(march, robust=False), fit(coasted, robust=False)]
        # A tube cannot pass through itself, but a curve that does (a tip curled
        # into the stem) may still be the tube but for its end, while one that
        # keeps apart may have stopped short: both are carried on, and the
        # better (a curve passing through itself handicapped) wins.
        seeds = [max(candidates, key=standing)]
        apart = [c for c in candidates if not passes_through_itself(c)]
        if apart and max(apart, key=standing) is not seeds[0]:
            seeds.append(max(apart, key=standing))
        carried = [
            _carry_on(
                seed, fit, standing, points_mm, base_mm, cameras, masks, radius_mm, voxel_mm, refine, wider
            )
            for seed in seeds
        ]
        best = max(carried, key=standing)
    if wider is not None and worst_misfit(best, cameras, masks) > MISFIT:
        # A part of the tube that one view does not show (passing in front of something
        # of its own grey level, or behind something) is not in the hull, and the march
        # stops where it starts, though the other views go on showing the tube: it is
        # carried on through the voxels that every view but one sees.
        best = _carry_on(best, fit, standing, wider(), base_mm, cameras, masks, radius_mm, voxel_mm, refine)
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
        # pipeline.reconstruct.tube_fit.refit_body), and the tip fitted again against it.
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
        hold = float(polyline_arclength(bent)[-1]) - HELD_TIP_RADII * radius
        # The stem may bulge towards the tip (see bridge_under_tip): it is
        # refitted both as it is and bridged there, and the tube that explains
        # the silhouettes better is kept (bridging a stem that does bend there
        # loses its bend, where the readings near the tip are dropped); the tip
        # is then fitted again against it. Measured on the 150-frame r 9 loop:
        # 0.405 / 1.308 / 0.833 mm mean / p95 / median tip without the bridge,
        # 0.372 / 1.133 / 0.867 with it.
        stems = [bent]
        bridged = bridge_under_tip(bent, radius, hold_from_mm=hold)
        if bridged is not bent:
            stems.append(bridged)
        # The tip and a stem bulging towards it hold each other in place (each
        # explains pixels the other should), and the first bend, made against
        # the bulge, can take the tip farther off: the stem as the fit had it,
        # bridged, is a hypothesis too.
        others = []
        bridged = bridge_under_tip(best.points_mm, radius, hold_from_mm=hold)
        if bridged is not best.points_mm:
            others.append(bridged)
        refits = [
            refit_body(start, cameras, contrasts, radius_mm=radius, hold_from_mm=hold, base_fixed=base_known)
            for start in stems + others
        ]
        first = 0
        if len(stems) > 1:
            standings = [
                ranked_score(replace(best, points_mm=r), cameras, masks) for r in refits[: len(stems)]
            ]
            first = int(np.argmax(standings))

        # The tips under the refitted stems are near their place (the first bend put
        # them there): they are fitted by Gauss-Newton over the bend's spans
        # (refine_tip_to_pixels), not searched for. Placing the tip again under the
        # refitted stem (12-frame r 9 ninety loop, and 150 frames of it; searched for):
        # mean / p95 / median tip / length 0.44 / 1.61 / 2.11 / 1.10 -> 0.40 / 1.30 /
        # 1.92 / 0.86 (0.43 / 1.47 / 1.90 / 1.05 -> 0.42 / 1.42 / 1.77 / 0.94). Frames
        # started from the hull (2026-12-04), these tips searched for against fitted:
        # 192 frames of 16 loops (`synth --shape loop`, seeds 1-8, r 5-9, both rigs,
        # every fifth of 60 frames) 231 -> 180 ms a start, mean 0.230 -> 0.219 mm, mean
        # tip 0.90 -> 0.74 mm, frames more than 2 mm off 14 -> 11; 280 frames of 28
        # drawn cases (`draw_cases(7100, 14)` and 7101, 30 frames, every third, the true
        # tube end) 60 -> 55 ms, mean 0.631 -> 0.624 mm, frames off 71 -> 70. Their
        # continuations (continue_tip) fitted too: 140 ms a start on the loops, but 12
        # frames off instead of 7 (seeds 1-4). Whole sessions tracked from such starts
        # (`accuracy_table --draw 97`, 103, 109 and 115, 8 cases of 90 frames each; same
        # day): the mean error averaged over the 32 sessions 0.352 mm either way, frames
        # more than 2 mm off 561 -> 586 (one session's 36 -> 67), good frames flagged
        # 201 -> 84 (a close call of the tube's end no longer close). A track's course
        # depends on its start: of draw 2's ten sessions (150 frames) two came out
        # worse, a tapered loop 0.23 -> 0.30 mm (its track went astray for 16 frames)
        # and a two-camera shape 2.18 -> 2.34 mm, and the other eight within 0.02 mm.
        def fit_tip(axis_mm: FloatArray) -> FloatArray:
            return refine_tip_to_pixels(
                axis_mm,
                cameras,
                masks,
                contrasts,
                radius,
                spans_radii=BEND_SPANS_RADII,
                rejects=lambda axis: self_intersects(axis, radius),
                cap=cap,
            )

        bents = [fit_tip(refit) for refit in refits]
        if len(bents) > 1:
            # With their tips bent, the hypotheses are compared by how they
            # match the grey levels (pipeline.reconstruct.tube_drawing.coverage_mismatch): the
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
        # course takes it is tried too (see continue_tip).
        ordered = [bents[first]] + [b for n, b in enumerate(bents) if n != first]
        best = replace(best, points_mm=continue_tip(ordered, bend, mismatch, radius))

        def refit(axis_mm: FloatArray) -> FloatArray:
            track = robust_track(axis_mm)
            tube = fit_tube(
                track,
                cameras,
                contrasts,
                radius_mm=radius,
                base_fixed=base_known,
                masks=masks,
                cap=cap,
                session_radii=session_radii,
            )
            return tube.points_mm

        # A tip that ends inside the stem may be a loop run the wrong way
        # round, or one that left its loop for the stem where they cross.
        axis = free_tip_from_stem(best.points_mm, refit, bend, mismatch, radius)
        best = replace(best, points_mm=axis)
    return smooth_curve(best.points_mm, n_points=n_points), best


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
    wider: Callable[[], FloatArray] | None = None,
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
    (:func:`.tube_scores.ranked_score`) if it ranks above ``best``. A ``best`` that passes
    through itself is carried on too, however well it explains the silhouettes.
    ``wider`` () -> (Q, 3) mm, the voxels that every view but one sees: the march
    from the end is tried through them too, across a stretch of tube that one view
    does not show, where the hull stops and a march towards the rest of the tube
    would join another part of it.
    """
    score = standing(best)
    for _ in range(_CARRY_ON_ROUNDS):
        if worst_misfit(best, cameras, masks) <= MISFIT and not passes_through_itself(best):
            break
        lost = _unexplained_points(points_mm, best, cameras, masks, radius_mm)
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
        starts = [(len(curve) - 1, None, False, points_mm)]
        if wider is not None:
            starts.append((len(curve) - 1, None, False, wider()))
        if j < len(curve) - 1:
            starts.append((j, near.mean(axis=0) - curve[j], False, points_mm))
        back = int(np.searchsorted(arc, arc[-1] - _COAST_BACK_RADII * radius_mm))
        if back > len(curve) // 2:
            starts.append((back, None, True, points_mm))
        candidates = []
        for k, heading, coast, voxels in starts:
            march = march_hull(
                voxels,
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
    points_mm: FloatArray,
    fit: TubeFit,
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.bool_]],
    radius_mm: float,
) -> FloatArray:
    """(U, 3) hull points that project, in some view, onto silhouette pixels more
    than a pixel away from the fitted tube's re-projection (drawn at ``radius_mm`` where
    the fit read no radius)."""
    radius = fit.radius_mm if np.isfinite(fit.radius_mm) else radius_mm
    pts = np.asarray(points_mm, dtype=np.float64)
    lost = np.zeros(len(pts), dtype=bool)
    grow = np.ones((3, 3), np.uint8)
    for cam, mask in zip(cameras, masks, strict=True):
        tube = cv2.dilate(tube_mask(cam, fit.points_mm, radius).view(np.uint8), grow).view(bool)
        free = mask & ~tube
        px = np.round(cam.project(pts)).astype(np.int64)
        h, w = mask.shape
        ok = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        lost[ok] |= free[px[ok, 1], px[ok, 0]]
    return pts[lost]


def _bridged_to_base(
    points_mm: FloatArray, wider: Callable[[], FloatArray], base_mm: FloatArray, reach_mm: float
) -> FloatArray:
    """The hull's (P, 3) ``points_mm``, and where none lies within ``reach_mm`` of the base
    (the march's first cross-section), the voxels every view but one sees (``wider``) up
    to a reach past the nearest: a view that lost the tube's first part (a thin tube the
    threshold breaks there, or one passing before something of its own grey level) cuts
    it from the hull, and the march would find nothing to start on."""
    if not len(points_mm):
        return points_mm
    gap = float(np.sqrt(np.min(np.einsum("ij,ij->i", points_mm - base_mm, points_mm - base_mm))))
    if gap <= reach_mm:
        return points_mm
    others = wider()
    near = others[np.linalg.norm(others - base_mm, axis=1) <= gap + reach_mm]
    return np.unique(np.concatenate([points_mm, near]), axis=0)


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
    session_radii: RadiusProfile | None = None,
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
        session_radii=session_radii,
    )
