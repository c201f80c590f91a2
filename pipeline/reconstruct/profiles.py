"""Reading the grey images along lines: across the tube (its two edges) and along it (its end).

Sub-pixel edges come from the grey levels, not the masks: an edge is where a
profile crosses half way between the tube's and the background's local levels,
interpolated between samples. Also the projection's Jacobian, by finite differences.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import Camera, project_in_views

FloatArray = NDArray[np.float64]

# Finite-difference step for the projection Jacobian (mm): the projection is
# smooth on this scale, and 1e-3 mm keeps the truncation error < 1e-6 px.
JAC_EPS_MM = 1e-3
# A reading is trusted when the tube stands out from the background by this much.
MIN_CONTRAST = 12.0


def project_with_jacobians(cameras: Sequence[Camera], pts: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Pixels (C, K, 2) of points (K, 3) mm in C cameras, and the projection's
    Jacobians (C, K, 2, 3) px/mm by finite differences (the shifted points built
    once for all cameras)."""
    k = len(pts)
    shifted = np.concatenate([pts] + [pts + JAC_EPS_MM * e for e in np.eye(3)])
    px = project_in_views(cameras, shifted).reshape(len(cameras), 4, k, 2)
    # The Jacobians keep the layout the per-camera np.stack gave them, a (C, 3, K, 2)
    # block viewed as (C, K, 2, 3), and the pixels are a fresh (C, K, 2) array:
    # the tube fit's einsum calls sum in another order over other strides (seen:
    # last-bit differences in the image tangents), and the curves are kept bit
    # for bit.
    jac = ((px[:, 1:] - px[:, :1]) / JAC_EPS_MM).transpose(0, 2, 3, 1)  # (C, K, 2, 3)
    return np.ascontiguousarray(px[:, 0]), jac


