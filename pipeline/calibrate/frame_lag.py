"""Whether each camera's video keeps time with the others': a video started a few frames late.

Cameras started by hand, or a stream that dropped frames at its start, leave one video's
frame i showing another moment than the others' frame i. Each frame's tube is then
fitted to views of two moments, and a refinement of the cameras takes the difference for
cameras that moved. Told apart by the moving tube: fitted to the other views alone, a
frame's tube re-projects onto the camera's own silhouette best at the frame of that
camera that shows the same moment. Over the session's sample frames, a camera whose
silhouettes d frames away match the others' tubes clearly better than those of the same
frame is out of step by d frames (:func:`camera_lags`).

On a rendered 300-frame `bend_rotate` session (`pipeline synth --frames 300`; 2026-12-06),
its sample frames' tubes, fitted to the two other views, matched every camera's own
silhouettes best in the same frame; with cam1's video moved by 1, 3 and -2 frames, cam1's
silhouettes at the moved frame left 0.68, 0.33 and 0.45 times the pixels of the same frame
unexplained, all 14 frames the tube moved in matching best on that side, while the other
cameras' (whose tubes were fitted to cam1's view too) were best a frame away at 0.91-0.97,
7-9 of the 14 frames on that side. docs/calibration.md has the measures on drawn sessions
that set the bars below.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..reconstruct.frame import camera_silhouette, frame_contrasts, frame_silhouettes
from ..reconstruct.frame_task import FrameMap, map_here
from ..reconstruct.model import SessionModel
from ..reconstruct.quality import tube_mask
from ..reconstruct.tube_fit import fit_tube
from .adjust import Tube

# Frames either way a camera's silhouettes are compared at: a lag of up to one less is named.
MAX_LAG_FRAMES = 4
# A camera is out of step where its silhouettes at the lag leave at most this share of the
# pixels they leave in step (summed over the frames) ...
LAG_SHARE = 0.8
# ... and at least this share of the frames whose tube moved (at least LAG_FRAMES of them)
# match it best on the same side (earlier or later): each frame's own best is less sure
# than the sum's, the tube's course off by as much in places as it moves in a frame.
LAG_VOTES = 2.0 / 3.0
LAG_FRAMES = 6
# The tube refitted to the other views: rounds of the fit, and how far from the tube
# fitted to every view its sides are sought (radii).
_REFIT_ROUNDS = 2
_REFIT_SEEK_RADII = 0.6

FloatArray = NDArray[np.float64]
Image = NDArray[np.uint8]
# (camera index, first frame, stop) -> that camera's grey images of frames first <= i < stop
# (None where its video has none).
FramesOfCamera = Callable[[int, int, int], Sequence[Image | None]]


@dataclass(frozen=True)
class CameraLag:
    """A camera whose video is out of step with the others'.

    name : the camera.
    frames : its frame ``i + frames`` shows the moment of the others' frame ``i``
        (negative: its video started late, its frame i is a later moment).
    share : the pixels its silhouettes at the lag leave unexplained, as a share of those of
        the same frame (summed over the frames).
    votes, frames_read : of the frames whose tube moved, how many match it best on the same
        side (earlier or later).
    """

    name: str
    frames: int
    share: float
    votes: int
    frames_read: int

    def describe(self) -> str:
        """The problem line of the summary."""
        n = abs(self.frames)
        count = "frame" if n == 1 else f"{n} frames"
        if self.frames < 0:
            when, fix = "after", f"cut its first {count}"
        else:
            when, fix = "before", f"cut the first {count} of the other videos"
        return (
            f"camera {self.name}'s video seems to have started {n} frame{'' if n == 1 else 's'} {when} "
            f"the others: its frame i{self.frames:+d} shows what their frame i shows ({self.votes} of "
            f"{self.frames_read} sample frames agree); the cameras were kept as given; {fix} and rerun"
        )


@dataclass(frozen=True, eq=False)
class LagContext:
    """What each sample frame's comparison needs (:func:`frame_mismatches`): the session's
    model, each camera's frames (``frames_of``) and how far either way to compare them."""

    model: SessionModel
    frames_of: FramesOfCamera
    reach: int = MAX_LAG_FRAMES


