"""The per-frame path: images -> silhouettes -> hull -> centreline -> quality.

Pure: arrays in, a :class:`~pipeline.reconstruct.frame_result.FrameResult` out; no logging,
no files. A frame that cannot be reconstructed is a result with status "empty"
or "failed" and a reason, never an exception. What never changes over a session
(cameras, settings, the voxel grid and its lookup tables, background images) is
a :class:`~pipeline.reconstruct.model.SessionModel`, built once in the parent and sent to every worker.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ..carve.hull import carve, voxel_centers_mm
from ..carve.silhouette import extract_silhouette
from ..errors import SettingsError
from ..geometry.camera import Camera, project_in_views
from ..geometry.polyline import axis_gap_mm
from .centerline import fit_centerline
from .frame_result import NO_SHARED_VOXEL, FrameResult, nothing_seen
from .model import SessionModel
from .model import build_model as build_model  # re-exported: build the model, then reconstruct frames
from .ordering import infer_base
from .quality import (
    BARELY_MEET_SHARE,
    SILHOUETTES_APART,
    hull_shares,
    suspect_reason,
    tube_figures,
    tube_masks,
    tube_width_px,
    unexplained_reason,
)
from .radius_profile import RadiusProfile
from .side_readings import REDUNDANT_VIEWS
from .spline import smooth_curve
from .tracking import (
    TrackedFit,
    held_length,
    judge_fit,
    predict_axis,
    predict_length,
    prediction_miss_mm,
    track_tube,
    track_without_odd_view,
    usual_misfit,
    velocity_pair,
)
from .tube_fit import foreground_contrast
from .tube_scores import radius_from_silhouettes

# Fewer occupied voxels than this cannot hold a tube: the frame is "failed"
# (something was seen, but no curve can come of it).
MIN_VOXELS = 8
# A view whose silhouette holds more than this share of the image shows no tube: a thin
# manipulator covers about 1 % of a view at the rigs' distances, a close-up 10-20 %.
MAX_SILHOUETTE_SHARE = 0.5
# session.toml's tube radius and the silhouettes' rough reading of it (area over perimeter)
# must agree within this factor. On 62 rendered sessions (the draws of docs/accuracy.md, the
# disk sessions of draws 2-133, the bench's; three frames each, 2026-12-04) they were at
# most 2.1 times apart (a two-camera r 4.5 tube with 1.45x disks, beside a dark object).
RADIUS_AGREEMENT = 4.0
# Radius used to start the search when neither session.toml nor the silhouettes give one (mm).
_FALLBACK_RADIUS_MM = 6.0
# A tracked frame keeps the silhouette's blobs that its predicted tube, drawn this many
# times as wide, reaches (tube_blobs): two radii beyond the tube's edge on each side.
TRACK_REACH_RADII = 3.0


def frame_silhouettes(images: Sequence[NDArray[np.uint8]], model: SessionModel) -> list[NDArray[np.bool_]]:
    """Per camera (H, W) bool silhouette of one frame's (H, W) uint8 grey images."""
    return [camera_silhouette(image, model, k) for k, image in enumerate(images)]


def camera_silhouette(image: NDArray[np.uint8], model: SessionModel, camera: int) -> NDArray[np.bool_]:
    """(H, W) bool silhouette of camera number ``camera``'s (H, W) uint8 grey image."""
    sil = model.settings.silhouette
    background = model.backgrounds[camera] if sil.method == "background" else None
    return extract_silhouette(image, sil, background=background)


def frame_contrasts(images: Sequence[NDArray[np.uint8]], model: SessionModel) -> list[NDArray[np.float32]]:
    """Per camera (H, W) float32 "how much tube" of one frame's grey images
    (:func:`pipeline.reconstruct.tube_fit.foreground_contrast`), which the fit reads."""
    sil = model.settings.silhouette
    return [
        foreground_contrast(
            image, polarity=sil.polarity, background=bg if sil.method == "background" else None
        )
        for image, bg in zip(images, model.backgrounds, strict=True)
    ]


