"""What ``make bench`` measured: the report, its targets, a Markdown table and JSON.

Pure functions of a :class:`BenchReport`; nothing here measures anything, so the
test can feed a small fake report through every output.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from .timing import StageStats

REALTIME_FPS = 30.0
# The end-to-end wall-time targets are for this many frames (the demo session).
TARGET_FRAMES = 900

# The per-frame figure: silhouettes + carving + centreline + quality of one frame,
# wall time and the thread's CPU time (one process, OpenCV on one thread).
RECONSTRUCT = "silhouettes to quality"
RECONSTRUCT_CPU = "silhouettes to quality, CPU"
# Stage names in the order of the per-frame path; the chart and table follow it.
STAGE_ORDER = (
    "decode",
    "silhouettes",
    "carving",
    "centreline",
    "quality",
    "encode",
    "mcap",
    "rerun",
    "all stages",
    RECONSTRUCT,
    RECONSTRUCT_CPU,
)
# The speed targets for every shape: end to end with 2 workers over decoding
# the three videos alone, and the 99th percentile of RECONSTRUCT (a live camera's 30 fps).
SHAPE_DECODE_RATIO_LIMIT = 20.0
RECONSTRUCT_P99_LIMIT_MS = 33.0
# The live targets, replaying a 320x240 session at 30 fps on this machine.
LIVE_P50_LIMIT_MS = 20.0
LIVE_P99_LIMIT_MS = 50.0
LIVE_GAP_LIMIT_MM = 0.05
# Carving methods compared at 128^3 (BenchReport.carving_methods keys).
OURS = "ours (coarse-to-fine)"
LOOKUP = "lookup gather"
BRUTE_FORCE = "brute force (projectPoints)"
ORIGINAL = "original (big cubes, projectPoints)"
# What the original work reported for itself (per point cloud, per frame), seconds.
ORIGINAL_PUBLISHED_S = {"point cloud": 2.0, "frame": 16.0}


@dataclass(frozen=True)
class EndToEndRun:
    """One ``python -m pipeline process`` subprocess, process start to files closed.

    Attributes
    ----------
    label : what was run, e.g. "2 mm, 2 workers".
    jobs : --jobs given.
    voxel_mm : voxel size of the session processed.
    frames : frames processed.
    wall_s : wall time of the subprocess, seconds.
    exit_code : its exit status (0 all frames ok or empty).
    peak_rss_mb : peak of the summed RSS of the process tree (psutil sampling), MiB.
    cpu_s : user + sys CPU time of the process tree, seconds.
    walls_s : wall times of every repeat of this run, in the order run, seconds; the run reported
        (``wall_s`` and the rest) is the median one.
    """

    label: str
    jobs: int
    voxel_mm: float
    frames: int
    wall_s: float
    exit_code: int
    peak_rss_mb: float
    cpu_s: float = float("nan")
    walls_s: tuple[float, ...] = ()

    @property
    def fps(self) -> float:
        return self.frames / self.wall_s if self.wall_s > 0 else float("nan")

    @property
    def realtime_factor(self) -> float:
        """How many times faster than the 30 fps recording plays."""
        return self.fps / REALTIME_FPS


@dataclass(frozen=True)
class ScalingRow:
    """Carving cost at one resolution: grid set-up once per session, carve once per frame.

    Attributes
    ----------
    label : e.g. "1 mm (256^3), 320x240".
    grid_shape : voxels along x, y, z.
    image_px : (width, height) of the masks.
    setup_s : build_grid wall time, seconds.
    carve : per-frame carve time.
    """

    label: str
    grid_shape: tuple[int, int, int]
    image_px: tuple[int, int]
    setup_s: float
    carve: StageStats


@dataclass(frozen=True)
class ShapeRun:
    """One shape's session against the per-shape speed targets.

    Attributes
    ----------
    name : e.g. "loop".
    session : its session directory.
    description : how it was rendered, e.g. "pipeline synth recordings/bench-loop --shape loop".
    end_to_end : the median ``process`` run with 2 workers (every run's wall time in
        its ``walls_s``), or None when it was not run.
    decode_floor_s : seconds to only decode ``decode_frames`` frames of each of its videos.
    decode_frames : frames per video decoded for the floor (those processed end to end).
    reconstruct : per-frame silhouettes-to-quality wall time (:data:`RECONSTRUCT`).
    reconstruct_cpu : the same frames' thread CPU time (:data:`RECONSTRUCT_CPU`).
    statuses : frames timed by status ("ok", "empty", "failed").
    initialised_frames : of those, frames fitted from the hull rather than from the track.
    """

    name: str
    session: str
    description: str
    end_to_end: EndToEndRun | None
    decode_floor_s: float
    decode_frames: int
    reconstruct: StageStats
    reconstruct_cpu: StageStats
    statuses: dict[str, int] = field(default_factory=dict)
    initialised_frames: int = 0

    @property
    def decode_ratio(self) -> float:
        """End to end (2 workers) over decode only, per shape."""
        return ratio_of(wall_s(self.end_to_end), self.decode_floor_s)


@dataclass(frozen=True)
class LiveRun:
    """One ``python -m pipeline live --replay`` subprocess .

    Attributes
    ----------
    label : what was replayed, e.g. "bend_rotate (demo)".
    frame_sets : frame-sets matched (written + dropped).
    written : frames reconstructed and written.
    dropped : frame-sets dropped because the reconstruction fell behind.
    unmatched : camera frames no frame of every other camera matched.
    latency_p50_ms, latency_p99_ms : capture of a frame's last image to its result written, ms.
    camera_fps : per camera, frames per second delivered.
    wall_s : the subprocess's wall time, seconds.
    peak_rss_mb : the peak of its process tree's summed RSS (the run and its restart worker), MiB.
    rss_growth_mb : its lowest RSS over 75-95 % of the run less its lowest over 25-45 %, MiB
        (flat memory: ~0; the lows leave out the frames the Rerun writer batches up).
    gap_to_process_mm : mean distance of its centrelines to ``process``'s on the frames
        both hold, mm (NaN: no ``process`` recording to compare with).
    exit_code : its exit status.
    """

    label: str
    frame_sets: int
    written: int
    dropped: int
    unmatched: int
    latency_p50_ms: float
    latency_p99_ms: float
    camera_fps: tuple[float, ...]
    wall_s: float
    peak_rss_mb: float
    rss_growth_mb: float
    gap_to_process_mm: float
    exit_code: int


@dataclass(frozen=True)
class Target:
    """One speed target; ``passed`` is None when it was not measured in this run."""

    name: str
    measured: float
    limit: float
    unit: str
    higher_is_better: bool = False

    @property
    def passed(self) -> bool | None:
        if not math.isfinite(self.measured):
            return None
        return self.measured >= self.limit if self.higher_is_better else self.measured <= self.limit

    @property
    def verdict(self) -> str:
        return {True: "PASS", False: "MISS", None: "not measured"}[self.passed]


@dataclass
class BenchReport:
    """Everything one bench run measured (times in the units their names give).

    Attributes
    ----------
    meta : machine, load, versions, frames and options of the run.
    stages : ours, per-frame stage -> stats (keys from :data:`STAGE_ORDER` and extras).
    original : the original method, per-frame stage -> stats, for the stages it does differently.
    carving_methods : carving at 128^3 by method (OURS, LOOKUP, BRUTE_FORCE, ORIGINAL)
        -> per-frame stats.
    one_off_s : once-per-run costs, seconds (grid set-up, closing the recordings).
    identical_frames : frames on which ours equalled brute force voxel for voxel.
    compared_frames : frames compared with brute force.
    lookup_identical_frames, lookup_compared_frames : the same against the plain lookup
        gather (every frame timed; checks the coarse-to-fine skipping, not the tables).
    compared_frames : frames compared with brute force.
    end_to_end : the ``process`` subprocess runs.
    decode_floor_s : wall time to only decode the three videos of the whole session.
    decode_frames : frames per video decoded for the floor.
    scaling : carving set-up and per-frame cost by resolution.
    shapes : the demo and further shapes against the per-shape speed targets.
    live : ``live --replay`` of the demo and further shapes .
    """

    meta: dict[str, Any] = field(default_factory=dict)
    stages: dict[str, StageStats] = field(default_factory=dict)
    original: dict[str, StageStats] = field(default_factory=dict)
    carving_methods: dict[str, StageStats] = field(default_factory=dict)
    one_off_s: dict[str, float] = field(default_factory=dict)
    identical_frames: int = 0
    compared_frames: int = 0
    lookup_identical_frames: int = 0
    lookup_compared_frames: int = 0
    end_to_end: list[EndToEndRun] = field(default_factory=list)
    decode_floor_s: float = float("nan")
    decode_frames: int = 0
    scaling: list[ScalingRow] = field(default_factory=list)
    shapes: list[ShapeRun] = field(default_factory=list)
    live: list[LiveRun] = field(default_factory=list)

    def run(self, *, jobs: int, voxel_mm: float) -> EndToEndRun | None:
        """The end-to-end run with ``jobs`` workers at ``voxel_mm``, if there was one."""
        for r in self.end_to_end:
            if r.jobs == jobs and math.isclose(r.voxel_mm, voxel_mm):
                return r
        return None


def wall_s(run: EndToEndRun | None) -> float:
    return run.wall_s if run is not None else float("nan")


def ratio_of(a: float, b: float) -> float:
    return a / b if b and math.isfinite(a) and math.isfinite(b) else float("nan")


def speedup_2_over_1(report: BenchReport) -> float:
    """Throughput of 2 workers over 1 worker at 2 mm (wall 1 worker / wall 2 workers)."""
    return ratio_of(wall_s(report.run(jobs=1, voxel_mm=2.0)), wall_s(report.run(jobs=2, voxel_mm=2.0)))


def targets(report: BenchReport) -> list[Target]:
    """The run's speed targets, then those per shape, against what ``report`` measured."""
    two = report.run(jobs=2, voxel_mm=2.0)
    # The wall-time targets are for the whole 900-frame demo; a shorter run (--quick)
    # would pass them without saying anything.
    full = [r for r in report.end_to_end if r.frames >= TARGET_FRAMES]
    two_full = next((r for r in full if r.jobs == 2 and math.isclose(r.voxel_mm, 2.0)), None)
    fine = [r for r in full if math.isclose(r.voxel_mm, 1.0)]
    carve = report.carving_methods.get(OURS) or report.stages.get("carving")
    carve_ms = carve.median_ms if carve else float("nan")
    peak = max((r.peak_rss_mb for r in report.end_to_end), default=float("nan"))
    identical = ratio_of(100.0 * report.identical_frames, report.compared_frames)
    return [
        Target("carve median at 128^3", carve_ms, 1.0, "ms"),
        Target(
            f"carve identical to brute force ({report.identical_frames}/{report.compared_frames} frames)",
            identical,
            100.0,
            "%",
            higher_is_better=True,
        ),
        Target(f"end to end {TARGET_FRAMES} frames, 2 workers", wall_s(two_full), 10.0, "s"),
        Target("end to end / decode only", ratio_of(wall_s(two), report.decode_floor_s), 5.0, "x"),
        Target(f"end to end {TARGET_FRAMES} frames at 1 mm", wall_s(fine[0] if fine else None), 30.0, "s"),
        Target("peak memory", peak / 1024.0, 1.5, "GiB"),
        Target("2 workers / 1 worker", speedup_2_over_1(report), 1.6, "x", higher_is_better=True),
        *[t for shape in report.shapes for t in shape_targets(shape)],
        *[t for run in report.live for t in live_targets(run)],
    ]


