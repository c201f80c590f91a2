"""Grey levels of any stored depth, read as the videos' 8-bit levels by one rule."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.session.grey_levels import full_scale_level, grey_8bit

LEVELS = np.array([[0, 40, 150, 255]], np.uint8)


def test_8_bit_levels_are_kept() -> None:
    np.testing.assert_array_equal(grey_8bit(LEVELS), LEVELS)
    np.testing.assert_array_equal(grey_8bit(LEVELS.astype(np.uint16)), LEVELS)  # 8-bit values in 16 bits


@pytest.mark.parametrize("bits", [10, 12, 14, 16])
def test_a_deeper_cameras_levels_are_scaled_from_their_depths_full_range(bits: int) -> None:
    stored = np.round(LEVELS * ((2**bits - 1) / 255)).astype(np.uint16)
    assert full_scale_level(stored) == 2**bits - 1
    np.testing.assert_array_equal(grey_8bit(stored), LEVELS)


def test_levels_are_not_stretched_to_the_brightest_pixel() -> None:
    # A dim 16-bit scene reads as dim: a background keeps the frames' levels.
    dim = np.array([[0, 20000, 30000]], np.uint16)
    np.testing.assert_array_equal(grey_8bit(dim), [[0, 78, 117]])


def test_floating_point_levels_up_to_1_are_scaled_by_255_and_others_as_stored() -> None:
    np.testing.assert_array_equal(grey_8bit(np.array([[0.0, 0.5, 1.0]], np.float32)), [[0, 128, 255]])
    np.testing.assert_array_equal(grey_8bit(np.array([[-3.0, 40.0, 150.0]], np.float32)), [[0, 40, 150]])
    np.testing.assert_array_equal(grey_8bit(np.array([[np.nan, 1.0]], np.float32)), [[0, 255]])
