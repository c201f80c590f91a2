"""Where each view sees the tube's sides: sub-pixel edge readings along the curve.

At samples along a curve, each camera's grey image is read along the image normal of
the projected curve (:mod:`pipeline.reconstruct.profiles`); the two places where it
crosses half way between the tube's and the background's grey level are the
silhouette's edges. :func:`read_sides` returns them per sample and camera, with the
readings another part of the tube contaminates dropped (:func:`centre_across`,
``crowded``); :func:`consistent_readings` drops those a solution disagrees with.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import Camera
from ..geometry.polyline import (
    by_fraction,
    polyline_arclength,
    resample_polyline,
    unit_tangents,
    vector_norms,
)
from .disks import Disks, outline_along, read_disks, rims, spans_along
from .profiles import (
    median_1d,
    nanmedian_rows,
    percentile_1d,
    project_with_jacobians,
    sample_lines_in,
    side_edges,
    theil_sen_slope,
)
from .radius_profile import RadiusProfile
from .tube_tip import END_SPAN_MM, MIN_SIN_VIEW, tip_zone

FloatArray = NDArray[np.float64]

# Sampling step along the image profiles (px).
_PROFILE_STEP_PX = 0.5
# Two-edge readings a view needs for its own half-width (see read_sides).
_OWN_WIDTH_READINGS = 5
# A radius read along the tube that varies by more than this fraction of its median is
# a tube's own profile (width_ratios): at the true axes of rendered sessions (8 frames
# each, 2026-12-03), uniform tubes' varied by 2-9 % (median 2-5 %), tapered, stepped and
# disk ones' by 20-50 % (median 20-44 %).
_FLAT_PROFILE = 0.15
# Another part of the tube touches a sample's silhouette when the two
# projected tubes come within this many pixels (their edges' blur).
CROWD_MARGIN_PX = 2.0
# A reading wider than this factor times the expected width (+1 px) is contaminated.
_WIDTH_TOLERANCE = 1.3
# The radius along the tube is the median over a sample's readings and those of
# this many samples either side (4 mm apart): spacer disks (2 mm thick, a few
# per 20 mm) and stray readings stay a minority of the window even where it is
# cut short at the tube's ends; a step or taper is followed within ~16 mm.
_PROFILE_HALF_SPAN = 4
# Over the tube's last END_SPAN_MM (the span its end is extrapolated from, see
# pipeline.reconstruct.tube_tip) an edge may sit no farther from the axis than
# this factor times the tube's own radius at the end, on rigs of REDUNDANT_VIEWS or more
# (see _end_limit). Measured on 31 rendered sessions (12 with loops or spacer disks,
# `accuracy_table` draws 2, 13 and 21, the demo; 90 tracked frames each, the true tube end;
# 2026-12-03), without the limit and with it: the three-camera disk sessions' median tips
# 1.38, 1.27, 2.95 against 0.59, 0.89, 2.54 mm (frames more than 2 mm off 29, 24 against
# 8, 1); the 18 three-camera sessions' frames more than 2 mm off 319 against 281, the
# bench's loop's median tip 0.43 against 0.50 mm. On two-camera rigs the limit lost tracks
# (a tapered r 5 tube 1.03 against 1.29 mm mean). 1.2 and 1.15 kept less of the gain.
_END_TOLERANCE = 1.12
# A spacer disk's outline this close to the tube's edge (px) is read as one with it (the
# gap blurred over) ...
_DISK_GAP_PX = 0.5
# ... and this close, the reading says nothing of the tube's own radius.
_DISK_NEAR_PX = 1.5
# Spacing (mm) of the side readings a session's spacer disks are read from (see
# read_radius_profile): a disk 1-4 mm thick seen edge-on is one to four readings.
DISK_SPACING_MM = 1.0
# Rigs of this many views or more read each sample more often than it has unknowns
# across (two): only there may one view's edges be doubted, dropped or outvoted. Two
# views' readings are exactly the two numbers that place each sample.
REDUNDANT_VIEWS = 3


@dataclass(frozen=True, eq=False)
class SideReadings:
    """Side readings at K samples in C cameras; (K, C) arrays unless noted, mm.

    ``left``/``right`` are the silhouette's edges along the image normal (negative
    and positive side), converted to mm at the sample; ``use`` (K, C, 2) says which
    edges are trusted; ``apparent`` (K, C) is each view's own reading of the
    half-width at each sample, which a single trusted edge is moved in by;
    ``radii_mm`` (K,) the radius along the tube (:func:`_radius_profile`);
    ``end_radius_mm`` the tube's own radius at its end (:func:`_end_radius`). ``rows`` (K, C, 3)
    maps a 3-D motion of the sample (mm) to the motion of its projection along
    the normal (mm); ``across`` (K, C, 2) maps a motion of its projection (px) to
    that motion along the normal (mm), or is None. ``widths_mm`` (K, C): the
    half-width of each view's two edges where no other part crowds them (NaN
    elsewhere), which the radius along the tube is read from.
    """

    rows: FloatArray
    left: FloatArray
    right: FloatArray
    use: NDArray[np.bool_]
    radius_mm: float
    apparent: FloatArray
    radii_mm: FloatArray
    across: FloatArray | None = None
    end_radius_mm: float = float("nan")
    widths_mm: FloatArray | None = None

    @property
    def readings(self) -> int:
        return int(self.use.sum())

    def centres(self) -> tuple[FloatArray, FloatArray]:
        """Where each view puts the axis along its normal (mm), and the reading's weight:
        the mid-point of two trusted edges (weight 1), or one trusted edge moved in by
        the view's apparent half-width (weight 1/2: it also carries that one's error)."""
        both = self.use[..., 0] & self.use[..., 1]
        centre = np.where(
            both,
            0.5 * (self.left + self.right),
            np.where(self.use[..., 0], self.left + self.apparent, self.right - self.apparent),
        )
        weight = np.where(both, 1.0, np.where(self.use.any(axis=-1), 0.5, 0.0))
        return centre, weight

    def residual_mm(self) -> float:
        """RMS distance of the trusted edges from the tube's edges at +-radius, mm."""
        gaps = np.concatenate(
            [
                (self.left + self.radii_mm[:, None])[self.use[..., 0]],
                (self.right - self.radii_mm[:, None])[self.use[..., 1]],
            ]
        )
        return float(np.sqrt(np.mean(gaps**2))) if gaps.size else float("nan")


