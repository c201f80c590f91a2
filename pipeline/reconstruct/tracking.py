"""Tracking: each frame's tube starts from the frames before it.

A manipulator moves continuously at 30 frames a second: the previous frames'
tubes are the best evidence there is for this frame's. Within a track, a
frame's fit starts from the last two tubes extrapolated with their velocity
(:func:`predict_axis`) and needs only a few rounds; a global initialisation
(the march through the hull, :func:`pipeline.reconstruct.centerline.fit_centerline`) runs
where a track starts and wherever it is lost.

Tracks are cut at fixed frame indices, not where the runner happens to split
the work: frame ``i`` belongs to the segment starting at
``SEGMENT_FRAMES * (i // SEGMENT_FRAMES)``, whose track starts ``WARMUP_FRAMES``
before it (:func:`track_start`), so that each segment's first frames are
already settled. A frame's curve therefore depends on the frames from its
track's start to itself only, the same whatever ``--jobs``, ``--frames`` or
backend the run uses.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import Camera
from ..geometry.polyline import axis_gap_mm, by_fraction, self_intersects
from .disks import Disks
from .frame_result import FrameResult
from .profiles import theil_sen_slope
from .quality import tube_figures
from .radius_profile import RadiusProfile
from .spline import Centerline, smooth_curve
from .tip_bend import REFINE_SPANS_RADII, refine_tip_to_pixels, tip_meets_tube
from .tube_fit import TubeFit, fit_tube

FloatArray = NDArray[np.float64]

# Frames per segment (3 s at 30 fps): each starts one global initialisation (and
# its warm-up), so the march runs on ~1 % of a steady track's frames, and a wrong
# start that no lost-track test catches is forgotten within 3 s. Against segments
# of 30 frames, on 31 rendered sessions (`accuracy_table` draws 2, 7 and 11, the
# demo, four loops; 150 frames, 2026-12-02): mean error averaged over the
# sessions 0.667 -> 0.641 mm, frames > 2 mm off 1056 -> 1050; the bench's loop
# processed in 40.7-43.2 s of CPU instead of 44.2-45.8 (two runs each, interleaved).
SEGMENT_FRAMES = 90
# A segment's track starts this many frames before it, so that its first frame is
# the third tracked one, not the initialisation.
WARMUP_FRAMES = 3
# Gauss-Newton rounds of a tracked fit (each re-reads the images): the
# prediction is within a fraction of a radius of the tube.
TRACK_ROUNDS = 2
# ... seeking the tube's peak this close to the prediction (radii).
TRACK_SEEK_RADII = 0.6
# A fit that moved farther than this many radii from its prediction is given as
# many rounds again, from where it got to.
TRACK_SETTLED_RADII = 0.5
# With every part where the prediction puts it, the crowding test knows where
# another part's blurred edges reach a sample's: two edges' worth, not one
# (the margin pipeline.reconstruct.tube_fit.refit_body uses once a loop's tip is placed).
TRACK_CROWD_MARGIN_PX = 4.0
# The track is lost where the fitted tube leaves more than this fraction of a
# silhouette unexplained beyond what the track's frames usually leave (usual_misfit;
# pipeline.reconstruct.quality.misfit_fractions; the initialisation's bar,
# pipeline.reconstruct.tube_scores.MISFIT, is the same 1 % without the usual share),
# after as many rounds of the fit again from where the first left it ...
# - Spacer disks the tube is drawn without leave 1-2.5 % of every frame:
#   judged against 1 % alone, their tracks were lost at up to 63 of 150 frames. Beyond
#   the usual share, on 12 rendered sessions with loops or disks (150 frames each,
#   tracked from frame 0, 2026-12-02) the disks' tracks started again from the hull
#   2-41 times instead of 2-63 (all 12: 141 against 274), at the same accuracy (mean
#   error averaged 0.915 against 0.929 mm, median tip 1.64 against 1.60 mm); 19
#   sessions without disks were unchanged but one (a two-camera r 4.5 shape whose
#   track is lost 27 times either way).
# - The rounds again: a tube that turns or curls faster than its velocity predicts is
#   still on its way after the first rounds, and its track was lost there for a start
#   from the hull, which on two cameras can pick a tube that explains both silhouettes
#   and lies tens of mm off in depth. On the 31 sessions above and beside them (12 with
#   loops or disks, `accuracy_table` draws 2, 13 and 21 without them, the demo; 150
#   frames each, 2026-12-02), the mean error averaged 0.589 -> 0.523 mm, its p95 2.18
#   -> 1.64 mm, the median tip 1.15 -> 1.08 mm, frames > 2 mm off 951 -> 938; a
#   two-camera r 7.5 random shape 1.41 -> 0.41 mm mean (p95 10.2 -> 1.25 mm), 21 of
#   the 31 unchanged.
LOST_MISFIT = 0.01
# ... passes through itself (parts' axes closer than this many radii) ...
LOST_CLOSEST_RADII = 1.5
# ... or moved farther than this many radii from its prediction in one frame, beyond
# how far the frames before lay from their own (prediction_miss_mm; see
# pipeline.reconstruct.quality.SUSPECT_JUMP_RADII).
LOST_JUMP_RADII = 1.5
# A track's prediction is expected to miss by the least of its last this many frames'
# misses of their own (prediction_miss_mm): the last alone let a track that jumps about
# (two cameras, spacer disks) go unflagged after each wide miss (see
# pipeline.reconstruct.quality.SUSPECT_JUMP_RADII).
MISS_FRAMES = 3
# Every tracked tip is fitted to the grey levels (refine_tip_to_pixels) over its last
# TRACK_TIP_SPANS_RADII radii: the side readings stop short of the end (the tip zone,
# pipeline.reconstruct.tube_tip), and the course extrapolated over it misses the tip
# where the tube straightens or turns toward its end. Where the tip meets another part
# of the tube in two views or lies against it in space (tip_meets_tube), its last radius
# is fitted too (REFINE_SPANS_RADII): the other part's edges, not the tip's, are what
# its side readings find there. Measured on `accuracy_table --draw 409`, `--draw 2` and
# `--draw 433` (8 cases of 90 frames each, 2026-12-06), against refining only those tips
# and those over the tube in one view whose other views leave them unplaced across:
# median tips 2.10 -> 0.41 mm (a tapered random shape, its frames more than 2 mm off 59
# -> 2), 2.24 -> 0.34 (a stepped s-curve on two cameras, 73 -> 5), 3.96 -> 0.28 (a
# random shape on two cameras, 89 -> 0), and closer by 0.03 mm or more on 16 of the
# other 21 (farther on one: a two-camera tube with spacer disks off everywhere either
# way, 4.45 -> 4.95 mm); the means within 0.02 mm but for a two-camera loop, 0.44 ->
# 0.50 mm, and disk sessions 1-9 mm off, 0.8-1.1 mm closer; frames more than 2 mm off
# 630 -> 433 in all. Fitting every tip's last radius as well (draws 409 and 2): tips
# 0.01-0.11 mm closer on ten of the 16, 0.07 mm farther on one, the two-camera loop 0.43
# -> 0.37 mm mean, at nearly twice the cost (9.4 against 5.5 ms a frame on the demo's
# frames, one core).
TRACK_TIP_SPANS_RADII = (4.0,)
# Where the tip meets another part of the tube (tip_meets_tube) and the stretch before it
# that the side readings place more loosely than LOOSE_END_SPREAD
# (pipeline.reconstruct.placement.Placement.loose_end_mm; samples that every view reads
# spread 0.6-0.9) is LOOSE_END_RADII or longer, judged over the last
# LOOSE_END_WITHIN_RADII, that stretch is bent to the grey levels first, its middle free
# of its tip (refine_tip_to_pixels' loose_span_radii): a loop's end that runs along its
# stem is crowded in every view, and the course the fit carries over it from the frames
# before drifts 2-5 mm off in its middle while the tip stays placed (the bench's r 7 loop,
# `recordings/bench-loop-round`). A loose end whose tip meets no other part is one the
# views look along, which the grey levels do not place either. Measured on
# `accuracy_table --draw 2`, 409, 433, 439 and 443 (8 cases of 90 frames each, 40
# sessions; 2026-12-06), against no such bend: frames more than 2 mm off 745 -> 707;
# two-camera sessions without disks 124 -> 74 (a stepped loop 46 -> 17, 0.50 -> 0.37 mm
# mean; a tapered random shape 39 -> 18, 1.68 -> 0.55 mm), three-camera loops 15 -> 13,
# three-camera other shapes without disks 11 -> 17 (a stepped random shape of draw 439,
# 4 -> 10, 0.37 -> 0.41 mm mean), with disks 253 -> 261; median tips closer by 0.03 mm
# or more on 4, farther on 1 (a two-camera loop with disks, off everywhere either way).
# The bench's loops (900 frames, `process` and `evaluate`): r 7, mean 0.279 -> 0.246 mm,
# p95 0.78 -> 0.62 mm, frames off 158 -> 78; r 9, 0.200 -> 0.193 mm, 41 -> 30; the demo
# unchanged. Without the tip's meeting as a condition: the same on the bench's loops, but
# draw 2's two-camera tapered random shape (150 frames) 23 -> 66 frames off (its tip 0.55
# -> 1.88 mm), and 707 -> 704 frames off on the five draws. The bend's length left free as
# well: draw 443's tapered loop's tip 0.51 -> 1.79 mm (its end lengthened past the true
# one); the part drawn with the radii along it and the tip's spans too: a two-camera
# stepped s-curve's tip 0.34 -> 1.82 mm. On the r 7 loop's first 300 frames, with the
# middle moved along the end's directions across and 3 steps, bars of 1.5, 2 and 2.5 left
# 20, 27 and 27 frames off (none: 68), 3 left 53; a shortest stretch of 4 radii 54, of
# 6 radii 35.
LOOSE_END_SPREAD = 2.0
LOOSE_END_RADII = 5.0
LOOSE_END_WITHIN_RADII = 16.0
# Where the track is lost on a rig of REDUNDANT_VIEWS or more, leaving part of a
# silhouette unexplained, the view it leaves most unexplained is left out and the track
# fitted to the others (track_without_odd_view): a camera whose image disagrees with the
# rest (a frame from another moment, a hand in front of its lens) otherwise pulls the tube
# off in every view and sends the frame to a start from a hull it has cut. Two views place
# a tube whether they agree or not: the others' tube is taken where it explains their
# silhouettes and leaves more than ODD_VIEW_MISFIT of the left-out view's unexplained,
# beyond ODD_VIEW_CONTRAST times the most it leaves of another view's. On 24 frames with
# one camera's picture taken 8 or 16 frames away (four shapes, three seeds; 2026-12-06)
# the view left most unexplained was the odd one wherever one was named (22), as each view
# left out in turn had found; that costs one fit where three took 50-95 ms, and a lost
# track whose tube leaves every view explained (a jump, a tube through itself) none: the
# thicker loop of `make bench` (300 frames, one core) started its six tracks in 310-720 ms
# against 370-750 ms. On nine frames with one camera's picture
# taken 8-16 frames away (three random shapes at two offsets, three other sessions), the
# others' tube came out 0.13-0.43 mm off at most on eight, the odd camera named, against
# 1.9-63 mm from the fit to every view or a start from the hull, which named another
# camera on two; the ninth odd picture was explained, and its frame 1.97 mm off, as
# before. The tube fitted to the others left none of their silhouettes unexplained and
# 6-134 % of the odd view's; on a tube with spacer disks, drawn without them, a
# clean view left 5-10 % where the others left 0.5-2.7 %. On 29 rendered sessions without
# such a fault (draws 353 and 359, 11 of 40-60 frames, a loop and a disk tube of 150;
# 2026-12-06) no view was left out, and every curve stayed as it was.
ODD_VIEW_MISFIT = 0.05
ODD_VIEW_CONTRAST = 10.0
# The track's last this many frames predict a frame's length (predict_length): a
# second at 30 fps.
LENGTH_FRAMES = 30
# A frame's misfit is judged beyond what its track's frames usually leave (usual_misfit),
# of which at most this counts: a track that leaves more at every frame is not on the tube.
USUAL_MISFIT_MAX = 0.03


def segment_start(index: int) -> int:
    """First frame of the segment that frame ``index`` belongs to."""
    return SEGMENT_FRAMES * (index // SEGMENT_FRAMES)


def track_start(index: int) -> int:
    """The frame where the track that reconstructs frame ``index`` starts."""
    return max(0, segment_start(index) - WARMUP_FRAMES)


def starts_next_track(index: int) -> bool:
    """Whether the track of the segment after frame ``index``'s starts at ``index``."""
    return (index + WARMUP_FRAMES) % SEGMENT_FRAMES == 0


