"""The benchmark as Markdown: stage times, carving, end to end, live, scaling, shapes.

Each table beside its target (:func:`pipeline.measure.bench.report.targets`)."""

from __future__ import annotations

import math

from .report import (
    LIVE_GAP_LIMIT_MM,
    LIVE_P50_LIMIT_MS,
    LIVE_P99_LIMIT_MS,
    ORIGINAL_PUBLISHED_S,
    OURS,
    REALTIME_FPS,
    RECONSTRUCT_P99_LIMIT_MS,
    SHAPE_DECODE_RATIO_LIMIT,
    STAGE_ORDER,
    TARGET_FRAMES,
    BenchReport,
    ratio_of,
    speedup_2_over_1,
    targets,
    wall_s,
)


def _f(value: float, digits: int = 2) -> str:
    return "n/a" if not math.isfinite(value) else f"{value:.{digits}f}"


def _x(ratio: float) -> str:
    """A ratio with about three significant digits: 0.031, 2.45, 18.3, 11118."""
    if not math.isfinite(ratio):
        return "n/a"
    if ratio >= 100:
        return f"{ratio:.0f}"
    return f"{ratio:.3g}"


def _stage_rows(report: BenchReport) -> list[str]:
    names = [s for s in STAGE_ORDER if s in report.stages]
    names += [s for s in report.stages if s not in names]
    rows = [
        "| stage (per frame) | ours median ms | ours p95 ms | original median ms | original / ours |",
        "|---|---:|---:|---:|---:|",
    ]
    for name in names:
        ours = report.stages[name]
        orig = report.original.get(name)
        orig_ms = orig.median_ms if orig else float("nan")
        rows.append(
            f"| {name} | {_f(ours.median_ms, 3)} | {_f(ours.p95_ms, 3)} | {_f(orig_ms, 1)} "
            f"| {_x(ratio_of(orig_ms, ours.median_ms))} |"
        )
    if "all stages" in report.original:
        rows.append("")
        rows.append(
            "Original 'all stages': ours with carving and centreline replaced by the original's "
            f"(measured on {report.original['all stages'].count} frames)."
        )
    return rows


def _carving_rows(report: BenchReport) -> list[str]:
    ours = report.carving_methods.get(OURS)
    rows = [
        "| carving at 128^3, 3 cameras | median ms | p95 ms | frames | / ours |",
        "|---|---:|---:|---:|---:|",
    ]
    for name, s in report.carving_methods.items():
        ratio = ratio_of(s.median_ms, ours.median_ms) if ours else float("nan")
        rows.append(f"| {name} | {_f(s.median_ms, 3)} | {_f(s.p95_ms, 3)} | {s.count} | {_x(ratio)} |")
    return rows


def _end_to_end_rows(report: BenchReport) -> list[str]:
    rows = [
        "| end to end (`process`, files closed) | frames | wall s (median) | runs s | fps "
        "| x real time | CPU s | peak RSS MiB |",
        "|---|---:|---:|---|---:|---:|---:|---:|",
    ]
    for r in report.end_to_end:
        status = "" if r.exit_code == 0 else f" (exit {r.exit_code})"
        runs = ", ".join(_f(w) for w in r.walls_s)
        rows.append(
            f"| {r.label}{status} | {r.frames} | {_f(r.wall_s)} | {runs} | {_f(r.fps, 0)} "
            f"| {_f(r.realtime_factor, 1)} | {_f(r.cpu_s, 1)} | {_f(r.peak_rss_mb, 0)} |"
        )
    floor_fps = ratio_of(report.decode_frames, report.decode_floor_s)
    rows.append(
        f"| decode only (3 videos, 1 process) | {report.decode_frames} | {_f(report.decode_floor_s)} | "
        f"| {_f(floor_fps, 0)} | {_f(floor_fps / REALTIME_FPS, 1)} | | |"
    )
    return rows


def _live_rows(report: BenchReport) -> list[str]:
    rows = [
        "| live (`live --replay`, 30 fps) | frame-sets | written | dropped | unmatched | latency p50 ms "
        "| p99 ms | cameras fps | vs process mm | peak RSS MiB | RSS growth MiB |",
        "|---|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|",
    ]
    for r in report.live:
        status = "" if r.exit_code == 0 else f" (exit {r.exit_code})"
        rates = ", ".join(_f(f, 1) for f in r.camera_fps)
        rows.append(
            f"| {r.label}{status} | {r.frame_sets} | {r.written} | {r.dropped} | {r.unmatched} "
            f"| {_f(r.latency_p50_ms, 1)} | {_f(r.latency_p99_ms, 1)} | {rates} "
            f"| {_f(r.gap_to_process_mm, 3)} | {_f(r.peak_rss_mb, 0)} | {_f(r.rss_growth_mb, 1)} |"
        )
    rows.append("")
    rows.append(
        "Latency: from the capture of a frame's last image to its result written. Targets: no frame-set "
        f"dropped, p50 <= {LIVE_P50_LIMIT_MS:g} ms, p99 <= {LIVE_P99_LIMIT_MS:g} ms, centrelines within "
        f"{LIVE_GAP_LIMIT_MM:g} mm of process's on the same frames (mean)."
    )
    return rows


