"""The Rerun log of a processed session, for review in the Rerun viewer.

Units: millimetres, the world frame of calibration.toml (z up), the pipeline's own
units, so nothing is converted here (the MCAP is the file in metres).

Entities::

    world                                   ViewCoordinates RIGHT_HAND_Z_UP (static)
    world/workspace                         Boxes3D, the carving box (static)
    world/cameras/<name>                    Transform3D, camera -> world (static)
    world/cameras/<name>/image              Pinhole K, resolution (static)
    world/cameras/<name>/image/jpeg         EncodedImage, the camera frame
    world/cameras/<name>/image/silhouette   EncodedImage, tinted RGBA PNG of the silhouette
    world/cameras/<name>/image/centerline   LineStrips2D, the centreline re-projected (with distortion)
    world/hull                              Points3D, occupied voxel centres
    world/centerline                        LineStrips3D, base -> tip
    world/centerline_smoothed               Points3D, the samples after temporal smoothing, base -> tip
    world/tip                               Points3D
    plots/tip/{x,y,z}, plots/length, plots/curvature, plots/iou/<name>, plots/voxels, plots/suspect
                                            Scalars; their SeriesLines colour and name (static)

Timelines: ``frame`` (sequence: frame index, the one the layout opens on) and ``time``
(timestamp of the frame).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from numpy.typing import NDArray

from ..geometry.camera import Camera
from ..reconstruct.frame_result import FrameResult
from ..session.settings import Workspace

CENTERLINE_RGB = (255, 140, 0)
SMOOTHED_RGB = (40, 170, 255)
TIP_RGB = (255, 40, 40)
# The hull is context, not the result: thin points, so the curves show between them.
# (Rerun draws a translucent point darker but still hides what is behind it.)
_HULL_RGB = (150, 150, 150)
_HULL_RADIUS_FRACTION = 0.2  # of a voxel edge
# The curves in UI points (screen pixels at 100 % scaling), so they stay thick at any
# zoom. Two lines in one place hide each other by turns (Rerun draws a line flat, at
# its centre's depth), so the smoothed curve is drawn as its samples: spheres, whose
# near halves stand out of the per-frame line as a dotted core, and apart from it
# where the two differ.
_CENTERLINE_RADIUS_PT = 3.5
_SMOOTHED_RADIUS_PT = 1.8
_TIP_RADIUS_PT = 5.0
_IMAGE_PLANE_MM = 60.0  # how far from its centre a camera's frustum is drawn

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
# Pixel conventions: OpenCV (the calibration, Camera.project) puts (0, 0) at the centre of
# the top-left pixel; Rerun's image space at its top-left corner (an image spans [0, W] x
# [0, H]). Pixel coordinates and the principal point shift by half a pixel into Rerun.
OPENCV_TO_RERUN_PX = 0.5


def rerun_intrinsics(camera: Camera) -> NDArray[np.float64]:
    """(3, 3) K with the principal point in Rerun's pixel convention."""
    k = np.array(camera.matrix, dtype=np.float64)
    k[:2, 2] += OPENCV_TO_RERUN_PX
    return k


# A live viewer's stream sends what it has this often: ten updates a second. A send is a
# call per entity (~25); made for every frame, they cost the run more than its drawing is worth.
LIVE_SEND_S = 0.1

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
    """(5, 3) the camera's centre and its image corners at ``_IMAGE_PLANE_MM``, world frame."""
    w, h = cam.width, cam.height
    pixels = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], dtype=np.float64)
    rays = pixels @ np.linalg.inv(rerun_intrinsics(cam)).T  # camera frame, z = 1
    corners_cam = rays * _IMAGE_PLANE_MM
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


@dataclass
class _Series:
    """Per-frame scalars, kept until the end and sent as columns."""

    frames: list[int] = field(default_factory=list)
    times_ns: list[int] = field(default_factory=list)
    values: dict[str, list[float]] = field(default_factory=dict)

    def add(self, frame: int, time_ns: int, values: dict[str, float]) -> None:
        self.frames.append(frame)
        self.times_ns.append(time_ns)
        for key, value in values.items():
            # Rows appear in order, so a series first seen late is padded with NaN.
            column = self.values.setdefault(key, [float("nan")] * (len(self.frames) - 1))
            column.append(value)
        for key, column in self.values.items():
            if key not in values:
                column.append(float("nan"))


def _points_columns(items: list[NDArray[np.float64]]) -> Any:
    return rr.Points3D.columns(positions=np.concatenate(items) if items else np.zeros((0, 3)))


# Per kind of row: the component columns of the present items, and each item's
# instance count (a row without an item has none).
_KINDS: dict[str, tuple[Callable[[list[Any]], Any], Callable[[Any], int]]] = {
    "points": (_points_columns, len),
    "strips3d": (lambda items: rr.LineStrips3D.columns(strips=items), lambda _: 1),
    "strips2d": (lambda items: rr.LineStrips2D.columns(strips=items), lambda _: 1),
    "image": (lambda items: rr.EncodedImage.columns(blob=items), lambda _: 1),
}