def predict_axis(previous: Sequence[FrameResult], index: int | None = None) -> FloatArray | None:
    """(N, 3) mm: frame ``index``'s axis predicted from the last frames' results, or None.

    ``previous``: the track's results so far, oldest first; ``index``: the frame
    predicted (default: the one after the last). The last ok curve, moved on at the
    velocity it had from the one before where :func:`velocity_pair` gives one:
    constant velocity, over any gap between the frames (a live run drops frames when
    it falls behind); None when the last frame has no curve (the track is lost).
    """
    if not previous or previous[-1].centerline_mm is None:
        return None
    last = previous[-1]
    axis = np.asarray(last.centerline_mm, dtype=np.float64)
    ahead = 1 if index is None else index - last.index
    pair = velocity_pair(previous)
    if pair is None:
        return axis
    before, apart = pair
    if apart == 1 and ahead == 1:
        return 2.0 * axis - before
    return axis + ahead * ((axis - before) / apart)


def velocity_pair(previous: Sequence[FrameResult]) -> tuple[FloatArray, int] | None:
    """The curve (N, 3) mm the track's last one moved from, and how many frames before
    it, where the two give the track's velocity; None where they do not.

    Both frames ok and neither suspect (the curves are uniform in arc length with the
    same sample count, so sample k of one matches sample k of the other; a suspect
    curve, cut short say, would send the prediction's samples off by its error each
    frame)."""
    if len(previous) < 2 or previous[-2].suspect or previous[-1].suspect:
        return None
    before, last = previous[-2], previous[-1]
    apart = last.index - before.index
    if before.centerline_mm is None or last.centerline_mm is None or apart <= 0:
        return None
    if before.centerline_mm.shape != last.centerline_mm.shape:
        return None
    return np.asarray(before.centerline_mm, dtype=np.float64), apart