@dataclass(frozen=True, eq=False)
class _CameraEdges:
    """Side readings at K points in C cameras; (C, K) arrays unless noted, lengths in mm
    at each point."""

    px: FloatArray  # (C, K, 2) projected points
    t_hat: FloatArray  # (C, K, 2) unit image tangents
    r_px: FloatArray  # the radius' image size
    rows: FloatArray  # (C, K, 3) d(motion along the normal, mm) / d(point, mm)
    across: FloatArray  # (C, K, 2) d(motion along the normal, mm) / d(projection, px)
    lo: FloatArray  # negative-side edge, mm along the normal
    hi: FloatArray  # positive-side edge
    ok: NDArray[np.bool_]  # both edges found in a usable view
    limit: FloatArray  # farthest an edge may sit from the axis, mm
    floor: FloatArray  # least half-width of a reading of the tube alone, mm
    px_per_mm: FloatArray  # image px per mm across the tube (1 where the view has none)
    # (C, K) a spacer disk carries either edge out: the reading places the axis, but says
    # nothing of the tube's own radius
    on_disk: NDArray[np.bool_]


def _camera_edges(
    pts: FloatArray,
    tangents: FloatArray,
    cameras: Sequence[Camera],
    contrasts: Sequence[NDArray[np.float32]],
    radius_mm: float | FloatArray,
    *,
    core: float = 0.6,
    disks: Disks | None = None,
) -> _CameraEdges:
    """Read the silhouette's two edges across the tube at each point, in each view; with
    ``disks``, each taken against the outline the disks draw on its line (the points being
    the whole axis from the base): an edge a disk carries out reads as the tube's would.

    All views are handled as one (C, K) batch and share one set of profile
    offsets, so that the edge search runs once over all of them (it is a dozen
    numpy calls: per call, not per element, is what costs).
    """
    px, jac = project_with_jacobians(cameras, pts)  # (C, K, 2), (C, K, 2, 3)
    ok = np.isfinite(px).all(axis=-1)
    t_img = np.einsum("ckij,kj->cki", jac, tangents)
    t_len = vector_norms(t_img)
    t_hat = t_img / np.maximum(t_len, 1e-12)[..., None]
    normal = np.stack([-t_hat[..., 1], t_hat[..., 0]], axis=-1)
    row = np.einsum("cki,ckij->ckj", normal, jac)  # px per mm of motion, along the normal
    scale = vector_norms(row)  # px per mm across the tube
    ok &= (scale > 0) & (t_len > MIN_SIN_VIEW * scale)
    r_px = radius_mm * scale
    # A tube wider than the image (a point of a diverging fit near a camera's
    # centre) has no edges in it to read.
    ok &= r_px < np.array([max(cam.size_px) for cam in cameras], dtype=np.float64)[:, None]
    lo: FloatArray = np.zeros(scale.shape)
    hi: FloatArray = np.zeros(scale.shape)
    found: NDArray[np.bool_] = np.zeros(scale.shape, dtype=bool)
    on_disk: NDArray[np.bool_] = np.zeros(scale.shape, dtype=bool)
    if ok.any():
        reach = float(np.max(2.5 * r_px[ok] + 3.0))
        steps = np.arange(-reach, reach + 1e-9, _PROFILE_STEP_PX)
        profiles = sample_lines_in(contrasts, px, normal, steps).reshape(-1, len(steps))
        left, right, both = side_edges(profiles, steps, r_px.ravel(), core=core)
        lo, hi, found = left.reshape(scale.shape), right.reshape(scale.shape), both.reshape(scale.shape)
        if disks is not None:
            spans = spans_along(cameras, rims(pts, polyline_arclength(pts), disks), px, normal)
            outline_lo, outline_hi = outline_along(r_px, spans, gap_px=_DISK_GAP_PX)
            lo, hi = lo - (outline_lo + r_px), hi - (outline_hi - r_px)
            near_lo, near_hi = outline_along(r_px, spans, gap_px=_DISK_NEAR_PX)
            on_disk = (near_lo < -r_px) | (near_hi > r_px)
    safe = np.where(scale > 0, scale, 1.0)
    # An edge may sit no farther from the axis than the radius allows (by 30 %,
    # +0.5 px of edge blur).
    limit = (_WIDTH_TOLERANCE * r_px + 0.5) / safe
    floor = np.maximum(r_px / _WIDTH_TOLERANCE - 0.5, 0.0) / safe
    return _CameraEdges(
        px,
        t_hat,
        r_px,
        row / safe[..., None],
        normal / safe[..., None],
        lo / safe,
        hi / safe,
        ok & found,
        limit,
        floor,
        safe,
        on_disk,
    )


