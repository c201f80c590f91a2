"""Per-frame quality figures, computed without ground truth.

A user flags a frame by these: how many voxels the hull holds, how well the
reconstructed tube re-projects onto each silhouette (IoU per camera), the RMS
residual of the tube fit, and the tube radius read from the silhouettes (a radius
far from the robot's, or a low IoU, says the frame is not to be trusted).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..geometry.camera import Camera, project_in_views
from ..geometry.polyline import (
    polyline_arclength,
    resample_polyline,
    self_intersects,
    vector_norms,
)
from ..session.settings import Workspace
from .disks import Disks, rim_pixels, rims
from .tube_drawing import DRAW_SHIFT, DRAWABLE_PX, Window, fill_hull, pixel_coverages

FloatArray = NDArray[np.float64]

# Below this IoU in some camera a frame's curve is doubtful. Measured on 27 synthetic
# sessions (every shape, both rigs, tube radii 4-9 mm, 2-4 cameras, 320-640 px wide) and
# their re-encodings: the worst camera of a good frame scores >= 0.78; frames tens of mm
# off (a threshold on the wrong side of the tube's grey level, Otsu splitting the
# background, 160x120 images) score 0.003-0.38, a few up to 0.69.
DOUBTFUL_IOU = 0.7

# A frame is suspect (see suspect_reason) where its tube leaves more than this
# fraction of some silhouette unexplained (misfit_fractions), beyond what its track's
# frames usually leave (pipeline.reconstruct.tracking.usual_misfit: spacer disks the tube
# is drawn without leave 1-2.5 % of every frame). On two seeded draws
# (`accuracy_table --draw 2 --cases 10 --frames 150` and `--draw 7 --cases 8 --frames
# 120`, 2026-12-02) that took the three-camera good frames flagged from 88 of 549 to 81
# and from 29 of 415 to 7, and their frames more than 2 mm off flagged from 160 of 201
# to 160 and from 38 of 65 to 37. The usual share itself is no sign of a wrong curve:
# flagging every frame of a track whose frames usually leave over 1 % unexplained (the
# robot has parts the drawn tube lacks), on the 19 spacer-disk sessions of `accuracy_table`
# draws 2, 191-223 and 307 (`process`, 90-150 frames, 2026-12-05), flagged 6 more of 318
# three-camera frames more than 2 mm off (299 were flagged: the smoothed curve's test
# catches most) at 53 more of 222 good ones, and on two cameras 81 more of 940 off at 64
# more of 290 good ...
SUSPECT_MISFIT = 0.02
# A pixel of the drawn tube off a view's silhouette is stray (a misfit) only where the
# grey levels show less than this much of it covered (pipeline.reconstruct.tube_drawing
# .pixel_coverages): a thin or faint part of the tube that the threshold lost in one
# view, over a background nearly as bright, is still the tube. On 31 rendered sessions
# (`accuracy_table` draws 2, 7 and 11, the demo, four loops; 150 frames, 2026-12-02),
# against counting every such pixel: frames fitted from the hull again 610 -> 454 (a lost
# track), mean error averaged over the sessions 0.642 -> 0.610 mm, frames > 2 mm off 984 ->
# 927, good frames flagged 203 -> 135 (a round-ended loop tapered to a 2.7 mm end: mean
# 0.46 -> 0.27 mm; a thin stepped tube: 52 -> 5 flagged); a bar of 0.25 did less (162
# flagged). The initialiser's own tests between its hypotheses
# (pipeline.reconstruct.tube_scores.worst_misfit) count every such pixel: reading the grey
# levels there too changed one of the 31 sessions, by little.
STRAY_COVERAGE = 0.1
# ... where two of its parts come closer than this many radii (a tube cannot
# pass through itself) ...
SUSPECT_CLOSEST_RADII = 1.5
# ... where it lies farther than this many radii from its track's prediction, judged
# only where the prediction carries the track's velocity
# (pipeline.reconstruct.tracking.velocity_pair): after a suspect frame the prediction
# holds the last curve still and misses a moving tube by a frame's motion, so that a
# sweep of a few radii a frame was flagged every other frame. On 46 three-camera
# sessions (`accuracy_table` draws 2, 7, 13, 41, 61, 73 and 103 and 14 cases of draw 91,
# two coils made from draw 97's disk case, the demo; 90 frames each, 2026-12-03),
# against judging every frame after an unsuspect one: good frames flagged for a jump 11
# against 39 (all reasons 245 against 263 of ~3,100), frames more than 2 mm off 370
# against 377, 179 of them flagged against 176. The radii count beyond how far the
# track's last frames each lay from their own prediction (tracking.prediction_miss_mm): a
# tube that speeds up or turns misses a constant-velocity prediction by about as much
# each frame. Against the radii alone, on 116 sessions (`accuracy_table` draws with and
# without spacer disks, 16 `synth --frames 20` and `--frames 40` renders whose tube sweeps
# and turns by up to a radius a frame; 90 frames, 2026-12-05): good frames flagged 185 ->
# 165 of ~7,880, frames more than 2 mm off flagged 600 -> 611 of ~1,600 (docs/accuracy.md) ...
SUSPECT_JUMP_RADII = 1.0
# ... or where its length is more than this far from the length its track predicts
# (pipeline.reconstruct.tracking.predict_length): a tip cut short or run on along its own
# course changes the length by as much as it puts the tip off. On two seeded draws
# (`accuracy_table --draw 2 --cases 10 --frames 150` and `--draw 7 --cases 8 --frames
# 120`, 2026-12-02) the flag names 46 and 44 % of the frames more than 2 mm off, and
# 14.1 and 15.4 % of the others; a 2.5 mm bar names more of both (52 and 16 % on the
# first draw), and a length change of 3 % since the frame before far fewer of the
# frames off (28-29 %; 7.2 and 14.5 % of the others).
SUSPECT_LENGTH_MM = 3.0
# After the last frame, a frame is also suspect where its curve lies farther than this
# from the session's smoothed one (off_smoothed): the smoothed curve is the frame's
# neighbours' account of it, and a curve that far from it is more than 2 mm off itself
# or beside neighbours that are. On two seeded draws (`accuracy_table --draw 2 --cases 10
# --frames 150` and `--draw 7 --cases 8 --frames 120`, 2026-12-02) it takes the share of
# the three-camera cases' frames more than 2 mm off that are flagged from 15 and 19 % (the
# signs above alone) to 31 and 59 %, and of their other frames from 12.6 and 6.7 % to 14.6
# and 7.0 %. On all the cases, whose two-camera ones hold long stretches of wrong frames,
# beside which the smoothed curve is off too: 43 and 44 % to 65 and 60 %, 14.1 and 15.6 %
# to 24.8 and 17.4 %. 1.5 and 1 mm bars name more of both.
SUSPECT_SMOOTHED_MM = 2.0
# After the last frame, too, where the run's curves agree on the tube's length (half of
# them within this of their median: a backbone that keeps its length), a frame whose
# length lies more than SUSPECT_LENGTH_MM from that median is suspect (off_length): a
# tip cut short or run on, or two views' depth taken wrong by a drift too slow for the
# track's own length to notice. A robot whose length changes through the run (one that
# extends) has no one length: none is judged so. On the 72 sessions of `accuracy_table`
# draws 2, 409, 433, 439, 443, 701, 703, 709 and 711 (8 cases, 90 frames, 2026-12-06),
# it flagged 36 more of the 1,376 frames more than 2 mm off (1,262 -> 1,298) and none
# more of the 5,104 good ones; at 1 mm of agreement 25 more, at 2 mm from the median
# (1.5 of agreement) 58 and 7.
RUN_LENGTH_AGREE_MM = 1.5

# cv2 drawing takes fixed-point coordinates with this many fractional bits.
_SHIFT = 4
# Spacing of the discs that make up the drawn tube, as a fraction of the radius:
# discs closer than r/2 leave no visible scallops between them.
_DISC_SPACING = 0.5


# A tube fewer pixels across than this in a camera's images is too thin for a threshold
# to hold whole: its edges blur over a pixel or two. On `synth --radius-mm R --frames 60
# --seed 3` (2026-12-06): 1.4 px across (R = 1), 30 frames empty (one camera saw nothing)
# and 12 failed; 1.7 px (R = 1.5), every frame ok but 21 doubtful in one camera; 2.4 px
# (R = 2) and wider, curves as close as the thicker tubes' (0.11 mm mean).
THIN_TUBE_PX = 2.0

# A session's tube fits explain its views where their edges lie near a tube whose radius
# varies smoothly along it: the fit's residual (the RMS distance of the trusted edges from
# the tube's, FrameResult.fit_residual_mm) is the edges' own noise. Where, in median over
# the ok frames, it exceeds both of these (in pixels of the images, and as a share of the
# tube's radius), the robot has parts the tube does not draw (a gripper, spacer disks not found), whose
# edges pull the fit, or the cameras disagree, and the summary says so. On the 40 sessions
# of `accuracy_table --draw 2`, 409, 433, 439 and 443 (8 cases of 90 frames each,
# 2026-12-06): the 30 without spacer disks (uniform, tapered and stepped tubes, loops among
# them) 0.08-0.15 px and 0.02-0.07 radii; the 10 with them 0.32-1.11 px and 0.12-0.29
# radii, 8 of which had frames more than 2 mm off that the suspect flag left unflagged, or
# every frame off. On the fresh draws 701 and 703 (same day), 0.08-0.14 px and 0.02-0.05
# radii without disks (12 sessions), 0.32-1.07 px and 0.11-0.24 radii with them (4). With
# the calibration 0.15 deg off and kept as given (draw 409, `--refine false`), a
# three-camera random shape 0.88 px and 0.29 radii (0.09 px refined); on two cameras,
# which leave no edge over to disagree, 0.08-0.18 px.
UNEXPLAINED_PX = 0.25
UNEXPLAINED_RADII = 0.1
# A frame whose own residual exceeds this and UNEXPLAINED_RADII is suspect for it
# (unexplained_reason; not a reason the track acts on: its curve is the one the track
# carried). A frame's residual spreads more than a run's median: tubes with small disks
# (1.32-1.38 times the radius, 0.32-0.37 px in median) whose curves came within 0.09-0.15 mm
# cross the run's bar on most frames. On those 40 sessions and the 16 of draws 701 and 703
# (same day), the flag named, of the 961 frames more than 2 mm off, 760 without this
# reason, 920 with it at this bar, 927 at the run's; of the 4,079 good ones, 520, 732 and
# 1,008 (all 505 good frames of the tubes with disks at the run's bar, 234 at this one).
# On draws 709 and 711, not among those the bar was chosen on: 342 of 415 frames off
# (217 without the reason), 182 of 1,025 good ones (152).
UNEXPLAINED_FRAME_PX = 0.4


def edge_residual(widths_px: FloatArray, radius_mm: float, residual_mm: float) -> tuple[float, float]:
    """A frame's fit residual ``residual_mm`` in pixels of the images (by the tube's width
    (C,) ``widths_px`` in each camera, :func:`tube_width_px`, averaged over those that see
    it) and as a share of the tube's ``radius_mm``; NaN where either is unknown."""
    seen = widths_px[np.isfinite(widths_px)]
    if not (len(seen) and np.isfinite(residual_mm) and np.isfinite(radius_mm) and radius_mm > 0):
        return math.nan, math.nan
    return residual_mm * float(np.mean(seen)) / (2.0 * radius_mm), residual_mm / radius_mm


