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
from numpy.typing import NDArray

from ..geometry.camera import Camera
from ..reconstruct.frame_result import FrameResult
from ..session.settings import Workspace
from .rerun_layout import (
    CENTERLINE_PATH,
    HULL_PATH,
    IMAGE_PLANE_MM,
    OPENCV_TO_RERUN_PX,
    SMOOTHED_PATH,
    TIP_PATH,
    camera_path,
    image_path,
    iou_path,
    rerun_intrinsics,
    series_colors,
)

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


# A live viewer's stream sends what it has this often: ten updates a second. A send is a
# call per entity (~25); made for every frame, they cost the run more than its drawing is worth.
LIVE_SEND_S = 0.1
SUSPECT_PLOT = "plots/suspect"


@dataclass
class _Series:
    """Per-frame scalars, kept until they are sent as columns (with the other rows)."""

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
        watching); otherwise rows and plots go out 100 frames at a time.
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

    @property
    def frames_waiting(self) -> int:
        """How many written frames' plot rows wait for the next batch to be sent."""
        return len(self._series.frames)

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
                    image_plane_distance=IMAGE_PLANE_MM,
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
            # The plots go with them, so that a long live run's memory stays flat.
            self._columns.send(self._rec)
            self._send_series(self._series)
            self._series = _Series()

    def _scalars(self, result: FrameResult) -> dict[str, float]:
        values: dict[str, float] = {
            "plots/voxels": float(result.voxel_count),
            SUSPECT_PLOT: float(result.suspect),
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

    def mark_suspect(self, frame: int, time_ns: int) -> None:
        """Frame ``frame``'s suspect plot set to 1 after the fact (found beside the smoothed
        curves): in place while the series is still held, else as a row of its own."""
        held = self._series
        if frame in held.frames:
            held.values.setdefault(SUSPECT_PLOT, [float("nan")] * len(held.frames))[
                held.frames.index(frame)
            ] = 1.0
        else:
            held.add(frame, time_ns, {SUSPECT_PLOT: 1.0})

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
