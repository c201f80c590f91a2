"""load_recording: MCAP -> numpy, agreeing with the plain mcap reader, and lenient
with files cut short mid-write."""

from __future__ import annotations

import dataclasses
import io
import json
import logging
import os
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import rewrite_mcap, rig_cameras
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

import pipeline
from pipeline.errors import PipelineError
from pipeline.reconstruct.frame_result import FrameResult
from pipeline.record.load import JsonDecoderFactory
from pipeline.record.mcap_log import McapRecorder

T0_NS = 1_600_000_000_000_000_000
DT_NS = 40_000_000
N_FRAMES = 24
N_POINTS = 7
FAILED = {5, 6, 17}


def _curve(i: int) -> np.ndarray:
    s = np.linspace(0.0, 1.0, N_POINTS)
    return np.column_stack([128 + 10 * s * np.cos(i), 128 + 10 * s * np.sin(i), 150 * s])


def _result(i: int, rng: np.random.Generator) -> FrameResult:
    if i in FAILED:
        return FrameResult.failed(i, "worker died twice")
    points = rng.uniform(0, 256, (20 + i, 3)).astype(np.float32)
    return FrameResult(
        index=i,
        status="ok",
        points_mm=points,
        centerline_mm=_curve(i),
        iou=(1.0, 0.5, 0.25),
        timings_s={"carve": 0.001 * i},
    )


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[FrameResult]]:
    rng = np.random.default_rng(3)
    results = [_result(i, rng) for i in range(N_FRAMES)]
    path = tmp_path_factory.mktemp("recording") / "s.mcap"
    buf = io.BytesIO()
    # Small chunks so that truncations fall between and inside many of them.
    recorder = McapRecorder(
        buf, rig_cameras(), chunk_size=3000, metadata={"centerline_points": str(N_POINTS)}
    )
    for r in results:
        recorder.write_frame(r, T0_NS + r.index * DT_NS, jpegs=[b"jpeg"] * 3)
    smoothed = np.stack([_curve(i) + 1.0 for i in range(N_FRAMES)])
    smoothed[list(FAILED)] = np.nan
    recorder.write_smoothed(smoothed, [T0_NS + i * DT_NS for i in range(N_FRAMES)])
    recorder.finish()
    path.write_bytes(buf.getvalue())
    return path, results


def test_arrays_hold_the_written_frames_in_metres(written: tuple[Path, list[FrameResult]]) -> None:
    path, results = written
    rec = pipeline.load_recording(path)
    assert rec.complete and len(rec) == N_FRAMES
    assert rec.camera_names == ("cam0", "cam1", "cam2")
    np.testing.assert_array_equal(rec.frame_indices, np.arange(N_FRAMES))
    np.testing.assert_array_equal(rec.timestamps_ns, T0_NS + np.arange(N_FRAMES) * DT_NS)
    assert rec.centerlines_m.shape == (N_FRAMES, N_POINTS, 3)
    for r in results:
        if r.index in FAILED:
            assert np.isnan(rec.centerlines_m[r.index]).all()
            assert rec.statuses[r.index] == "failed"
            assert rec.metrics[r.index]["reason"] == "worker died twice"
            continue
        assert r.centerline_mm is not None
        # Centrelines travel as float64: exact up to the mm -> m multiplication.
        np.testing.assert_allclose(rec.centerlines_m[r.index], r.centerline_mm / 1000, rtol=1e-15)
        # Points travel as float32 metres: 7 significant digits.
        np.testing.assert_allclose(rec.points_m[r.index], r.points_mm / 1000, rtol=1e-6)
    assert rec.smoothed_centerlines_m is not None
    np.testing.assert_allclose(rec.smoothed_centerlines_m[0], (_curve(0) + 1.0) / 1000, rtol=1e-15)
    assert np.isnan(rec.smoothed_centerlines_m[5]).all()


