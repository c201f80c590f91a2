"""In-process measurements for ``make bench``: per-frame stages, carving methods, resolutions.

Everything here calls the pipeline's own functions (the runner's
:func:`~pipeline.run.runner.process_range`, the recorders, :func:`~pipeline.carve.hull.carve`)
so that what is timed is what ``process`` runs.
"""

from __future__ import annotations

import dataclasses
import logging
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from ...baseline.carving import carve_original
from ...baseline.curve import polyfit_centerline
from ...carve.hull import HullGrid, build_grid, carve, carve_brute_force, voxel_centers_mm
from ...geometry.camera import Camera
from ...reconstruct.frame import reconstruct_with_silhouettes
from ...reconstruct.frame_result import FrameResult
from ...reconstruct.model import SessionModel, build_model
from ...run.runner import process_range
from ...session.folder import Session
from ...session.settings import Workspace
from .report import BRUTE_FORCE, LOOKUP, ORIGINAL, OURS, RECONSTRUCT, RECONSTRUCT_CPU, ScalingRow
from .timing import StageStats, StageTimer

log = logging.getLogger(__name__)

Masks = list[NDArray[np.bool_]]

# FrameResult.timings_s / runner keys -> the bench's stage names.
_STAGE_NAMES = {
    "decode": "decode",
    "silhouette": "silhouettes",
    "carve": "carving",
    "centerline": "centreline",
    "quality": "quality",
    "encode": "encode",
}
# The runner's keys that make up "silhouettes to quality", the per-frame figure.
_RECONSTRUCT_KEYS = ("silhouette", "carve", "centerline", "quality")


@dataclass
class StageRun:
    """The per-frame stage run: its timer, the session's model and every frame's masks."""

    timer: StageTimer
    model: SessionModel
    setup_s: float
    masks: dict[int, Masks]
    results: dict[int, FrameResult]
    close_s: float

    def status_counts(self) -> dict[str, int]:
        """Frames timed by status: "ok", "empty", "failed"."""
        statuses = [r.status for r in self.results.values()]
        return {k: statuses.count(k) for k in ("ok", "empty", "failed")}

    def initialised_frames(self) -> int:
        """Frames fitted from the hull rather than from the track (a track's start, or a lost track)."""
        return sum(r.status == "ok" and not r.tracked for r in self.results.values())


@contextmanager
def opencv_threads(count: int) -> Iterator[None]:
    """Hold OpenCV to ``count`` threads inside the block (then restore its setting)."""
    before = cv2.getNumThreads()
    cv2.setNumThreads(count)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def time_stages(session: Session, out_dir: Path, *, frames: int) -> StageRun:
    """Time every per-frame stage of ``process`` on the first ``frames`` frames, in this process.

    Decode, silhouettes, carving, centreline, quality and JPEG/PNG encoding are timed
    inside the runner's own task function; MCAP and Rerun writing are timed around
    each recorder's ``write_frame`` into files in ``out_dir``. Rerun encodes and
    writes in a background thread, so its per-frame figure is the logging call and
    the rest shows in ``close_s`` (footers, flushes).

    The per-frame figure is recorded twice per frame: RECONSTRUCT, the wall
    time of silhouettes + carving + centreline + quality, and RECONSTRUCT_CPU, the
    thread CPU time of the same call, which leaves out the time other processes on a
    loaded machine hold the core. OpenCV is held to one thread meanwhile, since the target is for one
    core and the thread CPU time would miss work done on OpenCV's other threads.
    The tracked runner recomputes the last frames of a segment to start the next
    one's track; those warm-up fits are not samples (they produce no output).
    """
    import rerun as rr

    from ...record.mcap_log import McapRecorder
    from ...record.rerun_log import RerunRecorder

    start = time.perf_counter()
    model = build_model(session)
    setup_s = time.perf_counter() - start
    masks: dict[int, Masks] = {}
    cpu_s: dict[int, float] = {}

    def frame_fn(
        index: int, images: Sequence[NDArray[np.uint8]], m: SessionModel, previous: Sequence[FrameResult]
    ) -> tuple[FrameResult, Masks]:
        cpu_start = time.thread_time()
        result, sil = reconstruct_with_silhouettes(index, images, m, previous)
        # A frame's first fit is the one output; a later one is another segment's warm-up.
        cpu_s.setdefault(index, time.thread_time() - cpu_start)
        masks[index] = sil
        return result, sil

    timer = StageTimer()
    n = min(frames, session.frame_count)
    names = tuple(c.name for c in session.cameras)
    with opencv_threads(1):
        outputs = process_range(
            model, session.video_paths, names, 0, n, images=True, frame_fn=frame_fn, tracked=True
        )

    out_dir.mkdir(parents=True, exist_ok=True)
    stream = rr.RecordingStream(application_id="pipeline-bench", recording_id=uuid.uuid4())
    stream.set_log_time_enabled(False)
    stream.save(out_dir / "bench.rrd")
    rerun = RerunRecorder(stream, session.cameras, session.settings.workspace)
    results: dict[int, FrameResult] = {}
    with (out_dir / "bench.mcap").open("wb") as sink:
        mcap = McapRecorder(sink, session.cameras, images=True)
        for out in outputs:
            result = out.result
            results[result.index] = result
            total = 0.0
            for key, seconds in result.timings_s.items():
                timer.add(_STAGE_NAMES.get(key, key), seconds)
                total += seconds
            if result.index in cpu_s:  # not a frame whose images could not be decoded
                timer.add(RECONSTRUCT, sum(result.timings_s.get(k, 0.0) for k in _RECONSTRUCT_KEYS))
                timer.add(RECONSTRUCT_CPU, cpu_s[result.index])
            time_ns = session.timestamp_ns(result.index)
            t0 = time.perf_counter()
            mcap.write_frame(result, time_ns, jpegs=out.jpegs)
            t1 = time.perf_counter()
            rerun.write_frame(result, time_ns, jpegs=out.jpegs, silhouettes_png=out.silhouettes_png)
            t2 = time.perf_counter()
            timer.add("mcap", t1 - t0)
            timer.add("rerun", t2 - t1)
            timer.add("all stages", total + t2 - t0)
        t0 = time.perf_counter()
        mcap.finish()
    rerun.finish()
    stream.flush()
    stream.disconnect()
    close_s = time.perf_counter() - t0
    return StageRun(timer, model, setup_s, masks, results, close_s)


