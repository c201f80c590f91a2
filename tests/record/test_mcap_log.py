"""The MCAP writer: topics, schemas, zstd chunks, times, metres, conventions.

Files are written to BytesIO from hand-made FrameResults and read back with the
plain mcap reader (and, once, converted by the `rerun` CLI).
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
import pyarrow as pa
import pytest
from conftest import rig_cameras
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import StreamReader
from mcap_protobuf.decoder import DecoderFactory
from scipy.spatial.transform import Rotation

from pipeline.reconstruct.frame_result import FrameResult
from pipeline.record.mcap_log import METRICS_SCHEMA, McapRecorder, camera_calibration

T0_NS = 1_700_000_000_000_000_000
DT_NS = 33_333_333
N_FRAMES = 6
CURVE_MM = np.column_stack([np.full(5, 100.0), np.linspace(0.0, 40.0, 5), np.linspace(10.0, 50.0, 5)])
POINTS_MM = np.array([[1000.0, 2000.0, 3000.0], [4.0, 5.0, 6.0]], dtype=np.float32)


def _result(i: int) -> FrameResult:
    if i == 2:
        return FrameResult(index=i, status="empty", reason="no silhouette in cam1")
    if i == 4:
        return FrameResult.failed(i, "camera cam0: frame could not be decoded")
    return FrameResult(
        index=i,
        status="ok",
        points_mm=POINTS_MM,
        centerline_mm=CURVE_MM + i,
        curvature_per_mm=np.full(5, 0.002),
        length_mm=40.0,
        radius_mm=6.0,
        fit_residual_mm=float("nan"),
        iou=(0.9, 0.8, 0.7),
        timings_s={"carve": 0.01},
    )


def _smoothed(i: int) -> np.ndarray:
    """Frame i's smoothed curve, (5, 3) mm; NaN where the frame has no curve (2 and 4)."""
    return CURVE_MM + i + 0.5 if _result(i).status == "ok" else np.full_like(CURVE_MM, np.nan)


def _write(*, images: bool = True) -> bytes:
    buf = io.BytesIO()
    recorder = McapRecorder(buf, rig_cameras(), images=images, chunk_size=2000)
    for i in range(N_FRAMES):
        jpegs = [b"\xff\xd8fake-jpeg-%d" % i] * 3
        recorder.write_frame(_result(i), T0_NS + i * DT_NS, jpegs=jpegs)
    times_ns = [T0_NS + i * DT_NS for i in range(N_FRAMES)]
    recorder.write_smoothed(np.stack([_smoothed(i) for i in range(N_FRAMES)]), times_ns)
    recorder.finish()
    return buf.getvalue()


@pytest.fixture(scope="module")
def mcap_bytes() -> bytes:
    return _write()


def _messages(data: bytes) -> list[tuple[str, str, str, int, int, Any]]:
    """(topic, schema name, schema encoding, log_time, publish_time, decoded) per message."""
    reader = make_reader(io.BytesIO(data), decoder_factories=[DecoderFactory()])
    out = []
    for schema, channel, message in reader.iter_messages():
        if channel.message_encoding == "json":
            decoded: Any = json.loads(message.data)
        else:
            decode = DecoderFactory().decoder_for(channel.message_encoding, schema)
            assert decode is not None
            decoded = decode(message.data)
        assert schema is not None
        out.append(
            (channel.topic, schema.name, schema.encoding, message.log_time, message.publish_time, decoded)
        )
    return out


