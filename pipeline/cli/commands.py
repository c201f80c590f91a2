"""The subcommands: each calls one library function and prints what it returns."""

from __future__ import annotations

import argparse
import io
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, TextIO

from ..errors import Interrupted, OutputError

EXIT_OK, EXIT_FRAMES_FAILED, EXIT_BAD_INPUT, EXIT_INTERNAL_ERROR = 0, 1, 2, 3


# Where a run's wall time starts when the OS cannot tell when this process started.
_IMPORTED_AT = time.perf_counter()


def _process_started_at() -> float:
    """The ``time.perf_counter()`` reading of this process's start, so that a run's wall
    time includes the interpreter's start and the imports (~1 s of a 9 s run); the time
    of this module's import where the OS does not say (not Linux)."""
    try:
        with open("/proc/self/stat", encoding="ascii") as f:
            # Field 22, starttime, in clock ticks since boot; counted after the ")" that
            # closes field 2 (the command name, which may hold spaces).
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])
        age_s = time.clock_gettime(time.CLOCK_BOOTTIME) - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, AttributeError):
        return _IMPORTED_AT
    return time.perf_counter() - max(0.0, age_s)


def say(text: str, stream: TextIO | None = None, *, result: str = "") -> None:
    """Print ``text`` to ``stream`` (stdout by default). Stdout closed by its reader (``| head``)
    has taken what it wanted; one that cannot take more (``> /dev/full``) loses a run's summary,
    not the run: its outputs are written by then, and the exit status stays the run's. Where
    ``text`` is all the command makes (``result`` names it, for the message), that is an
    OutputError instead: with exit status 0, a script would keep an empty report."""
    stream = sys.stdout if stream is None else stream
    try:
        print(text, file=stream, flush=True)
    except (OSError, ValueError) as exc:  # BrokenPipeError among the former, a closed stream the latter
        if stream is not sys.stdout:
            raise
        # Later prints, and the flush at exit, go nowhere instead of failing again.
        try:
            fd = sys.stdout.fileno()
        except (OSError, ValueError):  # closed in this process: its descriptor is 1
            fd = 1
        null_onto(fd, "stdout")
        if result and isinstance(exc, OSError) and not isinstance(exc, BrokenPipeError):
            raise OutputError(
                f"stdout: cannot take {result} ({exc.strerror or exc}); free space, or send it elsewhere"
            ) from None


# The standard streams the caller closed (``>&-``), opened on the null device at the start.
_CLOSED_BY_CALLER: set[str] = set()


def check_stdout_takes(result: str) -> None:
    """Before the run: stdout, where ``result`` goes (a script asked for it there), is open.
    Closed by the caller it was put on the null device, and the result would be lost with
    exit status 0."""
    if "stdout" in _CLOSED_BY_CALLER:
        raise OutputError(
            f"stdout: closed (>&-), so it cannot take {result}; leave it open, or send it to a file"
        )


def open_closed_std_streams() -> None:
    """A standard stream the caller closed (``>&-``) is opened on the null device: Python
    leaves it None, and the first print (or a worker process inheriting the descriptor)
    would fail. What goes to it is dropped, as a closed stream asks.

    An open one whose encoding cannot spell every character (an ASCII or Latin-1 locale, a
    path in another script) writes those as escapes (``\\xfc``): strictly encoded, the
    first such line would fail, and the lines after it ("wrote ...") would be lost."""
    for fd, name in ((1, "stdout"), (2, "stderr")):
        stream = getattr(sys, name)
        if stream is None:
            null_onto(fd, name)
            _CLOSED_BY_CALLER.add(name)
        elif isinstance(stream, io.TextIOWrapper) and stream.errors == "strict":
            stream.reconfigure(errors="backslashreplace")


def null_onto(fd: int, name: str) -> None:
    """Open the null device on descriptor ``fd``, and the Python stream ``name`` ("stdout" or
    "stderr") on that where the stream is closed or missing: what is written there is dropped."""
    null = os.open(os.devnull, os.O_WRONLY)
    if null != fd:
        os.dup2(null, fd)
        os.close(null)
    stream = getattr(sys, name)
    if stream is None or stream.closed:
        setattr(sys, name, open(fd, "w", encoding="utf-8", errors="replace", closefd=False))


