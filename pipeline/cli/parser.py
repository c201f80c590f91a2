"""The command line's options: one argparse parser with a subparser per command."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

from ..measure.arguments import OneLineParser, worker_jobs
from .commands import (
    EXIT_BAD_INPUT,
    cmd_calibrate,
    cmd_evaluate,
    cmd_live,
    cmd_process,
    cmd_synth,
    cmd_synth_calib,
)

# How the program names itself in usage and error lines: the console script's name;
# ``python -m pipeline`` passes its own (pipeline.__main__).
PROG = "pipeline"


def _frame_range(text: str) -> tuple[int, int | None]:
    """START:STOP -> (START, STOP): frames START <= i < STOP; either may be left out."""
    start, sep, stop = text.partition(":")
    try:
        lo = int(start) if start else 0
        hi = int(stop) if stop else None
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected START:STOP (e.g. 0:300), got {text!r}") from None
    if not sep or lo < 0 or (hi is not None and hi <= lo):
        raise argparse.ArgumentTypeError(f"expected START:STOP with 0 <= START < STOP, got {text!r}")
    return lo, hi


# The longest file or folder name (bytes) Linux's file systems take.
NAME_MAX = 255


def _path(text: str) -> Path:
    """A path argument: an empty one (a shell variable left unset) is no path; Path("")
    would be the current folder. A name longer than any file system takes is no file's."""
    if not text:
        raise argparse.ArgumentTypeError("an empty path; give a file or folder")
    _check_name_lengths(text)
    return Path(text)


def _names_checked(text: str) -> str:
    """A path argument kept as text ("" where it means the default's): its names checked."""
    _check_name_lengths(text)
    return text


def _check_name_lengths(text: str) -> None:
    """A usage error where a file or folder name in the path ``text`` is longer than
    ``NAME_MAX`` bytes: the system refuses to look such a path up at all."""
    for part in Path(text).parts:
        size = len(os.fsencode(part))
        if size > NAME_MAX:
            raise argparse.ArgumentTypeError(
                f"the name {part[:24]}... is {size} bytes long, and no file or folder name may pass "
                f"{NAME_MAX}; give a shorter one"
            )


def _json_file(text: str) -> str:
    """--json's FILE (of process and live), with a path that is this process's stdout
    (``/dev/stdout``) taken as "-": opened as a file, a pipe there would be read, and
    waited on for good."""
    if text == "-":
        return text
    _check_name_lengths(text)
    try:
        here, out = os.stat(text), os.fstat(sys.stdout.fileno())
    except (OSError, ValueError):
        return text
    return "-" if (here.st_dev, here.st_ino) == (out.st_dev, out.st_ino) else text


def _board(text: str) -> tuple[int, int]:
    cols, sep, rows = text.lower().partition("x")
    if not sep or not cols.isdigit() or not rows.isdigit():
        raise argparse.ArgumentTypeError(
            f"expected COLSxROWS (e.g. 9x6: inner corners for --board, squares for --charuco), got {text!r}"
        )
    return int(cols), int(rows)


class _Parser(OneLineParser):
    """argparse, with a usage mistake on one line like every other error (exit status 2),
    pointing to ``--help`` instead of printing the whole usage above it (as the measuring
    tools' :class:`~pipeline.measure.arguments.OneLineParser`); where the words being
    parsed hold a path that starts with "-", the line says how to give it instead.
    Subcommands' parsers are of this class too (argparse makes them of their parent's)."""

    _words: Sequence[str] = ()

    def parse_known_args(self, args: Any = None, namespace: Any = None) -> Any:
        self._words = list(sys.argv[1:] if args is None else args)
        try:
            return super().parse_known_args(args, namespace)
        finally:
            self._words = ()

    def error(self, message: str) -> NoReturn:
        word = self._option_like_path()
        if word is not None:
            kind = "folder" if os.path.isdir(word) else "file"
            self.exit(
                EXIT_BAD_INPUT,
                f"error: {self.prog}: {word} is read as an option; to give the {kind} {word}, "
                f"write ./{word} (or -- {word})\n",
            )
        super().error(message)

    def _option_like_path(self) -> str | None:
        """The first of the words being parsed (before any ``--``) that argparse reads as an
        option (not "-", nor a negative number: this parser has no options like those) but
        that names an existing file or folder, such as a session folder called ``-x``."""
        for word in self._words:
            if word == "--":
                return None
            read_as_option = (
                word.startswith("-") and word != "-" and not self._negative_number_matcher.match(word)
            )
            if read_as_option and os.path.lexists(word):
                return word
        return None


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("pipeline")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown version"