@dataclass
class _Rows:
    """One entity's per-frame data (None: nothing at that frame)."""

    kind: str
    frames: list[int] = field(default_factory=list)
    times_ns: list[int] = field(default_factory=list)
    items: list[Any] = field(default_factory=list)


@dataclass
class _Columns:
    """Every entity's per-frame data, kept for up to ``batch`` frames and sent as
    columns: one ``send_columns`` of 100 frames costs a fraction of 100 ``log``
    calls, and logging is most of what the parent process does per frame.

    A frame without data (no curve, no silhouette) is a row with no instance: the
    viewer shows nothing there, as after a ``Clear``, rather than the previous
    frame's data.
    """

    batch: int = 100
    rows: dict[str, _Rows] = field(default_factory=dict)

    def add(self, path: str, kind: str, frame: int, time_ns: int, item: Any) -> None:
        rows = self.rows.setdefault(path, _Rows(kind))
        rows.frames.append(frame)
        rows.times_ns.append(time_ns)
        rows.items.append(item)

    def full(self) -> bool:
        return any(len(r.frames) >= self.batch for r in self.rows.values())

    def send(self, rec: rr.RecordingStream) -> None:
        for path, rows in self.rows.items():
            columns, count = _KINDS[rows.kind]
            present = [item for item in rows.items if item is not None]
            lengths = [0 if item is None else count(item) for item in rows.items]
            rec.send_columns(
                path,
                indexes=[
                    rr.TimeColumn("frame", sequence=np.asarray(rows.frames, dtype=np.int64)),
                    rr.TimeColumn("time", timestamp=np.asarray(rows.times_ns).astype("datetime64[ns]")),
                ],
                columns=columns(present).partition(lengths),
            )
        self.rows = {}


