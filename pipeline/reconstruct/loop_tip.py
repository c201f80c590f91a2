"""A loop's tip lying on its stem: the hypotheses that free it.

Where the tip lies on another part of the tube, its side readings are pulled by that
part's edges. Three hypotheses are fitted and bent to the grey levels: the stem
under the bent tip bridged where the tip pulled it (:func:`bridge_under_tip`), the
tip where the curve's own course takes it (:func:`continue_tip`), and the loop run the
other way round when the tip ends inside its stem (:func:`free_tip_from_stem`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import make_lsq_spline

from ..geometry.polyline import polyline_arclength
from .spline import KNOT_SPACING_MM
from .tip_bend import continue_on_circle
from .tube_scores import CLOSEST_RADII

FloatArray = NDArray[np.float64]

# The tip's last this many radii, as the bend placed them (its longest span,
# see pipeline.reconstruct.tip_bend.bend_tip_to_pixels), are held when the stem is refitted.
HELD_TIP_RADII = 4.0
# The stem under a bent tip is bridged (see bridge_under_tip) where it comes
# within this many radii of the tip's last HELD_TIP_RADII radii, at least
# _BRIDGE_APART_RADII radii before them along the curve.
_BRIDGE_REACH_RADII = 3.0
_BRIDGE_APART_RADII = 4.0
# Measured bulges of the stem under a loop's tip: up to 1.2 radii (r 9 ninety
# loop); a bridge that moves the stem farther is not correcting such a pull.
_BRIDGE_MOVE_RADII = 1.5
# Under a bent tip, the curve's last this many radii (one hypothesis each) are
# redone along the circle its _CIRCLE_FIT_RADII radii before follow, and the
# best matches to the grey levels bent (see continue_tip). Measured on the
# 150-frame r 9 ninety loop: 13 frames with tips 6-27 mm off before, none
# after (the chosen curve's continuations alone: 1, frame 33 at 14 mm; 3, 5
# and 8 radii back each won on some frames); bending every continuation
# instead of the best ones cost ~170 ms more a frame.
_CONTINUE_RADII = (3.0, 5.0, 8.0)
_CIRCLE_FIT_RADII = 6.0
# A loop run the wrong way round (see free_tip_from_stem): its tip ends inside a
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
# A tip inside its stem that left the loop for it (see free_tip_from_stem):
# the last this many radii redone on the circle this many radii before follow.
# Measured on the r 7 ninety loop's frame 149 (tip 28.6 mm off, left the loop
# ~6.4 radii before its end): redone 8 radii on the circle of the 10 before,
# refitted and bent, the tip comes to 0.5 mm (coverage mismatch 28 against
# 150; the truth's 26); 5 or 11 radii, or a circle of 6, stay 13-47 mm off.
_REDO_RADII = 8.0
_REDO_FIT_RADII = 10.0


def free_tip_from_stem(
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
    ``CLOSEST_RADII`` radii of a part at least ``_LOOP_APART_RADII`` radii
    before it, the loop is also run the other way: the curve up to that part
    (the junction), then the loop backwards from its end to a sample
    ``_REVERSE_RADII`` radii past the junction (where the wrong course left
    the loop for the tip: the new tip), each refitted (``refit``) and bent
    (``bend``). Where the loop crosses the stem in the views that see it
    edge-on, the march can also leave the loop for the stem: the curve's last
    ``_REDO_RADII`` radii are then redone along the circle the
    ``_REDO_FIT_RADII`` radii before follow
    (:func:`pipeline.reconstruct.tip_bend.continue_on_circle`), refitted and bent too. The
    axis that matches the grey levels best (``mismatch``, the frame's
    :func:`pipeline.reconstruct.tube_drawing.coverage_mismatch`), by ``_REVERSE_MARGIN``, wins.
    """
    pts = np.asarray(points_mm, dtype=np.float64)
    arc = polyline_arclength(pts)
    before = arc < arc[-1] - _LOOP_APART_RADII * radius_mm
    if not before.any():
        return pts
    gap = np.linalg.norm(pts[before] - pts[-1], axis=1)
    j = int(np.argmin(gap))
    if gap[j] >= CLOSEST_RADII * radius_mm:
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


def continue_tip(
    curves_mm: Sequence[FloatArray],
    bend: Callable[[FloatArray], FloatArray],
    mismatch: Callable[[Sequence[FloatArray]], list[float]],
    radius_mm: float,
) -> FloatArray:
    """The chosen curve (``curves_mm[0]``), or one whose tip follows its own course, bent.

    Each curve's last few radii (``_CONTINUE_RADII``) are redone along the
    circle the part before follows (:func:`pipeline.reconstruct.tip_bend.continue_on_circle`);
    of these continuations, of the chosen curve and of the other hypotheses'
    curves (each (M_i, 3), bent, world frame, mm), the one that best matches
    the grey levels (``mismatch``, the frame's
    :func:`pipeline.reconstruct.tube_drawing.coverage_mismatch`) is bent, and
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


def bridge_under_tip(points_mm: FloatArray, radius_mm: float, *, hold_from_mm: float) -> FloatArray:
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
