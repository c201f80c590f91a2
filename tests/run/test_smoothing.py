"""Temporal smoothing: less noise and jitter on slow motion, no blur on fast motion, NaN-safe."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from conftest import build_session
from numpy.typing import NDArray
from scipy.interpolate import make_smoothing_spline

from pipeline.measure.evaluate import tip_jitter
from pipeline.reconstruct.frame_result import FrameResult
from pipeline.record.load import load_recording
from pipeline.run.runner import process_session
from pipeline.run.smoothing import _spline_predictions, smooth_centerlines
from pipeline.session.folder import load_session

FPS = 30.0
LENGTH_MM = 100.0


def bending_arcs(bend_rad: NDArray[np.float64], *, n_points: int = 16) -> NDArray[np.float64]:
    """(F, n_points, 3) planar arcs of length 100 mm rising from the origin along +z,
    bent by ``bend_rad`` (F,) in the x-z plane: the manipulator's typical motion."""
    u = np.linspace(0.0, 1.0, n_points)[None, :]
    # Keep away from the 0/0 of a straight arc; 1e-9 rad is straight to 1e-10 mm.
    theta = np.where(np.abs(bend_rad) < 1e-9, 1e-9, bend_rad)[:, None]
    x = LENGTH_MM * (1.0 - np.cos(theta * u)) / theta
    z = LENGTH_MM * np.sin(theta * u) / theta
    return np.stack([x, np.zeros_like(x), z], axis=-1)


def times(frames: int) -> NDArray[np.float64]:
    return np.arange(frames) / FPS


def test_noise_and_jitter_drop_on_slow_motion() -> None:
    t = times(120)
    truth = bending_arcs(1.0 * np.sin(2 * np.pi * 0.3 * t))
    noisy = truth + np.random.default_rng(0).normal(0.0, 0.3, truth.shape)
    smoothed = smooth_centerlines(noisy, t)

    raw_err = np.linalg.norm(noisy - truth, axis=-1).mean()
    smooth_err = np.linalg.norm(smoothed - truth, axis=-1).mean()
    # Measured 0.45 of the raw error; 0.85 leaves room for other noise draws.
    assert smooth_err < 0.85 * raw_err
    raw_jitter = tip_jitter(noisy[:, -1])
    smooth_jitter = tip_jitter(smoothed[:, -1])
    # The stiff spline cross-validation picks here removes nearly all of the noise's
    # second difference; 0.5 is a loose bound.
    assert smooth_jitter < 0.5 * raw_jitter


def test_slow_noisy_motion_gets_the_jitter_of_the_truth() -> None:
    # The target: tip jitter within 1.5x the truth's. A 10 s bending cycle (the demo's
    # pace) seen with 0.3 mm of per-frame noise, as the reconstruction's tip has.
    t = times(600)
    truth = bending_arcs(1.0 * np.sin(2 * np.pi * 0.1 * t))
    noisy = truth + np.random.default_rng(5).normal(0.0, 0.3, truth.shape)
    smoothed = smooth_centerlines(noisy, t)
    assert tip_jitter(noisy[:, -1]) > 10 * tip_jitter(truth[:, -1])  # the noise dominates
    assert tip_jitter(smoothed[:, -1]) < 1.5 * tip_jitter(truth[:, -1])


def test_noise_correlated_between_neighbouring_frames_is_not_taken_for_motion() -> None:
    # The reconstruction's errors are alike in neighbouring frames (lag-1
    # autocorrelation ~0.5 at the tip): a spline through a frame's immediate
    # neighbours predicts its error, and cross-validation on them chose splines
    # that followed it (7.9x the truth's jitter on a nearly still straight tube).
    # Here, the straight session's sway seen with AR(1) noise of 0.3 mm.
    t = times(150)
    truth = bending_arcs(0.05 * np.sin(2 * np.pi * 0.2 * t))
    white = np.random.default_rng(3).normal(0.0, 0.3, truth.shape)
    rho = 0.55
    noise = white.copy()
    for f in range(1, len(t)):
        noise[f] = rho * noise[f - 1] + np.sqrt(1.0 - rho**2) * white[f]
    smoothed = smooth_centerlines(truth + noise, t)
    assert tip_jitter(smoothed[:, -1]) < 1.5 * tip_jitter(truth[:, -1])


def rotating_arcs(plane_rad: NDArray[np.float64], *, bend_rad: float = 1.0) -> NDArray[np.float64]:
    """(F, 16, 3) arcs bent by ``bend_rad`` whose bending plane turns to ``plane_rad`` (F,)."""
    arcs = bending_arcs(np.full(len(plane_rad), bend_rad))
    c, s = np.cos(plane_rad)[:, None], np.sin(plane_rad)[:, None]
    x, y, z = arcs[..., 0], arcs[..., 1], arcs[..., 2]
    return np.stack([c * x - s * y, s * x + c * y, z], axis=-1)


