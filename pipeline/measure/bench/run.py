"""``make bench``: speed, side by side with the original algorithm.

``python -m pipeline.measure.bench [--frames 900] [--quick]`` makes (or reuses) the demo
session, then measures on this machine:

- per-frame stages of ``process`` (median and 95th percentile, in process);
- carving at 128^3 by method: ours, a plain lookup gather, brute force, the original
  big-cube heuristic, with ours checked voxel for voxel against brute force;
- the original's sphere-fit/polyfit centreline against ours;
- carving set-up and per-frame cost at 1 mm voxels and 640x480 masks;
- ``python -m pipeline process`` end to end (subprocess, start to files closed) with
  1 and 2 workers, and at 1 mm; decode-only as the floor; peak memory of each run;
- per shape (the demo, a loop, a random shape with a round end, each rendered
  once beside the demo and reused): ``process`` with 2 workers over its decode floor,
  and the 99th percentile of the per-frame silhouettes-to-quality time on one core;
- live: the demo and the loop replayed through ``python -m pipeline live`` at
  30 fps: latency p50/p99, frame-sets dropped, camera rates, memory, and the centrelines
  against what ``process`` recorded of the same frames.

It writes recordings/bench.json and recordings/bench.png and prints a Markdown
table with PASS/MISS per target. Misses never fail the command: speed is reported,
not asserted.
"""

from __future__ import annotations

import argparse
import logging
import os
import platform
import sys
import tempfile
import time
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from ...errors import PipelineError
from ...session.folder import load_session
from ..arguments import OneLineParser, at_least, not_a_session, stopped_in_one_line
from .chart import plot_report
from .e2e import decode_floor, ensure_session, median_run, run_process, voxel_session
from .live import run_live
from .per_shape import DEMO_SHAPE, FLOOR_REPEATS, SHAPES, BenchShape, measure_shapes, shape_run
from .report import STAGE_ORDER, BenchReport, EndToEndRun, LiveRun, write_json
from .table import format_table
from .timing import StageStats

log = logging.getLogger("pipeline.measure.bench")

DEMO_DIR = Path("recordings/demo")
DEMO_FRAMES = 900  # the demo `make process` uses; rendered once, reused


def _evenly(items: Sequence[int], count: int) -> list[int]:
    """Up to ``count`` items spread evenly over ``items`` (all of them if there are fewer)."""
    if len(items) <= count:
        return list(items)
    picks = np.linspace(0, len(items) - 1, count).round().astype(int)
    return [items[i] for i in picks]