def unexplained_reason(widths_px: FloatArray, radius_mm: float, residual_mm: float) -> str:
    """Why a frame's curve may be off where its fit's residual ``residual_mm`` (by its tube
    of ``radius_mm``, (C,) ``widths_px`` across in the cameras, :func:`tube_width_px`)
    exceeds both ``UNEXPLAINED_FRAME_PX`` and ``UNEXPLAINED_RADII``: its silhouettes' edges
    are not all its tube's; "" where they are, or either is unknown."""
    px, radii = edge_residual(widths_px, radius_mm, residual_mm)
    if not (px > UNEXPLAINED_FRAME_PX and radii > UNEXPLAINED_RADII):
        return ""
    return (
        f"its silhouettes' edges lie {px:.2f} px ({radii:.2f} radii) from its tube: "
        "parts the tube does not draw, or cameras that disagree"
    )


def tube_width_px(cameras: Sequence[Camera], points_mm: FloatArray, radius_mm: float) -> FloatArray:
    """(C,) how many pixels across each camera sees the tube of ``radius_mm`` around (N, 3)
    ``points_mm``: its diameter at the curve's median depth in that camera (NaN where the
    curve is behind it)."""
    out = np.full(len(cameras), np.nan)
    for k, cam in enumerate(cameras):
        depth = cam.to_camera(points_mm)[:, 2]
        depth = depth[depth > 0]
        if len(depth):
            out[k] = 2.0 * radius_mm * cam.focal_px / float(np.median(depth))
    return out


