"""Image formation: analytic tube masks, shading, textured backgrounds, sensor noise.

Pure functions of arrays: cameras and centrelines in, images out. The exact
tube geometry comes from :mod:`pipeline.synth.raycast`.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from .radius_profiles import Disks
from .raycast import Tube, camera_rays, cone_candidates, cone_candidates_brute, intersect, ray_directions
from .rig import SynthCamera

# Grey levels for polarity "dark"; "bright" is the photographic negative (255 - v).
TUBE_GREY = (20.0, 70.0)  # fully turned away from / facing the light
BACKGROUND_GREY = (115.0, 225.0)  # texture range
# A threshold halfway between the brightest tube and the darkest background, so
# that noise (sigma NOISE_SIGMA) and compression never cross it away from edges.
THRESHOLD_DARK = 92
NOISE_SIGMA = 2.5
RIM_SUPERSAMPLE = 3
# Key light from above and one side (world frame); a weaker headlight from each
# camera keeps the side away from the key light from going flat.
LIGHT_DIR = np.array([0.35, -0.45, 1.0]) / np.linalg.norm([0.35, -0.45, 1.0])
KEY_WEIGHT = 0.65
# Flicker: the whole scene's brightness scales by up to this fraction, independently
# per frame (mains-frequency lighting beating against the frame rate). At 4 % the
# brightest tube (73) and the darkest background (110) stay clear of THRESHOLD_DARK.
FLICKER = 0.04


def threshold_for(polarity: str) -> int:
    """The grey threshold that separates the rendered tube from its background."""
    return THRESHOLD_DARK if polarity == "dark" else 255 - THRESHOLD_DARK


def background_texture(width: int, height: int, *, seed: int, camera_index: int) -> NDArray[np.float64]:
    """A smooth random texture, fixed per (seed, camera): (H, W) float64 grey levels
    spanning BACKGROUND_GREY (polarity "dark"). Its features scale with the image, so
    that a larger image shows the same scene more finely."""
    rng = np.random.default_rng([seed, camera_index, 7])
    tex = np.zeros((height, width))
    scale = width / 320.0
    # Blurred white noise at three scales: blotches, patches and fine grain.
    for sigma, weight in ((24.0, 1.0), (8.0, 0.5), (2.0, 0.15)):
        layer = cv2.GaussianBlur(rng.standard_normal((height, width)), (0, 0), sigma * scale)
        tex += weight * layer / layer.std()
    # A gentle illumination gradient, different per camera.
    angle = rng.uniform(0.0, 2.0 * np.pi)
    v, u = np.mgrid[0:height, 0:width]
    tex += 0.8 * (np.cos(angle) * (u / width - 0.5) + np.sin(angle) * (v / height - 0.5))
    lo, hi = BACKGROUND_GREY
    return lo + (hi - lo) * (tex - tex.min()) / (tex.max() - tex.min())


def flicker_gains(seed: int, frames: int) -> NDArray[np.float64]:
    """Each frame's scene brightness factor, (F,) in [1 - FLICKER, 1 + FLICKER]; drawn per
    frame from (seed, frame) so that a frame renders the same on its own."""
    return np.array(
        [1.0 + FLICKER * np.random.default_rng([seed, f, 0xF11C]).uniform(-1.0, 1.0) for f in range(frames)]
    )


def _shade(normal: NDArray[np.float64], dirs: NDArray[np.float64]) -> NDArray[np.float64]:
    """Lambertian grey level (polarity "dark") of surface points, (Q, 3) normals -> (Q,)."""
    key = np.clip(normal @ LIGHT_DIR, 0.0, None)
    head = np.abs(np.einsum("ij,ij->i", normal, dirs))
    lo, hi = TUBE_GREY
    return lo + (hi - lo) * (KEY_WEIGHT * key + (1.0 - KEY_WEIGHT) * head)


def _subpixel_offsets(k: int) -> NDArray[np.float64]:
    """(k*k, 2) offsets of a k x k grid of sample points inside a pixel, in px."""
    g = (np.arange(k) + 0.5) / k - 0.5
    du, dv = np.meshgrid(g, g)
    return np.stack([du.ravel(), dv.ravel()], axis=1)


def tube_coverage(
    camera: SynthCamera, tube: Tube, *, supersample: int = RIM_SUPERSAMPLE
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Fraction of each pixel covered by the tube, and the mean grey level of the
    covered part (polarity "dark").

    Pixel centres are cast first; only pixels on the rim of that mask (a centre
    that disagrees with one of its 8 neighbours) get ``supersample`` x ``supersample``
    sub-pixel rays.

    Returns
    -------
    coverage : (H, W) float64 in [0, 1].
    grey : (H, W) float64, defined where coverage > 0.
    """
    rays = camera_rays(camera)
    h, w = camera.height, camera.width
    t, normal = intersect(tube, rays.origin_mm, rays.dirs, cone_candidates(tube, rays))
    hit = np.isfinite(t)
    grey_flat = np.zeros(h * w)
    grey_flat[hit] = _shade(normal[hit], rays.dirs[hit])
    coverage = hit.astype(np.float64).reshape(h, w)
    grey = grey_flat.reshape(h, w)
    if supersample <= 1 or not hit.any():
        return coverage, grey
    mask8 = hit.reshape(h, w).astype(np.uint8)
    kernel = np.ones((3, 3), np.uint8)
    rim = cv2.dilate(mask8, kernel) != cv2.erode(mask8, kernel)
    rv, ru = np.nonzero(rim)
    offsets = _subpixel_offsets(supersample)
    uv = (np.stack([ru, rv], axis=1)[:, None, :] + offsets[None]).reshape(-1, 2).astype(np.float64)
    dirs = ray_directions(camera, uv)
    t_sub, n_sub = intersect(tube, rays.origin_mm, dirs, cone_candidates_brute(tube, rays.origin_mm, dirs))
    hit_sub = np.isfinite(t_sub)
    shade_sub = np.zeros(len(uv))
    shade_sub[hit_sub] = _shade(n_sub[hit_sub], dirs[hit_sub])
    n_hit = hit_sub.reshape(len(ru), -1).sum(axis=1)
    coverage[rv, ru] = n_hit / offsets.shape[0]
    with np.errstate(invalid="ignore"):
        grey[rv, ru] = np.where(n_hit > 0, shade_sub.reshape(len(ru), -1).sum(axis=1) / n_hit, 0.0)
    return coverage, grey


