"""The Rerun recording's entity paths, colours and layout (its blueprint).

The 3-D view framed on the cameras and the workspace (:func:`framing_eye`), each
camera's image with its silhouette and re-projected centreline, and the plots, each
series in a colour of its own (:func:`series_colors`); see :func:`default_blueprint`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import rerun.blueprint as rrb
from numpy.typing import NDArray

from ..geometry.camera import Camera
from ..session.settings import Workspace

# Plot colours, one per series and all distinct: the viewer's own choice, a hash of the
# entity path, gave two lines of one plot the same colour. Tip axes in the usual
# x/y/z = red/green/blue.
_SERIES_RGB: dict[str, tuple[int, int, int]] = {
    "plots/tip/x": (235, 70, 60),
    "plots/tip/y": (80, 190, 70),
    "plots/tip/z": (70, 120, 240),
    "plots/length": (240, 170, 30),
    "plots/curvature": (190, 100, 240),
    "plots/voxels": (150, 150, 150),
    "plots/suspect": (250, 90, 180),
}


# Per camera (its IoU series), in calibration order; a rig of more cameras reuses them.
_CAMERA_RGB = (
    (60, 220, 210),
    (240, 240, 90),
    (150, 80, 30),
    (160, 245, 160),
    (255, 180, 150),
    (245, 245, 245),
    (40, 60, 160),
    (0, 130, 130),
)

HULL_PATH = "world/hull"
CENTERLINE_PATH = "world/centerline"
SMOOTHED_PATH = "world/centerline_smoothed"
TIP_PATH = "world/tip"
# The 3-D views' titles are their legends.
LEGEND_3D = "3-D: orange per frame, blue smoothed (dots), red tip"
LEGEND_3D_HULL = "+ hull (grey)"


def camera_path(name: str) -> str:
    return f"world/cameras/{name}"


def image_path(name: str) -> str:
    """The Pinhole entity: everything in pixels of camera ``name`` lives under it."""
    return f"{camera_path(name)}/image"


def camera_rgb(index: int) -> tuple[int, int, int]:
    """The colour of the ``index``-th camera's (calibration order) IoU series."""
    return _CAMERA_RGB[index % len(_CAMERA_RGB)]


def series_colors(camera_names: Sequence[str]) -> dict[str, tuple[int, int, int]]:
    """Every time series' entity path -> its RGB colour."""
    colors = dict(_SERIES_RGB)
    colors.update({iou_path(n): camera_rgb(i) for i, n in enumerate(camera_names)})
    return colors


def iou_path(name: str) -> str:
    return f"plots/iou/{name}"


# Rerun's 3-D view opens with a 55 degree vertical field of view. Everything is fitted
# into 90 % of it, and horizontally into 90 % of what a view 0.9 times as wide as tall
# shows (the 3-D view of this layout is about square in windows from 1280 x 800 up).
_FOV_Y_RAD = np.radians(55.0)


_FIT_MARGIN = 0.9


_MIN_VIEW_ASPECT = 0.9


_VIEW_ELEVATION_RAD = np.radians(35.0)  # looking down on the workspace, as from a bench


def framing_eye(
    cameras: Sequence[Camera], workspace: Workspace
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(eye_mm, target_mm)``, each (3,) world frame: a viewpoint of Rerun's 3-D view
    that shows the workspace and every camera's frustum whole.

    The eye looks at the centre of their bounding box, in through the widest gap
    between the cameras as seen from above (so none stands in front of the
    workspace), from ``_VIEW_ELEVATION_RAD`` above the horizon, and stands back until
    every point is inside the field of view.
    """
    lo = np.asarray(workspace.origin_mm, dtype=np.float64)
    hi = lo + np.asarray(workspace.size_mm, dtype=np.float64)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    cloud = np.concatenate([corners] + [_frustum_mm(cam) for cam in cameras])
    target = (cloud.min(axis=0) + cloud.max(axis=0)) / 2
    offsets_xy = [c.center_mm[:2] - target[:2] for c in cameras]
    azimuth = _widest_gap_azimuth([float(np.arctan2(y, x)) for x, y in offsets_xy])
    back = np.array(  # unit vector from the target toward the eye
        [
            np.cos(_VIEW_ELEVATION_RAD) * np.cos(azimuth),
            np.cos(_VIEW_ELEVATION_RAD) * np.sin(azimuth),
            np.sin(_VIEW_ELEVATION_RAD),
        ]
    )
    right = np.cross(-back, (0.0, 0.0, 1.0))
    right /= np.linalg.norm(right)
    up = np.cross(right, -back)
    offsets = cloud - target
    along, across, above = offsets @ back, offsets @ right, offsets @ up
    # From an eye at distance d a point lies at depth d - along, and is in view while
    # |across| <= (d - along) tan(half width) and |above| <= (d - along) tan(half height).
    tan_half_y = np.tan(_FOV_Y_RAD / 2) * _FIT_MARGIN
    tan_half_x = tan_half_y * _MIN_VIEW_ASPECT
    distance = float(np.max(along + np.maximum(np.abs(across) / tan_half_x, np.abs(above) / tan_half_y)))
    return target + distance * back, target


def _frustum_mm(cam: Camera) -> NDArray[np.float64]:
    """(5, 3) the camera's centre and its image corners at ``IMAGE_PLANE_MM``, world frame."""
    w, h = cam.width, cam.height
    pixels = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], dtype=np.float64)
    rays = pixels @ np.linalg.inv(rerun_intrinsics(cam)).T  # camera frame, z = 1
    corners_cam = rays * IMAGE_PLANE_MM
    # camera from world is x_cam = R X + (-R c): X = R^T x_cam + c.
    corners_world = corners_cam @ cam.camera_from_world + cam.center_mm
    return np.vstack([cam.center_mm, corners_world])


