"""The segmentation's NaN-aware median against numpy's (the slow, obviously correct reference)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from facade_pipeline.segmentation.grid import nanmedian0


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
