"""The chart of ``make bench``: recordings/bench.png (matplotlib, Agg backend)."""

from __future__ import annotations

from pathlib import Path

from .report import REALTIME_FPS, STAGE_ORDER, BenchReport


def plot_report(report: BenchReport, path: Path) -> None:
    """Bar charts: per-frame stages ours vs original and carving methods at 128^3 (log
    scale); end-to-end wall times against the decode floor and the 10 s target."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [s for s in STAGE_ORDER if s in report.stages] + [
        s for s in report.stages if s not in STAGE_ORDER
    ]
    fig, (ax1, ax2, ax3) = plt.subplots(1, 3, figsize=(17, 4.5), layout="constrained")
    y = list(range(len(names)))
    ours = [report.stages[n].median_ms for n in names]
    orig = [report.original[n].median_ms if n in report.original else float("nan") for n in names]
    ax1.barh([v - 0.2 for v in y], ours, height=0.4, label="ours", color="tab:blue")
    ax1.barh([v + 0.2 for v in y], orig, height=0.4, label="original", color="tab:red")
    ax1.set_yticks(y, names)
    ax1.invert_yaxis()
    ax1.set_xscale("log")
    ax1.set_xlabel("median time per frame (ms, log scale)")
    ax1.set_title("Per-frame stages")
    ax1.axvline(1000.0 / REALTIME_FPS, color="grey", linestyle="--", label="real time (33 ms)")
    ax1.legend(loc="upper right", fontsize="small")

    methods = list(report.carving_methods)
    ax2.barh(methods, [report.carving_methods[m].median_ms for m in methods], color="tab:green")
    ax2.invert_yaxis()
    ax2.set_xscale("log")
    ax2.set_xlabel("median carve time per frame (ms, log scale)")
    ax2.set_title("Carving at 128^3, 3 cameras")

    labels = [f"{r.label} ({r.frames} frames)" for r in report.end_to_end] + ["decode only"]
    walls = [r.wall_s for r in report.end_to_end] + [report.decode_floor_s]
    ax3.barh(labels, walls, color=["tab:blue"] * len(report.end_to_end) + ["tab:grey"])
    ax3.invert_yaxis()
    ax3.axvline(10.0, color="tab:red", linestyle="--", label="target, 2 workers (10 s)")
    ax3.set_xlabel("wall time, process start to files closed (s)")
    ax3.set_title("End to end")
    ax3.legend(loc="lower right")
    fig.savefig(path, dpi=120)
    plt.close(fig)
