"""Tests of pipeline.reconstruct.profiles: its fast order statistics against NumPy's own."""

from __future__ import annotations

import numpy as np
import scipy.stats

from pipeline.reconstruct.profiles import _run_lower_quartile, lower_quartile, nanmedian_rows, theil_sen_slope


def test_run_lower_quartile_equals_the_masked_lower_quartile() -> None:
    rng = np.random.default_rng(3)
    profile = rng.uniform(0.0, 255.0, size=(40, 31))
    first = rng.integers(0, 31, size=40)
    count = np.minimum(rng.integers(0, 12, size=40), 31 - first)
    count[:3] = 0  # empty runs: inf, as the masked version
    cols = np.arange(31)[None, :]
    region = (cols >= first[:, None]) & (cols < (first + count)[:, None])
    # The same order statistic of the same values: exactly equal, no tolerance.
    np.testing.assert_array_equal(_run_lower_quartile(profile, first, count), lower_quartile(profile, region))


def test_run_lower_quartile_of_no_runs_is_inf() -> None:
    out = _run_lower_quartile(np.ones((4, 5)), np.zeros(4, dtype=np.intp), np.zeros(4, dtype=np.intp))
    assert np.isinf(out).all()


def test_nanmedian_rows_equals_numpys_nanmedian() -> None:
    rng = np.random.default_rng(5)
    for _ in range(200):
        rows, cols = rng.integers(1, 30, size=2)
        values = rng.normal(size=(rows, cols))
        values[rng.random((rows, cols)) < rng.random()] = np.nan
        values[:, rng.integers(cols)] = rng.normal(size=rows)  # every row has a value
        np.testing.assert_array_equal(nanmedian_rows(values), np.nanmedian(values, axis=1))


def test_theil_sen_slope_equals_scipys() -> None:
    rng = np.random.default_rng(7)
    for _ in range(200):
        n = int(rng.integers(2, 40))
        x = rng.integers(0, 12, size=n).astype(np.float64)  # repeats, in any order
        y = rng.normal(size=n)
        if np.ptp(x) == 0:
            assert np.isnan(theil_sen_slope(x, y))
            continue
        # The same slopes' median: exactly equal, no tolerance.
        assert theil_sen_slope(x, y) == scipy.stats.theilslopes(y, x).slope


def test_theil_sen_slope_ignores_a_few_outliers() -> None:
    x = np.arange(20, dtype=np.float64)
    y = 0.5 * x + 3.0
    y[[4, 11, 17]] += [40.0, -25.0, 60.0]
    assert theil_sen_slope(x, y) == 0.5