@pytest.mark.parametrize(
    ("motion", "min_tip_travel_mm"),
    [
        # Bending +-34 degrees at 2 Hz: the tip swings 55 mm each way in 0.25 s.
        (lambda t: bending_arcs(0.6 * np.sin(2 * np.pi * 2.0 * t)), 50.0),
        # A 57-degree bend whose plane turns at 2 and 3 Hz: the tip circles at 0.6-0.9 m/s.
        (lambda t: rotating_arcs(2 * np.pi * 2.0 * t), 90.0),
        (lambda t: rotating_arcs(2 * np.pi * 3.0 * t), 90.0),
    ],
)
def test_fast_motion_is_not_blurred(
    motion: Callable[[NDArray[np.float64]], NDArray[np.float64]], min_tip_travel_mm: float
) -> None:
    t = times(90)
    truth = motion(t)
    assert np.ptp(truth[:, -1, 0]) > min_tip_travel_mm  # the motion really is fast
    smoothed = smooth_centerlines(truth, t)
    # Smoothing must not blur real motion; 0.1 mm is 1/20 of a voxel.
    assert np.abs(smoothed - truth).max() < 0.1


def test_polynomial_motion_is_kept_exactly_with_uneven_timestamps() -> None:
    # A local fit of degree 6 reproduces any motion polynomial of degree 6, whatever the sampling.
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.uniform(0.02, 0.05, 40))
    coeffs = rng.normal(0.0, 5.0, (7, 8, 3))
    curves = sum(c[None] * (t[:, None, None] - t.mean()) ** k for k, c in enumerate(coeffs))
    smoothed = smooth_centerlines(curves, t)
    # Noise-free: cross-validation picks the most supple spline (weight 1e-6 in frame
    # steps), which misses a degree-6 motion of ~10 mm by ~1e-7 mm.
    np.testing.assert_allclose(smoothed, curves, atol=1e-5)


@pytest.mark.parametrize("lam", [1e-6, 1e-2, 1.0, 1e2, 1e4])
def test_cross_validation_splines_are_scipys_smoothing_splines(lam: float) -> None:
    # The cross-validation solves its splines in Reinsch's form; they must be the
    # curves make_smoothing_spline fits (uneven knots, several series, new points
    # anywhere inside, on a knot included).
    rng = np.random.default_rng(7)
    x = np.cumsum(rng.uniform(0.5, 2.0, 40))
    y = np.cumsum(rng.normal(0.0, 1.0, (40, 5)), axis=0)
    x_new = np.concatenate([rng.uniform(x[0], x[-1], 30), x[[0, 7, -1]]])
    expected = make_smoothing_spline(x, y, lam=lam)(x_new)
    (got,) = _spline_predictions(x, y, x_new, np.array([lam]))
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-8 * np.abs(y).max())


def test_failed_frames_stay_nan_and_do_not_poison_neighbours() -> None:
    t = times(60)
    truth = bending_arcs(1.2 * np.sin(2 * np.pi * 1.0 * t))
    pred = truth.copy()
    failed = [10, 11, 30, 59]
    pred[failed] = np.nan
    smoothed = smooth_centerlines(pred, t)

    assert np.isnan(smoothed[failed]).all()
    ok = np.setdiff1d(np.arange(60), failed)
    assert np.isfinite(smoothed[ok]).all()
    # Neighbours of the gaps are fitted from fewer frames but stay as exact as elsewhere.
    assert np.abs(smoothed[ok] - truth[ok]).max() < 0.1


def test_a_wrong_frame_is_replaced_not_spread() -> None:
    # Frames 20 and 41 were reconstructed 15 mm off (a wrong tip, a mis-ordered loop).
    t = times(60)
    truth = bending_arcs(1.0 * np.sin(2 * np.pi * 0.5 * t))
    pred = truth.copy()
    pred[20, 8:] += [15.0, 0.0, 0.0]
    pred[41] += [0.0, 15.0, 0.0]
    smoothed = smooth_centerlines(pred, t)
    # Both frames are found and left out: neighbours are untouched and the
    # wrong frames become their neighbours' fit (exact to the filter's blur, < 0.01 mm here).
    assert np.abs(smoothed - truth).max() < 0.1
    plain = smooth_centerlines(pred, t, reject_outliers=False)
    assert (
        np.abs(plain - truth).max(axis=(1, 2))[[19, 21, 40, 42]].min() > 1.0
    )  # what least squares alone does


