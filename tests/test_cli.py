"""The CLI's own behaviour: argument parsing and how errors become exit statuses."""

from __future__ import annotations

import argparse

import pytest

from pipeline import cli
from pipeline.cli import EXIT_BAD_INPUT, EXIT_INTERNAL_ERROR, main
from pipeline.errors import CalibrationError


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
    assert "START:STOP" in capsys.readouterr().err


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
