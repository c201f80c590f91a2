"""Process a whole session: frame ranges in parallel, recordings written in frame order.

The parent builds the per-session model once, splits the frames into contiguous
ranges and hands each range to a joblib task (loky processes locally, Dask on a
cluster). A task opens the videos itself, decodes only its frames and returns,
per frame, the small :class:`~pipeline.reconstruct.frame_result.FrameResult` plus compressed
media (JPEG images, PNG silhouettes); no full-resolution frame crosses a process
boundary. Results come back in order and go straight into the MCAP and Rerun
writers, whose files carry temporary names until the run is complete.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import numbers
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from ..errors import Interrupted, SessionError, SettingsError, WorkersError
from ..reconstruct.frame_result import FrameResult
from ..reconstruct.frame_task import FrameFunction, FrameOutput, encode_silhouette, map_here, process_range
from ..reconstruct.tracking import SEGMENT_FRAMES, segment_start
from ..session.folder import Session
from ..session.settings import CURVE_METHODS
from .backends import (
    BACKENDS,
    DASK_CONNECT_TIMEOUT_S,
    check_scheduler,
    check_scheduler_address,
    parallel_backend,
)
from .interrupts import raise_if_interrupted, signals_blocked_in_children, signals_interrupt
from .output_target import OutputTarget, prepare_outputs
from .outputs import Writers
from .progress import advance, new_tally, progress_bar
from .summary import RunSummary, compress_failures
from .workers import (
    available_cores,
    describe_pool_failure,
    effective_jobs,
    local_frame_map,
    release_local_workers,
    start_local_workers,
    wait_for_local_workers,
)

__all__ = [
    "FrameOutput",
    "RunSummary",
    "compress_failures",
    "encode_silhouette",
    "frame_ranges",
    "process_range",
    "process_session",
]

log = logging.getLogger(__name__)

# Ranges of this many frames at most (three tracking segments): long enough that
# one seek per range is negligible, short enough that every worker gets several
# (load balance, retries).
MAX_RANGE_FRAMES = 3 * SEGMENT_FRAMES
# ... and at least a segment: a range costs a task, three seeks and its track's warm-up.
MIN_RANGE_FRAMES = SEGMENT_FRAMES


def frame_ranges(start: int, stop: int, n_workers: int) -> list[tuple[int, int]]:
    """Split ``[start, stop)`` into contiguous ranges, largest first.

    Each range takes the frames left divided by twice the number of workers
    (within MIN_RANGE_FRAMES..MAX_RANGE_FRAMES): long ranges while much is left,
    short ones at the end (guided self-scheduling), so that the workers run out
    of work within a short range of each other instead of one idling while
    another finishes a long one. Ranges end where a tracking segment does
    (:mod:`pipeline.reconstruct.tracking`) wherever they can, so that no segment's track
    is started twice.
    """
    ranges: list[tuple[int, int]] = []
    share = 2 * max(1, n_workers)
    at = start
    while at < stop:
        left = stop - at
        size = min(MAX_RANGE_FRAMES, max(MIN_RANGE_FRAMES, math.ceil(left / share)))
        if segment_start(at + size) > at:
            size = segment_start(at + size) - at
        if left - size < MIN_RANGE_FRAMES:  # no stub of a range at the end
            size = left
        ranges.append((at, at + size))
        at += size
    return ranges


def _run_ranges(
    ranges: list[tuple[int, int]],
    call: Callable[[tuple[int, int]], Any],
    n_jobs: int,
) -> Iterator[tuple[tuple[int, int], list[FrameOutput] | str]]:
    """Yield ``(range, outputs)`` in range order; ``(range, reason)`` for a range given up.

    The first ranges go to the workers before this returns (the caller opens its
    writers meanwhile); results are waited for as they are iterated.

    A task that dies (a killed worker, out of memory) or raises takes the pool's
    in-flight work with it. The unfinished ranges are run again in a fresh pool (the
    retry); if that breaks too, each remaining range runs alone, so that the ranges
    that only shared the pool with the culprit are not given up with it, and one
    that still dies alone is given up: its frames are marked failed, the run goes on.
    """
    from joblib import Parallel

    def dispatch(group: list[tuple[int, int]]) -> Iterator[list[FrameOutput]]:
        with signals_blocked_in_children():  # a fresh pool starts its workers here
            return iter(Parallel(n_jobs=n_jobs, return_as="generator")(call(r) for r in group))

    try:
        started = dispatch(ranges) if ranges else None
    except Exception:  # a pool broken from the start: the attempts below say why, and retry
        started = None
    return _attempts(list(ranges), dispatch, started)


def _attempts(
    pending: list[tuple[int, int]],
    dispatch: Callable[[list[tuple[int, int]]], Iterator[list[FrameOutput]]],
    started: Iterator[list[FrameOutput]] | None,
) -> Iterator[tuple[tuple[int, int], list[FrameOutput] | str]]:
    """The attempts of :func:`_run_ranges`; ``started``: the first one's results, if dispatched."""
    for attempt in ("parallel", "retry", "isolated"):
        if not pending:
            return
        groups = [pending] if attempt != "isolated" else [[r] for r in pending]
        survivors: list[tuple[int, int]] = []
        for group in groups:
            done = 0
            try:
                results = started if started is not None else dispatch(group)
                started = None  # the first attempt's results serve only once
                for outputs in results:
                    yield group[done], outputs
                    done += 1
            except Exception as exc:  # TerminatedWorkerError, BrokenProcessPool, a task's error
                first, last = group[done][0], group[done][1] - 1
                reason = f"worker died on frames {first}-{last}, also when retried ({type(exc).__name__})"
                log.warning(
                    "a worker failed on frames %d onwards (%s); %s",
                    group[done][0],
                    describe_pool_failure(exc),
                    "giving up on this range" if attempt == "isolated" else "retrying in a fresh pool",
                )
                if attempt == "isolated":
                    yield group[done], reason
                else:
                    survivors.extend(group[done:])
        pending = survivors