# A frame whose fit fails where some view's silhouette is less than this share within a
# voxel of the hull's voxels (hull_shares) has cameras that do not look at one place: its
# reason says so (SILHOUETTES_APART). On the first frame of `synth --shape random` renders
# (2026-12-06), the least share of a frame was 0.42-1.0 with every camera 0.3 or 0.6 deg off
# (`--calib-error 0.3`, `0.6`; refined, every frame ok) or one camera 1 deg off, 0.83 for a
# tube 1.7 px wide (`--radius-mm 2`), 1.0 on the demo's; 0.05-0.09 with every camera 1 or 2
# deg off (`--calib-error 1`, `2`), whose frames came out 13 mm off, or failed with `the
# hull holds no tube near the base`.
BARELY_MEET_SHARE = 0.25
SILHOUETTES_APART = (
    "the cameras' silhouettes barely meet in space: check that calibration.toml is this rig's, "
    "and that no camera has moved since it was calibrated"
)


def hull_shares(
    points_mm: NDArray[np.floating],
    masks: Sequence[NDArray[np.bool_]],
    cameras: Sequence[Camera],
    voxel_mm: float,
) -> FloatArray:
    """(C,) the share of each camera's (H, W) bool silhouette ``masks`` within a voxel
    (``voxel_mm`` across, projected at the hull's median depth) of the projections of the
    hull's voxel centres (Q, 3) ``points_mm``: 1 where the cameras' cones meet around all
    of what each one sees, near 0 where they meet only at their fringes (cameras that look
    at different places)."""
    points = np.asarray(points_mm, dtype=np.float64)
    shares = np.zeros(len(cameras))
    for c, (cam, mask) in enumerate(zip(cameras, masks, strict=True)):
        seen = int(np.count_nonzero(mask))
        depth = cam.to_camera(points)[:, 2]
        if not seen or not np.any(depth > 0):
            continue
        reach = max(1, math.ceil(voxel_mm * cam.focal_px / float(np.median(depth[depth > 0]))))
        h, w = mask.shape
        px = np.round(cam.project(points[depth > 0])).astype(np.int64)
        inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        hit = np.zeros((h, w), np.uint8)
        hit[px[inside, 1], px[inside, 0]] = 1
        near = cv2.dilate(hit, np.ones((2 * reach + 1, 2 * reach + 1), np.uint8)).view(bool)
        shares[c] = np.count_nonzero(mask & near) / seen
    return shares


