"""The progress bar of a run: frames done, redrawn at most every ``PROGRESS_REDRAW_S``."""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

PROGRESS_REDRAW_S = 0.5


def progress_bar(total: int, enabled: bool, *, elapsed_s: float = 0.0, tally: Path | None = None) -> Any:
    """A tqdm bar of ``total`` frames on stderr (frames/s and time left), its clock started
    ``elapsed_s`` ago, redrawn every PROGRESS_REDRAW_S until it is closed; moved on by
    the bytes the workers append to ``tally`` (one per frame done) as well as by the
    frames written."""
    from tqdm import tqdm

    bar = tqdm(
        total=total, unit="frame", file=sys.stderr, disable=not enabled, dynamic_ncols=True, smoothing=0.1
    )
    if enabled:
        bar.start_t -= elapsed_s  # tqdm's own clock (time.time) counts from its creation
        bar.refresh()
        # Frames arrive a range at a time: without redraws the clock would stand still
        # while the workers start and reconstruct their first ranges.
        threading.Thread(target=_redraw, args=(bar, tally), daemon=True, name="progress-redraw").start()
    return bar


def new_tally() -> Path:
    handle, name = tempfile.mkstemp(prefix="pipeline-progress-")
    os.close(handle)
    return Path(name)


def advance(bar: Any, done: int) -> None:
    """Move ``bar`` on to ``done`` frames (never back: the workers' tally may be ahead)."""
    with bar.get_lock():
        if done > bar.n and not bar.disable:
            bar.update(min(done, bar.total) - bar.n)


def _redraw(bar: Any, tally: Path | None) -> None:
    while True:
        time.sleep(PROGRESS_REDRAW_S)
        if tally is not None:
            with contextlib.suppress(OSError):
                advance(bar, tally.stat().st_size)
        with bar.get_lock():  # the lock close() takes to draw the last line: no redraw after it
            if bar.disable:  # closed
                return
            bar.refresh(nolock=True)
