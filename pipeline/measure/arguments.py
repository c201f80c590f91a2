"""The measuring tools' command lines (`accuracy_table`, `bench`): argument types, one-line
usage errors, and a stop by Ctrl-C, SIGTERM or SIGHUP said in one line."""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NoReturn

from ..run.interrupts import signals_interrupt

# What a stopped run exits with (128 + SIGINT), as the pipeline's own commands.
EXIT_INTERRUPTED = 130


class OneLineParser(argparse.ArgumentParser):
    """argparse, with a usage mistake on one line (exit status 2) pointing to ``--help``; the
    pipeline's own commands' parser (``pipeline.cli.parser``) builds on it."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"error: {self.prog}: {message} (see {self.prog} --help)\n")


def at_least(lowest: int) -> Any:
    """An argparse type: an integer of at least ``lowest``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < lowest:
            raise argparse.ArgumentTypeError(f"must be {lowest} or more, got {value}")
        return value

    return parse


def worker_jobs(text: str) -> int:
    """An argparse type for --jobs: a count of workers (1, 2, ...) or, as joblib counts
    them, -1 for one per core, -2 for all cores but one, and so on; 0 is neither."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value == 0:
        raise argparse.ArgumentTypeError("0 workers cannot run; give 1 or more, or -1 for one per core")
    return value


def not_a_session(out: Path, what: str) -> str:
    """Why ``out`` cannot take ``what`` (it is a file, or a session's own folder, whose
    files it would mix with its own); "" where it can."""
    if out.exists() and not out.is_dir():
        return f"{out}: is a file; give --out a folder for {what}"
    if (out / "calibration.toml").is_file():
        return f"{out}: is a session's folder; give --out a folder of its own for {what}"
    return ""


@contextlib.contextmanager
def stopped_in_one_line(prog: str) -> Iterator[None]:
    """The pipeline's signal policy for the block (:func:`pipeline.run.interrupts.signals_interrupt`:
    Ctrl-C, SIGTERM and SIGHUP raise KeyboardInterrupt, so that temporary folders are
    removed on the way out), and a stop said in one line with exit status 130, not a
    traceback."""
    try:
        with signals_interrupt():
            yield
    except KeyboardInterrupt:
        print(f"error: {prog}: interrupted; its output is not written", file=sys.stderr)
        raise SystemExit(EXIT_INTERRUPTED) from None
