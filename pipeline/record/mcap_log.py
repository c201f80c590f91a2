"""The MCAP log of a processed session: Foxglove protobuf schemas, zstd chunks.

Everything inside the pipeline is in millimetres; the MCAP follows the
ROS/Foxglove convention of metres. The conversion happens in :func:`_metres`
and nowhere else.

Topics (log_time = publish_time = the frame's timestamp, ns since the Unix epoch):

- ``/reconstruction/points``       foxglove.PointCloud, occupied voxel centres (x, y, z float32)
- ``/reconstruction/centerline``   foxglove.SceneUpdate, entity "centerline", one LINE_STRIP base -> tip
- ``/reconstruction/centerline_smoothed``  the same after temporal smoothing (written at the end)
- ``/reconstruction/centerline_points``, ``/reconstruction/centerline_smoothed_points``  foxglove.PointCloud,
  the same curves as their ordered samples (x, y, z float64, red, green, blue, alpha uint8), base
  first; no points where a frame has no curve. Tools that convert PointCloud but not SceneUpdate
  (Rerun's MCAP importer) keep the result this way.
- ``/reconstruction/metrics``      JSON (jsonschema :data:`METRICS_SCHEMA`), one message per frame,
  written last for its frame so a frame whose metrics survive a truncation has all its messages;
  a frame found suspect after the last frame (beside the smoothed curves) has them again at the
  end, suspect: a reader takes a frame's last metrics
- ``/tf``                          foxglove.FrameTransforms, world -> each camera (static, first frame)
- ``/cameras/<name>/calibration``  foxglove.CameraCalibration (static, first frame)
- ``/cameras/<name>/image``        foxglove.CompressedImage, JPEG (unless images are disabled)
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import IO, Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneEntityDeletion_pb2 import SceneEntityDeletion
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf.message import Message
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set, register_schema
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from ..geometry.camera import WORLD_FRAME, Camera
from ..reconstruct.frame_result import FrameResult

POINTS_TOPIC = "/reconstruction/points"
CENTERLINE_TOPIC = "/reconstruction/centerline"
SMOOTHED_TOPIC = "/reconstruction/centerline_smoothed"
CENTERLINE_POINTS_TOPIC = "/reconstruction/centerline_points"
SMOOTHED_POINTS_TOPIC = "/reconstruction/centerline_smoothed_points"
METRICS_TOPIC = "/reconstruction/metrics"
TF_TOPIC = "/tf"
CENTERLINE_ENTITY = "centerline"
SMOOTHED_ENTITY = "centerline_smoothed"
METADATA_NAME = "pipeline"

# The one mm -> m factor of the project (see _metres).
M_PER_MM = 1e-3

# A voxel centre is three float32 (x, y, z) metres: 12 bytes.
_POINT_FIELDS = tuple(
    PackedElementField(name=axis, offset=4 * i, type=PackedElementField.FLOAT32)
    for i, axis in enumerate("xyz")
)
_POINT_STRIDE = 12
# A centreline sample: float64 x, y, z metres (the curves' own precision, as in the SceneUpdate),
# then its colour as four uint8, which Foxglove and Rerun both read from these field names.
_SAMPLE_DTYPE = np.dtype([("xyz_m", "<f8", 3), ("rgba", "u1", 4)])
_SAMPLE_FIELDS = tuple(
    PackedElementField(name=axis, offset=8 * i, type=PackedElementField.FLOAT64)
    for i, axis in enumerate("xyz")
) + tuple(
    PackedElementField(name=channel, offset=24 + i, type=PackedElementField.UINT8)
    for i, channel in enumerate(("red", "green", "blue", "alpha"))
)
_CENTERLINE_COLOR = Color(r=1.0, g=0.55, b=0.0, a=1.0)
_SMOOTHED_COLOR = Color(r=0.2, g=0.6, b=1.0, a=1.0)
_CENTERLINE_THICKNESS_M = 0.004

_NUMBER_OR_NULL = {"type": ["number", "null"]}
METRICS_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "pipeline.FrameMetrics",
    "description": "Per-frame reconstruction figures; geometry in metres, null when unknown.",
    "type": "object",
    "properties": {
        "frame": {"type": "integer", "minimum": 0, "description": "frame index in the session"},
        "status": {"enum": ["ok", "empty", "failed"]},
        "reason": {"type": "string", "description": "why the frame is empty or failed"},
        "tip_m": {
            "type": ["array", "null"],
            "items": {"type": "number"},
            "minItems": 3,
            "maxItems": 3,
            "description": "centreline tip, world frame, metres",
        },
        "length_m": _NUMBER_OR_NULL,
        "mean_curvature_per_m": _NUMBER_OR_NULL,
        "radius_m": _NUMBER_OR_NULL,
        "fit_residual_m": _NUMBER_OR_NULL,
        "iou": {
            "type": "object",
            "additionalProperties": _NUMBER_OR_NULL,
            "description": "camera name -> IoU of the re-projected tube with the silhouette",
        },
        "voxel_count": {"type": "integer", "minimum": 0},
        "tracked": {"type": "boolean", "description": "fitted from the previous frames, not from the hull"},
        "suspect": {"type": "boolean", "description": "the curve may be wrong (see suspect_reason)"},
        "suspect_reason": {
            "type": "string",
            "description": "why the curve may be wrong; empty if nothing says so",
        },
        "timings_s": {"type": "object", "additionalProperties": {"type": "number"}},
        "latency_ms": {
            "type": "number",
            "description": "live runs only: from the capture of the frame's last image to its result "
            "being written, milliseconds",
        },
    },
    "required": ["frame", "status", "reason", "voxel_count"],
}


@dataclass(frozen=True)
class ChannelSchema:
    """What a reader needs to decode a topic's messages.

    name, encoding, data : the schema (a protobuf FileDescriptorSet, or a JSON Schema).
    message_encoding : "protobuf" or "json".
    """

    name: str
    encoding: str
    data: bytes
    message_encoding: str


# Called with every message the recorder writes, as written: (topic, schema, bytes, log time
# in ns since the Unix epoch). A live run passes one to publish the same topics on a server.
MessageMirror = Callable[[str, ChannelSchema, bytes, int], None]

METRICS_CHANNEL_SCHEMA = ChannelSchema(
    name=METRICS_SCHEMA["title"],
    encoding=SchemaEncoding.JSONSchema,
    data=json.dumps(METRICS_SCHEMA).encode(),
    message_encoding=MessageEncoding.JSON,
)


def protobuf_schema(message: Message) -> ChannelSchema:
    """The schema of ``message``'s type, as MCAP and Foxglove take it."""
    return ChannelSchema(
        name=message.DESCRIPTOR.full_name,
        encoding=SchemaEncoding.Protobuf,
        data=build_file_descriptor_set(type(message)).SerializeToString(),
        message_encoding=MessageEncoding.Protobuf,
    )


