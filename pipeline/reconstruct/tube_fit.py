"""Fit a tube of radius r to the silhouettes, starting from a rough centreline.

The visual hull is larger than the tube, not centred on it when the views are
uneven, and overshoots its end. The fit corrects all three from the grey images
(read by :mod:`pipeline.reconstruct.profiles`):

- Sides. At samples along the curve, each camera's grey image is read along the
  image normal of the projected curve; the two places where it crosses half way
  between the tube's and the background's grey level are the silhouette's edges,
  found to a fraction of a pixel. Their midpoint is where the axis must project.
  The per-camera 2-D offsets become one linear least-squares problem for the 3-D
  corrections of all samples (3 unknowns per sample, a smoothness term on the
  corrections, none along the tangent), solved a few times (Gauss-Newton).
- Contamination. Where another part of the tube lies across or beside a sample in
  one view (the curve's projection passes near itself: loops, crossings), that
  camera's reading there is dropped; so is a reading whose width is not the
  tube's (wider: another part beside it; narrower: another part's outline over
  it). After each solve, the readings the solution disagrees with (another part
  the curve does not know of) are dropped and the problem solved again. The
  other views, and the smoothness, carry the sample.
- The tip: after each round the curve is extended or trimmed to where the views
  see the tube end (:mod:`pipeline.reconstruct.tube_tip`).
- The radius is the median half-width of the clean readings, in mm.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.linalg import solveh_banded

from ..geometry.camera import Camera, project_in_views
from ..geometry.polyline import by_fraction, polyline_arclength, resample_polyline, vector_norms
from .profiles import median_1d, project_with_jacobians, sample_lines_in, side_edges
from .tube_tip import MIN_SIN_VIEW, refit_tip, tip_zone

FloatArray = NDArray[np.float64]

# Sampling step along the image profiles (px).
_PROFILE_STEP_PX = 0.5
# A curve sample explains the silhouette when it is the first to cover this many
# of its pixels in some view; samples of a false bridge own none (measured: 0 on
# every bridge sample, >= 4 on the tube's own samples 3 mm apart).
_MIN_OWNED_PX = 3
# cv2 drawing takes fixed-point coordinates with this many fractional bits.
_DRAW_SHIFT = 4
# How far from the rough curve (in radii) the first round seeks the tube's peak,
# and the later rounds (the curve is on the tube by then).
_FIRST_CORE = 1.6
_CORE = 0.6
# A reading whose residual after a first solve exceeds this many radii (or this
# many robust standard deviations of all residuals, if larger) is an outlier.
_OUTLIER_RADII = 0.25
_OUTLIER_SPREAD = 4.0
# Two-edge readings a view needs for its own half-width (see read_sides).
_OWN_WIDTH_READINGS = 5
# refit_body: its rounds (each re-reads the images), and its crowding margin
# (see _CROWD_MARGIN_PX): where a tip lies against the stem, the stem's
# readings are dropped where the tip's tube comes within 4 px of its own, two
# blurred edges' worth, not one. Measured on 9 rendered loop sessions (r 4-9,
# both rigs): mean error -0.01 to -0.07 mm and p95 -0.05 to -0.18 mm on every
# one against 2 px; 6 px gives the same to 0.03 mm. The same margin in every
# fit_tube round instead sends some frames astray (mid-curve errors of 10-19
# mm): with the tip not yet placed, more readings are dropped in the wrong place.
_BODY_ROUNDS = 2
_BODY_CROWD_MARGIN_PX = 4.0
# Another part of the tube touches a sample's silhouette when the two
# projected tubes come within this many pixels (their edges' blur).
_CROWD_MARGIN_PX = 2.0
# A reading wider than this factor times the expected width (+1 px) is contaminated.
_WIDTH_TOLERANCE = 1.3
# The radius along the tube is the median over a sample's readings and those of
# this many samples either side (4 mm apart): spacer disks (2 mm thick, a few
# per 20 mm) and stray readings stay a minority of the window even where it is
# cut short at the tube's ends; a step or taper is followed within ~16 mm.
_PROFILE_HALF_SPAN = 4


@dataclass(frozen=True, eq=False)
class TubeFit:
    """Result of :func:`fit_tube`.

    Attributes
    ----------
    points_mm : (K, 3) float64 fitted axis samples, base -> tip, world frame, mm.
    radius_mm : tube radius from the silhouette widths (median), NaN if no clean reading.
    residual_mm : RMS distance (mm) between the observed silhouette edges and the
        fitted tube's edges, over all clean readings; NaN if none.
    readings : number of clean (sample, camera) readings used.
    radii_mm : (K,) float64 the radius along the tube at each sample (the silhouette's
        half-widths near it, see :func:`_radius_profile`), or None without readings.
    """

    points_mm: FloatArray
    radius_mm: float
    residual_mm: float
    readings: int
    radii_mm: FloatArray | None = None

    @property
    def end_radius_mm(self) -> float:
        """The radius at the tip (the tube may taper), mm."""
        return float(self.radii_mm[-1]) if self.radii_mm is not None else self.radius_mm


def foreground_contrast(
    image: NDArray[np.uint8], *, polarity: str, background: NDArray[np.uint8] | None = None
) -> NDArray[np.float32]:
    """(H, W) float32 "how much foreground" image: higher on the tube.

    ``|image - background|`` when a background is given, else the grey level
    negated for a dark tube (``polarity == "dark"``) or as is for a bright one.
    """
    img = image.astype(np.float32)
    if background is not None:
        return np.abs(img - background.astype(np.float32))
    return (255.0 - img) if polarity == "dark" else img


def fit_tube(
    curve_mm: FloatArray,
    cameras: Sequence[Camera],
    contrasts: Sequence[NDArray[np.float32]],
    *,
    radius_mm: float,
    base_fixed: bool = True,
    spacing_mm: float = 4.0,
    iterations: int = 3,
    smoothness: float = 0.5,
    cap: str = "flat",
    masks: Sequence[NDArray[np.bool_]] | None = None,
    max_length_mm: float = np.inf,
    robust: bool = True,
    seek_radii: float = _FIRST_CORE,
    crowd_margin_px: float = _CROWD_MARGIN_PX,
    radii_mm: FloatArray | None = None,
) -> TubeFit:
    """Move ``curve_mm`` so that the tube around it projects onto every silhouette.

    Parameters
    ----------
    curve_mm : (M, 3) float64 rough axis ordered base -> tip, world frame, mm.
    cameras : the calibrated cameras, in the order of ``contrasts``.
    contrasts : per camera (H, W) float32 from :func:`foreground_contrast`.
    radius_mm : first guess of the tube radius, mm; re-estimated as the fit goes.
    base_fixed : keep the first point where it is (the known mount point).
    spacing_mm : distance between fitted samples along the curve.
    iterations : Gauss-Newton rounds (each re-reads the images).
    smoothness : weight of the second difference of the corrections, relative to
        one camera's reading of one sample.
    cap : shape of the tube's end, "flat" or "round" (a hemisphere): how far its silhouette
        reaches past the axis' end.
    masks : per camera (H, W) bool silhouettes, if known: they let a view whose
        end is hidden in another part of the tube still place it (see
        :func:`pipeline.reconstruct.tube_tip.refit_tip`).
    max_length_mm : the tip is never moved past this arc length (the hull's
        end: the tube lies inside the hull).
    robust : after each solve, drop the readings it disagrees with and solve
        again (see :func:`consistent_readings`).
    seek_radii : how far from ``curve_mm`` (in radii) the first round seeks the
        tube's peak: farther for a rough curve from the hull than for a
        tracked prediction.
    crowd_margin_px : a reading is dropped where another part's projected tube
        comes within this many pixels of the sample's (see :func:`_crowded`).
    radii_mm : (M,) first guess of the radius at each sample of ``curve_mm``, mm
        (a tapered or stepped tube); default ``radius_mm`` everywhere. Re-estimated
        as the fit goes, and returned as ``TubeFit.radii_mm``.

    Returns
    -------
    :class:`TubeFit`.
    """
    pts = np.asarray(curve_mm, dtype=np.float64)
    radius = float(radius_mm)
    # The radius along the tube, as (arc length, radius) samples; resampled with the curve.
    along = polyline_arclength(pts)
    if radii_mm is None:
        radii = np.full(len(pts), radius)
    else:
        # Given along the curve by sample (a bent tip may have added or dropped samples).
        radii = by_fraction(np.asarray(radii_mm, dtype=np.float64), len(pts))
    for i in range(iterations):
        pts = _resampled(pts, spacing_mm)
        arc = polyline_arclength(pts)
        local = np.interp(arc, along, radii)
        # The first round looks for the tube's peak within 1.6 radii of the
        # rough curve (the march may be a few mm off in crowded hull), later
        # rounds within 0.6 (the curve is on the tube by then).
        obs = read_sides(
            pts,
            cameras,
            contrasts,
            local,
            spacing_mm,
            core=seek_radii if i == 0 else _CORE,
            crowd_margin_px=crowd_margin_px,
        )
        if obs.readings >= 6:
            radius = obs.radius_mm
            local = obs.radii_mm
            pts = pts + _step(pts, obs, base_fixed=base_fixed, smoothness=smoothness, robust=robust)
        along, radii = polyline_arclength(pts), local
        pts = refit_tip(
            pts, cameras, contrasts, float(local[-1]), cap=cap, masks=masks, max_length_mm=max_length_mm
        )
    pts = _resampled(pts, spacing_mm)
    obs = read_sides(pts, cameras, contrasts, np.interp(polyline_arclength(pts), along, radii), spacing_mm)
    if obs.readings == 0:
        return TubeFit(pts, float("nan"), float("nan"), 0)
    return TubeFit(pts, obs.radius_mm, obs.residual_mm(), obs.readings, obs.radii_mm)


def refit_body(
    curve_mm: FloatArray,
    cameras: Sequence[Camera],
    contrasts: Sequence[NDArray[np.float32]],
    *,
    radius_mm: float,
    hold_from_mm: float,
    base_fixed: bool = True,
    spacing_mm: float = 4.0,
    iterations: int = _BODY_ROUNDS,
    smoothness: float = 0.5,
) -> FloatArray:
    """The curve before arc length ``hold_from_mm`` fitted again to the sides, the rest held.

    Where a loop's tip lies against its stem, the fit reads the stem's sides
    while its tip is still misplaced: the views where the tip's silhouette
    touches the stem's are not known to be crowded there, and their edges (the
    tip's) pull the stem off its axis. Once the tip is placed (by
    :func:`pipeline.reconstruct.tube_tip.bend_tip_to_pixels`), the stem's readings are taken
    again along the whole curve, so that the crowding test sees where the tip
    lies, and the stem is moved by them, its base and the curve past
    ``hold_from_mm`` held.

    Parameters
    ----------
    curve_mm : (M, 3) float64 axis, base -> tip, world frame, mm.
    cameras, contrasts : as for :func:`fit_tube`.
    radius_mm : tube radius, mm.
    hold_from_mm : arc length (mm) from which the curve is held as it is.

    Returns
    -------
    (K, 3) float64 axis, resampled every ~``spacing_mm``; the same end.
    """
    pts = np.asarray(curve_mm, dtype=np.float64)
    pts = _resampled(pts, spacing_mm)
    held = polyline_arclength(pts) >= hold_from_mm
    for _ in range(iterations):
        obs = read_sides(
            pts, cameras, contrasts, radius_mm, spacing_mm, crowd_margin_px=_BODY_CROWD_MARGIN_PX
        )
        if obs.readings < 6:
            break
        pts = pts + _step(pts, obs, base_fixed=base_fixed, smoothness=smoothness, held=held)
    return pts


def _step(
    pts: FloatArray,
    obs: SideReadings,
    *,
    base_fixed: bool,
    smoothness: float,
    robust: bool = True,
    held: NDArray[np.bool_] | None = None,
) -> FloatArray:
    """(K, 3) Gauss-Newton correction of the samples ``pts`` (mm) from the readings
    ``obs``; ``robust``: solved again without the readings the first solve
    disagrees with (see :func:`consistent_readings`)."""
    step = _solve_corrections(pts, obs, base_fixed=base_fixed, smoothness=smoothness, held=held)
    kept = consistent_readings(obs, step) if robust else obs
    if kept is not obs:
        step = _solve_corrections(pts, kept, base_fixed=base_fixed, smoothness=smoothness, held=held)
    return step


def trim_unexplained_tail(
    curve_mm: FloatArray,
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.bool_]],
    *,
    radius_mm: float,
    min_pixels: int = _MIN_OWNED_PX,
) -> FloatArray:
    """Cut the curve after the last point that explains silhouette pixels.

    Every voxel of a false bridge projects inside every silhouette, so a march that
    runs past the tip into one is consistent with each mask; but the tube it adds
    covers no silhouette pixel that the curve before it does not already cover.
    Each pixel is owned by the first sample (from the base) whose disc (the tube's
    projected radius + 0.5 px) covers it; the curve ends at the last sample owning
    at least ``min_pixels`` pixels in some view.

    Parameters
    ----------
    curve_mm : (M, 3) float64 ordered base -> tip, world frame, mm.
    cameras, masks : the cameras and their (H, W) bool silhouettes.
    radius_mm : tube radius, mm.

    Returns
    -------
    (M', 3) float64, M' <= M: a prefix of ``curve_mm``.
    """
    pts = np.asarray(curve_mm, dtype=np.float64)
    m = len(pts)
    owned = np.zeros(m, dtype=np.int64)
    one = 1 << _DRAW_SHIFT
    for cam, mask, px in zip(cameras, masks, project_in_views(cameras, pts), strict=True):
        owner = np.zeros(mask.shape, np.int32)
        depth = cam.to_camera(pts)[:, 2]
        focal = cam.focal_px
        ok = np.isfinite(px).all(axis=1) & (depth > 0)
        # Only the samples in view are drawn: the others' centres are any integers.
        centres = np.round(np.where(ok[:, None], px, 0.0) * one).astype(np.int64)
        radii = np.round((focal * radius_mm / np.where(ok, depth, 1.0) + 0.5) * one).astype(np.int64)
        # Drawn from the tip back, so the sample nearest the base wins each pixel.
        drawn = zip(ok.tolist(), centres.tolist(), radii.tolist(), strict=True)
        for k, (seen, (cx, cy), r) in reversed(list(enumerate(drawn))):
            if seen:
                cv2.circle(owner, (cx, cy), r, k + 1, -1, cv2.LINE_8, _DRAW_SHIFT)
        counts = np.bincount(owner[mask], minlength=m + 1)[1:]
        owned = np.maximum(owned, counts)
    needed = np.nonzero(owned >= min_pixels)[0]
    last = int(needed[-1]) if len(needed) else m - 1
    return pts[: max(last + 1, 2)]


def _sample_count(pts: FloatArray, spacing_mm: float, *, arclength_mm: FloatArray | None = None) -> int:
    arc = polyline_arclength(pts) if arclength_mm is None else arclength_mm
    return max(6, round(float(arc[-1]) / spacing_mm) + 1)


def _resampled(pts: FloatArray, spacing_mm: float) -> FloatArray:
    """(M, 3) polyline resampled every ~``spacing_mm`` (its arc length computed once)."""
    arc = polyline_arclength(pts)
    return resample_polyline(pts, _sample_count(pts, spacing_mm, arclength_mm=arc), arclength_mm=arc)


def _tangents(pts: FloatArray) -> FloatArray:
    # np.gradient's own arithmetic (central differences / 2, one-sided at the
    # ends), without its per-call overhead.
    d = np.empty_like(pts)
    d[1:-1] = (pts[2:] - pts[:-2]) / 2.0
    d[0] = pts[1] - pts[0]
    d[-1] = pts[-1] - pts[-2]
    return d / np.maximum(vector_norms(d)[:, None], 1e-12)


@dataclass(frozen=True, eq=False)
class SideReadings:
    """Side readings at K samples in C cameras; (K, C) arrays unless noted, mm.

    ``left``/``right`` are the silhouette's edges along the image normal (negative
    and positive side), converted to mm at the sample; ``use`` (K, C, 2) says which
    edges are trusted; ``apparent`` (K, C) is each view's own reading of the
    half-width at each sample, which a single trusted edge is moved in by;
    ``radii_mm`` (K,) the radius along the tube (:func:`_radius_profile`). ``rows`` (K, C, 3)
    maps a 3-D motion of the sample (mm) to the motion of its projection along
    the normal (mm); ``across`` (K, C, 2) maps a motion of its projection (px) to
    that motion along the normal (mm), or is None.
    """

    rows: FloatArray
    left: FloatArray
    right: FloatArray
    use: NDArray[np.bool_]
    radius_mm: float
    apparent: FloatArray
    radii_mm: FloatArray
    across: FloatArray | None = None

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


def _camera_edges(
    pts: FloatArray,
    tangents: FloatArray,
    cameras: Sequence[Camera],
    contrasts: Sequence[NDArray[np.float32]],
    radius_mm: float | FloatArray,
    *,
    core: float = 0.6,
) -> _CameraEdges:
    """Read the silhouette's two edges across the tube at each point, in each view.

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
    lo: FloatArray = np.zeros(scale.shape)
    hi: FloatArray = np.zeros(scale.shape)
    found: NDArray[np.bool_] = np.zeros(scale.shape, dtype=bool)
    if ok.any():
        reach = float(np.max(2.5 * r_px[ok] + 3.0))
        steps = np.arange(-reach, reach + 1e-9, _PROFILE_STEP_PX)
        profiles = sample_lines_in(contrasts, px, normal, steps).reshape(-1, len(steps))
        left, right, both = side_edges(profiles, steps, r_px.ravel(), core=core)
        lo, hi, found = left.reshape(scale.shape), right.reshape(scale.shape), both.reshape(scale.shape)
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
    )


