"""A calibrated camera: the one place that knows the projection conventions.

Convention (OpenCV, "camera from world"): ``x_cam = R @ X_world + t``, with R the
Rodrigues vector ``rotation`` and t ``translation_mm``; pixels follow OpenCV's
distortion model (k1, k2, p1, p2, k3) and intrinsic matrix K. All lengths are
millimetres in the world frame of calibration.toml.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property, lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

# The world frame's name, beside the cameras' (each its own name) in the recordings' frames.
WORLD_FRAME = "world"

# Fewer points than this are projected view by view with cv2.projectPoints: the
# array version's ~30 calls cost more than three small projectPoints calls.
_MIN_POINTS_IN_VIEWS = 48


@dataclass(frozen=True, eq=False)
class Camera:
    """One calibrated camera.

    Attributes
    ----------
    name : camera name; the video's file stem.
    size_px : (width, height) of its images in pixels.
    matrix : (3, 3) float64 intrinsic matrix K (pixels).
    distortions : (5,) float64 OpenCV coefficients k1, k2, p1, p2, k3.
    rotation : (3,) float64 Rodrigues vector, camera from world.
    translation_mm : (3,) float64, camera from world, millimetres.
    """

    name: str
    size_px: tuple[int, int]
    matrix: FloatArray
    distortions: FloatArray
    rotation: FloatArray
    translation_mm: FloatArray

    @property
    def width(self) -> int:
        return self.size_px[0]

    @property
    def height(self) -> int:
        return self.size_px[1]

    @cached_property
    def camera_from_world(self) -> FloatArray:
        """(3, 3) rotation matrix R with x_cam = R @ X_world + t (read-only).

        Computed once per camera: it is used on every projection of every frame.
        """
        rot = np.asarray(cv2.Rodrigues(np.asarray(self.rotation, dtype=np.float64))[0], dtype=np.float64)
        rot.flags.writeable = False
        return rot

    @cached_property
    def focal_px(self) -> float:
        """The mean of fx and fy (pixels per unit of x/z): a length's image size at
        unit depth. Computed once per camera (it sizes every drawn disc)."""
        return float(np.mean(np.diag(self.matrix)[:2]))

    @property
    def center_mm(self) -> FloatArray:
        """(3,) optical centre in the world frame: -R^T t."""
        return -self.camera_from_world.T @ self.translation_mm

    def to_camera(self, points_mm: FloatArray) -> FloatArray:
        """(N, 3) world points -> (N, 3) camera-frame points, mm."""
        return np.asarray(points_mm, dtype=np.float64) @ self.camera_from_world.T + self.translation_mm

    def project(self, points_mm: FloatArray) -> FloatArray:
        """(N, 3) world points (mm) -> (N, 2) float64 pixel coordinates, distortion included.

        Points behind the camera get NaN.
        """
        pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        if len(pts) == 0:
            return np.zeros((0, 2))
        px, _ = cv2.projectPoints(pts, self.rotation, self.translation_mm, self.matrix, self.distortions)
        px = np.asarray(px, dtype=np.float64).reshape(-1, 2)
        px[self.to_camera(pts)[:, 2] <= 0] = np.nan
        return px

    def normalized_to_pixels(self, x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Normalised image coordinates (x/z, y/z) -> distorted pixel coordinates (u, v).

        The same model as ``cv2.projectPoints`` (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4
        [tau_x tau_y]]]]), written out in float64 NumPy so that callers projecting millions
        of points that share structure (a voxel grid) can build x and y cheaply themselves.

        Parameters
        ----------
        x, y : float64 arrays of one shape, camera frame, unitless.

        Returns
        -------
        u, v : float64 arrays of that shape, pixels (OpenCV: pixel centres at integers).
        """
        k = np.zeros(14)
        dist = np.asarray(self.distortions, dtype=np.float64).ravel()
        k[: len(dist)] = dist
        # In-place arithmetic: this runs on millions of points per session (build_grid).
        x2 = x * x
        y2 = y * y
        r2 = x2 + y2
        radial = r2 * k[4]  # 1 + k1 r2 + k2 r4 + k3 r6, by Horner
        radial += k[1]
        radial *= r2
        radial += k[0]
        radial *= r2
        radial += 1.0
        if k[5:8].any():  # rational model
            den = r2 * k[7]
            den += k[6]
            den *= r2
            den += k[5]
            den *= r2
            den += 1.0
            radial /= den
        xy2 = x * y
        xy2 *= 2.0
        xd = x * radial
        yd = y * radial
        # Tangential: xd += p1 2xy + p2 (r2 + 2x^2); yd += p1 (r2 + 2y^2) + p2 2xy.
        x2 *= 2.0
        x2 += r2
        x2 *= k[3]
        xd += x2
        y2 *= 2.0
        y2 += r2
        y2 *= k[2]
        yd += y2
        xd += k[2] * xy2
        yd += k[3] * xy2
        if k[8:12].any():  # thin prism
            xd = xd + r2 * (k[8] + r2 * k[9])
            yd = yd + r2 * (k[10] + r2 * k[11])
        if k[12:14].any():  # tilted sensor (Scheimpflug), OpenCV's computeTiltProjectionMatrix
            tilt = _tilt_matrix(k[12], k[13])
            w = tilt[2, 0] * xd + tilt[2, 1] * yd + tilt[2, 2]
            w = np.where(w == 0.0, 1.0, 1.0 / np.where(w == 0.0, 1.0, w))
            xd, yd = (
                w * (tilt[0, 0] * xd + tilt[0, 1] * yd + tilt[0, 2]),
                w * (tilt[1, 0] * xd + tilt[1, 1] * yd + tilt[1, 2]),
            )
        m = self.matrix
        xd *= m[0, 0]
        xd += m[0, 2]
        yd *= m[1, 1]
        yd += m[1, 2]
        return xd, yd

    def undistort_pixels(self, pixels: FloatArray) -> FloatArray:
        """(N, 2) distorted pixels -> (N, 2) normalised image coordinates (x/z, y/z)."""
        pts = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        # Iterative undistortion with a tight criterion: the default 5 iterations
        # leave ~0.1 px errors at the image corners with k1 ~ -0.1.
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
        und = cv2.undistortPoints(pts, self.matrix, self.distortions, criteria=criteria)
        return np.asarray(und, dtype=np.float64).reshape(-1, 2)

    def rays(self, pixels: FloatArray) -> FloatArray:
        """(N, 2) pixels -> (N, 3) unit ray directions in the world frame."""
        xy = self.undistort_pixels(pixels)
        d_cam = np.column_stack([xy, np.ones(len(xy))])
        d_world = d_cam @ self.camera_from_world  # R^T applied to row vectors
        return d_world / np.linalg.norm(d_world, axis=1, keepdims=True)


