"""Tracking: segments at fixed frames, the prediction, and curves that do not depend
on how a run splits its frames."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pipeline.geometry.polyline import axis_gap_mm
from pipeline.measure.evaluate import centerline_distances
from pipeline.reconstruct import frame as frame_module
from pipeline.reconstruct.frame_result import FrameResult
from pipeline.reconstruct.frame_task import LOST_FITS_KEPT, Tracker, decode_frames, process_range
from pipeline.reconstruct.model import build_model
from pipeline.reconstruct.tracking import (
    LENGTH_FRAMES,
    MISS_FRAMES,
    SEGMENT_FRAMES,
    WARMUP_FRAMES,
    TrackedFit,
    held_length,
    predict_axis,
    predict_length,
    prediction_miss_mm,
    segment_start,
    track_start,
    track_tube,
    velocity_pair,
)
from pipeline.session.folder import Session, load_session
from pipeline.synth import render_session
from pipeline.synth.session_render import SceneOptions
from pipeline.synth.variety import Case, draw_cases, render_case


def _ok(index: int, axis_mm: np.ndarray) -> FrameResult:
    return FrameResult(index=index, status="ok", centerline_mm=axis_mm, radius_mm=5.0)


def test_tracks_start_a_few_frames_before_their_segment() -> None:
    assert segment_start(0) == 0 and track_start(0) == 0
    assert segment_start(SEGMENT_FRAMES - 1) == 0
    assert segment_start(SEGMENT_FRAMES) == SEGMENT_FRAMES
    assert track_start(SEGMENT_FRAMES + 5) == SEGMENT_FRAMES - WARMUP_FRAMES
    assert track_start(WARMUP_FRAMES - 1) == 0


def test_the_prediction_moves_the_last_curve_on_by_its_velocity() -> None:
    axis = np.column_stack([np.zeros(8), np.zeros(8), np.linspace(0.0, 70.0, 8)])
    step = np.array([1.0, -0.5, 0.0])
    predicted = predict_axis([_ok(4, axis), _ok(5, axis + step)])
    assert predicted is not None
    np.testing.assert_allclose(predicted, axis + 2 * step)
    # Across gaps (a live run drops frames): the same velocity per frame, over the gap.
    np.testing.assert_allclose(predict_axis([_ok(3, axis), _ok(5, axis + step)]), axis + 1.5 * step)  # type: ignore[arg-type]
    np.testing.assert_allclose(predict_axis([_ok(4, axis), _ok(5, axis + step)], 8), axis + 4 * step)  # type: ignore[arg-type]


def test_a_suspect_frame_lends_the_prediction_no_velocity() -> None:
    axis = np.column_stack([np.zeros(8), np.zeros(8), np.linspace(0.0, 70.0, 8)])
    short = axis * np.array([1.0, 1.0, 0.5])  # a curve cut short: its samples bunch up
    suspect = replace(_ok(4, short), suspect_reason="length 35.0 mm, -35.0 mm from its track's")
    # From a suspect frame on: the last curve as it is, not moved on by a made-up velocity.
    np.testing.assert_allclose(predict_axis([suspect, _ok(5, axis)]), axis)  # type: ignore[arg-type]
    last = replace(_ok(5, short), suspect_reason="length 35.0 mm, -35.0 mm from its track's")
    np.testing.assert_allclose(predict_axis([_ok(4, axis), last]), short)  # type: ignore[arg-type]


def test_a_fast_tube_is_judged_against_its_velocity_not_against_a_prediction_held_still(
    tmp_path: Path,
) -> None:
    # A three-segment arm sweeping ~25 mm a frame. After a suspect frame the prediction
    # holds the last curve still (it lends no velocity), and so misses this tube by a
    # frame's motion: a frame fitted from it is not judged against it, or every other
    # frame of a fast sweep would be flagged for a jump it did not make.
    render_session(tmp_path, shape="three_segments", frames=30, seed=4, progress=False, jobs=1)
    session = load_session(tmp_path)
    model = build_model(session)
    frames = dict(decode_frames(session.video_paths, range(9)))
    truth = np.load(tmp_path / "ground_truth.npz")["centerlines"]
    assert np.linalg.norm(truth[8] - truth[7], axis=1).max() > 4 * session.settings.manipulator.radius_mm
    previous: list[FrameResult] = []
    for index in range(8):
        previous.append(frame_module.reconstruct_with_silhouettes(index, frames[index], model, previous)[0])
    held = [replace(previous[-2], suspect_reason="a reason"), replace(previous[-1], suspect_reason="")]
    assert velocity_pair(held) is None
    result, _ = frame_module.reconstruct_with_silhouettes(8, frames[8], model, held)
    assert result.centerline_mm is not None
    assert np.abs(result.centerline_mm[-1] - truth[8][-1]).max() < 2.0
    assert "prediction" not in result.suspect_reason


@pytest.mark.parametrize("seed", range(4))
def test_the_prediction_miss_is_the_least_of_the_last_frames_jumps(seed: int) -> None:
    rng = np.random.default_rng(seed)
    jumps = rng.uniform(0.0, 10.0, MISS_FRAMES + 2)
    track = [replace(_ok(i, np.zeros((8, 3))), jump_mm=float(j)) for i, j in enumerate(jumps)]
    # A tube that speeds up or turns misses each prediction by about as much: the least of
    # the last frames' misses; one wide miss among small ones is a jump, not a turn.
    assert prediction_miss_mm(track) == min(jumps[-MISS_FRAMES:])
    # No velocity to have missed by: too few frames, one not predicted with a velocity
    # (NaN), or a suspect one among them.
    assert prediction_miss_mm(track[-MISS_FRAMES + 1 :]) == 0.0
    for k in range(len(track) - MISS_FRAMES, len(track)):
        unpredicted = [*track[:k], replace(track[k], jump_mm=float("nan")), *track[k + 1 :]]
        flagged = [*track[:k], replace(track[k], suspect_reason="a reason"), *track[k + 1 :]]
        assert prediction_miss_mm(unpredicted) == 0.0 and prediction_miss_mm(flagged) == 0.0


def test_a_frame_records_how_far_it_lies_from_its_tracks_prediction(tmp_path: Path) -> None:
    render_session(tmp_path, shape="random", frames=6, seed=3, progress=False, jobs=1)
    session = load_session(tmp_path)
    model = build_model(session)
    previous: list[FrameResult] = []
    for index, images in decode_frames(session.video_paths, range(6)):
        previous.append(frame_module.reconstruct_with_silhouettes(index, images, model, previous)[0])
    # A frame whose two before it give the track's velocity lies as far from the last curve
    # moved on at that velocity as the flag judges; the others (the first two, and those
    # after a suspect frame) were predicted with no velocity: NaN.
    judged = 0
    for k in range(6):
        predicted = predict_axis(previous[:k])
        if velocity_pair(previous[:k]) is None or predicted is None:
            assert np.isnan(previous[k].jump_mm), k
        else:
            assert previous[k].jump_mm == axis_gap_mm(previous[k].centerline_mm, predicted), k
            judged += 1
    assert judged >= 2


@pytest.mark.parametrize(("shape", "seed"), [("bend_rotate", 0), ("random", 1), ("random", 2)])
def test_a_tube_whose_sweep_speeds_up_and_turns_is_not_flagged_for_it(
    tmp_path: Path, shape: str, seed: int
) -> None:
    # A 20-frame render plays its whole motion in those frames: the tube sweeps and turns
    # by up to a radius or more a frame, and misses each constant-velocity prediction by
    # about as much as the frame before missed its own.
    render_session(tmp_path, shape=shape, frames=20, seed=seed, progress=False, jobs=1)
    session = load_session(tmp_path)
    truth = np.load(tmp_path / "ground_truth.npz")["centerlines"]
    names = tuple(camera.name for camera in session.cameras)
    outputs = list(process_range(build_model(session), session.video_paths, names, 0, 20, images=False))
    jumps = [o.result.index for o in outputs if "prediction" in o.result.suspect_reason]
    off = [
        o.result.index
        for o in outputs
        if o.result.centerline_mm is None
        or centerline_distances(truth[o.result.index], o.result.centerline_mm).max() > 2.0
    ]
    assert not [index for index in jumps if index not in off]


def _lengths(indices: np.ndarray, lengths_mm: np.ndarray) -> list[FrameResult]:
    pairs = zip(indices, lengths_mm, strict=True)
    return [FrameResult(index=int(i), status="ok", length_mm=float(n)) for i, n in pairs]


@pytest.mark.parametrize("seed", range(6))
def test_the_length_predicted_follows_the_track_and_not_its_outliers(seed: int) -> None:
    rng = np.random.default_rng(seed)
    # A backbone of 150-350 mm, kept or extended at up to 0.5 mm a frame, read to
    # 0.3 mm, over a track with gaps (dropped frames), a few of whose frames have their
    # tip cut short or run on by 3-40 mm.
    frames = np.sort(rng.choice(np.arange(60), size=LENGTH_FRAMES + 5, replace=False))
    start, rate = rng.uniform(150.0, 350.0), rng.choice([0.0, rng.uniform(-0.5, 0.5)])
    lengths = start + rate * frames + rng.normal(0.0, 0.3, len(frames))
    wrong = rng.choice(len(frames), size=4, replace=False)
    lengths[wrong] += rng.choice([-1.0, 1.0], 4) * rng.uniform(3.0, 40.0, 4)
    track = _lengths(frames, lengths)
    ahead = int(frames[-1]) + int(rng.integers(1, 4))
    assert abs(predict_length(track, ahead) - (start + rate * ahead)) < 1.0
    # A failed frame (no length) says nothing, but takes its place among the last frames;
    # a track with no length at all predicts none.
    failed = FrameResult.failed(ahead - 1, "lost")
    assert predict_length([*track, failed], ahead) == predict_length(track[1 - LENGTH_FRAMES :], ahead)
    assert np.isnan(predict_length([FrameResult.failed(3, "lost")], 4))
    assert np.isnan(predict_length([], 4))
    # Fewer than three frames: their median.
    assert predict_length(track[:2], ahead) == pytest.approx(np.median(lengths[:2]))


@pytest.mark.parametrize("seed", range(4))
def test_the_length_held_for_an_unseen_end_does_not_run_on_with_a_creeping_track(seed: int) -> None:
    rng = np.random.default_rng(seed)
    # An end no view places, lengthened by the fit 1-3 mm a frame: over a young track
    # (5-10 frames) the line through its lengths runs on past the last of them, and a
    # tube held to it would creep on; the median stays among them. Over a second of a
    # steady track whose last 8-13 frames crept, it stays within 2 mm of the steady length.
    start = rng.uniform(150.0, 350.0)
    young = int(rng.integers(5, 11))
    lengths = start + np.cumsum(rng.uniform(1.0, 3.0, young))
    track = _lengths(np.arange(young), lengths)
    assert predict_length(track, young) > lengths[-1]
    assert held_length(track) == pytest.approx(np.median(lengths)) and held_length(track) < lengths[-1]
    creeping = int(rng.integers(8, 14))
    lengths = start + rng.normal(0.0, 0.3, LENGTH_FRAMES)
    lengths[-creeping:] += np.cumsum(rng.uniform(1.0, 3.0, creeping))
    assert abs(held_length(_lengths(np.arange(LENGTH_FRAMES), lengths)) - start) < 2.0
    assert np.isnan(held_length([])) and np.isnan(held_length([FrameResult.failed(3, "lost")]))


def test_a_track_whose_last_frame_has_no_curve_is_lost() -> None:
    axis = np.column_stack([np.zeros(8), np.zeros(8), np.linspace(0.0, 70.0, 8)])
    assert predict_axis([]) is None
    assert predict_axis([_ok(4, axis), FrameResult.failed(5, "camera lost")]) is None


def _tracked_with_losses(
    session: Session, frames: range, monkeypatch: pytest.MonkeyPatch
) -> tuple[list[FrameResult], list[TrackedFit]]:
    """``frames`` of ``session`` tracked one after the other: their results, and the first
    fit of each frame after the first (its ``lost`` says why the track was lost there,
    "" where it held)."""
    fits: list[TrackedFit] = []

    def recorded(*args: Any, **kwargs: Any) -> TrackedFit:
        fit = track_tube(*args, **kwargs)
        fits.append(fit)
        return fit

    monkeypatch.setattr(frame_module, "track_tube", recorded)
    tracker = Tracker(build_model(session), [c.name for c in session.cameras], images=False)
    results, held = [], []
    for n, (i, images) in enumerate(decode_frames(session.video_paths, frames)):
        first = len(fits)
        results.append(tracker.step(i, images).result)
        if n > 0:  # a frame's first fit, where there is a track, is its prediction's
            held.append(fits[first])
    return results, held


@pytest.mark.parametrize("seed", [1, 3])
def test_a_track_over_spacer_disks_is_lost_only_where_it_is_off_the_tube(
    tmp_path: Path, seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Disks, which the tube drawn does not have, leave about 1 % of every silhouette
    # unexplained: a frame is judged against what its track's frames usually leave, so a
    # track on the tube holds where a view's share crosses 1 %, and a track is lost for a
    # silhouette left unexplained only where its fit has left the tube. Over such sessions
    # of seeds 0-7 (24 frames, 2026-12-04) tracks were lost for it 3 times, 6 times
    # judged on 1 % alone.
    render_session(
        tmp_path,
        shape="random",
        frames=24,
        seed=seed,
        options=SceneOptions(profile="disks"),
        progress=False,
        jobs=1,
    )
    session = load_session(tmp_path)
    truth = np.load(tmp_path / "ground_truth.npz")["centerlines"]
    results, held = _tracked_with_losses(session, range(24), monkeypatch)
    kept = [fit for fit in held if not fit.lost]
    assert sum(fit.misfit > 0.01 for fit in kept) >= 3  # held where the disks' share crosses 1 %
    for index, fit in enumerate(held, start=1):
        if fit.lost == "leaves part of a silhouette unexplained":
            assert fit.curve is not None
            assert centerline_distances(fit.curve.points_mm, truth[index]).max() > 2.0
    assert sum(not r.tracked for r in results) <= 3


def _tracked_tip_errors(case: Case, directory: Path, frames: int) -> list[float]:
    """The drawn ``case`` rendered for ``frames`` frames and tracked from frame 0 with its
    true tube end: each frame's tip distance from the truth, mm."""
    session_dir = render_case(case, directory, frames, jobs=1)
    truth = np.load(session_dir / "ground_truth.npz")
    session = load_session(session_dir)
    model = replace(build_model(session), tip=str(truth["tip"]))
    tracker = Tracker(model, [c.name for c in session.cameras], images=False)
    return [
        float(np.linalg.norm(tracker.step(i, images).result.centerline_mm[-1] - truth["centerlines"][i][-1]))
        for i, images in decode_frames(session.video_paths, range(frames))
    ]