def read_sides(
    pts: FloatArray,
    cameras: Sequence[Camera],
    contrasts: Sequence[NDArray[np.float32]],
    radius_mm: float | FloatArray,
    spacing_mm: float,
    *,
    core: float = 0.6,
    crowd_margin_px: float = CROWD_MARGIN_PX,
    session_radii: RadiusProfile | None = None,
) -> SideReadings:
    """Side readings at the K samples ``pts`` (mm) where the tube's radius is
    ``radius_mm`` (one for all, or (K,) along the tube); ``session_radii``: the radius
    along the tube read on the session's frames, for the stretches no view of this
    frame reads (:func:`_radius_profile`)."""
    tangents = unit_tangents(pts)
    arc = polyline_arclength(pts)
    expected = np.broadcast_to(np.asarray(radius_mm, dtype=np.float64), arc.shape)
    # Samples within a radius of either end see the cap, not the sides: no radius
    # from them; and no reading at all in the tip zone, whose tangent (so its
    # profile's direction) is the least certain: see refit_tip.
    interior = (arc > expected) & (arc < arc[-1] - expected)
    sides_seen = arc < arc[-1] - tip_zone(float(expected[-1]))
    disks = None if session_radii is None else session_radii.disks
    e = _camera_edges(pts, tangents, cameras, contrasts, expected, core=core, disks=disks)
    ok = e.ok & sides_seen  # (C, K)
    apart_mm = 2.5 * float(expected.max()) + spacing_mm
    crowd = _crowded(e.px, e.t_hat, e.r_px, arc, apart_mm, margin_px=crowd_margin_px)
    rows, left, right = e.rows.transpose(1, 0, 2), e.lo.T, e.hi.T
    # A reading narrower than the tube (by the width tolerance) found an edge
    # inside the silhouette: the outline of another part lying over this one.
    narrow = ok & (e.hi - e.lo < 2.0 * e.floor)
    # The radius along the tube from every two-edge reading no other part crowds,
    # whatever its width: the width tests below judge widths by the radius
    # expected, so they would keep a tapered or stepped tube's thinner part from
    # ever being read.
    uncrowded = (ok & ~crowd[..., 0] & ~crowd[..., 1] & ~e.on_disk).T & interior[:, None]
    radii = _radius_profile(arc, 0.5 * (right - left), uncrowded, expected, session_radii)
    # The end's radius from the uncrowded readings no narrower than the tube (a
    # taper's end is), whatever their width above it (see _end_radius).
    end_radius = _end_radius(arc, 0.5 * (right - left), uncrowded & ~narrow.T)
    limit = _end_limit(e, arc, end_radius)
    # A trusted edge is uncrowded on its side and within the limit of the axis
    # (the axis being where the other edge says, if that one is further out).
    use_lo = ok & ~crowd[..., 0] & ~narrow & (-e.lo < limit + np.maximum(0.0, e.hi))
    use_hi = ok & ~crowd[..., 1] & ~narrow & (e.hi < limit + np.maximum(0.0, -e.lo))
    keep = ~(use_lo & use_hi & (e.hi - e.lo > 2.0 * limit))
    use = np.stack([use_lo & keep, use_hi & keep], axis=-1).transpose(1, 0, 2)  # (K, C, 2)
    both = use[..., 0] & use[..., 1] & interior[:, None] & ~e.on_disk.T
    half = 0.5 * (right - left)[both]
    radius = median_1d(half) if half.size >= 3 else float(np.median(expected))
    # One edge places the axis a half-width in from it: the half-width as this
    # view reads it, along the tube in proportion to the radius there.
    ratio = width_ratios(0.5 * (right - left), both, radii, radius)
    return SideReadings(
        rows,
        left,
        right,
        use,
        radius,
        radii[:, None] * ratio[None, :],
        radii,
        e.across.transpose(1, 0, 2),
        end_radius,
        np.where(uncrowded, 0.5 * (right - left), np.nan),
    )


