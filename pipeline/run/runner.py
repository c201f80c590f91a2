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

import contextlib
import dataclasses
import logging
import math
import os
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from ..errors import Interrupted, SessionError, SettingsError
from ..reconstruct.frame_result import FrameResult
from ..reconstruct.frame_task import FrameFunction, FrameOutput, encode_silhouette, process_range
from ..reconstruct.tracking import SEGMENT_FRAMES, segment_start
from ..session.folder import Session
from .interrupts import deferred_signals, signals_blocked_in_children, signals_interrupt
from .outputs import OutputTarget, RunSummary, Writers, compress_failures, prepare_outputs
from .workers import (
    available_cores,
    describe_pool_failure,
    effective_jobs,
    loky_options,
    release_local_workers,
    shared_with_local_workers,
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
BACKENDS = ("loky", "threading", "dask")
DASK_CONNECT_TIMEOUT_S = 10
PROGRESS_REDRAW_S = 0.5


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


@contextlib.contextmanager
def _backend(backend: str, scheduler: str | None, n_jobs: int, model: Any) -> Iterator[tuple[int, Any]]:
    """joblib's parallel_config for ``backend``, yielding the number of workers and the
    model to hand them; for Dask, a client for the run (and a local cluster when no
    scheduler is given)."""
    import joblib

    if backend in ("loky", "threading"):
        options = loky_options() if backend == "loky" else {}
        with joblib.parallel_config(backend=backend, n_jobs=n_jobs, **options):
            if backend == "loky" and n_jobs > 1:
                with shared_with_local_workers(model) as shared:
                    yield n_jobs, shared
            else:
                yield n_jobs, model
        return
    # distributed logs ~45 INFO lines while a cluster starts, and warnings as an interrupted
    # one stops (cancelled tasks, workers killed), in this process and in its workers
    # (which read the variable): the run's own lines say what matters.
    quiet = not log.isEnabledFor(logging.DEBUG)
    if quiet:
        os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "critical")
    from distributed import Client, LocalCluster

    if quiet:
        # Dask's logging config gives these their own handlers (tornado's: a client's
        # callback that finds its connections closed as an interrupted run stops).
        for name in ("distributed", "tornado", "tornado.application"):
            logging.getLogger(name).setLevel(logging.CRITICAL)

    cluster = None
    if scheduler:
        try:
            client = Client(scheduler, timeout=DASK_CONNECT_TIMEOUT_S)
        except OSError as exc:  # refused, unreachable, timed out
            raise SettingsError(
                f"cannot reach the Dask scheduler at {scheduler} ({exc}); "
                "check --scheduler and that the scheduler is running"
            ) from None
    else:
        # A cluster interrupted while it starts cannot be closed (distributed's own exit
        # handler then fails on it with a traceback): a signal waits the seconds it takes.
        with deferred_signals(), signals_blocked_in_children():
            cluster = LocalCluster(n_workers=n_jobs, threads_per_worker=1, processes=True)
            client = Client(cluster)
    try:
        # The model is scattered to the workers once, not shipped with every range.
        with joblib.parallel_config(backend="dask", client=client, scatter=[model]):
            workers = len(client.scheduler_info().get("workers", {}))
            yield max(1, workers), model
    finally:
        _close_dask(client, cluster)


def _close_dask(client: Any, cluster: Any) -> None:
    """Close the run's client, and its local cluster if it started one (whose workers are
    killed if they do not stop within seconds), without letting a failure to close hide
    how the run ended."""
    for closing in (client, cluster):
        if closing is not None:
            try:
                closing.close()
            except Exception as exc:
                log.debug("closing %s failed: %s", type(closing).__name__, exc)