def _metres(values_mm: Any) -> NDArray[np.float64]:
    """Millimetres (the pipeline's unit) -> metres (the MCAP's unit): the only conversion."""
    return np.asarray(values_mm, dtype=np.float64) * M_PER_MM


def _timestamp(time_ns: int) -> Timestamp:
    stamp = Timestamp()
    stamp.FromNanoseconds(time_ns)
    return stamp


def _finite_or_none(value: float) -> float | None:
    # JSON has no NaN: unknown figures are null.
    return float(value) if math.isfinite(value) else None


def frame_metrics(result: FrameResult, camera_names: Sequence[str]) -> dict[str, Any]:
    """The JSON metrics of one frame (matches :data:`METRICS_SCHEMA`)."""
    tip = result.tip_mm
    curvature = result.curvature_per_mm
    mean_curvature = (
        float(np.mean(curvature)) / M_PER_MM if curvature is not None and len(curvature) else math.nan
    )
    return {
        "frame": int(result.index),
        "status": result.status,
        "reason": result.reason,
        "tip_m": None if tip is None else [float(v) for v in _metres(tip)],
        "length_m": _finite_or_none(float(_metres(result.length_mm))),
        "mean_curvature_per_m": _finite_or_none(mean_curvature),
        "radius_m": _finite_or_none(float(_metres(result.radius_mm))),
        "fit_residual_m": _finite_or_none(float(_metres(result.fit_residual_mm))),
        "iou": {name: _finite_or_none(v) for name, v in zip(camera_names, result.iou, strict=False)},
        "voxel_count": int(result.voxel_count),
        "tracked": bool(result.tracked),
        "suspect": result.suspect,
        "suspect_reason": result.suspect_reason,
        "timings_s": {k: float(v) for k, v in result.timings_s.items()},
    }