def prediction_miss_mm(previous: Sequence[FrameResult]) -> float:
    """How far (mm) the track's last ``MISS_FRAMES`` curves each lay, at least, from the
    prediction the frames before it made of it with their velocity (their
    ``FrameResult.jump_mm``): how much the track's velocity keeps changing from frame to
    frame. A tube that speeds up, slows down or turns misses a constant-velocity
    prediction by about as much again in the next frame; a track that jumps about misses
    some of its predictions by little. 0 where any of those frames is suspect or was not
    predicted with a velocity. ``previous``: the track's results so far, oldest first."""
    last = previous[-MISS_FRAMES:]
    if len(last) < MISS_FRAMES or any(r.suspect or not math.isfinite(r.jump_mm) for r in last):
        return 0.0
    return min(r.jump_mm for r in last)


def predict_length(previous: Sequence[FrameResult], index: int) -> float:
    """Frame ``index``'s length (mm) from the lengths of the track's last
    ``LENGTH_FRAMES`` ok frames (``previous``, oldest first), or NaN without any.

    The Theil-Sen line through them (the median of the slopes between every two
    frames, the median intercept), extrapolated to ``index``: a backbone keeps
    its length, or changes it as smoothly as an extending robot does, while a
    frame or a few with a tip cut short or run on lie off the line and do not
    move it. With fewer than three frames, their median.
    """
    frames, lengths = _last_lengths(previous)
    if not len(lengths):
        return math.nan
    if len(lengths) < 3:
        return float(np.median(lengths))
    slope = theil_sen_slope(frames, lengths)
    return float(np.median(lengths - slope * frames)) + slope * index