def _original_per_frame(report: BenchReport) -> StageStats:
    """The original's whole frame, estimated: our stage medians with carving and centreline
    swapped for the original's (decode, silhouettes and writing are taken as ours)."""
    ours, orig = report.stages, report.original
    swapped = ("carving", "centreline")
    total = ours["all stages"].median_ms - sum(ours[s].median_ms for s in swapped)
    total += sum(orig[s].median_ms for s in swapped)
    count = min(orig[s].count for s in swapped)
    return StageStats(total, float("nan"), count)


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def run_bench(
    demo_dir: Path,
    *,
    frames: int = DEMO_FRAMES,
    stage_frames: int = 300,
    original_frames: int = 10,
    scaling_frames: int = 20,
    fine_end_to_end: bool = True,
    repeats: int = 5,
    shapes: Sequence[BenchShape] = SHAPES,
    shape_stage_frames: int = 300,
    shape_repeats: int = 1,
    live: bool = True,
    work_dir: Path | None = None,
) -> BenchReport:
    """Measure everything ``make bench`` reports on the session in ``demo_dir``.

    Parameters
    ----------
    demo_dir : a session directory (rendered first if it has no calibration.toml).
    frames : frames processed end to end and decoded for the floor.
    stage_frames : frames timed stage by stage in this process.
    original_frames : frames run through the original method and brute force (seconds each).
    scaling_frames : frames carved at each resolution.
    fine_end_to_end : also time ``process`` end to end at 1 mm voxels.
    repeats : runs of each end-to-end configuration; the median is reported (the
        peak memory is the largest of them).
    shapes : sessions beyond the demo for the per-shape rows, rendered (once)
        beside ``demo_dir``; the demo's row reuses the demo's own measurements.
    shape_stage_frames : frames of each further shape timed one by one.
    shape_repeats : end-to-end runs of each further shape (a 900-frame loop takes minutes).
    live : replay the demo (and the loop, among ``shapes``) through ``pipeline live``
        ``frames`` of each at 30 fps.
    work_dir : scratch directory for outputs (a temporary one by default).
    """
    from .stages import carving_scaling, compare_methods, time_stages

    report = BenchReport()
    report.meta = {
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "load_before": _load(),
    }
    ensure_session(demo_dir, frames=DEMO_FRAMES)
    session = load_session(demo_dir)
    n = min(frames, session.frame_count)
    report.meta.update(session=str(demo_dir), frames=n, fps=session.fps)
    with tempfile.TemporaryDirectory(prefix="pipeline-bench-", dir=work_dir) as tmp_name:
        tmp = Path(tmp_name)
        log.info("decoding %d frames of %d videos (the floor)", n, len(session.video_paths))
        report.decode_floor_s = decode_floor(session.video_paths, frames=n, repeats=FLOOR_REPEATS)
        report.decode_frames = n

        voxel = f"{session.settings.workspace.voxel_mm:g} mm"
        configs = [(demo_dir, jobs, 2.0, f"{voxel}, {jobs} worker{'s' * (jobs > 1)}") for jobs in (1, 2)]
        if fine_end_to_end:
            fine = voxel_session(demo_dir, tmp / "demo_1mm", voxel_mm=1.0)
            configs.append((fine, 2, 1.0, "1 mm, 2 workers"))
        # Round after round of every configuration, not all runs of one then the next:
        # a shared machine's speed drifts by ~10 % over minutes, and the 2/1-worker
        # ratio compares runs that should see the same machine.
        runs: list[list[EndToEndRun]] = [[] for _ in configs]
        for _ in range(repeats):
            for (directory, jobs, voxel_mm, label), done in zip(configs, runs, strict=True):
                done.append(
                    run_process(directory, tmp / "out", jobs=jobs, frames=n, voxel_mm=voxel_mm, label=label)
                )
        report.end_to_end = [median_run(done) for done in runs]

        log.info("timing the per-frame stages on %d frames", min(stage_frames, n))
        stages = time_stages(session, tmp / "stages", frames=min(stage_frames, n))
        report.shapes = [
            shape_run(
                DEMO_SHAPE,
                demo_dir,
                end_to_end=report.run(jobs=2, voxel_mm=2.0),
                decode_floor_s=report.decode_floor_s,
                decode_frames=n,
                stages=stages,
            )
        ]
        report.shapes += measure_shapes(
            shapes,
            demo_dir.parent,
            tmp / "shapes",
            frames=n,
            session_frames=DEMO_FRAMES,
            stage_frames=shape_stage_frames,
            repeats=shape_repeats,
        )
        if live:
            report.live = _live_runs(demo_dir, shapes, tmp, frames=n, fps=session.fps)
    stats = stages.timer.stats()
    order = [s for s in STAGE_ORDER if s in stats] + [s for s in stats if s not in STAGE_ORDER]
    report.stages = {name: stats[name] for name in order}
    report.meta["stage_frames"] = stages.status_counts()
    report.one_off_s = {"build_grid at 128^3": stages.setup_s, "close the recordings": stages.close_s}

    # Frames with something in every view: the others carve nothing and time nothing.
    seen = [i for i in sorted(stages.masks) if all(m.any() for m in stages.masks[i])]
    subset = _evenly(seen, original_frames)
    log.info("original method and brute force on %d frames (seconds each)", len(subset))
    comparison = compare_methods(stages.model, stages.masks, all_frames=seen, original_frames=subset)
    report.carving_methods = comparison.methods
    report.original = dict(comparison.original)
    report.original["all stages"] = _original_per_frame(report)
    report.identical_frames = comparison.identical_frames
    report.compared_frames = comparison.compared_frames
    report.lookup_identical_frames = comparison.lookup_identical_frames
    report.lookup_compared_frames = comparison.lookup_compared_frames
    same = f"{comparison.identical_frames}/{comparison.compared_frames}"
    print(f"carving identical to brute force: {same} frames", flush=True)

    log.info("carving at 1 mm and 640x480")
    report.scaling = carving_scaling(
        session.cameras, session.settings.workspace, stages.masks, _evenly(seen, scaling_frames)
    )
    report.meta["load_after"] = _load()
    return report