def frame_mismatches(index: int, axis: tuple[FloatArray, FloatArray], context: LagContext) -> FloatArray:
    """(C, 2 reach + 1) for one sample frame ``index`` and its tube fitted to every view
    (``axis``: (K, 3) points and (K,) radii, mm): per camera, the pixels its silhouettes of
    frames ``index - reach`` to ``index + reach`` leave unexplained by the tube fitted again to
    the other views (NaN rows where a frame is missing or no tube was read)."""
    model, reach = context.model, context.reach
    cameras = model.cameras
    out = np.full((len(cameras), 2 * reach + 1), np.nan)
    if index < reach:
        return out  # too near the session's start for a frame either way
    read = [context.frames_of(k, index - reach, index + reach + 1) for k in range(len(cameras))]
    spans = [[image for image in span if image is not None] for span in read]
    if any(len(span) < 2 * reach + 1 for span in spans):
        return out  # near the session's end, or a frame that does not decode: no comparison
    images = [span[reach] for span in spans]
    contrasts = frame_contrasts(images, model)
    masks = frame_silhouettes(images, model)
    points_mm, radii_mm = axis
    for k, camera in enumerate(cameras):
        others = [v for v in range(len(cameras)) if v != k]
        fit = fit_tube(
            points_mm,
            [cameras[v] for v in others],
            [contrasts[v] for v in others],
            radius_mm=float(np.median(radii_mm)),
            radii_mm=radii_mm,
            base_fixed=False,
            iterations=_REFIT_ROUNDS,
            seek_radii=_REFIT_SEEK_RADII,
            masks=[masks[v] for v in others],
        )
        if not np.isfinite(fit.radius_mm):
            continue
        drawn = tube_mask(camera, fit.points_mm, fit.radii_mm if fit.radii_mm is not None else fit.radius_mm)
        out[k] = [np.count_nonzero(camera_silhouette(image, model, k) ^ drawn) for image in spans[k]]
    return out


def camera_lags(
    model: SessionModel,
    tubes: Sequence[tuple[int, Tube]],
    frames_of: FramesOfCamera,
    map_frames: FrameMap = map_here,
    *,
    reach: int = MAX_LAG_FRAMES,
) -> list[CameraLag]:
    """The cameras out of step with the others, from the sample frames' ``tubes``
    ((frame index, tube fitted to every view) each) and each camera's frames around them
    (``frames_of``), compared frame by frame by ``map_frames``; [] where none is, or the rig
    has fewer than three cameras (a tube fitted to one view is not placed)."""
    cameras = model.cameras
    if len(cameras) < 3 or not tubes:
        return []
    axes = [(index, (tube.points_mm, tube.radii_mm)) for index, tube in tubes]
    counts = np.array(map_frames(frame_mismatches, axes, LagContext(model, frames_of, reach)))  # (F, C, 2R+1)
    lags = []
    for k, camera in enumerate(cameras):
        compared = counts[:, k][np.isfinite(counts[:, k]).all(axis=1)]
        unexplained = compared.sum(axis=0)
        # Per frame whose tube moved (the frames tell the moments apart): where its own best lies.
        moved = compared[compared.max(axis=1) > compared.min(axis=1)]
        sides = np.sign(np.argmin(moved, axis=1) - reach).tolist() if len(moved) else []
        lag = int(np.argmin(unexplained)) - reach if len(compared) else 0
        in_step = unexplained[reach] if len(compared) else 0.0
        # A least at the reach's end may lie beyond it: no lag to name.
        if not 0 < abs(lag) < reach or len(sides) < LAG_FRAMES or not in_step > 0:
            continue
        share = float(unexplained[lag + reach] / in_step)
        votes = sides.count(int(np.sign(lag)))
        if share <= LAG_SHARE and votes >= LAG_VOTES * len(sides):
            lags.append(CameraLag(camera.name, lag, share, votes, len(sides)))
    return lags
