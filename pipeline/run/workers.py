"""The local worker processes of a run (loky): started as early as possible, handed the
model as one memory-mapped file, killed at the end.

Spawning a worker and importing the per-frame modules into it takes ~0.8 s, more
than the parent needs to load the session and build the model. So the command
line starts the workers first thing, before it imports anything heavy itself, and
the run picks them up: joblib keeps one reusable loky executor per process, which
the run's ``Parallel`` calls reuse as long as the number of workers matches.
Started at the top of ``pipeline process`` rather than after the model, the two
workers of the 900-frame demo start reconstructing 0.2-0.3 s sooner.

Only this module keeps state between calls (the warm-up tasks in flight): loky's
executor is one per process anyway.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import signal
import tempfile
import textwrap
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from ..errors import SettingsError
from ..reconstruct.frame_task import FrameMap, Frames, PerFrame, map_here
from .interrupts import signals_blocked_in_children

T = TypeVar("T")

log = logging.getLogger(__name__)

# Where the shared model's file goes, as joblib would put its own copy: in memory when
# the machine has a shared-memory folder with room to spare (containers often mount a
# small one), else in the temporary folder; JOBLIB_TEMP_FOLDER overrides both.
_SHARED_MEMORY_DIR = Path("/dev/shm")
_SHARED_MEMORY_MIN_FREE_BYTES = 2_000_000_000

# The warm-up tasks of the workers started ahead of the run, and how many workers.
_warm_up: Iterator[None] | None = None
_warm_up_workers = 0


# How often a worker checks that the run's process is still there.
_PARENT_CHECK_S = 1.0
# The shared model's folder: its name holds the run's process id, so that a later run
# can tell the folder of a run that was killed (SIGKILL) from one in use.
_MODEL_PREFIX = "pipeline-model-"


# How long a dead worker may go unnoticed by its pool before the run steps in. loky notices a
# death within milliseconds, except that of a worker killed while handing back its results
# (the OOM killer at the wrong moment): its pool then waits for good on the rest of the
# message. Seconds are plenty for the first; the second costs this long.
HANDBACK_TIMEOUT_S = 10.0
# The same for a pool being shut down (an interrupt, the end of a run), whose workers are
# killed and gone in milliseconds: an interrupt should not wait long.
_SHUTDOWN_GRACE_S = 2.0
# How often the watch looks at the pool.
_WATCH_S = 0.25

# The watch over the local pool (started with the workers, stopped with them).
_watch_stop: threading.Event | None = None
# Set when the watch has ended a stuck pool, until describe_pool_failure has said so.
_ended_stuck_pool = False


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity, which containers and taskset narrow)."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def effective_jobs(jobs: int) -> int:
    """Number of workers for ``jobs`` as joblib counts them (-1 = one per core, -2 = all but
    one, ...), at most one per core: more only cost memory (each holds its own imports and
    buffers), and ``--jobs 1000`` started hundreds of processes before any check."""
    cpus = available_cores()
    return max(1, cpus + 1 + jobs) if jobs < 0 else max(1, min(jobs, cpus))


def exit_with_parent(parent_pid: int) -> None:
    """In a worker process (loky's initializer, live's restart worker): exit when the run's
    process ``parent_pid`` is gone.

    A run killed outright (SIGKILL, an out-of-memory kill of the parent) cannot stop its
    workers, and loky's own idle timeout does not fire while a worker waits on a queue
    its siblings still hold open: they ran on for hours, ~150 MB each, holding the run's
    stdout and stderr open (a pipe reading them never ended).
    """

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(_PARENT_CHECK_S)
        os._exit(1)

    threading.Thread(target=watch, name="pipeline-parent-watch", daemon=True).start()


def loky_options() -> dict[str, Any]:
    """joblib's loky backend options for every pool of a run (the same ones, so that a
    run reuses the workers started ahead)."""
    return {"initializer": exit_with_parent, "initargs": (os.getpid(),)}


def _import_frame_modules() -> None:
    from ..reconstruct import frame  # noqa: F401


def start_local_workers(n_workers: int) -> None:
    """Start ``n_workers`` loky workers importing the per-frame modules, and return at once.

    Does nothing for fewer than two workers (one runs in the calling process) or when
    as many are already starting.
    """
    global _warm_up, _warm_up_workers
    if n_workers < 2 or (_warm_up is not None and _warm_up_workers == n_workers):
        return
    _start_watch()
    from joblib import Parallel, delayed, parallel_config

    with parallel_config(backend="loky", **loky_options()), signals_blocked_in_children():
        parallel = Parallel(n_jobs=n_workers, return_as="generator_unordered")
        # Held until wait_for_local_workers: a generator dropped unfinished aborts its pool.
        _warm_up = iter(parallel(delayed(_import_frame_modules)() for _ in range(n_workers)))
    _warm_up_workers = n_workers


def wait_for_local_workers() -> None:
    """Return once the workers started by :func:`start_local_workers` are ready (at once if none)."""
    global _warm_up
    for _ in _warm_up or ():
        pass
    _warm_up = None


def release_local_workers() -> None:
    """Stop the worker processes at once.

    They hold the memory-mapped model (hundreds of MB for fine grids) and would
    otherwise idle for minutes; and a later run in the same process (another session,
    a changed environment) should start from fresh workers, not inherit these. They
    are killed rather than asked to exit: after a run they are idle (every result is
    in), and their interpreters' orderly teardown took ~0.1 s at the end of each run
    for nothing; after a failure or Ctrl-C their work is no longer wanted.
    """
    global _warm_up
    if _warm_up is not None:
        # A run that never started (a session that does not load): its workers are still
        # importing. They are let finish (under a second) rather than killed with the
        # warm-up tasks in flight, which races loky's manager thread (a KeyError
        # traceback from that thread on stderr, below the one-line error).
        with contextlib.suppress(Exception):
            wait_for_local_workers()
        _warm_up = None
    from joblib.externals.loky import reusable_executor

    executor = getattr(reusable_executor, "_executor", None)  # loky keeps one per process
    pool = _current_pool()  # taken first: the shutdown drops the executor's references
    if executor is not None:
        with contextlib.suppress(Exception):
            executor.shutdown(wait=False, kill_workers=True)
    if pool is not None:
        # loky's own shutdown(wait=True) waits for good on a pool stuck on a dead
        # worker's results: wait a bounded time, then end the pool as the watch does.
        pool.manager.join(_SHUTDOWN_GRACE_S)
        if pool.manager.is_alive():
            _end_stuck_pool(pool)
            pool.manager.join(_SHUTDOWN_GRACE_S)
    _stop_watch()


@dataclass(frozen=True)
class _Pool:
    """What the watch needs of loky's executor: its manager thread (which collects the
    results), its worker processes, and this process's end of the results' pipe."""

    manager: threading.Thread
    processes: list[Any]
    result_writer: Any
    shutting_down: bool


def _current_pool() -> _Pool | None:
    """The local pool of this process, if one is running (loky's private attributes)."""
    from joblib.externals.loky import reusable_executor

    executor = getattr(reusable_executor, "_executor", None)
    manager = getattr(executor, "_executor_manager_thread", None)
    results = getattr(executor, "_result_queue", None)
    processes = getattr(executor, "_processes", None)
    if manager is None or results is None or processes is None:
        return None
    try:
        shutting_down = bool(executor._flags.shutdown)  # type: ignore[union-attr]
        return _Pool(manager, list(processes.values()), results._writer, shutting_down)
    except (AttributeError, RuntimeError):  # changed under us: look again at the next tick
        return None


def _has_exited(process: Any) -> bool:
    """Whether a worker process has ended, read from its sentinel: unlike ``exitcode``,
    this does not reap it (loky's manager thread does that, and would wait on a reaped one)."""
    from multiprocessing.connection import wait

    try:
        return bool(wait([process.sentinel], timeout=0))
    except (OSError, ValueError, AttributeError):  # closed: loky has let it go already
        return False


def _end_stuck_pool(pool: _Pool) -> None:
    """End a pool whose manager thread waits for the rest of a result that a dead worker
    was handing back (a message cut short in the results' pipe, which the other workers
    and this process still hold open): kill the workers, then close this process's end,
    so that the manager reads the end of the pipe, marks the pool broken and fails its
    tasks (BrokenProcessPool) as it does for any dead worker."""
    global _ended_stuck_pool
    _ended_stuck_pool = True
    from multiprocessing.connection import wait

    for process in pool.processes:
        if not _has_exited(process):  # the dead are not reaped yet: their ids are still theirs
            with contextlib.suppress(OSError):
                os.kill(process.pid, signal.SIGKILL)  # loky's processes have no kill()
    deadline = time.monotonic() + _SHUTDOWN_GRACE_S
    for process in pool.processes:
        with contextlib.suppress(Exception):
            wait([process.sentinel], timeout=max(0.0, deadline - time.monotonic()))
    _close_before_the_manager(pool.result_writer)


def _close_before_the_manager(connection: Any) -> None:
    """Close this process's end of the results' pipe so that loky's manager thread, which
    wakes on it and closes the same end as it tears the broken pool down, finds it closed.

    ``Connection.close`` closes the descriptor before it forgets it: a manager woken in
    between would close it a second time (OSError EBADF, a traceback from its thread on
    stderr). The handle is forgotten first here.
    """
    handle, connection._handle = getattr(connection, "_handle", None), None
    if handle is not None:
        with contextlib.suppress(OSError):
            os.close(handle)


def _watch(stop: threading.Event) -> None:
    """Until ``stop`` is set: end the local pool if one of its workers has been dead for
    HANDBACK_TIMEOUT_S (_SHUTDOWN_GRACE_S once the pool is being shut down) while the pool
    still runs (see :func:`_end_stuck_pool`). A pool that notices a death itself, or
    kills its workers, takes them out of its list at once."""
    stuck: tuple[threading.Thread, float] | None = None  # (the pool's manager, since when)
    while not stop.wait(_WATCH_S):
        pool = _current_pool()
        if pool is None or not pool.manager.is_alive() or not any(map(_has_exited, pool.processes)):
            stuck = None
            continue
        if stuck is None or stuck[0] is not pool.manager:
            stuck = (pool.manager, time.monotonic())
        bound = _SHUTDOWN_GRACE_S if pool.shutting_down else HANDBACK_TIMEOUT_S
        if time.monotonic() - stuck[1] > bound:
            log.debug("a worker died handing back its results; ending its pool")
            _end_stuck_pool(pool)
            stuck = None


def _start_watch() -> None:
    global _watch_stop, _ended_stuck_pool
    if _watch_stop is None:
        _ended_stuck_pool = False
        _watch_stop = threading.Event()
        threading.Thread(target=_watch, args=(_watch_stop,), daemon=True, name="pipeline-pool-watch").start()


def _stop_watch() -> None:
    global _watch_stop
    if _watch_stop is not None:
        _watch_stop.set()
        _watch_stop = None


def describe_pool_failure(exc: BaseException) -> str:
    """What broke a pool, for a warning line: the exception's name and its message on one
    line, shortened to whole words (a first line alone may stop mid-sentence: Dask's "...
    increase the joblib/dask connection timeout with:"), or, when the watch ended a stuck
    pool, that a worker died handing back its results (loky's own words for that, "A result
    has failed to un-serialize", mislead)."""
    global _ended_stuck_pool
    if _ended_stuck_pool:
        _ended_stuck_pool = False
        return "a worker died while handing back its results"
    text = str(exc).strip()
    first = textwrap.shorten(" ".join(text.split()), 200) if text else ""  # whole words
    return f"{type(exc).__name__}: {first}" if first else type(exc).__name__


def local_frame_map(n_workers: int) -> FrameMap:
    """A :data:`~pipeline.reconstruct.frame_task.FrameMap` on the run's local workers (the
    pool :func:`start_local_workers` started): the frames dealt out in turn, one task per
    worker, the model shared once (:func:`shared_with_local_workers`); the results in the
    frames' order, the same as :func:`~pipeline.reconstruct.frame_task.map_here` gives.
    With fewer than two workers or frames, here."""

    def run(fn: PerFrame, frames: Frames, model: Any) -> list[Any]:
        if n_workers < 2 or len(frames) < 2:
            return map_here(fn, frames, model)
        from joblib import Parallel, delayed, parallel_config

        deals = [list(frames[k::n_workers]) for k in range(n_workers)]
        with (
            shared_with_local_workers(model) as shared,
            parallel_config(backend="loky", **loky_options()),
            signals_blocked_in_children(),
        ):
            parts = Parallel(n_jobs=n_workers)(delayed(map_here)(fn, deal, shared) for deal in deals)
        out: list[Any] = [None] * len(frames)
        for k, part in enumerate(parts):
            out[k::n_workers] = part
        return out

    return run


@contextlib.contextmanager
def shared_with_local_workers(obj: T) -> Iterator[T]:
    """``obj`` with its NumPy arrays memory-mapped, read-only, from one file that the
    workers map too instead of receiving copies; the file is removed on exit.

    joblib would memory-map large arguments by itself, but into a folder that it
    deletes at the end of each ``Parallel`` call, before handing over the last
    results, and that deletion races joblib's resource tracker and sleeps 0.1 s
    when it loses (it did in every 2-worker run of the demo). Arrays already backed
    by a file are passed to the workers by reference, so joblib has nothing to clean.
    """
    import joblib

    with shared_file(obj) as path:
        yield joblib.load(path, mmap_mode="r")


@contextlib.contextmanager
def shared_file(obj: object) -> Iterator[Path]:
    """The path of one file holding ``obj`` (``joblib.dump``), in the folder the workers
    share (shared memory where it has room); the file is removed on exit, and those of
    runs killed before they could remove theirs are removed first."""
    import joblib

    folder = _shared_folder()
    _remove_dead_runs_models(folder)
    with tempfile.TemporaryDirectory(prefix=f"{_MODEL_PREFIX}{os.getpid()}-", dir=folder) as tmp:
        path = Path(tmp) / "model.joblib"
        try:
            joblib.dump(obj, path)
        except OSError as exc:
            where = f"JOBLIB_TEMP_FOLDER={folder}" if "JOBLIB_TEMP_FOLDER" in os.environ else tmp
            raise SettingsError(
                f"{where}: cannot hold the session's model for the workers ({exc.strerror or exc}); "
                "free space there, or set JOBLIB_TEMP_FOLDER to a folder with room"
            ) from None
        yield path


def _remove_dead_runs_models(folder: str | None) -> None:
    """Remove the shared models of runs that were killed before they could (SIGKILL)."""
    base = Path(folder or tempfile.gettempdir())
    with contextlib.suppress(OSError):
        for entry in base.iterdir():
            pid = entry.name[len(_MODEL_PREFIX) :].partition("-")[0]
            if entry.name.startswith(_MODEL_PREFIX) and pid.isdigit() and not _alive(int(pid)):
                shutil.rmtree(entry, ignore_errors=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _shared_folder() -> str | None:
    """The folder for the shared model (None: the system's temporary folder)."""
    if "JOBLIB_TEMP_FOLDER" in os.environ:
        folder = os.environ["JOBLIB_TEMP_FOLDER"]
        if not os.path.isdir(folder) or not os.access(folder, os.W_OK):
            raise SettingsError(
                f"JOBLIB_TEMP_FOLDER={folder}: is not a writable folder; create it, or unset the "
                "variable to use the system's temporary folder"
            )
        return folder
    try:
        stats = os.statvfs(_SHARED_MEMORY_DIR)
    except (OSError, AttributeError):  # no such folder, or not a POSIX system
        return None
    roomy = stats.f_bsize * stats.f_bavail > _SHARED_MEMORY_MIN_FREE_BYTES
    return str(_SHARED_MEMORY_DIR) if roomy and os.access(_SHARED_MEMORY_DIR, os.W_OK) else None


@contextlib.contextmanager
def started_early(jobs: int, backend: str) -> Iterator[None]:
    """Start the run's local workers now (``backend`` "loky" only); kill them if the
    block fails before a run has taken them over (a session that does not load)."""
    if backend == "loky":
        start_local_workers(effective_jobs(jobs))
    try:
        yield
    except BaseException:
        release_local_workers()
        raise
