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
import os
import shutil
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, TypeVar

from .errors import SettingsError

T = TypeVar("T")

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


def _exit_with_parent(parent_pid: int) -> None:
    """Loky worker initializer: exit when the run's process is gone.

    A run killed outright (SIGKILL, an out-of-memory kill of the parent) cannot stop its
    workers, and loky's own idle timeout does not fire while a worker waits on a queue
    its siblings still hold open: they ran on for hours, ~150 MB each.
    """

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(_PARENT_CHECK_S)
        os._exit(1)

    threading.Thread(target=watch, name="pipeline-parent-watch", daemon=True).start()


def loky_options() -> dict[str, Any]:
    """joblib's loky backend options for every pool of a run (the same ones, so that a
    run reuses the workers started ahead)."""
    return {"initializer": _exit_with_parent, "initargs": (os.getpid(),)}


def _import_frame_modules() -> None:
    from . import reconstruct  # noqa: F401


def start_local_workers(n_workers: int) -> None:
    """Start ``n_workers`` loky workers importing the per-frame modules, and return at once.

    Does nothing for fewer than two workers (one runs in the calling process) or when
    as many are already starting.
    """
    global _warm_up, _warm_up_workers
    if n_workers < 2 or (_warm_up is not None and _warm_up_workers == n_workers):
        return
    from joblib import Parallel, delayed, parallel_config

    with parallel_config(backend="loky", **loky_options()):
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
    if executor is not None:
        with contextlib.suppress(Exception):
            executor.shutdown(wait=True, kill_workers=True)


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

    folder = _shared_folder()
    _remove_dead_runs_models(folder)
    with tempfile.TemporaryDirectory(prefix=f"{_MODEL_PREFIX}{os.getpid()}-", dir=folder) as tmp:
        path = Path(tmp) / "model.joblib"
        joblib.dump(obj, path)
        yield joblib.load(path, mmap_mode="r")


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
