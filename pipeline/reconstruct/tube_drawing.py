"""A tube drawn with sub-pixel coverage in a view, and compared with its grey levels.

A view's grey levels are scaled to coverage (0 background, 1 tube) with local levels
read from the pixels certainly on either side (:func:`pixel_coverages`). A tube (its
axis, a radius and a flat or round end) is drawn on a canvas finer than the image,
the sum of circles and polygons of its rings (:func:`draw_tube`), and its squared
difference from that coverage is the mismatch (:func:`coverage_mismatch`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import Camera
from ..geometry.polyline import polyline_arclength
from .disks import Disks, rim_pixels, rims
from .profiles import MIN_CONTRAST

FloatArray = NDArray[np.float64]
# A pixel window ((x0, y0), (x1, y1)), half-open.
Window = tuple[tuple[int, int], tuple[int, int]]

# (x, y) -> (-y, x) applied to (y, x): a quarter turn left.
_QUARTER_LEFT = np.array([-1.0, 1.0])
# A drawn uint8 level (0-255, averaged over the finer canvas) as float32
# coverage: the table of its float32 quotients by 255.
_LEVELS = np.arange(256, dtype=np.float32) / 255.0
# cv2 drawing takes fixed-point coordinates with this many fractional bits.
DRAW_SHIFT = 4
# Shapes are drawn only where their pixels lie within this of the image origin: a point
# near a camera's plane projects arbitrarily far, past what fixed point holds in 32 bits.
DRAWABLE_PX = 1e5
# cv2's filled circles and polygons take in every pixel their outline touches:
# a circle comes out 0.42 (fine) pixel wider in radius than the pixel centres
# it should hold (mean over 200 random circles, r 4-30 px; spread 0.08), a
# polygon 0.50 pixel wider on every edge (300 random rectangles; spread 0.07).
# On the 4 times finer canvas of the bend that is 0.1 px of the image on every
# edge, and made the drawn tip 0.25-0.5 mm long against exact coverage: the
# shapes are drawn smaller by these amounts.
_CIRCLE_BIAS = 0.42
_POLYGON_BIAS = 0.5
SUPERSAMPLE = 4
_RING_POINTS = 24
# The rings' unit circle, (_RING_POINTS, 1) each.
_RING_COS = np.cos(np.linspace(0.0, 2.0 * np.pi, _RING_POINTS, endpoint=False))[:, None]
_RING_SIN = np.sin(np.linspace(0.0, 2.0 * np.pi, _RING_POINTS, endpoint=False))[:, None]
# A window drawn around a tube reaches this far past its drawn edge (px), where whole
# tubes are compared (coverage_mismatch) ...
_WINDOW_PX = 20.0
# ... and this far past the farthest a tube moved by a bounded number of radii can reach
# (a tip's bends, pipeline.reconstruct.tip_bend): the window's whole-pixel bounds and the
# pixels its edge partly covers.
_WINDOW_EDGE_PX = 2.0
# Erosion / dilation (px) of the silhouette that picks the pixels certainly on
# the tube / on the background, to scale the grey levels to coverage.
_CORE_PX = 5
# ... and the local levels: Gaussian averages over those pixels, with these
# widths (px); fewer than _NEAR_WEIGHT of such pixels in the kernel's weight
# leave the global median.
_TUBE_SIGMA_PX = 3.0
_BACKGROUND_SIGMA_PX = 4.0
_NEAR_WEIGHT = 1e-3
# A pixel's coverage depends on the pixels this far around it: the Gaussians' reach
# (OpenCV's float kernels span 4 sigmas each way: 16 px at 4 px) and the core's
# erosion (half of _CORE_PX), with a margin.
_COVERAGE_REACH_PX = 24


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
    (sub-pixel, flat end, see :func:`draw_tube`) and the coverage read from
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
        windows = [w for w in (view_window(cam, axis, radius_mm) for axis in axes_mm) if w is not None]
        if len(windows) < len(axes_mm):
            continue  # a tube this view does not see whole: no fair comparison here
        x0, y0 = (min(w[0][i] for w in windows) for i in (0, 1))
        x1, y1 = (max(w[1][i] for w in windows) for i in (0, 1))
        seen = coverage[y0:y1, x0:x1]
        for n, axis in enumerate(axes_mm):
            difference = drawn_coverage(cam, axis, radius_mm, ((x0, y0), (x1, y1)), cap=caps[n]) - seen
            costs[n] += float(np.add.reduce(difference * difference, axis=None))
    return costs


def drawn_coverage(
    camera: Camera,
    axis_mm: FloatArray,
    radius_mm: float,
    window: Window,
    *,
    cap: str,
    disks: Disks | None = None,
) -> NDArray[np.float32]:
    """(y1 - y0, x1 - x0) float32 in [0, 1]: how much of each pixel of the image
    window ((x0, y0), (x1, y1)) the tube of radius ``radius_mm`` around (K, 3)
    ``axis_mm`` (world frame, mm, from the base) with end ``cap`` and spacer ``disks``
    covers (:func:`draw_tube`, averaged by :func:`canvas_levels`): comparable with
    :func:`pixel_coverages`."""
    (x0, y0), (x1, y1) = window
    canvas = np.zeros(((y1 - y0) * SUPERSAMPLE, (x1 - x0) * SUPERSAMPLE), np.uint8)
    draw_tube(canvas, camera, *tube_points(axis_mm, radius_mm, flat_end=cap == "flat"), radius_mm, (x0, y0))
    if disks is not None:
        disk_rims = rims(axis_mm, polyline_arclength(axis_mm), disks)
        if len(disk_rims):
            draw_disks(canvas, rim_pixels([camera], disk_rims)[0], (x0, y0))
    return _LEVELS[canvas_levels(canvas)]


def view_window(
    cam: Camera, axis_mm: FloatArray, radius_mm: float, *, reach_radii: float | None = None
) -> Window | None:
    """Pixel window ((x0, y0), (x1, y1)) around the tube of (K, 3) ``axis_mm``, None if
    not seen: ``_WINDOW_PX`` past its drawn edge, or, with ``reach_radii``, room for the
    tube moved by up to that many radii (nearer the camera too, where it looks wider)
    and ``_WINDOW_EDGE_PX`` more: every pixel such a tube can cover."""
    px = cam.project(axis_mm)
    depth = cam.to_camera(axis_mm)[:, 2]
    if not (np.isfinite(px).all() and (depth > radius_mm).all()):
        return None
    if reach_radii is None:
        margin = cam.focal_px * radius_mm / float(depth.min()) + _WINDOW_PX
    else:
        nearest = float(depth.min()) - reach_radii * radius_mm
        if not nearest > radius_mm:
            return None
        margin = (1.0 + reach_radii) * cam.focal_px * radius_mm / nearest + _WINDOW_EDGE_PX
    w, h = cam.size_px
    x0, y0 = (max(int(np.floor(v)), 0) for v in px.min(axis=0) - margin)
    x1, y1 = (min(int(np.ceil(v)), n) for v, n in zip(px.max(axis=0) + margin, (w, h), strict=True))
    return ((x0, y0), (x1, y1)) if x1 > x0 and y1 > y0 else None


def pixel_coverages(
    contrasts: Sequence[NDArray[np.float32]],
    masks: Sequence[NDArray[np.bool_]],
    windows: Sequence[Window | None] | None = None,
) -> list[NDArray[np.float32]]:
    """Per view, (H, W) float32 in [0, 1]: how much of each pixel the tube covers
    (:func:`_coverage` of its (H, W) contrast and bool silhouette).

    ``windows``: per view, the pixel window ((x0, y0), (x1, y1)) wanted, or None for
    none of it; the other pixels come out 0. Each is read from a crop reaching
    ``_COVERAGE_REACH_PX`` beyond it, which gives its pixels the whole image's
    coverage, but for the levels assumed where no certain pixel is near (the medians
    of the crop's, not of the image's).
    """
    if windows is None:
        return [_coverage(contrast, mask) for contrast, mask in zip(contrasts, masks, strict=True)]
    out = []
    for contrast, mask, window in zip(contrasts, masks, windows, strict=True):
        coverage = np.zeros(contrast.shape, np.float32)
        if window is not None:
            (x0, y0), (x1, y1) = window
            h, w = contrast.shape
            cx0, cy0 = max(x0 - _COVERAGE_REACH_PX, 0), max(y0 - _COVERAGE_REACH_PX, 0)
            cx1, cy1 = min(x1 + _COVERAGE_REACH_PX, w), min(y1 + _COVERAGE_REACH_PX, h)
            crop = _coverage(contrast[cy0:cy1, cx0:cx1], mask[cy0:cy1, cx0:cx1])
            coverage[y0:y1, x0:x1] = crop[y0 - cy0 : y1 - cy0, x0 - cx0 : x1 - cx0]
        out.append(coverage)
    return out


def _coverage(contrast: NDArray[np.float32], mask: NDArray[np.bool_]) -> NDArray[np.float32]:
    """(H, W) float32 in [0, 1]: how much of each pixel the tube covers, from its grey level.

    The contrast scaled between the background's local level (pixels well
    outside the silhouette, averaged nearby) and the tube's (well inside),
    clipped: edge pixels, blurred by the optics and the video, come out in
    between. Local, because the scene is textured and the tube shaded: with one
    level for each, a background patch darker than the median reads as part
    covered, and the tip is drawn towards it.
    """
    if not mask.any():
        # No silhouette pixel near (a window where a view lost the tube): none of it here.
        return np.zeros(contrast.shape, np.float32)
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


def tube_points(axis_mm: FloatArray, radius_mm: float, *, flat_end: bool) -> tuple[FloatArray, FloatArray]:
    """What :func:`draw_tube` draws of the tube around (K, 3) ``axis_mm``: disc
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
        n1, n2 = normals(tangent)
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