@pytest.mark.parametrize("wrong", [2, 3, 56, 57])
def test_a_wrong_frame_near_the_ends_is_replaced(wrong: int) -> None:
    # Near the ends the degree-6 local fit is one-sided and passes too much noise to
    # judge a frame; a wrong frame there was kept (a 5.6 mm tip at frame 147 of 150
    # took a loop's smoothed jitter from 1.1 to 35 times the truth's). The first and
    # last two frames are still not judged: a fit from one side only is pulled by the
    # wrong frame as much as the frame itself is off.
    t = times(60)
    truth = bending_arcs(1.0 * np.sin(2 * np.pi * 0.5 * t))
    pred = truth.copy()
    pred[wrong, 8:] += [6.0, 0.0, 0.0]
    smoothed = smooth_centerlines(pred, t)
    # The wrong frame becomes the spline through its neighbours: within the spline's
    # extrapolation error of a 0.5 Hz motion (measured < 0.5 mm at the very end).
    assert np.abs(smoothed[wrong] - truth[wrong]).max() < 0.5
    others = np.arange(60) != wrong
    assert np.abs(smoothed[others] - truth[others]).max() < 0.1


def test_three_wrong_frames_in_a_row_are_replaced() -> None:
    t = times(60)
    truth = bending_arcs(1.0 * np.sin(2 * np.pi * 0.5 * t))
    pred = truth.copy()
    pred[28:31] += np.random.default_rng(3).normal(0.0, 8.0, (3, 16, 3))
    smoothed = smooth_centerlines(pred, t)
    # Outliers are sought in +-8 frames: three in a row leave 14 good frames to fit.
    assert np.abs(smoothed - truth).max() < 0.1


def test_mostly_wrong_frames_are_left_as_they_are() -> None:
    # Every other frame is wrong (a pose the reconstruction keeps failing on): no fit
    # can be trusted, so smoothing must not mix right and wrong frames.
    t = times(40)
    truth = bending_arcs(1.0 * np.sin(2 * np.pi * 0.5 * t))
    pred = truth.copy()
    pred[::2] += np.random.default_rng(4).normal(0.0, 10.0, (20, 16, 3))
    smoothed = smooth_centerlines(pred, t)
    raw_err = np.linalg.norm(pred - truth, axis=2).mean(axis=1)
    smooth_err = np.linalg.norm(smoothed - truth, axis=2).mean(axis=1)
    # No frame ends up worse than reconstructed (0.01 mm: rounding, and the filter's blur).
    assert (smooth_err <= raw_err + 0.01).all()


def test_all_failed_or_single_frame_pass_through() -> None:
    nan = np.full((5, 4, 3), np.nan)
    assert np.isnan(smooth_centerlines(nan, times(5))).all()
    one = np.ones((1, 4, 3))
    np.testing.assert_array_equal(smooth_centerlines(one, times(1)), one)


def test_bad_timestamps_are_refused() -> None:
    with pytest.raises(ValueError, match="strictly increasing"):
        smooth_centerlines(np.zeros((3, 4, 3)), np.array([0.0, 0.0, 1.0]))
    with pytest.raises(ValueError, match="2 timestamps for 3 frames"):
        smooth_centerlines(np.zeros((3, 4, 3)), np.array([0.0, 1.0]))


_WRONG_FRAME = 31


def _swaying_rod(index: int, images: object, model: object) -> tuple[FrameResult, None]:
    """A stand-in frame function: a rod swaying smoothly, frame _WRONG_FRAME's curve 5 mm off."""
    z = np.linspace(0.0, 160.0, 64)
    sway = 10.0 * np.sin(index / 9.0) * (z / 160.0) ** 2
    curve = np.column_stack([128.0 + sway, np.full_like(z, 128.0), z])
    if index == _WRONG_FRAME:
        curve[:, 1] += 5.0 * z / 160.0
    voxels = np.full((20, 3), 128.0, dtype=np.float32)
    return FrameResult(index=index, status="ok", points_mm=voxels, centerline_mm=curve, length_mm=160.0), None


def test_a_frame_far_from_its_smoothed_curve_is_flagged_suspect_in_the_recording(tmp_path: Path) -> None:
    session = load_session(build_session(tmp_path / "session", frames=60))
    summary = process_session(
        session, out_dir=tmp_path / "out", jobs=1, images=False, progress=False, frame_fn=_swaying_rod
    )
    assert [frame for frame, _ in summary.frames_suspect] == [_WRONG_FRAME]
    recording = load_recording(tmp_path / "out" / f"{session.name}.mcap")
    flagged = {m["frame"]: m["suspect_reason"] for m in recording.metrics if m["suspect"]}
    assert list(flagged) == [_WRONG_FRAME] and "from the smoothed curve" in flagged[_WRONG_FRAME]
    assert len(recording.metrics) == 60  # one frame's metrics each, the last written
    wrong = next(m for m in recording.metrics if m["frame"] == _WRONG_FRAME)
    assert wrong["length_m"] == pytest.approx(0.16) and wrong["status"] == "ok"


