"""Spacer disks along the tube: drawn into its outline, and read from a session's frames.

Tendon-driven robots carry disks along the backbone: short cylinders wider than the tube,
centred on it and perpendicular to it. Seen at an angle, a disk's outline is an ellipse
that reaches along the tube's outline as far as the disk is wide, so that over most of
the tube the silhouette's edge across a side reading is a disk's, not the tube's; a
reading's mid-point is then the axis only where the ellipse is cut across its own axes.
The tube model draws them: along each side reading's line, the outline it expects is the
tube's two edges united with every disk's span on that line that touches them
(:func:`outline_along`), and the edges read are taken against that outline instead of
the tube's own radius (:func:`pipeline.reconstruct.side_readings.read_sides`).

Where the disks are is read once per session (:func:`read_disks`), from the half-widths
the sample frames read along their axes: at a disk's centre every view reads the disk's
radius (the line across the tube cuts its ellipse through the centre, along the major
axis), between disks farther apart than their radius the tube's own.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import Camera, project_in_views
from .width_bins import binned_medians

FloatArray = NDArray[np.float64]

# A disk's outline is the convex hull of the rims of its two faces, each drawn as a
# polygon of this many points.
_RIM_POINTS = 24
_FACES = (-0.5, 0.5)
# A disk is drawn perpendicular to the backbone's chord over this far either side of it
# (mm), not to the tangent at its centre: a tangent a wiggle of the curve turns tilts the
# disk's ellipse across the readings, and the readings turn the curve further. Fitted from
# the true axis of a helix (r 6 tube, r 11.5 mm disks every 20 mm, `accuracy_table --draw
# 439`, frame 40, the disks' true places; 2026-12-06), the curve 250 mm long grew to 267 mm
# over 8 rounds with the tangent, to 252 mm with the chord.
_CHORD_HALF_MM = 8.0
# Disk thickness (mm) drawn. Not read from the frames: from the true axis of that frame
# (its disks 2.5 mm thick), 0.5 to 3.5 mm put the fitted axis 0.33-0.48 mm off (mean), as
# the true 2.5 mm did.
THICKNESS_MM = 2.0


@dataclass(frozen=True)
class Disks:
    """Spacer disks: their centres' arc lengths from the base ``arc_mm`` (D,) mm, increasing,
    and their common radius and thickness, mm."""

    arc_mm: FloatArray
    radius_mm: float
    thickness_mm: float = THICKNESS_MM

    def describe(self) -> str:
        """One line for the summary: how many disks, their size and spacing."""
        spacing = f", {np.median(np.diff(self.arc_mm)):.1f} mm apart" if len(self.arc_mm) > 1 else ""
        return f"{len(self.arc_mm)} spacer disks of radius {self.radius_mm:.1f} mm{spacing}"

    def from_tip(self, length_mm: float) -> Disks:
        """The same disks placed by arc length from the tip of a tube ``length_mm`` long
        (its axis run backwards), increasing."""
        return Disks((length_mm - self.arc_mm)[::-1], self.radius_mm, self.thickness_mm)

    def to_dict(self) -> dict[str, Any]:
        """The disks for the recordings' metadata (in the radius profile's JSON), to 0.001 mm;
        the thickness drawn is not read, and not written."""
        return {"arc_mm": np.round(self.arc_mm, 3).tolist(), "radius_mm": round(self.radius_mm, 3)}

    @classmethod
    def from_dict(cls, data: Any) -> Disks | None:
        """The disks :meth:`to_dict` wrote; None where ``data`` is not one."""
        try:
            arc = np.asarray(data["arc_mm"], dtype=np.float64)
            radius = float(data["radius_mm"])
        except (ValueError, TypeError, KeyError):
            return None
        ordered = arc.ndim == 1 and len(arc) > 0 and bool(np.all(np.diff(arc) > 0))
        return cls(arc, radius) if ordered and np.isfinite(radius) and radius > 0 else None


def rims(axis_mm: FloatArray, arc_mm: FloatArray, disks: Disks) -> FloatArray:
    """(D', F, R, 3) the rims (mm) of the disks that lie on the axis ``axis_mm`` (K, 3), whose
    arc lengths from the base are ``arc_mm`` (K,): each disk at ``_FACES`` across its thickness,
    ``_RIM_POINTS`` points each."""
    along = disks.arc_mm[(disks.arc_mm > arc_mm[0]) & (disks.arc_mm < arc_mm[-1])]
    if len(along) == 0 or len(arc_mm) < 2:
        return np.zeros((0, len(_FACES), _RIM_POINTS, 3))

    def at(arc: FloatArray) -> FloatArray:
        return np.stack([np.interp(arc, arc_mm, axis_mm[:, i]) for i in range(3)], axis=1)

    centres = at(along)
    chord = at(np.minimum(along + _CHORD_HALF_MM, arc_mm[-1])) - at(
        np.maximum(along - _CHORD_HALF_MM, arc_mm[0])
    )
    t = chord / np.linalg.norm(chord, axis=1, keepdims=True)
    other = np.where(np.abs(t[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    n1 = np.cross(t, other)
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
    n2 = np.cross(t, n1)
    angle = np.linspace(0.0, 2.0 * np.pi, _RIM_POINTS, endpoint=False)
    ring = disks.radius_mm * (np.cos(angle)[:, None] * n1[:, None] + np.sin(angle)[:, None] * n2[:, None])
    faces = [centres[:, None] + f * disks.thickness_mm * t[:, None] + ring for f in _FACES]
    return np.stack(faces, axis=1)


def rim_pixels(cameras: Sequence[Camera], rims_mm: FloatArray) -> FloatArray:
    """(C, D, F R, 2) the pixels of the rims ``rims_mm`` (D, F, R, 3) (:func:`rims`) in each
    of C views."""
    d = len(rims_mm)
    return project_in_views(cameras, rims_mm.reshape(-1, 3)).reshape(len(cameras), d, -1, 2)


def spans_along(
    cameras: Sequence[Camera], rims_mm: FloatArray, px: FloatArray, normal: FloatArray
) -> FloatArray:
    """(C, K, D, 2) each disk's span [from, to] (px) along the K lines of each of C views,
    NaN where it misses the line. A line starts at ``px`` (C, K, 2) and runs along the
    unit ``normal`` (C, K, 2); ``rims_mm`` (D, F, R, 3) from :func:`rims`. A disk's outline
    in a view is the convex hull of its rims' pixels (seen edge-on, a bar as long as the
    disk is wide and as wide as it is thick)."""
    n_views, k = px.shape[:2]
    d = rims_mm.shape[0]
    if d == 0 or k == 0:
        return np.full((n_views, k, d, 2), np.nan)
    rim_px = rim_pixels(cameras, rims_mm)
    hulls = np.full((n_views, d, rim_px.shape[2], 2), np.nan)
    for view in range(n_views):
        for disk in range(d):
            points = rim_px[view, disk]
            if np.isfinite(points).all():
                hull = cv2.convexHull(points.astype(np.float32))[:, 0, :]
                # Padded with its last vertex: edges of no length cross no line.
                hulls[view, disk] = np.vstack([hull, np.repeat(hull[-1:], len(points) - len(hull), axis=0)])
    offset = hulls[:, None] - px[:, :, None, None, :]  # (C, K, D, H, 2)
    n = normal[:, :, None, None, :]
    side = offset[..., 0] * n[..., 1] - offset[..., 1] * n[..., 0]  # across the line
    along = offset[..., 0] * n[..., 0] + offset[..., 1] * n[..., 1]
    side_next, along_next = np.roll(side, -1, axis=-1), np.roll(along, -1, axis=-1)
    # A hull's edge crosses the line where its ends lie on either side of it.
    with np.errstate(invalid="ignore", divide="ignore"):
        crosses = (side <= 0) != (side_next <= 0)
        crosses &= np.isfinite(side) & np.isfinite(side_next)
        at = np.where(crosses, along + side / (side - side_next) * (along_next - along), np.nan)
    hit = crosses.any(axis=-1)
    lo = np.where(hit, np.min(np.where(crosses, at, np.inf), axis=-1), np.nan)
    hi = np.where(hit, np.max(np.where(crosses, at, -np.inf), axis=-1), np.nan)
    return np.stack([lo, hi], axis=-1)


def outline_along(
    r_px: FloatArray, spans_px: FloatArray, *, gap_px: float = 0.0
) -> tuple[FloatArray, FloatArray]:
    """(C, K) each, the outline's two edges (px, negative and positive side) along the
    lines across a tube of image radius ``r_px`` (C, K) with disks whose spans on those
    lines are ``spans_px`` (C, K, D, 2): the tube's edges, carried out over every span that
    touches them or lies within ``gap_px`` of them (a wider gap is read as one, the tube's
    edge first)."""
    lo, hi = -np.asarray(r_px, dtype=np.float64), np.asarray(r_px, dtype=np.float64).copy()
    if spans_px.shape[-2] == 0:
        return lo, hi
    start, stop = spans_px[..., 0], spans_px[..., 1]
    # Disks can chain (one span touching the next): three passes carry a chain of three
    # outwards, more than a line across the tube meets.
    for _ in range(3):
        out = (start <= hi[..., None] + gap_px) & (stop > hi[..., None])
        hi = np.maximum(hi, np.max(np.where(out, stop, -np.inf), axis=-1))
        out = (stop >= lo[..., None] - gap_px) & (start < lo[..., None])
        lo = np.minimum(lo, np.min(np.where(out, start, np.inf), axis=-1))
    return lo, hi


# read_disks pools the readings in bins of this length along the tube (mm), a bin kept
# where this many frames read it ...
_BIN_MM = 1.0
_MIN_FRAMES = 3
# ... and finds disks where the profile of the bins' medians rises above the tube's own
# radius (its lower fifth) by at least this fraction of it, at least this many times
# along the tube.
_MIN_RISE = 0.15
_MIN_DISKS = 3
# A disk is a stretch of bins above this fraction of the way from the tube's radius to the
# disks' (the profile's top twentieth), between falls below this lower fraction (so that
# a step's wider part, dipping on a stray reading, stays one stretch); stretches this few
# bins apart are one.
_LEVEL = 0.6
_LOW = 0.3
_GAP_BINS = 2
# A disk's stretch is no longer than this many disk radii: its ellipse, seen at any angle,
# reaches along the tube less than its radius either side, and its thickness less again.
_MAX_LENGTH_RADII = 2.5
# Read so on the half-widths along the curves recorded on 58 rendered sessions
# (`accuracy_table --draw 2`, 409, 433, 439 and 443, and the first 18 disk cases of
# pipeline.synth.variety.draw_cases(seed, 8) from seed 700; 2026-12-06): disks found on
# all 28 sessions that have them (5-12 of 9-17 on four whose curves were off), on none of
# the 30 without (uniform, tapered and stepped tubes, loops among them).


def read_disks(readings: Sequence[tuple[FloatArray, FloatArray]]) -> Disks | None:
    """The spacer disks of the half-widths read along the sample frames' axes (each frame's
    (arc lengths (R,) mm, half-widths (R,) mm) of its two-edge readings, disks included),
    or None where the tube has none.

    A stretch longer than a disk can be is another part of the tube (a step's wider part,
    or a stretch the frames' axes are off on) and left out; one that runs into either end of
    the bins read is a step, a taper or a disk cut short: kept only where it is no longer
    than the others, one disk's worth.
    """
    profile = binned_medians(readings, _BIN_MM, _MIN_FRAMES)
    if profile is None:
        return None
    read = np.flatnonzero(np.isfinite(profile))
    if len(read) < 10:
        return None
    tube, top = np.percentile(profile[read], [20.0, 95.0])
    if top - tube < _MIN_RISE * tube:
        return None
    stretches = [
        (first, last)
        for first, last in _stretches(profile, tube + _LEVEL * (top - tube), tube + _LOW * (top - tube))
        if (last - first + 1) * _BIN_MM <= _MAX_LENGTH_RADII * top
    ]
    if not stretches:
        return None
    lengths = np.array([last - first + 1 for first, last in stretches])
    ends = np.array(
        [first <= read[0] + _GAP_BINS or last >= read[-1] - _GAP_BINS for first, last in stretches]
    )
    if np.count_nonzero(~ends) < _MIN_DISKS:
        return None
    usual = float(np.median(lengths[~ends]))
    kept = [s for s, n, end in zip(stretches, lengths, ends, strict=True) if not end or n <= 1.5 * usual]
    centres = np.array([(first + last + 1) * 0.5 * _BIN_MM for first, last in kept])
    radius = float(np.median([np.nanmax(profile[first : last + 1]) for first, last in kept]))
    return Disks(centres, radius)


def _stretches(profile: FloatArray, level: float, low: float) -> list[tuple[int, int]]:
    """The stretches of ``profile`` (B,) (NaN: not read) above ``level`` as (first, last)
    bins: runs fewer than ``_GAP_BINS`` bins apart, or with no bin read below ``low``
    between them, joined."""
    index = np.flatnonzero(profile > level)
    if len(index) == 0:
        return []
    runs = [[int(index[0]), int(index[0])]]
    for i in index[1:].tolist():
        between = profile[runs[-1][1] + 1 : i]
        if i - runs[-1][1] <= _GAP_BINS + 1 or not np.any(between < low):
            runs[-1][1] = i
        else:
            runs.append([i, i])
    return [(first, last) for first, last in runs]