def live_targets(run: LiveRun) -> list[Target]:
    """The live targets for one replay."""
    return [
        Target(f"live {run.label}: frame-sets dropped", float(run.dropped), 0.0, "frames"),
        Target(f"live {run.label}: latency p50", run.latency_p50_ms, LIVE_P50_LIMIT_MS, "ms"),
        Target(f"live {run.label}: latency p99", run.latency_p99_ms, LIVE_P99_LIMIT_MS, "ms"),
        Target(
            f"live {run.label}: centrelines vs process (mean)",
            run.gap_to_process_mm,
            LIVE_GAP_LIMIT_MM,
            "mm",
        ),
    ]


def shape_targets(shape: ShapeRun) -> list[Target]:
    """The speed targets for one shape.

    The ratio target is for 900 frames: a shorter run (--quick) spreads the fixed
    start-up over fewer frames and would miss it without saying anything about the
    per-frame cost, so it is "not measured" then.
    """
    run = shape.end_to_end
    full = run is not None and run.frames >= TARGET_FRAMES
    return [
        Target(
            f"end to end / decode only, {shape.name} ({TARGET_FRAMES} frames, 2 workers)",
            shape.decode_ratio if full else float("nan"),
            SHAPE_DECODE_RATIO_LIMIT,
            "x",
        ),
        Target(
            f"p99 silhouettes to quality, {shape.name} ({shape.reconstruct.count} frames, 1 core)",
            shape.reconstruct.p99_ms,
            RECONSTRUCT_P99_LIMIT_MS,
            "ms",
        ),
    ]


