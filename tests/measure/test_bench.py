"""make bench's plumbing: the stage timer, the report's targets, table, JSON and chart.

Never a timing assertion: the numbers here are made up, and what is checked is
how they are summarised and shown.
"""

from __future__ import annotations

import json
import math
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest
from conftest import build_session, rig_cameras

from pipeline.carve.hull import carve
from pipeline.errors import PipelineError
from pipeline.measure.bench.chart import plot_report
from pipeline.measure.bench.e2e import ensure_session, median_run, voxel_session
from pipeline.measure.bench.per_shape import BenchShape, measure_shape, shape_run
from pipeline.measure.bench.report import (
    RECONSTRUCT,
    RECONSTRUCT_CPU,
    BenchReport,
    EndToEndRun,
    LiveRun,
    ScalingRow,
    ShapeRun,
    speedup_2_over_1,
    targets,
    write_json,
)
from pipeline.measure.bench.run import build_parser
from pipeline.measure.bench.stages import (
    StageRun,
    compare_methods,
    lookup_gather,
    scaled_camera,
    time_stages,
    upsample_masks,
)
from pipeline.measure.bench.table import format_table
from pipeline.measure.bench.timing import StageStats, StageTimer
from pipeline.session.folder import load_session


def test_stage_stats_are_median_and_95th_percentile_in_ms() -> None:
    stats = StageStats.from_seconds([i / 1000 for i in range(1, 101)])  # 1..100 ms
    assert stats.count == 100
    assert stats.median_ms == pytest.approx(50.5)
    # numpy's linear interpolation: 1 + 0.95 * 99 = 95.05 ms, 1 + 0.99 * 99 = 99.01 ms
    assert stats.p95_ms == pytest.approx(95.05)
    assert stats.p99_ms == pytest.approx(99.01)
    assert math.isnan(StageStats.from_seconds([]).median_ms)


def test_stage_timer_collects_one_sample_per_block_and_frame_timings() -> None:
    timer = StageTimer()
    for _ in range(3):
        with timer.time("decode"):
            time.sleep(0.001)
    for stage, seconds in {"carving": 0.002, "centreline": 0.004}.items():
        timer.add(stage, seconds)
    stats = timer.stats()
    assert list(stats) == ["decode", "carving", "centreline"]
    assert stats["decode"].count == 3
    # sleep() never returns early, so every sample is at least its 1 ms.
    assert min(timer.samples_s["decode"]) >= 0.001
    assert stats["centreline"].median_ms == pytest.approx(4.0)


def test_stage_timer_records_a_sample_when_the_block_raises() -> None:
    timer = StageTimer()
    with pytest.raises(RuntimeError), timer.time("carving"):
        raise RuntimeError("boom")
    assert timer.stats()["carving"].count == 1


def _fake_report() -> BenchReport:
    ms = StageStats
    return BenchReport(
        meta={"session": "demo", "frames": 900, "cpus": 2, "load_before": 0.1, "load_after": 1.2},
        stages={"decode": ms(0.6, 0.9, 300), "carving": ms(0.8, 1.4, 300), "centreline": ms(2.0, 3.0, 300)},
        original={"carving": ms(8000.0, 9000.0, 10), "centreline": ms(50.0, 60.0, 10)},
        carving_methods={"ours": ms(0.8, 1.4, 10), "brute force": ms(160.0, 170.0, 10)},
        identical_frames=10,
        compared_frames=10,
        end_to_end=[
            EndToEndRun("2 mm, 1 worker", 1, 2.0, 900, 10.0, 0, 700.0),
            EndToEndRun("2 mm, 2 workers", 2, 2.0, 900, 7.0, 0, 1200.0, walls_s=(6.5, 7.0, 7.5)),
        ],
        decode_floor_s=2.0,
        decode_frames=900,
        scaling=[ScalingRow("1 mm, 320x240", (256, 256, 256), (320, 240), 3.5, ms(4.0, 6.0, 10))],
    )


