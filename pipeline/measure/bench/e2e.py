"""End-to-end timings for ``make bench``: the sessions, ``process`` subprocesses, decode floor.

Each end-to-end run is the real command line in a fresh Python process, timed
from process start to exit (outputs closed and renamed into place), so it
includes imports and the per-session set-up exactly as a user pays them.
"""

from __future__ import annotations

import logging
import resource
import shutil
import subprocess
import sys
import time
import tomllib
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import psutil
import tomli_w

from ...errors import PipelineError
from ...session.video import read_frames
from .report import EndToEndRun

log = logging.getLogger(__name__)

# How often the process tree's memory is sampled: short enough to catch the
# set-up's peak, which lasts a fraction of a second; not shorter, since a sample
# costs ~1-1.5 ms of CPU that the timed run, on the same two cores, loses.
RSS_SAMPLE_S = 0.05


def ensure_session(directory: Path, *, frames: int, synth_args: Sequence[str] = ()) -> Path:
    """Render a session into ``directory`` unless its calibration.toml exists.

    ``synth_args`` are ``pipeline synth`` options (none: the demo, bend_rotate). An
    existing session is reused as it is: delete the directory to render it again.
    The session is rendered beside ``directory`` and renamed into place when
    complete: the renderer writes calibration.toml first and the videos last, so a
    render stopped half way must not leave a directory that looks finished.
    """
    if (directory / "calibration.toml").exists():
        return directory
    if directory.exists() and any(directory.iterdir()):
        raise PipelineError(
            f"{directory}: not a session (no calibration.toml) and not empty; "
            "delete it or name another directory to render the session into"
        )
    partial = directory.with_name(directory.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    log.info("rendering a %d-frame session into %s %s", frames, directory, " ".join(synth_args))
    cmd = [sys.executable, "-m", "pipeline", "synth", str(partial), "--frames", str(frames), *synth_args]
    subprocess.run(cmd, check=True)
    if directory.exists():
        directory.rmdir()  # empty, checked above
    partial.rename(directory)
    return directory


def tree_rss(proc: psutil.Process) -> int:
    """Summed RSS of ``proc`` and all its descendants, bytes (0 once it is gone)."""
    total = 0
    try:
        procs = [proc, *proc.children(recursive=True)]
    except psutil.Error:
        return 0
    for p in procs:
        try:
            total += p.memory_info().rss
        except psutil.Error:
            continue  # a worker that exited between listing and reading
    return total


def run_process(
    session_dir: Path,
    out_dir: Path,
    *,
    jobs: int,
    frames: int,
    voxel_mm: float,
    label: str,
    extra_args: tuple[str, ...] = (),
) -> EndToEndRun:
    """Run ``python -m pipeline process`` on ``session_dir`` and time it, start to exit.

    CPU time (user + sys) of the whole tree is reported beside the wall time: on a
    shared machine it shows what the run needs, whatever others take.
    Peak memory is the largest summed RSS of the process tree (the CLI process and
    its loky workers) seen by sampling every RSS_SAMPLE_S. Summing RSS counts pages
    shared between processes (libraries, memory-mapped tables) once per process, so
    it is an upper bound on the memory actually used.
    """
    cmd = [
        sys.executable,
        "-m",
        "pipeline",
        "process",
        str(session_dir),
        "--out",
        str(out_dir),
        "--force",
        "--jobs",
        str(jobs),
        "--frames",
        f"0:{frames}",
        *extra_args,
    ]
    log.info("timing: %s", " ".join(cmd[1:]))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    popen = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    proc = psutil.Process(popen.pid)
    peak = 0
    while popen.poll() is None:
        peak = max(peak, tree_rss(proc))
        time.sleep(RSS_SAMPLE_S)
    wall = time.perf_counter() - start
    # Children's CPU time counts every descendant reaped so far (the loky workers are
    # reaped by the CLI process when its pool shuts down), so the difference is this run's.
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_s = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    stderr = popen.stderr.read().decode(errors="replace") if popen.stderr else ""
    if popen.returncode == 1:  # the run finished, some frames failed: say which
        failed = [line for line in stderr.splitlines() if "failed" in line]
        log.warning("%s: some frames failed:\n%s", label, "\n".join(failed[-10:]))
    elif popen.returncode != 0:
        log.warning("%s exited with %d:\n%s", label, popen.returncode, stderr[-2000:])
    return EndToEndRun(
        label=label,
        jobs=jobs,
        voxel_mm=voxel_mm,
        frames=frames,
        wall_s=wall,
        exit_code=int(popen.returncode),
        peak_rss_mb=peak / 1024**2,
        cpu_s=cpu_s,
    )


def median_run(runs: Sequence[EndToEndRun]) -> EndToEndRun:
    """The median of repeated runs of one configuration, by wall time, with every run's
    wall time in the order run and the largest peak memory of them all."""
    if not runs:
        raise ValueError("median_run needs at least one run")
    median = sorted(runs, key=lambda r: r.wall_s)[len(runs) // 2]
    peak = max(r.peak_rss_mb for r in runs)
    return replace(median, peak_rss_mb=peak, walls_s=tuple(r.wall_s for r in runs))


def decode_floor(video_paths: Sequence[Path], *, frames: int, repeats: int = 1) -> float:
    """Seconds to only decode ``frames`` frames of every video, one after another in this process.

    The median of ``repeats`` passes: a pass takes a few tenths of a second, so one
    scheduler stall on a loaded machine would move it, and every ratio to it, by a
    large fraction.
    """
    passes = []
    for _ in range(repeats):
        start = time.perf_counter()
        for path in video_paths:
            for _ in read_frames(path, 0, frames):
                pass
        passes.append(time.perf_counter() - start)
    return sorted(passes)[len(passes) // 2]


def voxel_session(source: Path, target: Path, *, voxel_mm: float) -> Path:
    """A copy of session ``source`` in ``target`` carved at ``voxel_mm``.

    Videos, calibration and backgrounds are symlinked (nothing large is copied);
    session.toml is the source's with ``[workspace] voxel_mm`` replaced.
    """
    target.mkdir(parents=True, exist_ok=True)
    for path in source.iterdir():
        if path.name in ("session.toml", "ground_truth.npz"):
            continue
        link = target / path.name
        if link.is_symlink() or link.exists():
            if link.is_dir() and not link.is_symlink():
                shutil.rmtree(link)
            else:
                link.unlink()
        link.symlink_to(path.resolve())
    settings_path = source / "session.toml"
    data = tomllib.loads(settings_path.read_text()) if settings_path.exists() else {}
    data.setdefault("workspace", {})["voxel_mm"] = float(voxel_mm)
    (target / "session.toml").write_text(tomli_w.dumps(data))
    return target
