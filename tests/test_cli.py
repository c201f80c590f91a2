"""The CLI's own behaviour: argument parsing and how errors become exit statuses."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib.metadata
import json
import os
import subprocess
import sys
import time
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from pipeline.cli import EXIT_BAD_INPUT, EXIT_FRAMES_FAILED, EXIT_INTERNAL_ERROR, main
from pipeline.cli import parser as cli_parser
from pipeline.errors import CalibrationError, Interrupted, PipelineError
from pipeline.record.load import load_recording
from pipeline.run import runner, workers
from pipeline.run.summary import RunSummary
from pipeline.session import folder as session
from pipeline.synth.session_render import MIN_PARALLEL_FRAMES

PIPELINE = str(Path(sys.executable).parent / "pipeline")  # the console script
ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(
    ("text", "expected"),
    [("0:300", (0, 300)), (":10", (0, 10)), ("5:", (5, None)), ("7:8", (7, 8))],
)
def test_frame_range_parses(text: str, expected: tuple[int, int | None]) -> None:
    assert cli_parser._frame_range(text) == expected


@pytest.mark.parametrize("text", ["10", "a:b", "5:5", "9:3", "-1:4", ""])
def test_frame_range_rejects(text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match="START:STOP"):
        cli_parser._frame_range(text)


def test_bad_argument_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["process", "somewhere", "--frames", "9:3"])
    assert exit_info.value.code == 2  # argparse's usage-error status, the same as bad input
    err = capsys.readouterr().err
    # One line, like every other error, pointing to the subcommand's help.
    assert err.count("\n") == 1 and err.startswith("error: pipeline process: ")
    assert "START:STOP" in err and err.rstrip().endswith("(see pipeline process --help)")


@pytest.mark.parametrize(
    "command",
    [["process", "-x"], ["process", "s", "--out", "-x"], ["evaluate", "-x", "gt.npz"]],
    ids=["session", "out", "recording"],
)
def test_a_folder_named_like_an_option_is_named_with_how_to_give_it(
    command: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "-x").mkdir()
    with pytest.raises(SystemExit) as exit_info:
        main(command)
    assert exit_info.value.code == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: pipeline {command[0]}: ")
    assert "-x is read as an option; to give the folder -x, write ./-x (or -- -x)" in err


def test_a_folder_named_like_an_option_after_a_double_dash_is_the_session(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "-x").mkdir()
    assert main(["process", "--out", str(tmp_path / "out"), "--", "-x"]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err == "error: -x: the session directory is empty\n"


LONG = "s" * 300
# An unset shell variable ("$SESSION") gives an empty argument, which Path("") reads as ".".
EMPTY = "an empty path"
# The system refuses to look a name longer than 255 bytes up at all (ENAMETOOLONG), where a
# missing file's lookup answers "not there".
TOO_LONG = f"the name {'s' * 24}... is 300 bytes long, and no file or folder name may pass 255"


@pytest.mark.parametrize(
    ("command", "argument", "message"),
    [
        (["process", ""], "video_dir", EMPTY),
        (["process", "s", "--out", ""], "-o/--out", EMPTY),
        (["evaluate", "r.mcap", ""], "ground_truth", EMPTY),
        (["calibrate", "boards", "-o", ""], "-o/--output", EMPTY),
        (["process", LONG], "video_dir", TOO_LONG),
        (["process", "s", "--json", f"out/{LONG}"], "--json", TOO_LONG),
        (["evaluate", "r.mcap", LONG], "ground_truth", TOO_LONG),
        (["calibrate", LONG, "-o", "c.toml"], "calib_dir", TOO_LONG),
        (["synth", f"{LONG}/s"], "out_dir", TOO_LONG),
        (["live", "--replay", LONG], "--replay", TOO_LONG),
    ],
)
def test_a_path_no_file_could_have_is_a_usage_error(
    capsys: pytest.CaptureFixture[str], command: list[str], argument: str, message: str
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(command)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"argument {argument}: {message}" in err


def test_json_before_the_session_folder_takes_stdout_not_the_folder(tmp_path: Path) -> None:
    from pipeline.cli.parser import build_parser, with_json_before_a_folder

    session, out = tmp_path / "take", tmp_path / "out"
    session.mkdir()
    out.mkdir()
    # `process -o out --json take`: argparse gave --json the session and missed the session.
    assert with_json_before_a_folder(["process", "-o", str(out), "--json", str(session)]) == [
        "process", "-o", str(out), "--json=-", str(session)
    ]  # fmt: skip
    # Beside the session, a folder after --json is a mistaken FILE, left for its own message.
    words = ["process", str(session), "--json", str(out)]
    assert with_json_before_a_folder(words) == words
    # evaluate's --json is a flag: a folder after it is its ground truth, as given.
    words = ["evaluate", str(tmp_path / "run.mcap"), "--json", str(session)]
    assert with_json_before_a_folder(words) == words
    assert build_parser().parse_args(words).json is True


@pytest.mark.parametrize("command", ["process", "live"])
def test_json_to_the_file_that_is_stdout_is_stdout(
    command: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pipeline.cli.parser import build_parser

    stdout, other = tmp_path / "stdout", tmp_path / "summary.json"
    with stdout.open("w", encoding="utf-8") as f:
        monkeypatch.setattr(sys, "stdout", f)
        parser = build_parser()
        assert parser.parse_args([command, "s", "--json", str(stdout)]).json == "-"
        assert parser.parse_args([command, "s", "--json", str(other)]).json == str(other)
        assert parser.parse_args([command, "s", "--json"]).json == "-"


def _raising(exc: BaseException) -> object:
    def command(args: argparse.Namespace) -> int:
        raise exc

    return command


def test_pipeline_error_is_one_line_and_exit_2(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(
        cli_parser, "cmd_evaluate", _raising(CalibrationError("cal.toml: bad\n  camera 'c0'"))
    )
    assert main(["evaluate", "r.mcap", "gt.npz"]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err == "error: cal.toml: bad camera 'c0'\n"


def test_a_bug_is_one_line_and_exit_3_without_debug(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(cli_parser, "cmd_evaluate", _raising(ZeroDivisionError("division by zero")))
    assert main(["evaluate", "r.mcap", "gt.npz"]) == EXIT_INTERNAL_ERROR
    err = capsys.readouterr().err
    assert err.startswith("internal error: ZeroDivisionError: division by zero")
    assert "--debug" in err and err.count("\n") == 1


@pytest.mark.parametrize("where", ["before", "after"])
def test_debug_shows_a_bugs_traceback_with_the_same_exit_status(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], where: str
) -> None:
    # --debug may come before the subcommand or follow it.
    monkeypatch.setattr(cli_parser, "cmd_evaluate", _raising(ZeroDivisionError("division by zero")))
    command = ["evaluate", "r.mcap", "gt.npz"]
    assert main(["--debug", *command] if where == "before" else [*command, "--debug"]) == EXIT_INTERNAL_ERROR
    err = capsys.readouterr().err
    assert err.startswith("Traceback") and "internal error: ZeroDivisionError: division by zero" in err


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out == f"pipeline {importlib.metadata.version('pipeline')}\n"


def test_process_help_states_the_frame_range_convention(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["process", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "START <= i < STOP (STOP excluded" in out
    assert "-o OUT, --out OUT" in out and "-j JOBS, --jobs JOBS" in out and "--json [FILE]" in out


@pytest.mark.parametrize(
    ("command", "usage"),
    [([sys.executable, "-m", "pipeline"], "usage: python -m pipeline "), ([PIPELINE], "usage: pipeline ")],
)
def test_the_program_names_itself_as_invoked(command: list[str], usage: str) -> None:
    proc = subprocess.run([*command, "--help"], capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(usage)


def test_a_run_counts_its_wall_time_from_the_process_start() -> None:
    # Half a second passes before the CLI is even imported: the wall time must include it.
    code = (
        "import time; time.sleep(0.5); from pipeline.cli import commands; "
        "print(time.perf_counter() - commands._process_started_at())"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert 0.5 <= float(proc.stdout) < 30.0


class _FakeRun:
    """Stands in for load_session and process_session; keeps what the CLI passed."""

    def __init__(self, summary: RunSummary) -> None:
        self.summary = summary
        self.kwargs: dict[str, Any] = {}

    def process_session(self, session: object, **kwargs: Any) -> RunSummary:
        self.kwargs = kwargs
        return self.summary


def _fake_run(monkeypatch: pytest.MonkeyPatch, summary: RunSummary) -> _FakeRun:
    fake = _FakeRun(summary)
    monkeypatch.setattr(runner, "process_session", fake.process_session)
    monkeypatch.setattr(session, "load_session", lambda directory: directory)
    monkeypatch.setattr(workers, "started_early", lambda jobs, backend: contextlib.nullcontext())
    return fake


OK_RUN = RunSummary(frames_ok=4, frames_empty=0, frames_failed=[], wall_s=2.0, fps=2.0)


def test_short_options_and_the_scheduler_reach_the_run(monkeypatch: pytest.MonkeyPatch) -> None:
    fake = _fake_run(monkeypatch, OK_RUN)
    before = time.perf_counter()
    assert main(["process", "s", "-o", "elsewhere", "-j", "3", "--scheduler", "tcp://host:8786"]) == 0
    assert (fake.kwargs["out_dir"], fake.kwargs["jobs"]) == (Path("elsewhere"), 3)
    # --scheduler implies --backend dask
    assert (fake.kwargs["backend"], fake.kwargs["scheduler"]) == ("dask", "tcp://host:8786")
    assert fake.kwargs["started_at"] < before  # the process started before this call
    assert main(["process", "s"]) == 0 and fake.kwargs["backend"] == "loky"


def test_scheduler_with_another_backend_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["process", "s", "--scheduler", "tcp://host:8786", "--backend", "threading"])
    assert exit_info.value.code == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--scheduler" in err and "--backend threading" in err


FAILED_RUN = RunSummary(
    frames_ok=2,
    frames_empty=0,
    frames_failed=[
        (2, "camera cam1: frame could not be decoded"),
        (3, "camera cam1: frame could not be decoded"),
    ],
    wall_s=2.0,
    fps=2.0,
    frames_doubtful=[1],
    outputs=[(Path("out/s.mcap"), 10)],
)


def test_failures_and_warnings_go_to_stderr_the_rest_to_stdout(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    _fake_run(monkeypatch, FAILED_RUN)
    assert main(["process", "s"]) == EXIT_FRAMES_FAILED
    captured = capsys.readouterr()
    assert captured.err.splitlines() == FAILED_RUN.problem_lines()
    assert (
        "failed 2-3: camera cam1: frame could not be decoded" in captured.err and "doubtful" in captured.err
    )
    assert captured.out.splitlines() == [line for line in FAILED_RUN.lines() if line not in captured.err]
    assert captured.out.startswith("frames: 4 processed") and "wrote out/s.mcap" in captured.out


@pytest.mark.parametrize(
    ("px", "radii", "said"),
    [(0.6, 0.2, True), (0.2, 0.2, False), (0.6, 0.05, False), (float("nan"), float("nan"), False)],
)
def test_edges_the_tube_does_not_explain_are_said_on_stderr_and_the_run_still_succeeds(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], px: float, radii: float, said: bool
) -> None:
    # Said only where the edges lie beyond both bars: a pixel's noise, a share of the radius.
    summary = dataclasses.replace(OK_RUN, edge_residual_px=px, edge_residual_radii=radii)
    _fake_run(monkeypatch, summary)
    assert main(["process", "s"]) == 0
    captured = capsys.readouterr()
    assert ("unexplained: the silhouettes' edges lie" in captured.err) is said
    assert "unexplained" not in captured.out
    if said:
        assert (
            f"{px:.2f} px ({radii:.2f} radii)" in captured.err
            and "spacer disks" in captured.err
            and "cameras that disagree" in captured.err
        )
    # The JSON summary holds the figures, None for none (strict JSON).
    data = json.loads(json.dumps(summary.to_dict(), allow_nan=False))
    assert data["edge_residual_px"] == (None if px != px else px)
    assert any(line.startswith("unexplained") for line in data["problems"]) is said
    # Cameras refined on such edges are named as moved, and doubted with them.
    moved = dataclasses.replace(summary, camera_warnings=["camera cam1 seems to have moved ..."])
    doubted = [line for line in moved.problem_lines() if "the cameras' corrections above" in line]
    assert len(doubted) == said
    assert "corrections above" not in " ".join(summary.problem_lines())


def test_a_run_without_any_tube_exits_1_with_the_reason_on_stderr(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    _fake_run(monkeypatch, RunSummary(frames_ok=0, frames_empty=4, frames_failed=[], wall_s=1.0, fps=4.0))
    assert main(["process", "s"]) == EXIT_FRAMES_FAILED
    captured = capsys.readouterr()
    assert "no tube in any frame" in captured.err and "polarity" in captured.err
    assert "no tube" not in captured.out


def test_json_summary_to_stdout_or_a_file(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    _fake_run(monkeypatch, FAILED_RUN)
    assert main(["process", "s", "--json"]) == EXIT_FRAMES_FAILED
    captured = capsys.readouterr()
    # stdout holds the JSON alone; the text summary moves to stderr.
    assert json.loads(captured.out) == FAILED_RUN.to_dict()
    assert "frames: 4 processed" in captured.err
    target = tmp_path / "summary.json"
    assert main(["process", "s", "--json", str(target)]) == EXIT_FRAMES_FAILED
    data = json.loads(target.read_text())
    assert data["frames"]["failed"] == 2 and data["exit_code"] == 1 and data["doubtful"] == [1]
    assert "frames: 4 processed" in capsys.readouterr().out


def test_a_json_summary_is_written_whole_or_not_at_all(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    from pipeline.cli import commands

    _fake_run(monkeypatch, FAILED_RUN)
    target = tmp_path / "summary.json"
    earlier = json.dumps({**OK_RUN.to_dict(), "wall_s": 1.5}) + "\n"
    target.write_text(earlier)

    def full_disk(*args: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(commands.os, "replace", full_disk)
    assert main(["process", "s", "--json", str(target)]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err.endswith(
        f"error: {target}: cannot write the JSON summary (No space left on device)\n"
    )
    assert target.read_text() == earlier
    assert sorted(p.name for p in tmp_path.iterdir()) == ["summary.json"]
    # Through a link, the file it leads to is written, and the link kept.
    monkeypatch.undo()
    _fake_run(monkeypatch, FAILED_RUN)
    link = tmp_path / "link.json"
    link.symlink_to(target)
    assert main(["process", "s", "--json", str(link)]) == EXIT_FRAMES_FAILED
    assert link.is_symlink() and json.loads(target.read_text()) == FAILED_RUN.to_dict()
    # ... and so through a link to a file yet to be made.
    ahead = tmp_path / "ahead.json"
    ahead.symlink_to(tmp_path / "made" / "later.json")
    (tmp_path / "made").mkdir()
    assert main(["process", "s", "--json", str(ahead)]) == EXIT_FRAMES_FAILED
    assert ahead.is_symlink() and json.loads(ahead.read_text()) == FAILED_RUN.to_dict()
    assert sorted(p.name for p in (tmp_path / "made").iterdir()) == ["later.json"]


def test_a_run_refused_or_stopped_leaves_its_reason_in_the_json_file_not_an_earlier_summary(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    target = tmp_path / "summary.json"
    target.write_text(json.dumps(OK_RUN.to_dict()) + "\n")  # an earlier run's: exit 0
    for raised, code in (
        (PipelineError("s/session.toml: radius_mm 60 is wider than the workspace"), EXIT_BAD_INPUT),
        (Interrupted("interrupted; the earlier recordings are kept"), 130),
        (RuntimeError("a bug"), EXIT_INTERNAL_ERROR),
    ):

        def run(*args: object, raised: BaseException = raised, **kwargs: object) -> None:
            raise raised

        monkeypatch.setattr(runner, "process_session", run)
        monkeypatch.setattr(session, "load_session", lambda directory: directory)
        monkeypatch.setattr(workers, "started_early", lambda jobs, backend: contextlib.nullcontext())
        assert main(["process", "s", "--json", str(target)]) == code
        err = capsys.readouterr().err.strip()
        assert json.loads(target.read_text()) == {"error": err.removeprefix("error: "), "exit_code": code}
        # ... and on stdout, where it carries the JSON.
        assert main(["process", "s", "--json"]) == code
        assert json.loads(capsys.readouterr().out)["exit_code"] == code
    # A refusal of the file itself writes nothing there.
    layout = tmp_path / "layout.json"
    layout.write_text('{"layout": {}}\n')
    assert main(["process", "s", "--json", str(layout)]) == EXIT_BAD_INPUT
    assert layout.read_text() == '{"layout": {}}\n'


def test_json_never_takes_the_place_of_a_recording_or_another_json_file(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    fake = _fake_run(monkeypatch, OK_RUN)
    # A recording of this run, or its lock, in an --out folder the run would make.
    for name in ("s.mcap", "s.rrd", ".s.lock"):
        target = tmp_path / "new" / "out" / name
        assert main(["process", "s", "-o", str(target.parent), "--json", str(target)]) == EXIT_BAD_INPUT
        assert "is one of the files this run writes (its recordings, its lock)" in capsys.readouterr().err
    # The --out folder the run would make (its recordings went in, then the summary failed).
    for out in (tmp_path / "made-by-the-run", tmp_path / "a" / "b"):
        assert main(["process", "s", "-o", str(out), "--json", str(out)]) == EXIT_BAD_INPUT
        assert f"{out}: is a directory; give --json a file name" in capsys.readouterr().err
        assert not out.exists()
    # A JSON file that is not a summary (a layout, a settings file).
    layout = tmp_path / "layout.json"
    layout.write_text('{"layout": {"panels": []}}\n')
    assert main(["process", "s", "--json", str(layout)]) == EXIT_BAD_INPUT
    assert "exists and is not a JSON summary" in capsys.readouterr().err
    assert layout.read_text() == '{"layout": {"panels": []}}\n' and fake.kwargs == {}


def test_json_into_the_out_folder_that_the_run_makes(tmp_path: Path) -> None:
    from conftest import build_session

    session_dir = build_session(tmp_path / "s", frames=3)
    out = tmp_path / "new" / "out"  # made by the run, parents and all
    code = main(["process", str(session_dir), "-o", str(out), "--json", str(out / "summary.json")])
    assert code in (0, 1)
    assert json.loads((out / "summary.json").read_text())["exit_code"] == code
    assert (out / "s.mcap").is_file()


def test_json_to_a_missing_folder_fails_before_the_run(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    fake = _fake_run(monkeypatch, OK_RUN)
    assert main(["process", "s", "--json", str(tmp_path / "no" / "summary.json")]) == EXIT_BAD_INPUT
    assert fake.kwargs == {}  # never started
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "does not exist" in err and err.count("\n") == 1
    (tmp_path / "file").write_text("a file, not a folder")
    assert main(["process", "s", "--json", str(tmp_path / "file" / "summary.json")]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "file is a file, not a folder; give --json a file in a folder" in err and err.count("\n") == 1


def test_json_that_cannot_be_opened_fails_before_the_run(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    fake = _fake_run(monkeypatch, OK_RUN)
    target = tmp_path / "loop.json"
    target.symlink_to(target)  # a link that leads back to itself
    assert main(["process", "s", "--json", str(target)]) == EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert err == (
        f"error: {target}: cannot be written (Too many levels of symbolic links); give --json a file "
        "in a folder you can write to\n"
    )
    # A writable folder (by its permission bits) where no file can be made: /sys for root.
    from pipeline.cli import commands

    def refused(*args: object, **kwargs: object) -> None:
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(commands, "open", refused, raising=False)
    summary = tmp_path / "summary.json"
    assert main(["process", "s", "--json", str(summary)]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err == (
        f"error: {summary}: cannot be written; give --json a file in a folder you can write to\n"
    )
    assert fake.kwargs == {}  # never started
    monkeypatch.undo()
    # Where it can, the check leaves no file behind: the run writes it.
    fake = _fake_run(monkeypatch, OK_RUN)
    assert main(["process", "s", "--json", str(summary)]) == 0
    assert json.loads(summary.read_text())["exit_code"] == 0


def test_interrupt_exits_130(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(cli_parser, "cmd_evaluate", _raising(KeyboardInterrupt()))
    assert main(["evaluate", "r.mcap", "gt.npz"]) == 130
    assert "interrupted" in capsys.readouterr().err


def test_help_lists_every_command(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    for command in ("process", "synth", "synth-calib", "calibrate", "evaluate"):
        assert command in out


def test_a_run_from_the_command_line_exits_0_with_its_summary_on_stdout(
    make_session: Callable[..., Path], tmp_path: Path
) -> None:
    # ``python -m pipeline`` leaves without the interpreter's teardown (pipeline.__main__):
    # its summary must still reach a pipe and its outputs be complete.
    session = make_session(tmp_path / "session")
    out = tmp_path / "out"
    command = [sys.executable, "-m", "pipeline", "process", str(session), "--out", str(out), "--jobs", "2"]
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}  # stdout block-buffered
    proc = subprocess.run(command, capture_output=True, text=True, timeout=300, check=False, env=env)
    assert proc.returncode == 0, proc.stderr
    assert "frames: 4 processed, 4 ok" in proc.stdout and f"wrote {out / 'session.mcap'}" in proc.stdout, (
        proc.stdout
    )
    assert load_recording(out / "session.mcap").complete


# Ctrl-C just as the program ends: an exit handler registered before any of the program's,
# and so run after them all, sends the process SIGINT.
_CTRL_C_AT_EXIT = (
    "import atexit, os, signal, time\n"
    "atexit.register(lambda: (os.kill(os.getpid(), signal.SIGINT), time.sleep(0.2)))\n"
)


def _console_script_start() -> str:
    """Python that starts the program as the console script installed with the package does,
    through the entry point pyproject.toml names."""
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    module, _, function = scripts["pipeline"].partition(":")
    return f"import sys\nfrom {module} import {function}\nsys.argv[0] = 'pipeline'\nsys.exit({function}())\n"


@pytest.mark.parametrize(
    "start",
    [
        _console_script_start(),
        "import runpy\nrunpy.run_module('pipeline', run_name='__main__', alter_sys=True)\n",
    ],
    ids=["console-script", "python-m"],
)
def test_ctrl_c_as_the_program_ends_changes_neither_its_lines_nor_its_status(
    start: str, tmp_path: Path
) -> None:
    # The console script and `python -m pipeline` leave the same way: the run's status, and a
    # signal once it is over ignored, not a traceback from an exit handler it landed in.
    missing = tmp_path / "missing.mcap"
    command = [sys.executable, "-c", _CTRL_C_AT_EXIT + start, "evaluate", str(missing), str(tmp_path)]
    proc = subprocess.run(command, capture_output=True, text=True, timeout=60, check=False, cwd=ROOT)
    assert proc.returncode == EXIT_BAD_INPUT, proc.stderr
    assert (
        proc.stderr == f"error: recording {missing} does not exist; run `python -m pipeline process` first\n"
    )


def test_a_command_that_leaves_a_worker_pool_running_still_exits(tmp_path: Path) -> None:
    # `synth` renders longer sessions on a joblib pool it never shuts down itself; the fast
    # exit must still stop the pool's manager thread: a wait on it would last for good, and
    # `make process` on a fresh clone would never get past rendering the demo.
    frames = str(MIN_PARALLEL_FRAMES)
    command = [sys.executable, "-m", "pipeline", "synth", str(tmp_path / "s"), "--frames", frames]
    proc = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "s" / "calibration.toml").is_file()


def test_say_to_a_stdout_closed_in_the_process_drops_the_text_and_goes_on() -> None:
    # A library or a caller closed sys.stdout: what is said is dropped, later prints too.
    script = (
        "import sys; from pipeline.cli.commands import say; sys.stdout.close(); "
        "say('lost'); say('lost too'); print('after', flush=True); print('went on', file=sys.stderr)"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stderr == "went on\n" and done.stdout == ""
