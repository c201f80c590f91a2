"""A signal whose KeyboardInterrupt Python drops (raised inside a __del__ or a garbage-collector
callback) still stops a run: the run's loop raises it again."""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time

import pytest

from pipeline.run.interrupts import raise_if_interrupted, signals_interrupt


class _SignalledWhileCollected:
    """Sends the process SIGTERM from its __del__, where Python drops what the handler raises."""

    def __del__(self) -> None:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.2)  # the handler runs here, inside __del__


def test_a_signal_dropped_inside_a_finaliser_is_raised_again(monkeypatch: pytest.MonkeyPatch) -> None:
    dropped: list[BaseException | None] = []
    monkeypatch.setattr(sys, "unraisablehook", lambda unraisable: dropped.append(unraisable.exc_value))
    with signals_interrupt():
        raise_if_interrupted()  # no signal yet: nothing
        _SignalledWhileCollected()  # collected at once; its KeyboardInterrupt is dropped
        assert len(dropped) == 1 and isinstance(dropped[0], KeyboardInterrupt)
        with pytest.raises(KeyboardInterrupt, match="SIGTERM"):
            raise_if_interrupted()
    raise_if_interrupted()  # outside the policy: nothing


class _LibraryThread(threading.Thread):
    """A library's thread: its code is its own run(), not a target of this project's."""

    def run(self) -> None:
        raise OSError(9, "Bad file descriptor")


def test_a_library_threads_failure_once_a_signal_ended_the_run_goes_to_the_debug_log(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    printed: list[str] = []
    monkeypatch.setattr(threading, "excepthook", lambda args: printed.append(args.thread.name))
    with signals_interrupt():
        before = _LibraryThread(name="before the signal")
        before.start()
        before.join()
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1.0)  # the handler raises here
        with caplog.at_level(logging.DEBUG, logger="pipeline.run.interrupts"):
            # raise_if_interrupted raises again in a thread of the project's own.
            ours = threading.Thread(target=raise_if_interrupted, name="ours")
            for thread in (_LibraryThread(name="library"), ours):
                thread.start()
                thread.join()
    assert printed == ["before the signal", "ours"]  # this project's own failures still show
    assert [r.exc_info[1].errno for r in caplog.records if r.exc_info and r.exc_info[1]] == [9]


def test_a_signal_once_the_outputs_are_in_place_is_ignored() -> None:
    # Ctrl-C as a run renames its outputs into place (held till the renames are done), or as
    # it prints its summary: the outputs are written, and the run ends as it would have.
    from pipeline.run.interrupts import deferred_signals, outputs_in_place

    with signals_interrupt():
        with deferred_signals():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.2)  # held
            outputs_in_place()  # the renames done: the held signal is dropped
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.2)
        raise_if_interrupted()  # nothing was raised, and nothing is pending
    with pytest.raises(KeyboardInterrupt), signals_interrupt():  # the next run's policy is whole again
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(1.0)