def lookup_gather(grid: HullGrid, masks: Sequence[NDArray[np.bool_]]) -> NDArray[np.int64]:
    """Carving by a plain precomputed lookup: every voxel's pixel gathered in every camera.

    The scale reference between brute force and coarse-to-fine: no projection per
    frame, but no skipping of empty space either. Reads the grid's own voxel->pixel
    table, so it returns exactly :func:`~pipeline.carve.hull.carve`'s answer.

    Returns
    -------
    (P,) int64 sorted flat voxel indices.
    """
    pixels = np.zeros(grid.sentinel + 1, dtype=np.bool_)
    for c, mask in enumerate(masks):
        start = int(grid.pixel_offsets[c])
        pixels[start : start + mask.size] = mask.ravel()
    occupied = pixels[grid.voxel_pixels[0]]
    for table in grid.voxel_pixels[1:]:
        occupied &= pixels[table]
    f, v = np.nonzero(occupied)
    per_coarse = len(grid.fine_offsets)
    ids = grid.coarse_offsets[f // per_coarse] + grid.fine_offsets[f % per_coarse] + grid.voxel_offsets[v]
    ids.sort()
    return ids


def _best_time(fn: Callable[[], object], *, repeat: int = 1) -> float:
    """Best-of-``repeat`` wall time of ``fn()``, seconds (the best is the least disturbed run)."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


@dataclass
class CarvingComparison:
    """Carving and centreline by method on the same frames (see :func:`compare_methods`)."""

    methods: dict[str, StageStats]
    original: dict[str, StageStats]
    identical_frames: int
    compared_frames: int
    lookup_identical_frames: int
    lookup_compared_frames: int


def compare_methods(
    model: SessionModel,
    masks: dict[int, Masks],
    *,
    all_frames: Sequence[int],
    original_frames: Sequence[int],
    brute_force: bool = True,
) -> CarvingComparison:
    """Ours against the original method and the references, frame by frame.

    ``all_frames``: ours and the lookup gather are timed on these (cheap). On
    ``original_frames``: the original's big-cube carving with per-frame
    cv2.projectPoints and its sphere-fit/polyfit curve, brute force (every voxel
    projected each frame), and the check that ours equals brute force voxel for voxel.
    """
    grid, cameras, ws = model.grid, model.cameras, model.settings.workspace
    timer = StageTimer()
    lookup_identical = 0
    for i in all_frames:
        # Best of 3: carving takes well under a millisecond, where one scheduler hiccup
        # on a loaded machine would otherwise dominate the sample.
        timer.add(OURS, _best_time(partial(carve, grid, masks[i]), repeat=3))
        timer.add(LOOKUP, _best_time(partial(lookup_gather, grid, masks[i])))
        lookup_identical += bool(np.array_equal(carve(grid, masks[i]), lookup_gather(grid, masks[i])))
    original = StageTimer()
    base = model.settings.manipulator.base_mm
    n_points = model.settings.centerline.points
    identical = 0
    for i in original_frames:
        m = masks[i]
        t0 = time.perf_counter()
        ids = carve_original(cameras, ws, m)
        elapsed = time.perf_counter() - t0
        original.add("carving", elapsed)
        timer.add(ORIGINAL, elapsed)
        points = voxel_centers_mm(ws, ids).astype(np.float64)
        if len(points) >= 4:
            t0 = time.perf_counter()
            try:
                polyfit_centerline(points, base, n_points=n_points)
            except (ValueError, np.linalg.LinAlgError):
                pass  # the original's failures still cost their time
            original.add("centreline", time.perf_counter() - t0)
        if brute_force:
            t0 = time.perf_counter()
            reference = carve_brute_force(cameras, ws, m)
            timer.add(BRUTE_FORCE, time.perf_counter() - t0)
            ours = carve(grid, m)
            if np.array_equal(ours, reference):
                identical += 1
            else:
                log.error(
                    "frame %d: carve differs from brute force (%d vs %d voxels)", i, len(ours), len(reference)
                )
    compared = len(original_frames) if brute_force else 0
    return CarvingComparison(
        timer.stats(), original.stats(), identical, compared, lookup_identical, len(all_frames)
    )


def scaled_camera(camera: Camera, factor: int) -> Camera:
    """``camera`` with images ``factor`` times larger in each direction.

    OpenCV puts pixel centres at integers, so pixel i covers [i - 0.5, i + 0.5) and the
    upsampled pixel f*i + j (cv2.resize INTER_NEAREST) covers f*(i - 0.5) + 0.5 + j - 0.5:
    the new coordinate is f * u + (f - 1) / 2. Hence fx, fy scale by f and cx, cy
    become f * c + (f - 1) / 2.
    """
    k = np.array(camera.matrix, dtype=np.float64)
    k[0, 0] *= factor
    k[1, 1] *= factor
    k[0, 1] *= factor
    k[0, 2] = factor * k[0, 2] + (factor - 1) / 2
    k[1, 2] = factor * k[1, 2] + (factor - 1) / 2
    w, h = camera.size_px
    return dataclasses.replace(camera, size_px=(w * factor, h * factor), matrix=k)


def upsample_masks(masks: Sequence[NDArray[np.bool_]], factor: int) -> Masks:
    """(H, W) bool masks -> (factor*H, factor*W) bool, each pixel repeated (INTER_NEAREST)."""
    out = []
    for mask in masks:
        h, w = mask.shape
        big = cv2.resize(mask.view(np.uint8), (w * factor, h * factor), interpolation=cv2.INTER_NEAREST)
        out.append(big.view(np.bool_))
    return out


def carving_scaling(
    cameras: Sequence[Camera],
    workspace: Workspace,
    masks: dict[int, Masks],
    frames: Sequence[int],
    *,
    voxel_sizes_mm: Sequence[float] = (2.0, 1.0),
    factors: Sequence[int] = (1, 2),
) -> list[ScalingRow]:
    """build_grid set-up time and per-frame carve time at each voxel size and image scale."""
    rows = []
    for factor in factors:
        cams = [scaled_camera(c, factor) for c in cameras] if factor != 1 else list(cameras)
        frame_masks = {i: upsample_masks(masks[i], factor) if factor != 1 else masks[i] for i in frames}
        for voxel_mm in voxel_sizes_mm:
            ws = dataclasses.replace(workspace, voxel_mm=voxel_mm)
            t0 = time.perf_counter()
            grid = build_grid(cams, ws)
            setup_s = time.perf_counter() - t0
            timer = StageTimer()
            for i in frames:
                timer.add("carve", _best_time(partial(carve, grid, frame_masks[i]), repeat=3))
            nx = ws.shape[0]
            w, h = cams[0].size_px
            rows.append(
                ScalingRow(
                    label=f"{voxel_mm:g} mm ({nx}^3), {w}x{h}",
                    grid_shape=ws.shape,
                    image_px=(w, h),
                    setup_s=setup_s,
                    carve=timer.stats()["carve"],
                )
            )
            del grid
    return rows