def _no_worker_finished(reasons: list[str], target: OutputTarget) -> WorkersError:
    """The error of a run whose every range was given up (``reasons``, one a range): a
    recording of nothing but failed frames would only replace the outputs there (under
    --force) with nothing."""
    others = f" (as on all {len(reasons)} ranges of the run)" if len(reasons) > 1 else ""
    return WorkersError(
        f"no frame was reconstructed: {reasons[0]}{others}; {target.mcap_path} and "
        f"{target.rrd_path} were not written (existing ones are untouched). Check the workers' "
        "memory, or the Dask scheduler and its workers, and rerun"
    )


def _failed_range(span: tuple[int, int], reason: str) -> list[FrameOutput]:
    return [FrameOutput(FrameResult.failed(i, reason), None, None) for i in range(*span)]


def process_session(
    session: Session,
    *,
    out_dir: Path = Path("recordings"),
    jobs: int = -1,
    backend: str = "loky",
    scheduler: str | None = None,
    frames: tuple[int, int | None] | None = None,
    images: bool = True,
    force: bool = False,
    curve: str | None = None,
    progress: bool = True,
    frame_fn: FrameFunction | None = None,
    started_at: float | None = None,
) -> RunSummary:
    """Reconstruct every frame of ``session`` into ``out_dir/<name>.mcap`` and ``.rrd``.

    Parameters
    ----------
    session : a loaded session (:func:`pipeline.load_session`).
    out_dir : output directory, created if needed.
    jobs : parallel workers; -1 = one per core, -2 = all but one, ...
    backend : "loky" (local processes), "threading" or "dask".
    scheduler : Dask scheduler address (with backend "dask"); None starts a local cluster.
    frames : (start, stop) to process only frames start <= i < stop (stop None: to the end).
    images : store the camera images (JPEG) in the recordings.
    force : replace existing outputs (atomically, at the end of the run).
    curve : centreline method, overriding session.toml ("fit" or "polyfit").
    progress : show a progress bar on stderr.
    frame_fn : replaces the per-frame computation (tests, experiments): called as
        ``frame_fn(index, images, session)`` and returning (FrameResult, silhouettes or
        None); must be picklable (a module-level function or a partial of one).

    started_at : the ``time.perf_counter()`` reading the summary's wall time and the progress
        bar's clock count from (the command line passes its process's start); default: now.

    Raises
    ------
    TypeError : ``session`` is not a loaded session (a folder's path: load it first).
    SettingsError : an unknown ``backend`` or ``curve``, ``jobs`` 0, a ``scheduler`` with
        another backend than "dask" or that is not one.
    SessionError : ``frames`` selects none of the session's frames.
    OutputError : an output exists (without ``force``), the directory is not
        writable, or the disk filled up; temporary files are removed.
    Interrupted : Ctrl-C, SIGTERM or SIGHUP, after removing temporary files; its
        message says what was done.
    """
    with signals_interrupt():
        return _process_session(
            session,
            out_dir=Path(out_dir),
            jobs=jobs,
            backend=backend,
            scheduler=scheduler,
            frames=frames,
            images=images,
            force=force,
            curve=curve,
            progress=progress,
            frame_fn=frame_fn,
            started_at=started_at,
        )