def draw_tube(
    canvas: NDArray[np.uint8],
    cam: Camera,
    discs_mm: FloatArray,
    outline_mm: FloatArray,
    radius_mm: float | FloatArray,
    origin: tuple[int, int],
    *,
    pixels: FloatArray | None = None,
) -> tuple[int, int, int, int]:
    """Draw (255) a tube given by :func:`tube_points` on a ``SUPERSAMPLE``-times
    finer canvas whose pixel (0, 0) is the image's pixel ``origin`` (x, y);
    ``radius_mm``: one for every disc, or (D,) each its own; ``pixels``: the
    (D + O, 2) projection of its discs and outline, if known.

    Returns the canvas rectangle (x0, y0, x1, y1), half-open, that holds every
    canvas pixel drawn (with a margin)."""
    one = SUPERSAMPLE * (1 << DRAW_SHIFT)
    # Pixel centres sit at integer coordinates; on the finer canvas pixel (u, v)'s
    # centre is at s u + (s - 1) / 2.
    offset = np.asarray(origin, dtype=np.float64) - (SUPERSAMPLE - 1) / (2 * SUPERSAMPLE)
    focal = cam.focal_px
    if pixels is None:
        pixels = cam.project(np.vstack([discs_mm, outline_mm]))
    px = (pixels - offset) * one
    # cv2 fills what its outlines touch: shapes come out too large (see _CIRCLE_BIAS).
    bias = _CIRCLE_BIAS * (1 << DRAW_SHIFT)
    # Array methods (.round()), not np.round's wrapper: this runs for every
    # bend tried in every view.
    # A disc narrower than the bias (a thin tube far away) is drawn as a point.
    radii = np.maximum(focal * radius_mm / cam.to_camera(discs_mm)[:, 2] * one - bias, 0.0).round()
    centres = px[: len(discs_mm)].round().astype(np.int64)
    # What is drawn, in fixed point: x0, y0, x1, y1 (plain ints: few shapes).
    far = 1 << 62
    box = [far, far, -far, -far]
    for (cx, cy), r in zip(centres.tolist(), radii.astype(np.int64).tolist(), strict=True):
        cv2.circle(canvas, (cx, cy), r, 255, -1, cv2.LINE_8, DRAW_SHIFT)
        if cx - r < box[0]:
            box[0] = cx - r
        if cy - r < box[1]:
            box[1] = cy - r
        if cx + r > box[2]:
            box[2] = cx + r
        if cy + r > box[3]:
            box[3] = cy + r
    if len(outline_mm):
        hull = fill_hull(canvas, px[len(discs_mm) :], 255)
        x, y, w, h = cv2.boundingRect(hull)
        box = [min(box[0], x), min(box[1], y), max(box[2], x + w), max(box[3], y + h)]
    return _canvas_rectangle(canvas, box)