def held_length(previous: Sequence[FrameResult]) -> float:
    """The length (mm) a frame's tube keeps where no view places its end: the median of
    the track's last ``LENGTH_FRAMES`` frames' lengths (``previous``, oldest first), NaN
    without any.

    Not extrapolated as :func:`predict_length` is: an end that every view sees over
    another part of the tube, or end-on, leaves the fit free to lengthen the tube a
    little each frame, and a line through those lengths runs on with them. Measured on
    the tapered loop of ``accuracy_table --draw 2`` (2026-12-03): its tip, over its stem in
    two views and end-on in the third over frames 81-106, ran up to 43 mm on held to the
    line, and comes to at most 8 mm held at the median.
    """
    _, lengths = _last_lengths(previous)
    return float(np.median(lengths)) if len(lengths) else math.nan


def _last_lengths(previous: Sequence[FrameResult]) -> tuple[FloatArray, FloatArray]:
    """The frame indices (L,) and lengths (L,) mm of the track's last ``LENGTH_FRAMES``
    frames (``previous``, oldest first) that have a length."""
    known = [(r.index, r.length_mm) for r in previous[-LENGTH_FRAMES:] if math.isfinite(r.length_mm)]
    frames = np.array([i for i, _ in known], dtype=np.float64)
    return frames, np.array([n for _, n in known], dtype=np.float64)