def _live_runs(
    demo_dir: Path, shapes: Sequence[BenchShape], tmp: Path, *, frames: int, fps: float
) -> list[LiveRun]:
    """The demo, and those of ``shapes`` marked live, replayed live for ``frames`` frames
    and compared with what ``process`` recorded of them above."""
    sessions = [(DEMO_SHAPE.name, demo_dir, tmp / "out" / f"{demo_dir.resolve().name}.mcap")]
    for shape in shapes:
        if shape.live:
            out = tmp / "shapes" / shape.directory / "out" / f"{shape.directory}.mcap"
            sessions.append((shape.name, demo_dir.parent / shape.directory, out))
    runs = []
    for label, directory, process_mcap in sessions:
        count = load_session(directory).frame_count
        # The whole replay, or the frames the other rows processed (--quick, --frames).
        duration_s = None if frames >= count else frames / fps
        runs.append(
            run_live(directory, tmp / "live", label=label, duration_s=duration_s, process_mcap=process_mcap)
        )
    return runs


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="python -m pipeline.measure.bench",
        description="Speed of the pipeline, side by side with the original algorithm.",
    )
    parser.add_argument("--frames", type=at_least(1), default=DEMO_FRAMES, help="frames processed end to end")
    parser.add_argument(
        "--quick",
        action="store_true",
        help="smoke run: 120 frames, 3 original frames, no 1 mm end to end, 60 frames timed per shape",
    )
    parser.add_argument(
        "--shape-repeats",
        type=at_least(1),
        default=1,
        help="end-to-end runs of each shape beyond the demo, the median reported (default 1)",
    )
    parser.add_argument("--no-shapes", action="store_true", help="only the demo's row of the per-shape table")
    parser.add_argument("--no-live", action="store_true", help="leave out the live replays (pipeline live)")
    parser.add_argument(
        "--original-frames",
        type=at_least(1),
        default=None,
        help="frames run through the original method and brute force (default 10, 3 with --quick)",
    )
    parser.add_argument(
        "--demo", type=Path, default=DEMO_DIR, help="session directory (default recordings/demo)"
    )
    parser.add_argument(
        "--out", type=Path, default=Path("recordings"), help="where bench.json and bench.png go"
    )
    return parser


def _run(args: argparse.Namespace) -> BenchReport:
    """run_bench with the command line's options (--quick: the smoke run's sizes)."""
    shapes = () if args.no_shapes else SHAPES
    if args.quick:
        return run_bench(
            args.demo,
            frames=min(args.frames, 120),
            stage_frames=60,
            original_frames=args.original_frames or 3,
            scaling_frames=5,
            fine_end_to_end=False,
            repeats=1,
            shapes=shapes,
            shape_stage_frames=60,
            shape_repeats=args.shape_repeats,
            live=not args.no_live,
        )
    return run_bench(
        args.demo,
        frames=args.frames,
        original_frames=args.original_frames or 10,
        shapes=shapes,
        shape_repeats=args.shape_repeats,
        live=not args.no_live,
    )


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    for why in (
        not_a_session(args.out, "bench.json and bench.png"),
        f"{args.demo}: is a file; give --demo a session folder" if args.demo.is_file() else "",
    ):
        if why:
            parser.exit(2, f"error: {why}\n")
    logging.basicConfig(level=logging.INFO, format="%(levelname)s: %(message)s")
    start = time.perf_counter()
    try:
        with stopped_in_one_line(parser.prog):
            report = _run(args)
    except PipelineError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(report, args.out / "bench.json")
    plot_report(report, args.out / "bench.png")
    print(format_table(report))
    print(
        f"wrote {args.out / 'bench.json'} and {args.out / 'bench.png'} ({time.perf_counter() - start:.0f} s)"
    )
    return 0
