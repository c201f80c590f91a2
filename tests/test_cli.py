"""The CLI's own behaviour: argument parsing and how errors become exit statuses."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from pipeline import cli
from pipeline.cli import EXIT_BAD_INPUT, EXIT_INTERNAL_ERROR, main
from pipeline.errors import CalibrationError
from pipeline.recording import load_recording
from pipeline.synth.session_render import MIN_PARALLEL_FRAMES


@pytest.mark.parametrize(
    ("text", "expected"),
    [("0:300", (0, 300)), (":10", (0, 10)), ("5:", (5, None)), ("7:8", (7, 8))],
)
def test_frame_range_parses(text: str, expected: tuple[int, int | None]) -> None:
    assert cli._frame_range(text) == expected


@pytest.mark.parametrize("text", ["10", "a:b", "5:5", "9:3", "-1:4", ""])
def test_frame_range_rejects(text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match="START:STOP"):
        cli._frame_range(text)


def test_bad_argument_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["process", "somewhere", "--frames", "9:3"])
    assert exit_info.value.code == 2  # argparse's usage-error status, the same as bad input
    err = capsys.readouterr().err
    # One line, like every other error, pointing to the subcommand's help.
    assert err.count("\n") == 1 and err.startswith("error: python -m pipeline process: ")
    assert "START:STOP" in err and err.rstrip().endswith("(see python -m pipeline process --help)")


def _raising(exc: BaseException) -> object:
    def command(args: argparse.Namespace) -> int:
        raise exc

    return command


def test_pipeline_error_is_one_line_and_exit_2(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(cli, "_cmd_evaluate", _raising(CalibrationError("cal.toml: bad\n  camera 'c0'")))
    assert main(["evaluate", "r.mcap", "gt.npz"]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err == "error: cal.toml: bad camera 'c0'\n"


def test_a_bug_is_one_line_and_exit_3_without_debug(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(cli, "_cmd_evaluate", _raising(ZeroDivisionError("division by zero")))
    assert main(["evaluate", "r.mcap", "gt.npz"]) == EXIT_INTERNAL_ERROR
    err = capsys.readouterr().err
    assert err.startswith("internal error: ZeroDivisionError: division by zero")
    assert "--debug" in err and err.count("\n") == 1


def test_debug_lets_a_bug_through(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(cli, "_cmd_evaluate", _raising(ZeroDivisionError("division by zero")))
    with pytest.raises(ZeroDivisionError):
        main(["--debug", "evaluate", "r.mcap", "gt.npz"])


def test_interrupt_exits_130(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(cli, "_cmd_evaluate", _raising(KeyboardInterrupt()))
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


def test_a_command_that_leaves_a_worker_pool_running_still_exits(tmp_path: Path) -> None:
    # `synth` renders longer sessions on a joblib pool it never shuts down itself; the fast
    # exit must still stop the pool's manager thread (it once waited forever on it, so
    # `make process` on a fresh clone never got past rendering the demo).
    frames = str(MIN_PARALLEL_FRAMES)
    command = [sys.executable, "-m", "pipeline", "synth", str(tmp_path / "s"), "--frames", frames]
    proc = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "s" / "calibration.toml").is_file()