def test_a_tracked_tip_by_a_spacer_disk_does_not_curl_onto_it(tmp_path: Path) -> None:
    # A disk a radius or so from the end, seen at an angle, is read across a tangent
    # that is off by the tip's error: its chord's mid-point lies off the axis in the
    # same sense, and the tip curls frame after frame (this drawn case: median tip
    # 1.45 mm without the end's own width limit, 0.9 mm with it).
    drawn = next(c for c in draw_cases(2, 10) if c.profile == "disks" and c.cameras == 3)
    # With synth's own disks (1.5x, 2 mm thick, every 20 mm), which this measure was made on.
    case = replace(drawn, disk_spacing_mm=20.0, disk_ratio=1.5, disk_thickness_mm=2.0)
    assert np.median(_tracked_tip_errors(case, tmp_path, 24)) < 1.1


def test_a_tracked_tip_over_its_own_tube_in_one_view_is_placed_where_the_others_cannot(
    tmp_path: Path,
) -> None:
    # This drawn stepped tube's thin end lies over its own body in one view, and from
    # frame 26 on the other two see the course behind the tip nearly along one line: their
    # edges fix it in one direction across only, and unrefined it drifted along the other
    # (4.4 mm off at frame 40, four frames more than 2 mm off by frame 46).
    case = next(c for c in draw_cases(13, 8) if c.profile == "step" and c.cameras == 3)
    assert max(_tracked_tip_errors(case, tmp_path, 47)) < 2.0


