"""How firmly the side readings place each sample: pipeline.reconstruct.placement."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from pipeline.geometry.polyline import unit_tangents
from pipeline.reconstruct.placement import (
    BAND_UPPER,
    LOOSE_SPREAD,
    Placement,
    normal_equations,
    spread_across,
)
from pipeline.reconstruct.side_readings import SideReadings

FloatArray = NDArray[np.float64]
RADIUS = 5.0
SPACING = 4.0


def _straight_tube(k: int) -> tuple[FloatArray, SideReadings]:
    """K samples SPACING mm apart along x, each read by two views square to each other
    (one fixes y, the other z), every edge trusted and where the axis is."""
    pts = np.column_stack([np.arange(k) * SPACING, np.zeros(k), np.zeros(k)])
    rows = np.zeros((k, 2, 3))
    rows[:, 0, 1] = 1.0
    rows[:, 1, 2] = 1.0
    sides = SideReadings(
        rows,
        np.full((k, 2), -RADIUS),
        np.full((k, 2), RADIUS),
        np.ones((k, 2, 2), dtype=bool),
        RADIUS,
        np.full((k, 2), RADIUS),
        np.full(k, RADIUS),
    )
    return pts, sides


def _looking_along(sides: SideReadings, samples: slice, degrees: float) -> SideReadings:
    """``sides`` with the second view turned, at ``samples``, to within ``degrees`` of the
    first's plane with the tube (their common, epipolar, plane): it fixes y again there."""
    rows = sides.rows.copy()
    angle = np.radians(degrees)
    rows[samples, 1] = [0.0, np.cos(angle), np.sin(angle)]
    return SideReadings(
        rows, sides.left, sides.right, sides.use, sides.radius_mm, sides.apparent, sides.radii_mm
    )


def test_samples_every_view_fixes_are_placed_firmly() -> None:
    pts, sides = _straight_tube(50)
    spread = spread_across(pts, sides, base_fixed=True, smoothness=0.5)
    # A sample read by two views square to each other is placed no more loosely than its
    # own two readings place it: one reading's noise, far below the bar.
    assert spread.max() <= 1.0 + 1e-9 and spread[0] == 0.0  # the base is held
    assert Placement(pts, sides, base_fixed=True, smoothness=0.5).loose_stretch(RADIUS) is None


@pytest.mark.parametrize("seed", range(6))
def test_a_stretch_the_views_look_along_is_named_loose(seed: int) -> None:
    rng = np.random.default_rng(seed)
    k = 60
    # 64-80 mm that the two views look along, to within 2 degrees (with no reading across
    # in one direction, a stretch reaches LOOSE_SPREAD at its middle from about 56 mm on).
    length = int(rng.integers(16, 21))
    first = int(rng.integers(5, k - length - 8))
    pts, sides = _straight_tube(k)
    along = _looking_along(sides, slice(first, first + length), float(rng.uniform(0.0, 2.0)))
    placement = Placement(pts, along, base_fixed=True, smoothness=0.5)
    spread = placement.spread()
    middle = first + length // 2
    assert spread[middle] > LOOSE_SPREAD
    # Outside the stretch, beyond a few samples that the smoothness ties to it, firm.
    outside = np.ones(k, dtype=bool)
    outside[first - 4 : first + length + 4] = False
    assert spread[outside].max() <= 1.0 + 1e-9
    # The stretch named lies within the one the views look along, and covers its middle.
    stretch = placement.loose_stretch(RADIUS)
    assert stretch is not None
    start, end = stretch
    assert first * SPACING <= start <= middle * SPACING <= end <= (first + length - 1) * SPACING
    reason = placement.loose_reason(RADIUS)
    assert f"{start:.0f}-{end:.0f} mm from the base" in reason