def sample_image(image: NDArray[np.float32], xy: FloatArray) -> FloatArray:
    """Bilinear samples of ``image`` at pixel positions ``xy`` (..., 2); edge pixels repeat."""
    shape = xy.shape[:-1]
    flat = xy.reshape(-1, 2).astype(np.float32)
    # cv2.remap's maps must be 2-D; a (n, 1) map reads n pixels in one call.
    out = cv2.remap(
        image,
        np.ascontiguousarray(flat[:, :1]),
        np.ascontiguousarray(flat[:, 1:]),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return np.asarray(out, dtype=np.float64).reshape(shape)


def sample_lines_in(
    images: Sequence[NDArray[np.float32]], start_px: FloatArray, direction: FloatArray, steps: FloatArray
) -> FloatArray:
    """(C, K, S) bilinear samples of C images along K lines each: at ``start_px``
    (C, K, 2) + ``steps`` (S,) x ``direction`` (C, K, 2), px; edge pixels repeat,
    as :func:`sample_image`. The maps of all images are built by one array call per
    axis (no (C, K, S, 2) array to build, cast and split), one cv2.remap per image
    into one array."""
    maps = []
    for axis in range(2):
        at = start_px[..., axis, None] + steps * direction[..., axis, None]
        if not np.isfinite(at).all():
            at = np.nan_to_num(at)  # a point behind a camera (rare: the check is cheaper)
        maps.append(at.astype(np.float32))
    out = np.empty(maps[0].shape, dtype=np.float32)
    for j, image in enumerate(images):
        cv2.remap(
            image, maps[0][j], maps[1][j], cv2.INTER_LINEAR, dst=out[j], borderMode=cv2.BORDER_REPLICATE
        )
    return out.astype(np.float64)


def side_edges(
    profile: FloatArray, steps: FloatArray, r_px: FloatArray, *, core: float = 0.6
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """Sub-pixel silhouette edges on (K, S) profiles taken at offsets ``steps`` (px).

    An edge is where the profile falls half way from the tube's level to the
    background's level on that side, interpolated between samples. The levels are
    local, because the tube is shaded and the scene textured: the background is
    the lower quartile of the profile's outer part on that side; the tube's level
    is first the profile's peak near the centre, then (second pass) its value one
    pixel inside the first edge estimate, i.e. the rim's own shade.

    Returns left and right offsets (px) and whether both were found.
    """
    k, s = profile.shape
    step = steps[1] - steps[0]
    near = np.abs(steps)[None, :] <= np.maximum(1.0, core * r_px)[:, None]
    peak_idx = np.argmax(np.where(near, profile, -np.inf), axis=1)
    peak = profile[np.arange(k), peak_idx]
    # Both sides in one pass (half the numpy calls): the negative side is the
    # positive side of the mirrored profile, rows 0..K-1 below; K..2K-1 are as is.
    both = np.concatenate([profile[:, ::-1], profile])
    start = np.concatenate([s - 1 - peak_idx, peak_idx])
    top = np.concatenate([peak, peak])
    # The outer part, 1.5 r + 2 to 2.5 r + 3 px from the centre, is one run of
    # samples on each side (``steps`` ascend): where it starts in ``both``'s rows
    # and how long it is, found by bisection instead of (2K, S) masks.
    inner_px, outer_px = 1.5 * r_px + 2.0, 2.5 * r_px + 3.0
    neg_end = np.searchsorted(steps, -inner_px, "right")  # steps <= -(1.5 r + 2)
    pos_start = np.searchsorted(steps, inner_px, "left")  # steps >= 1.5 r + 2
    first = np.concatenate([s - neg_end, pos_start])
    neg_start = np.searchsorted(steps, -outer_px, "left")  # steps >= -(2.5 r + 3)
    pos_end = np.searchsorted(steps, outer_px, "right")  # steps <= 2.5 r + 3
    count = np.concatenate([neg_end - neg_start, pos_end - pos_start])
    bg = _run_lower_quartile(both, first, np.maximum(count, 0))
    ok = np.isfinite(bg) & (top - bg >= MIN_CONTRAST)
    bg = np.where(ok, bg, top)
    ahead = np.arange(s)[None, :] > start[:, None]  # both passes search past the peak
    pos, hit = crossing(both, ahead, 0.5 * (top + bg), 1)
    # The rim's shade, one pixel inside the first estimate (not past the peak).
    rim_at = np.minimum(np.maximum(pos - 1.0 / step, np.minimum(start, pos)), np.maximum(start, pos))
    rim = interp_rows(both, rim_at)
    rim = np.where(rim - bg >= MIN_CONTRAST, rim, top)
    pos, hit2 = crossing(both, ahead, 0.5 * (rim + bg), 1)
    found = ok & hit & hit2
    left = steps[0] + (s - 1 - pos[:k]) * step
    right = steps[0] + pos[k:] * step
    return left, right, found[:k] & found[k:]


def lower_quartile(profile: FloatArray, region: NDArray[np.bool_]) -> FloatArray:
    """(K,) lower quartile of each row of ``profile`` over ``region``; inf where empty.

    The lower quartile, not the median: another part of the tube crossing the
    outer profile raises a median but not the background's lower values."""
    ordered = np.sort(np.where(region, profile, np.inf), axis=1)
    count = region.sum(axis=1)
    return np.asarray(ordered[np.arange(len(profile)), (count // 4).clip(0, profile.shape[1] - 1)])


def _run_lower_quartile(profile: FloatArray, first: NDArray[np.intp], count: NDArray[np.intp]) -> FloatArray:
    """:func:`lower_quartile` of each row of (K, S) ``profile`` over the run of
    ``count`` (K,) samples from index ``first`` (K,): the same value, sorting only
    the runs (a few samples each) instead of whole rows."""
    width = int(count.max()) if len(count) else 0
    if width == 0:
        return np.full(len(profile), np.inf)
    offsets = np.arange(width)
    rows = np.arange(len(profile))[:, None]
    cols = np.minimum(first[:, None] + offsets, profile.shape[1] - 1)
    run = np.where(offsets < count[:, None], profile[rows, cols], np.inf)
    run.sort(axis=1)
    return np.asarray(run[rows[:, 0], count // 4])


def interp_rows(profile: FloatArray, at: FloatArray) -> FloatArray:
    """Linear interpolation of each row of (K, S) ``profile`` at fractional index ``at`` (K,)."""
    s = profile.shape[1]
    # np.minimum / np.maximum, not np.clip: the same values at a fraction of the call's cost.
    lo = np.minimum(np.maximum(np.floor(at).astype(np.intp), 0), s - 2)
    frac = np.minimum(np.maximum(at - lo, 0.0), 1.0)
    rows = np.arange(len(at))
    return np.asarray((1 - frac) * profile[rows, lo] + frac * profile[rows, lo + 1])


def crossing(
    profile: FloatArray, ahead: NDArray[np.bool_], level: FloatArray, side: int
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """First fractional index, among the samples ``ahead`` (K, S) bool (those past
    each row's start), towards ``side`` (+1/-1), where each row of (K, S)
    ``profile`` falls below ``level`` (K,); and whether it does."""
    k, s = profile.shape
    below = (profile < level[:, None]) & ahead
    if side > 0:
        j = np.argmax(below, axis=1)
    else:
        j = s - 1 - np.argmax(below[:, ::-1], axis=1)
    rows = np.arange(k)
    hit = below[rows, j]  # argmax lands on a True wherever a row has one
    j = np.minimum(np.maximum(j, 1), s - 2)
    inner = j - side
    a, b = profile[rows, inner], profile[rows, j]
    frac = np.minimum(np.maximum((a - level) / np.maximum(a - b, 1e-9), 0.0), 1.0)
    return np.asarray(inner + side * frac, dtype=np.float64), np.asarray(hit)


def end_edge(profile: FloatArray, t: FloatArray, radius_mm: float, mm_per_px: float) -> float | None:
    """Where a (1, S) profile read along the 3-D end line at ``t`` (mm) leaves the tube, mm.

    Levels as in :func:`side_edges`: a first crossing half way between the tube's peak
    and the profile's lowest decile, then half way between the rim (one pixel
    inside) and the lower quartile of what lies past the end. One row: scalar
    arithmetic (the same as :func:`crossing` and :func:`interp_rows` on one row),
    which costs a tenth of their array calls.
    """
    row = profile[0]
    step = t[1] - t[0]
    inside = np.nonzero(t <= -radius_mm)[0]  # t: mm past the current end
    if len(inside) == 0:
        return None
    start = int(np.argmax(row[inside]))
    peak = float(row[start])
    bg = percentile_1d(row, 0.10)
    if peak - bg < MIN_CONTRAST:
        return None
    pos = _first_below(row, start, 0.5 * (peak + bg))
    if pos is None:
        return None
    px_steps = mm_per_px / step  # one pixel, in samples
    beyond = row[int(np.ceil(pos + px_steps)) :]
    if len(beyond):
        bg = percentile_1d(beyond, 0.25)
    at = max(pos - px_steps, float(start))
    lo = min(max(int(np.floor(at)), 0), len(row) - 2)
    frac = min(max(at - lo, 0.0), 1.0)
    rim = (1 - frac) * float(row[lo]) + frac * float(row[lo + 1])
    if rim - bg < MIN_CONTRAST:
        rim = peak
    pos = _first_below(row, start, 0.5 * (rim + bg))
    if pos is None:
        return None
    return float(t[0] + pos * step)


def _first_below(row: FloatArray, start: int, level: float) -> float | None:
    """:func:`crossing` towards +1 on one (S,) row: the fractional index, or None."""
    below = np.flatnonzero(row[start + 1 :] < level)
    if len(below) == 0:
        return None
    j = min(max(start + 1 + int(below[0]), 1), len(row) - 2)
    a, b = float(row[j - 1]), float(row[j])
    return (j - 1) + min(max((a - level) / max(a - b, 1e-9), 0.0), 1.0)


def percentile_1d(values: FloatArray, q: float) -> float:
    """``np.percentile(values, 100 q)`` (linear interpolation) of a 1-D array, without
    its per-call overhead."""
    ordered = np.sort(values)
    at = q * (len(ordered) - 1)
    lo = int(at)
    hi = min(lo + 1, len(ordered) - 1)
    a, b = float(ordered[lo]), float(ordered[hi])
    gamma = at - lo
    # numpy's own lerp, exact at both ends.
    return b - (b - a) * (1.0 - gamma) if gamma >= 0.5 else a + (b - a) * gamma


def median_1d(values: FloatArray) -> float:
    """``np.median`` of a non-empty 1-D array (the same value), without its per-call overhead."""
    ordered = np.sort(values)
    n = len(ordered)
    if n % 2:
        return float(ordered[n // 2])
    return float((ordered[n // 2 - 1] + ordered[n // 2]) / 2)


def theil_sen_slope(x: FloatArray, y: FloatArray) -> float:
    """The Theil-Sen slope of (N,) ``y`` over (N,) ``x``: the median of the slopes between
    every two points apart in ``x``, which outliers barely move while they are fewer
    than about three in ten; NaN where no two points are apart.

    ``scipy.stats.theilslopes``'s slope, without the confidence interval it also works
    out (5 us against its 230 on a few tens of points: this runs in every side reading
    and every tracked frame).
    """
    i, j = _pairs(len(x))
    run = x[j] - x[i]
    apart = run != 0
    return median_1d((y[j] - y[i])[apart] / run[apart]) if apart.any() else float("nan")


@functools.lru_cache(maxsize=64)
def _pairs(n: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Every pair (i < j) of ``n`` points, as two index arrays (the same for every call)."""
    i, j = np.triu_indices(n, 1)
    return i, j


def nanmedian_rows(values: FloatArray) -> FloatArray:
    """(R,) ``np.nanmedian(values, axis=1)`` of an (R, N) array whose every row has a
    finite value (the same values), without its per-call overhead: NaN sorts last,
    so each row's median is read at the middle of its finite count."""
    ordered = np.sort(values, axis=1)
    count = np.isfinite(ordered).sum(axis=1)
    rows = np.arange(len(ordered))
    return 0.5 * (ordered[rows, (count - 1) // 2] + ordered[rows, count // 2])
