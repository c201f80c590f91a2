"""The tube's end: extend or trim the fitted curve to where the views see the tip.

The end is sought along the curve's own continuation (a parabola in arc length
fitted to the measured part just before the end), each view reads where its grey
image leaves the tube along that line, and the end cap's own extent in that view
is taken off. Views seeing the end nearly head-on are weighted down. A view
where the end line crosses another part of the tube (a loop's tip coming back to
its stem) gives no edge reading; given the silhouettes, it is read from pixels
instead: where discs along the end line stop adding more silhouette pixels that
the rest of the curve (drawn at its own radius along it) leaves unexplained than
background pixels. Where the end line runs over another part of the tube in that
view, the end may lie anywhere over that part: the view then only bounds it.
Where no view places the end, a tracked frame gives the curve the length its
track has held. The end never moves past where the hull ends.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import Camera, project_in_views
from ..geometry.polyline import cut_polyline, polyline_arclength
from .profiles import JAC_EPS_MM, end_edge, sample_image
from .quality import tube_mask
from .tube_drawing import DRAW_SHIFT

FloatArray = NDArray[np.float64]
_log = logging.getLogger(__name__)

# Sampling step along the 3-D end line (mm).
_TIP_STEP_MM = 0.25
# Views where the tangent is closer than this (sin of the angle) to the line of
# sight see the tube end-on: their normal and their tip reading are unreliable.
MIN_SIN_VIEW = 0.3
# The curve's last half radius (at most _TIP_ZONE_MM) has no side readings (its
# profiles cross the end cap); it is regenerated from a parabola fitted over the
# END_SPAN_MM before it. Measured on rendered helix / straight / three-segment
# sessions: this beats a longer zone or a cubic (median tip 0.3-0.5 mm against
# 0.5-0.8 mm); lengths in mm, not radii, because what limits the extrapolation
# is the curve's torsion, not the tube's thickness.
_TIP_ZONE_MM = 3.0
END_SPAN_MM = 24.0
_END_DEGREE = 2
# Reading the end from a view's pixels (see _end_by_pixels): discs every
# _PIXEL_STEP_MM along the end line; fewer than _MIN_PIXELS silhouette pixels of
# its own say nothing. Such a reading weighs _PIXEL_WEIGHT times an edge reading.
_PIXEL_STEP_MM = 0.5
_MIN_PIXELS = 4
_PIXEL_WEIGHT = 0.5
# A disc along the end line owning less than this share of the pixels it would
# own without the rest of the tube drawn is hidden by another part of it.
_HIDDEN_SHARE = 0.5


def refit_tip(
    pts: FloatArray,
    cameras: Sequence[Camera],
    contrasts: Sequence[NDArray[np.float32]],
    radius_mm: float,
    *,
    cap: str,
    masks: Sequence[NDArray[np.bool_]] | None = None,
    max_length_mm: float = np.inf,
    radii_mm: FloatArray | None = None,
    unseen_length_mm: float = np.nan,
) -> FloatArray:
    """Extend or trim the curve to where the views see the tube end.

    The end is sought along the curve's own continuation: a parabola in arc
    length fitted to the measured part before the last half radius (which has no
    side readings, see :func:`read_sides`), so that a loop's tip is sought on the
    loop and not on a tangent line. That last part is regenerated from it.
    ``radius_mm`` is the tube's radius at its end; ``radii_mm``, (M,), the radius
    at each point of ``pts`` (default ``radius_mm`` everywhere): the parts of a
    tapered or stepped tube that lie across the end line in a view are as wide
    as they are there, not as the end. Where no view reads the end (hidden in
    another part of the tube, or seen end-on), the curve is given
    ``unseen_length_mm`` if that is finite (a tracked frame: the length its track
    has held), and left as long as it is otherwise.
    """
    arc = polyline_arclength(pts)
    radii = np.full(len(pts), float(radius_mm)) if radii_mm is None else np.asarray(radii_mm, np.float64)
    anchor = max(arc[-1] - tip_zone(radius_mm), 0.5 * arc[-1])
    path = end_frame(pts, arc, at_mm=anchor, span_mm=END_SPAN_MM)
    lead = arc[-1] - anchor  # the current end, in arc length past the anchor
    u = np.arange(lead - 2.0 * radius_mm - 4.0, lead + 3.0 * radius_mm + 12.0, _TIP_STEP_MM)
    line = path(u)
    end = path(np.array([lead]))[0]
    end_dir = path(np.array([lead + 0.5]))[0] - path(np.array([lead - 0.5]))[0]
    if not np.linalg.norm(end_dir) > 0:
        return pts  # no direction at the end (a curve collapsed to a point): none to read along
    end_dir /= np.linalg.norm(end_dir)
    # Parts of the tube away from the end can lie across the end line in a view
    # (a loop's tip coming back to its stem): that view's reading is skipped.
    apart = arc < arc[-1] - (2.5 * radius_mm + 4.0)
    others, others_radii = pts[apart], radii[apart]
    body = cut_polyline(pts, anchor)
    body_radii = np.interp(polyline_arclength(body), arc, radii)
    # Where the views cannot place the end, past the anchor (mm).
    unseen = unseen_length_mm - anchor if np.isfinite(unseen_length_mm) else lead
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
        # (within that part's radius, + 1 px for the samples' spacing) is not the end's.
        if edge is not None and len(others):
            read = line_px[(u >= min(lead, lead + edge)) & (u <= lead + max(edge, 0.0))]
            if len(read) and _overlaps(others_px, others_radii * px_per_mm + 1.0, read):
                edge = None
        if edge is not None:
            # The end cap reaches r past the axis' end in the image (a round cap), a flat
            # end's face r cos: the axis ends that far back from the edge, measured in
            # the image along the projected end line (which bends on a curved end),
            # not in the continuation's parameter, which runs faster than its length
            # there. On 48 rendered sessions (`accuracy_table --draw 191`, 193, 197,
            # 199, 201 and 203; 8 cases of 90 frames each; 2026-12-05), against the
            # parameter: three cameras, median tips summed 26.75 -> 17.91 mm, 13 of 24
            # sessions within 0.5 mm instead of 11, frames more than 2 mm off 323 -> 311;
            # two cameras, mean errors summed 10.39 -> 10.90 mm, median tips 49.9 ->
            # 53.2 mm, frames off 674 -> 660; of the flat-or-round choices, one clear one
            # became a close call (its 90 good frames flagged) and a spacer-disk one
            # became clear (its 86 frames off, 86 -> 25 flagged).
            reach_px = radius_mm * px_per_mm * (1.0 if cap == "round" else cos_view)
            estimates.append(back_along(line_px, u, lead + edge, reach_px) - lead)
            weights.append(sin_view**2)
        elif masks is not None:
            # No end in sight along the line: the silhouette pixels that only
            # the end can explain say where it is, if any do.
            span = _end_by_pixels(cam, masks[view], body, path, lead, radius_mm, body_radii_mm=body_radii)
            if span is not None:
                # A disc centred on the axis' end reaches r past it, a flat
                # end's outline r cos / sin (along the line, in mm): the
                # difference, in mm along the line.
                extra = 0.0 if cap == "round" else radius_mm * (1.0 - cos_view) / sin_view
                low, high = span[0] + extra, span[1] + extra
                # An end hidden over another part of the tube, where it may be
                # as far as the view can tell, is left to the other views.
                if not low <= unseen <= high:
                    estimates.append(min(max(unseen, low), high) - lead)
                    weights.append(_PIXEL_WEIGHT * sin_view**2)
    stop = lead + _weighted_median(np.asarray(estimates), np.asarray(weights)) if estimates else unseen
    stop = min(stop, max_length_mm - anchor)
    if stop <= 0:
        return cut_polyline(pts, anchor + stop)
    ahead = np.append(np.arange(2.0, stop, 2.0), stop)
    return np.vstack([body, path(ahead)])


def _end_by_pixels(
    cam: Camera,
    mask: NDArray[np.bool_],
    body_mm: FloatArray,
    path: Callable[[FloatArray], FloatArray],
    lead: float,
    radius_mm: float,
    *,
    body_radii_mm: FloatArray | None = None,
) -> tuple[float, float] | None:
    """Where the end is along ``path`` (mm past the anchor), read from one view's pixels:
    (low, high), the span it lies in.

    The tube of the curve up to the anchor (``body_mm``, (B, 3), its radius
    ``body_radii_mm``, (B,), default ``radius_mm`` throughout) is drawn; then
    discs along the end line, from the anchor on, each owning the pixels no
    nearer disc (nor the body) covers. The end is where the count of owned
    silhouette pixels minus owned background pixels peaks: past it a disc adds
    only background (low = high). Where the discs just past the peak are hidden
    by the body (the end line runs over another part of the tube), the end lies
    somewhere over that part: the span runs to its far side. None when no disc
    adds a silhouette pixel.
    """
    u = np.arange(0.0, lead + 3.0 * radius_mm + 12.0, _PIXEL_STEP_MM)
    line = path(u)
    depth = cam.to_camera(line)[:, 2]
    px = cam.project(line)
    if not (np.isfinite(px).all() and (depth > radius_mm).all()):
        return None
    focal = cam.focal_px
    one = 1 << DRAW_SHIFT
    centres = np.round(px * one).astype(np.int64)
    radii = np.maximum(np.round((focal * radius_mm / depth - 0.5) * one).astype(np.int64), 0)
    # Only pixels in the discs' bounding box (and a pixel or two around it) can be owned:
    # the counts are taken there.
    w, h = cam.size_px
    low = (centres - radii[:, None]).min(axis=0) >> DRAW_SHIFT
    high = (centres + radii[:, None]).max(axis=0) >> DRAW_SHIFT
    x0, y0 = max(int(low[0]) - 2, 0), max(int(low[1]) - 2, 0)
    x1, y1 = min(int(high[0]) + 3, w), min(int(high[1]) + 3, h)
    if x1 <= x0 or y1 <= y0:
        return None
    owner = np.zeros((y1 - y0, x1 - x0), np.int32)
    centres -= np.array([x0, y0]) * one
    # Drawn from the far end back, so the disc nearest the anchor wins each pixel.
    for k in range(len(u) - 1, -1, -1):
        cv2.circle(
            owner, (int(centres[k, 0]), int(centres[k, 1])), int(radii[k]), k + 1, -1, cv2.LINE_8, DRAW_SHIFT
        )
    free = np.bincount(owner.ravel(), minlength=len(u) + 1)[1:]
    window = ((x0, y0), (x1, y1))
    body_radii = radius_mm if body_radii_mm is None else body_radii_mm
    owner[tube_mask(cam, body_mm, body_radii, window=window)] = 0
    seen = mask[y0:y1, x0:x1]
    inside = np.bincount(owner[seen], minlength=len(u) + 1)[1:]
    outside = np.bincount(owner[~seen], minlength=len(u) + 1)[1:]
    # A disc that the body covers for the most part (the end line running over
    # another part of the tube) says nothing: the few pixels left to it are the
    # drawn body's and the silhouette's disagreement at that part's edges.
    hidden = inside + outside < _HIDDEN_SHARE * free
    inside[hidden] = 0
    outside[hidden] = 0
    if inside.sum() < _MIN_PIXELS:
        return None
    gain = np.cumsum(inside - outside)
    peak = int(np.argmax(gain))
    # The gain still at its peak over hidden discs: the end lies somewhere in
    # the part of the tube they cross, unseen.
    last = peak
    while last + 1 < len(u) and hidden[last + 1]:
        last += 1
    return float(u[peak]), float(u[last])


def back_along(line_px: FloatArray, u: FloatArray, at: float, reach_px: float) -> float:
    """The parameter, below ``at``, where the projected line (U, 2) ``line_px``, sampled at
    increasing (U,) ``u``, first comes ``reach_px`` from its own point at ``at``, walking
    back from there (linear between samples; the first sample where it never does)."""
    edge = np.array([np.interp(at, u, line_px[:, 0]), np.interp(at, u, line_px[:, 1])])
    behind = u < at
    back_u = np.append(at, u[behind][::-1])  # from ``at`` back to the first sample
    gap = np.append(0.0, np.linalg.norm(line_px[behind][::-1] - edge, axis=1))
    far = np.flatnonzero(gap >= reach_px)
    if not len(far):
        return float(back_u[-1])
    k = int(far[0])
    if k == 0:  # no reach
        return at
    return float(np.interp(reach_px, gap[k - 1 : k + 1], back_u[k - 1 : k + 1]))


def tip_zone(radius_mm: float) -> float:
    """Length (mm) at the tip end with no side readings: see _TIP_ZONE_MM."""
    return min(0.5 * radius_mm, _TIP_ZONE_MM)


def _overlaps(centres_px: FloatArray, reach_px: FloatArray, points_px: FloatArray) -> bool:
    """Whether a point of (P, 2) ``points_px`` lies within ``reach_px`` ((C,)) of one
    of (C, 2) ``centres_px``, each centre its own reach."""
    gap = centres_px[:, None, :] - points_px[None, :, :]
    return bool((np.einsum("cpi,cpi->cp", gap, gap) < (reach_px**2)[:, None]).any())


def min_distance(a: FloatArray, b: FloatArray) -> float:
    """Smallest distance between a point of (A, D) ``a`` and a point of (B, D) ``b``."""
    gap = a[:, None, :] - b[None, :, :]
    return float(np.sqrt(np.einsum("abi,abi->ab", gap, gap).min()))


# The continuation is run in the polynomial's own parameter, not by its length. Where the
# curve's course changes over the span (a coil running into a straight end) the
# parabola's speed reaches 1.12 mm a mm, and an end read along it, a round cap's length
# taken off a reading in that parameter, lies short (0.35-1.6 mm, median 1.0 mm, read
# from the true axis of six seeded coils with round ends, r 5-7 mm, 320x240; 0.0-0.65 mm
# by its length). Re-parametrized by its length (sampled every 0.25 mm) in the end
# reading and the tip's bends alike, it was measured on 45 three-camera sessions of
# `accuracy_table` draws 2, 7, 13, 41, 61, 73, 91, 97 (one made uniform) and 103 and the
# demo (90 frames each, 2026-12-03): median tips averaged 0.640 against 0.710 mm, means
# 0.238 against 0.241 mm, frames more than 2 mm off 309 against 320, but 144 of them
# flagged against 173, and good frames flagged 439 against 262 (three more ends close
# calls between flat and round); the coil 0.58 against 1.28 mm.
# It also sent a hull-started frame of a random shape, with a stretch hidden in one view,
# 10 mm off (its resumed march set off from a slightly different end:
# tests/reconstruct/test_frame.py, seed 1). In the end reading alone, with the bends
# kept in the parameter, a coiled tube with disks (draw 97) had its tip curl across
# (2.27 against 0.82 mm). Only the cap's length turned into the parameter at the
# continuation's speed where the end is read (refit_tip), on 46 three-camera sessions
# (the 45 above and draw 97's coil with disks; 90 frames, 2026-12-03): median tips 0.660
# against 0.709 mm, the uniform coil 0.53 against 1.28 mm, but frames more than 2 mm off
# 448 against 370, as two round ends' evidence faded (draw 97's coil with disks, mean vote
# +0.10 +- 0.05 against +0.75 +- 0.07, 87 frames off against 57; a stepped r 4.5 tube
# chosen flat, 51 against 2). Left out: the cap is taken off in the image instead (refit_tip).
def end_frame(
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
