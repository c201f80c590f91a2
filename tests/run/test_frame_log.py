"""The per-frame record a run keeps for its finish, on disk."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.run.frame_log import FrameLog


@pytest.mark.parametrize("seed", range(4))
def test_the_log_gives_back_each_frames_curve_and_metrics_as_added(seed: int, tmp_path: Path) -> None:
    rng = np.random.default_rng(seed)
    n_frames, n_points = int(rng.integers(5, 40)), int(rng.integers(8, 80))
    # Frames without a curve anywhere, the first ones included; messages of any length.
    has = rng.random(n_frames) > 0.3
    curves = [rng.normal(size=(n_points, 3)) * 100.0 if h else None for h in has]
    messages = [bytes(rng.integers(0, 256, int(rng.integers(0, 300)), dtype=np.uint8)) for _ in has]
    log = FrameLog(tmp_path)
    for k, (curve, message) in enumerate(zip(curves, messages, strict=True)):
        log.add(1000 + 2 * k, 10**18 + 33_333_333 * k, curve, message)
    assert len(log) == n_frames and list(log.frames) == [1000 + 2 * k for k in range(n_frames)]
    stacked = log.stacked_curves()
    if not has.any():
        assert stacked is None
    else:
        assert stacked is not None and stacked.shape == (n_frames, n_points, 3)
        for row, curve in zip(stacked, curves, strict=True):
            if curve is None:
                assert np.isnan(row).all()
            else:
                np.testing.assert_array_equal(row, curve)
    for k in rng.permutation(n_frames):
        assert log.metrics(int(k)) == messages[k]
    log.add(0, 0, None, b"after reading")  # reading does not disturb what comes next
    assert log.metrics(n_frames) == b"after reading"
    assert not list(tmp_path.iterdir())  # nothing named is left, even before closing
    log.close()


def test_curves_of_more_than_one_length_give_no_stack(tmp_path: Path) -> None:
    log = FrameLog(tmp_path)
    log.add(0, 0, np.zeros((10, 3)), b"{}")
    log.add(1, 1, np.zeros((12, 3)), b"{}")
    assert log.stacked_curves() is None and log.metrics(1) == b"{}"
    log.close()
