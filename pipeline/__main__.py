import atexit
import os
import sys
import threading

from .cli import main


def _exit(code: int) -> None:
    """Exit without the interpreter tearing down every module: after a run that imported
    NumPy, SciPy, OpenCV, PyAV and Rerun that teardown alone takes ~0.3 s, and it has
    nothing left to do. The outputs are closed by then. The rest of a normal exit
    happens as usual, in its order: threading's own shutdown (its exit hooks, which stop
    pools such as joblib's worker manager, then the join of every non-daemon thread),
    the exit handlers (joblib's temporary folders, logging), the streams flushed."""
    # threading._shutdown is what the interpreter itself calls first at exit; joining the
    # threads without its hooks would wait forever on a pool's manager thread.
    threading._shutdown()  # type: ignore[attr-defined]
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


_exit(main(prog="python -m pipeline"))