def _line_update(
    curve_mm: NDArray[np.float64] | None, time_ns: int, entity: str, color: Color
) -> SceneUpdate:
    """A SceneUpdate drawing ``curve_mm`` as one LINE_STRIP, or deleting the entity when None."""
    if curve_mm is None or not np.isfinite(curve_mm).all():
        # No curve this frame: delete the previous frame's line rather than leave it on screen.
        return SceneUpdate(
            deletions=[
                SceneEntityDeletion(
                    timestamp=_timestamp(time_ns), type=SceneEntityDeletion.MATCHING_ID, id=entity
                )
            ]
        )
    points = [Point3(x=x, y=y, z=z) for x, y, z in _metres(curve_mm).tolist()]
    line = LinePrimitive(
        type=LinePrimitive.LINE_STRIP,
        pose=_identity_pose(),
        thickness=_CENTERLINE_THICKNESS_M,
        scale_invariant=False,
        points=points,
        color=color,
    )
    entity_msg = SceneEntity(
        timestamp=_timestamp(time_ns), frame_id=WORLD_FRAME, id=entity, lines=[line], frame_locked=True
    )
    return SceneUpdate(entities=[entity_msg])


def _identity_pose() -> Pose:
    # Set explicitly: an unset pose is read as all-zero (an invalid quaternion) by some
    # consumers, and `rerun mcap convert` then produces a file that fails verification.
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = 0.0, 0.0, 0.0
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = 0.0, 0.0, 0.0, 1.0
    return pose


def point_cloud(points_mm: NDArray[np.float32], time_ns: int) -> PointCloud:
    """(P, 3) voxel centres (world frame, mm) -> a PointCloud of float32 x, y, z in metres."""
    data = np.ascontiguousarray(_metres(points_mm).reshape(-1, 3), dtype="<f4").tobytes()
    return PointCloud(
        timestamp=_timestamp(time_ns),
        frame_id=WORLD_FRAME,
        pose=_identity_pose(),
        point_stride=_POINT_STRIDE,
        fields=_POINT_FIELDS,
        data=data,
    )


def centerline_cloud(curve_mm: NDArray[np.float64] | None, time_ns: int, color: Color) -> PointCloud:
    """(N, 3) centreline samples (world frame, mm, base first) -> a PointCloud of them in that
    order, in metres and ``color``; no points when ``curve_mm`` is None or not finite."""
    if curve_mm is None or not np.isfinite(curve_mm).all():
        curve_mm = np.zeros((0, 3))
    samples = np.zeros(len(curve_mm), _SAMPLE_DTYPE)
    samples["xyz_m"] = _metres(curve_mm)
    samples["rgba"] = [round(255 * c) for c in (color.r, color.g, color.b, color.a)]
    return PointCloud(
        timestamp=_timestamp(time_ns),
        frame_id=WORLD_FRAME,
        pose=_identity_pose(),
        point_stride=_SAMPLE_DTYPE.itemsize,
        fields=_SAMPLE_FIELDS,
        data=samples.tobytes(),
    )