def _canvas_rectangle(canvas: NDArray[np.uint8], box: list[int]) -> tuple[int, int, int, int]:
    """The canvas rectangle (x0, y0, x1, y1), half-open, that holds the fixed-point ``box``
    drawn in (x0, y0, x1, y1, inclusive), and two canvas pixels more on each side: cv2 fills
    what its outlines touch."""
    height, width = canvas.shape
    return (
        max((box[0] >> DRAW_SHIFT) - 2, 0),
        max((box[1] >> DRAW_SHIFT) - 2, 0),
        min((box[2] >> DRAW_SHIFT) + 3, width),
        min((box[3] >> DRAW_SHIFT) + 3, height),
    )


def fill_hull(canvas: NDArray[np.uint8], points: FloatArray, colour: int) -> NDArray[np.int32]:
    """Fill (``colour``) the convex hull of ``points`` (P, 2), in ``DRAW_SHIFT`` fixed point
    of the canvas' pixels, drawn smaller by cv2's bias (see ``_POLYGON_BIAS``); returns the
    hull drawn, (H, 2) fixed point."""
    hull = cv2.convexHull(points.astype(np.float32))[:, 0, :].astype(np.float64)
    hull = _shrink_convex(hull, _POLYGON_BIAS * (1 << DRAW_SHIFT)).round().astype(np.int32)
    cv2.fillConvexPoly(canvas, hull, colour, cv2.LINE_8, DRAW_SHIFT)
    return np.asarray(hull)