def _process_session(
    session: Session,
    *,
    out_dir: Path,
    jobs: int,
    backend: str,
    scheduler: str | None,
    frames: tuple[int, int | None] | None,
    images: bool,
    force: bool,
    curve: str | None,
    progress: bool,
    frame_fn: FrameFunction | None,
    started_at: float | None,
) -> RunSummary:
    t0 = time.perf_counter() if started_at is None else started_at
    if not isinstance(session, Session):
        raise TypeError(
            f"process_session takes a loaded session, not {type(session).__name__} {session!r}: "
            "give pipeline.load_session(folder)"
        )
    if backend not in BACKENDS:
        raise SettingsError(f"backend {backend!r} unknown; use one of {', '.join(BACKENDS)}")
    if curve is not None and curve not in CURVE_METHODS:
        raise SettingsError(f"curve {curve!r} unknown; use one of {', '.join(CURVE_METHODS)}")
    if isinstance(jobs, bool) or not isinstance(jobs, numbers.Integral) or jobs == 0:
        raise SettingsError(f"jobs {jobs!r}: give 1 or more workers, or -1 for one per core")
    if scheduler and backend != "dask":
        raise SettingsError(f"scheduler {scheduler!r} runs on a Dask cluster: give backend='dask'")
    if backend == "dask" and scheduler:
        check_scheduler_address(scheduler)
        check_scheduler(scheduler, DASK_CONNECT_TIMEOUT_S)
    start, stop = _frame_span(session, frames)
    if frames is not None and frames[1] is not None and frames[1] <= session.frame_count:
        # The frames asked for are in every video: a shorter one (Session.problems) cut none.
        session = dataclasses.replace(session, problems=())
    n_jobs = effective_jobs(jobs)
    if n_jobs < jobs and not (backend == "dask" and scheduler):
        log.warning(
            "--jobs %d is more than the %d cores available; using %d", jobs, available_cores(), n_jobs
        )
    elif jobs < -available_cores():
        log.warning("--jobs %d leaves none of the %d cores; using 1", jobs, available_cores())
    target = prepare_outputs(out_dir, session.name, force)
    failed = True
    try:
        summary = _run_with(
            session, target, t0, start, stop, n_jobs, backend, scheduler, images, curve, progress, frame_fn
        )
        failed = False
    finally:
        target.release(failed=failed)
    return summary