def _report(summary: Any, json_to: str | None) -> None:
    """Print a run's summary: the failures and warnings to stderr, where scripts and logs look
    for them, the rest to stdout unless stdout carries the JSON summary (``json_to`` "-");
    the JSON summary to ``json_to`` if given. A JSON summary that cannot be written, to a
    file or to stdout, is an OutputError: a script asked for it."""
    problems = set(summary.problem_lines())
    for line in summary.lines():
        say(line, sys.stderr if line in problems or json_to == "-" else sys.stdout)
    if json_to == "-":
        say(json.dumps(summary.to_dict(), indent=2), result="the JSON summary")
    elif json_to is not None:
        try:
            write_json_file(json_to, summary.to_dict())
        except OSError as exc:  # the recordings are written; only the summary file is lost
            raise OutputError(f"{json_to}: cannot write the JSON summary ({exc.strerror or exc})") from None


def write_json_file(path: str | Path, document: dict[str, Any]) -> None:
    """Write ``document`` as JSON to ``path`` whole: under a name of this run's, then renamed
    into place, so that a full disk leaves the earlier file (OSError) and two runs given the
    same file leave one whole summary."""
    target = Path(os.path.realpath(path))
    partial = target.with_name(f".{target.name}.{os.getpid()}.partial")
    try:
        with open(partial, "x", encoding="utf-8") as file:
            file.write(json.dumps(document, indent=2) + "\n")
        os.replace(partial, target)
    except OSError:
        partial.unlink(missing_ok=True)
        raise


def cmd_process(args: argparse.Namespace) -> int:
    from ..run.workers import started_early

    started_at = _process_started_at()
    if args.json == "-":
        check_stdout_takes("the JSON summary")
    elif args.json is not None:
        # A session is named after its folder (pipeline.session.folder.load_session).
        name = Path(args.video_dir).resolve().name
        _check_json_path(Path(args.json), _recordings(Path(args.out), name))
        args.json_file_checked = True  # a run refused or stopped from here on says so there
    # --scheduler names a Dask scheduler: it implies --backend dask (checked in main).
    backend = args.backend or ("dask" if args.scheduler else "loky")
    # The workers spawn and import while this process loads the session and model.
    with started_early(args.jobs, backend):
        from ..run.runner import process_session
        from ..session.folder import load_session

        session = load_session(args.video_dir)
        summary = process_session(
            session,
            out_dir=args.out,
            jobs=args.jobs,
            backend=backend,
            scheduler=args.scheduler,
            frames=args.frames,
            images=not args.no_images,
            force=args.force,
            curve=args.curve,
            progress=sys.stderr.isatty(),
            started_at=started_at,
        )
    _report(summary, args.json)
    return summary.exit_code


def cmd_live(args: argparse.Namespace) -> int:
    from ..live.run import run_live
    from ..live.sources import open_rig
    from ..live.stream import DEFAULT_FOXGLOVE, check_foxglove, parse_host_port, viewer_from_choice

    if args.duration is not None and not args.duration > 0:
        args.usage_error(f"--duration must be > 0 seconds, got {args.duration:g}")
    _rig_dir_after_viewer(args)
    replay = None if args.replay is None else Path(args.replay) if args.replay else args.rig_dir
    if args.rig_dir is None and replay is None:
        args.usage_error("give RIG_DIR, or --replay SESSION_DIR")
    rig, sources = open_rig(args.rig_dir, replay)
    if args.json == "-":
        check_stdout_takes("the JSON summary")
    elif args.json is not None:
        _check_json_path(Path(args.json), _recordings(Path(args.out), rig.name))
        args.json_file_checked = True  # a run refused or stopped from here on says so there
    foxglove = None if args.foxglove is None else parse_host_port(args.foxglove or DEFAULT_FOXGLOVE)
    if foxglove is not None:
        check_foxglove(*foxglove)  # before a viewer is spawned for the run
    viewer_url = viewer_from_choice(args.viewer or [])
    summary = run_live(
        rig,
        sources,
        out_dir=args.out,
        viewer_url=viewer_url,
        foxglove=foxglove,
        duration_s=args.duration,
        images=not args.no_images,
        force=args.force,
    )
    _report(summary, args.json)
    return summary.exit_code


