"""End to end accuracy on rendered sessions: the accuracy targets, per shape.

Each session is rendered by the synthetic renderer (the independent oracle), read
back through load_session / read_frames (so video compression is included), and
every frame goes through build_model / reconstruct_frame. The frames of a short
session sweep one whole motion cycle, so 12 frames show 12 different poses.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.measure.evaluate import EvaluationReport, evaluate_centerlines, evaluate_recording
from pipeline.reconstruct.frame import build_model, reconstruct_frame
from pipeline.reconstruct.frame_task import process_range
from pipeline.reconstruct.tip_shape import with_session_tip
from pipeline.run.runner import process_session
from pipeline.session.folder import load_session
from pipeline.session.video import read_frames
from pipeline.synth import render_session
from pipeline.synth.variety import Case, draw_cases, render_case

FRAMES = 12

# The accuracy targets: mean and p95 of the symmetric centreline distance (mm),
# median tip error (mm), mean length error (%), failed frames.
MEAN_MM, P95_MM, TIP_MM, LENGTH_PCT = 0.4, 1.0, 1.0, 1.0


def _measure(directory: Path) -> EvaluationReport:
    """Reconstruct every frame of a rendered session and evaluate it against its truth."""
    session = load_session(directory)
    model = build_model(session)
    truth = np.load(directory / "ground_truth.npz")["centerlines"]
    streams = [read_frames(p, 0, session.frame_count) for p in session.video_paths]
    curves = np.full((session.frame_count, model.settings.centerline.points, 3), np.nan)
    for index in range(session.frame_count):
        result = reconstruct_frame(index, [next(s)[1] for s in streams], model)
        if result.status == "ok" and result.centerline_mm is not None:
            curves[index] = result.centerline_mm
    return evaluate_centerlines(curves, truth)


SESSIONS = {
    "bend_rotate": {"shape": "bend_rotate"},
    "s_curve": {"shape": "s_curve"},
    "straight": {"shape": "straight"},
    "three_segments": {"shape": "three_segments"},
    "helix": {"shape": "helix"},
    # Sessions unlike the demo: the other camera placement, thicker and thinner tubes.
    "unseen_helix_ninety_r9": {"shape": "helix", "arrangement": "ninety", "radius_mm": 9.0},
    "unseen_bend_ninety_r4": {"shape": "bend_rotate", "arrangement": "ninety", "radius_mm": 4.0, "seed": 5},
    "unseen_loop_r4": {"shape": "loop", "radius_mm": 4.0, "seed": 3},
    "loop": {"shape": "loop"},
    "unseen_loop_ninety_r9": {"shape": "loop", "arrangement": "ninety", "radius_mm": 9.0, "seed": 7},
}

# Loops (the tip coming back within a diameter or two of its stem, crossing it
# in the views) meet the targets, the thick one too: its tip lies against the
# stem in every view and the hull merges them; the tip is bent to the grey
# levels, the stem under it bridged, and the tip where the curve's own course
# takes it tried (pipeline.reconstruct.tip_bend, pipeline.reconstruct.loop_tip). Measured on these
# 12-frame sessions (mean / p95 / median tip mm / length %):
#   loop (oblique, r 6):   0.22 / 0.55 / 0.32 / 0.27
#   unseen_loop_ninety_r9: 0.26 / 0.83 / 0.62 / 0.25
#   unseen_loop_r4:        0.18 / 0.42 / 0.66 / 0.23


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("accuracy")
    out = {}
    for name, kwargs in SESSIONS.items():
        directory = root / name
        render_session(directory, frames=FRAMES, progress=False, jobs=1, **kwargs)  # type: ignore[arg-type]
        out[name] = directory
    return out


@pytest.mark.slow
@pytest.mark.parametrize("name", list(SESSIONS))
def test_accuracy_targets(name: str, rendered: dict[str, Path]) -> None:
    acc = _measure(rendered[name])
    assert acc.failed_frames == 0
    assert acc.mean_mm <= MEAN_MM, acc
    assert acc.p95_mm <= P95_MM, acc
    assert acc.tip_median_mm <= TIP_MM, acc
    assert acc.length_error_pct <= LENGTH_PCT, acc


# Tip jitter needs motion at a real pace and enough frames for the temporal
# smoothing: 90-frame sessions (one motion cycle in 3 s), processed end to end
# (process_session smooths after the last frame) and evaluated from the recording.
# The straight tube barely moves, so its true jitter is tiny and the ratio hardest.
JITTER_FRAMES = 90
JITTER_RATIO = 1.5
JITTER_SESSIONS = {
    "straight_r8": {"shape": "straight", "radius_mm": 8.0, "seed": 4},
    "bend_ninety_r5": {"shape": "bend_rotate", "arrangement": "ninety", "radius_mm": 5.0, "seed": 6},
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(JITTER_SESSIONS))
def test_smoothed_tip_jitter_and_accuracy(name: str, tmp_path: Path) -> None:
    directory = tmp_path / name
    render_session(directory, frames=JITTER_FRAMES, progress=False, jobs=1, **JITTER_SESSIONS[name])  # type: ignore[arg-type]
    process_session(load_session(directory), out_dir=tmp_path, jobs=1, images=False, progress=False)
    smoothed = evaluate_recording(tmp_path / f"{name}.mcap", directory).smoothed
    assert smoothed is not None
    assert smoothed.jitter_ratio <= JITTER_RATIO, smoothed
    assert smoothed.failed_frames == 0
    assert smoothed.mean_mm <= MEAN_MM, smoothed
    assert smoothed.p95_mm <= P95_MM, smoothed
    assert smoothed.tip_median_mm <= TIP_MM, smoothed
    assert smoothed.length_error_pct <= LENGTH_PCT, smoothed


# The tracked model on a seeded draw of the renderer's variety (random shapes, round
# and flat ends, spacer disks, a dark object in one view, flicker, both rigs), at
# 30 frames a second, processed as a run does (pipeline.reconstruct.frame_task.process_range:
# tracked, segments and all). Held here: the kinds the model covers, three cameras
# and a uniform radius (disks included); tapered and stepped tubes and two-camera
# rigs are measured in docs/accuracy.md and not yet held to the targets.
# The bounds are the tracked model's targets; measured on these four cases (a random
# shape beside a dark object, a straight tube with disks, a round end, disks beside a
# dark object): mean 0.09-0.19, p95 0.19-0.38, tip median 0.24-0.41 mm, no frame off.
DRAW_SEED, DRAW_CASES, DRAW_FRAMES = 11, 4, 40
DRAW_MEAN_MM, DRAW_P95_MM, DRAW_TIP_MM = 0.2, 0.5, 0.5


def _drawn_cases() -> list[Case]:
    cases = draw_cases(DRAW_SEED, 40)
    return [c for c in cases if c.cameras == 3 and c.profile in ("uniform", "disks")][:DRAW_CASES]


@pytest.mark.slow
@pytest.mark.parametrize("case", _drawn_cases(), ids=lambda c: c.name)
def test_the_tracked_model_on_drawn_robots(case: Case, tmp_path: Path) -> None:
    directory = render_case(case, tmp_path / case.name, DRAW_FRAMES, jobs=1)
    session = load_session(directory)
    model, _ = with_session_tip(build_model(session), session.video_paths, 0, session.frame_count)
    names = [c.name for c in session.cameras]
    outputs = process_range(model, session.video_paths, names, 0, session.frame_count, images=False)
    curves = np.stack([o.result.centerline_mm for o in outputs if o.result.centerline_mm is not None])
    assert len(curves) == DRAW_FRAMES  # no failed frame
    truth = np.load(directory / "ground_truth.npz")["centerlines"]
    acc = evaluate_centerlines(curves, truth)
    assert acc.mean_mm <= DRAW_MEAN_MM, acc
    assert acc.p95_mm <= DRAW_P95_MM, acc
    assert acc.tip_median_mm <= DRAW_TIP_MM, acc
    # Every frame more than 2 mm off somewhere carries the suspect flag.
    suspect = {o.result.index for o in outputs if o.result.suspect}
    assert set(acc.off_indices) <= suspect, (acc.off_indices, sorted(suspect))
