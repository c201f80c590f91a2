"""The live rows of ``make bench``: a session replayed through ``pipeline live``.

Each run is the real command line in a fresh process, replaying a session's videos
at their frame rate as if they were cameras, with no viewer; its JSON summary gives
the latencies, drops and camera rates, and its recording is compared with what
``process`` recorded of the same session.
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil

from ...record.load import Recording, load_recording
from .e2e import RSS_SAMPLE_S, tree_rss
from .report import LiveRun

log = logging.getLogger(__name__)


def mean_gap_mm(live: Recording, offline: Recording) -> float:
    """Mean distance between two recordings' centrelines on the frames both hold (ok in
    both), mm; NaN when they share none."""
    common = np.intersect1d(live.frame_indices, offline.frame_indices)
    a = live.centerlines_m[np.searchsorted(live.frame_indices, common)]
    b = offline.centerlines_m[np.searchsorted(offline.frame_indices, common)]
    gaps = np.linalg.norm(a - b, axis=-1).mean(axis=-1) * 1000.0
    gaps = gaps[np.isfinite(gaps)]
    return float(gaps.mean()) if len(gaps) else float("nan")


def _low_rss(samples: list[tuple[float, int]], start: float, stop: float) -> int:
    """The lowest RSS sampled between ``start`` and ``stop`` (fractions of the run's
    duration): what the run holds, without the frames its writers batch up meanwhile."""
    end = samples[-1][0]
    return min((rss for t, rss in samples if start * end <= t <= stop * end), default=samples[-1][1])


def run_live(
    session_dir: Path,
    out_dir: Path,
    *,
    label: str,
    duration_s: float | None = None,
    process_mcap: Path | None = None,
) -> LiveRun:
    """Replay ``session_dir`` through ``python -m pipeline live`` and measure it."""
    with tempfile.TemporaryDirectory(prefix="pipeline-live-bench-") as tmp:
        summary_path = Path(tmp) / "summary.json"
        cmd = [
            sys.executable,
            "-m",
            "pipeline",
            "live",
            "--replay",
            str(session_dir),
            "--out",
            str(out_dir),
            "--viewer",
            "none",
            "--force",
            "--json",
            str(summary_path),
        ]
        if duration_s is not None:
            cmd += ["--duration", f"{duration_s:g}"]
        log.info("live: %s", " ".join(cmd[1:]))
        start = time.perf_counter()
        popen = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        proc = psutil.Process(popen.pid)
        samples: list[tuple[float, int]] = []
        while popen.poll() is None:
            try:
                # The run and its restart worker (pipeline.live.restarts).
                samples.append((time.perf_counter() - start, tree_rss(proc)))
            except psutil.Error:
                pass
            time.sleep(RSS_SAMPLE_S)
        wall = time.perf_counter() - start
        stderr = popen.stderr.read().decode(errors="replace") if popen.stderr else ""
        if not summary_path.exists():
            log.warning("live on %s exited with %d:\n%s", session_dir, popen.returncode, stderr[-2000:])
            nan = float("nan")
            return LiveRun(label, 0, 0, 0, 0, nan, nan, (), wall, nan, nan, nan, int(popen.returncode))
        summary = json.loads(summary_path.read_text())
    live = summary["live"]
    written = int(summary["frames"]["processed"])
    mcap = out_dir / f"{session_dir.resolve().name}.mcap"
    gap = float("nan")
    if process_mcap is not None and process_mcap.exists():
        gap = mean_gap_mm(load_recording(mcap), load_recording(process_mcap))
    return LiveRun(
        label=label,
        frame_sets=written + int(live["frames_dropped"]),
        written=written,
        dropped=int(live["frames_dropped"]),
        unmatched=sum(int(v) for v in live["frames_unmatched"].values()),
        latency_p50_ms=_number(live["latency_ms"]["p50"]),
        latency_p99_ms=_number(live["latency_ms"]["p99"]),
        camera_fps=tuple(_number(v) for v in live["camera_fps"].values()),
        wall_s=wall,
        peak_rss_mb=max((rss for _, rss in samples), default=0) / 1024**2,
        rss_growth_mb=(
            (_low_rss(samples, 0.75, 0.95) - _low_rss(samples, 0.25, 0.45)) / 1024**2
            if samples
            else float("nan")
        ),
        gap_to_process_mm=gap,
        exit_code=int(popen.returncode),
    )


def _number(value: object) -> float:
    return float(value) if isinstance(value, int | float) else float("nan")