def _run_with(
    session: Session,
    target: OutputTarget,
    t0: float,
    start: int,
    stop: int,
    n_jobs: int,
    backend: str,
    scheduler: str | None,
    images: bool,
    curve: str | None,
    progress: bool,
    frame_fn: FrameFunction | None,
) -> RunSummary:
    if curve is not None:
        settings = session.settings
        settings = dataclasses.replace(
            settings, centerline=dataclasses.replace(settings.centerline, method=curve)
        )
        session = dataclasses.replace(session, settings=settings)

    from joblib import delayed

    names = tuple(c.name for c in session.cameras)
    # Absolute paths: Dask workers may run elsewhere (with the session at the same path).
    videos = tuple(p.resolve() for p in session.video_paths)
    writer: Writers | None = None
    done = 0
    tip = doubt = ""
    refinement = None
    radii = None  # the tube's radius along it, read from the session (RadiusProfile)
    written: list[tuple[Path, int]] = []
    # Local workers tell the bar of each frame as they finish it (a range's results
    # come back whole): one byte each, appended to a file of this run's.
    tally = new_tally() if progress and backend != "dask" else None
    # Shown from here on, while the workers start and the model is built, not only from
    # the first results.
    bar = progress_bar(stop - start, progress, elapsed_s=time.perf_counter() - t0, tally=tally)
    try:
        with bar:
            if backend == "loky":
                # Local workers start now (unless the command line started them already): they
                # spawn and import the per-frame modules while the parent builds the model.
                start_local_workers(n_jobs)
            if frame_fn is None:
                from ..calibrate.background_order import check_background_order
                from ..calibrate.refine import refined_cameras, sample_session
                from ..calibrate.video_order import check_video_order
                from ..reconstruct.frame import check_declared_radius
                from ..reconstruct.frame_task import camera_frames
                from ..reconstruct.model import build_model
                from ..reconstruct.tip_shape import end_assumed, with_session_tip

                model: Any = build_model(session)
                # The sample frames that settle the cameras and the tube's end are
                # reconstructed on the local workers, which would wait for them otherwise;
                # where the given cameras are kept, the end is read on the cameras' frames.
                frame_map = local_frame_map(n_jobs) if backend == "loky" else map_here
                paths = session.video_paths
                samples = sample_session(paths, start, stop)
                # Backgrounds, and videos, in other cameras' places would fail every frame, or be
                # taken for cameras that moved: named first.
                if session.settings.silhouette.method == "background":
                    folder = session.directory / "background"
                    check_background_order(session.backgrounds, samples, names, folder)
                check_video_order(model, samples, paths)
                check_declared_radius(model, samples, session.directory / "session.toml")
                frames_of = functools.partial(camera_frames, paths)
                cameras, refinement, tips, radii = refined_cameras(model, samples, frame_map, frames_of)
                if cameras is not session.cameras:
                    session = dataclasses.replace(session, cameras=cameras)
                    model = build_model(session)
                model, choice = with_session_tip(
                    model, paths, start, stop, frame_map, tips, session_radii=radii
                )
                tip = end_assumed(model, choice)
                doubt = choice.doubt if choice is not None else ""
            else:
                model = session  # a replacement frame function gets the session as its model
            with parallel_backend(backend, scheduler, n_jobs, model) as (n_workers, shared):

                def call(span: tuple[int, int]) -> Any:
                    # The model is a positional argument of its own: the local workers map
                    # its arrays, Dask scatters it once (joblib's dask backend scatters
                    # arguments, not closures).
                    return delayed(process_range)(
                        shared,
                        videos,
                        names,
                        span[0],
                        span[1],
                        images=images,
                        frame_fn=frame_fn,
                        tally=None if tally is None else str(tally),
                    )

                ranges = frame_ranges(start, stop, n_workers)
                if backend == "loky":
                    wait_for_local_workers()
                results = _run_ranges(ranges, call, n_jobs)
                # The writers open (importing Rerun, logging the cameras) while the workers
                # start on the first ranges.
                writer = Writers(
                    session,
                    target,
                    images=images,
                    cameras_used="" if refinement is None else refinement.describe(),
                    tube_end=tip,
                    radius_profile=radii,
                    frame_doubt=doubt,
                )
                given_up: list[str] = []  # why each range given up was
                reconstructed = False  # some range came back from the workers
                for span, outputs in results:
                    raise_if_interrupted()
                    if isinstance(outputs, str):  # a range given up: its frames fail
                        given_up.append(outputs)
                        outputs = _failed_range(span, outputs)
                    else:
                        reconstructed = True
                    for out in outputs:
                        writer.write(out)
                        done += 1
                        advance(bar, done)
                if given_up and not reconstructed:
                    raise _no_worker_finished(given_up, target)
        assert writer is not None
        raise_if_interrupted()
        writer.finish()
        if frame_fn is None:
            from ..calibrate.refine import remove_refined_calibration, write_refined_calibration

            path = target.out_dir / f"{target.name}.calibration.toml"
            if refinement is not None and refinement.changed:
                written.append(
                    write_refined_calibration(path, target.partial(path), session.cameras, refinement)
                )
            else:
                remove_refined_calibration(path)  # an earlier run's: not these outputs' cameras
    except KeyboardInterrupt as exc:
        if writer is not None and writer.committed:
            message = f"interrupted as the run ended; {target.mcap_path} and {target.rrd_path} are complete"
        else:
            if writer is not None:
                writer.abort()
            message = (
                f"interrupted with {done} of {stop - start} frames written; temporary files removed, "
                "existing outputs untouched"
            )
        raise Interrupted(message) from exc
    except BaseException:
        if writer is not None:
            writer.abort()
        raise
    finally:
        if backend == "loky":
            release_local_workers()
        if tally is not None:
            tally.unlink(missing_ok=True)
    wall = time.perf_counter() - t0
    summary = writer.summary(wall)
    return dataclasses.replace(
        summary,
        tip=tip,
        cameras=refinement.describe() if refinement is not None else "",
        camera_warnings=refinement.warnings() if refinement is not None else [],
        session_problems=list(session.problems) + (refinement.problems() if refinement is not None else []),
        outputs=summary.outputs + written,
    )


def _frame_span(session: Session, frames: tuple[int, int | None] | None) -> tuple[int, int]:
    n = session.frame_count
    if frames is None:
        return 0, n
    start, stop = frames
    # Where the videos differ in length, the session is its shortest video's: named.
    shortest = ""
    if len(set(session.frame_counts)) > 1:
        path = session.video_paths[session.frame_counts.index(n)]
        shortest = f", as long as its shortest video, {path.name}"
    if stop is not None and stop > n and start < n:
        log.warning(
            "--frames %d:%d reaches past the session's %d frames%s; running to its end",
            start,
            stop,
            n,
            shortest,
        )
    stop = n if stop is None else min(stop, n)
    if not 0 <= start < stop:
        raise SessionError(
            f"{session.directory}: --frames {start}:{frames[1] or ''} selects no frame "
            f"(the session has {n} frames, 0-{n - 1}{shortest})"
        )
    return start, stop