def draw_disks(
    canvas: NDArray[np.uint8], disks_px: FloatArray, origin: tuple[int, int]
) -> tuple[int, int, int, int]:
    """Draw (255) spacer disks on a canvas as :func:`draw_tube` does, each the convex hull of
    its rims' pixels ``disks_px`` (D, P, 2) in the image (:func:`pipeline.reconstruct.disks.rims`,
    projected); returns the canvas rectangle drawn, as :func:`draw_tube` does (empty:
    (0, 0, 0, 0))."""
    one = SUPERSAMPLE * (1 << DRAW_SHIFT)
    offset = np.asarray(origin, dtype=np.float64) - (SUPERSAMPLE - 1) / (2 * SUPERSAMPLE)
    far = 1 << 62
    box = [far, far, -far, -far]
    for disk_px in disks_px:
        if not (np.isfinite(disk_px).all() and (np.abs(disk_px) < DRAWABLE_PX).all()):
            continue
        hull = fill_hull(canvas, (disk_px - offset) * one, 255)
        x, y, w, h = cv2.boundingRect(hull)
        box = [min(box[0], x), min(box[1], y), max(box[2], x + w), max(box[3], y + h)]
    return (0, 0, 0, 0) if box[0] > box[2] else _canvas_rectangle(canvas, box)


def canvas_levels(canvas: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """(h, w) uint8: each ``SUPERSAMPLE`` x ``SUPERSAMPLE`` block of the (h s, w s)
    canvas averaged (each block on its own: any part of the canvas whose sides
    are multiples of s gives the same levels as the whole)."""
    h, w = canvas.shape
    levels = cv2.resize(canvas, (w // SUPERSAMPLE, h // SUPERSAMPLE), interpolation=cv2.INTER_AREA)
    return np.asarray(levels, dtype=np.uint8)


def level_difference(levels: NDArray[np.uint8], seen: NDArray[np.float32]) -> float:
    """Sum over the pixels of ((h, w) uint8 ``levels`` as coverage - (h, w) float32 ``seen``)^2."""
    difference = level_residuals(levels, seen)
    return float(np.add.reduce(difference * difference, axis=None))


def level_residuals(levels: NDArray[np.uint8], seen: NDArray[np.float32]) -> NDArray[np.float32]:
    """(h w,) float32: each pixel's (h, w) uint8 ``levels`` as coverage less its (h, w)
    float32 ``seen`` coverage (the terms :func:`level_difference` squares and sums)."""
    # cv2's table look-up and float32 difference: the same IEEE results as NumPy's, in
    # half the time.
    return np.asarray(cv2.subtract(cv2.LUT(levels, _LEVELS), seen), dtype=np.float32).ravel()


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


def normals(direction: FloatArray) -> tuple[FloatArray, FloatArray]:
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