def is_doubtful(iou: Sequence[float]) -> bool:
    """Whether a frame's per-camera IoUs say its curve is not to be trusted (DOUBTFUL_IOU)."""
    return bool(iou) and min(iou) < DOUBTFUL_IOU


def reaches_walls(points_mm: NDArray[np.floating], workspace: Workspace, base_mm: ArrayLike) -> bool:
    """Whether occupied voxels lie against a wall of the carving box other than the base's.

    points_mm : (P, 3) occupied voxel centres, world frame, mm.
    base_mm : (3,) the curve's base; the wall nearest it is where the tube is mounted.

    The box cuts off whatever leaves it: a hull against another wall says the tube may
    go on beyond it, and its curve ends short there.
    """
    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    lo = np.asarray(workspace.origin_mm, dtype=np.float64)
    hi = lo + np.asarray(workspace.size_mm, dtype=np.float64)
    base = np.asarray(base_mm, dtype=np.float64)
    # Walls as (axis, side): side 0 the low wall, 1 the high one; the base's is the nearest.
    gaps = np.stack([base - lo, hi - base], axis=1)  # (3, 2)
    base_wall = np.unravel_index(int(np.argmin(np.abs(gaps))), gaps.shape)
    on_wall = np.stack([pts < lo + workspace.voxel_mm, pts > hi - workspace.voxel_mm], axis=2)  # (P, 3, 2)
    on_wall[:, base_wall[0], base_wall[1]] = False
    return bool(on_wall.any())