def _widest_gap_azimuth(azimuths_rad: Sequence[float]) -> float:
    """The direction (rad, about z) halfway across the widest gap between ``azimuths_rad``."""
    if not azimuths_rad:
        return float(np.radians(-60.0))
    ordered = np.sort(np.mod(azimuths_rad, 2 * np.pi))
    gaps = np.diff(np.append(ordered, ordered[0] + 2 * np.pi))
    k = int(np.argmax(gaps))
    return float(ordered[k] + gaps[k] / 2)


def default_blueprint(
    cameras: Sequence[Camera], workspace: Workspace, *, fps: float | None = None
) -> rrb.Blueprint:
    """The 3-D world beside the camera views, the plots below; the ``frame`` timeline.

    The 3-D view opens framed on the workspace and all cameras, with the hull hidden
    (its eye in the blueprint panel shows it); the tab beside it shows the same view
    with the hull. ``fps`` : the videos' rate, at which the ``frame`` timeline plays.
    """
    names = [c.name for c in cameras]
    eye, target = framing_eye(cameras, workspace)
    eye_controls = rrb.EyeControls3D(
        kind=rrb.Eye3DKind.Orbital, position=eye, look_target=target, eye_up=(0.0, 0.0, 1.0)
    )
    world = rrb.Tabs(
        rrb.Spatial3DView(
            origin="world",
            name=LEGEND_3D,
            eye_controls=eye_controls,
            overrides={HULL_PATH: rrb.EntityBehavior(visible=False)},
        ),
        rrb.Spatial3DView(origin="world", name=LEGEND_3D_HULL, eye_controls=eye_controls),
        active_tab=0,
    )
    cameras_row = rrb.Horizontal(*[rrb.Spatial2DView(origin=image_path(n), name=n) for n in names])
    plots = rrb.Horizontal(
        rrb.TimeSeriesView(origin="plots/tip", name="tip (mm)"),
        rrb.TimeSeriesView(origin="plots/length", name="length (mm)"),
        rrb.TimeSeriesView(origin="plots/curvature", name="mean curvature (1/mm)"),
        rrb.TimeSeriesView(origin="plots/iou", name="re-projection IoU"),
        rrb.TimeSeriesView(origin="plots/voxels", name="voxels"),
        rrb.TimeSeriesView(origin="plots/suspect", name="suspect (1: the curve may be wrong)"),
    )
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(world, cameras_row, column_shares=[2, 3]),
            plots,
            row_shares=[3, 1],
        ),
        rrb.TimePanel(state="collapsed", timeline="frame", fps=fps),
        collapse_panels=True,
    )


IMAGE_PLANE_MM = 60.0  # how far from its centre a camera's frustum is drawn


# Pixel conventions: OpenCV (the calibration, Camera.project) puts (0, 0) at the centre of
# the top-left pixel; Rerun's image space at its top-left corner (an image spans [0, W] x
# [0, H]). Pixel coordinates and the principal point shift by half a pixel into Rerun.
OPENCV_TO_RERUN_PX = 0.5


def rerun_intrinsics(camera: Camera) -> NDArray[np.float64]:
    """(3, 3) K with the principal point in Rerun's pixel convention."""
    k = np.array(camera.matrix, dtype=np.float64)
    k[:2, 2] += OPENCV_TO_RERUN_PX
    return k
