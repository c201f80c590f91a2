"""The tube's end: extend or trim the fitted curve to where the views see the tip.

The end is sought along the curve's own continuation (a parabola in arc length
fitted to the measured part just before the end), each view reads where its grey
image leaves the tube along that line, and the end cap's own extent in that view
is taken off. Views seeing the end nearly head-on are weighted down. A view
where the end line crosses another part of the tube (a loop's tip coming back to
its stem) gives no edge reading; given the silhouettes, it is read from pixels
instead: where discs along the end line stop adding more silhouette pixels that
the rest of the curve leaves unexplained than background pixels. The end never
moves past where the hull ends.

Where the tip lies against another part of the tube (a thick loop's tip on its
stem), its side readings are pulled off it by the other part's edges, in every
view that does not separate them. :func:`bend_tip_to_pixels` then bends and
lengthens the curve's last few radii until the tube it describes, drawn with
sub-pixel coverage, matches each view's grey levels near the tip; it starts
where the fit left the tip, or where the curve's own course takes it
(:func:`continue_on_circle`), and :func:`coverage_mismatch` compares whole
tubes by the same measure.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import Camera, project_in_views
from ..geometry.polyline import cut_polyline, polyline_arclength
from .profiles import JAC_EPS_MM, MIN_CONTRAST, end_edge, sample_image
from .quality import tube_mask

FloatArray = NDArray[np.float64]
_log = logging.getLogger(__name__)

# Sampling step along the 3-D end line (mm).
_TIP_STEP_MM = 0.25
# Views where the tangent is closer than this (sin of the angle) to the line of
# sight see the tube end-on: their normal and their tip reading are unreliable.
MIN_SIN_VIEW = 0.3
# The curve's last half radius (at most _TIP_ZONE_MM) has no side readings (its
# profiles cross the end cap); it is regenerated from a parabola fitted over the
# _END_SPAN_MM before it. Measured on rendered helix / straight / three-segment
# sessions: this beats a longer zone or a cubic (median tip 0.3-0.5 mm against
# 0.5-0.8 mm); lengths in mm, not radii, because what limits the extrapolation
# is the curve's torsion, not the tube's thickness.
_TIP_ZONE_MM = 3.0
_END_SPAN_MM = 24.0
_END_DEGREE = 2
# Reading the end from a view's pixels (see _end_by_pixels): discs every
# _PIXEL_STEP_MM along the end line; fewer than _MIN_PIXELS silhouette pixels of
# its own say nothing. Such a reading weighs _PIXEL_WEIGHT times an edge reading.
_PIXEL_STEP_MM = 0.5
_MIN_PIXELS = 4
_PIXEL_WEIGHT = 0.5
# (x, y) -> (-y, x) applied to (y, x): a quarter turn left.
_QUARTER_LEFT = np.array([-1.0, 1.0])
# A drawn uint8 level (0-255, averaged over the finer canvas) as float32
# coverage: the table of its float32 quotients by 255.
_LEVELS = np.arange(256, dtype=np.float32) / 255.0
# cv2 drawing takes fixed-point coordinates with this many fractional bits.
_DRAW_SHIFT = 4
# cv2's filled circles and polygons take in every pixel their outline touches:
# a circle comes out 0.42 (fine) pixel wider in radius than the pixel centres
# it should hold (mean over 200 random circles, r 4-30 px; spread 0.08), a
# polygon 0.50 pixel wider on every edge (300 random rectangles; spread 0.07).
# On the 4 times finer canvas of the bend that is 0.1 px of the image on every
# edge, and made the drawn tip 0.25-0.5 mm long against exact coverage: the
# shapes are drawn smaller by these amounts.
_CIRCLE_BIAS = 0.42
_POLYGON_BIAS = 0.5
# Bending the tip to the pixels (bend_tip_to_pixels): the curve's last 4
# radii are bent, then its last 2, then its last 1, each by a pattern search
# with these steps (mm); the tube is drawn _SUPERSAMPLE times finer than the
# image (coverage to 1/16 of a pixel), with _RING_POINTS points on each circle
# of its flat end, in a window reaching _WINDOW_PX past the drawn tube (room for
# the largest bend allowed, 1.5 radii: ~8 px for r = 9 mm at the rigs' ~0.6
# px/mm). Measured on rendered loops (r 4, 6, 7.5, 9 mm, both rigs, 12-16
# frames each), median tip on the r 9 loops: one span of 3, 4 or 6 radii
# 1.6-2.5, 1.7-2.6, 2.4-3.8 mm; 4 then 2 radii 1.4-2.3 mm; 4, 2, 1 radii
# 1.1-2.0 mm (6, 4, 2: 1.3-2.3 mm). Started from the true curve, the searches
# moved the tip by 1.1 mm (median, r 9 ninety loop), mostly shorter, and
# by as much against the renderer's exact coverage: the drawn tube was biased
# (cv2's fill, the end face square to the chord; see _CIRCLE_BIAS and
# _end_tangents), not the grey levels. Unbiased, 0.3 mm against exact coverage,
# 0.5 mm against the grey levels read with local levels (0.8 mm with global
# ones). The first step of 8 mm (bounded by _MAX_BEND_RADII) lets a search
# from a tip far off leave a local minimum: r 7 oblique loop mean / p95 /
# length 0.34 / 0.68 mm / 0.66 % -> 0.24 / 0.64 / 0.22, others unchanged
# (a radius limit of 2 instead of 1.5 changed nothing but for the worse).
_BEND_SPANS_RADII = (4.0, 2.0, 1.0)
_BEND_STEPS_MM = (8.0, 4.0, 2.0, 1.0, 0.5, 0.25)
# The tip is moved at most this many radii across or along: farther, it is
# another hypothesis of where the tube goes, not a correction of the fit.
_MAX_BEND_RADII = 1.5
_SUPERSAMPLE = 4
_RING_POINTS = 24
# The bend search stops drawing a bend's views once those drawn sum to this
# factor times the best bend's cost: the views are drawn in another order than
# the total sums them in, and the two sums of the same parts may differ in their
# last bits (~1e-16 relative), so a bend is dropped only where its full total
# could not have come out below the best either.
_PARTIAL_MARGIN = 1.0 + 1e-9
# The rings' unit circle, (_RING_POINTS, 1) each.
_RING_COS = np.cos(np.linspace(0.0, 2.0 * np.pi, _RING_POINTS, endpoint=False))[:, None]
_RING_SIN = np.sin(np.linspace(0.0, 2.0 * np.pi, _RING_POINTS, endpoint=False))[:, None]
_WINDOW_PX = 20.0
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
# Erosion / dilation (px) of the silhouette that picks the pixels certainly on
# the tube / on the background, to scale the grey levels to coverage.
_CORE_PX = 5
# ... and the local levels: Gaussian averages over those pixels, with these
# widths (px); fewer than _NEAR_WEIGHT of such pixels in the kernel's weight
# leave the global median.
_TUBE_SIGMA_PX = 3.0
_BACKGROUND_SIGMA_PX = 4.0
_NEAR_WEIGHT = 1e-3


def refit_tip(
    pts: FloatArray,
    cameras: Sequence[Camera],
    contrasts: Sequence[NDArray[np.float32]],
    radius_mm: float,
    *,
    cap: str,
    masks: Sequence[NDArray[np.bool_]] | None = None,
    max_length_mm: float = np.inf,
) -> FloatArray:
    """Extend or trim the curve to where the views see the tube end.

    The end is sought along the curve's own continuation: a parabola in arc
    length fitted to the measured part before the last half radius (which has no
    side readings, see :func:`read_sides`), so that a loop's tip is sought on the
    loop and not on a tangent line. That last part is regenerated from it.
    """
    arc = polyline_arclength(pts)
    anchor = max(arc[-1] - tip_zone(radius_mm), 0.5 * arc[-1])
    path = _end_frame(pts, arc, at_mm=anchor, span_mm=_END_SPAN_MM)
    lead = arc[-1] - anchor  # the current end, in arc length past the anchor
    u = np.arange(lead - 2.0 * radius_mm - 4.0, lead + 3.0 * radius_mm + 12.0, _TIP_STEP_MM)
    line = path(u)
    end = path(np.array([lead]))[0]
    end_dir = path(np.array([lead + 0.5]))[0] - path(np.array([lead - 0.5]))[0]
    end_dir /= np.linalg.norm(end_dir)
    # Parts of the tube away from the end can lie across the end line in a view
    # (a loop's tip coming back to its stem): that view's reading is skipped.
    others = pts[arc < arc[-1] - (2.5 * radius_mm + 4.0)]
    probe = np.concatenate([line, others, end + JAC_EPS_MM * np.eye(3), end[None]])
    estimates, weights = [], []
    probe_px = project_in_views(cameras, probe)  # (C, P, 2): every view in one go
    for view, (cam, contrast) in enumerate(zip(cameras, contrasts, strict=True)):
        px = probe_px[view]
        line_px, others_px = px[: len(u)], px[len(u) : len(u) + len(others)]
        end_px, jac = px[-1], (px[-4:-1] - px[-1]).T / JAC_EPS_MM  # (2,), (2, 3)
        if not np.isfinite(line_px).all():
            continue
        depth = float(cam.to_camera(end[None])[0, 2])
        px_per_mm = cam.focal_px / depth
        sin_view = min(float(np.linalg.norm(jac @ end_dir)) / px_per_mm, 1.0)
        if sin_view < MIN_SIN_VIEW or not np.isfinite(end_px).all():
            continue
        cos_view = np.sqrt(max(0.0, 1.0 - sin_view**2))
        profile = sample_image(contrast, line_px)[None, :]
        edge = end_edge(profile, u - lead, radius_mm, 1.0 / (px_per_mm * sin_view))
        # Where the tip touches another part in this view, the end line runs on
        # through that part and leaves it at its far side: a reading whose line,
        # from the current end to the edge found, passes over another part's axis
        # (within its radius, + 1 px for the samples' spacing) is not the end's.
        if edge is not None and len(others):
            read = line_px[(u >= min(lead, lead + edge)) & (u <= lead + max(edge, 0.0))]
            if len(read) and _min_distance(others_px, read) < radius_mm * px_per_mm + 1.0:
                edge = None
        if edge is not None:
            cap_mm = radius_mm / sin_view if cap == "round" else radius_mm * cos_view / sin_view
            estimates.append(edge - cap_mm)
            weights.append(sin_view**2)
        elif masks is not None:
            # No end in sight along the line: the silhouette pixels that only
            # the end can explain say where it is, if any do.
            stop = _end_by_pixels(cam, masks[view], cut_polyline(pts, anchor), path, lead, radius_mm)
            if stop is not None:
                # A disc centred on the axis' end reaches r past it, a flat
                # end's outline r cos / sin (along the line, in mm): the
                # difference, in mm along the line.
                extra = 0.0 if cap == "round" else radius_mm * (1.0 - cos_view) / sin_view
                estimates.append(stop + extra - lead)
                weights.append(_PIXEL_WEIGHT * sin_view**2)
    shift = _weighted_median(np.asarray(estimates), np.asarray(weights)) if estimates else 0.0
    stop = min(lead + shift, max_length_mm - anchor)
    if stop <= 0:
        return cut_polyline(pts, anchor + stop)
    ahead = np.append(np.arange(2.0, stop, 2.0), stop)
    return np.vstack([cut_polyline(pts, anchor), path(ahead)])


def bend_tip_to_pixels(
    points_mm: FloatArray,
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.bool_]],
    contrasts: Sequence[NDArray[np.float32]],
    radius_mm: float,
    *,
    spans_radii: Sequence[float] = _BEND_SPANS_RADII,
    steps_mm: Sequence[float] = _BEND_STEPS_MM,
    rejects: Callable[[FloatArray], bool] | None = None,
    coverages: Sequence[NDArray[np.float32]] | None = None,
    cap: str = "flat",
) -> FloatArray:
    """The curve with its last few radii bent and lengthened to match the views' pixels.

    For each span L in ``spans_radii`` in turn (in radii, at most half the
    curve), the end part (past arc length ``s0``, L before the end) is moved by
    ``a ((s - s0) / L)^2`` across the end tangent (``a``: two components, mm;
    the curve before ``s0`` is kept and the join is smooth), then lengthened
    along its own continuation or cut, by ``dl`` mm. (a, dl) minimise, summed
    over the views in a window around the end part, the squared difference
    between the tube's drawn coverage (sub-pixel, flat end: :func:`_draw_tube`)
    and the coverage read from the grey levels (:func:`_coverage`), by a
    pattern search. Unlike the side readings, this holds where the tip touches
    another part of the tube: that part is drawn too, so its edges are not
    taken for the tip's. A longer span sets the tip's course, the shorter ones
    then its last few mm.

    Parameters
    ----------
    points_mm : (M, 3) float64 axis, base -> tip, world frame, mm.
    cameras, masks, contrasts : per camera: the camera, its (H, W) bool
        silhouette and (H, W) float32 foreground contrast.
    radius_mm : tube radius, mm.
    spans_radii : lengths of the bent part, in radii, one search each.
    steps_mm : the pattern search's steps, largest first: how far from
        ``points_mm`` the tip is sought.
    rejects : a bent axis (K, 3) this returns True for is not taken (a tube
        that passes through itself, say).
    coverages : the views' :func:`pixel_coverages`, if already read.
    cap : the tube's end, "flat" or "round" (a hemisphere around the axis' end).

    Returns
    -------
    (M', 3) float64, the bent axis; ``points_mm`` when no bend matches better.
    """
    pts = np.asarray(points_mm, dtype=np.float64)
    # The grey levels read as coverage once for all the spans.
    seen = pixel_coverages(contrasts, masks) if coverages is None else coverages
    for span in spans_radii:
        pts = _bend_once(pts, cameras, seen, radius_mm, span * radius_mm, rejects, steps_mm, cap == "flat")
    return pts


def _bend_once(
    pts: FloatArray,
    cameras: Sequence[Camera],
    coverages: Sequence[NDArray[np.float32]],
    radius_mm: float,
    span_mm: float,
    rejects: Callable[[FloatArray], bool] | None,
    steps_mm: Sequence[float],
    flat_end: bool,
) -> FloatArray:
    """One search of :func:`bend_tip_to_pixels`, bending the last ``span_mm``;
    ``coverages``: per camera, (H, W) float32 from :func:`_coverage`."""
    arc = polyline_arclength(pts)
    start = max(float(arc[-1]) - span_mm, 0.5 * float(arc[-1]))
    # The part before the bend (to a radius before it, so that the drawn
    # pieces overlap) is drawn once per view.
    keep = max(start - radius_mm, 0.0)
    first = max(int(np.searchsorted(arc, keep)) - 1, 0)
    body = cut_polyline(pts, keep)
    bender = _end_bender(pts, arc, start, _end_frame(pts, arc, at_mm=float(arc[-1]), span_mm=_END_SPAN_MM))
    windows = []
    for cam, coverage in zip(cameras, coverages, strict=True):
        window = _window(cam, pts[first:], radius_mm)
        if window is None:
            continue
        (x0, y0), (x1, y1) = window
        fixed = np.zeros(((y1 - y0) * _SUPERSAMPLE, (x1 - x0) * _SUPERSAMPLE), np.uint8)
        _draw_tube(fixed, cam, *_tube_points(body, radius_mm, flat_end=False), radius_mm, (x0, y0))
        windows.append((cam, coverage[y0:y1, x0:x1], fixed, (x0, y0)))
    if not windows:
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

    view_cameras = [window[0] for window in windows]

    # The body's levels, once per view: a bend's drawing changes only the
    # blocks it touches, which alone are averaged again (see _levels).
    fixed_levels = [_levels(window[2]) for window in windows]

    def view_cost(view: int, discs: FloatArray, outline: FloatArray, pixels: FloatArray) -> float:
        cam, seen, fixed, origin = windows[view]
        canvas = fixed.copy()
        x0, y0, x1, y1 = _draw_tube(canvas, cam, discs, outline, radius_mm, origin, pixels=pixels)
        levels = fixed_levels[view].copy()
        x0, y0 = x0 // _SUPERSAMPLE, y0 // _SUPERSAMPLE
        x1, y1 = -(-x1 // _SUPERSAMPLE), -(-y1 // _SUPERSAMPLE)
        if x1 > x0 and y1 > y0:
            s = _SUPERSAMPLE
            levels[y0:y1, x0:x1] = _levels(canvas[y0 * s : y1 * s, x0 * s : x1 * s])
        return _level_difference(levels, seen)

    # Views are drawn in the order of their share of the best bend's cost, the
    # largest first: a bend that cannot win is then found out in fewer views.
    order = list(range(len(windows)))

    def mismatch(p: FloatArray, below: float) -> float:
        """The bend's cost, summed over the views in their own order; or, once
        the views drawn so far reach ``below``, their partial sum (the others
        can only add: the bend cannot win, and the search compares a kept
        cost only with a lower best)."""
        if np.hypot(p[0], p[1]) > _MAX_BEND_RADII * radius_mm or abs(p[2]) > _MAX_BEND_RADII * radius_mm:
            return np.inf
        bent = bender(p[:2], float(p[2]))
        discs, outline = _tube_points(bent[first:], radius_mm, flat_end=flat_end)
        # Projected in all views in one go (the same pixels as view by view).
        pixels = project_in_views(view_cameras, np.vstack([discs, outline]))
        parts = [0.0] * len(windows)
        partial = 0.0
        for view in order[:-1]:
            parts[view] = view_cost(view, discs, outline, pixels[view])
            partial += parts[view]
            # Summed in another order than the total, the partial sum may
            # differ from a sum of the same parts in its last bits: the margin.
            if partial >= below * _PARTIAL_MARGIN:
                return partial
        parts[order[-1]] = view_cost(order[-1], discs, outline, pixels[order[-1]])
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
    return bender(p[:2], float(p[2])) if p.any() else pts


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


def coverage_mismatch(
    axes_mm: Sequence[FloatArray],
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.bool_]],
    contrasts: Sequence[NDArray[np.float32]],
    radius_mm: float,
    *,
    coverages: Sequence[NDArray[np.float32]] | None = None,
    cap: str | Sequence[str] = "flat",
) -> list[float]:
    """How far each of several tubes is from the views' grey levels: one cost each.

    The cost :func:`bend_tip_to_pixels` minimises, for whole tubes: per view,
    the sum of squared differences between the tube's drawn coverage
    (sub-pixel, flat end, see :func:`_draw_tube`) and the coverage read from
    the grey levels (:func:`_coverage`), over one window holding all the tubes
    (so that the costs compare), summed over the views. Unlike the
    silhouettes' IoU, this sees where a tip lies on another part of the tube
    (its edges blur into the other part's), and a flat end.

    Parameters
    ----------
    axes_mm : each (M_i, 3) float64 axis, base -> tip, world frame, mm.
    cameras, masks, contrasts : per camera: the camera, its (H, W) bool
        silhouette and (H, W) float32 foreground contrast.
    radius_mm : tube radius, mm (the same for all).
    coverages : the views' :func:`pixel_coverages`, if already read.
    cap : the tubes' end, "flat" or "round"; or one per axis.

    Returns
    -------
    One cost per axis (squared coverage, summed over pixels: lower is better).
    """
    costs = [0.0] * len(axes_mm)
    caps = [cap] * len(axes_mm) if isinstance(cap, str) else list(cap)
    if coverages is None:
        coverages = pixel_coverages(contrasts, masks)
    for cam, coverage in zip(cameras, coverages, strict=True):
        windows = [w for w in (_window(cam, axis, radius_mm) for axis in axes_mm) if w is not None]
        if len(windows) < len(axes_mm):
            continue  # a tube this view does not see whole: no fair comparison here
        x0, y0 = (min(w[0][i] for w in windows) for i in (0, 1))
        x1, y1 = (max(w[1][i] for w in windows) for i in (0, 1))
        seen = coverage[y0:y1, x0:x1]
        for n, axis in enumerate(axes_mm):
            canvas = np.zeros(((y1 - y0) * _SUPERSAMPLE, (x1 - x0) * _SUPERSAMPLE), np.uint8)
            points = _tube_points(axis, radius_mm, flat_end=caps[n] == "flat")
            _draw_tube(canvas, cam, *points, radius_mm, (x0, y0))
            costs[n] += _squared_difference(canvas, seen)
    return costs


def tip_meets_tube(
    points_mm: FloatArray,
    cameras: Sequence[Camera],
    radius_mm: float,
    *,
    span_radii: float = _BEND_SPANS_RADII[0],
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
    if len(far) and _min_distance(tip, far) < _TOUCH_RADII * radius_mm:
        min_views = 1
    meeting = 0
    for cam in cameras:
        focal = cam.focal_px
        reach = focal * radius_mm / np.concatenate([cam.to_camera(tip)[:, 2], cam.to_camera(others)[:, 2]])
        if not (reach > 0).all():
            continue
        # Both tubes' projected radii (the largest: the nearest) and a pixel.
        touch = reach[: len(tip)].max() + reach[len(tip) :].max() + 1.0
        if _min_distance(cam.project(tip), cam.project(others)) < touch:
            meeting += 1
            if meeting >= min_views:
                return True
    return False


def _window(
    cam: Camera, axis_mm: FloatArray, radius_mm: float
) -> tuple[tuple[int, int], tuple[int, int]] | None:
    """Pixel window ((x0, y0), (x1, y1)) around the tube of (K, 3) ``axis_mm``, None if not seen."""
    px = cam.project(axis_mm)
    depth = cam.to_camera(axis_mm)[:, 2]
    if not (np.isfinite(px).all() and (depth > radius_mm).all()):
        return None
    margin = cam.focal_px * radius_mm / float(depth.min()) + _WINDOW_PX
    w, h = cam.size_px
    x0, y0 = (max(int(np.floor(v)), 0) for v in px.min(axis=0) - margin)
    x1, y1 = (min(int(np.ceil(v)), n) for v, n in zip(px.max(axis=0) + margin, (w, h), strict=True))
    return ((x0, y0), (x1, y1)) if x1 > x0 and y1 > y0 else None


def pixel_coverages(
    contrasts: Sequence[NDArray[np.float32]], masks: Sequence[NDArray[np.bool_]]
) -> list[NDArray[np.float32]]:
    """Per view, (H, W) float32 in [0, 1]: how much of each pixel the tube covers
    (:func:`_coverage` of its (H, W) contrast and bool silhouette)."""
    return [_coverage(contrast, mask) for contrast, mask in zip(contrasts, masks, strict=True)]


def _coverage(contrast: NDArray[np.float32], mask: NDArray[np.bool_]) -> NDArray[np.float32]:
    """(H, W) float32 in [0, 1]: how much of each pixel the tube covers, from its grey level.

    The contrast scaled between the background's local level (pixels well
    outside the silhouette, averaged nearby) and the tube's (well inside),
    clipped: edge pixels, blurred by the optics and the video, come out in
    between. Local, because the scene is textured and the tube shaded: with one
    level for each, a background patch darker than the median reads as part
    covered, and the tip is drawn towards it.
    """
    grow = np.ones((_CORE_PX, _CORE_PX), np.uint8)
    core = cv2.erode(mask.view(np.uint8), grow).view(bool)
    away = ~cv2.dilate(mask.view(np.uint8), grow).view(bool)
    tube_all = float(np.median(contrast[core])) if core.any() else float(contrast[mask].max())
    background_all = float(np.median(contrast[away])) if away.any() else 0.0
    tube = _local_mean(contrast, core, _TUBE_SIGMA_PX, tube_all)
    background = _local_mean(contrast, away, _BACKGROUND_SIGMA_PX, background_all)
    scale = np.maximum(tube - background, MIN_CONTRAST)
    return np.clip((contrast - background) / scale, 0.0, 1.0).astype(np.float32)


def _local_mean(
    image: NDArray[np.float32], where: NDArray[np.bool_], sigma_px: float, default: float
) -> NDArray[np.float32]:
    """(H, W) float32 Gaussian-weighted mean of ``image`` over the pixels ``where``
    (normalised convolution); ``default`` where none is near."""
    weight = where.astype(np.float32)
    total = cv2.GaussianBlur(image * weight, (0, 0), sigma_px)
    norm = cv2.GaussianBlur(weight, (0, 0), sigma_px)
    near = norm > _NEAR_WEIGHT
    return np.where(near, total / np.where(near, norm, 1.0), np.float32(default)).astype(np.float32)


def _tube_points(axis_mm: FloatArray, radius_mm: float, *, flat_end: bool) -> tuple[FloatArray, FloatArray]:
    """What :func:`_draw_tube` draws of the tube around (K, 3) ``axis_mm``: disc
    centres (D, 3) every half radius along the axis (as
    :func:`pipeline.reconstruct.quality.tube_mask`), and the outline (O, 3) of its flat end
    ((0, 3) without ``flat_end``), world frame, mm.

    With ``flat_end``, the last radius is the outline of a straight cylinder
    piece (its two end circles: their projection's convex hull is the piece's),
    and the discs stop where it starts (a disc of radius r there stays inside
    that piece in any view); a disc at the end would reach a radius past a flat
    end seen side-on.
    """
    # The discs are interpolated on the whole axis' arc length up to where the
    # body ends: the same points as cutting it there and resampling the cut
    # (see resample_polyline), with one arc length instead of four (this runs
    # for every bend tried).
    arc = polyline_arclength(axis_mm)
    length = max(float(arc[-1]) - radius_mm, 0.0) if flat_end else float(arc[-1])
    if length > 0:
        n = max(2, int(np.ceil(length / (0.5 * radius_mm))) + 1)
        # np.linspace(0, length, n)'s own arithmetic (k * step, the last one
        # exactly ``length``), and one array for the three coordinates: fewer
        # calls for what runs for every bend tried.
        step = length / (n - 1)
        if step > 0:
            u = np.arange(n, dtype=np.float64) * step
            u[-1] = length
        else:  # a denormal length: np.linspace's own way round
            u = np.linspace(0.0, length, n)
        discs = np.empty((n, 3))
        for i in range(3):
            discs[:, i] = np.interp(u, arc, axis_mm[:, i])
    else:
        discs = axis_mm[:1]
    end, back = axis_mm[-1], discs[-1]
    gap = end - back
    if not flat_end or not gap.dot(gap) > 0:
        return discs, np.zeros((0, 3))
    rings = np.empty((2, _RING_POINTS, 3))
    for k, (centre, tangent) in enumerate(
        zip((back, end), _end_tangents(axis_mm, arc, radius_mm), strict=True)
    ):
        n1, n2 = _normals(tangent)
        rings[k] = centre + radius_mm * (_RING_COS * n1 + _RING_SIN * n2)
    return discs, rings.reshape(-1, 3)


def _end_tangents(axis_mm: FloatArray, arc: FloatArray, radius_mm: float) -> tuple[FloatArray, FloatArray]:
    """Tangents (3,) of (K, 3) ``axis_mm`` a radius before its end and at its end.

    From a parabola in arc length fitted to the axis' last two radii: the end
    face is square to the tube's own tangent, which on a tight bend (a loop's
    tip, ~30 mm) turns ~8 degrees over the last radius, and a ring square to the
    chord instead puts the face's rim ~1 mm off on one side.
    """
    s = arc - arc[-1]
    sel = s >= -2.0 * radius_mm
    if np.count_nonzero(sel) < 3:
        sel = np.zeros(len(s), dtype=bool)
        sel[-3:] = True
    if np.count_nonzero(sel) < 3:
        chord = axis_mm[-1] - axis_mm[0]
        return chord, chord
    x = s[sel]
    # np.vander(x, 3, increasing=True)'s columns (1, x, x x), without its overhead.
    v = np.empty((len(x), 3))
    v[:, 0] = 1.0
    v[:, 1] = x
    v[:, 2] = x * x
    # The normal equations (3 x 3, well conditioned on a few mm): a tenth of lstsq's cost.
    coef = np.linalg.solve(v.T @ v, v.T @ axis_mm[sel])
    return coef[1] - 2.0 * radius_mm * coef[2], coef[1]


def _draw_tube(
    canvas: NDArray[np.uint8],
    cam: Camera,
    discs_mm: FloatArray,
    outline_mm: FloatArray,
    radius_mm: float,
    origin: tuple[int, int],
    *,
    pixels: FloatArray | None = None,
) -> tuple[int, int, int, int]:
    """Draw (255) a tube given by :func:`_tube_points` on a ``_SUPERSAMPLE``-times
    finer canvas whose pixel (0, 0) is the image's pixel ``origin`` (x, y);
    ``pixels``: the (D + O, 2) projection of its discs and outline, if known.

    Returns the canvas rectangle (x0, y0, x1, y1), half-open, that holds every
    canvas pixel drawn (with a margin)."""
    one = _SUPERSAMPLE * (1 << _DRAW_SHIFT)
    # Pixel centres sit at integer coordinates; on the finer canvas pixel (u, v)'s
    # centre is at s u + (s - 1) / 2.
    offset = np.asarray(origin, dtype=np.float64) - (_SUPERSAMPLE - 1) / (2 * _SUPERSAMPLE)
    focal = cam.focal_px
    if pixels is None:
        pixels = cam.project(np.vstack([discs_mm, outline_mm]))
    px = (pixels - offset) * one
    # cv2 fills what its outlines touch: shapes come out too large (see _CIRCLE_BIAS).
    bias = _CIRCLE_BIAS * (1 << _DRAW_SHIFT)
    # Array methods (.round()), not np.round's wrapper: this runs for every
    # bend tried in every view.
    radii = (focal * radius_mm / cam.to_camera(discs_mm)[:, 2] * one - bias).round()
    centres = px[: len(discs_mm)].round().astype(np.int64)
    # What is drawn, in fixed point: x0, y0, x1, y1 (plain ints: few shapes).
    far = 1 << 62
    box = [far, far, -far, -far]
    for (cx, cy), r in zip(centres.tolist(), radii.astype(np.int64).tolist(), strict=True):
        cv2.circle(canvas, (cx, cy), r, 255, -1, cv2.LINE_8, _DRAW_SHIFT)
        if cx - r < box[0]:
            box[0] = cx - r
        if cy - r < box[1]:
            box[1] = cy - r
        if cx + r > box[2]:
            box[2] = cx + r
        if cy + r > box[3]:
            box[3] = cy + r
    if len(outline_mm):
        hull = cv2.convexHull(px[len(discs_mm) :].astype(np.float32))[:, 0, :].astype(np.float64)
        hull = _shrink_convex(hull, _POLYGON_BIAS * (1 << _DRAW_SHIFT)).round().astype(np.int32)
        cv2.fillConvexPoly(canvas, hull, 255, cv2.LINE_8, _DRAW_SHIFT)
        x, y, w, h = cv2.boundingRect(hull)
        box = [min(box[0], x), min(box[1], y), max(box[2], x + w), max(box[3], y + h)]
    # In canvas pixels, two more on each side: cv2 fills what its outlines touch.
    height, width = canvas.shape
    return (
        max((box[0] >> _DRAW_SHIFT) - 2, 0),
        max((box[1] >> _DRAW_SHIFT) - 2, 0),
        min((box[2] >> _DRAW_SHIFT) + 3, width),
        min((box[3] >> _DRAW_SHIFT) + 3, height),
    )


def _squared_difference(canvas: NDArray[np.uint8], seen: NDArray[np.float32]) -> float:
    """Sum over the image's pixels of (drawn coverage - ``seen``)^2: the
    ``_SUPERSAMPLE``-times finer (h s, w s) uint8 ``canvas`` (0 / 255) averaged
    to (h, w) ``seen``'s pixels, float32."""
    return _level_difference(_levels(canvas), seen)