def reconstruct_frame(
    index: int,
    images: Sequence[NDArray[np.uint8] | None],
    model: SessionModel,
    previous: Sequence[FrameResult] = (),
) -> FrameResult:
    """One frame, from its grey images (one per camera, None if undecodable)."""
    for cam, image in zip(model.cameras, images, strict=True):
        if image is None:
            return FrameResult.failed(index, f"camera {cam.name!r} image could not be decoded")
    result, _ = reconstruct_with_silhouettes(index, [im for im in images if im is not None], model, previous)
    return result


def reconstruct_with_silhouettes(
    index: int,
    images: Sequence[NDArray[np.uint8]],
    model: SessionModel,
    previous: Sequence[FrameResult] = (),
    *,
    restart_here: bool = True,
) -> tuple[FrameResult, list[NDArray[np.bool_]]]:
    """:func:`frame_silhouettes` + :func:`reconstruct_from_silhouettes`, with the
    silhouette time recorded under "silhouette"; the silhouettes are returned too
    (the runner logs them)."""
    start = time.perf_counter()
    masks = frame_silhouettes(images, model)
    elapsed = time.perf_counter() - start
    result = reconstruct_from_silhouettes(index, images, masks, model, previous, restart_here=restart_here)
    result.timings_s["silhouette"] = elapsed
    return result, masks


def reconstruct_from_silhouettes(
    index: int,
    images: Sequence[NDArray[np.uint8]],
    masks: Sequence[NDArray[np.bool_]],
    model: SessionModel,
    previous: Sequence[FrameResult] = (),
    *,
    restart_here: bool = True,
) -> FrameResult:
    """Hull, centreline and quality figures of one frame from its silhouettes.

    Parameters
    ----------
    index : frame index in the session.
    images : per camera (H, W) uint8 grey image (the tube fit reads its edges).
    masks : per camera (H, W) bool silhouette.
    model : the session's model.
    previous : the track's results before this frame, oldest first
        (:mod:`pipeline.reconstruct.tracking`); empty: the frame is fitted from the hull alone.
    restart_here : where the track is lost, start it again from the hull in this call;
        False: keep the lost track's fit, flagged suspect and with its ``lost`` reason, for
        the caller to start the track again elsewhere (a live run's restart worker,
        :mod:`pipeline.live.restarts`, so that this frame does not wait for it).

    Returns
    -------
    FrameResult with status "ok", "empty" (no silhouette in some view, or no
    occupied voxel) or "failed" (with the reason: too little hull for a curve,
    or a numerical failure of the fit).
    """
    timings: dict[str, float] = {}
    start = time.perf_counter()
    blind = tuple(cam.name for cam, mask in zip(model.cameras, masks, strict=True) if not mask.any())
    if blind:
        return FrameResult(
            index=index, status="empty", reason=nothing_seen(blind), unseen_by=blind, timings_s=timings
        )
    # A view that is mostly silhouette (a dark or covered lens, a threshold on the wrong
    # side of the scene) has a hull of the whole workspace in it, which takes minutes to
    # search and holds no tube. Every such view is named: the user fixes them all at once.
    shares = {
        cam.name: float(np.count_nonzero(mask)) / mask.size
        for cam, mask in zip(model.cameras, masks, strict=True)
    }
    covered = {name: share for name, share in shares.items() if share > MAX_SILHOUETTE_SHARE}
    if covered:
        if len(covered) == 1:
            ((name, share),) = covered.items()
            seen = f"camera {name!r} sees {100 * share:.0f} % of its image as tube; check its picture"
        else:
            names = _listed([repr(name) for name in covered])
            percent = _listed([f"{100 * share:.0f}" for share in covered.values()])
            seen = f"cameras {names} see {percent} % of their images as tube; check their pictures"
        return FrameResult.failed(
            index, f"{seen}, and [silhouette] polarity and threshold in session.toml", timings_s=timings
        )
    points = voxel_centers_mm(model.settings.workspace, carve(model.grid, masks))
    timings["carve"] = time.perf_counter() - start
    if len(points) == 0:
        return FrameResult(
            index=index,
            status="empty",
            reason=NO_SHARED_VOXEL,
            timings_s=timings,
        )
    if len(points) < MIN_VOXELS:
        return _failed(
            index, f"only {len(points)} occupied voxels, too few for a curve", points, masks, model, timings
        )
    # The fit and the quality figures see only the tube's blobs (see tube_blobs): those the
    # hull supports, and where a track predicts this frame's tube, those along it.
    predicted = predict_axis(previous, index) if model.settings.centerline.method == "fit" else None
    radius_mm = previous[-1].radius_mm if predicted is not None else float("nan")
    try:
        masks = tube_blobs(masks, points, model, predicted, radius_mm)
        return _curve_and_quality(
            index, images, masks, points, model, timings, previous, predicted, restart_here
        )
    except (ValueError, ArithmeticError, np.linalg.LinAlgError, cv2.error) as exc:
        # Numerical trouble with this frame's data (OpenCV's included: a drawing
        # asked for an impossible disc) is a failed frame, not a crash; on one line.
        reason = " ".join(str(exc).split())
        return _failed(index, f"centreline fit failed: {reason}", points, masks, model, timings)


