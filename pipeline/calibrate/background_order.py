"""Whether each background image is its camera's: a scene matches its own view pixel for pixel.

With ``[silhouette] method = "background"`` each frame is compared with its camera's
background image. Two images swapped (``background/cam1.png`` holding cam2's scene) make
every frame's silhouette most of the image: each frame then fails or is flagged, and
nothing says why. A camera's scene is the median of its sample frames (the tube moves,
the scene does not); its own background correlates with it nearly perfectly, another
camera's (another viewpoint) barely. On three rendered sessions (`pipeline synth --shape
random`, ten frames; seeds 1-3, both arrangements, one with a dark object and flicker, one
of two cameras; 2026-12-05) each background correlated 0.75-0.91 with its own camera's
scene (sensor noise and the video's compression keep it from 1) and -0.17-0.26 with the
others'.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..errors import SessionError

# A background is taken for another camera's where it correlates with that camera's scene
# at least this much, and this much better than with its own.
MATCHES = 0.6
MARGIN = 0.3


def scene_correlations(
    backgrounds: Sequence[NDArray[np.uint8]], frames: Sequence[tuple[int, Sequence[NDArray[np.uint8]]]]
) -> NDArray[np.float64]:
    """(C, C): entry [i, j] the correlation of camera i's background with camera j's scene
    (the median of its images in ``frames``: (index, per camera grey image)); NaN where the
    two differ in size or either is flat."""
    cameras = len(backgrounds)
    scenes = [np.median(np.stack([images[j] for _, images in frames]), axis=0) for j in range(cameras)]
    out = np.full((cameras, cameras), np.nan)
    for i, background in enumerate(backgrounds):
        for j, scene in enumerate(scenes):
            if background.shape == scene.shape:
                out[i, j] = _correlation(background, scene)
    return out


def _correlation(a: NDArray[np.generic], b: NDArray[np.generic]) -> float:
    """Pearson's correlation of two images' pixels; NaN where either is flat."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return float(np.corrcoef(np.ravel(a), np.ravel(b))[0, 1])


def check_background_order(
    backgrounds: Sequence[NDArray[np.uint8] | None],
    frames: Sequence[tuple[int, Sequence[NDArray[np.uint8]]]],
    camera_names: Sequence[str],
    folder: Path,
) -> None:
    """SessionError naming the background images (``folder``/<camera>.png, one per camera of
    ``camera_names``, in calibration order) that match another camera's scene clearly better
    than their own (``MATCHES``, ``MARGIN``); nothing otherwise, or without backgrounds."""
    if not frames or any(b is None for b in backgrounds):
        return
    correlation = scene_correlations([b for b in backgrounds if b is not None], frames)
    moves = []
    for i, row in enumerate(correlation):
        if np.isnan(row).all():
            continue
        j = int(np.nanargmax(row))
        own = row[i]
        if j != i and row[j] >= MATCHES and not own >= row[j] - MARGIN:
            moves.append(
                f"{camera_names[i]}.png looks like {camera_names[j]}'s scene (correlation "
                f"{row[j]:.2f}, against {own:.2f} with {camera_names[i]}'s)"
            )
    if moves:
        raise SessionError(
            f"{folder}: the background images do not match their cameras: {'; '.join(moves)}; "
            "rename them, or take each camera's background again"
        )