def read_sides(
    pts: FloatArray,
    cameras: Sequence[Camera],
    contrasts: Sequence[NDArray[np.float32]],
    radius_mm: float | FloatArray,
    spacing_mm: float,
    *,
    core: float = 0.6,
    crowd_margin_px: float = _CROWD_MARGIN_PX,
) -> SideReadings:
    """Side readings at the K samples ``pts`` (mm) where the tube's radius is
    ``radius_mm`` (one for all, or (K,) along the tube)."""
    c = len(cameras)
    tangents = _tangents(pts)
    arc = polyline_arclength(pts)
    expected = np.broadcast_to(np.asarray(radius_mm, dtype=np.float64), arc.shape)
    # Samples within a radius of either end see the cap, not the sides: no radius
    # from them; and no reading at all in the tip zone, whose tangent (so its
    # profile's direction) is the least certain: see refit_tip.
    interior = (arc > expected) & (arc < arc[-1] - expected)
    sides_seen = arc < arc[-1] - tip_zone(float(expected[-1]))
    e = _camera_edges(pts, tangents, cameras, contrasts, expected, core=core)
    ok = e.ok & sides_seen  # (C, K)
    apart_mm = 2.5 * float(expected.max()) + spacing_mm
    crowd = _crowded(e.px, e.t_hat, e.r_px, arc, apart_mm, margin_px=crowd_margin_px)
    # A trusted edge is uncrowded on its side and within the limit of the axis
    # (the axis being where the other edge says, if that one is further out).
    use_lo = ok & ~crowd[..., 0] & (-e.lo < e.limit + np.maximum(0.0, e.hi))
    use_hi = ok & ~crowd[..., 1] & (e.hi < e.limit + np.maximum(0.0, -e.lo))
    # A reading narrower than the tube (by the same tolerance) found an edge
    # inside the silhouette: the outline of another part lying over this one.
    keep = ~(ok & (e.hi - e.lo < 2.0 * e.floor))
    use_lo &= keep
    use_hi &= keep
    keep = ~(use_lo & use_hi & (e.hi - e.lo > 2.0 * e.limit))
    use = np.stack([use_lo & keep, use_hi & keep], axis=-1).transpose(1, 0, 2)  # (K, C, 2)
    rows, left, right = e.rows.transpose(1, 0, 2), e.lo.T, e.hi.T
    both = use[..., 0] & use[..., 1] & interior[:, None]
    half = 0.5 * (right - left)[both]
    radius = median_1d(half) if half.size >= 3 else float(np.median(expected))
    # The radius along the tube from every two-edge reading no other part crowds,
    # whatever its width: the width tests above judge widths by the radius
    # expected, so they would keep a tapered or stepped tube's thinner part from
    # ever being read.
    uncrowded = (ok & ~crowd[..., 0] & ~crowd[..., 1]).T & interior[:, None]
    radii = _radius_profile(arc, 0.5 * (right - left), uncrowded, expected)
    # One edge places the axis a half-width in from it: the half-width as this
    # view reads it (its blur and grey levels bias both edges alike, by up to
    # half a pixel, which the mid-point of two edges cancels and one edge does
    # not), where it has enough two-edge readings to say; along the tube, in
    # proportion to the radius there.
    ratio = np.ones(c)
    for j in range(c):
        own = 0.5 * (right[:, j] - left[:, j])[both[:, j]]
        if own.size >= _OWN_WIDTH_READINGS and radius > 0:
            ratio[j] = median_1d(own) / radius
    return SideReadings(
        rows, left, right, use, radius, radii[:, None] * ratio[None, :], radii, e.across.transpose(1, 0, 2)
    )


