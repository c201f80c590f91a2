"""A dark object in one camera's background: a blob a grey threshold also picks up, in that view only.

It is part of the scene, so it is painted into that camera's background texture (and
so also into its empty-scene image), where the tube never passes in front of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .raycast import project_points
from .rig import SynthCamera

DISTRACTOR_GREY = 40.0  # polarity "dark": as dark as the tube's shaded side
CLEARANCE_PX = 10.0  # kept between the blob and the tube's image, at 320x240


@dataclass(frozen=True)
class Distractor:
    """An elliptical blob in camera ``camera_index``'s image.

    center_px : (2,) (u, v); axes_px : (2,) semi-axes; angle : of the first axis from +u (rad).
    """

    camera_index: int
    center_px: NDArray[np.float64]
    axes_px: NDArray[np.float64]
    angle: float


def _inside(d: Distractor, uv: NDArray[np.float64]) -> NDArray[np.float64]:
    """Signed elliptical distance of pixel positions (..., 2) to the blob's edge, in px
    (approximately): negative inside."""
    c, s = np.cos(d.angle), np.sin(d.angle)
    rel = uv - d.center_px
    x = (c * rel[..., 0] + s * rel[..., 1]) / d.axes_px[0]
    y = (-s * rel[..., 0] + c * rel[..., 1]) / d.axes_px[1]
    return (np.sqrt(x * x + y * y) - 1.0) * float(d.axes_px.min())


def place_distractor(
    cameras: list[SynthCamera],
    centerlines_mm: NDArray[np.float64],
    widest_radius_mm: float,
    *,
    seed: int,
    tries: int = 200,
) -> Distractor:
    """A blob in a random camera, placed away from every pose of the tube in that view.

    centerlines_mm : (F, N, 3) mm, world frame; widest_radius_mm : the tube's widest radius.
    Falls back to the last candidate if none of ``tries`` clears the tube (a crowded view).
    """
    rng = np.random.default_rng([seed, 0xD15])
    index = int(rng.integers(len(cameras)))
    cam = cameras[index]
    scale = cam.width / 320.0
    pts = centerlines_mm[:: max(1, len(centerlines_mm) // 40), ::4].reshape(-1, 3)
    uv = project_points(cam, pts)
    depth = np.linalg.norm(pts - cam.center, axis=1)
    reach = cam.K[0, 0] * widest_radius_mm / depth + CLEARANCE_PX * scale  # tube half-width + clearance, px
    candidate = Distractor(index, np.zeros(2), np.ones(2), 0.0)
    for _ in range(tries):
        axes = rng.uniform(10.0, 22.0, 2) * scale
        margin = axes.max() + 4.0 * scale
        center = rng.uniform([margin, margin], [cam.width - margin, cam.height - margin])
        candidate = Distractor(index, center, axes, float(rng.uniform(0.0, np.pi)))
        if np.all(_inside(candidate, uv) > reach):
            break
    return candidate


def paint_distractor(background: NDArray[np.float64], d: Distractor) -> NDArray[np.float64]:
    """The background (H, W) grey levels (polarity "dark") with the blob on it, its edge
    anti-aliased over ~1 px."""
    v, u = np.mgrid[0 : background.shape[0], 0 : background.shape[1]]
    cover = np.clip(0.5 - _inside(d, np.stack([u, v], axis=-1).astype(np.float64)), 0.0, 1.0)
    return background * (1.0 - cover) + DISTRACTOR_GREY * cover