def test_a_tracked_tip_that_meets_no_other_part_is_placed_by_the_grey_levels(tmp_path: Path) -> None:
    # This drawn tapered shape straightens toward its tip, where the side readings stop
    # (the tip zone): the course extrapolated from before the zone put its tip 0.65 mm
    # off (median over these 40 frames, 1.11 mm at worst) and drifted on after them.
    case = next(c for c in draw_cases(409, 8) if c.profile == "tapered" and c.cameras == 3)
    errors = _tracked_tip_errors(case, tmp_path, 40)
    assert np.median(errors) < 0.5
    assert max(errors) < 0.9


def test_a_loops_end_along_its_stem_is_placed_by_the_grey_levels(tmp_path: Path) -> None:
    # This thick loop's last 30-40 mm run along its stem, crowded in every view: no side
    # reading places them, and the course carried over them drifted 2-5 mm off in their
    # middle while the tip stayed placed (measured: 9 of these 60 frames more than 2 mm
    # off somewhere without the loose stretch's own bend, 3 with it).
    render_session(
        tmp_path,
        shape="loop",
        frames=60,
        seed=7,
        arrangement="ninety",
        radius_mm=7.0,
        options=SceneOptions(tip="round"),
        progress=False,
        jobs=1,
    )
    truth = np.load(tmp_path / "ground_truth.npz")
    session = load_session(tmp_path)
    tracker = Tracker(
        replace(build_model(session), tip="round"), [c.name for c in session.cameras], images=False
    )
    worst = []
    for i, images in decode_frames(session.video_paths, range(60)):
        curve, true = tracker.step(i, images).result.centerline_mm, truth["centerlines"][i]
        worst.append(max(centerline_distances(curve, true).max(), centerline_distances(true, curve).max()))
    assert sum(w > 2.0 for w in worst) <= 4


