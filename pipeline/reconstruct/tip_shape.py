"""The tube's end, flat or round, chosen once per session from a few of its frames.

A flat end and a hemispherical one cover different pixels around the tip: seen
side-on, the flat end's outline is square where the round one's is a half
disc, and the round end reaches a radius past its centre (the backbone's end).
On frames spread over the session, each frame's curve has its tip placed by
the grey levels under either end (:func:`pipeline.reconstruct.tip_bend.bend_tip_to_pixels`);
the end whose tubes match the grey levels better, summed over the frames
(:func:`pipeline.reconstruct.tube_drawing.coverage_mismatch`), is the session's.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from .frame import frame_contrasts, reconstruct_with_silhouettes
from .frame_task import decode_frames
from .model import SessionModel
from .tip_bend import bend_tip_to_pixels
from .tube_drawing import coverage_mismatch, pixel_coverages

# Frames sampled over the session: enough that one frame whose tip is hidden
# (end-on in most views, or against another part) does not decide.
SAMPLE_FRAMES = 6
# The bend under each end: its last radius, sought within a few mm of the fit.
_SPANS_RADII = (2.0, 1.0)
_STEPS_MM = (2.0, 1.0, 0.5, 0.25)


@dataclass(frozen=True)
class TipChoice:
    """The session's tube end and its evidence.

    tip : "flat" or "round".
    frames : frames whose tips were compared.
    flat_cost, round_cost : the grey-level mismatch of the tips under each end,
        summed over those frames (lower is better).
    """

    tip: str
    frames: int
    flat_cost: float
    round_cost: float

    def describe(self) -> str:
        if not self.frames:
            return f"{self.tip} (no frame showed a tip to choose by; set [manipulator] tip in session.toml)"
        ratio = max(self.flat_cost, self.round_cost) / max(min(self.flat_cost, self.round_cost), 1e-12)
        return (
            f"{self.tip} (chosen from {self.frames} frames, {ratio:.2f}x the other's grey-level mismatch; "
            "[manipulator] tip in session.toml fixes it)"
        )


def sample_frames(start: int, stop: int, count: int = SAMPLE_FRAMES) -> list[int]:
    """Up to ``count`` frame indices spread evenly over ``[start, stop)``."""
    n = min(count, stop - start)
    return sorted({int(i) for i in np.linspace(start, stop - 1, n).round()}) if n > 0 else []


def choose_tip(model: SessionModel, frames: Sequence[tuple[int, Sequence[NDArray[np.uint8]]]]) -> TipChoice:
    """The end ("flat" or "round") that explains the tips of ``frames`` best.

    ``frames``: (index, per camera (H, W) uint8 grey image). Each is
    reconstructed from its hull; frames without a curve are skipped.
    """
    flat = round_ = 0.0
    used = 0
    for index, images in frames:
        result, masks = reconstruct_with_silhouettes(index, images, model)
        if result.status != "ok" or result.centerline_mm is None or not np.isfinite(result.radius_mm):
            continue
        contrasts = frame_contrasts(images, model)
        coverages = pixel_coverages(contrasts, masks)
        # The end's own radius: a tapered or stepped tube is thinner there.
        radius = float(result.radii_mm[-1]) if result.radii_mm is not None else result.radius_mm
        bent = [
            bend_tip_to_pixels(
                result.centerline_mm,
                model.cameras,
                masks,
                contrasts,
                radius,
                spans_radii=_SPANS_RADII,
                steps_mm=_STEPS_MM,
                coverages=coverages,
                cap=cap,
            )
            for cap in ("flat", "round")
        ]
        costs = coverage_mismatch(
            bent, model.cameras, masks, contrasts, radius, coverages=coverages, cap=("flat", "round")
        )
        flat += costs[0]
        round_ += costs[1]
        used += 1
    tip = "round" if used and round_ < flat else "flat"
    return TipChoice(tip, used, flat, round_)


def with_session_tip(
    model: SessionModel, video_paths: Sequence[Path], start: int, stop: int
) -> tuple[SessionModel, TipChoice | None]:
    """``model`` with its tube end settled: the settings' "flat" or "round" as they are;
    for "auto", the end :func:`choose_tip` finds on frames spread over ``[start, stop)``
    of the videos (and that choice, for the summary)."""
    settings = model.settings
    if settings.manipulator.tip != "auto" or settings.centerline.method != "fit":
        return model, None
    choice = choose_tip(model, decode_frames(video_paths, sample_frames(start, stop)))
    return dataclasses.replace(model, tip=choice.tip), choice