def _rig_dir_after_viewer(args: argparse.Namespace) -> None:
    """``--viewer connect 9876 rig/`` (or ``--viewer none rig/``): argparse gives the rig
    directory to --viewer, whose words are ``spawn``, ``none`` or ``connect ADDRESS``; and
    ``--foxglove rig/`` to --foxglove, whose address is optional (a folder is no address)."""
    words = args.viewer or []
    take = 2 if words[:1] == ["connect"] else 1
    if len(words) == take + 1 and args.rig_dir is None:
        args.rig_dir, args.viewer = Path(words[-1]), words[:take]
    if args.foxglove and args.rig_dir is None and Path(args.foxglove).is_dir():
        args.rig_dir, args.foxglove = Path(args.foxglove), ""


def _check_json_path(path: Path, outputs: tuple[Path, ...] = ()) -> None:
    """Before the run: the JSON summary can be written to ``path`` (through a link, to the
    file it leads to) without taking the place of one of the run's ``outputs`` or of a file
    that is not a JSON summary (a video, a calibration, a layout), and its folder takes a
    new file (:func:`_report` writes one and renames it into place). A folder that does not
    exist yet is accepted where it is the folder of the run's ``outputs``: the run makes it."""
    try:
        path.stat()
    except (FileNotFoundError, NotADirectoryError):
        pass  # a new file (or a link to one), or a file given as its folder: named below
    except OSError as exc:  # a name too long, a loop of links, a folder this user cannot enter
        raise OutputError(
            f"{path}: cannot be written ({exc.strerror}); give --json a file in a folder you can write to"
        ) from None
    target = Path(os.path.realpath(path))
    if any(target == Path(os.path.realpath(out)) for out in outputs):
        raise OutputError(
            f"{path}: is one of the files this run writes (its recordings, its lock); give --json another "
            "file name"
        )
    if target.is_dir() or any(target == Path(os.path.realpath(out.parent)) for out in outputs):
        # The run's --out folder is one, though the run has not made it yet.
        raise OutputError(f"{path}: is a directory; give --json a file name (or - for stdout)")
    if target.exists() and not target.is_file():
        raise OutputError(f"{path}: is not a regular file (a pipe or device); give --json a file name (or -)")
    if target.parent.exists() and not target.parent.is_dir():
        raise OutputError(f"{path}: {path.parent} is a file, not a folder; give --json a file in a folder")
    if not target.parent.is_dir():
        if any(target.parent == Path(os.path.realpath(out.parent)) for out in outputs):
            return  # the run's --out folder, which the run makes (and checks) before any work
        raise OutputError(
            f"{path}: folder {path.parent} does not exist; give --json a file in an existing one"
        )
    if target.exists() and not _holds_summary(target):
        raise OutputError(
            f"{path}: exists and is not a JSON summary; give --json a new file name (or - for stdout)"
        )
    if not _takes_a_new_file(target.parent):
        raise OutputError(f"{path}: cannot be written; give --json a file in a folder you can write to")


def _takes_a_new_file(folder: Path) -> bool:
    """Whether a file can be made in ``folder``, found by making one and removing it.
    Permission bits do not tell: root passes them in /sys, and in a folder made immutable,
    where nothing is created."""
    probe = folder / f".pipeline-json-probe.{os.getpid()}"
    try:
        with open(probe, "xb"):
            pass
    except OSError:
        return False
    probe.unlink(missing_ok=True)
    return True


# A JSON summary is far smaller than this; a larger file is something else.
_SUMMARY_MAX_BYTES = 1 << 20


