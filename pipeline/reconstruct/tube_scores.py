"""How well a fitted tube explains the silhouettes: the scores that rank hypotheses.

:func:`silhouette_score` (mean re-projection IoU, handicapped for a curve whose parts
come closer than a tube allows), the worst view's misfit fraction, and the radius
read from the silhouettes (:func:`radius_from_silhouettes`).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import Camera
from ..geometry.polyline import self_intersects
from .quality import misfit_fractions, reprojection_iou
from .tube_fit import TubeFit

FloatArray = NDArray[np.float64]

# A fitted tube whose worst view's misfit fraction (pipeline.reconstruct.quality) exceeds
# this leaves part of a silhouette unexplained: other hypotheses are tried.
# Measured on rendered sessions (radii 4-9 mm, both rigs): 0 on smooth shapes,
# <= 0.8 % where a loop's fit follows the tube, 2.8-12 % where it went astray.
MISFIT = 0.01
# Two parts of a tube of radius r touch when their axes are 2 r apart; a fitted
# axis may stray from the true one by up to a quarter radius (the fit's outlier
# limit, pipeline.reconstruct.side_readings.OUTLIER_RADII) on each part: a curve whose parts
# come closer than this many radii passes through itself and is not the tube.
# Measured on rendered loops (r 4-9 mm, both rigs): the true curves keep
# 2.1-4.2 r; the wrong hypotheses (a tip curled into the stem, a march run
# back along it) come to 0.5-1.4 r.
CLOSEST_RADII = 1.5
# ... yet where the stem hides a tip in most views, a curve whose tip curled
# into the stem can still be the tube but for its end (the bend then moves the
# tip): it is not dropped, it ranks this much lower in mean re-projection IoU.
# Measured where the tip hides: right and wrong tips differ by 0.01-0.03 in
# IoU; a curve that stops short of a loop's last part loses 0.1-0.5.
_IMPLAUSIBLE = 0.05


def worst_misfit(fit: TubeFit, cameras: Sequence[Camera], masks: Sequence[NDArray[np.bool_]]) -> float:
    """The worst view's :func:`.quality.misfit_fractions` of a fitted tube (1 if no radius)."""
    if not (np.isfinite(fit.radius_mm) and fit.radius_mm > 0):
        return 1.0
    return max(misfit_fractions(cameras, masks, fit.points_mm, fit.radius_mm))


def passes_through_itself(fit: TubeFit) -> bool:
    """Whether a fitted tube's parts come closer than ``CLOSEST_RADII`` radii: not a tube."""
    return self_intersects(fit.points_mm, fit.radius_mm, closest_radii=CLOSEST_RADII)


def ranked_score(fit: TubeFit, cameras: Sequence[Camera], masks: Sequence[NDArray[np.bool_]]) -> float:
    """How a candidate ranks: its :func:`silhouette_score`, less ``_IMPLAUSIBLE`` if
    its parts come closer than a tube allows (:func:`passes_through_itself`)."""
    penalty = _IMPLAUSIBLE if passes_through_itself(fit) else 0.0
    return silhouette_score(fit, cameras, masks) - penalty


def silhouette_score(fit: TubeFit, cameras: Sequence[Camera], masks: Sequence[NDArray[np.bool_]]) -> float:
    """How well a fitted tube explains the silhouettes: its mean re-projection IoU."""
    radius = fit.radius_mm if np.isfinite(fit.radius_mm) else 0.0
    if radius <= 0:
        return 0.0
    return float(np.mean(reprojection_iou(cameras, masks, fit.points_mm, radius)))


def radius_from_silhouettes(
    cameras: Sequence[Camera], masks: Sequence[NDArray[np.bool_]], centre_mm: FloatArray
) -> float:
    """Rough tube radius (mm) from the silhouettes' area / perimeter, NaN if none.

    A long strip of width w has area ~ w L and perimeter ~ 2 L, so w/2 ~
    area / perimeter (px), converted at the depth of ``centre_mm`` (3,). Only a
    first guess: the tube fit measures the radius properly.
    """
    radii = []
    for cam, mask in zip(cameras, masks, strict=True):
        contours, _ = cv2.findContours(mask.view(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        perimeter = sum(cv2.arcLength(c, True) for c in contours)
        depth = float(cam.to_camera(np.asarray(centre_mm, dtype=np.float64)[None])[0, 2])
        if perimeter > 0 and depth > 0:
            focal = cam.focal_px
            radii.append(np.count_nonzero(mask) / perimeter * depth / focal)
    return float(np.median(radii)) if radii else float("nan")
