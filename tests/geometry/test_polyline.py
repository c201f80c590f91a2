"""Tests of pipeline.geometry.polyline: arc length and norms equal numpy's own, bit for bit."""

from __future__ import annotations

import numpy as np

from pipeline.geometry.polyline import polyline_arclength, resample_polyline, vector_norms


def test_vector_norms_equal_linalg_norm_exactly() -> None:
    v = np.random.default_rng(5).normal(0.0, 100.0, (3, 40, 3))
    # The same reduction in the same order: no tolerance.
    np.testing.assert_array_equal(vector_norms(v), np.linalg.norm(v, axis=-1))


def test_arclength_equals_the_cumulative_segment_norms_exactly() -> None:
    pts = np.random.default_rng(6).normal(0.0, 50.0, (30, 3))
    expected = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    np.testing.assert_array_equal(polyline_arclength(pts), expected)
    # float32 input: summed in float32 as before, returned as float64.
    pts32 = pts.astype(np.float32)
    expected32 = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts32, axis=0), axis=1))])
    got32 = polyline_arclength(pts32)
    assert got32.dtype == np.float64
    np.testing.assert_array_equal(got32, expected32)


def test_resample_with_given_arclength_is_the_same() -> None:
    pts = np.cumsum(np.random.default_rng(7).normal(0.0, 3.0, (25, 3)), axis=0)
    np.testing.assert_array_equal(
        resample_polyline(pts, 40, arclength_mm=polyline_arclength(pts)), resample_polyline(pts, 40)
    )
    # Uniform in chord length: the samples' arc length is a linspace (to rounding).
    s = polyline_arclength(resample_polyline(pts, 40))
    assert s[-1] <= polyline_arclength(pts)[-1] + 1e-9  # chords of a polyline never exceed it


def test_values_by_fraction_keep_their_ends_and_interpolate_between() -> None:
    from pipeline.geometry.polyline import by_fraction

    values = np.array([6.0, 6.0, 4.0])  # at 0, 1/2 and 1 of the way along
    np.testing.assert_allclose(by_fraction(values, 5), [6.0, 6.0, 6.0, 5.0, 4.0])