def test_a_frame_whose_length_is_not_the_runs_is_flagged_after_the_run(tmp_path: Path) -> None:
    # A curve a few mm short over a few frames whose course the smoothed curve follows (a
    # slow drift): the run's length, not the track's, says so.
    short = range(20, 26)

    def shortened(index: int, images: object, model: object) -> tuple[FrameResult, None]:
        result, _ = _swaying_rod(index, images, model)
        if index == _WRONG_FRAME:  # back on the sway: only the lengths tell
            result = dataclasses.replace(
                result, centerline_mm=_swaying_rod(index - 1, None, None)[0].centerline_mm
            )
        return (dataclasses.replace(result, length_mm=155.0) if index in short else result), None

    session = load_session(build_session(tmp_path / "session", frames=60))
    summary = process_session(
        session, out_dir=tmp_path / "out", jobs=1, images=False, progress=False, frame_fn=shortened
    )
    assert [frame for frame, _ in summary.frames_suspect] == list(short)
    recording = load_recording(tmp_path / "out" / f"{session.name}.mcap")
    flagged = {m["frame"]: m["suspect_reason"] for m in recording.metrics if m["suspect"]}
    assert all(flagged[i] == "length 155.0 mm, -5.0 mm from the run's" for i in short), flagged


def test_a_doubt_over_the_tube_end_makes_every_written_frame_suspect(tmp_path: Path) -> None:
    from pipeline.reconstruct.frame_task import FrameOutput
    from pipeline.reconstruct.tip_shape import TIP_DOUBT
    from pipeline.run.output_target import prepare_outputs
    from pipeline.run.outputs import Writers

    session = load_session(build_session(tmp_path / "session", frames=60))
    target = prepare_outputs(tmp_path / "out", session.name, force=False)
    try:
        writer = Writers(session, target, images=False, frame_doubt=TIP_DOUBT)
        for index in range(40):
            result, _ = _swaying_rod(index, None, None)
            if index == 7:
                result = FrameResult.failed(index, "camera 'cam0' image could not be decoded")
            writer.write(FrameOutput(result=result, jpegs=None, silhouettes_png=None))
        writer.finish()
        summary = writer.summary(0.0)
    finally:
        target.release(failed=False)
    recording = load_recording(tmp_path / "out" / f"{session.name}.mcap")
    reasons = {m["frame"]: m["suspect_reason"] for m in recording.metrics}
    ok = [i for i in range(40) if i != 7]
    # Every ok frame carries the doubt (the wrong frame too, already suspect, so not
    # written again beside its smoothed curve); the failed frame is not suspect, only failed.
    assert [frame for frame, _ in summary.frames_suspect] == ok
    assert all(reasons[i] == TIP_DOUBT for i in ok) and reasons[7] == ""
    assert len(recording.metrics) == 40


def test_a_loosely_placed_course_is_written_suspect_but_leaves_the_track_alone(tmp_path: Path) -> None:
    from pipeline.reconstruct.frame_task import FrameOutput
    from pipeline.reconstruct.tracking import velocity_pair
    from pipeline.run.output_target import prepare_outputs
    from pipeline.run.outputs import Writers

    loose = "its course 40-96 mm from the base is barely seen across (the views look along it)"
    session = load_session(build_session(tmp_path / "session", frames=60))
    target = prepare_outputs(tmp_path / "out", session.name, force=False)
    results = []
    try:
        writer = Writers(session, target, images=False)
        for index in range(30):
            result, _ = _swaying_rod(index, None, None)
            if index in (11, 12):
                result = dataclasses.replace(result, doubt_reason=loose)
            results.append(result)
            writer.write(FrameOutput(result=result, jpegs=None, silhouettes_png=None))
        writer.finish()
        summary = writer.summary(0.0)
    finally:
        target.release(failed=False)
    # The track still takes its velocity from those frames: their course elsewhere holds.
    assert velocity_pair(results[:13]) is not None
    recording = load_recording(tmp_path / "out" / f"{session.name}.mcap")
    reasons = {m["frame"]: m["suspect_reason"] for m in recording.metrics if m["suspect"]}
    assert reasons == {11: loose, 12: loose}
    assert [frame for frame, _ in summary.frames_suspect] == [11, 12]
