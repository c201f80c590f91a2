import atexit
import os
import sys
import threading

from .cli import main


def _exit(code: int) -> None:
    """Exit without the interpreter tearing down every module: after a run that imported
    NumPy, SciPy, OpenCV, PyAV and Rerun that teardown alone takes ~0.3 s, and it has
    nothing left to do. The outputs are closed by then; other threads are joined, the
    exit handlers run (joblib's temporary folders, logging) and the streams are flushed
    as at a normal exit."""
    for thread in threading.enumerate():
        if thread is not threading.main_thread() and not thread.daemon:
            thread.join()
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


_exit(main())