def _failed(
    index: int,
    reason: str,
    points_mm: NDArray[np.floating],
    masks: Sequence[NDArray[np.bool_]],
    model: SessionModel,
    timings: dict[str, float],
) -> FrameResult:
    """A failed frame with its ``reason``, and where the cameras' silhouettes barely meet
    around the hull's voxels (Q, 3) ``points_mm`` (:func:`~.quality.hull_shares`), that too:
    cameras that look at different places are the cause to mend, not the fit."""
    shares = hull_shares(points_mm, masks, model.cameras, model.settings.workspace.voxel_mm)
    if float(shares.min()) < BARELY_MEET_SHARE:
        reason = f"{reason}; {SILHOUETTES_APART}"
    return FrameResult.failed(index, reason, points_mm=points_mm, timings_s=timings)


def hull_but_one_view(model: SessionModel, masks: Sequence[NDArray[np.bool_]]) -> NDArray[np.float64]:
    """(Q, 3) mm: the centres of the voxels that project onto the silhouettes (H, W)
    bool ``masks`` of every camera but (at least) one: the hull each camera would
    leave if it saw nothing, all together."""
    everything = [np.ones_like(mask) for mask in masks]
    indices = [carve(model.grid, [*masks[:c], everything[c], *masks[c + 1 :]]) for c in range(len(masks))]
    return voxel_centers_mm(model.settings.workspace, np.unique(np.concatenate(indices))).astype(np.float64)


def tube_blobs(
    masks: Sequence[NDArray[np.bool_]],
    points_mm: NDArray[np.floating],
    model: SessionModel,
    predicted_mm: NDArray[np.float64] | None = None,
    radius_mm: float = float("nan"),
) -> list[NDArray[np.bool_]]:
    """Per camera, the (H, W) silhouette without the blobs that are not the tube's.

    The hull's: a dark object in one view's background is silhouette there but carves
    no voxel: the other views do not see it where it would have to be. The tube's own
    silhouette is one blob (or a few, where it leaves the image) that the occupied
    voxels ``points_mm`` ((P, 3), mm) project into; the blobs none of them projects into
    are dropped. Whole blobs are kept, not only the pixels near a voxel: a tube thinner
    than the voxels (a tapered tip) carves few of them, but its silhouette is joined to
    the rest.

    The track's: with two views, such an object carves voxels where its cone crosses
    the other view's silhouette of the tube, and the hull keeps it; judged on it, the
    tube leaves it unexplained in every frame, and the track would be called lost at
    each. The tube moves little from one frame to the next, so its silhouette lies along
    a track's prediction of it (``predicted_mm``, (N, 3) mm, of radius ``radius_mm``):
    of the blobs the hull keeps, only those that the predicted tube, drawn
    ``TRACK_REACH_RADII`` times as wide, reaches are kept (all of them where it reaches
    none).
    """
    pts = np.asarray(points_mm, dtype=np.float64)
    track = predicted_mm if np.isfinite(radius_mm) and radius_mm > 0 else None
    wide: list[NDArray[np.bool_]] | None = None
    out = []
    for view, (mask, px) in enumerate(zip(masks, project_in_views(model.cameras, pts), strict=True)):
        count, labels = cv2.connectedComponents(mask.view(np.uint8), connectivity=8)
        if count <= 2:  # background and one blob: nothing to drop
            out.append(mask)
            continue
        h, w = mask.shape
        ij = np.round(px[np.isfinite(px).all(axis=1)]).astype(np.int64)
        ij = ij[(ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)]
        hit = np.zeros(count, dtype=bool)
        hit[labels[ij[:, 1], ij[:, 0]]] = True
        hit[0] = False  # the background
        if track is not None:
            if wide is None:
                wide = tube_masks(model.cameras, track, TRACK_REACH_RADII * radius_mm)
            near = np.zeros(count, dtype=bool)
            near[labels[wide[view]]] = True
            if (hit & near).any():
                hit &= near
        out.append(hit[labels])
    return out