def read_radius_profile(
    tubes: Sequence[tuple[FloatArray, FloatArray, Sequence[NDArray[np.float32]]]],
    cameras: Sequence[Camera],
    spacing_mm: float,
) -> RadiusProfile | None:
    """The tube's radius along it pooled over fitted frames (:class:`RadiusProfile`), with
    its spacer disks if it has any: each frame's axis (K, 3) mm from the base, sampled every
    ~``spacing_mm``, the radius along it (K,) mm and its per camera (H, W) float32
    foreground contrasts. The disks are read from the half-widths every
    ``DISK_SPACING_MM`` (:func:`pipeline.reconstruct.disks.read_disks`), the radius from
    those at the axes' samples with the disks drawn; None where too few frames read either."""
    dense = []
    for axis_mm, radii_mm, contrasts in tubes:
        arc = polyline_arclength(axis_mm)
        n = max(round(float(arc[-1]) / DISK_SPACING_MM) + 1, 2)
        dense.append((resample_polyline(axis_mm, n, arclength_mm=arc), by_fraction(radii_mm, n), contrasts))
    disks = read_disks(side_widths(dense, cameras, DISK_SPACING_MM))
    if disks is None:
        return RadiusProfile.pooled(side_widths(tubes, cameras, spacing_mm))
    drawn = RadiusProfile.of_disks(disks)
    profile = RadiusProfile.pooled(side_widths(tubes, cameras, spacing_mm, drawn))
    return drawn if profile is None else replace(profile, disks=disks)


def side_widths(
    tubes: Sequence[tuple[FloatArray, FloatArray, Sequence[NDArray[np.float32]]]],
    cameras: Sequence[Camera],
    spacing_mm: float,
    session_radii: RadiusProfile | None = None,
) -> list[tuple[FloatArray, FloatArray]]:
    """Each tube's two-edge half-widths (mm) clear of its other parts, with their arc lengths
    from the base (mm), read at its axis' samples, ~``spacing_mm`` apart (:func:`read_sides`;
    tubes as for :func:`read_radius_profile`)."""
    readings = []
    for axis_mm, radii_mm, contrasts in tubes:
        widths = read_sides(
            axis_mm, cameras, contrasts, radii_mm, spacing_mm, session_radii=session_radii
        ).widths_mm
        assert widths is not None  # read_sides reads them
        read = np.isfinite(widths)
        sample, _ = np.nonzero(read)
        readings.append((polyline_arclength(axis_mm)[sample], widths[read]))
    return readings