def usual_misfit(previous: Sequence[FrameResult]) -> float:
    """The share of a silhouette the track's last ``LENGTH_FRAMES`` frames (``previous``,
    oldest first) usually leave unexplained: the median of their worst views', at most
    ``USUAL_MISFIT_MAX``; 0 without any. Spacer disks the tube is drawn without leave
    1-2.5 % of every frame unexplained."""
    worst = [max(r.misfits) for r in previous[-LENGTH_FRAMES:] if r.misfits]
    return min(float(np.median(worst)), USUAL_MISFIT_MAX) if worst else 0.0


@dataclass(frozen=True, eq=False)
class TrackedFit:
    """A fitted tube, the curve it gives and how that curve re-projects.

    fit : the fitted tube; None where the fit found no radius.
    curve : the fit's samples as the smooth curve a frame writes
        (:func:`pipeline.reconstruct.spline.smooth_curve`); None without a fit.
    radii_mm : (N,) the radius along ``curve``, mm; None where the fit read no
        radius profile.
    iou, misfits : per camera, the curve's tube re-projected onto the silhouettes
        (:func:`pipeline.reconstruct.quality.tube_figures`); empty without a curve.
    lost : why the track is lost here ("" where it holds).
    """

    fit: TubeFit | None
    curve: Centerline | None = None
    radii_mm: FloatArray | None = None
    iou: tuple[float, ...] = ()
    misfits: tuple[float, ...] = ()
    lost: str = ""

    @property
    def misfit(self) -> float:
        """The worst view's share of its silhouette the curve's tube leaves
        unexplained (:func:`pipeline.reconstruct.quality.misfit_fractions`); inf without a curve."""
        return max(self.misfits) if self.misfits else np.inf


def judge_fit(
    fit: TubeFit,
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.bool_]],
    *,
    n_points: int,
    radius_mm: float = np.nan,
    contrasts: Sequence[NDArray[np.float32]] | None = None,
    disks: Disks | None = None,
) -> TrackedFit:
    """``fit`` as the curve of ``n_points`` a frame writes, its tube drawn once in every
    view against the silhouettes (and ``contrasts``, see
    :func:`pipeline.reconstruct.quality.misfit_fractions`), with its spacer ``disks``;
    ``radius_mm`` draws it where the fit read no radius.
    A curve with non-finite points is never the best (misfit inf)."""
    curve = smooth_curve(fit.points_mm, n_points=n_points)
    # The fit's samples and the curve's are both uniform in arc length, end to end.
    radii = None if fit.radii_mm is None else by_fraction(fit.radii_mm, n_points)
    radius = fit.radius_mm if np.isfinite(fit.radius_mm) else radius_mm
    drawn = radii if radii is not None and np.isfinite(radii).all() else radius
    if not np.isfinite(curve.points_mm).all():
        return TrackedFit(fit, curve, radii)
    iou, misfits = tube_figures(cameras, masks, curve.points_mm, drawn, contrasts, disks)
    return TrackedFit(fit, curve, radii, iou, misfits)