def build_parser(prog: str = PROG) -> argparse.ArgumentParser:
    parser = _Parser(
        prog=prog,
        description="3-D centreline of a continuum manipulator from three calibrated cameras. "
        "Geometry in millimetres in the world frame of calibration.toml (metres in the .mcap); "
        "frame ranges START:STOP include START and exclude STOP.",
        epilog=f"--debug may also follow the command. '{prog} COMMAND --help' for a command's "
        "options. Exit status: 0 done; 1 some frames failed, or no tube in any frame; 2 bad input; "
        "3 internal error (a bug); 130 interrupted.",
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logging")
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    # The same global options on every subcommand, so that they may also follow it. SUPPRESS:
    # left out after the subcommand, they do not reset what was given before it.
    common = _Parser(add_help=False)
    common.add_argument(
        "--debug", action="store_true", default=argparse.SUPPRESS, help="show tracebacks and debug logging"
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser(
        "process",
        parents=[common],
        help="reconstruct every frame of a session into .mcap and .rrd",
        description="Decode the session's videos, reconstruct every frame in parallel and write "
        "OUT/<session>.mcap and OUT/<session>.rrd, then a summary (failures and warnings on "
        "stderr). Exit 0: all frames ok or empty, some tube found; 1: some frames failed, no "
        "tube in any frame, or the summary names another problem; 2: bad input (nothing written).",
    )
    p.add_argument("video_dir", type=_path, help="session directory: calibration.toml + one video per camera")
    p.add_argument(
        "-o", "--out", type=_path, default=Path("recordings"), help="output directory (default: recordings)"
    )
    p.add_argument(
        "-j",
        "--jobs",
        type=worker_jobs,
        default=-1,
        help="parallel workers; -1 = one per core (default), -2 = all cores but one",
    )
    p.add_argument(
        "--backend",
        choices=("loky", "threading", "dask"),
        default=None,
        help="joblib backend: loky = local processes (default), threading, dask = a Dask cluster "
        "(--scheduler's, or a local one)",
    )
    p.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="Dask scheduler address, e.g. tcp://host:8786; implies --backend dask",
    )
    p.add_argument(
        "--frames",
        type=_frame_range,
        metavar="START:STOP",
        help="process only frames START <= i < STOP (STOP excluded, counted from 0); "
        "START or STOP may be left out: 100: or :300",
    )
    p.add_argument(
        "--json",
        nargs="?",
        const="-",
        type=_json_file,
        metavar="FILE",
        help="also write the run's summary as JSON to FILE, or to stdout with - or no FILE "
        "(the text summary then goes to stderr)",
    )
    p.add_argument(
        "--no-images",
        action="store_true",
        help="do not store the camera images (JPEG) in the .mcap and .rrd: smaller, faster files",
    )
    p.add_argument("--force", action="store_true", help="replace existing outputs (atomically)")
    p.add_argument(
        "--curve",
        choices=("fit", "polyfit"),
        default=None,
        help="centreline method: fit (ours, default) or polyfit (the original method, a baseline)",
    )
    p.set_defaults(func=cmd_process, usage_error=p.error)

    p = sub.add_parser(
        "live",
        parents=[common],
        help="reconstruct live cameras (or a replayed session) as it happens",
        description="Read each camera of the rig ([live] in RIG_DIR/session.toml: a V4L2 device, a "
        "device index or a stream URL), reconstruct every matched frame-set as it arrives, stream it "
        "to a Rerun viewer (and a Foxglove server with --foxglove), and write OUT/<rig>.mcap and "
        "OUT/<rig>.rrd, renamed into place when the run stops: Ctrl-C, SIGTERM, --duration, or the "
        "end of a replay. Exit 0: frames reconstructed, some tube found; 1: some frames failed, no "
        "tube in any frame, or the summary names another problem; 2: bad input (nothing written).",
    )
    p.add_argument(
        "rig_dir",
        type=_path,
        nargs="?",
        help="rig directory: calibration.toml + session.toml with [live]; with --replay SESSION_DIR "
        "it may be left out (the session is its own rig)",
    )
    p.add_argument(
        "-o", "--out", type=_path, default=Path("recordings"), help="output directory (default: recordings)"
    )
    p.add_argument(
        "--viewer",
        nargs="+",
        metavar=("spawn|none|connect", "ADDRESS"),
        help="Rerun viewer: spawn one (default, where a window can open), none, or connect to a "
        "running one's gRPC address (PORT, HOST:PORT or rerun+http://HOST:PORT/proxy)",
    )
    p.add_argument(
        "--foxglove",
        nargs="?",
        const="",
        metavar="HOST:PORT",
        help="also serve the MCAP's topics on a Foxglove WebSocket server (default 127.0.0.1:8765)",
    )
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    p.add_argument(
        "--replay",
        nargs="?",
        const="",
        type=_names_checked,
        metavar="SESSION_DIR",
        help="play SESSION_DIR's videos at their frame rate as the cameras (default: RIG_DIR's own)",
    )
    p.add_argument(
        "--json",
        nargs="?",
        const="-",
        type=_json_file,
        metavar="FILE",
        help="also write the run's summary as JSON to FILE, or to stdout with - or no FILE",
    )
    p.add_argument("--no-images", action="store_true", help="do not store or stream the camera images")
    p.add_argument("--force", action="store_true", help="replace existing outputs (when the run stops)")
    p.set_defaults(func=cmd_live, usage_error=p.error)

    from ..synth.names import ARRANGEMENT_NAMES, IMAGE_SIZES, PROFILES, RANDOM_SHAPE, SHAPES, TIPS

    p = sub.add_parser(
        "synth",
        parents=[common],
        help="render a synthetic three-camera session with ground truth",
        description="Render a session directory (calibration.toml, one video per camera, session.toml, "
        "backgrounds) of a moving tube, plus OUT_DIR/ground_truth.npz.",
    )
    p.add_argument("out_dir", type=_path, help="session directory to write")
    p.add_argument(
        "--shape",
        choices=(*SHAPES, RANDOM_SHAPE),
        default="bend_rotate",
        help="motion of the manipulator ('random': a smooth random shape and motion drawn from --seed)",
    )
    p.add_argument(
        "--tip", choices=TIPS, default="flat", help="tube end: flat cut or round (hemispherical) cap"
    )
    p.add_argument(
        "--profile",
        choices=PROFILES,
        default="uniform",
        help="radius along the tube: uniform, tapered (to 0.6 at the tip), disks (1.5x, 2 mm thick, every "
        "20 mm) or step (to 0.7 half way)",
    )
    p.add_argument("--cameras", type=int, choices=(2, 3), default=3, help="cameras in the rig (default 3)")
    p.add_argument(
        "--size",
        choices=[f"{w}x{h}" for w, h in IMAGE_SIZES],
        default="320x240",
        help="image size in pixels (default 320x240)",
    )
    p.add_argument("--distractor", action="store_true", help="a dark object in one camera's background")
    p.add_argument("--flicker", action="store_true", help="scene brightness varying frame to frame (4 %%)")
    p.add_argument(
        "--calib-error",
        type=float,
        default=0.0,
        metavar="DEG",
        help="write a calibration.toml off by this much, 0-2 (each camera turned DEG degrees, moved "
        "6.7*DEG mm, focal 2*DEG %%, principal point 6.7*DEG px); the videos use the true cameras",
    )
    p.add_argument(
        "--bumped-camera",
        type=int,
        metavar="INDEX",
        help="with --calib-error, only this camera (0, 1, ...) is off: turned DEG degrees about its "
        "centre, as a camera knocked since the rig was calibrated",
    )
    p.add_argument("--frames", type=int, default=900, help="number of frames at 30 fps (default 900)")
    p.add_argument(
        "--seed", type=int, default=0, help="random seed (noise, textures; the shape for --shape random)"
    )
    p.add_argument(
        "--polarity",
        choices=("dark", "bright"),
        default="dark",
        help="tube darker or brighter than the scene",
    )
    p.add_argument("--radius-mm", type=float, default=6.0, help="tube radius in mm (default 6)")
    p.add_argument("--arrangement", choices=ARRANGEMENT_NAMES, default="oblique", help="camera placement")
    p.set_defaults(func=cmd_synth)

    p = sub.add_parser(
        "synth-calib",
        parents=[common],
        help="render chessboard or ChArUco calibration images for the synthetic rig",
        description="Write OUT_DIR/<camera>/intrinsics/*.png, OUT_DIR/<camera>/world.png, "
        "OUT_DIR/board.toml and the true cameras as OUT_DIR/truth_calibration.toml.",
    )
    p.add_argument("out_dir", type=_path)
    p.add_argument("--arrangement", choices=ARRANGEMENT_NAMES, default="oblique", help="camera placement")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--board",
        choices=("chessboard", "charuco"),
        default="chessboard",
        help="chessboard (9x6 inner corners, 20 mm) or ChArUco (7x5 squares, 50 mm, DICT_4X4_50; "
        "views may show it in part)",
    )
    p.set_defaults(func=cmd_synth_calib)

    p = sub.add_parser(
        "calibrate",
        parents=[common],
        help="calibrate the cameras from board images into calibration.toml",
        description="Read CALIB_DIR/<camera>/intrinsics/* and CALIB_DIR/<camera>/world.*, calibrate "
        "every camera into the world frame of the board in world.*, and write calibration.toml "
        "plus a report (error table, bar chart, world axes drawn on each world image).",
    )
    p.add_argument("calib_dir", type=_path)
    p.add_argument("-o", "--output", type=_path, required=True, help="calibration.toml to write")
    p.add_argument(
        "--board",
        type=_board,
        metavar="COLSxROWS",
        help="inner corners of the chessboard (overrides board.toml)",
    )
    p.add_argument("--square-mm", type=float, help="square size in mm (overrides board.toml)")
    p.add_argument(
        "--charuco",
        type=_board,
        metavar="COLSxROWS",
        help="a ChArUco board of COLSxROWS squares instead (markers 0.75 square, DICT_4X4_50, "
        "unless board.toml says)",
    )
    p.add_argument("--shared-intrinsics", action="store_true", help="one set of intrinsics for all cameras")
    p.add_argument(
        "--drop-outliers", action="store_true", help="drop views whose error stands out, and recalibrate"
    )
    p.add_argument("--force", action="store_true", help="replace an existing calibration file at -o")
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser(
        "evaluate",
        parents=[common],
        help="accuracy of a recording against ground truth",
        description="Compare the centrelines in RECORDING.mcap with GROUND_TRUTH.npz (or a session "
        "directory holding ground_truth.npz): centreline, tip, base and length errors, jitter.",
    )
    p.add_argument("recording", type=_path, help="the .mcap that process or live wrote")
    p.add_argument(
        "ground_truth",
        type=_path,
        help="ground_truth.npz, or the synthetic session's folder that holds it (synth writes it)",
    )
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(func=cmd_evaluate)
    return parser