def tube_mask(
    camera: Camera,
    centerline_mm: FloatArray,
    radius_mm: float | FloatArray,
    *,
    supersample: int = 1,
    window: Window | None = None,
) -> NDArray[np.bool_]:
    """(H, W) bool: the tube of ``radius_mm`` around ``centerline_mm`` seen by ``camera``;
    with ``window`` ((x0, y0), (x1, y1)), only those pixels: (y1 - y0, x1 - x0).

    The tube (with round ends) is drawn as the union of discs of the projected
    radius (f r / depth) centred on the projected axis, resampled at r/2 along the
    curve. Exact for the sides to well under a pixel at the depths of this rig;
    ``supersample`` > 1 draws at that many times the resolution and keeps pixels
    more than half covered.

    Parameters
    ----------
    camera : the camera.
    centerline_mm : (N, 3) float64 axis, world frame, mm.
    radius_mm : tube radius, mm: one for all, or (N,) at each axis point (a tapered tube).
    supersample : drawing resolution factor.
    """
    dense, radii = _disc_centres(centerline_mm, radius_mm)
    return _draw_tube(camera, dense, camera.project(dense), radii, supersample=supersample, window=window)


def tube_masks(
    cameras: Sequence[Camera],
    centerline_mm: FloatArray,
    radius_mm: float | FloatArray,
    disks: Disks | None = None,
) -> list[NDArray[np.bool_]]:
    """:func:`tube_mask` in each camera (the same masks): the discs' centres found
    once and projected in all views at once; with its spacer ``disks`` drawn too (the
    axis running from the base)."""
    dense, radii = _disc_centres(centerline_mm, radius_mm)
    masks = [
        _draw_tube(cam, dense, px, radii, supersample=1)
        for cam, px in zip(cameras, project_in_views(cameras, dense), strict=True)
    ]
    if disks is not None:
        pts = np.asarray(centerline_mm, dtype=np.float64)
        _draw_disks(masks, cameras, rims(pts, polyline_arclength(pts), disks))
    return masks


def _draw_disks(masks: list[NDArray[np.bool_]], cameras: Sequence[Camera], rims_mm: FloatArray) -> None:
    """Draw (True) the disks whose rims are ``rims_mm`` (D, F, R, 3) into each camera's
    (H, W) mask: each the convex hull of its rims' pixels."""
    if len(rims_mm) == 0:
        return
    for mask, disks_px in zip(masks, rim_pixels(cameras, rims_mm), strict=True):
        for disk_px in disks_px:
            if np.isfinite(disk_px).all() and (np.abs(disk_px) < DRAWABLE_PX).all():
                fill_hull(mask.view(np.uint8), disk_px * (1 << DRAW_SHIFT), 1)


def _disc_centres(centerline_mm: FloatArray, radius_mm: float | FloatArray) -> tuple[FloatArray, FloatArray]:
    """The drawn discs: (n, 3) centres, the axis resampled every ~r/2 (mm, world frame;
    r the least radius), and (n,) their radii (mm) from ``radius_mm`` (a float, or (N,)
    along the axis)."""
    pts = np.asarray(centerline_mm, dtype=np.float64)
    along = np.broadcast_to(np.asarray(radius_mm, dtype=np.float64), (len(pts),))
    if len(pts) <= 1:
        return pts, np.array(along)
    seg = vector_norms(pts[1:] - pts[:-1])
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(2, math.ceil(float(seg.sum()) / (_DISC_SPACING * float(along.min()))) + 1)
    # The same arc length resample_polyline would compute (the segments' cumulative sum).
    dense = resample_polyline(pts, n, arclength_mm=arc)
    return dense, np.interp(np.linspace(0.0, arc[-1], n), arc, along)