def width_ratios(
    half_mm: FloatArray, both: NDArray[np.bool_], radii_mm: FloatArray, radius_mm: float
) -> FloatArray:
    """(C,) each view's half-width of the tube per mm of its radius, from the half-widths
    ``half_mm`` (K, C) of its two-edge readings ``both`` (K, C), the radius read along the
    tube ``radii_mm`` (K,) and the tube's median radius ``radius_mm``; 1 for a view with
    fewer than ``_OWN_WIDTH_READINGS`` of them.

    A view's blur and grey levels bias both its edges alike, by up to half a pixel: the
    mid-point of two edges cancels that, one edge moved in by the radius does not, and is
    moved in by the view's own half-width instead. Where the radius read along the tube
    varies by more than ``_FLAT_PROFILE`` of its median (a taper, a step, spacer disks),
    each reading is taken against the radius at its own sample; elsewhere a view's readings
    are pooled against the tube's median radius, which more readings hold steady.
    Pooled on a stepped tube, a view whose two-edge readings all lay on the wider part (the
    thinner part crowded by another in that view) took the thinner part for that much
    wider, and put its one-edge readings there 1.2-1.7 mm off: at the true axis of a random
    shape stepped from 6 to 4.2 mm (``pipeline synth --shape random --seed 12 --profile step
    --arrangement ninety``, frame 20, 2026-12-03), whose frames then came out 0.75 mm off
    in mean instead of 0.19.
    """
    ratio = np.ones(half_mm.shape[1])
    middle = float(np.median(radii_mm)) if len(radii_mm) else 0.0
    local = middle > 0 and float(np.ptp(radii_mm)) > _FLAT_PROFILE * middle
    for j in range(half_mm.shape[1]):
        if local:
            mine = both[:, j] & (radii_mm > 0)
            if np.count_nonzero(mine) >= _OWN_WIDTH_READINGS:
                ratio[j] = median_1d(half_mm[mine, j] / radii_mm[mine])
        else:
            own = half_mm[both[:, j], j]
            if own.size >= _OWN_WIDTH_READINGS and radius_mm > 0:
                ratio[j] = median_1d(own) / radius_mm
    return ratio


# Where another part of the tube hides a stretch of it from every view, the profile there
# is a line across the gap. Keeping the track's profile there instead (the previous frame's,
# on rigs of three cameras or more) was measured (2026-12-03). Tracked from frame 0 with
# the true end, on 32 stepped, tapered and disk sessions of `accuracy_table` draws 2, 7,
# 13, 41, 61, 73 and 91: frames more than 2 mm off 284 -> 263, a stepped r 6 tube hidden
# just past its step (read 5.3 mm there against 4.2) 11 -> 0. Through `accuracy_table` on
# draws 2, 7 and 13 and a fresh draw 97 (the same renders both ways): the three-camera
# frames off 154 -> 160, draw 97's stepped r 7 shape 10 -> 22; carried by the distance
# along the tube rather than by sample fraction, draw 97's three-camera frames off 67 ->
# 83. On two cameras a radius read wrong was carried along as well (a disk tube's mean
# 4.9 -> 7.8 mm). Left out. So was reading and drawing every sample with the median, by
# arc length from the base, of the own profiles of the track's last LENGTH_FRAMES
# unsuspect frames (pipeline.reconstruct.tracking), measured end to end on 58 sessions
# of pipeline.synth.variety.draw_cases(seed, 14), seeds 7000-7010 (90 frames each,
# `process`, 2026-12-04): three-camera frames more than 2 mm off 334 -> 340 (stepped
# tubes 125 -> 123), unflagged 224 -> 240; two-camera stepped tubes 329 -> 389.
def _radius_profile(
    arc_mm: FloatArray,
    half_mm: FloatArray,
    both: NDArray[np.bool_],
    expected_mm: FloatArray,
    session: RadiusProfile | None = None,
) -> FloatArray:
    """(K,) the tube's radius along it (mm), from the half-widths ``half_mm`` (K, C) of
    the two-edge readings ``both`` (K, C) at arc lengths ``arc_mm`` (K,).

    The median of the readings of each sample and its neighbours within
    ``_PROFILE_HALF_SPAN`` samples, in every view (a disk or a stray reading is
    one sample, a taper or a step many); samples without readings take the
    ``session`` profile where it reads them (:mod:`pipeline.reconstruct.radius_profile`),
    else the profile interpolated along the arc, ``expected_mm`` where there is none.
    """
    readings = np.where(both, half_mm, np.nan)
    seen = np.flatnonzero(both.any(axis=1))
    if len(seen) < 3:
        return np.array(expected_mm, dtype=np.float64)
    # NaN-padded windows of the per-view readings: the median of a window is that of
    # all its samples' views (a sample read in more views weighs more).
    span = 2 * _PROFILE_HALF_SPAN + 1
    padded = np.pad(readings, ((_PROFILE_HALF_SPAN, _PROFILE_HALF_SPAN), (0, 0)), constant_values=np.nan)
    windows = np.lib.stride_tricks.sliding_window_view(padded, span, axis=0)  # (K, C, span)
    smoothed = nanmedian_rows(windows[seen].reshape(len(seen), -1))
    profile = np.interp(arc_mm, arc_mm[seen], smoothed)
    if session is None:
        return profile
    pooled = session.at(arc_mm)
    gap = ~both.any(axis=1) & np.isfinite(pooled)
    return np.where(gap, pooled, profile)