def test_a_track_that_falls_behind_its_tube_is_given_more_rounds_not_lost(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Fitted every fifth frame, the tube moves farther between fits than the track's
    # velocity predicts; where the first rounds leave part of a silhouette unexplained,
    # more rounds from where they got to catch it up (without them, frame 50 of this
    # random shape is started again from the hull for it). A fit that catches up by
    # more than LOST_JUMP_RADII is still started again (15, 20 and 35 here).
    render_session(tmp_path, shape="random", frames=60, seed=4, progress=False, jobs=1)
    results, held = _tracked_with_losses(load_session(tmp_path), range(0, 60, 5), monkeypatch)
    assert "leaves part of a silhouette unexplained" not in [fit.lost for fit in held]
    assert sum(not r.tracked for r in results) <= 4


@pytest.fixture(scope="module")
def session_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("tracking") / "bend"
    # Long enough to cross a segment boundary; the motion is fast (one cycle), which
    # is fine here: the test is about which frames a curve depends on, not accuracy.
    render_session(directory, frames=SEGMENT_FRAMES + 12, progress=False, jobs=1, seed=4)
    return directory


def test_a_frames_curve_does_not_depend_on_how_the_run_splits_the_frames(session_dir: Path) -> None:
    session = load_session(session_dir)
    model = build_model(session)
    names = [c.name for c in session.cameras]
    n = session.frame_count

    def curves(*spans: tuple[int, int]) -> dict[int, np.ndarray]:
        out = {}
        for start, stop in spans:
            for o in process_range(model, session.video_paths, names, start, stop, images=False):
                assert o.result.status == "ok", o.result.reason
                assert o.result.centerline_mm is not None
                out[o.result.index] = o.result.centerline_mm
        return out

    whole = curves((0, n))
    # Split inside a segment, at a segment boundary, and a range starting late.
    split = curves((0, 17), (17, SEGMENT_FRAMES), (SEGMENT_FRAMES, n))
    late = curves((SEGMENT_FRAMES + 5, n))
    assert sorted(whole) == sorted(split) == list(range(n))
    for i in range(n):
        np.testing.assert_array_equal(whole[i], split[i])
    for i in late:
        np.testing.assert_array_equal(whole[i], late[i])
    # The progress tally gets a byte per frame of the range, none for its warm-up.
    tally = session_dir.parent / "tally"
    process_range(model, session.video_paths, names, SEGMENT_FRAMES + 5, n, images=False, tally=str(tally))
    assert tally.stat().st_size == n - (SEGMENT_FRAMES + 5)
    # Most frames are fitted from their track, not from the hull.
    tracked = [o.result.tracked for o in process_range(model, session.video_paths, names, 0, n, images=False)]
    assert sum(tracked) >= n - 2 * (WARMUP_FRAMES + 1)


class _StartsHere:
    """Restarts (pipeline.reconstruct.frame_task.Restarts) computed at once in this process,
    but caught up only at the ``lag``-th look after the start (the lost frame's own the
    first), or when the frame may wait."""

    available = True

    def __init__(self, model: Any, lag: int) -> None:
        self.model, self.lag = model, lag
        self.started: list[int] = []
        self.before: list[FrameResult] = []
        self.track: list[FrameResult] = []
        self.results: list[FrameResult] = []
        self.pending = 0
        self.waited = 0  # looks at which the frame could wait (and was given the track)

    @property
    def under_way(self) -> bool:
        return bool(self.results)

    @property
    def nearly_caught_up(self) -> bool:
        return self.pending <= 1 and len(self.results) > 1

    def start(self, index: int, images: Any, previous: Any) -> bool:
        if self.results:
            return False
        self.started.append(index)
        self.before, self.track, self.pending = list(previous), list(previous), self.lag
        self.follow(index, images)
        return True

    def follow(self, index: int, images: Any) -> None:
        result = frame_module.reconstruct_with_silhouettes(index, images, self.model, self.track)[0]
        self.track = [*self.track, result][-LENGTH_FRAMES:]
        self.results.append(result)

    def caught_up(self, may_wait: Any) -> list[FrameResult] | None:
        if not self.results:
            return None
        if self.pending > 0:
            if not may_wait():
                self.pending -= 1
                return None
            self.waited += 1
        track, self.results = [*self.before, *self.results][-LENGTH_FRAMES:], []
        return track


def _rendered(directory: Path, *, frames: int, seed: int) -> tuple[Session, Any, list[str]]:
    """A random shape rendered into ``directory``: its session, model and camera names."""
    render_session(directory, shape="random", frames=frames, seed=seed, progress=False, jobs=1)
    session = load_session(directory)
    return session, build_model(session), [c.name for c in session.cameras]


def _same(a: FrameResult, b: FrameResult) -> bool:
    assert a.centerline_mm is not None and b.centerline_mm is not None
    return bool(np.array_equal(a.centerline_mm, b.centerline_mm)) and a.suspect_reason == b.suspect_reason


def test_a_lost_track_started_elsewhere_takes_over_as_process_has_it_once_caught_up(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # With its starts from the hull run elsewhere (a live run's restart worker), a frame
    # whose track is lost keeps the lost track's fit, flagged, the frames after go on from
    # it, and the started track follows them until it has caught up (three frames here); from
    # then on the frames are a waiting track's (process's), to the bit.
    session, model, names = _rendered(tmp_path, frames=20, seed=4)
    frames = decode_frames(session.video_paths, range(20))
    losing = {"now": False}

    def lost_when_told(*args: Any, **kwargs: Any) -> TrackedFit:
        fit = track_tube(*args, **kwargs)
        return replace(fit, lost="told to") if losing["now"] else fit

    monkeypatch.setattr(frame_module, "track_tube", lost_when_told)

    def run(tracker: Tracker) -> list[FrameResult]:
        out = []
        for i, images in frames:
            losing["now"] = i == 10
            out.append(tracker.step(i, images).result)
        return out

    waited = run(Tracker(model, names, images=False))
    assert [r.index for r in waited if not r.tracked] == [0, 10]
    starts = _StartsHere(model, lag=3)  # caught up with frame 12, taken over at 13
    went_on = run(Tracker(model, names, images=False, restarts=starts))
    assert starts.started == [10]
    assert went_on[10].lost == "told to" and "its track was lost here" in went_on[10].suspect_reason
    assert not any(r.lost for r in went_on[11:13])  # followed the lost fit
    assert [r.index for r in went_on if not _same(r, waited[r.index])] == [10, 11, 12]


def test_a_frame_lost_again_from_a_lost_fit_takes_the_started_track_once_it_is_there(tmp_path: Path) -> None:
    # Fitted every tenth frame, this random shape's track is lost at frames 10, 30 and 40
    # (started again from the hull there), and from the lost fits kept at 10 and 30 again
    # at 20 and 40.
    session, model, names = _rendered(tmp_path, frames=60, seed=4)
    frames = decode_frames(session.video_paths, range(0, 60, 10))
    waiting = Tracker(model, names, images=False)
    waited = [waiting.step(i, images).result for i, images in frames]
    assert [r.index for r in waited if not r.tracked] == [0, 10, 30, 40]

    # The tracks started at 10 and 30 have caught up by 20 and 40: those frames are fitted
    # from them, as process fits them, not from a fit that is a poor guide.
    starts = _StartsHere(model, lag=2)
    elsewhere = Tracker(model, names, images=False, restarts=starts)  # never waits at the loss
    went_on = [elsewhere.step(i, images).result for i, images in frames]
    assert starts.started == [10, 30]
    assert [r.index for r in went_on if r.lost and "its track was lost here" in r.suspect_reason] == [10, 30]
    assert [r.index for r, w in zip(went_on, waited, strict=True) if not _same(r, w)] == [10, 30]
    assert starts.waited == 0

    # The track started at 10 has not caught up by 20: frame 20 keeps its fit, flagged as
    # 10's was, without waiting (no frame-set could). Frame 30, lost after LOST_FITS_KEPT
    # lost fits, waits for the started track however long that takes, and is process's
    # (started again from the hull, as process has it). Frame 40, lost in process too,
    # starts the next track and cannot wait for it either.
    assert LOST_FITS_KEPT == 2
    slow = _StartsHere(model, lag=6)
    tracker = Tracker(model, names, images=False, restarts=slow)
    late = [tracker.step(i, images).result for i, images in frames]
    assert slow.started == [10, 40] and slow.waited == 1
    flagged = [r.index for r in late if r.lost and "its track was lost here" in r.suspect_reason]
    assert flagged == [10, 20, 40, 50]
    assert [r.index for r, w in zip(late, waited, strict=True) if not _same(r, w)] == [10, 20, 40, 50]

    # A start that comes while the frame can wait for it gives the frame process's result.
    patient = Tracker(model, names, images=False, restarts=_StartsHere(model, lag=2), may_wait=lambda: True)
    for (i, images), w in zip(frames, waited, strict=True):
        assert _same(patient.step(i, images).result, w)


def test_a_tracker_with_starts_elsewhere_starts_each_segments_track_where_process_does(
    tmp_path: Path,
) -> None:
    # process starts the track of each segment from the hull WARMUP_FRAMES before it (frame
    # 87 for the segment at 90); a tracker with starts elsewhere starts one there too, and
    # once it has caught up (taken over at 91 here) its frames are process's, whatever its
    # own track was before (here one started at frame 80).
    session, model, names = _rendered(tmp_path, frames=96, seed=5)
    processed = [o.result for o in process_range(model, session.video_paths, names, 80, 96, images=False)]
    starts = _StartsHere(model, lag=3)  # caught up with frame 90
    tracker = Tracker(model, names, images=False, restarts=starts)
    live = [tracker.step(i, images).result for i, images in decode_frames(session.video_paths, range(80, 96))]
    assert starts.started == [SEGMENT_FRAMES - WARMUP_FRAMES]
    differ = [r.index for r, p in zip(live, processed, strict=True) if not _same(r, p)]
    assert differ and max(differ) < SEGMENT_FRAMES + 1


@pytest.mark.parametrize("seed", range(3))
def test_a_frame_one_camera_took_at_another_moment_is_fitted_to_the_others_and_named(
    tmp_path: Path, seed: int
) -> None:
    # One camera's picture of frame 20 is its picture of frame 36 (a frame dropped and
    # doubled, a stream that stalled): the tube fitted to all three views is pulled off
    # in each, and the hull it would start again from is cut by the odd view.
    render_session(tmp_path, shape="random", frames=40, seed=seed, progress=False, jobs=1)
    session = load_session(tmp_path)
    model = build_model(session)
    truth = np.load(tmp_path / "ground_truth.npz")["centerlines"]
    odd = seed % len(session.cameras)
    late = dict(decode_frames(session.video_paths, [36]))[36][odd]
    previous: list[FrameResult] = []
    for index, images in decode_frames(session.video_paths, range(12, 24)):
        if index == 20:
            images = [late if view == odd else image for view, image in enumerate(images)]
        previous.append(frame_module.reconstruct_with_silhouettes(index, images, model, previous)[0])
    named = {r.index: r.suspect_reason for r in previous if "image disagrees" in r.suspect_reason}
    assert list(named) == [20]
    assert named[20].startswith(f"camera {session.cameras[odd].name}'s image disagrees")
    swapped = previous[20 - 12]
    assert swapped.tracked and swapped.centerline_mm is not None
    assert centerline_distances(truth[20], swapped.centerline_mm).max() < 1.0
    # The track goes on from it.
    assert all(r.tracked for r in previous[20 - 12 :])


@pytest.mark.parametrize("seed", [4, 5])
def test_a_lost_track_with_no_start_in_the_hull_keeps_its_fit_flagged(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, seed: int
) -> None:
    # A thin tube that the views' thresholds lose near the base: the track is lost there,
    # and neither the hull nor the voxels every view but one sees hold a start. The lost
    # track's fit is the frame's, flagged, where the frame would otherwise fail.
    render_session(tmp_path, shape="random", frames=6, seed=seed, progress=False, jobs=1)
    session = load_session(tmp_path)
    model = build_model(session)
    frames = decode_frames(session.video_paths, range(6))
    previous: list[FrameResult] = []
    for index, images in frames[:5]:
        previous.append(frame_module.reconstruct_with_silhouettes(index, images, model, previous)[0])
    assert all(r.status == "ok" for r in previous)
    track = frame_module.track_tube

    def lost_track(*args: Any, **kwargs: Any) -> TrackedFit:
        return replace(track(*args, **kwargs), lost="leaves part of a silhouette unexplained")

    def no_start(*args: Any, **kwargs: Any) -> Any:
        raise ValueError("the hull holds no tube near the base")

    monkeypatch.setattr(frame_module, "track_tube", lost_track)
    monkeypatch.setattr(frame_module, "fit_centerline", no_start)
    index, images = frames[5]
    result = frame_module.reconstruct_with_silhouettes(index, images, model, previous)[0]
    assert result.status == "ok" and result.tracked
    assert "no start from the hull: the hull holds no tube near the base" in result.lost
    assert result.suspect and result.suspect_reason.startswith("its track was lost here")
    truth = np.load(tmp_path / "ground_truth.npz")["centerlines"][index]
    assert result.centerline_mm is not None
    assert centerline_distances(truth, result.centerline_mm).mean() < 0.5
    # With no track to keep, the frame fails as before, with the hull's reason.
    alone = frame_module.reconstruct_with_silhouettes(index, images, model, [])[0]
    assert alone.status == "failed" and "the hull holds no tube near the base" in alone.reason