def test_loader_agrees_with_the_plain_mcap_reader(written: tuple[Path, list[FrameResult]]) -> None:
    path, _ = written
    rec = pipeline.load_recording(path)
    curves: dict[int, np.ndarray] = {}
    metrics: dict[int, dict] = {}
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message in reader.iter_messages(
            topics=["/reconstruction/centerline", "/reconstruction/metrics"]
        ):
            if channel.topic == "/reconstruction/metrics":
                data = json.loads(message.data)
                metrics[message.log_time] = data
        f.seek(0)
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, _, message, update in reader.iter_decoded_messages(topics=["/reconstruction/centerline"]):
            if update.entities:
                line = update.entities[0].lines[0]
                curves[message.log_time] = np.array([(p.x, p.y, p.z) for p in line.points])
    assert [metrics[t]["frame"] for t in sorted(metrics)] == rec.frame_indices.tolist()
    assert [metrics[t] for t in sorted(metrics)] == rec.metrics
    for row, t in enumerate(rec.timestamps_ns.tolist()):
        if t in curves:
            np.testing.assert_array_equal(rec.centerlines_m[row], curves[t])
        else:
            assert np.isnan(rec.centerlines_m[row]).all()


def test_metrics_table_has_one_column_per_figure_and_camera(written: tuple[Path, list[FrameResult]]) -> None:
    path, _ = written
    rec = pipeline.load_recording(path)
    table = rec.metrics_table()
    assert {len(column) for column in table.values()} == {N_FRAMES}
    np.testing.assert_array_equal(table["timestamp_ns"], rec.timestamps_ns)
    np.testing.assert_array_equal(table["frame"], np.arange(N_FRAMES))
    assert table["frame"].dtype == np.int64 and table["voxel_count"].dtype == np.int64
    np.testing.assert_array_equal(table["status"], rec.statuses)
    failed = np.isin(np.arange(N_FRAMES), sorted(FAILED))
    assert set(table["reason"][failed]) == {"worker died twice"} and set(table["reason"][~failed]) == {""}
    for k, name in enumerate(("cam0", "cam1", "cam2")):
        column = table[f"iou/{name}"]
        assert column.dtype == np.float64
        np.testing.assert_array_equal(column[~failed], (1.0, 0.5, 0.25)[k])
        assert np.isnan(column[failed]).all()  # a failed frame has no IoU: NaN, not a number
    tips_m = np.column_stack([table[f"tip_m/{axis}"] for axis in "xyz"])
    np.testing.assert_array_equal(tips_m[~failed], rec.centerlines_m[~failed, -1])
    assert np.isnan(tips_m[failed]).all()
    for name in ("length_m", "mean_curvature_per_m", "radius_m", "fit_residual_m"):
        assert table[name].dtype == np.float64
    # Every column matches the frame's JSON; a stage a failed frame never ran is NaN.
    for row, metrics in enumerate(rec.metrics):
        assert table["voxel_count"][row] == metrics["voxel_count"]
        if failed[row]:
            assert np.isnan(table["timings_s/carve"][row])
        else:
            assert table["timings_s/carve"][row] == metrics["timings_s"]["carve"] == 0.001 * row


def test_the_plain_mcap_reader_decodes_the_metrics_with_the_documented_decoder(
    written: tuple[Path, list[FrameResult]],
) -> None:
    path, _ = written
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory(), JsonDecoderFactory()])
        decoded = [m for *_, m in reader.iter_decoded_messages(topics=["/reconstruction/metrics"])]
    assert decoded == pipeline.load_recording(path).metrics


def test_a_file_cut_mid_write_reads_up_to_its_last_complete_chunk(
    written: tuple[Path, list[FrameResult]], tmp_path: Path
) -> None:
    path, _ = written
    data = path.read_bytes()
    full = pipeline.load_recording(path)
    counts = []
    for fraction in (0.05, 0.2, 0.37, 0.5, 0.71, 0.9, 0.999):
        cut = tmp_path / f"cut{fraction}.mcap"
        cut.write_bytes(data[: int(len(data) * fraction)])
        rec = pipeline.load_recording(cut)
        assert not rec.complete
        n = len(rec)
        counts.append(n)
        # What is read is exactly the start of the full recording, nothing invented.
        np.testing.assert_array_equal(rec.frame_indices, full.frame_indices[:n])
        np.testing.assert_array_equal(rec.centerlines_m, full.centerlines_m[:n])
        assert rec.metrics == full.metrics[:n]
    assert counts == sorted(counts) and counts[-1] == N_FRAMES and 0 < counts[2] < N_FRAMES


@pytest.mark.parametrize("size", [8, 100])
def test_a_file_cut_before_its_first_frame_is_named_cut_short(
    written: tuple[Path, list[FrameResult]], tmp_path: Path, size: int
) -> None:
    path, _ = written
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:size])  # the opening magic alone, or a little more
    with pytest.raises(PipelineError, match=r"cut\.mcap: an MCAP cut short before its first frame"):
        pipeline.load_recording(cut)


