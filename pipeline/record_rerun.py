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
    world/centerline_smoothed               LineStrips3D, after temporal smoothing
    world/tip                               Points3D
    plots/tip/{x,y,z}, plots/length, plots/curvature, plots/iou/<name>, plots/voxels, plots/suspect   Scalars

Timelines: ``frame`` (sequence: frame index) and ``time`` (timestamp of the frame).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from numpy.typing import NDArray

from .camera import Camera
from .frame_result import FrameResult
from .settings import Workspace

_CENTERLINE_RGB = (255, 140, 0)
_SMOOTHED_RGB = (50, 150, 255)
_TIP_RGB = (255, 40, 40)
_HULL_RGB = (150, 150, 150)
_CURVE_RADIUS_MM = 1.5
_HULL_RADIUS_FRACTION = 0.4  # of a voxel edge: points that nearly touch read as a solid
# Pixel conventions: OpenCV (the calibration, Camera.project) puts (0, 0) at the centre of
# the top-left pixel; Rerun's image space at its top-left corner (an image spans [0, W] x
# [0, H]). Pixel coordinates and the principal point shift by half a pixel into Rerun.
OPENCV_TO_RERUN_PX = 0.5


def rerun_intrinsics(camera: Camera) -> NDArray[np.float64]:
    """(3, 3) K with the principal point in Rerun's pixel convention."""
    k = np.array(camera.matrix, dtype=np.float64)
    k[:2, 2] += OPENCV_TO_RERUN_PX
    return k


def camera_path(name: str) -> str:
    return f"world/cameras/{name}"


def image_path(name: str) -> str:
    """The Pinhole entity: everything in pixels of camera ``name`` lives under it."""
    return f"{camera_path(name)}/image"


def default_blueprint(camera_names: Sequence[str]) -> rrb.Blueprint:
    """The 3-D world beside the camera views, the plots below."""
    cameras = rrb.Horizontal(
        *[rrb.Spatial2DView(origin=image_path(n), name=n) for n in camera_names],
    )
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
            rrb.Horizontal(
                rrb.Spatial3DView(origin="world", name="3-D"),
                cameras,
                column_shares=[2, 3],
            ),
            plots,
            row_shares=[3, 1],
        ),
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
    """

    def __init__(self, stream: rr.RecordingStream, cameras: Sequence[Camera], workspace: Workspace) -> None:
        self._rec = stream
        self._cameras = tuple(cameras)
        self._workspace = workspace
        self._series = _Series()
        self._columns = _Columns()
        self._statics_written = False

    def write_statics(self) -> None:
        """The world's axes, the workspace box and the cameras (all static)."""
        rec = self._rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        ws = self._workspace
        rec.log(
            "world/workspace",
            rr.Boxes3D(
                mins=[ws.origin_mm], sizes=[ws.size_mm], colors=[(120, 120, 120)], labels=["workspace"]
            ),
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
                    image_plane_distance=60.0,
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
        rec.log("world/hull", rr.Points3D.from_fields(radii=radius, colors=[_HULL_RGB]), static=True)
        rec.log(
            "world/centerline",
            rr.LineStrips3D.from_fields(radii=_CURVE_RADIUS_MM, colors=[_CENTERLINE_RGB]),
            static=True,
        )
        rec.log(
            "world/centerline_smoothed",
            rr.LineStrips3D.from_fields(radii=_CURVE_RADIUS_MM, colors=[_SMOOTHED_RGB]),
            static=True,
        )
        rec.log("world/tip", rr.Points3D.from_fields(radii=3.0, colors=[_TIP_RGB]), static=True)
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
                rr.LineStrips2D.from_fields(radii=1.0, colors=[_CENTERLINE_RGB], draw_order=2.0),
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
        add("world/hull", "points", frame, time_ns, np.asarray(result.points_mm).reshape(-1, 3))
        add("world/centerline", "strips3d", frame, time_ns, curve)
        add("world/tip", "points", frame, time_ns, None if curve is None else curve[-1:])
        if self._columns.full():
            self._columns.send(self._rec)
        self._series.add(result.index, time_ns, self._scalars(result))

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
            values[f"plots/iou/{cam.name}"] = float(iou)
        return values

    def write_smoothed(
        self, centerlines_mm: NDArray[np.float64], frames: Sequence[int], times_ns: Sequence[int]
    ) -> None:
        """(F, N, 3) mm smoothed centrelines (NaN rows: no curve) at their frames."""
        for curve, frame, time_ns in zip(centerlines_mm, frames, times_ns, strict=True):
            ok = len(curve) > 0 and bool(np.isfinite(curve).all())
            self._columns.add(
                "world/centerline_smoothed", "strips3d", int(frame), int(time_ns), curve if ok else None
            )
        self._columns.send(self._rec)

    def finish(self, *, flush_timeout_s: float = 1e38) -> None:
        """Send the queued rows and the time series as columns, and flush the stream
        (RuntimeError if that takes longer than ``flush_timeout_s``)."""
        self._columns.send(self._rec)
        series = self._series
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
        self._rec.flush(timeout_sec=flush_timeout_s)