def _curve_and_quality(
    index: int,
    images: Sequence[NDArray[np.uint8]],
    masks: Sequence[NDArray[np.bool_]],
    points: NDArray[np.float32],
    model: SessionModel,
    timings: dict[str, float],
    previous: Sequence[FrameResult],
    predicted: NDArray[np.float64] | None,
    restart_here: bool = True,
) -> FrameResult:
    settings = model.settings
    cameras = model.cameras
    disks = model.disks
    start = time.perf_counter()
    pts = points.astype(np.float64)
    radius_guess = settings.manipulator.radius_mm or radius_from_silhouettes(cameras, masks, pts.mean(axis=0))
    if not np.isfinite(radius_guess) or radius_guess <= 0:
        radius_guess = _FALLBACK_RADIUS_MM
    known = settings.manipulator.base_mm is not None
    if settings.manipulator.base_mm is not None:
        base = np.asarray(settings.manipulator.base_mm, dtype=np.float64)
    else:
        ws = settings.workspace
        base = infer_base(pts, np.asarray(ws.origin_mm), np.asarray(ws.size_mm), radius_mm=radius_guess)
    n_points = settings.centerline.points
    # How far the track's last frames lay from their own predictions: a jump is judged beyond it.
    missed_mm = prediction_miss_mm(previous)
    # The share of a silhouette the track's frames usually leave unexplained, and the length
    # its tube keeps where no view places its end.
    usual, kept_length = usual_misfit(previous), held_length(previous)
    tracked = False
    lost = ""
    odd_view: int | None = None  # a view left out of the fit: its image disagrees with the others'
    if settings.centerline.method == "polyfit":
        curve = smooth_curve(_polyfit()(pts, base if known else None, n_points=n_points), n_points=n_points)
        radius, residual, radii = radius_guess, float("nan"), None
        figures = None
        placement = None
    else:
        contrasts = frame_contrasts(images, model)

        def track(
            start_mm: NDArray[np.float64],
            radius_mm: float,
            radii_mm: NDArray[np.float64] | None,
            miss_mm: float = 0.0,
            views: Sequence[int] | None = None,
        ) -> TrackedFit:
            """The tube tracked from ``start_mm`` in ``views`` (default: every view)."""
            seen = range(len(cameras)) if views is None else views
            return track_tube(
                start_mm,
                [cameras[v] for v in seen],
                [masks[v] for v in seen],
                [contrasts[v] for v in seen],
                radius_mm=radius_mm,
                base_known=known,
                cap=model.tip,
                radii_mm=radii_mm,
                n_points=n_points,
                usual_misfit=usual,
                length_mm=kept_length,
                prediction_miss_mm=miss_mm,
                session_radii=model.radius_profile,
            )

        held = None
        if predicted is not None:
            last = previous[-1]
            held = track(predicted, last.radius_mm, last.radii_mm, missed_mm)
            if held.lost and len(cameras) >= REDUNDANT_VIEWS:
                others = track_without_odd_view(
                    lambda views: track(predicted, last.radius_mm, last.radii_mm, missed_mm, views),
                    held,
                    cameras,
                    masks,
                    contrasts,
                    n_points=n_points,
                    disks=disks,
                )
                if others is not None:
                    held, odd_view = others
        if held is not None and held.curve is not None and (not held.lost or not restart_here):
            best, tracked, lost = held, True, held.lost
        else:
            # A track starts here, or was lost: the tube from the hull, fitted
            # again as a tracked frame would be; of that, the hull's own fit
            # and the lost track's, the one that leaves least of the
            # silhouettes unexplained.
            _check_declared_radius(settings.manipulator.radius_mm, cameras, masks, pts)
            lost_fit = held if held is not None and held.curve is not None else None
            # The start draws the tube's spacer disks, as the track does, on three cameras
            # or more: fitted without them, dense disks widen the tube's radius by half and
            # bend the curve by their outlines. On the 16 three-camera disk sessions of
            # `accuracy_table --draw 2`, 409, 433, 439 and 443 and of
            # pipeline.synth.variety.draw_cases from seed 700 (90 frames, 2026-12-07), 4 came
            # out better by more than 0.01 mm (mean 0.870 -> 0.759 mm and 86 -> 54 frames more
            # than 2 mm off; 2.005 -> 1.730, 0.935 -> 0.827, 0.324 -> 0.283), 2 worse (0.400 ->
            # 0.457, 1.407 -> 1.473), and frames off over all 52 sessions went 887 -> 838; on
            # ten fresh ones (draw_cases from seed 1000, same day), 4 better, 2 worse, means
            # summed 5.87 -> 5.67 mm (docs/accuracy.md). On two cameras (draw 2, 150 frames,
            # 2026-12-06) a disk session went 0.61 -> 0.84 mm.
            disks_drawn = RadiusProfile.of_disks(disks) if len(cameras) >= REDUNDANT_VIEWS else None
            try:
                _, init = fit_centerline(
                    pts,
                    cameras,
                    masks,
                    contrasts,
                    base_mm=base,
                    base_known=known,
                    radius_mm=radius_guess,
                    voxel_mm=settings.workspace.voxel_mm,
                    n_points=n_points,
                    cap=model.tip,
                    wider_hull=(lambda: hull_but_one_view(model, masks)) if len(cameras) > 2 else None,
                    session_radii=disks_drawn,
                )
            except ValueError as exc:
                if lost_fit is None:
                    raise
                # No start in the hull, nor in the voxels every view but one sees (a thin tube
                # that the views lose near the base): the lost track's fit is the frame's, flagged.
                best, tracked, lost = lost_fit, True, f"{lost_fit.lost}; no start from the hull: {exc}"
            else:
                options = [track(init.points_mm, init.radius_mm, init.radii_mm)]
                if held is not None:
                    options.append(held)
                if np.isfinite(init.radius_mm) and init.radius_mm > 0:
                    options.append(
                        judge_fit(init, cameras, masks, n_points=n_points, contrasts=contrasts, disks=disks)
                    )
                best = min(options, key=lambda o: o.misfit)
                if best.curve is None:  # no fit read a tube: the hull's, drawn at the radius guessed
                    best = judge_fit(
                        init,
                        cameras,
                        masks,
                        n_points=n_points,
                        radius_mm=radius_guess,
                        contrasts=contrasts,
                        disks=disks,
                    )
        if best.fit is None or best.curve is None:
            raise ValueError("the fit gave no curve")
        curve, radii = best.curve, best.radii_mm
        radius, residual = best.fit.radius_mm, best.fit.residual_mm
        placement = best.fit.placement
        # The curve's figures, found as it was judged (its tube drawn once).
        figures = best.iou, best.misfits
    timings["centerline"] = time.perf_counter() - start
    start = time.perf_counter()
    if not np.all(np.isfinite(curve.points_mm)):
        raise ValueError("the curve has non-finite points")
    iou, misfits = (
        figures if figures is not None else tube_figures(cameras, masks, curve.points_mm, radius, disks=disks)
    )
    draw_radius = radius if np.isfinite(radius) else radius_guess
    drawn = radii if radii is not None and np.isfinite(radii).all() else draw_radius
    # Only a prediction that carries the track's velocity says where this frame's tube
    # should be: one that holds the last curve still (after a suspect frame) misses a
    # moving tube by a frame's motion (see SUSPECT_JUMP_RADII).
    jump = float("nan")
    if predicted is not None and velocity_pair(previous) is not None:
        jump = axis_gap_mm(curve.points_mm, predicted)
    reason = suspect_reason(
        cameras,
        masks,
        curve.points_mm,
        drawn,
        iou=iou,
        misfit=misfits,
        jump_mm=jump,
        prediction_miss_mm=missed_mm,
        expected_length_mm=predict_length(previous, index),
        usual_misfit=usual,
        odd_view=odd_view,
    )
    if lost:
        reason = "; ".join(filter(None, [f"its track was lost here ({lost})", reason]))
    loose = placement.loose_reason(draw_radius) if placement is not None else ""
    widths = tube_width_px(cameras, curve.points_mm, radius)
    doubt = "; ".join(filter(None, [loose, unexplained_reason(widths, radius, residual)]))
    timings["quality"] = time.perf_counter() - start
    return FrameResult(
        index=index,
        status="ok",
        points_mm=points,
        centerline_mm=curve.points_mm,
        tangents=curve.tangents,
        curvature_per_mm=curve.curvature_per_mm,
        length_mm=curve.length_mm,
        radius_mm=float(radius),
        radii_mm=radii,
        fit_residual_mm=float(residual),
        tube_width_px=tuple(widths.tolist()),
        iou=iou,
        misfits=tuple(misfits),
        tracked=tracked,
        lost=lost,
        jump_mm=jump,
        suspect_reason=reason,
        doubt_reason=doubt,
        timings_s=timings,
    )