def _end_radius(arc_mm: FloatArray, half_mm: FloatArray, both: NDArray[np.bool_]) -> float:
    """The tube's own radius at its end (mm): the lower quartile of the two-edge
    readings ``both`` (K, C) of ``half_mm`` (K, C) over the last window of samples
    read (``2 _PROFILE_HALF_SPAN + 1``), each carried to the end (``arc_mm`` (K,))
    along the tube's taper over twice as many samples; NaN where fewer than three
    samples were read, or the taper carries them to nothing. ``both`` leaves out
    readings narrower than the tube can be (another part's outline over it), which a
    lower quartile would take.

    Not the profile's last value: a window median there leans to the inside of a
    taper (the end is its narrowest part), and spacer disks seen at an angle widen
    most of the silhouette (a disk's ellipse reaches along the tube as far as the
    disk is wide), so that the median half-width is the disks' more than the
    tube's. A round end's cap, which sets where the tip is placed, is the tube's.
    """
    seen = np.flatnonzero(both.any(axis=1))
    if len(seen) < 3:
        return float("nan")
    last = seen[-(2 * _PROFILE_HALF_SPAN + 1) :]
    # The taper: the Theil-Sen slope of the narrowest readings of the samples over twice
    # that window, which the disks' samples (fewer than half) do not move; only
    # a tube narrowing towards its end is carried (one widening there is a disk's or a
    # step's reading, which the lower quartile leaves). A tapered end read without it was
    # 6-7 % too wide (random shapes, 320x240, r 5 and 7.5 mm tapered to 0.6, ten hull
    # starts each): the round cap taken off too long (tips 0.4-0.5 mm short) and the
    # end's choice tilted towards round. On 48 rendered sessions (`accuracy_table --draw
    # 191`, 193, 197, 199, 201 and 203; 8 cases of 90 frames each; 2026-12-05), against
    # the plain lower quartile: three cameras, frames more than 2 mm off 311 either way,
    # flagged 227 -> 295, good frames flagged 137 -> 35 (close calls of the end settled),
    # 14 sessions with the median tip within 0.5 mm instead of 13, but median tips summed
    # 17.91 -> 21.64 mm (spacer-disk sessions, every frame off either way: 1.38 -> 4.80
    # and 4.64 -> 5.55 mm) and mean errors 7.83 -> 8.13 mm; two cameras, mean errors summed
    # 10.90 -> 10.41 mm, median tips 53.2 -> 45.1 mm, frames off 660 -> 693, flagged 510 ->
    # 560, good frames flagged 183 -> 49. Without the two limits (the slope through the
    # last window's per-sample narrowest readings, either sign), three-camera disk tips
    # went 1.38 -> 5.47, 1.98 -> 5.78 and 4.64 -> 9.86 mm.
    span = seen[-4 * _PROFILE_HALF_SPAN - 2 :]
    narrowest = np.where(both[span], half_mm[span], np.inf).min(axis=1)
    taper = theil_sen_slope(arc_mm[span], narrowest)
    slope = min(taper, 0.0) if math.isfinite(taper) else 0.0
    # The steepest taper a tube of this median radius can have: a cone from twice it to
    # nothing over the tube's length. A steeper slope is the readings' scatter (a few
    # samples of a lost fit), not a taper.
    if arc_mm[-1] > 0:
        slope = max(slope, -2.0 * median_1d(half_mm[both]) / float(arc_mm[-1]))
    to_end = arc_mm[last] - arc_mm[-1]  # (W,) <= 0
    radius = percentile_1d((half_mm[last] - slope * to_end[:, None])[both[last]], 0.25)
    return radius if radius > 0 else float("nan")  # carried past nothing: no reading


