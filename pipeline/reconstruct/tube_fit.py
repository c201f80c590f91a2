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
  corrections, none along the tangent; :func:`pipeline.reconstruct.placement.normal_equations`),
  solved a few times (Gauss-Newton).
- Contamination. Where another part of the tube lies across or beside a sample in
  one view (the curve's projection passes near itself: loops, crossings), that
  camera's reading there is dropped; so is a reading whose width is not the
  tube's (wider: another part beside it; narrower: another part's outline over
  it). After each solve, the readings the solution disagrees with (another part
  the curve does not know of) are dropped and the problem solved again. The
  other views, and the smoothness, carry the sample.
- The tip: after each round the curve is extended or trimmed to where the views
  see the tube end (:mod:`pipeline.reconstruct.tube_tip`), its cap the tube's own
  radius at the end (the narrowest readings there, not the disks' or the taper's
  wider ones before it).
- The radius is the median half-width of the clean readings, in mm.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.linalg import solveh_banded

from ..geometry.camera import Camera, project_in_views
from ..geometry.polyline import by_fraction, polyline_arclength, resample_polyline
from .placement import Placement, normal_equations
from .radius_profile import RadiusProfile
from .side_readings import CROWD_MARGIN_PX, SideReadings, consistent_readings, read_sides
from .tube_tip import refit_tip

FloatArray = NDArray[np.float64]

# Distance between the fitted samples along the curve, mm.
FIT_SPACING_MM = 4.0
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
# refit_body: its rounds (each re-reads the images), and its crowding margin
# (see CROWD_MARGIN_PX): where a tip lies against the stem, the stem's
# readings are dropped where the tip's tube comes within 4 px of its own, two
# blurred edges' worth, not one. Measured on 9 rendered loop sessions (r 4-9,
# both rigs): mean error -0.01 to -0.07 mm and p95 -0.05 to -0.18 mm on every
# one against 2 px; 6 px gives the same to 0.03 mm. The same margin in every
# fit_tube round instead sends some frames astray (mid-curve errors of 10-19
# mm): with the tip not yet placed, more readings are dropped in the wrong place.
_BODY_ROUNDS = 2
_BODY_CROWD_MARGIN_PX = 4.0


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
    placement : the last readings at the samples, which tell how firmly they place each
        one (:class:`pipeline.reconstruct.placement.Placement`), or None without readings.
        They stay the fit's where its tip is bent later: the bend moves only the last radii.
    """

    points_mm: FloatArray
    radius_mm: float
    residual_mm: float
    readings: int
    radii_mm: FloatArray | None = None
    placement: Placement | None = None

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
    spacing_mm: float = FIT_SPACING_MM,
    iterations: int = 3,
    smoothness: float = 0.5,
    cap: str = "flat",
    masks: Sequence[NDArray[np.bool_]] | None = None,
    max_length_mm: float = np.inf,
    robust: bool = True,
    seek_radii: float = _FIRST_CORE,
    crowd_margin_px: float = CROWD_MARGIN_PX,
    radii_mm: FloatArray | None = None,
    unseen_length_mm: float = np.nan,
    session_radii: RadiusProfile | None = None,
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
    unseen_length_mm : the curve's length (mm) where no view reads its end (see
        :func:`pipeline.reconstruct.tube_tip.refit_tip`); NaN: as long as it is.
    session_radii : the radius along the tube read on the session's frames, taken
        where no view of this frame reads it (:mod:`pipeline.reconstruct.radius_profile`).

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
            session_radii=session_radii,
        )
        end_radius = float(local[-1])
        if obs.readings >= 6:
            radius = obs.radius_mm
            local = obs.radii_mm
            if np.isfinite(obs.end_radius_mm):
                end_radius = obs.end_radius_mm
            pts = pts + _step(pts, obs, base_fixed=base_fixed, smoothness=smoothness, robust=robust)
        along, radii = polyline_arclength(pts), local
        pts = refit_tip(
            pts,
            cameras,
            contrasts,
            end_radius,
            cap=cap,
            masks=masks,
            max_length_mm=max_length_mm,
            radii_mm=local,
            unseen_length_mm=unseen_length_mm,
        )
    pts = _resampled(pts, spacing_mm)
    local = np.interp(polyline_arclength(pts), along, radii)
    obs = read_sides(pts, cameras, contrasts, local, spacing_mm, session_radii=session_radii)
    if obs.readings == 0:
        return TubeFit(pts, float("nan"), float("nan"), 0)
    placement = Placement(pts, obs, base_fixed=base_fixed, smoothness=smoothness)
    return TubeFit(pts, obs.radius_mm, obs.residual_mm(), obs.readings, obs.radii_mm, placement)


def refit_body(
    curve_mm: FloatArray,
    cameras: Sequence[Camera],
    contrasts: Sequence[NDArray[np.float32]],
    *,
    radius_mm: float,
    hold_from_mm: float,
    base_fixed: bool = True,
    spacing_mm: float = FIT_SPACING_MM,
    iterations: int = _BODY_ROUNDS,
    smoothness: float = 0.5,
) -> FloatArray:
    """The curve before arc length ``hold_from_mm`` fitted again to the sides, the rest held.

    Where a loop's tip lies against its stem, the fit reads the stem's sides
    while its tip is still misplaced: the views where the tip's silhouette
    touches the stem's are not known to be crowded there, and their edges (the
    tip's) pull the stem off its axis. Once the tip is placed (by
    :func:`pipeline.reconstruct.tip_bend.bend_tip_to_pixels`), the stem's readings are taken
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