def test_topics_and_schemas(mcap_bytes: bytes) -> None:
    topics = {(t, name, enc) for t, name, enc, *_ in _messages(mcap_bytes)}
    expected = {
        ("/reconstruction/points", "foxglove.PointCloud", "protobuf"),
        ("/reconstruction/centerline", "foxglove.SceneUpdate", "protobuf"),
        ("/reconstruction/centerline_smoothed", "foxglove.SceneUpdate", "protobuf"),
        ("/reconstruction/centerline_points", "foxglove.PointCloud", "protobuf"),
        ("/reconstruction/centerline_smoothed_points", "foxglove.PointCloud", "protobuf"),
        ("/reconstruction/metrics", "pipeline.FrameMetrics", "jsonschema"),
        ("/tf", "foxglove.FrameTransforms", "protobuf"),
    }
    for cam in ("cam0", "cam1", "cam2"):
        expected.add((f"/cameras/{cam}/calibration", "foxglove.CameraCalibration", "protobuf"))
        expected.add((f"/cameras/{cam}/image", "foxglove.CompressedImage", "protobuf"))
    assert topics == expected


def test_chunks_are_zstd(mcap_bytes: bytes) -> None:
    chunks = [
        r for r in StreamReader(io.BytesIO(mcap_bytes), emit_chunks=True).records if isinstance(r, Chunk)
    ]
    assert len(chunks) > 1  # chunk_size=2000 bytes forces several
    assert {c.compression for c in chunks} == {"zstd"}


def test_log_and_publish_times_are_frame_timestamps(mcap_bytes: bytes) -> None:
    messages = _messages(mcap_bytes)
    frame_times = {T0_NS + i * DT_NS for i in range(N_FRAMES)}
    for topic, _, _, log_time, publish_time, _ in messages:
        assert log_time == publish_time
        assert log_time in frame_times, topic
    metrics = [(m[3], m[5]) for m in messages if m[0] == "/reconstruction/metrics"]
    assert [t for t, _ in metrics] == [T0_NS + d["frame"] * DT_NS for _, d in metrics]
    statics = [m[3] for m in messages if m[0] in ("/tf", "/cameras/cam0/calibration")]
    assert statics == [T0_NS, T0_NS]  # once, at the first frame's time


def test_geometry_is_in_metres_with_an_identity_pose(mcap_bytes: bytes) -> None:
    clouds = [m[5] for m in _messages(mcap_bytes) if m[0] == "/reconstruction/points"]
    cloud = clouds[0]
    assert cloud.frame_id == "world" and cloud.point_stride == 12
    assert [(f.name, f.offset, f.type) for f in cloud.fields] == [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)]
    # Explicitly set, not merely defaulted: HasField is False for an unset sub-message.
    assert cloud.HasField("pose") and cloud.pose.HasField("orientation")
    assert cloud.pose.orientation.w == 1.0 and cloud.pose.position.x == 0.0
    xyz = np.frombuffer(cloud.data, dtype="<f4").reshape(-1, 3)
    # float32 keeps 7 significant digits: 3.0 m is exact, 0.004 m to ~1e-9.
    np.testing.assert_allclose(xyz, POINTS_MM / 1000.0, rtol=1e-7)
    updates = [m[5] for m in _messages(mcap_bytes) if m[0] == "/reconstruction/centerline"]
    entity = updates[0].entities[0]
    assert entity.id == "centerline" and entity.frame_id == "world"
    (line,) = entity.lines
    assert line.type == 0  # LINE_STRIP
    got = np.array([(p.x, p.y, p.z) for p in line.points])
    np.testing.assert_allclose(got, CURVE_MM / 1000.0, rtol=1e-12)  # float64 on the wire


def test_frames_without_a_curve_delete_the_line(mcap_bytes: bytes) -> None:
    updates = [m[5] for m in _messages(mcap_bytes) if m[0] == "/reconstruction/centerline"]
    assert [len(u.entities) for u in updates] == [1, 1, 0, 1, 0, 1]
    assert updates[2].deletions[0].id == "centerline"


def _samples(cloud: Any) -> np.ndarray:
    """A centreline PointCloud's x, y, z -> (N, 3) float64, read through its field table."""
    offsets = {f.name: (f.offset, f.type) for f in cloud.fields}
    assert {offsets[a][1] for a in "xyz"} == {8}  # FLOAT64
    raw = np.frombuffer(cloud.data, np.uint8).reshape(-1, cloud.point_stride)
    return np.column_stack([raw[:, offsets[a][0] : offsets[a][0] + 8].copy().view("<f8") for a in "xyz"])