def project_in_views(cameras: Sequence[Camera], points_mm: FloatArray) -> FloatArray:
    """(N, 3) world points (mm) -> (C, N, 2) float64 pixels in each of C cameras.

    The same values as :meth:`Camera.project` in each (NaN behind a camera), in
    one set of array calls for all views: ``cv2.projectPoints`` also computes its
    (2N, 15) Jacobian, most of its time, and costs a call per view. Its own
    arithmetic, operation for operation (so bit for bit: checked against it in
    tests/geometry/test_camera.py), for the five-coefficient model; other models go
    through :meth:`Camera.project`.
    """
    pts = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    constants = _view_constants(tuple(cameras))
    if len(pts) < _MIN_POINTS_IN_VIEWS or constants is None:
        return np.stack([cam.project(pts) for cam in cameras]).reshape(len(cameras), len(pts), 2)
    r00, r01, r02, r10, r11, r12, r20, r21, r22, t0, t1, t2, k1, k2, p1, p2, k3, fx, fy, cx, cy = constants
    big_x, big_y, big_z = pts[:, 0], pts[:, 1], pts[:, 2]
    # OpenCV's order: ((R0 X + R1 Y) + R2 Z) + t, left to right.
    x = r00 * big_x + r01 * big_y + r02 * big_z + t0
    y = r10 * big_x + r11 * big_y + r12 * big_z + t1
    z = r20 * big_x + r21 * big_y + r22 * big_z + t2
    behind = z <= 0
    inv_z = 1.0 / np.where(z != 0, z, 1.0)  # OpenCV: z ? 1/z : 1
    x = x * inv_z
    y = y * inv_z
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    a1 = 2 * x * y
    a2 = r2 + 2 * x * x
    a3 = r2 + 2 * y * y
    radial = 1 + k1 * r2 + k2 * r4 + k3 * r6
    xd = x * radial + p1 * a1 + p2 * a2
    yd = y * radial + p1 * a3 + p2 * a1
    px = np.stack([xd * fx + cx, yd * fy + cy], axis=-1)
    if behind.any():
        px[behind] = np.nan
    return px


@lru_cache(maxsize=16)
def _view_constants(cameras: tuple[Camera, ...]) -> tuple[FloatArray, ...] | None:
    """:func:`project_in_views`' per-view constants, each (C, 1), stacked once per
    set of cameras: R's nine entries (row by row), t's three, k1 k2 p1 p2 k3, fx,
    fy, cx, cy; None when a camera has more than five distortion coefficients."""
    if any(np.asarray(cam.distortions).size > 5 for cam in cameras):
        return None
    rot = np.stack([cam.camera_from_world for cam in cameras]).reshape(len(cameras), 9)
    t = np.stack([np.asarray(cam.translation_mm, dtype=np.float64) for cam in cameras])
    k = np.zeros((len(cameras), 5))
    for j, cam in enumerate(cameras):
        dist = np.asarray(cam.distortions, dtype=np.float64).ravel()
        k[j, : len(dist)] = dist
    intrinsics = np.array(
        [[cam.matrix[a, b] for a, b in ((0, 0), (1, 1), (0, 2), (1, 2))] for cam in cameras]
    )
    columns = np.concatenate([rot, t, k, intrinsics], axis=1)
    out = tuple(np.ascontiguousarray(columns[:, i : i + 1]) for i in range(columns.shape[1]))
    for a in out:
        a.flags.writeable = False
    return out


def _tilt_matrix(tau_x: float, tau_y: float) -> FloatArray:
    """(3, 3) OpenCV tilted-sensor projection matrix for angles tau_x, tau_y (radians)."""
    cx, sx, cy, sy = np.cos(tau_x), np.sin(tau_x), np.cos(tau_y), np.sin(tau_y)
    rot_x = np.array([[1.0, 0.0, 0.0], [0.0, cx, sx], [0.0, -sx, cx]])
    rot_y = np.array([[cy, 0.0, -sy], [0.0, 1.0, 0.0], [sy, 0.0, cy]])
    rot = rot_y @ rot_x
    proj_z = np.array([[rot[2, 2], 0.0, -rot[0, 2]], [0.0, rot[2, 2], -rot[1, 2]], [0.0, 0.0, 1.0]])
    return proj_z @ rot
