"""calibration.toml in the aniposelib layout: read (validated) and write.

One table per camera (``[cam_0]``, ``[cam_1]``, ...) with ``name``, ``size``
(width, height px), ``matrix`` (3x3), ``distortions`` (k1 k2 p1 p2 k3),
``rotation`` (Rodrigues vector, camera from world) and ``translation`` (mm);
an optional ``[metadata]`` table is kept as free-form data.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import tomli_w

from ..errors import CalibrationError
from ..geometry.camera import WORLD_FRAME, Camera
from .toml_file import read_toml

REQUIRED_KEYS = ("name", "size", "matrix", "distortions", "rotation", "translation")
# aniposelib's marks its fisheye cameras; every other key is a typo of one of these (a
# misspelt "fisheye" would pass a fisheye lens off as a standard one).
KNOWN_KEYS = (*REQUIRED_KEYS, "fisheye")
# A camera's name is its video's file stem, and its frame's name in the recordings: a path
# separator splits the first, and the world frame's own name (WORLD_FRAME) would loop the second.
NAME_FORBIDS = ("/", "\\", "\0")


def read_calibration(path: Path) -> list[Camera]:
    """Read and validate calibration.toml; raise CalibrationError naming file, camera and key."""
    try:
        data = read_toml(path, error=CalibrationError)
    except FileNotFoundError:
        raise CalibrationError(
            f"{path}: not found; every session needs a calibration.toml (see docs/input.md)"
        ) from None
    return cameras_from_dict(data, source=str(path))


def cameras_from_dict(data: dict[str, Any], *, source: str = "calibration.toml") -> list[Camera]:
    tables = {k: v for k, v in data.items() if k != "metadata"}
    if not tables:
        raise CalibrationError(f"{source}: no camera tables ([cam_0], [cam_1], ...)")
    cameras = [_camera(source, key, table) for key, table in tables.items()]
    names = [c.name for c in cameras]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise CalibrationError(f"{source}: camera name {dupes[0]!r} appears more than once")
    for i, a in enumerate(cameras):
        for b in cameras[i + 1 :]:
            if np.linalg.norm(a.center_mm - b.center_mm) < _SAME_PLACE_MM:
                raise CalibrationError(
                    f"{source}: cameras {a.name!r} and {b.name!r} stand at the same place "
                    f"({np.linalg.norm(a.center_mm - b.center_mm):.2g} mm apart): one camera's table "
                    "copied from the other's, or translations not in mm (a calibration in metres); "
                    "give each camera its own calibration, in mm"
                )
    return cameras


# Two cameras' centres closer than this (mm) are one camera twice: a table copied over
# another. Two views from one place see the same silhouette, and their cones do not meet.
_SAME_PLACE_MM = 1.0


def _array(source: str, where: str, value: Any, shape: tuple[int, ...]) -> np.ndarray:
    try:
        arr = np.asarray(value)
        # Text and booleans are not numbers even where numpy would convert them ("1.5", true).
        if arr.dtype.kind not in "iufO":
            raise TypeError(arr.dtype)
        # Object arrays hold TOML's unbounded integers (OverflowError) or dates (TypeError).
        arr = arr.astype(np.float64)
    except (TypeError, ValueError, OverflowError):
        raise CalibrationError(f"{source}: {where} must be numbers of shape {shape}") from None
    if arr.shape != shape:
        raise CalibrationError(f"{source}: {where} has shape {arr.shape}, expected {shape}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(
            f"{source}: {where} holds a non-finite number (nan or inf); calibrate the camera again"
        )
    return arr


def _camera(source: str, key: str, table: Any) -> Camera:
    # A quoted TOML key may hold a newline; the message must stay one line.
    label = f"[{key}]" if key.isprintable() else f"[{key!r}]"
    if not isinstance(table, dict):
        if not isinstance(table, list | dict):  # a bare key above the first table
            raise CalibrationError(
                f"{source}: {label[1:-1]} = ... is not in a table; a camera's keys go under its [cam_N] "
                "table, other notes under [metadata]"
            )
        raise CalibrationError(f"{source}: {label} must be a table")
    unknown = [k for k in table if k not in KNOWN_KEYS]
    if unknown:
        raise CalibrationError(
            f"{source}: {label} has unknown key {unknown[0]!r}; a camera's keys are {', '.join(KNOWN_KEYS)}"
        )
    missing = [k for k in REQUIRED_KEYS if k not in table]
    if missing:
        raise CalibrationError(
            f"{source}: {label} is missing key(s) {', '.join(missing)}; docs/input.md shows a camera's table"
        )
    name = table["name"]
    if not isinstance(name, str) or not name:
        raise CalibrationError(f"{source}: {label} name must be a non-empty string")
    where = f"{label} (camera {name!r})"
    if any(c in name for c in NAME_FORBIDS) or name in (".", ".."):
        raise CalibrationError(
            f"{source}: {where} name cannot hold / or \\ or be . or ..: it names the camera's video "
            "file (cam0 -> cam0.mp4); rename the camera and its video"
        )
    if name == WORLD_FRAME:
        raise CalibrationError(
            f"{source}: {where} name {WORLD_FRAME!r} is the recordings' own frame (the one the "
            "hull and the centreline are in); rename the camera and its video"
        )
    size = table["size"]
    # Whole numbers, as integers or as floats (aniposelib's resized cameras write 320.0).
    if (
        not isinstance(size, list)
        or len(size) != 2
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in size)
        or not all(v > 0 and float(v).is_integer() for v in size)
    ):
        raise CalibrationError(f"{source}: {where} size must be [width, height] positive integers")
    if not isinstance(table.get("fisheye", False), bool):
        raise CalibrationError(f"{source}: {where} fisheye must be true or false, got {table['fisheye']!r}")
    if table.get("fisheye") is True:
        raise CalibrationError(
            f"{source}: {where} is a fisheye calibration, which this pipeline does not model; "
            "calibrate the camera with the standard lens model (fisheye = false)"
        )
    matrix = _array(source, f"{where} matrix", table["matrix"], (3, 3))
    fx, fy = matrix[0, 0], matrix[1, 1]
    if fx <= 0 or fy <= 0 or not np.allclose(matrix[2], [0, 0, 1]) or matrix[1, 0] != 0:
        raise CalibrationError(
            f"{source}: {where} matrix must be [[fx,0,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0"
        )
    fov_deg = max(_field_of_view_deg(size[0], fx), _field_of_view_deg(size[1], fy))
    if fov_deg > _MAX_FIELD_OF_VIEW_DEG:
        raise CalibrationError(
            f"{source}: {where} focal length fx {fx:g}, fy {fy:g} gives a {fov_deg:.0f}-degree field of "
            f"view over {size[0]}x{size[1]} pixels: fx and fy are in pixels, not mm; check the calibration"
        )
    if abs(matrix[0, 1]) > _MAX_SKEW * fx:
        # OpenCV's projection (and so every view's here) ignores a skew term: the pixels
        # would be off by it times y.
        raise CalibrationError(
            f"{source}: {where} matrix has a skew term ({matrix[0, 1]:g}) that OpenCV's projection "
            "ignores; calibrate with zero skew"
        )
    dist = np.asarray(table["distortions"], dtype=object).ravel()
    if len(dist) not in (4, 5, 8, 12, 14):
        raise CalibrationError(f"{source}: {where} distortions must hold 4, 5, 8, 12 or 14 numbers")
    distortions = _array(source, f"{where} distortions", list(dist), (len(dist),))
    reach = _unfolded_reach(matrix, (size[0], size[1]), distortions)
    if reach < 1.0:
        named = ", ".join(f"{n} {v:g}" for n, v in zip(DISTORTION_NAMES, distortions, strict=False))
        raise CalibrationError(
            f"{source}: {where} distortion ({named}) folds the image before its corners (its radius "
            f"stops growing {100 * reach:.0f} % of the way out); check the coefficients and their order "
            f"({', '.join(DISTORTION_NAMES[: len(distortions)])})"
        )
    rotation = _rotation(source, where, table["rotation"])
    translation = _array(source, f"{where} translation", table["translation"], (3,))
    return Camera(
        name=name,
        size_px=(int(size[0]), int(size[1])),
        matrix=matrix,
        distortions=distortions,
        rotation=rotation,
        translation_mm=translation,
    )


# OpenCV's order of the distortion coefficients.
DISTORTION_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "tau_x", "tau_y")
# How far out (times the corners' distorted radius) an undistorted radius is looked for: a
# lens that squeezes its corners ten times over is no lens this pipeline models.
_FOLD_SEARCH = 10.0


def _unfolded_reach(matrix: np.ndarray, size: tuple[int, int], distortions: np.ndarray) -> float:
    """How far the radial distortion (``distortions``: (N,) in OpenCV's order) of a camera
    with ``matrix`` ((3, 3), px) and images of ``size`` ((W, H), px) maps out without
    folding, as a fraction of the image corners' radius: 1.0 when the distorted radius
    r_d(r) = r (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6) grows with
    r (normalised, unitless) until it reaches the farthest corner.

    Below 1, pixels past the fold are no ray's image and nearer ones two rays' (a
    calibration that carves nothing). Tangential, prism and tilt terms are left out: they
    are small in any lens the radial terms fit.
    """
    k = np.zeros(8)
    k[: min(len(distortions), 8)] = distortions[:8]
    fx, fy, cx, cy = matrix[0, 0], matrix[1, 1], matrix[0, 2], matrix[1, 2]
    # The corners' normalised radius (pixel centres at integers: the image spans -0.5..W-0.5).
    xs = (np.array([-0.5, size[0] - 0.5]) - cx) / fx
    ys = (np.array([-0.5, size[1] - 0.5]) - cy) / fy
    corner = float(np.hypot(np.abs(xs).max(), np.abs(ys).max()))
    r = np.linspace(0.0, _FOLD_SEARCH * corner, 20_001)
    r2 = r * r
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        r_d = r * (1 + r2 * (k[0] + r2 * (k[1] + r2 * k[4]))) / (1 + r2 * (k[5] + r2 * (k[6] + r2 * k[7])))
        grows = np.diff(r_d) > 0  # False at a fold, and where a rational model's denominator crosses 0
    out = int(np.argmax(r_d >= corner)) if np.any(r_d >= corner) else len(r_d)
    folds = np.flatnonzero(~grows[:out])
    if folds.size == 0 and out < len(r_d):
        return 1.0
    end = folds[0] if folds.size else len(r_d) - 1
    return float(np.nanmax(r_d[: end + 1]) / corner)


def _field_of_view_deg(pixels: int, focal_px: float) -> float:
    """The angle (degrees) that ``pixels`` across subtend at a focal length of ``focal_px``."""
    return float(np.degrees(2.0 * np.arctan2(0.5 * pixels, focal_px)))


# A pinhole camera with polynomial distortion describes lenses up to ~120 degrees; a
# calibration that puts its field of view past this has a focal length in other units
# (mm) or a broken matrix, and its cones swallow the whole workspace.
_MAX_FIELD_OF_VIEW_DEG = 160.0
# A matrix[0][1] (skew) beyond this fraction of fx is refused: below it, its effect is a
# thousandth of a pixel per thousand pixels of image height.
_MAX_SKEW = 1e-6


def _rotation(source: str, where: str, value: Any) -> np.ndarray:
    """A Rodrigues 3-vector, or a 3x3 matrix that must be a proper rotation."""
    arr = np.asarray(value, dtype=object)
    if arr.shape == (3, 3):
        rot = _array(source, f"{where} rotation", value, (3, 3))
        if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) or not math.isclose(
            float(np.linalg.det(rot)), 1.0, abs_tol=1e-6
        ):
            raise CalibrationError(f"{source}: {where} rotation matrix is not a rotation")
        rvec, _ = cv2.Rodrigues(rot)
        return np.asarray(rvec, dtype=np.float64).ravel()
    return _array(source, f"{where} rotation", value, (3,))


def calibration_dict(cameras: list[Camera], metadata: dict[str, Any] | None = None) -> dict[str, Any]:
    """The TOML document for ``cameras`` (aniposelib layout)."""
    doc: dict[str, Any] = {}
    for i, cam in enumerate(cameras):
        doc[f"cam_{i}"] = {
            "name": cam.name,
            "size": [int(cam.size_px[0]), int(cam.size_px[1])],
            "matrix": np.asarray(cam.matrix, dtype=float).tolist(),
            "distortions": np.asarray(cam.distortions, dtype=float).ravel().tolist(),
            "rotation": np.asarray(cam.rotation, dtype=float).ravel().tolist(),
            "translation": np.asarray(cam.translation_mm, dtype=float).ravel().tolist(),
        }
    if metadata:
        doc["metadata"] = metadata
    return doc


def write_calibration(path: Path, cameras: list[Camera], metadata: dict[str, Any] | None = None) -> None:
    """Write calibration.toml (aniposelib layout)."""
    Path(path).write_text(tomli_w.dumps(calibration_dict(cameras, metadata)))