def check_declared_radius(
    model: SessionModel, frames: Sequence[tuple[int, Sequence[NDArray[np.uint8]]]], source: Path
) -> None:
    """SettingsError before a run where session.toml's (``source``) ``[manipulator]
    radius_mm`` is more than ``RADIUS_AGREEMENT`` times off the tube the sample ``frames``
    ((index, per camera grey image)) show: the median of their silhouettes' rough readings
    (those of frames in which every view sees part of a tube). Every frame started from
    the hull would fail for it (:func:`_check_declared_radius`); named once, up front."""
    declared = model.settings.manipulator.radius_mm
    if not declared:
        return
    seen = []
    for _, images in frames:
        masks = frame_silhouettes(images, model)
        if not all(m.any() and np.count_nonzero(m) <= MAX_SILHOUETTE_SHARE * m.size for m in masks):
            continue
        points = voxel_centers_mm(model.settings.workspace, carve(model.grid, masks)).astype(np.float64)
        if len(points) >= MIN_VOXELS:
            masks = tube_blobs(masks, points, model)
            seen.append(radius_from_silhouettes(model.cameras, masks, points.mean(axis=0)))
    seen = [r for r in seen if np.isfinite(r) and r > 0]
    if not seen:
        return
    typical = float(np.median(seen))
    if not 1.0 / RADIUS_AGREEMENT <= declared / typical <= RADIUS_AGREEMENT:
        raise SettingsError(
            f"{source}: [manipulator] radius_mm = {declared:g} mm, but the silhouettes show a tube of "
            f"about {typical:.1f} mm; correct radius_mm, or leave it out to take the silhouettes'"
        )