def tube_mask(
    camera: SynthCamera,
    centerline_mm: NDArray[np.float64],
    radius_mm: float | NDArray[np.float64],
    *,
    supersample: int = 1,
    tip: str = "flat",
    disks: Disks | None = None,
) -> NDArray[np.bool_]:
    """The exact analytic silhouette of a tube.

    Parameters
    ----------
    camera : the true camera.
    centerline_mm : (N, 3) float64, world frame, base -> tip.
    radius_mm : tube radius, one or (N,) per centreline point.
    supersample : 1 = the pixel centre's ray decides; k > 1 = rim pixels are in the
        mask when at least half of their k x k sub-pixel rays hit.
    tip, disks : the tube's end ("flat" or "round") and spacer disks (see :class:`Tube`).

    Returns
    -------
    (H, W) bool.
    """
    coverage, _ = tube_coverage(
        camera, Tube.from_centerline(centerline_mm, radius_mm, tip=tip, disks=disks), supersample=supersample
    )
    return coverage >= 0.5


def render_frame(
    cameras: list[SynthCamera],
    centerline_mm: NDArray[np.float64],
    radius_mm: float | NDArray[np.float64],
    backgrounds: list[NDArray[np.float64]],
    *,
    polarity: str = "dark",
    seed: int = 0,
    frame_index: int = 0,
    noise_sigma: float = NOISE_SIGMA,
    supersample: int = RIM_SUPERSAMPLE,
    tip: str = "flat",
    disks: Disks | None = None,
    gain: float = 1.0,
) -> list[NDArray[np.uint8]]:
    """One frame per camera, before video compression.

    Parameters
    ----------
    cameras : the true cameras.
    centerline_mm : (N, 3) float64, world frame, base -> tip.
    radius_mm : tube radius, one or (N,) per centreline point.
    backgrounds : per camera, (H, W) float64 grey levels (polarity "dark"),
        from :func:`background_texture`.
    polarity : "dark" (dark tube on a light scene) or "bright" (the negative).
    seed, frame_index : the sensor noise is drawn from (seed, frame_index, camera),
        so any frame renders the same on its own as in a whole session.
    noise_sigma : Gaussian sensor noise, grey levels.
    supersample : sub-pixel rays per side on the silhouette rim (anti-aliasing).
    tip, disks : the tube's end ("flat" or "round") and spacer disks (see :class:`Tube`).
    gain : the scene's brightness factor (flicker), applied before the sensor noise.

    Returns
    -------
    per camera, (H, W) uint8.
    """
    tube = Tube.from_centerline(centerline_mm, radius_mm, tip=tip, disks=disks)
    images = []
    for c, (camera, background) in enumerate(zip(cameras, backgrounds, strict=True)):
        coverage, grey = tube_coverage(camera, tube, supersample=supersample)
        img = background * (1.0 - coverage) + grey * coverage
        if polarity == "bright":
            img = 255.0 - img
        if gain != 1.0:
            img = gain * img
        rng = np.random.default_rng([seed, frame_index, c])
        img = img + noise_sigma * rng.standard_normal(img.shape)
        images.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    return images