def test_centrelines_are_also_point_clouds_of_their_ordered_samples(mcap_bytes: bytes) -> None:
    messages = _messages(mcap_bytes)
    for topic, curve, rgba in (
        ("/reconstruction/centerline_points", lambda i: CURVE_MM + i, (255, 140, 0, 255)),
        ("/reconstruction/centerline_smoothed_points", _smoothed, (51, 153, 255, 255)),
    ):
        clouds = [(m[3], m[5]) for m in messages if m[0] == topic]
        assert [t for t, _ in clouds] == [T0_NS + i * DT_NS for i in range(N_FRAMES)], topic
        for i, (_, cloud) in enumerate(clouds):
            assert cloud.frame_id == "world" and cloud.pose.orientation.w == 1.0
            if i in (2, 4):  # no curve: no points, so a viewer shows none rather than the last one
                assert cloud.data == b""
                continue
            # Base first and float64 metres, exactly the SceneUpdate's numbers.
            np.testing.assert_allclose(_samples(cloud), curve(i) / 1000.0, rtol=1e-12)
            offsets = {f.name: f.offset for f in cloud.fields}
            raw = np.frombuffer(cloud.data, np.uint8).reshape(-1, cloud.point_stride)
            colours = raw[:, [offsets[c] for c in ("red", "green", "blue", "alpha")]]
            assert {tuple(c) for c in colours.tolist()} == {rgba}


def test_metrics_follow_their_schema(mcap_bytes: bytes) -> None:
    metrics = [m[5] for m in _messages(mcap_bytes) if m[0] == "/reconstruction/metrics"]
    for m in metrics:
        jsonschema.validate(m, METRICS_SCHEMA)
    ok, empty, failed = metrics[0], metrics[2], metrics[4]
    assert ok["status"] == "ok" and ok["voxel_count"] == 2
    assert ok["tip_m"] == pytest.approx((CURVE_MM[-1] / 1000).tolist(), rel=1e-12)
    assert ok["length_m"] == pytest.approx(0.04, rel=1e-12)
    assert ok["mean_curvature_per_m"] == pytest.approx(2.0, rel=1e-12)
    assert ok["fit_residual_m"] is None  # NaN is not JSON: unknown is null
    assert ok["iou"] == {"cam0": 0.9, "cam1": 0.8, "cam2": 0.7}
    assert empty["status"] == "empty" and empty["reason"] == "no silhouette in cam1"
    assert failed["status"] == "failed" and failed["tip_m"] is None


def test_tf_is_the_camera_pose_in_the_world(mcap_bytes: bytes) -> None:
    (tf,) = [m[5] for m in _messages(mcap_bytes) if m[0] == "/tf"]
    points_mm = np.random.default_rng(0).uniform(0, 256, (10, 3))
    for cam, transform in zip(rig_cameras(), tf.transforms, strict=True):
        assert (transform.parent_frame_id, transform.child_frame_id) == ("world", cam.name)
        q = transform.rotation
        world_from_cam = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
        t = np.array([transform.translation.x, transform.translation.y, transform.translation.z])
        # Inverting the pose must give the calibration's camera-from-world mapping.
        x_cam_m = (points_mm / 1000.0 - t) @ world_from_cam
        np.testing.assert_allclose(x_cam_m * 1000.0, cam.to_camera(points_mm), atol=1e-9)


def test_camera_calibration_holds_k_d_and_p(mcap_bytes: bytes) -> None:
    calibrations = {m[0]: m[5] for m in _messages(mcap_bytes) if m[0].endswith("/calibration")}
    for cam in rig_cameras():
        calib = calibrations[f"/cameras/{cam.name}/calibration"]
        assert calib.frame_id == cam.name and (calib.width, calib.height) == (320, 240)
        assert calib.distortion_model == "plumb_bob"
        np.testing.assert_array_equal(np.reshape(calib.K, (3, 3)), cam.matrix)
        np.testing.assert_array_equal(calib.D, cam.distortions)
        np.testing.assert_array_equal(np.reshape(calib.P, (3, 4))[:, :3], cam.matrix)
        np.testing.assert_array_equal(np.reshape(calib.R, (3, 3)), np.eye(3))