def _check_declared_radius(
    radius_mm: float | None,
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.bool_]],
    points_mm: NDArray[np.float64],
) -> None:
    """ValueError where session.toml's ``[manipulator] radius_mm`` is more than
    ``RADIUS_AGREEMENT`` times off the silhouettes' rough reading of the tube's radius: the
    fit then looks for the tube's edges in the wrong place and reads none."""
    if not radius_mm:
        return
    seen = radius_from_silhouettes(cameras, masks, points_mm.mean(axis=0))
    if np.isfinite(seen) and seen > 0 and not 1.0 / RADIUS_AGREEMENT <= radius_mm / seen <= RADIUS_AGREEMENT:
        raise ValueError(
            f"[manipulator] radius_mm = {radius_mm:g} mm, but the silhouettes show a tube of about "
            f"{seen:.1f} mm; correct radius_mm in session.toml, or leave it out to take the silhouettes'"
        )


def _polyfit() -> Callable[..., Any]:
    """The original method's curve (a baseline), imported only when asked for."""
    from ..baseline.curve import polyfit_centerline

    return polyfit_centerline


def _listed(items: Sequence[str]) -> str:
    """``a``, ``a and b``, ``a, b and c``."""
    return items[0] if len(items) == 1 else f"{', '.join(items[:-1])} and {items[-1]}"