def test_bytes_overwritten_inside_a_file_are_read_as_damage_not_as_a_cut(
    written: tuple[Path, list[FrameResult]], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path, _ = written
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 64] = bytes(64)
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(data)
    rec = pipeline.load_recording(damaged)
    assert rec.damaged and not rec.complete and 0 < len(rec) < N_FRAMES
    (warning,) = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warning.startswith(f"{damaged}: damaged after frame {rec.frame_indices[-1]}: ")
    assert "run `pipeline process` on its session again" in warning and "cut short" not in warning
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:middle])
    caplog.clear()
    assert not pipeline.load_recording(cut).damaged
    assert f"{cut}: cut short after frame" in caplog.text


def test_a_file_damaged_before_its_first_frame_is_named_damaged(
    written: tuple[Path, list[FrameResult]], tmp_path: Path
) -> None:
    path, _ = written
    data = bytearray(path.read_bytes())
    data[30:200] = b"x" * 170
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(data)
    with pytest.raises(
        PipelineError, match=r"damaged\.mcap: damaged before its first frame: .*pipeline process"
    ):
        pipeline.load_recording(damaged)


def test_a_files_warnings_go_to_on_warning_where_given_else_to_the_log(
    written: tuple[Path, list[FrameResult]], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path, _ = written
    cut = tmp_path / "cut%d.mcap"  # a % in the name is logged as it is
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    lines: list[str] = []
    with caplog.at_level(logging.WARNING):
        rec = pipeline.load_recording(cut, on_warning=lines.append)
    assert not caplog.records  # the caller chooses how to show them
    (line,) = lines
    assert line == (
        f"{cut}: cut short after frame {rec.frame_indices[-1]} (the run did not finish); "
        "read what precedes it"
    )
    with caplog.at_level(logging.WARNING):
        pipeline.load_recording(cut)
    assert [r.getMessage() for r in caplog.records] == lines


def test_not_an_mcap_is_a_pipeline_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"this is not an mcap file at all")
    with pytest.raises(PipelineError, match=r"bad\.mcap: is not a readable MCAP recording \(.*\); give the"):
        pipeline.load_recording(bad)
    bad.write_bytes(b"")
    with pytest.raises(PipelineError, match=r"bad\.mcap: is empty \(0 bytes\); give the \.mcap that"):
        pipeline.load_recording(bad)
    bad.write_text('{\n  "frames": {"processed": 4}, "exit_code": 0\n}\n')  # a --json summary
    with pytest.raises(PipelineError, match=r"bad\.mcap: is not an MCAP recording \(it starts like JSON"):
        pipeline.load_recording(bad)
    with pytest.raises(PipelineError, match=r"missing\.mcap: cannot read"):
        pipeline.load_recording(tmp_path / "missing.mcap")


def _mcap_with_metrics(path: Path, messages: list[bytes], metadata: dict[str, str] | None = None) -> Path:
    """A valid MCAP whose metrics topic holds ``messages``, as another tool (or another
    program's recording under the same topic name) would write it."""
    from mcap.writer import Writer

    with path.open("wb") as f:
        writer = Writer(f)
        writer.start()
        schema = writer.register_schema(name="metrics", encoding="jsonschema", data=b"{}")
        channel = writer.register_channel(
            topic="/reconstruction/metrics", message_encoding="json", schema_id=schema
        )
        writer.add_metadata("pipeline", metadata or {})
        for i, data in enumerate(messages):
            writer.add_message(channel_id=channel, log_time=T0_NS + i, publish_time=T0_NS + i, data=data)
        writer.finish()
    return path


@pytest.mark.parametrize(
    ("message", "reason"),
    [
        (b'{"status": "ok"}', "no frame index"),
        (b'{"frame": null, "status": "ok"}', "no frame index"),
        (b'{"frame": 1.5, "status": "ok"}', "no frame index"),
        (b'{"frame": 100000000000000000000000000000, "status": "ok"}', "no frame index"),
        (b'{"frame": 0}', "no status"),
        (b'{"frame": 0, "status": 5}', "no status"),
        (b"[1, 2]", "not a JSON object"),
    ],
    ids=[
        "no-frame",
        "null-frame",
        "float-frame",
        "huge-frame",
        "no-status",
        "int-status",
        "list",
    ],
)
def test_metrics_that_are_not_the_pipelines_are_named(tmp_path: Path, message: bytes, reason: str) -> None:
    path = _mcap_with_metrics(tmp_path / "other.mcap", [b'{"frame": 0, "status": "ok"}', message])
    with pytest.raises(PipelineError, match=rf"other\.mcap: .*not the pipeline's metrics \({reason}"):
        pipeline.load_recording(path)