@pytest.mark.parametrize(
    ("count", "model"),
    [
        (4, "plumb_bob"),
        (5, "plumb_bob"),
        (8, "rational_polynomial"),
        (12, "rational_polynomial"),
        (14, "rational_polynomial"),
    ],
)
def test_each_count_of_distortion_coefficients_is_named_by_its_model(count: int, model: str) -> None:
    coefficients = np.random.default_rng(count).normal(0.0, 0.01, count)
    cam = dataclasses.replace(rig_cameras()[0], distortions=coefficients)
    calib = camera_calibration(cam, 0)
    assert calib.distortion_model == model
    # The coefficients as given, k3 = 0 added where OpenCV's four leave it out.
    np.testing.assert_array_equal(calib.D, np.concatenate([coefficients, np.zeros(max(5 - count, 0))]))


def test_images_are_jpeg_in_the_camera_frame(mcap_bytes: bytes) -> None:
    images = [(m[0], m[5]) for m in _messages(mcap_bytes) if m[0].endswith("/image")]
    assert len(images) == 3 * N_FRAMES
    topic, image = images[0]
    assert image.format == "jpeg" and image.frame_id == topic.split("/")[2]
    assert image.data == b"\xff\xd8fake-jpeg-0"


def test_no_images_when_disabled() -> None:
    topics = {m[0] for m in _messages(_write(images=False))}
    assert not any(t.endswith("/image") for t in topics)
    assert "/reconstruction/points" in topics


def test_rerun_converts_the_mcap_into_a_valid_rrd(mcap_bytes: bytes, tmp_path: Path) -> None:
    rerun = Path(sys.executable).parent / "rerun"  # the CLI installed with rerun-sdk
    src, dst = tmp_path / "x.mcap", tmp_path / "x.rrd"
    src.write_bytes(mcap_bytes)
    env = {**os.environ, "RERUN_ANALYTICS": "off"}
    subprocess.run(
        [str(rerun), "mcap", "convert", str(src), "-o", str(dst)], check=True, env=env, capture_output=True
    )
    verify = subprocess.run([str(rerun), "rrd", "verify", str(dst)], env=env, capture_output=True, text=True)
    assert verify.returncode == 0, verify.stderr
    from rerun.chunk import RrdReader

    chunks = [c for c in RrdReader(dst).stream() if c.entity_path == "/reconstruction/points"]
    columns = {name for c in chunks for name in c.to_record_batch().schema.names}
    assert "Points3D:positions" in columns
    # The centrelines, which Rerun's importer does not take from a SceneUpdate, arrive as
    # the ordered samples of their PointClouds, one row per frame.
    for entity, curve in (
        ("/reconstruction/centerline_points", lambda i: CURVE_MM + i),
        ("/reconstruction/centerline_smoothed_points", _smoothed),
    ):
        table = RrdReader(dst).stream().collect().reader(index="message_log_time", contents=entity)
        rows = table.to_arrow_table()
        times_ns = rows.column("message_log_time").cast(pa.int64()).to_pylist()
        positions = rows.column(f"{entity}:Points3D:positions").to_pylist()
        got = dict(zip(times_ns, positions, strict=True))
        assert sorted(got) == [T0_NS + i * DT_NS for i in range(N_FRAMES)], entity
        for i in range(N_FRAMES):
            samples = got[T0_NS + i * DT_NS]
            if i in (2, 4):
                assert samples == [], (entity, i)
            else:
                # Rerun keeps float32: 0.15 m to ~1e-8 m.
                np.testing.assert_allclose(samples, curve(i) / 1000.0, atol=1e-7)