def _check_scheduler(address: str, timeout_s: float) -> None:
    """Ask ``address`` who it is, all within ``timeout_s``, and raise SettingsError unless
    a scheduler with workers answers. The Client's own timeout covers the connection, not
    the handshake after it: a server that accepts TCP but is not a scheduler (the
    dashboard's port, any HTTP server) kept the run waiting for good."""
    import asyncio

    from distributed.comm import connect

    async def identity() -> Any:
        comm = await connect(address, timeout=timeout_s)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    try:
        reply = asyncio.run(asyncio.wait_for(identity(), timeout_s))
    except OSError as exc:  # refused, unreachable, timed out (TimeoutError), closed on us
        why = " ".join(str(exc).split())[:200] or f"no answer within {timeout_s:g} s"
        raise SettingsError(
            f"cannot reach the Dask scheduler at {address} ({why}); "
            "check --scheduler and that the scheduler is running"
        ) from None
    except Exception as exc:  # it answered in another protocol
        raise SettingsError(
            f"--scheduler {address}: is not a Dask scheduler ({type(exc).__name__}); check the "
            "address (the scheduler's port, 8786 by default, not the dashboard's)"
        ) from None
    if not isinstance(reply, dict) or reply.get("type") != "Scheduler":
        raise SettingsError(
            f"--scheduler {address}: is not a Dask scheduler; check the address (the "
            "scheduler's port, 8786 by default, not the dashboard's)"
        )
    if not reply.get("workers"):
        raise SettingsError(
            f"--scheduler {address}: the scheduler has no workers; start some "
            f"(dask worker {address}) and rerun"
        )


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
    if backend not in BACKENDS:
        raise SettingsError(f"backend {backend!r} unknown; use one of {', '.join(BACKENDS)}")
    if backend == "dask" and scheduler:
        check_scheduler_address(scheduler)
        _check_scheduler(scheduler, DASK_CONNECT_TIMEOUT_S)
    start, stop = _frame_span(session, frames)
    n_jobs = effective_jobs(jobs)
    if n_jobs < jobs and not (backend == "dask" and scheduler):
        log.warning(
            "--jobs %d is more than the %d cores available; using %d", jobs, available_cores(), n_jobs
        )
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
    tip = ""
    refinement = None
    written: list[tuple[Path, int]] = []
    # Local workers tell the bar of each frame as they finish it (a range's results
    # come back whole): one byte each, appended to a file of this run's.
    tally = _new_tally() if progress and backend != "dask" else None
    # Shown from here on, while the workers start and the model is built, not only from
    # the first results.
    bar = _progress_bar(stop - start, progress, elapsed_s=time.perf_counter() - t0, tally=tally)
    try:
        with bar:
            if backend == "loky":
                # Local workers start now (unless the command line started them already): they
                # spawn and import the per-frame modules while the parent builds the model.
                start_local_workers(n_jobs)
            if frame_fn is None:
                from ..calibrate.refine import refined_cameras
                from ..reconstruct.model import build_model
                from ..reconstruct.tip_shape import with_session_tip

                model: Any = build_model(session)
                cameras, refinement = refined_cameras(model, session.video_paths, start, stop)
                if cameras is not session.cameras:
                    session = dataclasses.replace(session, cameras=cameras)
                    model = build_model(session)
                model, choice = with_session_tip(model, session.video_paths, start, stop)
                tip = choice.describe() if choice is not None else ""
            else:
                model = session  # a replacement frame function gets the session as its model
            with _backend(backend, scheduler, n_jobs, model) as (n_workers, shared):

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
                )
                for span, outputs in results:
                    if isinstance(outputs, str):  # a range given up: its frames fail
                        outputs = _failed_range(span, outputs)
                    for out in outputs:
                        writer.write(out)
                        done += 1
                        _advance(bar, done)
        assert writer is not None
        writer.finish()
        if frame_fn is None:
            from ..calibrate.refine import remove_refined_calibration, write_refined_calibration

            path = target.out_dir / f"{target.name}.calibration.toml"
            if refinement is not None and refinement.applied:
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
                f"interrupted after {done} of {stop - start} frames; temporary files removed, "
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
        outputs=summary.outputs + written,
    )


# The URL schemes of Dask's transports (distributed.comm); an address without one is tcp.
_SCHEDULER_SCHEMES = ("tcp", "tls", "ucx", "ws", "wss")


def check_scheduler_address(address: str) -> None:
    """Refuse, before any work, a ``--scheduler`` that cannot be a scheduler's address."""
    scheme, sep, rest = address.partition("://")
    if not sep:
        scheme, rest = "tcp", address
    host, colon, port = rest.rpartition(":")
    if scheme in _SCHEDULER_SCHEMES and colon and host and port.isdigit() and 0 < int(port) < 65536:
        return
    hint = " (http serves the dashboard, not the scheduler)" if scheme in ("http", "https") else ""
    raise SettingsError(
        f"--scheduler {address!r}: not a Dask scheduler address{hint}; give tcp://HOST:PORT "
        "(the scheduler's port, 8786 by default)"
    )


def _frame_span(session: Session, frames: tuple[int, int | None] | None) -> tuple[int, int]:
    n = session.frame_count
    if frames is None:
        return 0, n
    start, stop = frames
    stop = n if stop is None else min(stop, n)
    if not 0 <= start < stop:
        raise SessionError(
            f"{session.directory}: --frames {start}:{frames[1] or ''} selects no frame "
            f"(the session has {n} frames, 0-{n - 1})"
        )
    return start, stop


def _progress_bar(total: int, enabled: bool, *, elapsed_s: float = 0.0, tally: Path | None = None) -> Any:
    """A tqdm bar of ``total`` frames on stderr (frames/s and time left), its clock started
    ``elapsed_s`` ago, redrawn every PROGRESS_REDRAW_S until it is closed; moved on by
    the bytes the workers append to ``tally`` (one per frame done) as well as by the
    frames written."""
    from tqdm import tqdm

    bar = tqdm(
        total=total, unit="frame", file=sys.stderr, disable=not enabled, dynamic_ncols=True, smoothing=0.1
    )
    if enabled:
        bar.start_t -= elapsed_s  # tqdm's own clock (time.time) counts from its creation
        bar.refresh()
        # Frames arrive a range at a time: without redraws the clock would stand still
        # while the workers start and reconstruct their first ranges.
        threading.Thread(target=_redraw, args=(bar, tally), daemon=True, name="progress-redraw").start()
    return bar


def _new_tally() -> Path:
    handle, name = tempfile.mkstemp(prefix="pipeline-progress-")
    os.close(handle)
    return Path(name)


def _advance(bar: Any, done: int) -> None:
    """Move ``bar`` on to ``done`` frames (never back: the workers' tally may be ahead)."""
    with bar.get_lock():
        if done > bar.n and not bar.disable:
            bar.update(min(done, bar.total) - bar.n)


def _redraw(bar: Any, tally: Path | None) -> None:
    while True:
        time.sleep(PROGRESS_REDRAW_S)
        if tally is not None:
            with contextlib.suppress(OSError):
                _advance(bar, tally.stat().st_size)
        with bar.get_lock():  # the lock close() takes to draw the last line: no redraw after it
            if bar.disable:  # closed
                return
            bar.refresh(nolock=True)