class RerunRecorder:
    """Logs a session's frames to a Rerun recording stream.

    Parameters
    ----------
    stream : the recording, already given its sink (``stream.save(path)``) and blueprint.
    cameras : the session's cameras, in the order of FrameResult.iou and the media.
    workspace : the carving box, drawn once.
    live : send what was written, plots included, every LIVE_SEND_S (a viewer is
        watching); otherwise rows go out 100 frames at a time and the plots at the end.
    """

    def __init__(
        self,
        stream: rr.RecordingStream,
        cameras: Sequence[Camera],
        workspace: Workspace,
        *,
        live: bool = False,
    ) -> None:
        self._rec = stream
        self._cameras = tuple(cameras)
        self._workspace = workspace
        self._live = live
        self._series = _Series()
        self._columns = _Columns()
        self._sent_at = -math.inf
        self._statics_written = False

    def write_statics(self) -> None:
        """The world's axes, the workspace box and the cameras (all static)."""
        rec = self._rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        ws = self._workspace
        rec.log(
            "world/workspace",
            # No label: Rerun puts it at the box's centre, on top of the curve.
            rr.Boxes3D(mins=[ws.origin_mm], sizes=[ws.size_mm], colors=[(120, 120, 120)]),
            static=True,
        )
        for cam in self._cameras:
            # The calibration stores camera-from-world (x_cam = R X + t); Rerun's transform
            # here is parent_from_child = world-from-camera: rotation R^T, translation = the
            # optical centre -R^T t.
            rec.log(
                camera_path(cam.name),
                rr.Transform3D(
                    translation=cam.center_mm,
                    mat3x3=cam.camera_from_world.T,
                    relation=rr.TransformRelation.ParentFromChild,
                ),
                static=True,
            )
            # OpenCV camera axes: x right, y down, z forward (Rerun's Pinhole default RDF).
            rec.log(
                image_path(cam.name),
                rr.Pinhole(
                    image_from_camera=rerun_intrinsics(cam),
                    resolution=[cam.width, cam.height],
                    camera_xyz=rr.ViewCoordinates.RDF,
                    image_plane_distance=_IMAGE_PLANE_MM,
                ),
                static=True,
            )
        self._log_styles()
        self._statics_written = True

    def _log_styles(self) -> None:
        """Colours, sizes, media types and draw orders, once (static): per frame only the
        data is logged, which halves the cost of a frame in the parent process."""
        rec = self._rec
        radius = self._workspace.voxel_mm * _HULL_RADIUS_FRACTION
        rec.log(HULL_PATH, rr.Points3D.from_fields(radii=radius, colors=[_HULL_RGB]), static=True)
        rec.log(
            CENTERLINE_PATH,
            rr.LineStrips3D.from_fields(
                radii=rr.Radius.ui_points(_CENTERLINE_RADIUS_PT), colors=[CENTERLINE_RGB]
            ),
            static=True,
        )
        rec.log(
            SMOOTHED_PATH,
            rr.Points3D.from_fields(radii=rr.Radius.ui_points(_SMOOTHED_RADIUS_PT), colors=[SMOOTHED_RGB]),
            static=True,
        )
        rec.log(
            TIP_PATH,
            rr.Points3D.from_fields(radii=rr.Radius.ui_points(_TIP_RADIUS_PT), colors=[TIP_RGB]),
            static=True,
        )
        names = [cam.name for cam in self._cameras]
        for path, rgb in series_colors(names).items():
            rec.log(path, rr.SeriesLines(colors=[rgb], names=[path.rsplit("/", 1)[-1]]), static=True)
        for cam in self._cameras:
            base = image_path(cam.name)
            rec.log(
                f"{base}/jpeg",
                rr.EncodedImage.from_fields(media_type="image/jpeg", draw_order=0.0),
                static=True,
            )
            rec.log(
                f"{base}/silhouette",
                rr.EncodedImage.from_fields(media_type="image/png", draw_order=1.0),
                static=True,
            )
            rec.log(
                f"{base}/centerline",
                rr.LineStrips2D.from_fields(radii=1.0, colors=[CENTERLINE_RGB], draw_order=2.0),
                static=True,
            )

    def write_frame(
        self,
        result: FrameResult,
        time_ns: int,
        *,
        jpegs: Sequence[bytes] | None = None,
        silhouettes_png: Sequence[bytes] | None = None,
    ) -> None:
        """One frame: images, silhouettes, hull, centreline (3-D and re-projected), tip."""
        if not self._statics_written:
            self.write_statics()
        frame, add = result.index, self._columns.add
        curve = result.centerline_mm if result.status == "ok" else None
        for i, cam in enumerate(self._cameras):
            base = image_path(cam.name)
            if jpegs is not None:
                add(f"{base}/jpeg", "image", frame, time_ns, jpegs[i] or None)
            png = silhouettes_png[i] if silhouettes_png is not None else None
            add(f"{base}/silhouette", "image", frame, time_ns, png or None)
            pixels = None
            if curve is not None:
                pixels = cam.project(curve) + OPENCV_TO_RERUN_PX
                pixels = pixels[np.isfinite(pixels).all(axis=1)]
            add(f"{base}/centerline", "strips2d", frame, time_ns, pixels)
        add(HULL_PATH, "points", frame, time_ns, np.asarray(result.points_mm).reshape(-1, 3))
        add(CENTERLINE_PATH, "strips3d", frame, time_ns, curve)
        add(TIP_PATH, "points", frame, time_ns, None if curve is None else curve[-1:])
        self._series.add(result.index, time_ns, self._scalars(result))
        if self._live and time.monotonic() - self._sent_at >= LIVE_SEND_S:
            self._columns.send(self._rec)
            self._send_series(self._series)
            self._series = _Series()
            self._sent_at = time.monotonic()
        elif self._columns.full():
            self._columns.send(self._rec)

    def _scalars(self, result: FrameResult) -> dict[str, float]:
        values: dict[str, float] = {
            "plots/voxels": float(result.voxel_count),
            "plots/suspect": float(result.suspect),
        }
        tip = result.tip_mm if result.status == "ok" else None
        if tip is not None:
            values.update({f"plots/tip/{a}": float(v) for a, v in zip("xyz", tip, strict=True)})
        values["plots/length"] = float(result.length_mm)
        if result.curvature_per_mm is not None and len(result.curvature_per_mm):
            values["plots/curvature"] = float(np.mean(result.curvature_per_mm))
        for cam, iou in zip(self._cameras, result.iou, strict=False):
            values[iou_path(cam.name)] = float(iou)
        return values

    def write_smoothed(
        self, centerlines_mm: NDArray[np.float64], frames: Sequence[int], times_ns: Sequence[int]
    ) -> None:
        """(F, N, 3) mm smoothed centrelines (NaN rows: no curve) at their frames."""
        for curve, frame, time_ns in zip(centerlines_mm, frames, times_ns, strict=True):
            ok = len(curve) > 0 and bool(np.isfinite(curve).all())
            self._columns.add(SMOOTHED_PATH, "points", int(frame), int(time_ns), curve if ok else None)
        self._columns.send(self._rec)

    def finish(self, *, flush_timeout_s: float = 1e38) -> None:
        """Send the queued rows and the time series as columns, and flush the stream
        (RuntimeError if that takes longer than ``flush_timeout_s``)."""
        self._columns.send(self._rec)
        self._send_series(self._series)
        self._rec.flush(timeout_sec=flush_timeout_s)

    def _send_series(self, series: _Series) -> None:
        frames = np.asarray(series.frames, dtype=np.int64)
        times = np.asarray(series.times_ns, dtype=np.int64).astype("datetime64[ns]")
        for path, column in series.values.items():
            values = np.asarray(column, dtype=np.float64)
            keep = np.isfinite(values)  # a gap in the plot, not a zero, where a frame has no value
            if not keep.any():
                continue
            self._rec.send_columns(
                path,
                indexes=[
                    rr.TimeColumn("frame", sequence=frames[keep]),
                    rr.TimeColumn("time", timestamp=times[keep]),
                ],
                columns=rr.Scalars.columns(scalars=values[keep]),
            )