def camera_transform(camera: Camera, time_ns: int) -> FrameTransform:
    """world -> camera as Foxglove expects it: the camera's pose in the world frame.

    The calibration stores camera-from-world (x_cam = R X_world + t); the transform
    from parent "world" to child "<camera>" is its inverse, world-from-camera:
    translation = the optical centre -R^T t, rotation = R^T.
    """
    centre_m = _metres(camera.center_mm)
    x, y, z, w = Rotation.from_matrix(camera.camera_from_world.T).as_quat()
    transform = FrameTransform(
        timestamp=_timestamp(time_ns), parent_frame_id=WORLD_FRAME, child_frame_id=camera.name
    )
    transform.translation.x, transform.translation.y, transform.translation.z = (float(v) for v in centre_m)
    transform.rotation.x, transform.rotation.y = float(x), float(y)
    transform.rotation.z, transform.rotation.w = float(z), float(w)
    return transform


def camera_calibration(camera: Camera, time_ns: int) -> CameraCalibration:
    """The camera's intrinsics (pixels) with its OpenCV distortion, in its own frame.

    OpenCV's coefficients under their ROS model names, which Foxglove reads: 4 or 5
    (k1, k2, p1, p2[, k3]) as "plumb_bob", padded to 5; 8 (k4, k5, k6 too) as
    "rational_polynomial". 12 or 14 (thin prism s1-s4, tilt tx, ty) have no name of their
    own: they go as "rational_polynomial" whole, which OpenCV-based readers (ROS's
    image_geometry) take as they are and Foxglove reads the first 8 of."""
    k = np.asarray(camera.matrix, dtype=np.float64)
    projection = np.hstack([k, np.zeros((3, 1))])  # P = [K | 0]: no rectification
    coefficients = [float(v) for v in camera.distortions]
    plumb_bob = len(coefficients) <= 5
    return CameraCalibration(
        timestamp=_timestamp(time_ns),
        frame_id=camera.name,
        width=camera.width,
        height=camera.height,
        distortion_model="plumb_bob" if plumb_bob else "rational_polynomial",
        D=coefficients + [0.0] * (5 - len(coefficients)) if plumb_bob else coefficients,
        K=[float(v) for v in k.ravel()],
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=[float(v) for v in projection.ravel()],
    )