def _finite_or_none(value: Any) -> Any:
    """JSON has no NaN: write null instead."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite_or_none(v) for v in value]
    return value


def report_dict(report: BenchReport) -> dict[str, Any]:
    """The report as plain JSON data, derived figures (fps, ratios, targets) included."""
    data = asdict(report)
    for run, row in zip(report.end_to_end, data["end_to_end"], strict=True):
        row["fps"] = run.fps
        row["realtime_factor"] = run.realtime_factor
    for shape, row in zip(report.shapes, data["shapes"], strict=True):
        row["decode_ratio"] = shape.decode_ratio
    two = report.run(jobs=2, voxel_mm=2.0)
    data["ratios"] = {
        "end_to_end_over_decode": ratio_of(wall_s(two), report.decode_floor_s),
        "end_to_end_over_decode_by_shape": {s.name: s.decode_ratio for s in report.shapes},
        "workers_2_over_1": speedup_2_over_1(report),
        "original_over_ours": {
            k: ratio_of(v.median_ms, report.stages[k].median_ms)
            for k, v in report.original.items()
            if k in report.stages
        },
    }
    data["targets"] = [
        {"name": t.name, "measured": t.measured, "limit": t.limit, "unit": t.unit, "verdict": t.verdict}
        for t in targets(report)
    ]
    return dict(_finite_or_none(data))


def write_json(report: BenchReport, path: Path) -> None:
    Path(path).write_text(json.dumps(report_dict(report), indent=2) + "\n")