def _draw_tube(
    camera: Camera,
    dense: FloatArray,
    px: FloatArray,
    radii_mm: FloatArray,
    *,
    supersample: int,
    window: Window | None = None,
) -> NDArray[np.bool_]:
    """:func:`tube_mask` from the discs' centres (n, 3), their pixels (n, 2) and radii (n,) mm."""
    (x0, y0), (x1, y1) = ((0, 0), camera.size_px) if window is None else window
    w, h = x1 - x0, y1 - y0
    canvas = np.zeros((h * supersample, w * supersample), np.uint8)
    depth = camera.to_camera(dense)[:, 2]
    focal = camera.focal_px
    ok = np.isfinite(px).all(axis=1) & (depth > radii_mm)
    scale = supersample * (1 << _SHIFT)
    # Pixel centres sit at integer coordinates; at s-times resolution pixel (u, v)'s
    # centre is at s*u + (s-1)/2.
    centres = np.round((px[ok] + (supersample - 1) / (2 * supersample)) * scale).astype(np.int64)
    # cv2 fills a disc of radius R out to about R + 0.5 canvas pixels (measured:
    # 35 px for R = 3 against pi R^2 = 28): draw half a canvas pixel smaller.
    # (A disc under half a canvas pixel is drawn as one: cv2 takes no negative radius.)
    radii = np.round((focal * radii_mm[ok] / depth[ok] * supersample - 0.5) * (1 << _SHIFT)).astype(np.int64)
    radii = np.maximum(radii, 0)
    # The window's origin, moved in whole canvas pixels: the same pixels drawn.
    centres -= np.array([x0, y0]) * scale
    # Only the discs that reach the canvas are drawn: the others would draw nothing.
    margin = 2 << _SHIFT
    x, y = centres[:, 0], centres[:, 1]
    reach = (
        (x + radii > -margin)
        & (x - radii < (w * supersample << _SHIFT) + margin)
        & (y + radii > -margin)
        & (y - radii < (h * supersample << _SHIFT) + margin)
    )
    # Drawn in 1 at full resolution, so that the canvas is the mask (no threshold
    # pass over the image); in 255 when it is averaged down.
    colour = 255 if supersample > 1 else 1
    for cx, cy, r in zip(x[reach].tolist(), y[reach].tolist(), radii[reach].tolist(), strict=True):
        cv2.circle(canvas, (cx, cy), r, colour, -1, cv2.LINE_8, _SHIFT)
    if supersample > 1:
        return np.asarray(cv2.resize(canvas, (w, h), interpolation=cv2.INTER_AREA) > 127)
    return canvas.view(bool)


def silhouette_iou(predicted: NDArray[np.bool_], observed: NDArray[np.bool_]) -> float:
    """Intersection over union of two (H, W) bool masks; 1.0 when both are empty."""
    union = np.count_nonzero(predicted | observed)
    if union == 0:
        return 1.0
    return np.count_nonzero(predicted & observed) / union


def reprojection_iou(
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.bool_]],
    centerline_mm: FloatArray,
    radius_mm: float | FloatArray,
) -> tuple[float, ...]:
    """Per-camera IoU of the reconstructed tube, re-projected, with each silhouette
    (``radius_mm``: one, or (N,) along the axis)."""
    tubes = tube_masks(cameras, centerline_mm, radius_mm)
    return tuple(silhouette_iou(tube, mask) for tube, mask in zip(tubes, masks, strict=True))