def test_run_targets_pass_and_miss() -> None:
    report = _fake_report()
    verdicts = {t.name.split(" (")[0]: t.verdict for t in targets(report)}
    assert verdicts["carve median at 128^3"] == "PASS"  # 0.8 <= 1 ms
    assert verdicts["carve identical to brute force"] == "PASS"
    assert verdicts["end to end 900 frames, 2 workers"] == "PASS"  # 7 <= 10 s
    assert verdicts["end to end / decode only"] == "PASS"  # 3.5 <= 5
    assert verdicts["end to end 900 frames at 1 mm"] == "not measured"
    assert verdicts["peak memory"] == "PASS"  # 1200 MiB <= 1.5 GiB
    assert verdicts["2 workers / 1 worker"] == "MISS"  # 10 s / 7 s = 1.43 < 1.6
    assert speedup_2_over_1(report) == pytest.approx(10.0 / 7.0)


def test_table_json_and_chart_show_the_fake_measurement(tmp_path: Path) -> None:
    report = _fake_report()
    table = format_table(report)
    assert "| carving | 0.800 | 1.400 | 8000.0 | 10000 |" in table  # original / ours = 8000 / 0.8
    assert "| centreline | 2.000 | 3.000 | 50.0 | 25 |" in table
    # The median run's figures (900 / 7 s = 128.6 fps), beside every run's wall time.
    assert "| 2 mm, 2 workers | 900 | 7.00 | 6.50, 7.00, 7.50 | 129 | 4.3 | n/a | 1200 |" in table
    assert "carving identical to brute force on 10/10 frames" in table

    write_json(report, tmp_path / "bench.json")
    data = json.loads((tmp_path / "bench.json").read_text())
    assert data["ratios"]["workers_2_over_1"] == pytest.approx(10.0 / 7.0)
    assert data["ratios"]["original_over_ours"]["carving"] == pytest.approx(10000.0)
    assert data["end_to_end"][1]["fps"] == pytest.approx(900 / 7.0)
    assert {t["verdict"] for t in data["targets"]} == {"PASS", "MISS", "not measured"}

    plot_report(report, tmp_path / "bench.png")
    assert (tmp_path / "bench.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _shape(name: str, *, frames: int, wall_s: float, p99_ms: float) -> ShapeRun:
    run = EndToEndRun(f"{name}, 2 workers", 2, 2.0, frames, wall_s, 0, 800.0, walls_s=(wall_s,))
    return ShapeRun(
        name=name,
        session=f"recordings/bench-{name}",
        description=f"pipeline synth bench-{name} --shape {name}",
        end_to_end=run,
        decode_floor_s=2.0,
        decode_frames=frames,
        reconstruct=StageStats(12.0, 20.0, 300, p99_ms),
        reconstruct_cpu=StageStats(11.0, 18.0, 300, p99_ms - 2.0),
        statuses={"ok": 300, "empty": 0, "failed": 0},
        initialised_frames=4,
    )


def test_shape_targets_pass_and_miss() -> None:
    report = _fake_report()
    report.shapes = [
        _shape("loop", frames=900, wall_s=50.0, p99_ms=40.0),  # 25x, 40 ms
        _shape("helix", frames=900, wall_s=30.0, p99_ms=25.0),  # 15x, 25 ms
        _shape("quick", frames=120, wall_s=3.0, p99_ms=25.0),  # 1.5x, but not 900 frames
    ]
    verdicts = {t.name: t.verdict for t in targets(report)}
    assert verdicts["end to end / decode only, loop (900 frames, 2 workers)"] == "MISS"  # 25 > 20
    assert verdicts["p99 silhouettes to quality, loop (300 frames, 1 core)"] == "MISS"  # 40 > 33 ms
    assert verdicts["end to end / decode only, helix (900 frames, 2 workers)"] == "PASS"  # 15 <= 20
    assert verdicts["p99 silhouettes to quality, helix (300 frames, 1 core)"] == "PASS"  # 25 <= 33 ms
    # A short run spreads the start-up over fewer frames: its ratio says nothing of the target.
    assert verdicts["end to end / decode only, quick (900 frames, 2 workers)"] == "not measured"
    assert report.shapes[0].decode_ratio == pytest.approx(25.0)


def test_shape_rows_in_the_table_and_json(tmp_path: Path) -> None:
    report = _fake_report()
    report.shapes = [_shape("loop", frames=900, wall_s=50.0, p99_ms=40.0)]
    table = format_table(report)
    # frames, wall, runs, decode only, ratio, frames timed (from the hull), median, p95, p99, p99 CPU
    assert "| loop | 900 | 50.00 | 50.00 | 2.00 | 25.0 | 300 (4) | 12.00 | 20.00 | 40.00 | 38.00 |" in table
    assert "- loop: pipeline synth bench-loop --shape loop" in table
    assert "| p99 silhouettes to quality, loop (300 frames, 1 core) | 40.00 ms | <= 33 ms | MISS |" in table

    write_json(report, tmp_path / "bench.json")
    data = json.loads((tmp_path / "bench.json").read_text())
    (row,) = data["shapes"]
    assert row["decode_ratio"] == pytest.approx(25.0)
    assert row["reconstruct"]["p99_ms"] == pytest.approx(40.0)
    assert row["reconstruct_cpu"]["p99_ms"] == pytest.approx(38.0)
    assert row["end_to_end"]["walls_s"] == [50.0]
    assert data["ratios"]["end_to_end_over_decode_by_shape"] == {"loop": pytest.approx(25.0)}
    verdicts = {t["name"]: t["verdict"] for t in data["targets"]}
    assert verdicts["end to end / decode only, loop (900 frames, 2 workers)"] == "MISS"


def test_a_report_without_shapes_has_no_shape_table() -> None:
    assert "| shape | frames" not in format_table(_fake_report())


def test_median_run_keeps_every_wall_time_and_the_largest_peak() -> None:
    runs = [
        EndToEndRun("a", 2, 2.0, 900, wall, 0, peak)
        for wall, peak in ((9.0, 500.0), (7.0, 900.0), (8.0, 600.0))
    ]
    median = median_run(runs)
    assert median.wall_s == 8.0
    assert median.walls_s == (9.0, 7.0, 8.0)  # in the order run
    assert median.peak_rss_mb == 900.0
    with pytest.raises(ValueError, match="at least one run"):
        median_run([])


def test_ensure_session_renders_beside_and_renames_into_place(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    commands: list[list[str]] = []

    def fake_synth(cmd: list[str], check: bool) -> None:
        # `pipeline synth` writes calibration.toml first, so a stopped render looks
        # finished; here it completes.
        commands.append(cmd)
        out = Path(cmd[cmd.index("synth") + 1])
        out.mkdir()
        (out / "calibration.toml").write_text("# calibration\n")

    monkeypatch.setattr("pipeline.measure.bench.e2e.subprocess.run", fake_synth)
    (tmp_path / "bench-loop.partial").mkdir()  # left by a stopped render
    (tmp_path / "bench-loop.partial" / "cam0.mp4").write_bytes(b"half")
    session = ensure_session(tmp_path / "bench-loop", frames=900, synth_args=("--shape", "loop"))
    assert session == tmp_path / "bench-loop"
    assert (session / "calibration.toml").exists() and not (session / "cam0.mp4").exists()
    assert not (tmp_path / "bench-loop.partial").exists()
    (cmd,) = commands
    assert cmd[-5:] == [str(tmp_path / "bench-loop.partial"), "--frames", "900", "--shape", "loop"]
    ensure_session(session, frames=900, synth_args=("--shape", "loop"))
    assert len(commands) == 1  # reused, not rendered again


def test_ensure_session_will_not_render_over_a_folder_that_is_not_a_session(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("mine\n")
    with pytest.raises(PipelineError, match=r"not a session \(no calibration.toml\) and not empty"):
        ensure_session(tmp_path, frames=900)
    assert (tmp_path / "notes.txt").exists()


def test_voxel_session_links_the_inputs_and_overrides_voxel_mm(tmp_path: Path) -> None:
    source = tmp_path / "demo"
    source.mkdir()
    (source / "calibration.toml").write_text("# calibration\n")
    (source / "cam0.mp4").write_bytes(b"video")
    (source / "session.toml").write_text("[workspace]\nvoxel_mm = 2.0\n[silhouette]\nthreshold = 70\n")
    target = voxel_session(source, tmp_path / "fine", voxel_mm=1.0)
    assert (target / "cam0.mp4").is_symlink() and (target / "cam0.mp4").read_bytes() == b"video"
    settings = tomllib.loads((target / "session.toml").read_text())
    assert settings == {"workspace": {"voxel_mm": 1.0}, "silhouette": {"threshold": 70}}


def test_scaled_camera_maps_pixels_as_nearest_upsampling_does() -> None:
    cam = rig_cameras()[0]
    big = scaled_camera(cam, 2)
    points = np.random.default_rng(0).uniform(64, 192, (50, 3))
    # Pixel centres at integers: source pixel u covers [u - 0.5, u + 0.5), its two copies
    # cover [2u - 0.5, 2u + 1.5), centred at 2u + 0.5. Exact up to float rounding.
    np.testing.assert_allclose(big.project(points), 2 * cam.project(points) + 0.5, atol=1e-9)
    assert big.size_px == (2 * cam.width, 2 * cam.height)
    mask = np.zeros((cam.height, cam.width), bool)
    mask[10, 20] = True
    (up,) = upsample_masks([mask], 2)
    assert up.shape == (2 * cam.height, 2 * cam.width)
    assert np.array_equal(np.argwhere(up), [[20, 40], [20, 41], [21, 40], [21, 41]])


@pytest.fixture(scope="module")
def rod_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # 8 mm voxels (32^3): brute force and the original method take milliseconds, not seconds.
    return build_session(
        tmp_path_factory.mktemp("bench") / "rod",
        frames=4,
        empty_frames={3},
        settings={"workspace": {"voxel_mm": 8.0}},
    )


@pytest.fixture(scope="module")
def rod_run(rod_dir: Path) -> StageRun:
    return time_stages(load_session(rod_dir), rod_dir.parent / "out", frames=4)


def test_time_stages_times_every_stage_of_every_frame(rod_run: StageRun) -> None:
    stats = rod_run.timer.stats()
    for stage in ("decode", "silhouettes", "encode", "mcap", "rerun", "all stages"):
        assert stats[stage].count == 4, stage
    assert stats["carving"].count == 3  # an empty view ends the frame before carving
    assert sorted(rod_run.masks) == [0, 1, 2, 3]
    assert rod_run.results[3].status == "empty"  # the rod is out of view in frame 3


def test_time_stages_sums_silhouettes_to_quality_per_frame(rod_run: StageRun) -> None:
    stats = rod_run.timer.stats()
    # Every frame, the empty one too: its silhouettes were made and looked at.
    assert stats[RECONSTRUCT].count == stats[RECONSTRUCT_CPU].count == 4
    keys = ("silhouette", "carve", "centerline", "quality")
    expected = [sum(rod_run.results[i].timings_s.get(k, 0.0) for k in keys) for i in range(4)]
    assert rod_run.timer.samples_s[RECONSTRUCT] == expected
    assert all(s >= 0.0 for s in rod_run.timer.samples_s[RECONSTRUCT_CPU])
    assert rod_run.status_counts() == {"ok": 3, "empty": 1, "failed": 0}


def test_shape_run_summarises_a_stage_run(rod_run: StageRun, rod_dir: Path) -> None:
    shape = BenchShape("rod", "rod", ("--shape", "straight"))
    row = shape_run(shape, rod_dir, end_to_end=None, decode_floor_s=0.5, decode_frames=4, stages=rod_run)
    assert row.description == f"pipeline synth {rod_dir} --shape straight"
    assert row.reconstruct == rod_run.timer.stats()[RECONSTRUCT]
    assert row.statuses == {"ok": 3, "empty": 1, "failed": 0}
    # Frame 0 starts the track from the hull; later ok frames follow it or start again.
    assert 1 <= row.initialised_frames <= 3
    assert math.isnan(row.decode_ratio)  # no end-to-end run


def test_measure_shape_reuses_the_session_and_runs_process_with_2_workers(
    rod_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # `process` in a subprocess costs seconds of imports: a stand-in records the calls.
    calls: list[dict[str, object]] = []

    def fake_run_process(session_dir: Path, out_dir: Path, **kwargs: object) -> EndToEndRun:
        calls.append({"session_dir": session_dir, **kwargs})
        wall_s = (3.0, 1.0, 2.0)[len(calls) - 1]
        return EndToEndRun(str(kwargs["label"]), 2, 8.0, 4, wall_s, 0, 100.0)

    monkeypatch.setattr("pipeline.measure.bench.per_shape.run_process", fake_run_process)
    # The session exists, so nothing is rendered (its synth arguments would fail if run).
    shape = BenchShape("rod", rod_dir.name, ("--no-such-option",))
    row = measure_shape(
        shape, rod_dir.parent, tmp_path, frames=10, session_frames=4, stage_frames=4, repeats=3
    )
    assert [c["jobs"] for c in calls] == [2, 2, 2]
    assert {c["session_dir"] for c in calls} == {rod_dir}
    assert {c["frames"] for c in calls} == {4}  # no more than the session has
    assert row.end_to_end is not None and row.end_to_end.walls_s == (3.0, 1.0, 2.0)
    assert row.end_to_end.wall_s == 2.0  # the median run
    assert row.decode_frames == 4 and math.isfinite(row.decode_floor_s)
    assert row.reconstruct.count == 4


def test_lookup_gather_and_brute_force_agree_with_carve(rod_run: StageRun) -> None:
    comparison = compare_methods(
        rod_run.model, rod_run.masks, all_frames=[0, 1], original_frames=[0], brute_force=True
    )
    assert comparison.identical_frames == comparison.compared_frames == 1
    assert comparison.lookup_identical_frames == comparison.lookup_compared_frames == 2
    ids = lookup_gather(rod_run.model.grid, rod_run.masks[0])
    assert len(ids) > 0 and np.array_equal(ids, carve(rod_run.model.grid, rod_run.masks[0]))
    assert set(comparison.original) == {"carving", "centreline"}


def test_a_short_run_does_not_claim_the_900_frame_targets() -> None:
    report = _fake_report()
    report.end_to_end = [EndToEndRun("2 mm, 2 workers", 2, 2.0, 120, 3.0, 0, 600.0)]
    verdicts = {t.name: t.verdict for t in targets(report)}
    assert verdicts["end to end 900 frames, 2 workers"] == "not measured"


def test_the_command_line_takes_the_per_shape_options() -> None:
    args = build_parser().parse_args(["--no-shapes", "--shape-repeats", "3"])
    assert args.no_shapes and args.shape_repeats == 3
    defaults = build_parser().parse_args([])
    assert not defaults.no_shapes and defaults.shape_repeats == 1


def test_live_rows_and_targets(tmp_path: Path) -> None:
    report = _fake_report()
    report.live = [
        LiveRun("demo", 900, 900, 0, 0, 14.0, 31.5, (30.0, 30.0, 29.9), 31.0, 420.0, 0.4, 0.012, 0),
        LiveRun("loop", 900, 850, 50, 3, 35.0, 80.0, (30.0, 30.0, 30.0), 31.0, 430.0, 1.5, 0.3, 0),
    ]
    table = format_table(report)
    # frame-sets, written, dropped, unmatched, p50, p99, camera rates, vs process, peak RSS, growth
    assert "| demo | 900 | 900 | 0 | 0 | 14.0 | 31.5 | 30.0, 30.0, 29.9 | 0.012 | 420 | 0.4 |" in table
    verdicts = {t.name: t.verdict for t in targets(report)}
    assert verdicts["live demo: frame-sets dropped"] == "PASS"
    assert verdicts["live demo: latency p50"] == "PASS"  # 14 <= 20 ms
    assert verdicts["live demo: latency p99"] == "PASS"  # 31.5 <= 50 ms
    assert verdicts["live demo: centrelines vs process (mean)"] == "PASS"  # 0.012 <= 0.05 mm
    assert verdicts["live loop: frame-sets dropped"] == "MISS"
    assert verdicts["live loop: latency p50"] == "MISS"
    assert verdicts["live loop: latency p99"] == "MISS"
    assert verdicts["live loop: centrelines vs process (mean)"] == "MISS"
    write_json(report, tmp_path / "bench.json")
    data = json.loads((tmp_path / "bench.json").read_text())
    assert data["live"][1]["dropped"] == 50 and data["live"][0]["latency_p99_ms"] == 31.5
    assert "live (`live --replay`" not in format_table(_fake_report())  # no live runs: no table


@pytest.mark.parametrize(
    ("tool", "args", "line"),
    [
        ("bench", ["--frames", "0"], "argument --frames: must be 1 or more, got 0"),
        ("bench", ["--shape-repeats", "-1"], "argument --shape-repeats: must be 1 or more, got -1"),
        ("bench", ["--original-frames", "x"], "argument --original-frames: expected an integer, got 'x'"),
        ("bench", ["--bogus"], "unrecognized arguments: --bogus"),
        ("accuracy", ["--draw", "-1"], "argument --draw: must be 0 or more, got -1"),
        ("accuracy", ["--draw", "3", "--cases", "0"], "--cases takes one number of cases (1 or more), got 0"),
    ],
)
def test_the_measuring_tools_say_a_usage_mistake_in_one_line(
    tool: str, args: list[str], line: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from pipeline.measure import accuracy_table
    from pipeline.measure.bench import run

    main = run.main if tool == "bench" else accuracy_table.main
    with pytest.raises(SystemExit) as exit_info:
        main(args)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and line in err and err.rstrip().endswith("--help)")


def test_the_measuring_tools_refuse_a_session_folder_as_out_and_a_file_as_demo(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from pipeline.measure import accuracy_table
    from pipeline.measure.bench import run

    session = tmp_path / "s"
    session.mkdir()
    (session / "calibration.toml").write_text("")
    (session / "cam0.mp4").write_bytes(b"")
    for main, args in (
        (accuracy_table.main, ["--draw", "3", "--cases", "1", "--out", str(session)]),
        (run.main, ["--out", str(session)]),
    ):
        with pytest.raises(SystemExit) as exit_info:
            main(args)
        assert exit_info.value.code == 2
        assert f"{session}: is a session's folder; give --out a folder of its own" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        run.main(["--demo", str(session / "cam0.mp4"), "--out", str(tmp_path / "b")])
    assert (
        capsys.readouterr().err == f"error: {session / 'cam0.mp4'}: is a file; give --demo a session folder\n"
    )
    assert sorted(p.name for p in session.iterdir()) == ["calibration.toml", "cam0.mp4"]


def test_the_measuring_tools_end_on_sigterm_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    import os
    import signal

    from pipeline.measure.arguments import EXIT_INTERRUPTED, stopped_in_one_line

    handler = signal.getsignal(signal.SIGTERM)
    with pytest.raises(SystemExit) as exit_info, stopped_in_one_line("bench"):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the signal ends the block first
    assert exit_info.value.code == EXIT_INTERRUPTED
    assert capsys.readouterr().err == "error: bench: interrupted; its output is not written\n"
    assert signal.getsignal(signal.SIGTERM) is handler  # the policy ends with the block
