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
    path = end_frame(pts, arc, at_mm=anchor, span_mm=END_SPAN_MM)
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
            if len(read) and min_distance(others_px, read) < radius_mm * px_per_mm + 1.0:
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
    window = ((x0, y0), (x1, y1))
    owner[tube_mask(cam, body_mm, radius_mm, window=window)] = 0
    seen = mask[y0:y1, x0:x1]
    inside = np.bincount(owner[seen], minlength=len(u) + 1)[1:]
    outside = np.bincount(owner[~seen], minlength=len(u) + 1)[1:]
    if inside.sum() < _MIN_PIXELS:
        return None
    gain = np.cumsum(inside - outside)
    return float(u[int(np.argmax(gain))])


def tip_zone(radius_mm: float) -> float:
    """Length (mm) at the tip end with no side readings: see _TIP_ZONE_MM."""
    return min(0.5 * radius_mm, _TIP_ZONE_MM)


def min_distance(a: FloatArray, b: FloatArray) -> float:
    """Smallest distance between a point of (A, D) ``a`` and a point of (B, D) ``b``."""
    gap = a[:, None, :] - b[None, :, :]
    return float(np.sqrt(np.einsum("abi,abi->ab", gap, gap).min()))


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
