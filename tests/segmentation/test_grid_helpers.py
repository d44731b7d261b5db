"""The segmentation grid's array helpers against slow, obviously correct references: numpy's NaN median and a
scalar loop over every run of lattice values."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from facade_pipeline.segmentation.grid import best_run, nanmedian0


@pytest.mark.parametrize("shape", [(1, 4), (2, 5, 3), (7, 6), (288, 40, 3)])
def test_nanmedian0_is_numpys_nanmedian_over_the_first_axis(shape):
    rng = np.random.default_rng(len(shape) * 100 + shape[0])
    a = rng.normal(size=shape)
    a[rng.random(shape) < 0.3] = np.nan
    a[:, 0] = np.nan  # a position outside the view in every row
    a[:, 1] = 2.5  # ties
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the all-NaN column
        ref = np.nanmedian(a, axis=0)
    got = nanmedian0(a)
    assert got.shape == ref.shape
    assert np.array_equal(np.isnan(got), np.isnan(ref))
    assert np.allclose(got[~np.isnan(ref)], ref[~np.isnan(ref)], rtol=0, atol=0)


def test_nanmedian0_of_no_rows_is_nan():
    assert np.isnan(nanmedian0(np.zeros((0, 3, 2)))).all() and nanmedian0(np.zeros((0, 3, 2))).shape == (3, 2)


def _best_run_loop(values: np.ndarray) -> tuple[float, int, int]:
    """The reference: every run of >= 2 terms, summed from its start on, the first best kept."""
    best, lo, hi = -np.inf, 0, 0
    for i in range(len(values) - 1):
        s = values[i]
        for j in range(i + 1, len(values)):
            s += values[j]
            if not np.isfinite(s):
                break
            if s > best:
                best, lo, hi = s, i, j + 1
    return best, lo, hi


@pytest.mark.parametrize("seed", range(40))
def test_best_run_is_the_loop_over_every_run(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(0, 30))
    values = np.round(rng.normal(0.2, 1.0, n), 1 if seed % 2 else 6)  # rounded: equal sums occur
    values[rng.random(n) < 0.15] = -np.inf
    assert best_run(values) == _best_run_loop(values)
