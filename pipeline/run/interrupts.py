"""One signal policy: SIGINT, SIGTERM and SIGHUP end a run as Ctrl-C does.

While :func:`signals_interrupt` is active (the command line holds it from the first
line of ``main`` to the last), each of the three raises KeyboardInterrupt in the main
thread, so that every ``finally`` on the way out runs: temporary files and the shared
model removed, workers stopped, one line and exit status 130. A signal that arrives
while the outputs are being renamed into place (:func:`deferred_signals`) is held until
the renames are done, so that the pair is never split; further signals once the run is
ending are ignored, so that the clean-up it started completes (each step of it is
bounded in time). Python drops an exception raised inside a garbage-collector callback
or a ``__del__`` ("Exception ignored in ..."), where a signal can land too; a run's main
loop therefore asks :func:`raise_if_interrupted` between its steps. Once a signal has
ended the run, a library's thread that fails as the run tears its pool down under it
(loky's manager thread on a pipe already closed) goes to the debug log, not to stderr
as a traceback below the run's one line.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Iterator
from types import FrameType, TracebackType

INTERRUPT_SIGNALS: tuple[signal.Signals, ...] = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name)
)

log = logging.getLogger(__name__)

_installed = False  # signals_interrupt is active
_interrupted = ""  # the signal turned into KeyboardInterrupt already ("": none)
_deferring = 0  # depth of deferred_signals blocks
_pending: int | None = None  # a signal received while deferring
_complete = False  # the run's outputs are in place (outputs_in_place)


def _interrupt(signum: int) -> None:
    global _interrupted
    _interrupted = signal.Signals(signum).name
    raise KeyboardInterrupt(_interrupted)


def raise_if_interrupted() -> None:
    """Raise KeyboardInterrupt again if a signal already raised one and the run goes on
    (Python dropped it: see the module docstring); nothing otherwise."""
    if _installed and _interrupted:
        raise KeyboardInterrupt(_interrupted)


def _handler(signum: int, frame: FrameType | None) -> None:
    global _pending
    if _complete:
        return
    if _deferring:
        _pending = _pending or signum
    elif not _interrupted:
        _interrupt(signum)


@contextlib.contextmanager
def signals_interrupt() -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP raise KeyboardInterrupt inside the block (main thread only).

    A signal the process was started with ignored (``nohup``, a background job's SIGINT)
    stays ignored: the user asked for that. Nested blocks share the outermost one's policy.
    """
    global _installed, _interrupted, _pending, _complete
    if _installed or threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {}
    for sig in INTERRUPT_SIGNALS:
        if signal.getsignal(sig) is not signal.SIG_IGN:
            previous[sig] = signal.signal(sig, _handler)
    _installed, _interrupted, _pending, _complete = True, "", None, False
    thread_hook = threading.excepthook

    def quiet_once_interrupted(args: threading.ExceptHookArgs) -> None:
        if _interrupted and not _through_our_code(args.exc_traceback):
            log.debug("%s failed as the run ended", args.thread, exc_info=args.exc_value)
        else:
            thread_hook(args)

    threading.excepthook = quiet_once_interrupted
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        threading.excepthook = thread_hook
        _installed, _complete = False, False


def _through_our_code(traceback: TracebackType | None) -> bool:
    """Whether a failure's ``traceback`` passes through this project's code."""
    while traceback is not None:
        if str(traceback.tb_frame.f_globals.get("__name__", "")).startswith("pipeline"):
            return True
        traceback = traceback.tb_next
    return False


def outputs_in_place() -> None:
    """The run's outputs are renamed into place: a signal from now on (one held while they
    were, or Ctrl-C as the run prints its summary) has nothing left to stop, and is
    ignored, so that the run ends as it would have, summary and exit status included
    (an interrupt's "interrupted; nothing written" would be untrue by then)."""
    global _complete, _pending
    if _installed:
        _complete, _pending = True, None


@contextlib.contextmanager
def deferred_signals() -> Iterator[None]:
    """Hold the signals of :func:`signals_interrupt` until the block is done, then raise."""
    global _deferring, _pending
    _deferring += 1
    try:
        yield
    finally:
        _deferring -= 1
        if not _deferring and _pending is not None:
            signum, _pending = _pending, None
            if not _interrupted:
                _interrupt(signum)


# The signals a terminal sends its whole foreground group (Ctrl-C, a hang-up) that the run's
# worker processes leave to the run: SIGTERM, which loky and distributed stop workers with,
# is not among them.
_LEFT_TO_THE_RUN = {getattr(signal, name) for name in ("SIGINT", "SIGHUP") if hasattr(signal, name)}


@contextlib.contextmanager
def signals_blocked_in_children() -> Iterator[None]:
    """Block SIGINT and SIGHUP in this thread inside the block, so that the processes and
    threads it starts (workers, the resource trackers) begin with them blocked, and keep
    them so.

    A terminal signals every process of its foreground group: on Ctrl-C, workers printed
    tracebacks ("Fatal Python error: init_import_site" from an interpreter still starting,
    KeyboardInterrupt from a Dask worker), and a hang-up killed the resource tracker, whose
    successor printed a KeyError per file it was asked to forget; while the run stops its
    workers anyway. The run's own process handles the signal: one that arrives meanwhile is
    taken by another of its threads, or waits for the block's end; it is not lost. Main
    thread only (a no-op elsewhere, and where the system has no signal masks).
    """
    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        yield
        return
    from multiprocessing import resource_tracker

    previous = signal.pthread_sigmask(signal.SIG_BLOCK, _LEFT_TO_THE_RUN)
    try:
        # Started now if not yet (the first worker would start it): its start unblocks
        # SIGINT in the calling thread (Python 3.11's ensure_running), so block again.
        resource_tracker.ensure_running()
        signal.pthread_sigmask(signal.SIG_BLOCK, _LEFT_TO_THE_RUN)
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)