def track_tube(
    predicted_mm: FloatArray,
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.bool_]],
    contrasts: Sequence[NDArray[np.float32]],
    *,
    radius_mm: float,
    base_known: bool,
    cap: str = "flat",
    radii_mm: FloatArray | None = None,
    n_points: int = 64,
    usual_misfit: float = 0.0,
    length_mm: float = np.nan,
    prediction_miss_mm: float = 0.0,
    session_radii: RadiusProfile | None = None,
) -> TrackedFit:
    """The tube fitted from its prediction (N, 3) mm, and whether the track holds.

    A few rounds of :func:`pipeline.reconstruct.tube_fit.fit_tube` from the prediction,
    seeking the tube's sides near it; the tip is then placed by the grey levels, fitted
    from where the fit left it (:func:`pipeline.reconstruct.tip_bend.refine_tip_to_pixels`,
    over ``TRACK_TIP_SPANS_RADII``, or ``REFINE_SPANS_RADII`` where it lies against
    another part of the tube: :func:`pipeline.reconstruct.tip_bend.tip_meets_tube`).
    The track is lost (the caller initialises again from the hull) where the
    fit leaves part of a silhouette unexplained even after as many rounds again,
    passes through itself, or jumped from the prediction (``LOST_*``).
    ``cap``: the tube's end, "flat" or "round"; ``radii_mm``: (N,) the radius at
    each point of the prediction, mm (default ``radius_mm`` everywhere);
    ``n_points``: samples of the curve judged (:func:`judge_fit`); ``usual_misfit``:
    the share of a silhouette the track's frames usually leave unexplained
    (:func:`usual_misfit`), beyond which the misfit is judged; ``length_mm``: the
    length the tube keeps where no view reads its end (:func:`held_length`);
    ``prediction_miss_mm``: how far the track's last frames each lay, at least, from their
    own predictions (:func:`prediction_miss_mm`), beyond which a jump is judged;
    ``session_radii``: the radius along the tube read on the session's frames
    (:mod:`pipeline.reconstruct.radius_profile`), where no view of this frame reads it.
    """
    if not (np.isfinite(radius_mm) and radius_mm > 0):
        return TrackedFit(None, lost="no radius to track")
    disks = None if session_radii is None else session_radii.disks

    def rounds(start_mm: FloatArray, radius: float, radii: FloatArray | None) -> TubeFit:
        return fit_tube(
            start_mm,
            cameras,
            contrasts,
            radius_mm=radius,
            radii_mm=radii,
            base_fixed=base_known,
            masks=masks,
            iterations=TRACK_ROUNDS,
            cap=cap,
            seek_radii=TRACK_SEEK_RADII,
            crowd_margin_px=TRACK_CROWD_MARGIN_PX,
            unseen_length_mm=length_mm,
            session_radii=session_radii,
        )

    def judged_with_tip(fit: TubeFit) -> TrackedFit:
        """``fit`` judged, its tip first fitted to the grey levels as above, and the loose
        stretch before a tip that meets the tube too (the radii follow the bent tip by
        sample fraction)."""
        meets = tip_meets_tube(fit.points_mm, cameras, fit.radius_mm)
        radius = fit.end_radius_mm
        loose = 0.0
        if meets and fit.placement is not None:
            loose = fit.placement.loose_end_mm(LOOSE_END_SPREAD, LOOSE_END_WITHIN_RADII * radius) / radius
        bent = refine_tip_to_pixels(
            fit.points_mm,
            cameras,
            masks,
            contrasts,
            radius,
            spans_radii=REFINE_SPANS_RADII if meets else TRACK_TIP_SPANS_RADII,
            rejects=lambda axis: self_intersects(axis, fit.radius_mm),
            cap=cap,
            radii_mm=fit.radii_mm,
            loose_span_radii=loose if loose >= LOOSE_END_RADII else 0.0,
            disks=disks,
        )
        fit = replace(
            fit,
            points_mm=bent,
            radii_mm=None if fit.radii_mm is None else by_fraction(fit.radii_mm, len(bent)),
        )
        return judge_fit(fit, cameras, masks, n_points=n_points, contrasts=contrasts, disks=disks)

    def read_a_tube(fit: TubeFit) -> bool:
        return bool(np.isfinite(fit.radius_mm) and fit.radius_mm > 0 and len(fit.points_mm) >= 3)

    fit = rounds(predicted_mm, radius_mm, radii_mm)
    if (
        np.isfinite(fit.radius_mm)
        and axis_gap_mm(fit.points_mm, predicted_mm) > TRACK_SETTLED_RADII * radius_mm
    ):
        # A prediction this far off (fast motion) has not settled in a few rounds.
        fit = rounds(fit.points_mm, fit.radius_mm, fit.radii_mm)
    if not read_a_tube(fit):
        return TrackedFit(None, lost="the fit read no tube")
    judged = judged_with_tip(fit)
    lost_misfit = LOST_MISFIT + usual_misfit
    if judged.misfit > lost_misfit and judged.fit is not None:
        # Part of a silhouette left unexplained: as many rounds again, from where the fit
        # got to, before the track is called lost (see LOST_MISFIT).
        again = rounds(judged.fit.points_mm, judged.fit.radius_mm, judged.fit.radii_mm)
        if read_a_tube(again):
            retried = judged_with_tip(again)
            if retried.misfit < judged.misfit:
                judged = retried
    fit = judged.fit if judged.fit is not None else fit
    lost = ""
    if judged.misfit > lost_misfit:
        lost = "leaves part of a silhouette unexplained"
    elif self_intersects(fit.points_mm, fit.radius_mm, closest_radii=LOST_CLOSEST_RADII):
        lost = "passes through itself"
    elif axis_gap_mm(fit.points_mm, predicted_mm) > LOST_JUMP_RADII * fit.radius_mm + prediction_miss_mm:
        lost = "jumped from its prediction"
    return replace(judged, lost=lost)