def _levels(canvas: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """(h, w) uint8: each ``_SUPERSAMPLE`` x ``_SUPERSAMPLE`` block of the (h s, w s)
    canvas averaged (each block on its own: any part of the canvas whose sides
    are multiples of s gives the same levels as the whole)."""
    h, w = canvas.shape
    levels = cv2.resize(canvas, (w // _SUPERSAMPLE, h // _SUPERSAMPLE), interpolation=cv2.INTER_AREA)
    return np.asarray(levels, dtype=np.uint8)


def _level_difference(levels: NDArray[np.uint8], seen: NDArray[np.float32]) -> float:
    """Sum over the pixels of ((h, w) uint8 ``levels`` as coverage - (h, w) float32 ``seen``)^2."""
    # cv2's table look-up and float32 difference (the same IEEE results as
    # NumPy's, in half the time); the sum stays NumPy's pairwise one.
    difference = np.asarray(cv2.subtract(cv2.LUT(levels, _LEVELS), seen))
    return float(np.add.reduce(difference * difference, axis=None))


def _shrink_convex(polygon: FloatArray, by: float) -> FloatArray:
    """(P, 2) convex polygon with every edge moved inwards by ``by`` (same units)."""
    # Few whole-array operations (concatenations, not np.roll; np.add.reduce,
    # not np.sum; no column_stack): this runs for every bend tried in every view.
    ahead = np.concatenate((polygon[1:], polygon[:1]))
    edge = ahead - polygon
    length = np.sqrt(np.add.reduce(edge * edge, axis=1))
    keep = length > 1e-9
    if not keep.all():
        polygon, edge, length = polygon[keep], edge[keep], length[keep]
        ahead = np.concatenate((polygon[1:], polygon[:1]))
    if len(polygon) < 3:
        return polygon
    # Twice the signed area: positive when the polygon turns left (counter-clockwise).
    # (x y', y x') per vertex: the products of the shoelace formula.
    cross = polygon * ahead[:, ::-1]
    turn = float(np.add.reduce(cross[:, 0] - cross[:, 1]))
    sign = 1.0 if turn > 0 else -1.0 if turn < 0 else turn  # np.sign's, 0 and NaN included
    # (-dy, dx): the edge turned a quarter left (the sign flips are exact).
    inward = edge[:, ::-1] * _QUARTER_LEFT * (sign / length)[:, None]
    before = np.concatenate((inward[-1:], inward[:-1]))
    # A vertex moves so that both its edges move by ``by``: along the bisector.
    return polygon + (before + inward) * (by / (1.0 + np.add.reduce(before * inward, axis=1)))[:, None]


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
    ``ahead`` (u mm past the end -> points, see :func:`_end_frame`), bent alike,
    or cut if ``longer`` is negative."""
    return _end_bender(pts, arc, start, ahead)(across, longer)


def _end_bender(
    pts: FloatArray, arc: FloatArray, start: float, ahead: Callable[[FloatArray], FloatArray]
) -> Callable[[FloatArray, float], FloatArray]:
    """:func:`_bend_end` of one axis as a function of (``across``, ``longer``):
    what does not depend on the bend (the end's normals, the weights along the
    axis, the continuation's origin) is worked out once, for the many bends a
    search tries."""
    n1, n2 = _normals(pts[-1] - pts[-2])
    span = float(arc[-1]) - start
    w = (np.clip((arc - start) / span, 0.0, None) ** 2)[:, None]
    origin = ahead(np.zeros(1))

    def bent(across: FloatArray, longer: float) -> FloatArray:
        offset = across[0] * n1 + across[1] * n2
        out = pts + w * offset[None, :]
        if longer < 0:
            return cut_polyline(out, float(arc[-1]) + longer)
        if longer > 0:
            u = np.append(np.arange(2.0, longer, 2.0), longer)
            # The continuation is a least-squares fit: shifted to start at the end.
            more = ahead(u) - origin + pts[-1]
            return np.vstack([out, more + (((arc[-1] + u - start) / span) ** 2)[:, None] * offset[None, :]])
        return out

    return bent


def _normals(direction: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors perpendicular to (3,) ``direction`` and to each other."""
    # np.linalg.norm's own arithmetic (sqrt of x.dot(x)), and plain floats
    # for the rest: np.cross and per-element NumPy scalars are slow on single
    # vectors, and this runs for every bend tried.
    t = direction / math.sqrt(direction.dot(direction))
    tx, ty, tz = t.tolist()
    # t x e_k for the axis e_k least along t (the first such, as np.argmin), written out.
    size = [abs(tx), abs(ty), abs(tz)]
    k = size.index(min(size))
    i, j = (k + 1) % 3, (k + 2) % 3
    n1 = np.zeros(3)
    n1[i], n1[j] = t[j], -t[i]
    n1 /= math.sqrt(n1.dot(n1))
    a, b, c = n1.tolist()
    n2 = np.array([ty * c - tz * b, tz * a - tx * c, tx * b - ty * a])
    return n1, n2


def _end_by_pixels(
    cam: Camera,
    mask: NDArray[np.bool_],
    body_mm: FloatArray,
    path: Callable[[FloatArray], FloatArray],
    lead: float,
    radius_mm: float,
) -> float | None:
    """Where the end is along ``path`` (mm past the anchor), read from one view's pixels.

    The tube of the curve up to the anchor (``body_mm``, (B, 3)) is drawn; then
    discs along the end line, from the anchor on, each owning the pixels no
    nearer disc (nor the body) covers. The end is where the count of owned
    silhouette pixels minus owned background pixels peaks: past it a disc adds
    only background. None when no disc adds a silhouette pixel (the end hides
    in another part of the tube in this view).
    """
    u = np.arange(0.0, lead + 3.0 * radius_mm + 12.0, _PIXEL_STEP_MM)
    line = path(u)
    depth = cam.to_camera(line)[:, 2]
    px = cam.project(line)
    if not (np.isfinite(px).all() and (depth > radius_mm).all()):
        return None
    focal = cam.focal_px
    w, h = cam.size_px
    owner = np.zeros((h, w), np.int32)
    one = 1 << _DRAW_SHIFT
    centres = np.round(px * one).astype(np.int64)
    radii = np.round((focal * radius_mm / depth - 0.5) * one).astype(np.int64)
    # Drawn from the far end back, so the disc nearest the anchor wins each pixel.
    for k in range(len(u) - 1, -1, -1):
        cv2.circle(
            owner, (int(centres[k, 0]), int(centres[k, 1])), int(radii[k]), k + 1, -1, cv2.LINE_8, _DRAW_SHIFT
        )
    owner[tube_mask(cam, body_mm, radius_mm)] = 0
    inside = np.bincount(owner[mask], minlength=len(u) + 1)[1:]
    outside = np.bincount(owner[~mask], minlength=len(u) + 1)[1:]
    if inside.sum() < _MIN_PIXELS:
        return None
    gain = np.cumsum(inside - outside)
    return float(u[int(np.argmax(gain))])


def tip_zone(radius_mm: float) -> float:
    """Length (mm) at the tip end with no side readings: see _TIP_ZONE_MM."""
    return min(0.5 * radius_mm, _TIP_ZONE_MM)


def _min_distance(a: FloatArray, b: FloatArray) -> float:
    """Smallest distance between a point of (A, D) ``a`` and a point of (B, D) ``b``."""
    gap = a[:, None, :] - b[None, :, :]
    return float(np.sqrt(np.einsum("abi,abi->ab", gap, gap).min()))


def _end_frame(
    pts: FloatArray, arc: FloatArray, *, at_mm: float, span_mm: float
) -> Callable[[FloatArray], FloatArray]:
    """The curve's continuation past arc length ``at_mm``: u (mm, (U,)) -> (U, 3) points.

    A polynomial of degree ``_END_DEGREE`` in arc length, fitted by least squares
    to the ``span_mm`` of the curve before ``at_mm``; fewer samples give a lower
    degree. (A helix's torsion makes a parabola drift ~0.4 mm over 6 mm of
    extrapolation, which is why only half a radius is extrapolated.)
    """
    s = arc - at_mm
    sel = (s >= -span_mm) & (s <= 0.0)
    if sel.sum() < 4:
        sel = np.zeros(len(s), dtype=bool)
        sel[np.argsort(np.abs(s))[:4]] = True
    degree = int(min(_END_DEGREE, sel.sum() - 2))
    coef, *_ = np.linalg.lstsq(np.vander(s[sel], degree + 1, increasing=True), pts[sel], rcond=None)

    def path(u: FloatArray) -> FloatArray:
        return np.asarray(np.vander(np.atleast_1d(u), degree + 1, increasing=True) @ coef)

    return path


def _weighted_median(values: FloatArray, weights: FloatArray) -> float:
    order = np.argsort(values)
    cum = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cum, 0.5 * cum[-1])])