class McapRecorder:
    """Writes a session's frames to an open binary sink as MCAP.

    Parameters
    ----------
    sink : an open, writable binary file object (a file, ``io.BytesIO``); not closed here.
    cameras : the session's cameras, in the order of FrameResult.iou and the images.
    images : write ``/cameras/<name>/image`` when JPEG bytes are given.
    metadata : extra key/value strings for the "pipeline" metadata record.
    chunk_size : bytes of messages per zstd chunk.
    mirror : also called with every message written (see :data:`MessageMirror`).
    """

    def __init__(
        self,
        sink: IO[bytes],
        cameras: Sequence[Camera],
        *,
        images: bool = True,
        metadata: dict[str, str] | None = None,
        chunk_size: int = 1024 * 1024,
        mirror: MessageMirror | None = None,
    ) -> None:
        self._cameras = tuple(cameras)
        self._mirror = mirror
        self._mirror_schemas: dict[str, ChannelSchema] = {}
        self._names = tuple(c.name for c in cameras)
        self._images = images
        self._writer = Writer(sink, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library="pipeline")
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._statics_written = False
        self._finished = False
        # The names as a JSON list: a name may hold any character, a comma too.
        meta = {"cameras": json.dumps(self._names), "units": "metres", "frame_id": WORLD_FRAME}
        meta.update(metadata or {})
        # Metadata goes first so that even a file truncated early names its cameras.
        self._writer.add_metadata(METADATA_NAME, meta)

    # -- channels -------------------------------------------------------------------------------

    def _protobuf_channel(self, topic: str, message: Message) -> int:
        if topic not in self._channels:
            name = message.DESCRIPTOR.full_name
            if name not in self._schemas:
                self._schemas[name] = register_schema(self._writer, type(message))
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding=MessageEncoding.Protobuf, schema_id=self._schemas[name]
            )
        return self._channels[topic]

    def _json_channel(self, topic: str) -> int:
        if topic not in self._channels:
            schema = METRICS_CHANNEL_SCHEMA
            schema_id = self._writer.register_schema(
                name=schema.name, encoding=schema.encoding, data=schema.data
            )
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding=MessageEncoding.JSON, schema_id=schema_id
            )
        return self._channels[topic]

    def _write(self, topic: str, message: Message, time_ns: int) -> None:
        channel = self._protobuf_channel(topic, message)
        data = message.SerializeToString()
        self._writer.add_message(channel_id=channel, log_time=time_ns, publish_time=time_ns, data=data)
        if self._mirror is not None:
            name = message.DESCRIPTOR.full_name
            if name not in self._mirror_schemas:
                self._mirror_schemas[name] = protobuf_schema(message)
            self._mirror(topic, self._mirror_schemas[name], data, time_ns)

    # -- messages -------------------------------------------------------------------------------

    def write_statics(self, time_ns: int) -> None:
        """Calibration and camera poses, once, at ``time_ns`` (the first frame's time)."""
        transforms = FrameTransforms(transforms=[camera_transform(c, time_ns) for c in self._cameras])
        self._write(TF_TOPIC, transforms, time_ns)
        for camera in self._cameras:
            self._write(f"/cameras/{camera.name}/calibration", camera_calibration(camera, time_ns), time_ns)
        self._statics_written = True

    def write_frame(
        self,
        result: FrameResult,
        time_ns: int,
        *,
        jpegs: Sequence[bytes] | None = None,
        extra_metrics: dict[str, float] | None = None,
    ) -> bytes:
        """All messages of one frame; the metrics message comes last (see the module docstring).
        ``extra_metrics``: figures the frame's metrics gain (a live run's ``latency_ms``).
        Returns the metrics message written (JSON)."""
        if not self._statics_written:
            self.write_statics(time_ns)
        if self._images and jpegs is not None:
            for name, jpeg in zip(self._names, jpegs, strict=True):
                if jpeg:
                    image = CompressedImage(
                        timestamp=_timestamp(time_ns), frame_id=name, data=jpeg, format="jpeg"
                    )
                    self._write(f"/cameras/{name}/image", image, time_ns)
        self._write(POINTS_TOPIC, point_cloud(result.points_mm, time_ns), time_ns)
        curve = result.centerline_mm if result.status == "ok" else None
        self._write(
            CENTERLINE_TOPIC, _line_update(curve, time_ns, CENTERLINE_ENTITY, _CENTERLINE_COLOR), time_ns
        )
        self._write(CENTERLINE_POINTS_TOPIC, centerline_cloud(curve, time_ns, _CENTERLINE_COLOR), time_ns)
        figures = frame_metrics(result, self._names) | (extra_metrics or {})
        metrics = json.dumps(figures, allow_nan=False).encode()
        self.write_metrics(metrics, time_ns)
        return metrics

    def write_metrics(self, metrics: bytes, time_ns: int) -> None:
        """One frame's metrics message (JSON of :func:`frame_metrics`), at its frame's time."""
        self._writer.add_message(
            channel_id=self._json_channel(METRICS_TOPIC), log_time=time_ns, publish_time=time_ns, data=metrics
        )
        if self._mirror is not None:
            self._mirror(METRICS_TOPIC, METRICS_CHANNEL_SCHEMA, metrics, time_ns)

    def write_smoothed(self, centerlines_mm: NDArray[np.float64], times_ns: Sequence[int]) -> None:
        """Temporally smoothed centrelines, (F, N, 3) mm with NaN rows, at their frames' times."""
        for curve, time_ns in zip(centerlines_mm, times_ns, strict=True):
            update = _line_update(curve, int(time_ns), SMOOTHED_ENTITY, _SMOOTHED_COLOR)
            self._write(SMOOTHED_TOPIC, update, int(time_ns))
            cloud = centerline_cloud(curve, int(time_ns), _SMOOTHED_COLOR)
            self._write(SMOOTHED_POINTS_TOPIC, cloud, int(time_ns))

    def finish(self) -> None:
        """Write the summary section and footer; the sink stays open."""
        if not self._finished:
            self._writer.finish()
            self._finished = True
