"""The synthetic camera rig: three cameras placed like the original set-up (or two of them).

Shared by the session renderer and the calibration-board renderer so that both
film with the same (true) cameras. Deliberately independent of
``pipeline.geometry.camera``: the renderer is the oracle the reconstruction is tested
against, so it keeps its own description of a camera.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

WORKSPACE_CENTER_MM = np.array([128.0, 128.0, 128.0])
IMAGE_SIZE = (320, 240)  # width, height in pixels

# Azimuth (deg), distance from the workspace centre (mm), elevation (deg) and focal
# length (px) per camera. The oblique rig is the original's compromise: cameras not
# 90 degrees apart so that one board on the floor is seen by all three.
ARRANGEMENTS: dict[str, tuple[tuple[float, float, float, float], ...]] = {
    "oblique": ((-20.0, 620.0, 28.0, 312.0), (95.0, 700.0, 34.0, 360.0), (215.0, 560.0, 22.0, 280.0)),
    "ninety": ((0.0, 620.0, 24.0, 322.0), (90.0, 680.0, 26.0, 350.0), (180.0, 600.0, 22.0, 312.0)),
}


@dataclass(frozen=True, eq=False)
class SynthCamera:
    """A true camera: OpenCV conventions, x_cam = R @ X_world + t (mm), K and (k1,k2,p1,p2,k3)."""

    name: str
    width: int
    height: int
    K: NDArray[np.float64]
    dist: NDArray[np.float64]
    R: NDArray[np.float64]
    t: NDArray[np.float64]

    @property
    def center(self) -> NDArray[np.float64]:
        return -self.R.T @ self.t


def look_at(center_mm: NDArray[np.float64], target_mm: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation camera-from-world for a camera at ``center_mm`` looking at ``target_mm``,
    with world +z up in the image (OpenCV: x right, y down, z forward)."""
    z = target_mm - center_mm
    z = z / np.linalg.norm(z)
    down = np.array([0.0, 0.0, -1.0])
    y = down - (down @ z) * z
    y = y / np.linalg.norm(y)
    x = np.cross(y, z)
    return np.stack([x, y, z])


def make_rig(
    arrangement: str = "oblique", *, size: tuple[int, int] = IMAGE_SIZE, cameras: int = 3
) -> list[SynthCamera]:
    """The true cameras of ``arrangement`` ("oblique" or "ninety").

    size : (width, height) px, a multiple of 320x240: the same lenses on a finer sensor
        (focal lengths scaled; principal points scaled about pixel corners, OpenCV's
        pixel-centre convention: c' = s (c + 0.5) - 0.5).
    cameras : 3, or 2 for the rig without its last camera.
    """
    if arrangement not in ARRANGEMENTS:
        raise ValueError(f"unknown arrangement {arrangement!r}; use one of {tuple(ARRANGEMENTS)}")
    if cameras not in (2, 3):
        raise ValueError(f"a rig has 2 or 3 cameras, got {cameras}")
    w, h = size
    scale = w / IMAGE_SIZE[0]
    if w * IMAGE_SIZE[1] != h * IMAGE_SIZE[0] or scale < 1 or scale != int(scale):
        raise ValueError(f"image size must be a whole multiple of {IMAGE_SIZE}, got {size}")
    cams = []
    for i, (az_deg, dist_mm, el_deg, f_px) in enumerate(ARRANGEMENTS[arrangement][:cameras]):
        az, el = np.radians(az_deg), np.radians(el_deg)
        offset = dist_mm * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        center = WORKSPACE_CENTER_MM + offset
        R = look_at(center, WORKSPACE_CENTER_MM)
        # Principal points a little off centre, per lens; at 320x240 (scale 1) these are
        # exactly w/2 - 0.5 + 1.5 (i - 1) and h/2 - 0.5 - i.
        cx = scale * (IMAGE_SIZE[0] / 2 + 1.5 * (i - 1)) - 0.5
        cy = scale * (IMAGE_SIZE[1] / 2 - i) - 0.5
        f = f_px * scale
        K = np.array([[f, 0.0, cx], [0.0, f * 1.002, cy], [0, 0, 1]])
        # Mild barrel distortion, slightly different per lens.
        dist = np.array([-0.08 - 0.02 * i, 0.03, 0.0005 * (i - 1), -0.0004, 0.0])
        cams.append(SynthCamera(f"cam{i}", w, h, K, dist, R, -R @ center))
    return cams


def calibration_document(cameras: list[SynthCamera], *, metadata: dict[str, Any]) -> dict[str, Any]:
    """calibration.toml (aniposelib layout) of the true ``cameras``, with ``metadata``."""
    doc: dict[str, Any] = {}
    for i, cam in enumerate(cameras):
        rvec, _ = cv2.Rodrigues(cam.R)
        doc[f"cam_{i}"] = {
            "name": cam.name,
            "size": [cam.width, cam.height],
            "matrix": cam.K.tolist(),
            "distortions": cam.dist.tolist(),
            "rotation": np.asarray(rvec, dtype=float).ravel().tolist(),
            "translation": cam.t.tolist(),
        }
    doc["metadata"] = metadata
    return doc