@pytest.mark.parametrize("seed", range(4))
def test_a_short_stretch_is_bridged_by_its_neighbours(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    k = 60
    first = int(rng.integers(10, 45))
    pts, sides = _straight_tube(k)
    # Three samples (12 mm) that one view alone reads: the smoothness carries them.
    use = sides.use.copy()
    use[first : first + 3, 1] = False
    hidden = SideReadings(
        sides.rows, sides.left, sides.right, use, sides.radius_mm, sides.apparent, sides.radii_mm
    )
    assert Placement(pts, hidden, base_fixed=True, smoothness=0.5).loose_stretch(RADIUS) is None
    # Twenty (80 mm) are not carried.
    use[first - 8 : first + 12, 1] = False
    hidden = SideReadings(
        sides.rows, sides.left, sides.right, use, sides.radius_mm, sides.apparent, sides.radii_mm
    )
    assert Placement(pts, hidden, base_fixed=True, smoothness=0.5).loose_stretch(RADIUS) is not None


def test_the_ends_are_left_to_their_own_tests() -> None:
    # The last three radii (the tip's own fit) and the first two are not judged, however
    # loosely the views place them.
    k = 40
    pts, sides = _straight_tube(k)
    tip_samples = int(3 * RADIUS / SPACING)
    at_tip = _looking_along(sides, slice(k - tip_samples, k), 0.0)
    assert Placement(pts, at_tip, base_fixed=True, smoothness=0.5).loose_stretch(RADIUS) is None


def _exact_spread(pts: FloatArray, sides: SideReadings) -> FloatArray:
    """The spread of every sample from the dense inverse of the normal equations."""
    band, _ = normal_equations(pts, sides, base_fixed=True, smoothness=0.5)
    n = band.shape[1]
    dense = np.zeros((n, n))
    for d in range(BAND_UPPER + 1):
        diagonal = band[BAND_UPPER - d, d:]
        dense[np.arange(n - d), np.arange(d, n)] = diagonal
        dense[np.arange(d, n), np.arange(n - d)] = diagonal
    inverse = np.linalg.inv(dense)
    t = unit_tangents(pts)
    out = np.zeros(len(pts))
    for i in range(1, len(pts)):
        across = np.eye(3) - np.outer(t[i], t[i])
        out[i] = np.sqrt(
            np.linalg.eigvalsh(across @ inverse[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] @ across)[-1]
        )
    return out


@pytest.mark.parametrize("seed", range(5))
def test_the_spread_is_exact_where_it_may_pass_the_bar_and_a_bound_elsewhere(seed: int) -> None:
    rng = np.random.default_rng(200 + seed)
    k = 50
    # A gently bent course, views of random directions across it, edges dropped at random.
    s = np.arange(k) * SPACING
    pts = np.column_stack([s, 15.0 * np.sin(s / 90.0), np.zeros(k)])
    t = unit_tangents(pts)
    rows = rng.normal(size=(k, 2, 3))
    rows -= np.einsum("kcj,kj->kc", rows, t)[:, :, None] * t[:, None, :]
    rows /= np.linalg.norm(rows, axis=2, keepdims=True)
    # Over 80 mm, both views fix one direction only: the normal of the plane the course
    # bends in, which holds it and both views' lines of sight (their epipolar plane).
    first = int(rng.integers(5, 25))
    rows[first : first + 20] = [0.0, 0.0, 1.0]
    use = rng.random((k, 2, 2)) > 0.15
    sides = SideReadings(
        rows,
        np.full((k, 2), -RADIUS),
        np.full((k, 2), RADIUS),
        use,
        RADIUS,
        np.full((k, 2), RADIUS),
        np.full(k, RADIUS),
    )
    spread = spread_across(pts, sides, base_fixed=True, smoothness=0.5)
    exact = _exact_spread(pts, sides)
    loose = exact > LOOSE_SPREAD
    assert loose.any()
    # The same samples pass the bar, at their exact spread; the others' bound is no less
    # than their exact spread.
    np.testing.assert_array_equal(spread > LOOSE_SPREAD, loose)
    np.testing.assert_allclose(spread[loose], exact[loose], rtol=1e-9)
    assert np.all(spread[1:] >= exact[1:] * (1 - 1e-9))


@pytest.mark.parametrize("seed", range(4))
def test_the_loose_end_is_the_stretch_before_the_tip_that_no_reading_places(seed: int) -> None:
    rng = np.random.default_rng(seed)
    k = 60
    unread = int(rng.integers(4, 15))
    pts, sides = _straight_tube(k)
    placement = Placement(pts, sides, base_fixed=True, smoothness=0.5)
    assert placement.loose_end_mm(2.0, within_mm=80.0) == 0.0  # every sample read to the tip
    use = sides.use.copy()
    use[k - unread :] = False  # the last samples hidden in every view
    hidden = SideReadings(
        sides.rows, sides.left, sides.right, use, sides.radius_mm, sides.apparent, sides.radii_mm
    )
    loose = Placement(pts, hidden, base_fixed=True, smoothness=0.5).loose_end_mm(2.0, within_mm=80.0)
    # The smoothness carries the read samples' places a sample or two into the hidden stretch.
    assert (unread - 3) * SPACING <= loose <= unread * SPACING
    # All of the judged stretch where none of it is read.
    assert Placement(pts, hidden, base_fixed=True, smoothness=0.5).loose_end_mm(
        2.0, within_mm=(unread - 4) * SPACING
    ) == pytest.approx((unread - 4) * SPACING)
