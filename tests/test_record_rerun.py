"""The Rerun writer: checked with Rerun's own tools (`rerun rrd verify`, RrdReader)."""

from __future__ import annotations

import os
import subprocess
import sys
import uuid
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import pytest
import rerun as rr
from conftest import rig_cameras
from rerun.chunk import RrdReader

from pipeline.frame_result import FrameResult
from pipeline.record_rerun import RerunRecorder, default_blueprint
from pipeline.settings import Workspace

T0_NS = 1_700_000_000_000_000_000
DT_NS = 33_333_333
N_FRAMES = 8
EMPTY = 3


def _curve(i: int) -> np.ndarray:
    s = np.linspace(0.0, 1.0, 9)
    return np.column_stack([128 + 30 * s * np.sin(0.3 * i), np.full(9, 128.0), 150 * s])


def _result(i: int) -> FrameResult:
    if i == EMPTY:
        return FrameResult(index=i, status="empty", reason="nothing seen")
    return FrameResult(
        index=i,
        status="ok",
        points_mm=np.array([[128.0, 128.0, 10.0 * i]], np.float32),
        centerline_mm=_curve(i),
        curvature_per_mm=np.full(9, 0.01 * i),
        length_mm=150.0 + i,
        iou=(0.9, 0.8, 0.7),
    )


@pytest.fixture(scope="module")
def rrd(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rerun") / "s.rrd"
    cams = rig_cameras()
    stream = rr.RecordingStream(application_id="pipeline", recording_id=uuid.uuid4())
    stream.set_log_time_enabled(False)
    stream.save(path, default_blueprint=default_blueprint([c.name for c in cams]))
    recorder = RerunRecorder(stream, cams, Workspace())
    jpeg = cv2.imencode(".jpg", np.full((240, 320), 90, np.uint8))[1].tobytes()
    png = cv2.imencode(".png", np.zeros((240, 320, 4), np.uint8))[1].tobytes()
    for i in range(N_FRAMES):
        silhouettes = None if i == EMPTY else [png] * 3  # as when a frame has no silhouettes
        recorder.write_frame(_result(i), T0_NS + i * DT_NS, jpegs=[jpeg] * 3, silhouettes_png=silhouettes)
    smoothed = np.stack([_curve(i) + 1.0 for i in range(N_FRAMES)])
    smoothed[EMPTY] = np.nan
    recorder.write_smoothed(smoothed, list(range(N_FRAMES)), [T0_NS + i * DT_NS for i in range(N_FRAMES)])
    recorder.finish()
    stream.flush()
    stream.disconnect()
    return path


def _table(path: Path, entity: str, index: str | None = "frame") -> Any:
    store = RrdReader(path).stream().collect()
    return store.reader(index=index, contents=entity).to_arrow_table()


def _column(table: Any, suffix: str) -> list[Any]:
    (name,) = [n for n in table.column_names if n.endswith(suffix)]
    return table.column(name).to_pylist()


def test_rerun_verifies_the_file(rrd: Path) -> None:
    rerun = Path(sys.executable).parent / "rerun"  # the CLI installed with rerun-sdk
    env = {**os.environ, "RERUN_ANALYTICS": "off"}
    verify = subprocess.run([str(rerun), "rrd", "verify", str(rrd)], env=env, capture_output=True, text=True)
    assert verify.returncode == 0, verify.stderr


def test_the_blueprint_is_saved_with_the_recording(rrd: Path) -> None:
    reader = RrdReader(rrd)
    assert len(reader.blueprints()) == 1 and len(reader.recordings()) == 1


def test_rerun_reads_back_the_logged_centreline(rrd: Path) -> None:
    table = _table(rrd, "/world/centerline")
    frames = _column(table, "frame")
    strips = _column(table, "LineStrips3D:strips")
    got = {f: s for f, s in zip(frames, strips, strict=True) if s}
    assert sorted(got) == [i for i in range(N_FRAMES) if i != EMPTY]
    for i, (strip,) in got.items():
        # Rerun stores float32 positions: 150 mm to ~1e-5 mm.
        np.testing.assert_allclose(np.array(strip), _curve(i), atol=1e-4)
    (time_name,) = [n for n in table.column_names if n == "time"]
    times_ns = table.column(time_name).cast(pa.int64()).to_pylist()
    assert dict(zip(frames, times_ns, strict=True))[2] == T0_NS + 2 * DT_NS


def test_the_reprojected_centreline_uses_the_camera_model(rrd: Path) -> None:
    cam = rig_cameras()[1]
    table = _table(rrd, f"/world/cameras/{cam.name}/image/centerline")
    rows = dict(zip(_column(table, "frame"), _column(table, "LineStrips2D:strips"), strict=True))
    (strip,) = rows[5]
    # Distortion included: Camera.project's pixels, moved from OpenCV's pixel-centre origin
    # to Rerun's pixel-corner origin, to float32 precision.
    np.testing.assert_allclose(np.array(strip), cam.project(_curve(5)) + 0.5, atol=1e-3)


def test_cameras_are_logged_once_as_world_from_camera(rrd: Path) -> None:
    for cam in rig_cameras():
        pose = _table(rrd, f"/world/cameras/{cam.name}", index=None)
        (translation,) = _column(pose, "Transform3D:translation")
        (mat,) = _column(pose, "Transform3D:mat3x3")
        np.testing.assert_allclose(np.ravel(translation), cam.center_mm, rtol=1e-6)  # float32
        # Rerun stores 3x3 matrices column-major.
        np.testing.assert_allclose(np.reshape(mat, (3, 3)).T, cam.camera_from_world.T, atol=1e-6)
        pinhole = _table(rrd, f"/world/cameras/{cam.name}/image", index=None)
        (k,) = _column(pinhole, "Pinhole:image_from_camera")
        expected_k = cam.matrix + np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])  # principal point moved
        np.testing.assert_allclose(np.reshape(k, (3, 3)).T, expected_k, rtol=1e-6)
        assert _column(pinhole, "Pinhole:resolution") == [[[320.0, 240.0]]]  # one row, one instance


def test_time_series_are_sent_as_columns(rrd: Path) -> None:
    table = _table(rrd, "/plots/tip/z")
    frames, values = _column(table, "frame"), _column(table, "Scalars:scalars")
    assert frames == [i for i in range(N_FRAMES) if i != EMPTY]  # no value, no point
    assert [v[0] for v in values] == pytest.approx([150.0] * len(frames))
    table = _table(rrd, "/plots/voxels")
    assert [v[0] for v in _column(table, "Scalars:scalars")] == [
        0.0 if i == EMPTY else 1.0 for i in range(N_FRAMES)
    ]


def test_smoothed_centreline_has_its_own_entity(rrd: Path) -> None:
    table = _table(rrd, "/world/centerline_smoothed")
    rows = dict(zip(_column(table, "frame"), _column(table, "LineStrips3D:strips"), strict=True))
    np.testing.assert_allclose(np.array(rows[0][0]), _curve(0) + 1.0, atol=1e-4)
    assert not rows.get(EMPTY)


def test_a_frame_without_silhouettes_clears_the_previous_ones(rrd: Path) -> None:
    table = _table(rrd, "/world/cameras/cam2/image/silhouette")
    blobs = dict(zip(_column(table, "frame"), _column(table, "EncodedImage:blob"), strict=True))
    # A Clear reads back as a row with no instance: nothing shown at that frame.
    assert len(blobs[EMPTY - 1]) == 1 and len(blobs[EMPTY]) == 0 and len(blobs[EMPTY + 1]) == 1