# The same limit along the whole tube, with the radius profile from each window's shorth
# or lower quartile instead of its median (so that disks raise it less) and a single edge
# held to the limit too, was measured on 13 three-camera disk sessions of `accuracy_table`
# draws 2, 7, 41, 61, 91 and 97 (90 frames each, 2026-12-03): frames more than 2 mm off
# 300 -> 361 (shorth) and 362 (lower quartile). At the true axis of a coiled r 6 tube with
# r 9 disks every 20 mm (draw 97), even at its true radius, readings 3-10 mm from a disk
# put the axis 0.3-0.5 mm off (median): between the disk and the sample the tube turns
# by up to 20 degrees, tilting the disk's ellipse across the sample's profile. Left out:
# a tube whose disks are found has them drawn (pipeline.reconstruct.disks), and this limit
# holds where they are not. Dropping instead every
# reading whose profile line crosses a disk where it reaches past the tube, with the
# disks' true places and sizes from the renderer's ground truth (the best case of a model
# that only masks them), was measured too (2026-12-03): at the true axes of four of those
# sessions (five frames each) the readings left put the axis 0.08-0.24 mm off instead of
# 0.17-0.91 mm, but were a seventh to a half as many; end to end (`process`, 90 frames)
# the 13 sessions' mean error averaged 0.64 against 0.52 mm, median tips 0.84 against
# 1.13 mm, frames off 330 against 300; five two-camera disk sessions 4.2 against 2.9 mm.
def _end_limit(e: _CameraEdges, arc_mm: FloatArray, end_radius_mm: float) -> FloatArray:
    """(C, K) the farthest an edge may sit from the axis (mm): ``e.limit``, and over the
    tube's last ``END_SPAN_MM`` no more than ``_END_TOLERANCE`` times its own radius at
    the end (``end_radius_mm``, +0.5 px of edge blur).

    Spacer disks widen the silhouette by up to their own width: within the usual limit
    (the profile's radius, which they raise, times ``_WIDTH_TOLERANCE``) their
    readings are kept. A disk's ellipse read along a normal that is off by the
    tangent's error has its chord's mid-point off the axis in the same sense (an
    ellipse's chords are bisected on the axis only across its own axes; a
    cylinder's, between two parallel edges, on any line), so that near the tip,
    where nothing past it holds the tangent, a curl feeds itself frame after
    frame. Judged by the tube's own radius there, a disk's readings are dropped.

    Only on rigs of ``REDUNDANT_VIEWS`` or more: on two, a tip left with one view's
    readings is free along the other's normal.
    """
    if not np.isfinite(end_radius_mm) or e.r_px.shape[0] < REDUNDANT_VIEWS:
        return e.limit
    tight = _END_TOLERANCE * end_radius_mm + 0.5 / e.px_per_mm
    near_end = (arc_mm > arc_mm[-1] - END_SPAN_MM)[None, :]
    return np.where(near_end, np.minimum(e.limit, tight), e.limit)


def centre_across(
    point_mm: FloatArray,
    direction: FloatArray,
    cameras: Sequence[Camera],
    contrasts: Sequence[NDArray[np.float32]],
    *,
    radius_mm: float,
) -> FloatArray | None:
    """Move one point across the tube (perpendicular to ``direction``) to the axis.

    For tracking through a crowded stretch of hull: each view whose silhouette
    across the tube at the point has the tube's width (within 30 %) says where the
    axis is along its image normal; the views' least-squares correction, limited
    to the plane perpendicular to ``direction``, moves the point. None when no
    view gives a clean reading.

    Parameters
    ----------
    point_mm, direction : (3,) float64 point and unit tangent, world frame.
    cameras, contrasts : as for :func:`fit_tube`.
    radius_mm : tube radius, mm.
    """
    p = np.asarray(point_mm, dtype=np.float64)[None]
    d = np.asarray(direction, dtype=np.float64)[None]
    a_rows, b_vals = [], []
    e = _camera_edges(p, d, cameras, contrasts, radius_mm)
    for j in range(len(cameras)):
        width = float(e.hi[j, 0] - e.lo[j, 0])
        offset = 0.5 * float(e.lo[j, 0] + e.hi[j, 0])
        # The point is meant to be near the axis already: a reading that puts the
        # axis more than a radius away is of some other part of the tube.
        if (
            e.ok[j, 0]
            and 2.0 * radius_mm / _WIDTH_TOLERANCE < width < 2.0 * e.limit[j, 0]
            and abs(offset) < radius_mm
        ):
            a_rows.append(e.rows[j, 0])
            b_vals.append(offset)
    if not a_rows:
        return None
    # Basis of the plane across the tube: corrections along the tangent are not
    # observed by side readings.
    across = np.linalg.svd(d)[2][1:]  # (2, 3) orthonormal, perpendicular to d
    a = np.asarray(a_rows) @ across.T
    step, *_ = np.linalg.lstsq(a, np.asarray(b_vals), rcond=None)
    move = step @ across
    if not np.linalg.norm(move) <= radius_mm:
        return None
    return np.asarray(p[0] + move)


