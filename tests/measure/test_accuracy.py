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
from conftest import LENGTH_PCT, MEAN_MM, P95_MM, TIP_MM

from pipeline.measure.evaluate import EvaluationReport, evaluate_centerlines
from pipeline.reconstruct.frame import build_model, reconstruct_frame
from pipeline.session.folder import load_session
from pipeline.session.video import read_frames
from pipeline.synth import render_session

FRAMES = 12


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
