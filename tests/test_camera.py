"""Camera conventions: projection and rays agree, checked against the rig's own numbers."""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.camera import Camera
from pipeline.synth.rig import make_rig


def _camera(i: int = 0) -> Camera:
    c = make_rig()[i]
    rvec = cv2.Rodrigues(c.R)[0].ravel()
    return Camera(c.name, (c.width, c.height), c.K, c.dist, rvec, c.t)


def test_ray_through_projection_returns_to_the_point() -> None:
    cam = _camera()
    points = np.random.default_rng(0).uniform(0, 256, (200, 3))
    rays = cam.rays(cam.project(points))
    expected = points - cam.center_mm
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    # Iterative undistortion converges far below 1e-9 at these mild distortions.
    np.testing.assert_allclose(rays, expected, atol=1e-9)


def test_points_behind_the_camera_do_not_project() -> None:
    cam = _camera(1)
    behind = cam.center_mm - 100.0 * (np.array([128.0, 128, 128]) - cam.center_mm)
    assert np.isnan(cam.project(behind[None])).all()