def _radius_profile(
    arc_mm: FloatArray, half_mm: FloatArray, both: NDArray[np.bool_], expected_mm: FloatArray
) -> FloatArray:
    """(K,) the tube's radius along it (mm), from the half-widths ``half_mm`` (K, C) of
    the two-edge readings ``both`` (K, C) at arc lengths ``arc_mm`` (K,).

    The median of the readings of each sample and its neighbours within
    ``_PROFILE_HALF_SPAN`` samples, in every view (a disk or a stray reading is
    one sample, a taper or a step many); samples without readings take the
    profile interpolated along the arc, ``expected_mm`` where there is none.
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
    smoothed = np.nanmedian(windows[seen].reshape(len(seen), -1), axis=1)
    return np.interp(arc_mm, arc_mm[seen], smoothed)


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
    margin_px: float = _CROWD_MARGIN_PX,
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
    residual stands out. Readings off by more than ``_OUTLIER_RADII`` radii (or
    ``_OUTLIER_SPREAD`` robust standard deviations, if larger) are dropped;
    ``obs`` itself is returned when none is.
    """
    centre, weight = obs.centres()
    residual = np.abs(centre - np.einsum("kci,ki->kc", obs.rows, step))
    used = weight > 0
    if not used.any():
        return obs
    spread = 1.4826 * median_1d(residual[used])
    bad = used & (residual > max(_OUTLIER_RADII * obs.radius_mm, _OUTLIER_SPREAD * spread))
    if not bad.any():
        return obs
    use = obs.use & ~bad[..., None]
    return replace(obs, use=use)