def misfit_fractions(
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.bool_]],
    centerline_mm: FloatArray,
    radius_mm: float | FloatArray,
    contrasts: Sequence[NDArray[np.float32]] | None = None,
) -> tuple[float, ...]:
    """Gross disagreement of the re-projected tube with each (H, W) silhouette.

    Per camera: pixels of either that lie more than a pixel away from the other
    (silhouette pixels the tube misses, tube pixels off the silhouette), as a
    fraction of the silhouette's area (0 where it is empty). The drawn tube's
    round ends are left out of the stray pixels (the real ends may be flat: a
    disc there strays by up to half its area, which is not a misfit). Unlike
    1 - IoU this does not grow with the outline's length in pixels, so it means
    the same at any resolution: a fit that follows the tube leaves ~0-2 %, one
    that misses a part of the tube or strays off it, several %. ``contrasts``: per camera,
    the (H, W) float32 foreground contrast; given, a drawn pixel off the silhouette strays
    only where the grey levels show the tube covering less than ``STRAY_COVERAGE`` of it.
    """
    return tube_figures(cameras, masks, centerline_mm, radius_mm, contrasts)[1]


def tube_figures(
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.bool_]],
    centerline_mm: FloatArray,
    radius_mm: float | FloatArray,
    contrasts: Sequence[NDArray[np.float32]] | None = None,
    disks: Disks | None = None,
) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Per camera, :func:`reprojection_iou` and :func:`misfit_fractions` of one tube,
    drawn once (``contrasts``: see :func:`misfit_fractions`; with its spacer ``disks``)."""
    pts = np.asarray(centerline_mm, dtype=np.float64)
    tubes = tube_masks(cameras, pts, radius_mm, disks)
    along = np.broadcast_to(np.asarray(radius_mm, dtype=np.float64), (len(pts),))
    ends = (float(along[0]), float(along[-1]))
    views = list(zip(cameras, masks, tubes, strict=True))
    iou = tuple(silhouette_iou(tube, mask) for _, mask, tube in views)
    shown: Sequence[NDArray[np.float32] | None] = [None] * len(views) if contrasts is None else contrasts
    misfits = tuple(
        _misfit(cam, mask, pts, tube, ends, contrast)
        for (cam, mask, tube), contrast in zip(views, shown, strict=True)
    )
    return iou, misfits


def _misfit(
    camera: Camera,
    mask: NDArray[np.bool_],
    pts: FloatArray,
    tube: NDArray[np.bool_],
    end_radii_mm: tuple[float, float],
    contrast: NDArray[np.float32] | None = None,
) -> float:
    """:func:`misfit_fractions` in one camera, given its drawn tube (H, W), the axis (N, 3) mm
    and, if known, the view's (H, W) contrast."""
    area = np.count_nonzero(mask)
    if area == 0:
        return 0.0
    grow = np.ones((3, 3), np.uint8)
    missed = mask & ~cv2.dilate(tube.view(np.uint8), grow).view(bool)
    stray = tube & ~cv2.dilate(mask.view(np.uint8), grow).view(bool)
    ends = np.zeros(mask.shape, np.uint8)
    px = camera.project(pts[[0, -1]])
    depth = camera.to_camera(pts[[0, -1]])[:, 2]
    focal = camera.focal_px
    for (x, y), z, r in zip(px.tolist(), depth.tolist(), end_radii_mm, strict=True):
        if math.isfinite(x) and math.isfinite(y) and z > r and abs(x) < DRAWABLE_PX and abs(y) < DRAWABLE_PX:
            radius_px = focal * r / z + 1.5  # the disc, its outline and a pixel of rounding
            cv2.circle(ends, (round(x * 16), round(y * 16)), round(radius_px * 16), 1, -1, cv2.LINE_8, 4)
    stray &= ends == 0
    if contrast is not None and stray.any():
        # Read only around the stray pixels: most frames have none.
        ys, xs = np.nonzero(stray)
        window = ((int(xs.min()), int(ys.min())), (int(xs.max()) + 1, int(ys.max()) + 1))
        stray &= pixel_coverages([contrast], [mask], [window])[0] < STRAY_COVERAGE
    return (np.count_nonzero(missed) + np.count_nonzero(stray)) / area


