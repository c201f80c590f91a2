"""Camera conventions: projection and rays agree, checked against the rig's own numbers."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from pipeline.geometry.camera import Camera, project_in_views
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


@pytest.mark.parametrize("n_coefficients", [4, 5, 8, 12, 14])
def test_normalized_to_pixels_equals_cv2_project_points(n_coefficients: int) -> None:
    rng = np.random.default_rng(n_coefficients)
    dist = rng.normal(0.0, 0.05, n_coefficients)
    if n_coefficients == 14:
        dist[12:] = [0.02, -0.03]  # a tilted sensor, radians
    base = _camera(2)
    cam = Camera("c", base.size_px, base.matrix, dist, base.rotation, base.translation_mm)
    points = rng.uniform(0, 256, (500, 3))
    x_cam = cam.to_camera(points)
    u, v = cam.normalized_to_pixels(x_cam[:, 0] / x_cam[:, 2], x_cam[:, 1] / x_cam[:, 2])
    # Same float64 formula as OpenCV's; only the order of operations differs (~1e-13 px).
    np.testing.assert_allclose(np.column_stack([u, v]), cam.project(points), rtol=0, atol=1e-9)


@pytest.mark.parametrize("n_coefficients", [4, 5, 8])
def test_project_in_views_equals_each_cameras_project_bit_for_bit(n_coefficients: int) -> None:
    rng = np.random.default_rng(10 + n_coefficients)
    cams = []
    for i in range(3):
        base = _camera(i)
        dist = rng.normal(0.0, 0.05, n_coefficients)  # stronger than the rig's, all terms on
        cams.append(Camera(base.name, base.size_px, base.matrix, dist, base.rotation, base.translation_mm))
    # Inside the workspace, and far around it (some points behind some cameras).
    points = np.vstack([rng.uniform(0, 256, (300, 3)), rng.normal(128.0, 2000.0, (300, 3))])
    got = project_in_views(cams, points)
    assert got.shape == (3, 600, 2)
    assert np.isnan(got).any()  # the far points reach behind a camera
    for j, cam in enumerate(cams):
        # OpenCV's own arithmetic in its order: exactly equal, no tolerance (the
        # tube fit is chaotic on some loop frames: one rounding moves a curve).
        np.testing.assert_array_equal(got[j], cam.project(points))