def _scaling_rows(report: BenchReport) -> list[str]:
    rows = [
        "| carving resolution | grid | masks | set-up s | carve median ms | carve p95 ms |",
        "|---|---|---|---:|---:|---:|",
    ]
    for s in report.scaling:
        grid = "x".join(str(n) for n in s.grid_shape)
        rows.append(
            f"| {s.label} | {grid} | {s.image_px[0]}x{s.image_px[1]} | {_f(s.setup_s)} "
            f"| {_f(s.carve.median_ms, 3)} | {_f(s.carve.p95_ms, 3)} |"
        )
    return rows


def _shape_rows(report: BenchReport) -> list[str]:
    rows = [
        "| shape | frames | end to end s, 2 workers | runs s | decode only s | / decode only "
        "| frames timed (from the hull) | silhouettes to quality median ms | p95 ms | p99 ms | p99 CPU ms |",
        "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for shape in report.shapes:
        run = shape.end_to_end
        status = "" if run is None or run.exit_code == 0 else f" (exit {run.exit_code})"
        runs = ", ".join(_f(w) for w in run.walls_s) if run else ""
        sil, cpu = shape.reconstruct, shape.reconstruct_cpu
        rows.append(
            f"| {shape.name}{status} | {shape.decode_frames} | {_f(wall_s(run))} | {runs} "
            f"| {_f(shape.decode_floor_s)} | {_f(shape.decode_ratio, 1)} "
            f"| {sil.count} ({shape.initialised_frames}) | {_f(sil.median_ms)} | {_f(sil.p95_ms)} "
            f"| {_f(sil.p99_ms)} | {_f(cpu.p99_ms)} |"
        )
    rows.append("")
    rows.append(
        f"Targets: end to end / decode only <= {SHAPE_DECODE_RATIO_LIMIT:g}x at {TARGET_FRAMES} frames; "
        f"p99 silhouettes to quality <= {RECONSTRUCT_P99_LIMIT_MS:g} ms, timed in one process with "
        "OpenCV on one thread (CPU: the thread's CPU time, without the time other processes held the core)."
    )
    rows += [f"- {shape.name}: {shape.description}" for shape in report.shapes]
    return rows


def format_table(report: BenchReport) -> str:
    """The whole report as Markdown tables (docs/speed.md quotes this)."""
    meta = report.meta
    head = (
        f"Benchmark: {meta.get('session', '?')}, {meta.get('frames', '?')} frames, "
        f"{meta.get('cpus', '?')} CPUs, load average before/after "
        f"{meta.get('load_before', '?')} / {meta.get('load_after', '?')}; "
        f"frames timed stage by stage: {meta.get('stage_frames', '?')}"
    )
    two = report.run(jobs=2, voxel_mm=2.0)
    per_frame_ms = ratio_of(wall_s(two) * 1e3, two.frames) if two else float("nan")
    published_ms = ORIGINAL_PUBLISHED_S["frame"] * 1e3
    summary = [
        f"- end to end / decode only (2 workers): {_f(ratio_of(wall_s(two), report.decode_floor_s), 1)}x",
        f"- 2 workers / 1 worker throughput: {_f(speedup_2_over_1(report))}x",
        f"- carving identical to brute force on {report.identical_frames}/{report.compared_frames} frames, "
        f"to the plain lookup on {report.lookup_identical_frames}/{report.lookup_compared_frames}",
        f"- the original work, as published: {ORIGINAL_PUBLISHED_S['point cloud']:g} s per point cloud, "
        f"{ORIGINAL_PUBLISHED_S['frame']:g} s per frame; ours end to end (2 workers): "
        f"{_f(per_frame_ms)} ms per frame, {_x(ratio_of(published_ms, per_frame_ms))}x faster",
    ]
    summary += [f"- once per run: {name} {_f(s)} s" for name, s in report.one_off_s.items()]
    target_rows = ["| target | measured | limit | verdict |", "|---|---:|---:|---|"]
    for t in targets(report):
        sign = ">=" if t.higher_is_better else "<="
        target_rows.append(
            f"| {t.name} | {_f(t.measured)} {t.unit} | {sign} {t.limit:g} {t.unit} | {t.verdict} |"
        )
    blocks = [
        [head],
        _stage_rows(report),
        _carving_rows(report),
        _end_to_end_rows(report),
        *([_live_rows(report)] if report.live else []),
        summary,
        _scaling_rows(report),
        *([_shape_rows(report)] if report.shapes else []),
        target_rows,
    ]
    return "\n\n".join("\n".join(b) for b in blocks) + "\n"
