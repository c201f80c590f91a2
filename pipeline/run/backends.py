"""Where frame ranges run: joblib's loky or threading backend on this machine, or a Dask cluster.

:func:`parallel_backend` yields the job count and joblib's parallel backend for a run, starting a
local Dask cluster or connecting to a scheduler (checked first, within
``DASK_CONNECT_TIMEOUT_S``), and closes what it started.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator
from typing import Any

from ..errors import SettingsError
from .interrupts import deferred_signals, signals_blocked_in_children
from .workers import (
    loky_options,
    shared_with_local_workers,
)

log = logging.getLogger(__name__)

BACKENDS = ("loky", "threading", "dask")
DASK_CONNECT_TIMEOUT_S = 10
# The loggers that distributed configures, each with a level of its own.
_DASK_LOGGERS = ("distributed", "distributed.client", "distributed.gc", "tornado", "tornado.application")


@contextlib.contextmanager
def parallel_backend(
    backend: str, scheduler: str | None, n_jobs: int, model: Any
) -> Iterator[tuple[int, Any]]:
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
    # distributed logs ~45 INFO lines while a cluster starts, and warnings and errors as an
    # interrupted one stops (cancelled tasks, workers killed, the clients that joblib opens
    # in each worker finding the scheduler gone), in this process and in its workers: the
    # run's own lines say what matters. The workers read the variable as they start.
    quiet = not log.isEnabledFor(logging.DEBUG)
    if quiet:
        os.environ.setdefault("DASK_LOGGING", repr(dict.fromkeys(_DASK_LOGGERS, "critical")))
    from distributed import Client, LocalCluster

    if quiet:  # in case distributed was imported, and its logging set up, before
        for name in _DASK_LOGGERS:
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


def check_scheduler(address: str, timeout_s: float) -> None:
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