@lru_cache(maxsize=256)
def _second_difference_gram(k: int) -> FloatArray:
    """(3, k) diagonals 0, 1, 2 of D^T D, D the (k-2, k) second difference;
    entry [d, j] is (D^T D)[j - d, j]. Cached per k (read-only): curves keep their
    sample count from frame to frame."""
    stencil = np.array([1.0, -2.0, 1.0])
    out = np.zeros((3, k))
    rows = np.arange(k - 2)
    for p in range(3):
        for q in range(p, 3):
            np.add.at(out[q - p], rows + q, stencil[p] * stencil[q])
    out.flags.writeable = False
    return out


def _solve_corrections(
    pts: FloatArray,
    obs: SideReadings,
    *,
    base_fixed: bool,
    smoothness: float,
    held: NDArray[np.bool_] | None = None,
) -> FloatArray:
    """(K, 3) corrections: least squares over all clean readings, with smooth corrections.

    ``base_fixed`` holds the first sample where it is, ``held`` (K,) any others
    (their corrections are 0; the smoothness still joins their neighbours to them).
    """
    band, g = normal_equations(pts, obs, base_fixed=base_fixed, smoothness=smoothness, held=held)
    return np.asarray(solveh_banded(band, g)).reshape(len(pts), 3)


# The normal equations' upper bandwidth: a sample couples with the two either side
# of it through the second difference, 3 * 2 + 2 entries above the diagonal.
BAND_UPPER = 8


