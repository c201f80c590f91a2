"""The tube's radius along it, pooled over a session's frames (pipeline.reconstruct.radius_profile)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from pipeline.reconstruct.radius_profile import BIN_MM, HALF_WINDOW_BINS, MIN_FRAMES, RadiusProfile
from pipeline.reconstruct.side_readings import _radius_profile

FloatArray = NDArray[np.float64]


def _tube(rng: np.random.Generator, *, disks: bool) -> tuple[float, float, float, float, FloatArray]:
    """A tube stepped from ``wide`` to ``thin`` (mm) at ``step_mm`` of its ``length_mm``,
    or a uniform one (``wide`` throughout) with spacer disks at the arc lengths returned
    (mm; none on the stepped one: the renderer draws one or the other)."""
    length = float(rng.uniform(180.0, 260.0))
    wide = float(rng.uniform(4.5, 7.5))
    if disks:
        return (
            length,
            wide,
            wide,
            length,
            np.arange(float(rng.uniform(5.0, 15.0)), length, float(rng.uniform(14.0, 30.0))),
        )
    return (
        length,
        wide,
        wide * float(rng.uniform(0.6, 0.8)),
        float(rng.uniform(0.3, 0.7)) * length,
        np.zeros(0),
    )


def _frame_readings(
    rng: np.random.Generator, length: float, wide: float, thin: float, step: float, disks: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """One frame's two-edge readings (arc lengths, half-widths; mm) every 4 mm in two views,
    none over a stretch of 25-60 mm another part hides, wider over the disks, with noise
    and a few stray readings (another part's outline taken for an edge)."""
    arc = np.arange(6.0, length - 8.0, 4.0) + rng.uniform(0.0, 4.0)
    start = rng.uniform(0.0, length - 60.0)
    seen = (arc < start) | (arc > start + rng.uniform(25.0, 60.0))
    half = np.where(arc < step, wide, thin) + rng.normal(0.0, 0.05, len(arc))
    if len(disks):
        half[np.min(np.abs(arc[:, None] - disks[None, :]), axis=1) < 1.5] *= 1.6
    stray = rng.random(len(arc)) < 0.05
    half[stray] += rng.uniform(2.0, 6.0, stray.sum())
    arc, half = arc[seen], half[seen]
    return np.concatenate([arc, arc]), np.concatenate([half, half + rng.normal(0.0, 0.05, len(half))])


@pytest.mark.parametrize("disks", [False, True], ids=["stepped", "disks"])
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_the_frames_pooled_read_the_radius_each_frame_leaves_in_a_gap(seed: int, disks: bool) -> None:
    rng = np.random.default_rng(seed)
    length, wide, thin, step, at = _tube(rng, disks=disks)
    frames = [_frame_readings(rng, length, wide, thin, step, at) for _ in range(16)]
    profile = RadiusProfile.pooled(frames)
    assert profile is not None
    assert np.all(np.diff(profile.arc_mm) > 0)
    truth = np.where(profile.arc_mm < step, wide, thin)
    # Beyond the bins the step falls in, the radius of each side: the disks and the
    # stray readings are a minority of each window.
    clear = np.abs(profile.arc_mm - step) > BIN_MM
    np.testing.assert_allclose(profile.radius_mm[clear], truth[clear], atol=0.15)
    # The whole tube is read but for its ends.
    assert profile.arc_mm[0] < 12.0 and profile.arc_mm[-1] > length - 14.0
    # Outside the stretch read, no radius.
    assert np.isnan(profile.at(np.array([0.0, length + 5.0]))).all()


def test_too_few_frames_read_no_profile() -> None:
    rng = np.random.default_rng(4)
    length, wide, thin, step, at = _tube(rng, disks=False)
    frames = [_frame_readings(rng, length, wide, thin, step, at) for _ in range(MIN_FRAMES - 1)]
    assert RadiusProfile.pooled(frames) is None
    assert RadiusProfile.pooled([]) is None


def test_a_frames_gap_takes_the_sessions_radius_and_its_readings_stay_its_own() -> None:
    k = 50
    arc = np.arange(k) * 4.0
    truth = np.where(arc < 100.0, 6.0, 4.0)
    # One view reads the tube 0.2 mm wider than the session (this frame's blur), but not
    # from 60 to 140 mm, where another part hides it: the step lies in the gap.
    half = np.repeat(truth[:, None] + 0.2, 1, axis=1)
    both = ((arc < 60.0) | (arc > 140.0))[:, None]
    session = RadiusProfile(
        np.arange(10.0, 181.0, 2.0), np.where(np.arange(10.0, 181.0, 2.0) < 100.0, 6.0, 4.0)
    )
    alone = _radius_profile(arc, half, both, np.full(k, 6.0))
    pooled = _radius_profile(arc, half, both, np.full(k, 6.0), session)
    gap = ~both[:, 0]
    # Alone, the gap is a line from one side's radius to the other's: 1 mm off half way
    # into either side of the step.
    assert np.max(np.abs(alone[gap] - truth[gap])) > 0.8
    # Pooled, the gap has the session's radius, and what the frame reads is its own.
    np.testing.assert_allclose(pooled[gap], truth[gap])
    np.testing.assert_allclose(pooled[~gap], alone[~gap])
    # Beyond the stretch the session read (its last 12 mm here), the frame's own profile.
    beyond = arc > 180.0
    np.testing.assert_allclose(pooled[beyond], alone[beyond])


def test_the_window_keeps_a_step_where_it_is() -> None:
    """A running median of the bins keeps a step in place: each side's bins read its radius."""
    arc = np.arange(0.0, 200.0, 1.0)
    frames = [(arc, np.where(arc < 97.0, 6.0, 4.0)) for _ in range(MIN_FRAMES)]
    profile = RadiusProfile.pooled(frames)
    assert profile is not None
    before = profile.arc_mm < 96.0
    np.testing.assert_allclose(profile.radius_mm[before], 6.0)
    np.testing.assert_allclose(profile.radius_mm[profile.arc_mm > 98.0], 4.0)


@pytest.mark.parametrize("seed", range(4))
def test_the_profile_goes_through_the_recordings_metadata_whole(seed: int) -> None:
    rng = np.random.default_rng(seed)
    length, wide, thin, step, _ = _tube(rng, disks=False)
    readings = [_frame_readings(rng, length, wide, thin, step, np.zeros(0)) for _ in range(12)]
    profile = RadiusProfile.pooled(readings)
    assert profile is not None
    back = RadiusProfile.from_json(profile.to_json())
    assert back is not None
    np.testing.assert_allclose(back.arc_mm, profile.arc_mm, atol=5e-4)
    np.testing.assert_allclose(back.radius_mm, profile.radius_mm, atol=5e-4)
    # The summary's line names the radius's range and the stretch read.
    low, high = profile.radius_mm.min(), profile.radius_mm.max()
    assert profile.describe().startswith(f"{low:.2f}-{high:.2f} mm, read ")


@pytest.mark.parametrize(
    "text",
    [
        "",
        "3.0",
        "[1, 2]",
        '{"arc_mm": [1, 2]}',
        '{"arc_mm": [2, 1], "radius_mm": [3, 3]}',
        '{"arc_mm": [1, 2], "radius_mm": [3]}',
        '{"arc_mm": [1, 2], "radius_mm": [3, NaN]}',
        '{"arc_mm": "x", "radius_mm": "y"}',
    ],
)
def test_metadata_that_is_no_profile_reads_as_none(text: str) -> None:
    assert RadiusProfile.from_json(text) is None


def test_a_tube_of_one_radius_is_described_by_it() -> None:
    profile = RadiusProfile(np.arange(1.0, 200.0, BIN_MM), np.full(100, 3.004))
    assert profile.describe() == "3.00 mm, read 0-200 mm from the base on the session's sample frames"


@pytest.mark.parametrize("seed", range(4))
def test_a_taper_read_with_noise_is_followed_along_the_tube(seed: int) -> None:
    """The bins' running median follows a taper (its window is symmetric about each bin),
    and keeps every bin read by enough frames."""
    rng = np.random.default_rng(seed)
    length, base = float(rng.uniform(180.0, 260.0)), float(rng.uniform(5.0, 8.0))
    end = base * float(rng.uniform(0.5, 0.9))
    frames = []
    for _ in range(16):
        arc = np.arange(6.0, length - 8.0, 4.0) + rng.uniform(0.0, 4.0)
        frames.append((arc, base + (end - base) * arc / length + rng.normal(0.0, 0.08, len(arc))))
    profile = RadiusProfile.pooled(frames)
    assert profile is not None
    assert len(profile.arc_mm) >= int((length - 16.0) / BIN_MM) - 2
    truth = base + (end - base) * profile.arc_mm / length
    # Away from the ends, where the window is moved in (and reads the taper a few mm in).
    inner = slice(HALF_WINDOW_BINS, -HALF_WINDOW_BINS)
    np.testing.assert_allclose(profile.radius_mm[inner], truth[inner], atol=0.1)
