"""The accuracy table's command line: the default cases and a random draw of the variety."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.measure import accuracy_table
from pipeline.synth.variety import Case as DrawnCase
from pipeline.synth.variety import draw_cases


def test_draw_needs_one_number_of_cases(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        accuracy_table.main(["--draw", "3", "--cases", "loop", "helix"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "with --draw, --cases takes one number of cases (1 or more), got loop helix" in err


def test_zero_jobs_is_a_usage_error_before_anything_is_rendered(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    with pytest.raises(SystemExit) as exc:
        accuracy_table.main(["--jobs", "0", "--cases", "helix", "--out", str(tmp_path / "acc")])
    assert exc.value.code == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert "--jobs: 0 workers cannot run" in line
    assert not (tmp_path / "acc").exists()


def test_another_files_accuracy_json_is_not_replaced(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    (tmp_path / "accuracy.json").write_text("my notes")
    with pytest.raises(SystemExit) as exc:
        accuracy_table.main(["--cases", "helix", "--frames", "5", "--out", str(tmp_path)])
    assert exc.value.code == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"error: {tmp_path / 'accuracy.json'}: exists and is not an accuracy table's")
    assert (tmp_path / "accuracy.json").read_text() == "my notes"
    assert sorted(tmp_path.iterdir()) == [tmp_path / "accuracy.json"]  # nothing rendered
    # An earlier table's results may be replaced.
    (tmp_path / "accuracy.json").write_text('[{"case": {}, "frames": 5, "ours": {}, "polyfit": null}]')
    assert accuracy_table._not_our_results(tmp_path / "accuracy.json") == ""


def test_drawn_cases_are_labelled_by_their_description() -> None:
    case = draw_cases(3, 1)[0]
    assert isinstance(case, DrawnCase)
    session, rig = accuracy_table._row_labels(case)
    assert session == case.describe() and case.tip in session and case.profile in session
    assert rig == f"{case.arrangement}, {case.cameras} cameras"
    named = accuracy_table.default_cases()[-1]
    assert accuracy_table._row_labels(named) == (f"{named.name} (unseen)", named.arrangement)


@pytest.mark.parametrize("value", ["5", "-0.1", "nan"])
def test_a_calibration_error_out_of_range_is_refused_before_anything_is_rendered(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, value: str
) -> None:
    argv = ["--cases", "helix", "--out", str(tmp_path / "acc"), f"--calib-error=0.05,{value}"]
    with pytest.raises(SystemExit) as exc:
        accuracy_table.main(argv)
    assert exc.value.code == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert f"--calib-error takes degrees from 0 to 2, got {float(value):g} (see" in line
    assert not (tmp_path / "acc").exists()


def test_a_render_stopped_part_way_is_rendered_again_not_reused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pipeline.errors import UNFINISHED_RENDER

    case = draw_cases(5, 1)[0]
    renders: list[int] = []

    def render(case: DrawnCase, directory: Path, frames: int, *, jobs: int) -> None:
        directory.mkdir(parents=True, exist_ok=True)
        renders.append(frames)

    monkeypatch.setattr("pipeline.synth.variety.render_case", render)
    root = tmp_path / "sessions"
    directory = accuracy_table.prepare_session(case, root, 3)
    assert accuracy_table.prepare_session(case, root, 3) == directory and renders == [3]  # reused
    # A longer render of the same case, interrupted: the stamp of 3 frames must not stand for it.
    (directory / UNFINISHED_RENDER).write_text("stopped")
    accuracy_table.prepare_session(case, root, 3)
    assert renders == [3, 3]


def test_a_case_that_cannot_run_is_named_and_the_others_are_tabled(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import numpy as np

    from pipeline.errors import PipelineError
    from pipeline.measure.evaluate import evaluate_centerlines

    first, second = (c.name for c in accuracy_table.default_cases()[:2])
    line = np.stack([np.zeros(10), np.zeros(10), np.linspace(0.0, 100.0, 10)], axis=1)

    def run_case(
        case: accuracy_table.Case, root: Path, frames: int, **kwargs: object
    ) -> accuracy_table.CaseResult:
        if case.name == first:
            raise PipelineError("its session cannot be rendered here")
        report = evaluate_centerlines(np.stack([line] * 3), np.stack([line] * 3))
        return accuracy_table.CaseResult(case, frames, report, None)

    monkeypatch.setattr(accuracy_table, "run_case", run_case)
    assert accuracy_table.main(["--cases", first, second, "--frames", "3", "--out", str(tmp_path)]) == 1
    out, err = capsys.readouterr()
    assert f"error: case {first}: its session cannot be rendered here" in err
    assert "1 of 2 cases did not run (above); the table holds the others" in err
    assert f"| {second} |" in out and f"| {first} |" not in out
    assert (tmp_path / "accuracy.json").is_file()
