"""The tip bent to the grey levels: the end of the tube fitted to the views' pixels.

Where the tip lies against another part of the tube (a thick loop's tip on its
stem), its side readings are pulled off it by the other part's edges, in every
view that does not separate them; and the side readings stop short of any tube's end
(its course there is extrapolated). :func:`bend_tip_to_pixels` bends and
lengthens the curve's last few radii until the tube it describes, drawn with
sub-pixel coverage, matches each view's grey levels near the tip; it starts
where the fit left the tip, or where the curve's own course takes it
(:func:`continue_on_circle`), and whole tubes are compared by the same measure
(:func:`pipeline.reconstruct.tube_drawing.coverage_mismatch`); a start from the hull
searches so where the tip meets another part. Every tracked frame's tip, already near
its place, is fitted instead: the same bends, by damped Gauss-Newton on the pixel
differences (:func:`refine_tip_to_pixels`), in a few drawings where the search takes
tens; where the side readings leave a longer stretch before the tip loosely placed (it
lies along another part of the tube in the views), that stretch is bent to the grey
levels first, its middle free of its tip.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import Camera, project_in_views
from ..geometry.polyline import by_fraction, cut_polyline, polyline_arclength, unit_tangents
from .disks import Disks, rim_pixels, rims
from .tube_drawing import (
    SUPERSAMPLE,
    canvas_levels,
    draw_disks,
    draw_tube,
    level_difference,
    level_residuals,
    normals,
    pixel_coverages,
    tube_points,
    view_window,
)
from .tube_tip import END_SPAN_MM, end_frame, min_distance

FloatArray = NDArray[np.float64]

_log = logging.getLogger(__name__)

# Bending the tip to the pixels (bend_tip_to_pixels): the curve's last 4 radii are
# bent, then its last 2, then its last 1, each by a pattern search with the steps of
# _BEND_STEPS_MM and a fit from where it stops; the tube is drawn SUPERSAMPLE times
# finer than the image (coverage to 1/16 of a pixel), with _RING_POINTS points on each
# circle of its flat end, in a window holding every pixel the largest bend allowed can
# cover (_REACH_RADII). Measured on rendered loops (r 4, 6, 7.5, 9 mm, both rigs, 12-16 frames
# each), median tip on the r 9 loops: one span of 3, 4 or 6 radii 1.6-2.5, 1.7-2.6,
# 2.4-3.8 mm; 4 then 2 radii 1.4-2.3 mm; 4, 2, 1 radii 1.1-2.0 mm (6, 4, 2: 1.3-2.3
# mm). Started from the true curve, the searches moved the tip by 1.1 mm (median, r 9
# ninety loop), mostly shorter, and by as much against the renderer's exact coverage:
# the drawn tube was biased (cv2's fill, the end face square to the chord; see
# _CIRCLE_BIAS and _end_tangents), not the grey levels. Unbiased, 0.3 mm against exact
# coverage, 0.5 mm against the grey levels read with local levels (0.8 mm with global
# ones). The first step of 8 mm (bounded by _MAX_BEND_RADII) lets a search from a tip
# far off leave a local minimum: r 7 oblique loop mean / p95 / length 0.34 / 0.68 mm /
# 0.66 % -> 0.24 / 0.64 / 0.22, others unchanged (a radius limit of 2 instead of 1.5
# changed nothing but for the worse).
BEND_SPANS_RADII = (4.0, 2.0, 1.0)
# The search stops at 0.5 mm and the bend is then fitted from where it stopped, by the
# Gauss-Newton of refine_tip_to_pixels (_fit_bend), in a few drawings where a step of
# 0.25 mm took tens. On 144 frames started from the hull (every fifth of 60 frames of
# eight loops, `synth --shape loop`, seeds 1-8, r 5-9 mm, both rigs and ends, and four
# random shapes, seeds 11-14; the true tube end; 2026-12-05), a start took 224 ms instead
# of 273 (median CPU time; 242 against 295 mean), mean error 0.270 mm against 0.274,
# frames more than 2 mm off 13 against 16, median tip 0.50 against 0.48 mm. Whole sessions
# (`accuracy_table --draw 191`, 193 and 197, 8 cases of 90 frames each; same day): 21 of
# 24 unchanged; three two-camera sessions with spacer disks, which miss the targets
# either way, moved (a loop's mean 1.27 -> 1.63 mm, frames off 84 either way). The bench's
# two loop shapes rendered for 300 frames (`process --jobs 2`, then `evaluate`): mean 0.205
# -> 0.200 and 0.348 -> 0.263 mm, frames off 22 -> 8 and 73 -> 50, their tracks started
# again from the hull more often (another course from other starts). Stopped at 2
# mm, a start took a quarter less again at the same errors, but on a tip that left its
# loop for the stem (tests/reconstruct/test_centerline.py) the fit stopped 2.5 mm from
# the true tip where the search's last steps reach 0.7 mm: the mismatch is rough at the
# scale of a pixel's sixteenth, and Gauss-Newton finds no way down from 1-2 mm off.
_BEND_STEPS_MM = (8.0, 4.0, 2.0, 1.0, 0.5)
# The tip is moved at most this many radii across or along: farther, it is
# another hypothesis of where the tube goes, not a correction of the fit.
_MAX_BEND_RADII = 1.5
# ... so that the bent tip lies at most this many radii from where it was (across at
# the end, then along): the views are compared over the pixels that far around the
# bent part (every pixel a bend can cover, see view_window), not over more.
_REACH_RADII = math.hypot(_MAX_BEND_RADII, _MAX_BEND_RADII)
# The bend search stops drawing a bend's views once those drawn sum to this
# factor times the best bend's cost: the views are drawn in another order than
# the total sums them in, and the two sums of the same parts may differ in their
# last bits (~1e-16 relative), so a bend is dropped only where its full total
# could not have come out below the best either.
_PARTIAL_MARGIN = 1.0 + 1e-9
# Parts of the tube fewer than this many radii (along the curve) before the
# bent part are its own neighbours, not another part that it can lie on.
_APART_RADII = 4.0
# The tip is bent to the pixels only where it meets another part of the tube in
# at least this many views. Where one view alone sees it on another part, the
# others see it apart and their side readings place it (two views fix a point),
# and the robust fit outweighs the one misled view: on the bend_rotate demo
# (tip crossing the stem in one view of three, 14 of 100 frames) the bend left
# the tip error where it was (mean 0.56 against 0.53 mm unbent) at ~50 ms a
# frame. A loop's tip lying on its stem meets it in 2-3 views of 3.
_MIN_MEETING_VIEWS = 2
# ... unless the tip lies against the other part in space: axes within this many
# radii, surfaces within a diameter. Then the views that see them apart see them
# barely apart (the gap in an image is at most the gap in space), the edges
# of the one part blurred into the other's, and their side readings are as
# doubtful. (Measured: the r 6 loops' single-view frames, axes 3.4-3.6 radii
# apart, keep their bends (loop p95 1.03 -> 0.94 mm); the demo's, 4.5-4.6
# radii apart, stay unbent.)
_TOUCH_RADII = 4.0


# Refining a tip near its place (refine_tip_to_pixels, a tracked frame's): the bends
# of the search above over these spans, fitted by Gauss-Newton to the views' pixel
# differences, damped (Levenberg-Marquardt, the damping grown _DAMPING_GROWTH-fold
# until a step lowers the cost, at most _DAMPING_TRIES times for the first step and
# once for the later ones: once a step has been taken, one that does not lower the
# cost finds the fit at the drawing's resolution; 6.8 drawings a span instead of 8.5
# on the bench loop, its tips as close), the Jacobian by
# forward differences of _DIFFERENCE_MM (a third of a pixel at the rigs' ~0.6 px/mm:
# the drawn coverage moves in steps of a sixteenth of a pixel) and then updated from
# each step taken (Broyden's rank-one update), for at most _REFINE_STEPS steps or
# until one is shorter than _SETTLED_MM. Measured on three rendered loops (the
# bench's r 9 loop, a tapered r 7 loop, a round-ended r 5 loop; 90 tracked frames
# each, 2026-12-02), against the search (steps of 2, 1, 0.5 and 0.25 mm over three
# spans, ~128 drawings a frame): the bench loop's frames 33 ms instead of 89
# (median), mean errors 0.236, 0.510 and 0.190 mm against 0.248, 0.509 and 0.190,
# tip medians 0.49, 1.34 and 0.49 mm against 0.51, 3.07 and 0.49 (the tapered loop's
# tip lies on its stem, where its place is bistable: see docs/accuracy.md). One span
# (4 radii) was faster still (24-31 ms) but put the round end's tip 0.64 mm off;
# 6 steps instead of 3 changed nothing but the time (34-40 ms). On the same three loops
# (120 frames each, 2026-12-03; the frames timed in CPU time, interleaved with the
# spans as they are), against the spans fitted one after the other: one span of 2.5 or
# 4 radii, frames 13-21 % faster, tip medians 0.45 -> 0.57-0.63 mm on the round end and
# 0.54 -> 0.57-0.67 mm on the bench loop; both spans' bends fitted together (five
# parameters, one drawing set up), 8-15 % faster, tips 0.45 -> 0.56-0.59 and 0.54 ->
# 0.61-0.67 mm; the Jacobian from the drawn coverage's gradient at each edge pixel
# (moved as its nearest axis point) instead of three drawings, 13-15 % slower, tips
# 0.45 -> 0.50 and 0.54 -> 0.60 mm. Two steps instead of three, on 13 rendered sessions
# (the bench's three shapes, six loops, four random stepped shapes; 90 tracked frames
# each, the true tube end, 2026-12-05): 2 % less CPU time, summed means 3.26 -> 3.68 mm,
# frames more than 2 mm off 144 -> 151 (a two-camera round-ended loop 0.47 -> 0.99 mm).
REFINE_SPANS_RADII = (4.0, 1.0)
_DIFFERENCE_MM = 0.5
_REFINE_STEPS = 3
# A loose stretch's bend (refine_tip_to_pixels' loose_span_radii) has four parameters and
# starts up to a few mm off in its middle: given this many steps. Started 1.5 and 2.5 mm
# off in the middle of the last 6 and 8 radii of a rendered loop (r 6 mm; the test
# tests/reconstruct/test_centerline.py::test_a_loose_end_stretch_is_fitted_to_the_grey_levels),
# the middle came to 0.37, 0.61, 0.31 and 0.42 mm from its place in 6 steps (9 the same),
# 0.58, 0.66, 0.29 and 1.45 mm in 3.
_LOOSE_STEPS = 6
_SETTLED_MM = 0.05
_DAMPING = 1e-2
_DAMPING_GROWTH = 4.0
_DAMPING_TRIES = 4


def bend_tip_to_pixels(
    points_mm: FloatArray,
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.bool_]],
    contrasts: Sequence[NDArray[np.float32]],
    radius_mm: float,
    *,
    spans_radii: Sequence[float] = BEND_SPANS_RADII,
    steps_mm: Sequence[float] = _BEND_STEPS_MM,
    then_fit: bool = True,
    rejects: Callable[[FloatArray], bool] | None = None,
    coverages: Sequence[NDArray[np.float32]] | None = None,
    cap: str = "flat",
    disks: Disks | None = None,
) -> FloatArray:
    """The curve with its last few radii bent and lengthened to match the views' pixels.

    For each span L in ``spans_radii`` in turn (in radii, at most half the
    curve), the end part (past arc length ``s0``, L before the end) is moved by
    ``a ((s - s0) / L)^2`` across the end tangent (``a``: two components, mm;
    the curve before ``s0`` is kept and the join is smooth), then lengthened
    along its own continuation or cut, by ``dl`` mm. (a, dl) minimise, summed
    over the views in a window around the end part, the squared difference
    between the tube's drawn coverage (sub-pixel, flat end: :func:`draw_tube`)
    and the coverage read from the grey levels (:func:`_coverage`), by a
    pattern search, then fitted from where it stops by damped Gauss-Newton on
    the pixel differences (as :func:`refine_tip_to_pixels`). Unlike the side
    readings, this holds where the tip touches another part of the tube: that
    part is drawn too, so its edges are not taken for the tip's. A longer span
    sets the tip's course, the shorter ones then its last few mm.

    Parameters
    ----------
    points_mm : (M, 3) float64 axis, base -> tip, world frame, mm.
    cameras, masks, contrasts : per camera: the camera, its (H, W) bool
        silhouette and (H, W) float32 foreground contrast.
    radius_mm : tube radius, mm.
    spans_radii : lengths of the bent part, in radii, one search each.
    steps_mm : the pattern search's steps, largest first: how far from
        ``points_mm`` the tip is sought.
    then_fit : fit the bend from where the search stops (else the search's last
        step is the bend's resolution).
    rejects : a bent axis (K, 3) this returns True for is not taken (a tube
        that passes through itself, say).
    coverages : the views' :func:`pixel_coverages`, if already read.
    cap : the tube's end, "flat" or "round" (a hemisphere around the axis' end).
    disks : the tube's spacer disks, drawn with it.

    Returns
    -------
    (M', 3) float64, the bent axis; ``points_mm`` when no bend matches better.
    """
    pts = np.asarray(points_mm, dtype=np.float64)
    # The grey levels read as coverage once for all the spans.
    seen = pixel_coverages(contrasts, masks) if coverages is None else coverages
    for span in spans_radii:
        pts = _bend_once(
            pts, cameras, seen, radius_mm, span * radius_mm, rejects, steps_mm, then_fit, cap == "flat", disks
        )
    return pts


class _Drawn(NamedTuple):
    """What :class:`_TipDrawing` draws of a bend's end part: the discs (D, 3) mm and
    their radius (one, or (D,)), the flat end's outline (O, 3) mm, and their pixels
    (V, D + O, 2) in each view that sees the part."""

    discs_mm: FloatArray
    radii_mm: float | FloatArray
    outline_mm: FloatArray
    pixels: FloatArray
    # (V, D, P, 2) the rims' pixels of the spacer disks on the end part, in each view
    disks_px: FloatArray | None = None


class _TipDrawing:
    """Bends of a curve's last ``span_mm`` (see :func:`bend_tip_to_pixels`), drawn in
    every view that sees them against its coverage.

    What does not change from bend to bend is worked out once: the curve before
    the bend (to a radius before it, so that the drawn pieces overlap) drawn in a
    window of each view, and that drawing's levels; a bend's drawing changes only
    the blocks it touches, which alone are averaged again (see canvas_levels).
    ``radii_mm``: (M,) the radius at each point of ``pts`` the body is drawn with
    (default ``radius_mm``, the end's, throughout). With ``middle``, a bend also moves
    the middle of the bent part (see :func:`_end_bender`).
    """

    def __init__(
        self,
        pts: FloatArray,
        cameras: Sequence[Camera],
        coverages: Sequence[NDArray[np.float32]],
        radius_mm: float,
        span_mm: float,
        flat_end: bool,
        radii_mm: FloatArray | None = None,
        *,
        middle: bool = False,
        disks: Disks | None = None,
    ) -> None:
        arc = polyline_arclength(pts)
        start = max(float(arc[-1]) - span_mm, 0.5 * float(arc[-1]))
        keep = max(start - radius_mm, 0.0)
        self.first = max(int(np.searchsorted(arc, keep)) - 1, 0)
        self.radius_mm, self.flat_end = radius_mm, flat_end
        ahead = end_frame(pts, arc, at_mm=float(arc[-1]), span_mm=END_SPAN_MM)
        self.bent = _end_bender(pts, arc, start, ahead, middle=middle)
        self.parameters = 4 if middle else 3
        body, _ = tube_points(cut_polyline(pts, keep), radius_mm, flat_end=False)
        # The body as thick as it is along it (a tapered tube's stem drawn as thin as
        # its end leaves the stem's rim to the bent end, which then lies on it). On the
        # 42 sessions of `accuracy_table` draws 2, 7, 13, 41 and 61 (2026-12-03), with the
        # held length (pipeline.reconstruct.tracking.held_length), against the body drawn
        # at the end's radius and no held length: three-camera median tips 0.98 against
        # 1.06 mm (averaged over the sessions), frames more than 2 mm off 239 against 320;
        # two-camera median tips 1.35 against 1.56 mm, but mean 1.05 against 0.81 mm, most
        # of it one stepped shape of draw 41 whose track started 14-54 mm off in depth.
        body_radii = radius_mm if radii_mm is None else np.interp(polyline_arclength(body), arc, radii_mm)
        # ... and so is a loose stretch's bent part (it reaches back to where a taper is
        # thicker): its radii by arc length from its first point. The tip's spans are
        # drawn at the end's radius, which the end's readings hold (drawn with the radii
        # along them, a two-camera stepped s-curve's tip came 0.34 -> 1.82 mm off; see
        # pipeline.reconstruct.tracking.LOOSE_END_SPREAD).
        self.part_radii = (
            None
            if radii_mm is None or not middle
            else (arc[self.first :] - arc[self.first], radii_mm[self.first :])
        )
        # Per view that sees the end part: camera, coverage, drawing of the body, origin.
        self.windows: list[tuple[Camera, NDArray[np.float32], NDArray[np.uint8], tuple[int, int]]] = []
        for cam, coverage in zip(cameras, coverages, strict=True):
            window = view_window(cam, pts[self.first :], radius_mm, reach_radii=_REACH_RADII)
            if window is None:
                continue
            (x0, y0), (x1, y1) = window
            fixed = np.zeros(((y1 - y0) * SUPERSAMPLE, (x1 - x0) * SUPERSAMPLE), np.uint8)
            draw_tube(fixed, cam, body, np.zeros((0, 3)), body_radii, (x0, y0))
            self.windows.append((cam, coverage[y0:y1, x0:x1], fixed, (x0, y0)))
        self.cameras = [window[0] for window in self.windows]
        # Spacer disks: those before the bent part drawn with the body, the others with
        # each bend (they move with it).
        self.bent_disks: Disks | None = None
        if disks is not None and self.windows:
            still = dataclasses.replace(disks, arc_mm=disks.arc_mm[disks.arc_mm < start])
            self.bent_disks = dataclasses.replace(disks, arc_mm=disks.arc_mm[disks.arc_mm >= start])
            held = rims(pts, arc, still)
            if len(held):
                for (_, _, fixed, origin), disks_px in zip(
                    self.windows, rim_pixels(self.cameras, held), strict=True
                ):
                    draw_disks(fixed, disks_px, origin)
        self.fixed_levels = [canvas_levels(window[2]) for window in self.windows]

    def draw(self, p: FloatArray) -> tuple[FloatArray, _Drawn]:
        """The bend ``p`` (see :func:`_end_bender`): its axis, and what is drawn of its end part."""
        bent = self.bent(p)
        discs, outline = tube_points(bent[self.first :], self.radius_mm, flat_end=self.flat_end)
        radii: float | FloatArray = self.radius_mm
        if self.part_radii is not None:
            radii = np.interp(polyline_arclength(discs), *self.part_radii)
        disks_px = None
        if self.bent_disks is not None and len(self.bent_disks.arc_mm):
            moved = rims(bent, polyline_arclength(bent), self.bent_disks)
            if len(moved):
                disks_px = rim_pixels(self.cameras, moved)
        return bent, _Drawn(
            discs, radii, outline, project_in_views(self.cameras, np.vstack([discs, outline])), disks_px
        )

    def levels(self, view: int, drawn: _Drawn) -> NDArray[np.uint8]:
        """(h, w) uint8 levels of ``view``'s window with the bent end ``drawn`` over the body."""
        cam, _, fixed, origin = self.windows[view]
        canvas = fixed.copy()
        x0, y0, x1, y1 = draw_tube(
            canvas, cam, drawn.discs_mm, drawn.outline_mm, drawn.radii_mm, origin, pixels=drawn.pixels[view]
        )
        if drawn.disks_px is not None:
            d0, e0, d1, e1 = draw_disks(canvas, drawn.disks_px[view], origin)
            if d1 > d0:
                x0, y0, x1, y1 = min(x0, d0), min(y0, e0), max(x1, d1), max(y1, e1)
        levels = self.fixed_levels[view].copy()
        x0, y0 = x0 // SUPERSAMPLE, y0 // SUPERSAMPLE
        x1, y1 = -(-x1 // SUPERSAMPLE), -(-y1 // SUPERSAMPLE)
        if x1 > x0 and y1 > y0:
            s = SUPERSAMPLE
            levels[y0:y1, x0:x1] = canvas_levels(canvas[y0 * s : y1 * s, x0 * s : x1 * s])
        return levels

    def out_of_bounds(self, p: FloatArray) -> bool:
        limit = _MAX_BEND_RADII * self.radius_mm
        if len(p) > 3:  # across at the tip, then in the middle (see _end_bender)
            return bool(np.hypot(p[0], p[1]) > limit or np.hypot(p[2], p[3]) > limit)
        return bool(np.hypot(p[0], p[1]) > limit or abs(p[2]) > limit)


def refine_tip_to_pixels(
    points_mm: FloatArray,
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.bool_]],
    contrasts: Sequence[NDArray[np.float32]],
    radius_mm: float,
    *,
    spans_radii: Sequence[float] = REFINE_SPANS_RADII,
    rejects: Callable[[FloatArray], bool] | None = None,
    cap: str = "flat",
    radii_mm: FloatArray | None = None,
    loose_span_radii: float = 0.0,
    disks: Disks | None = None,
) -> FloatArray:
    """The bends of :func:`bend_tip_to_pixels` (its arguments but the search's
    steps), fitted from the curve's own tip by damped Gauss-Newton on each view's
    pixel differences instead of searched for: a few drawings a span where the search
    takes tens, for a tip already near its place (a tracked frame's), not for one that
    may be far from it. ``radius_mm`` is the tube's radius at its end, ``radii_mm``
    (M,) the radius at each point of ``points_mm`` (default ``radius_mm`` throughout).

    ``loose_span_radii``: the length (in radii) of the stretch before the tip that the
    side readings place loosely (:meth:`pipeline.reconstruct.placement.Placement.loose_end_mm`).
    Where it is longer than the spans, that stretch is bent first, as a whole and in its
    middle (four parameters, see :func:`_end_bender`): the spans' bends move the last few
    radii and the tip, and leave the middle of a longer stretch where the fit put it.

    Returns (M', 3) float64, the bent axis; ``points_mm`` when no bend matches better.
    """
    pts = np.asarray(points_mm, dtype=np.float64)
    # The grey levels read as coverage only where the bends are drawn: around the
    # longest span's part, with room for the tip to move by the largest bend allowed
    # in each span.
    arc = polyline_arclength(pts)
    # (span in radii, whether its middle is bent too), in the order fitted.
    fits = [(span, False) for span in spans_radii]
    if loose_span_radii > max(spans_radii):
        fits.insert(0, (loose_span_radii, True))
    end_part = pts[arc >= arc[-1] - (max(span for span, _ in fits) + 1.0) * radius_mm]
    reach = len(fits) * _REACH_RADII
    windows = [view_window(cam, end_part, radius_mm, reach_radii=reach) for cam in cameras]
    seen = pixel_coverages(contrasts, masks, windows)
    for span, middle in fits:
        # The radii follow a bent tip by sample fraction (a bend may add or drop samples).
        radii = None if radii_mm is None else by_fraction(radii_mm, len(pts))
        drawing = _TipDrawing(
            pts, cameras, seen, radius_mm, span * radius_mm, cap == "flat", radii, middle=middle, disks=disks
        )
        if drawing.windows:
            p = _fit_bend(
                drawing, np.zeros(drawing.parameters), rejects, _LOOSE_STEPS if middle else _REFINE_STEPS
            )
            pts = drawing.bent(p) if p.any() else pts
    return pts


def _fit_bend(
    drawing: _TipDrawing,
    start: FloatArray,
    rejects: Callable[[FloatArray], bool] | None,
    steps: int = _REFINE_STEPS,
) -> FloatArray:
    """The bend (3,) or (4,) of ``drawing`` fitted from ``start`` by damped Gauss-Newton
    on each view's pixel differences, in at most ``steps`` steps (see
    ``REFINE_SPANS_RADII``); ``start`` where no step lowers the cost."""

    def residuals(p: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The bend ``p``'s axis, and its drawn coverage less the seen, pixel by pixel."""
        bent, drawn = drawing.draw(p)
        parts = [
            level_residuals(drawing.levels(view, drawn), window[1])
            for view, window in enumerate(drawing.windows)
        ]
        return bent, np.concatenate(parts).astype(np.float64)

    p = np.asarray(start, dtype=np.float64)
    _, r = residuals(p)
    cost = float(r @ r)
    jacobian: FloatArray | None = None
    damping = _DAMPING
    for step_number in range(steps):
        if jacobian is None:
            jacobian = np.column_stack(
                [(residuals(p + _DIFFERENCE_MM * e)[1] - r) / _DIFFERENCE_MM for e in np.eye(len(p))]
            )
        gradient, normal = jacobian.T @ r, jacobian.T @ jacobian
        taken = False
        for _ in range(_DAMPING_TRIES if step_number == 0 else 1):
            # Marquardt's damping, scaled by each parameter's own curvature (and kept above
            # 0 for a parameter no pixel responds to).
            step = -np.linalg.solve(normal + damping * np.diag(np.diag(normal) + 1e-12), gradient)
            q = p + step
            if drawing.out_of_bounds(q):
                damping *= _DAMPING_GROWTH
                continue
            bent, r_q = residuals(q)
            cost_q = float(r_q @ r_q)
            if cost_q < cost and not (rejects is not None and rejects(bent)):
                jacobian += np.outer(r_q - r - jacobian @ step, step) / float(step @ step)
                p, r, cost, taken = q, r_q, cost_q, True
                damping = max(damping / _DAMPING_GROWTH, _DAMPING * 1e-2)
                break
            damping *= _DAMPING_GROWTH
        if not taken or float(np.linalg.norm(step)) < _SETTLED_MM:
            break
    _log.debug("tip refined by %s mm across, %+.2f mm longer (cost %.1f)", p[:2], p[2], cost)
    return p


def _bend_once(
    pts: FloatArray,
    cameras: Sequence[Camera],
    coverages: Sequence[NDArray[np.float32]],
    radius_mm: float,
    span_mm: float,
    rejects: Callable[[FloatArray], bool] | None,
    steps_mm: Sequence[float],
    then_fit: bool,
    flat_end: bool,
    disks: Disks | None = None,
) -> FloatArray:
    """One search (and fit) of :func:`bend_tip_to_pixels`, bending the last ``span_mm``;
    ``coverages``: per camera, (H, W) float32 from :func:`_coverage`."""
    drawing = _TipDrawing(pts, cameras, coverages, radius_mm, span_mm, flat_end, disks=disks)
    if not drawing.windows:
        return pts

    # The pattern search comes back to points it has tried (a step back after
    # a step forth): each bend's cost is kept. Its steps are sums of powers of
    # two, so the keys are exact.
    tried: dict[tuple[float, ...], float] = {}

    def cost(p: FloatArray, below: float) -> float:
        """Mismatch of the bend ``p`` (across (2,), longer, mm); inf out of
        bounds, or if it would beat ``below`` but ``rejects`` it (checked only
        then: most bends tried do not beat the best, and the check is dear)."""
        key = tuple(p.tolist())
        if key not in tried:
            tried[key] = mismatch(p, below)
        return tried[key]

    # Views are drawn in the order of their share of the best bend's cost, the
    # largest first: a bend that cannot win is then found out in fewer views.
    order = list(range(len(drawing.windows)))

    def mismatch(p: FloatArray, below: float) -> float:
        """The bend's cost, summed over the views in their own order; or, once
        the views drawn so far reach ``below``, their partial sum (the others
        can only add: the bend cannot win, and the search compares a kept
        cost only with a lower best)."""
        if drawing.out_of_bounds(p):
            return np.inf
        bent, drawn = drawing.draw(p)
        parts = [0.0] * len(order)

        def view_cost(view: int) -> float:
            levels = drawing.levels(view, drawn)
            return level_difference(levels, drawing.windows[view][1])

        partial = 0.0
        for view in order[:-1]:
            parts[view] = view_cost(view)
            partial += parts[view]
            # Summed in another order than the total, the partial sum may
            # differ from a sum of the same parts in its last bits: the margin.
            if partial >= below * _PARTIAL_MARGIN:
                return partial
        parts[order[-1]] = view_cost(order[-1])
        total = 0.0
        for part in parts:
            total += part
        if total < below:
            if rejects is not None and rejects(bent):
                return np.inf
            order[:] = sorted(order, key=lambda view: -parts[view])
        return total

    p, best = np.zeros(3), cost(np.zeros(3), np.inf)
    for step in steps_mm:
        improved = True
        while improved:
            improved = False
            for i in range(3):
                for sign in (1.0, -1.0):
                    q = p.copy()
                    q[i] += sign * step
                    c = cost(q, best)
                    if c < best:
                        best, p, improved = c, q, True
    _log.debug("tip bent by %s mm across, %+.2f mm longer (cost %.1f)", p[:2], p[2], best)
    if then_fit:
        p = _fit_bend(drawing, p, rejects)
    return drawing.bent(p) if p.any() else pts


def continue_on_circle(points_mm: FloatArray, *, redo_mm: float, fit_mm: float) -> FloatArray:
    """(M', 3) axis whose last ``redo_mm`` are replaced by the circle the part before follows.

    The circle (centre, radius, plane) is fitted, least squares, to the axis
    over the ``fit_mm`` before the cut, and followed from the cut, in the
    axis' direction of travel, for ``redo_mm``, in 2 mm steps. A loop's tip
    that lies on its stem has no readings of its own that a fit could follow:
    this is where its course takes it (the tip bend then corrects it to the
    pixels). A part too straight for a circle is continued straight.

    Parameters
    ----------
    points_mm : (M, 3) float64 axis, base -> tip, world frame, mm.
    redo_mm, fit_mm : lengths along the axis, mm.
    """
    pts = np.asarray(points_mm, dtype=np.float64)
    arc = polyline_arclength(pts)
    cut = cut_polyline(pts, float(arc[-1]) - redo_mm)
    cut_arc = polyline_arclength(cut)
    part = cut[cut_arc >= cut_arc[-1] - fit_mm]
    ahead = np.append(np.arange(2.0, redo_mm, 2.0), redo_mm)
    centre = part.mean(axis=0)
    _, spread, vt = np.linalg.svd(part - centre)
    xy = (part - centre) @ vt[:2].T
    # Kasa's algebraic circle: |p|^2 = 2 c . p + (R^2 - |c|^2), linear in c and R^2 - |c|^2.
    design = np.column_stack([2.0 * xy, np.ones(len(xy))])
    (cx, cy, k), *_ = np.linalg.lstsq(design, (xy**2).sum(axis=1), rcond=None)
    radius = float(np.sqrt(max(k + cx**2 + cy**2, 0.0)))
    # Sagitta below a thousandth of the chord (spread across / along): straight.
    if len(part) < 3 or spread[1] < 1e-3 * spread[0] or not 0.0 < radius < np.inf:
        along = vt[0] if (part[-1] - part[0]) @ vt[0] >= 0 else -vt[0]
        return np.vstack([cut, cut[-1] + np.outer(ahead, along)])
    rel = xy - (cx, cy)
    # The way round the part goes: the sign of the angle it sweeps, step by step
    # (its last step alone can be a sliver, where the cut fell by a sample).
    sweep = float(np.sum(rel[:-1, 0] * rel[1:, 1] - rel[:-1, 1] * rel[1:, 0]))
    angles = np.arctan2(rel[-1, 1], rel[-1, 0]) + np.sign(sweep or 1.0) * ahead / radius
    on_circle = radius * np.column_stack([np.cos(angles), np.sin(angles)])
    # Shifted to start at the cut (the circle passes within the fit's residual of it).
    from_cut = on_circle - radius * rel[-1] / np.linalg.norm(rel[-1])
    return np.vstack([cut, cut[-1] + from_cut @ vt[:2]])


def tip_meets_tube(
    points_mm: FloatArray,
    cameras: Sequence[Camera],
    radius_mm: float,
    *,
    span_radii: float = BEND_SPANS_RADII[0],
    min_views: int = _MIN_MEETING_VIEWS,
) -> bool:
    """Whether, in at least ``min_views`` views, the tube's last ``span_radii``
    radii touch or cross the image of a part of the tube at least
    ``_APART_RADII`` radii before them along the curve (projected tubes within a
    pixel): where the tip's side readings can be another part's edges.

    One such view is not enough (see ``_MIN_MEETING_VIEWS``): the others,
    which see the tip apart, place it; unless the tip lies against that part
    in space (axes within ``_TOUCH_RADII`` radii).

    ``points_mm`` : (M, 3) float64 axis, base -> tip, world frame, mm.
    """
    pts = np.asarray(points_mm, dtype=np.float64)
    arc = polyline_arclength(pts)
    start = float(arc[-1]) - span_radii * radius_mm
    tip, others = pts[arc >= start], pts[arc < start - _APART_RADII * radius_mm]
    if len(tip) == 0 or len(others) == 0:
        return False
    # Against another part, not near its own neighbours across a tight bend
    # (a 24 mm arc's chord on a 30 mm bend is 23 mm): parts twice as far back.
    far = pts[arc < start - 2.0 * _APART_RADII * radius_mm]
    if len(far) and min_distance(tip, far) < _TOUCH_RADII * radius_mm:
        min_views = 1
    meeting = 0
    for cam in cameras:
        focal = cam.focal_px
        reach = focal * radius_mm / np.concatenate([cam.to_camera(tip)[:, 2], cam.to_camera(others)[:, 2]])
        if not (reach > 0).all():
            continue
        # Both tubes' projected radii (the largest: the nearest) and a pixel.
        touch = reach[: len(tip)].max() + reach[len(tip) :].max() + 1.0
        if min_distance(cam.project(tip), cam.project(others)) < touch:
            meeting += 1
            if meeting >= min_views:
                return True
    return False


def _bend_end(
    pts: FloatArray,
    arc: FloatArray,
    start: float,
    across: FloatArray,
    longer: float,
    ahead: Callable[[FloatArray], FloatArray],
) -> FloatArray:
    """(M, 3) axis bent past arc length ``start`` by ``across`` (2,) mm at its end
    (across the end tangent, growing as the square of the arc length past
    ``start``), then lengthened by ``longer`` mm along its own continuation
    ``ahead`` (u mm past the end -> points, see :func:`end_frame`), bent alike,
    or cut if ``longer`` is negative."""
    return _end_bender(pts, arc, start, ahead)(np.array([across[0], across[1], longer]))


def _end_bender(
    pts: FloatArray,
    arc: FloatArray,
    start: float,
    ahead: Callable[[FloatArray], FloatArray],
    *,
    middle: bool = False,
) -> Callable[[FloatArray], FloatArray]:
    """:func:`_bend_end` of one axis as a function of the bend p = (across (2,),
    longer) mm: what does not depend on the bend (the end's normals, the weights
    along the axis, the continuation's origin) is worked out once, for the many
    bends a search tries.

    With ``middle``, p = (across (2,), middle (2,)) mm, the length kept: the
    middle of the bent part moves across by ``middle`` as well, with the weight
    16 t^2 (1 - t)^2 at the fraction t of the part (0 at both its ends, 1 in its
    middle), square to the axis at each point, in the directions across the axis'
    tangent at the middle. The tip's bend alone ties the middle to the tip (a
    quarter of the tip's motion at t = 1/2); this frees it. Within the bounds
    (:meth:`_TipDrawing.out_of_bounds`, ``_MAX_BEND_RADII`` each) a point then moves
    at most 1.93 radii (at t = 0.57), within ``_REACH_RADII``: the windows hold it.
    """
    n1, n2 = normals(pts[-1] - pts[-2])
    span = float(arc[-1]) - start
    w = (np.clip((arc - start) / span, 0.0, None) ** 2)[:, None]
    origin = ahead(np.zeros(1))
    if middle:
        t = np.clip((arc - start) / span, 0.0, 1.0)
        bump = (16.0 * t * t * (1.0 - t) * (1.0 - t))[:, None]
        at = min(max(int(np.searchsorted(arc, start + 0.5 * span)), 1), len(pts) - 1)
        tangents = unit_tangents(pts)
        # Each direction across the middle, made square to the axis at every point.
        m1, m2 = (bump * (m - (tangents @ m)[:, None] * tangents) for m in normals(pts[at] - pts[at - 1]))

    def bent(p: FloatArray) -> FloatArray:
        offset = p[0] * n1 + p[1] * n2
        out = pts + w * offset[None, :]
        if middle:
            return out + p[2] * m1 + p[3] * m2
        longer = float(p[2])
        if longer < 0:
            return cut_polyline(out, float(arc[-1]) + longer)
        if longer > 0:
            u = np.append(np.arange(2.0, longer, 2.0), longer)
            # The continuation is a least-squares fit: shifted to start at the end.
            more = ahead(u) - origin + pts[-1]
            return np.vstack([out, more + (((arc[-1] + u - start) / span) ** 2)[:, None] * offset[None, :]])
        return out

    return bent
