"""The same ranges on a Dask cluster give the same recordings as a local loky run."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import build_session

from pipeline.record.load import load_recording
from pipeline.run.runner import process_session
from pipeline.session.folder import load_session

distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def cluster() -> Iterator[object]:
    with distributed.LocalCluster(
        n_workers=2, processes=True, threads_per_worker=1, dashboard_address=None
    ) as local_cluster:
        yield local_cluster


@pytest.mark.slow
def test_dask_cluster_run_equals_the_local_run(cluster: object, tmp_path: Path) -> None:
    session = load_session(build_session(tmp_path / "dask", frames=10, empty_frames={4}))
    options: dict[str, Any] = {"images": False, "progress": False}
    local = process_session(session, out_dir=tmp_path / "loky", jobs=2, backend="loky", **options)
    remote = process_session(
        session,
        out_dir=tmp_path / "dask_out",
        backend="dask",
        scheduler=cluster.scheduler_address,  # type: ignore[attr-defined]
        **options,
    )
    assert (remote.frames_ok, remote.frames_empty, remote.frames_failed) == (
        local.frames_ok,
        local.frames_empty,
        local.frames_failed,
    )
    assert local.frames_ok > 0
    a = load_recording(tmp_path / "loky" / "dask.mcap")
    b = load_recording(tmp_path / "dask_out" / "dask.mcap")
    np.testing.assert_array_equal(a.frame_indices, b.frame_indices)
    np.testing.assert_array_equal(a.timestamps_ns, b.timestamps_ns)
    np.testing.assert_array_equal(a.statuses, b.statuses)
    # The same code on the same frames: identical numbers, NaN rows included.
    np.testing.assert_array_equal(a.centerlines_m, b.centerlines_m)
    for pa, pb in zip(a.points_m, b.points_m, strict=True):
        np.testing.assert_array_equal(pa, pb)

    def without_timings(metrics: list[dict]) -> list[dict]:
        return [{k: v for k, v in m.items() if k != "timings_s"} for m in metrics]

    assert without_timings(a.metrics) == without_timings(b.metrics)


def test_an_unreachable_scheduler_is_a_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from pipeline.errors import PipelineError
    from pipeline.run import runner

    monkeypatch.setattr(runner, "DASK_CONNECT_TIMEOUT_S", 1)  # a refused port needs no 10 s
    session = load_session(build_session(tmp_path / "s", frames=2))
    with pytest.raises(PipelineError, match=r"cannot reach the Dask scheduler at tcp://127\.0\.0\.1:9 "):
        process_session(session, out_dir=tmp_path / "out", backend="dask", scheduler="tcp://127.0.0.1:9")
    assert not (tmp_path / "out").exists()  # checked before any work: nothing written