@pytest.mark.parametrize("topic", [None, "/foo"])
def test_another_programs_mcap_is_named_not_the_pipelines(tmp_path: Path, topic: str | None) -> None:
    from mcap.writer import Writer

    path = tmp_path / "other.mcap"
    with path.open("wb") as f:
        writer = Writer(f)
        writer.start()
        if topic is not None:  # a message on another topic, or none at all
            schema = writer.register_schema(name="x", encoding="jsonschema", data=b"{}")
            channel = writer.register_channel(topic=topic, message_encoding="json", schema_id=schema)
            writer.add_message(channel_id=channel, log_time=T0_NS, publish_time=T0_NS, data=b"{}")
        writer.finish()
    with pytest.raises(PipelineError, match=r"other\.mcap: not a recording written by `pipeline process`"):
        pipeline.load_recording(path)


def _mcap_on_topic(
    path: Path, topic: str, encoding: str, schema: object | None, data: bytes, time_ns: int
) -> Path:
    """A valid MCAP holding one message on ``topic`` (``schema`` a protobuf message class, or
    None for a schema-less one), then one frame's metrics: another program's recording."""
    from mcap.writer import Writer
    from mcap_protobuf.schema import register_schema

    with path.open("wb") as f:
        writer = Writer(f)
        writer.start()
        schema_id = register_schema(writer, schema) if schema is not None else 0
        channel = writer.register_channel(topic=topic, message_encoding=encoding, schema_id=schema_id)
        writer.add_message(channel, log_time=time_ns, publish_time=0, data=data)
        metrics = writer.register_channel(
            topic="/reconstruction/metrics", message_encoding="json", schema_id=0
        )
        writer.add_message(metrics, log_time=T0_NS, publish_time=T0_NS, data=b'{"frame": 0, "status": "ok"}')
        writer.finish()
    return path


def test_messages_of_another_program_on_the_pipelines_topics_are_named_not_called_damage(
    tmp_path: Path,
) -> None:
    from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    cases = [
        ("/reconstruction/metrics", "protobuf", None, b"\x08\x01", T0_NS, r"protobuf encoding, not JSON"),
        (
            "/reconstruction/metrics",
            "json",
            None,
            b"[" * 100_000 + b"]" * 100_000,
            T0_NS,
            r"not JSON: maximum",
        ),
        ("/reconstruction/metrics", "json", None, b'{"frame": 1, "status": "\xff"}', T0_NS, r"not JSON"),
        ("/reconstruction/metrics", "json", None, b'{"frame": 1, "status": "ok"}', 2**64 - 1, r"past 2262"),
        (
            "/reconstruction/points",
            "protobuf",
            PointCloud,
            PointCloud(point_stride=12, data=bytes(24)).SerializeToString(),
            T0_NS,
            r"no field 'x'",
        ),
        (
            "/reconstruction/points",
            "protobuf",
            SceneUpdate,
            SceneUpdate().SerializeToString(),
            T0_NS,
            r"another schema",
        ),
    ]
    for n, (topic, encoding, schema, data, time_ns, why) in enumerate(cases):
        path = _mcap_on_topic(tmp_path / f"other{n}.mcap", topic, encoding, schema, data, time_ns)
        with pytest.raises(PipelineError) as info:
            pipeline.load_recording(path)
        message = str(info.value)
        assert re.search(
            rf"other{n}\.mcap: {topic} holds a message that is not the pipeline's .*{why}", message
        )
        assert "damaged" not in message and message.endswith("give a recording written by `pipeline process`")


