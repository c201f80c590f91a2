"""A signal whose KeyboardInterrupt Python drops (raised inside a __del__ or a garbage-collector
callback) still stops a run: the run's loop raises it again."""

from __future__ import annotations

import os
import signal
import sys
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