def suspect_reason(
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.bool_]],
    centerline_mm: FloatArray,
    radius_mm: float | FloatArray,
    *,
    iou: Sequence[float],
    misfit: Sequence[float],
    jump_mm: float = math.nan,
    prediction_miss_mm: float = 0.0,
    expected_length_mm: float = math.nan,
    usual_misfit: float = 0.0,
    odd_view: int | None = None,
) -> str:
    """Why a frame's curve (N, 3) mm may be wrong, without ground truth; "" if nothing says so.

    The tube re-projects poorly (``iou``, :func:`is_doubtful`) or leaves part of a
    silhouette unexplained (``misfit``, ``SUSPECT_MISFIT`` beyond the share its track's
    frames usually leave, ``usual_misfit``; both per camera, from
    :func:`tube_figures`); it passes through itself; it
    lies far from what its track predicted at its velocity (``jump_mm``, NaN where the
    prediction carried none), farther than the track's last frames lay from their own
    predictions (``prediction_miss_mm``) by ``SUSPECT_JUMP_RADII``; or its length
    is not the one its track predicts (``expected_length_mm``, NaN where none does).
    ``radius_mm``: one, or (N,) along the curve; ``odd_view``: the view whose image
    disagreed with the others', left out of the fit. The reasons found are joined by "; ".
    """
    names = [cam.name for cam in cameras]
    reasons = []
    if odd_view is not None:
        reasons.append(
            f"camera {names[odd_view]}'s image disagrees with the other cameras' "
            "(a frame from another moment, or something in front of its lens): fitted to theirs alone"
        )
    if is_doubtful(iou):
        worst = int(np.argmin(iou))
        reasons.append(f"camera {names[worst]} re-projects poorly (IoU {iou[worst]:.2f})")
    worst = int(np.argmax(misfit))
    if misfit[worst] > SUSPECT_MISFIT + usual_misfit:
        share = 100 * misfit[worst]
        # Silhouette pixels the tube misses and tube pixels off the silhouette, against the
        # silhouette's area: past 100 % where the tube is drawn elsewhere in that view.
        reasons.append(
            f"camera {names[worst]}'s silhouette and the tube drawn in it differ by {share:.0f} % of its area"
        )
    radius = float(np.median(radius_mm))  # the tube's, for the distances below
    if self_intersects(centerline_mm, radius, closest_radii=SUSPECT_CLOSEST_RADII):
        reasons.append("the tube passes through itself")
    if jump_mm > SUSPECT_JUMP_RADII * radius + prediction_miss_mm:
        reasons.append(f"{jump_mm:.1f} mm from its track's prediction")
    length = float(polyline_arclength(centerline_mm)[-1])
    if abs(length - expected_length_mm) > SUSPECT_LENGTH_MM:
        reasons.append(f"length {length:.1f} mm, {length - expected_length_mm:+.1f} mm from its track's")
    return "; ".join(reasons)


def off_length(lengths_mm: FloatArray) -> FloatArray:
    """(F,) mm: how much longer each frame's curve, of (F,) ``lengths_mm`` (NaN where it has
    none: 0 here), is than the run's median, where the run's lengths agree on one
    (``RUN_LENGTH_AGREE_MM``, their median absolute deviation); 0 throughout where they do
    not."""
    lengths = np.asarray(lengths_mm, dtype=np.float64)
    known = lengths[np.isfinite(lengths)]
    if not len(known):
        return np.zeros(len(lengths))
    median = float(np.median(known))
    if float(np.median(np.abs(known - median))) > RUN_LENGTH_AGREE_MM:
        return np.zeros(len(lengths))
    gaps = lengths - median
    return np.where(np.isfinite(gaps), gaps, 0.0)


def off_smoothed(curves_mm: FloatArray, smoothed_mm: FloatArray) -> FloatArray:
    """(F,) mm: how far each frame's curve of (F, N, 3) ``curves_mm`` lies from its
    smoothed one in (F, N, 3) ``smoothed_mm`` (:func:`pipeline.run.smoothing.smooth_centerlines`):
    the largest distance between samples at the same fraction of their lengths (so a
    curve cut short or run on is as far off as its tip); 0 where either has no curve
    (NaN rows)."""
    gaps = np.linalg.norm(np.asarray(curves_mm) - np.asarray(smoothed_mm), axis=2).max(axis=1)
    return np.where(np.isfinite(gaps), gaps, 0.0)