def track_without_odd_view(
    track: Callable[[Sequence[int]], TrackedFit],
    lost: TrackedFit,
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.bool_]],
    contrasts: Sequence[NDArray[np.float32]],
    *,
    n_points: int,
    disks: Disks | None = None,
) -> tuple[TrackedFit, int] | None:
    """A lost track held by the views but one: the fit, and the view that disagrees.

    ``lost`` is the track fitted to every view; the view it leaves most unexplained is
    the one left out, and ``track`` fits the tube from the prediction to the others
    (their indices). Two views place a tube whether or not they agree, so that fit is
    taken only where it holds and leaves more of the left-out view's silhouette
    unexplained than ``ODD_VIEW_MISFIT`` beyond ``ODD_VIEW_CONTRAST`` times the most it
    leaves of another view's: returned judged in every view, with that view. None where
    there is none (the track was lost for another reason than one view).
    """
    if not lost.misfits or lost.misfit <= 0:
        return None  # every view explained: lost for a jump or a tube through itself
    odd = int(np.argmax(lost.misfits))
    fitted = track([view for view in range(len(cameras)) if view != odd])
    if fitted.fit is None or fitted.curve is None or fitted.lost:
        return None
    judged = judge_fit(fitted.fit, cameras, masks, n_points=n_points, contrasts=contrasts, disks=disks)
    others = max(judged.misfits[view] for view in range(len(cameras)) if view != odd)
    far_off = judged.misfits[odd] > ODD_VIEW_MISFIT + ODD_VIEW_CONTRAST * others
    return (judged, odd) if far_off else None