# The commands whose --json takes an optional FILE (evaluate's is a flag).
JSON_FILE_COMMANDS = ("process", "live")


def with_json_before_a_folder(argv: Sequence[str]) -> list[str]:
    """``--json SESSION_DIR`` as ``--json=- SESSION_DIR`` for JSON_FILE_COMMANDS: argparse
    gives --json (whose FILE is optional) the folder that was meant as the session, then
    says the session is missing. A JSON summary is never written to a folder."""
    out = list(argv)
    command = next((word for word in out if not word.startswith("-")), None)
    if command not in JSON_FILE_COMMANDS:
        return out
    # The folders given, but for the output's: where the folder after --json is the only
    # one, it is the session (or rig); beside another, it is a mistaken FILE, named later.
    folders = [
        i
        for i, word in enumerate(out)
        # os.path's, not Path's: False for a name the system refuses (too long), not an error.
        if os.path.isdir(word) and (i == 0 or out[i - 1] not in ("-o", "--out"))
    ]
    for i, arg in enumerate(out[:-1]):
        if arg == "--json" and folders == [i + 1]:
            out[i] = "--json=-"
    return out


def with_negative_frames(argv: Sequence[str]) -> list[str]:
    """``--frames -5:10`` as ``--frames=-5:10``: argparse takes a value that starts with "-"
    for an option and says "expected one argument"; joined, _frame_range names the mistake."""
    out = list(argv)
    for i, arg in enumerate(out[:-1]):
        if arg == "--frames" and out[i + 1].startswith("-"):
            out[i : i + 2] = [f"--frames={out[i + 1]}"]
            break
    return out