def test_odd_figures_of_another_program_read_as_unknown_and_paths_as_the_system_gives_them(
    tmp_path: Path,
) -> None:
    figures = {"frame": 0, "status": "ok", "length_m": {"a": 1}, "voxel_count": 10**40, "radius_m": [1, 2]}
    path = _mcap_with_metrics(
        tmp_path / "odd.mcap", [json.dumps(figures).encode()], {"centerline_points": "999999999999"}
    )
    recording = pipeline.load_recording(os.fsencode(path))  # bytes, as os.listdir(bytes) gives paths
    assert recording.centerlines_m.shape == (1, 0, 3)  # no curve, and no 1e12-point array of NaN
    table = recording.metrics_table()
    assert table["voxel_count"].dtype == np.float64 and table["voxel_count"][0] == 1e40
    with pytest.raises(PipelineError, match=r"^an empty path; give the recording's \.mcap file$"):
        pipeline.load_recording("")


def test_camera_names_with_commas_come_back_whole(tmp_path: Path) -> None:
    names = ["a,b", "c", "d"]
    cameras = [dataclasses.replace(cam, name=name) for cam, name in zip(rig_cameras(), names, strict=True)]
    buf = io.BytesIO()
    recorder = McapRecorder(buf, cameras)
    recorder.write_frame(_result(0, np.random.default_rng(0)), T0_NS, jpegs=[b"jpeg"] * 3)
    recorder.finish()
    (tmp_path / "r.mcap").write_bytes(buf.getvalue())
    rec = pipeline.load_recording(tmp_path / "r.mcap")
    assert rec.camera_names == ("a,b", "c", "d")
    assert {"iou/a,b", "iou/c", "iou/d"} <= set(rec.metrics_table())
    # A recording written when the names were joined by commas reads as it did.
    empty = [b'{"frame": 0, "status": "empty"}']
    older = _mcap_with_metrics(tmp_path / "o.mcap", empty, {"cameras": "x,y,z"})
    assert pipeline.load_recording(older).camera_names == ("x", "y", "z")


def test_a_file_without_its_metadata_names_the_cameras_of_its_metrics(tmp_path: Path) -> None:
    # Another tool's filter that drops metadata records: the per-camera IoUs still name them.
    messages = [
        b'{"frame": 0, "status": "empty"}',
        b'{"frame": 1, "status": "ok", "iou": {"b": 0.9, "a": 0.8}}',
    ]
    rec = pipeline.load_recording(_mcap_with_metrics(tmp_path / "bare.mcap", messages))
    assert rec.camera_names == ("b", "a")


def test_a_folder_or_an_unexpanded_tilde_is_named_with_what_to_give(
    written: tuple[Path, list[FrameResult]], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    folder = written[0].parent
    with pytest.raises(
        PipelineError,
        match=r"cannot read: is not a regular file; give the recording's \.mcap file in it \(s\.mcap\)",
    ):
        pipeline.load_recording(folder)
    monkeypatch.setenv("HOME", str(tmp_path))
    with pytest.raises(PipelineError, match=rf"~ is not expanded here: give {tmp_path}/run\.mcap"):
        pipeline.load_recording("~/run.mcap")


def test_a_centerline_length_in_the_metadata_that_is_not_a_number_is_ignored(tmp_path: Path) -> None:
    path = _mcap_with_metrics(
        tmp_path / "odd.mcap", [b'{"frame": 0, "status": "empty"}'], {"centerline_points": "many"}
    )
    rec = pipeline.load_recording(path)
    assert rec.centerlines_m.shape == (1, 0, 3) and list(rec.statuses) == ["empty"]


def test_a_message_that_is_not_its_protobuf_is_read_as_damage(
    written: tuple[Path, list[FrameResult]], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path, _ = written

    def tenth_points_broken(topic: str, log_time_ns: int, data: bytes) -> bytes:
        if topic == "/reconstruction/points" and log_time_ns == T0_NS + 10 * DT_NS:
            return b"\xff\xff\xff\xff\x0f not a PointCloud"
        return data

    damaged = rewrite_mcap(path, tmp_path / "damaged.mcap", data=tenth_points_broken)
    rec = pipeline.load_recording(damaged)
    assert not rec.complete and 0 < len(rec) <= 10
    assert rec.damaged and "damaged.mcap: damaged after frame" in caplog.text


@pytest.mark.timeout(20)
def test_a_named_pipe_is_refused_not_waited_on(tmp_path: Path) -> None:
    pipe = tmp_path / "run.mcap"
    os.mkfifo(pipe)  # a read would block until something wrote to it
    with pytest.raises(PipelineError, match=r"run\.mcap: cannot read: is not a regular file"):
        pipeline.load_recording(pipe)
