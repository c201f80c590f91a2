"""The per-shape rows of ``make bench``: the speed targets beyond the demo.

Each shape is a session rendered once by ``pipeline synth`` into
``recordings/bench-<name>`` (like the demo) and reused. Per shape: ``process`` end to
end with 2 workers against decoding its three videos alone, and the per-frame
silhouettes-to-quality time in this process (:func:`~pipeline.measure.bench.stages.time_stages`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ...session.folder import load_session
from .e2e import decode_floor, ensure_session, median_run, run_process
from .report import RECONSTRUCT, RECONSTRUCT_CPU, EndToEndRun, ShapeRun
from .stages import StageRun, time_stages
from .timing import StageStats

log = logging.getLogger(__name__)

SHAPE_JOBS = 2  # the end-to-end target is for 2 workers
# Decode-only passes per floor (median): see decode_floor.
FLOOR_REPEATS = 3


@dataclass(frozen=True)
class BenchShape:
    """A session the bench renders once and reuses.

    Attributes
    ----------
    name : the row's name, e.g. "loop".
    directory : the session's directory name under the recordings folder.
    synth_args : the ``pipeline synth`` options that render it (none: the demo).
    live : whether it is also replayed live (the demo always is).
    """

    name: str
    directory: str
    synth_args: tuple[str, ...] = ()
    live: bool = False

    def describe(self, session_dir: Path) -> str:
        """The command that renders it into ``session_dir`` (900 frames, as the bench does)."""
        return " ".join(("pipeline synth", str(session_dir), *self.synth_args))


DEMO_SHAPE = BenchShape("bend_rotate (demo)", "demo")
# A loop, whose tip lies against its stem (the costliest frames the cascade fits); a
# random shape with a round end from the synthetic variety (random_shapes: curvature and
# twist drawn from the seed, sometimes a loop); and a thicker loop with a round end seen by
# the other rig, whose track is lost more often than the first's. All 320x240, three
# cameras: the conditions the speed targets are set for. The loops are replayed live too.
SHAPES = (
    BenchShape("loop", "bench-loop", ("--shape", "loop"), live=True),
    BenchShape(
        "random, round end (seed 1)",
        "bench-random-round",
        ("--shape", "random", "--tip", "round", "--seed", "1"),
    ),
    BenchShape(
        "loop, r 7 mm, round end, ninety rig (seed 7)",
        "bench-loop-round",
        ("--shape", "loop", "--seed", "7", "--arrangement", "ninety", "--radius-mm", "7", "--tip", "round"),
        live=True,
    ),
)


def shape_run(
    shape: BenchShape,
    session_dir: Path,
    *,
    end_to_end: EndToEndRun | None,
    decode_floor_s: float,
    decode_frames: int,
    stages: StageRun,
) -> ShapeRun:
    """One shape's row from its measurements (the demo's come from the demo's own runs)."""
    stats = stages.timer.stats()
    none = StageStats.from_seconds([])
    return ShapeRun(
        name=shape.name,
        session=str(session_dir),
        description=shape.describe(session_dir),
        end_to_end=end_to_end,
        decode_floor_s=decode_floor_s,
        decode_frames=decode_frames,
        reconstruct=stats.get(RECONSTRUCT, none),
        reconstruct_cpu=stats.get(RECONSTRUCT_CPU, none),
        statuses=stages.status_counts(),
        initialised_frames=stages.initialised_frames(),
    )


def measure_shape(
    shape: BenchShape,
    recordings: Path,
    work_dir: Path,
    *,
    frames: int,
    session_frames: int,
    stage_frames: int,
    repeats: int,
) -> ShapeRun:
    """Render ``shape`` into ``recordings`` if needed, then time it.

    Parameters
    ----------
    shape : the session to measure.
    recordings : the folder holding the sessions (recordings/).
    work_dir : scratch directory for the outputs of the runs.
    frames : frames processed end to end and decoded for the floor.
    session_frames : frames rendered when the session does not exist yet.
    stage_frames : frames timed one by one in this process.
    repeats : ``process`` runs with 2 workers; the median is reported (none: no row figures
        end to end).
    """
    session_dir = ensure_session(
        recordings / shape.directory, frames=session_frames, synth_args=shape.synth_args
    )
    session = load_session(session_dir)
    n = min(frames, session.frame_count)
    log.info("%s: decode only, then %d end-to-end run(s) of %d frames", shape.name, repeats, n)
    floor_s = decode_floor(session.video_paths, frames=n, repeats=FLOOR_REPEATS)
    voxel_mm = session.settings.workspace.voxel_mm
    label = f"{shape.name}, {SHAPE_JOBS} workers"
    runs = [
        run_process(session_dir, work_dir / "out", jobs=SHAPE_JOBS, frames=n, voxel_mm=voxel_mm, label=label)
        for _ in range(repeats)
    ]
    timed = min(stage_frames, n)
    log.info("%s: timing %d frames one by one", shape.name, timed)
    stages = time_stages(session, work_dir / "stages", frames=timed)
    return shape_run(
        shape,
        session_dir,
        end_to_end=median_run(runs) if runs else None,
        decode_floor_s=floor_s,
        decode_frames=n,
        stages=stages,
    )


def measure_shapes(
    shapes: Sequence[BenchShape],
    recordings: Path,
    work_dir: Path,
    *,
    frames: int,
    session_frames: int,
    stage_frames: int,
    repeats: int,
) -> list[ShapeRun]:
    """:func:`measure_shape` for each of ``shapes``, each in its own scratch folder."""
    return [
        measure_shape(
            shape,
            recordings,
            work_dir / shape.directory,
            frames=frames,
            session_frames=session_frames,
            stage_frames=stage_frames,
            repeats=repeats,
        )
        for shape in shapes
    ]
