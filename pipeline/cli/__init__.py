"""Command line: a thin layer over the library.

Each subcommand parses its arguments and calls one library function. A
:class:`PipelineError` becomes one line on stderr and exit status 2; anything
else is a bug: one line and exit status 3, its traceback only with ``--debug``.
Global options (``--debug``) are accepted before or after the subcommand. ``parser`` holds
the options, ``commands`` what each subcommand does, ``shutdown`` the way out. :func:`run`
is the program (the console script and ``python -m pipeline``); :func:`main` returns the
exit status instead of exiting.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
import traceback
from collections.abc import Callable, Sequence
from typing import NoReturn

from ..errors import Interrupted, PipelineError
from ..run.interrupts import signals_interrupt
from .commands import (
    EXIT_BAD_INPUT,
    EXIT_FRAMES_FAILED,
    EXIT_INTERNAL_ERROR,
    EXIT_OK,
    open_closed_std_streams,
    write_json_file,
)
from .parser import PROG, build_parser, with_json_before_a_folder, with_negative_frames
from .shutdown import exit_fast

__all__ = [
    "EXIT_BAD_INPUT",
    "EXIT_FRAMES_FAILED",
    "EXIT_INTERNAL_ERROR",
    "EXIT_OK",
    "PROG",
    "build_parser",
    "main",
    "run",
]

log = logging.getLogger("pipeline")


def run(prog: str = PROG) -> NoReturn:
    """The program: :func:`main` on the command line's words, then the exit with its status
    (:func:`~.shutdown.exit_fast`: no teardown of the modules, and a signal as the run ends
    ignored)."""
    exit_fast(main(prog=prog))


def main(argv: Sequence[str] | None = None, *, prog: str = PROG) -> int:
    open_closed_std_streams()
    try:
        os.getcwd()
    except FileNotFoundError:
        # Worker processes start in it (loky asks for it): every run would fail there.
        print("error: the current directory no longer exists; cd to a folder that does", file=sys.stderr)
        return EXIT_BAD_INPUT
    # SIGINT, SIGTERM and SIGHUP end the run the same way wherever they land: exit 130, one line.
    with signals_interrupt():
        try:
            return _main(argv, prog)
        except KeyboardInterrupt as exc:
            print(interrupted_line(exc), file=sys.stderr)
            return 130


def interrupted_line(exc: KeyboardInterrupt) -> str:
    """The line a run stopped by a signal ends with: what it leaves (see :class:`Interrupted`)."""
    return str(exc) if isinstance(exc, Interrupted) else "interrupted; nothing written"


def _main(argv: Sequence[str] | None, prog: str) -> int:
    parser = build_parser(prog)
    args = parser.parse_args(
        with_json_before_a_folder(with_negative_frames(sys.argv[1:] if argv is None else argv))
    )
    if getattr(args, "scheduler", None) and args.backend not in (None, "dask"):
        args.usage_error(f"--scheduler runs on a Dask cluster: drop --backend {args.backend}, or use dask")
    handler = logging.StreamHandler()
    if not args.debug:
        handler.addFilter(_own_records)
    logging.basicConfig(
        level=logging.DEBUG if args.debug else logging.INFO,
        format="%(levelname)s: %(message)s",
        handlers=[handler],
    )
    # Libraries' warnings and Rerun's own log lines (with colour codes even into a file) go
    # to --debug only: stderr carries the run's own lines.
    logging.captureWarnings(True)
    logging.getLogger("py.warnings").setLevel(logging.DEBUG if args.debug else logging.CRITICAL)
    if not args.debug:
        os.environ.setdefault("RUST_LOG", "off")
        _quiet_resource_trackers()
    if args.debug:
        # FFmpeg's own diagnostics (silenced in pipeline.session.video) help debug a damaged video.
        from ..session.video import show_ffmpeg_messages

        show_ffmpeg_messages()
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except KeyboardInterrupt as exc:
        _json_failure(args, interrupted_line(exc), 130)
        raise
    except PipelineError as exc:
        if args.debug:
            traceback.print_exc()
        line = f"error: {_one_line(exc)}"
        print(line, file=sys.stderr)
        _json_failure(args, line, EXIT_BAD_INPUT)
        return EXIT_BAD_INPUT
    except Exception as exc:
        # Not the user's mistake: a bug. One line by default, the traceback above it with
        # --debug; the exit status is the same either way.
        if args.debug:
            traceback.print_exc()
        line = (
            f"internal error: {type(exc).__name__}: {_one_line(exc)} "
            "(a bug: rerun with --debug for the traceback and report it)"
        )
        print(line, file=sys.stderr)
        _json_failure(args, line, EXIT_INTERNAL_ERROR)
        return EXIT_INTERNAL_ERROR


def _json_failure(args: argparse.Namespace, line: str, code: int) -> None:
    """Where the command was to write its JSON (``--json -``, ``evaluate --json``; a ``--json``
    file once it was found fit to write), a JSON object saying why there is none: a script
    reading it gets the reason, not nothing, nor an earlier run's summary. A stdout or file
    that cannot take it loses it (the line is on stderr)."""
    failure = {"error": line.removeprefix("error: "), "exit_code": code}
    if getattr(args, "json", None) in ("-", True):
        with contextlib.suppress(OSError, ValueError):
            print(json.dumps(failure), flush=True)
    elif getattr(args, "json_file_checked", False):
        with contextlib.suppress(OSError):
            write_json_file(args.json, failure)


# The resource trackers (processes that remove the workers' semaphores and folders if the
# run cannot) warn on their own stderr, the run's, when they remove something at the end:
# an interrupted run leaves that to them.
_TRACKER_WARNINGS = "ignore:resource_tracker:UserWarning"


def _quiet_resource_trackers() -> None:
    """Keep the resource trackers' warnings off stderr: they read PYTHONWARNINGS as they
    start, with the run's first workers."""
    rules = os.environ.get("PYTHONWARNINGS", "")
    if _TRACKER_WARNINGS not in rules.split(","):
        os.environ["PYTHONWARNINGS"] = ",".join(r for r in (rules, _TRACKER_WARNINGS) if r)


def _own_records(record: logging.LogRecord) -> bool:
    """Whether a log record is the project's own: without --debug, libraries' records
    (distributed's, asyncio's as a cluster stops, ...) stay off stderr."""
    return record.name == "pipeline" or record.name.startswith("pipeline.")


def _one_line(exc: BaseException) -> str:
    """The message on one line, so that scripts can grep stderr."""
    return " ".join(str(exc).split())


if __name__ == "__main__":
    run()