def _holds_summary(path: Path) -> bool:
    """Whether the file at ``path`` is empty or holds a JSON summary (an object with the
    ``exit_code`` every summary has)."""
    try:
        if path.stat().st_size > _SUMMARY_MAX_BYTES:
            return False
        text = path.read_bytes()
    except OSError:
        return False
    if not text.strip():
        return True
    try:
        summary = json.loads(text)
    except (ValueError, RecursionError):
        return False
    return isinstance(summary, dict) and "exit_code" in summary


def _recordings(out_dir: Path, name: str) -> tuple[Path, ...]:
    """The files a run named ``name`` writes into ``out_dir``, its lock among them."""
    from ..run.output_target import lock_path

    written = tuple(out_dir / f"{name}{suffix}" for suffix in (".mcap", ".rrd", ".calibration.toml"))
    return (*written, lock_path(out_dir, name))


def cmd_synth(args: argparse.Namespace) -> int:
    from ..synth import render_session
    from ..synth.session_render import SceneOptions

    width, height = (int(v) for v in args.size.split("x"))
    options = SceneOptions(
        tip=args.tip,
        profile=args.profile,
        cameras=args.cameras,
        size=(width, height),
        distractor=args.distractor,
        flicker=args.flicker,
        calib_error_deg=args.calib_error,
        bumped_camera=args.bumped_camera,
    )
    render_session(
        args.out_dir,
        shape=args.shape,
        frames=args.frames,
        seed=args.seed,
        polarity=args.polarity,
        radius_mm=args.radius_mm,
        arrangement=args.arrangement,
        options=options,
        progress=sys.stderr.isatty(),  # a bar's redraws fill a log file with lines
    )
    return EXIT_OK


def cmd_synth_calib(args: argparse.Namespace) -> int:
    from ..synth import render_calibration_views

    render_calibration_views(
        args.out_dir,
        arrangement=args.arrangement,
        seed=args.seed,
        board_type=args.board,
        progress=sys.stderr.isatty(),
    )
    return EXIT_OK


def cmd_calibrate(args: argparse.Namespace) -> int:
    from ..calibrate.report import format_table
    from ..calibrate.solve import calibrate_directory

    result = calibrate_directory(
        args.calib_dir,
        args.output,
        board=args.board,
        square_mm=args.square_mm,
        charuco=args.charuco,
        shared_intrinsics=args.shared_intrinsics,
        drop_outliers=args.drop_outliers,
        force=args.force,
    )
    try:
        say(format_table(result))
        say(f"wrote {args.output}; pictures: {', '.join(str(p) for p in result.report_files)}")
        for line in result.problems:
            print(f"warning: {line}", file=sys.stderr)
    except KeyboardInterrupt:
        raise Interrupted(
            f"interrupted as the calibration ended; {args.output} is written, with its report"
        ) from None
    return EXIT_FRAMES_FAILED if result.problems else EXIT_OK


def cmd_evaluate(args: argparse.Namespace) -> int:
    from ..measure.evaluate import evaluate_recording, format_report

    check_stdout_takes(f"the report of {args.recording.name}")
    report = evaluate_recording(args.recording, args.ground_truth)
    # A recording cut short or damaged is named by the reading's own warning (on stderr):
    # the report is of the frames it holds, and the exit status says it is not the whole run.
    # So is one of another session than the ground truth's, or of other videos than those
    # beside it: its figures may mean nothing. A recording without a curve in any frame
    # leaves nothing measured: a script's `evaluate && ...` must not take it for a pass.
    nothing = bool(report.frames) and report.failed_frames + report.empty_frames == report.frames
    whole = report.complete and not report.other_session and not report.other_videos
    code = EXIT_OK if whole and not nothing else EXIT_FRAMES_FAILED
    text = (
        json.dumps({**report.to_dict(), "exit_code": code}, indent=2) if args.json else format_report(report)
    )
    say(text, result=f"the report of {args.recording.name}")
    if nothing:
        print(
            f"warning: {args.recording}: no frame holds a curve to compare ({report.frames} frames "
            "failed or empty); nothing was measured",
            file=sys.stderr,
        )
    return code
