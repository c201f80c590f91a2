"""The command line's way out: the run's exit status, without the interpreter's teardown."""

from __future__ import annotations

import atexit
import contextlib
import os
import signal
import sys
import threading
from typing import NoReturn

from ..run.interrupts import INTERRUPT_SIGNALS


def exit_fast(code: int) -> NoReturn:
    """Exit with status ``code`` without the interpreter tearing down every module: after a
    run that imported NumPy, SciPy, OpenCV, PyAV and Rerun that teardown alone takes ~0.3 s,
    and it has nothing left to do. The outputs are closed by then. The rest of a normal exit
    happens as usual, in its order: threading's own shutdown (its exit hooks, which stop
    pools such as joblib's worker manager, then the join of every non-daemon thread), the
    exit handlers (joblib's temporary folders, logging), the streams flushed."""
    # threading._shutdown is what the interpreter itself calls first at exit; joining the
    # threads without its hooks would wait forever on a pool's manager thread.
    # The run is over: a signal now (Ctrl-C just as it ends) has nothing left to stop, and
    # raised inside threading's shutdown or an exit handler it would print a traceback.
    for sig in INTERRUPT_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    threading._shutdown()  # type: ignore[attr-defined]
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError, AttributeError):  # closed by the reader
            stream.flush()
    os._exit(code)