def normal_equations(
    pts: FloatArray,
    obs: SideReadings,
    *,
    base_fixed: bool,
    smoothness: float,
    held: NDArray[np.bool_] | None = None,
) -> tuple[FloatArray, FloatArray]:
    """The normal equations of :func:`_solve_corrections`: LAPACK's upper band
    (BAND_UPPER + 1, 3K) of the (3K, 3K) matrix and the (3K,) right-hand side, for the
    corrections of the K samples ``pts`` (mm) from the readings ``obs``. A held sample's
    rows and columns are the identity's and its right-hand side 0."""
    k = len(pts)
    tangents = _tangents(pts)
    centre, w = obs.centres()
    # Normal equations, block-diagonal data part: sum_j w a a^T and sum_j w a b.
    blocks = np.einsum("kc,kci,kcj->kij", w, obs.rows, obs.rows)
    rhs = np.einsum("kc,kci,kc->ki", w, obs.rows, centre)
    # Motion along the tangent is not observed by the sides: hold it (weight 1),
    # plus a tiny damping so that a sample with no reading stays solvable.
    blocks += tangents[:, :, None] * tangents[:, None, :] + 1e-3 * np.eye(3)
    # The system is banded: store it as LAPACK's upper band and solve it in O(K)
    # instead of densely.
    n, upper = 3 * k, BAND_UPPER
    band = np.zeros((upper + 1, n))
    for a in range(3):
        for b in range(a, 3):
            band[upper + a - b, b::3] += blocks[:, a, b]  # columns 3 i + b
    if k >= 3:
        # Second-difference penalty D^T D on each coordinate: the pentadiagonal
        # stencil (1, -4, 6, -4, 1) inside, trimmed at the ends.
        d2tdd = _second_difference_gram(k)  # diagonals 0, 1, 2 of D^T D
        for off in range(3):
            # Columns 3 i + a (i >= off) of that band row, all three coordinates at once.
            band[upper - 3 * off].reshape(k, 3)[off:] += smoothness * d2tdd[off, off:, None]
    g = rhs.reshape(-1)
    pinned = np.zeros(k, dtype=bool) if held is None else np.array(held, dtype=bool)
    pinned[0] |= base_fixed
    for i in np.flatnonzero(pinned):
        # Pin sample i: its rows and columns become the identity.
        for row in range(3 * i, 3 * i + 3):
            for d in range(1, min(upper, n - 1 - row) + 1):
                band[upper - d, row + d] = 0.0  # row, right of the diagonal
            for d in range(1, min(upper, row) + 1):
                band[upper - d, row] = 0.0  # column, above the diagonal
            band[upper, row] = 1.0
        g[3 * i : 3 * i + 3] = 0.0
    return band, g
