"""Local workers: started ahead of a run, reused by it, never left behind."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import tempfile
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import psutil
import pytest
from joblib import Parallel, delayed, parallel_config

from pipeline.cli import EXIT_BAD_INPUT, main
from pipeline.errors import SettingsError
from pipeline.run import workers


def _loky_workers() -> list[psutil.Process]:
    """Live loky worker processes of this test process (not loky's resource tracker)."""
    found = []
    for p in psutil.Process().children(recursive=True):
        with contextlib.suppress(psutil.Error):
            cmdline = " ".join(p.cmdline())
            if p.is_running() and "loky" in cmdline and "resource_tracker" not in cmdline:
                found.append(p)
    return found


@pytest.fixture(autouse=True)
def _no_workers_left() -> Iterator[None]:
    yield
    workers.release_local_workers()


@pytest.mark.parametrize(
    ("jobs", "expected"), [(1, 1), (3, 3), (0, 1), (-1, 4), (-2, 3), (-9, 1), (5, 4), (1000, 4)]
)
def test_effective_jobs_counts_like_joblib_up_to_the_cores(
    monkeypatch: pytest.MonkeyPatch, jobs: int, expected: int
) -> None:
    monkeypatch.setattr(workers, "available_cores", lambda: 4)
    assert workers.effective_jobs(jobs) == expected


def test_the_run_reuses_the_workers_started_ahead() -> None:
    workers.start_local_workers(2)
    workers.wait_for_local_workers()
    started = {p.pid for p in _loky_workers()}
    assert len(started) == 2
    # The run's pools use the same loky options, which is what lets them reuse the workers.
    with parallel_config(backend="loky", **workers.loky_options()):
        pids = Parallel(n_jobs=2)(delayed(os.getpid)() for _ in range(8))
    assert set(pids) <= started


def test_one_worker_starts_no_process() -> None:
    workers.release_local_workers()
    psutil.wait_procs(_loky_workers(), timeout=10)
    workers.start_local_workers(1)
    workers.wait_for_local_workers()
    assert not _loky_workers()


def test_workers_started_for_a_session_that_does_not_load_are_killed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The command line starts the workers before it reads the session: a bad
    # session must not leave them running, nor add a warning to its one-line error.
    session = str(tmp_path / "missing")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert main(["process", session, "--jobs", "2", "--out", str(tmp_path)]) == EXIT_BAD_INPUT
    assert "missing" in capsys.readouterr().err
    assert not [str(w.message) for w in caught]
    _, alive = psutil.wait_procs(_loky_workers(), timeout=10)
    assert not alive


def _backing_file(array: np.ndarray) -> str | None:
    return getattr(array, "filename", None)


def test_a_shared_model_is_mapped_by_the_workers_from_one_file_removed_afterwards() -> None:
    model = {"voxels": np.arange(1_000_000, dtype=np.int32), "name": "demo"}
    with workers.shared_with_local_workers(model) as shared:
        assert shared["name"] == "demo"
        np.testing.assert_array_equal(shared["voxels"], model["voxels"])
        path = Path(_backing_file(shared["voxels"]) or "")
        assert path.is_file()
        # Passed by reference: the workers map this very file, not a copy of their own.
        seen = Parallel(n_jobs=2, backend="loky")(delayed(_backing_file)(shared["voxels"]) for _ in range(4))
        assert {Path(f or "") for f in seen} == {path}
    workers.release_local_workers()
    assert not path.exists()


def test_the_shared_model_goes_where_joblib_would_put_its_own(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    model = {"voxels": np.zeros(10, np.int32)}
    monkeypatch.setenv("JOBLIB_TEMP_FOLDER", str(tmp_path))
    with workers.shared_with_local_workers(model) as shared:
        assert Path(_backing_file(shared["voxels"]) or "").parent.parent == tmp_path
    # No shared-memory folder (or one without room): the system's temporary folder.
    monkeypatch.delenv("JOBLIB_TEMP_FOLDER")
    monkeypatch.setattr(workers, "_SHARED_MEMORY_DIR", tmp_path / "no-such-folder")
    with workers.shared_with_local_workers(model) as shared:
        folder = Path(_backing_file(shared["voxels"]) or "").parent.parent
        assert folder == Path(tempfile.gettempdir())


def test_a_missing_joblib_temp_folder_is_named(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("JOBLIB_TEMP_FOLDER", str(tmp_path / "gone"))
    with pytest.raises(
        SettingsError, match=r"JOBLIB_TEMP_FOLDER=.*gone: is not a writable folder; create it"
    ):
        with workers.shared_with_local_workers({"a": np.zeros(3)}):
            pass


def test_a_joblib_temp_folder_without_room_is_named(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import errno

    import joblib

    def full(obj: object, path: object) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setenv("JOBLIB_TEMP_FOLDER", str(tmp_path))
    monkeypatch.setattr(joblib, "dump", full)
    with pytest.raises(
        SettingsError, match=r"JOBLIB_TEMP_FOLDER=.*: cannot hold the session's model .*No space"
    ):
        with workers.shared_with_local_workers({"a": np.zeros(3)}):
            pass
    assert not list(tmp_path.iterdir())  # its folder for the model removed


def test_the_shared_model_of_a_killed_run_is_removed_by_the_next(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("JOBLIB_TEMP_FOLDER", str(tmp_path))
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    )
    stale = tmp_path / f"pipeline-model-{int(dead.stdout)}-abc"  # that process has exited
    live = tmp_path / f"pipeline-model-{os.getpid()}-abc"  # this one has not
    for folder in (stale, live):
        folder.mkdir()
        (folder / "model.joblib").write_bytes(b"x" * 100)
    with workers.shared_with_local_workers({"a": np.zeros(3)}):
        assert not stale.exists() and live.exists()


# A parent killed outright (SIGKILL, the OOM killer) while its workers are busy: each is
# in a task that would run for ten minutes.
_KILLED_PARENT = """
import os, signal, time
import psutil
from joblib import Parallel, delayed, parallel_config
from pipeline.run import workers
with parallel_config(backend="loky", **workers.loky_options()):
    tasks = Parallel(n_jobs=2, return_as="generator_unordered")(delayed(time.sleep)(600) for _ in range(2))
    time.sleep(3)  # both workers started and asleep in their task
    print(" ".join(str(p.pid) for p in psutil.Process().children() if "resource_tracker" not in
          " ".join(p.cmdline())), flush=True)
    os.kill(os.getpid(), signal.SIGKILL)
"""


@pytest.mark.slow
def test_workers_exit_when_their_parent_is_killed() -> None:
    proc = subprocess.run([sys.executable, "-c", _KILLED_PARENT], capture_output=True, text=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    pids = [int(pid) for pid in proc.stdout.split()]
    assert len(pids) == 2
    orphans = [psutil.Process(pid) for pid in pids if psutil.pid_exists(pid)]
    # Generous: they notice within about a second; this only guards against them staying.
    _, alive = psutil.wait_procs(orphans, timeout=30)
    for p in alive:
        p.kill()
    assert not alive


def test_the_stuck_pools_results_pipe_is_forgotten_before_it_is_closed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # loky's manager thread wakes as the descriptor closes and closes the same end: it must
    # find the connection closed already, not close the descriptor a second time (EBADF).
    import multiprocessing

    reader, writer = multiprocessing.Pipe(duplex=False)
    descriptor = writer.fileno()
    handle_at_close: list[object] = []  # the connection's handle as its descriptor closes
    real_close = os.close

    def close(fd: int) -> None:
        if fd == descriptor:  # another thread's closes (a pool's, a viewer's) are not this one
            handle_at_close.append(writer._handle)  # type: ignore[attr-defined]
        real_close(fd)

    monkeypatch.setattr(workers.os, "close", close)
    workers._close_before_the_manager(writer)
    monkeypatch.undo()
    assert handle_at_close == [None]
    assert writer.closed
    writer.close()  # the manager's close: nothing left to close
    with pytest.raises(EOFError):
        reader.recv_bytes()
    reader.close()


def test_a_pool_failure_is_described_in_whole_sentences_on_one_line() -> None:
    # Dask's message for a cluster that lost its workers breaks its line mid-sentence.
    exc = OSError(
        "Timed out trying to connect to tcp://127.0.0.1:8786 after 30 s; increase the\n"
        "joblib/dask connection timeout with:\n"
        "    dask.config.set({'distributed.comm.timeouts.connect': '60s'})"
    )
    line = workers.describe_pool_failure(exc)
    assert "\n" not in line and line.startswith("OSError: Timed out trying to connect")
    assert "connection timeout with: dask.config.set(" in line