def _crowded(
    px: FloatArray,
    t_hat: FloatArray,
    r_px: FloatArray,
    arc: FloatArray,
    apart_mm: float,
    *,
    margin_px: float = CROWD_MARGIN_PX,
) -> NDArray[np.bool_]:
    """(C, K, 2) whether another part of the tube (more than ``apart_mm`` away along
    the curve) touches sample k's silhouette on its negative / positive side in view c.

    ``px``, ``t_hat`` (C, K, 2) and ``r_px`` (C, K) per view; ``arc`` (K,) mm. Another
    part at image offset ``delta`` from sample k lies on k's profile line when
    |delta . t_hat_k| is within its own radius (+1.5 px: samples are ~2 px apart
    along it), and touches k's silhouette on one side when delta . n_k is within
    the two radii (+2 px) on that side; a part over k's axis (within 1 px) spoils
    both sides. Parts farther along the profile only affect the background level,
    which the lower quartile ignores.
    """
    # delta . t_k = px_k' . t_k - px_k . t_k: (C, K, K') as one matrix product,
    # without the (C, K, K', 2) offsets.
    along = np.abs(_dot_rows(t_hat, px))
    near = (np.abs(arc[:, None] - arc[None, :]) > apart_mm) & (along < r_px[:, None, :] + 1.5)
    out = np.zeros((*r_px.shape, 2), dtype=bool)
    # Few (c, k, k') pairs are near (none on most frames): the rest only there.
    c, k, other = np.nonzero(near)
    if len(c) == 0:
        return out
    normal = np.stack([-t_hat[..., 1], t_hat[..., 0]], axis=-1)
    across = _dot_rows(normal, px)[c, k, other]
    touch = r_px[c, k] + r_px[c, other] + margin_px
    negative = (across < 1.0) & (across > -touch)
    positive = (across > -1.0) & (across < touch)
    out[c[negative], k[negative], 0] = True
    out[c[positive], k[positive], 1] = True
    return out


def _dot_rows(axes: FloatArray, px: FloatArray) -> FloatArray:
    """(C, K, K') ``(px[c, k'] - px[c, k]) . axes[c, k]`` for (C, K, 2) ``axes`` and ``px``."""
    return np.asarray(axes @ px.transpose(0, 2, 1) - np.einsum("cki,cki->ck", axes, px)[..., None])


def consistent_readings(obs: SideReadings, step: FloatArray) -> SideReadings:
    """``obs`` without the readings the solution ``step`` (K, 3) disagrees with.

    A reading contaminated by another part of the tube that the curve does not
    know of (a part it lacks or has in the wrong place) puts the axis where the
    other views and the neighbouring samples do not: after a first solve its
    residual stands out. Readings off by more than ``OUTLIER_RADII`` radii (or
    ``OUTLIER_SPREAD`` robust standard deviations, if larger) are dropped;
    ``obs`` itself is returned when none is.
    """
    centre, weight = obs.centres()
    residual = np.abs(centre - np.einsum("kci,ki->kc", obs.rows, step))
    used = weight > 0
    if not used.any():
        return obs
    spread = 1.4826 * median_1d(residual[used])
    bad = used & (residual > max(OUTLIER_RADII * obs.radius_mm, OUTLIER_SPREAD * spread))
    if not bad.any():
        return obs
    use = obs.use & ~bad[..., None]
    return replace(obs, use=use)


# A reading whose residual after a first solve exceeds this many radii (or this
# many robust standard deviations of all residuals, if larger) is an outlier.
# The last reading before an end that no view reads decides much of its own place (its
# leverage in the solve, 0.6-0.8 against 0.3-0.5 where three views read the tube), so a
# wrong one leaves little residual and swings the end after it: on the bench's thicker
# loop, started on the true axis, one such reading took the tip 12.9 mm off in two rounds.
# Judging a reading of leverage h above 0.5 by its residual times 0.5 / (1 - h) (towards
# the others' account of its place) kept those ends, and took that loop's frames more
# than 2 mm off 90 -> 75 (900 frames); but over the
# 40 sessions of `accuracy_table --draw 2`, 409, 433, 439 and 443 (90 frames, 2026-12-07),
# frames off went 581 -> 596 and two-camera means summed 14.69 -> 15.80 mm (a tapered shape
# 0.55 -> 1.22), three-camera ones 4.58 -> 4.61: left out.
OUTLIER_RADII = 0.25


OUTLIER_SPREAD = 4.0
