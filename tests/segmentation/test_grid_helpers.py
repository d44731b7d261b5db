"""The segmentation grid's array helpers against slow, obviously correct references: numpy's NaN median, a
scalar loop over every run of lattice values, one over every shift of the prior's relaxation and one over
every row, position and width of the bar evidence."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from facade_pipeline.segmentation.grid import (
    STEP_PX,
    Gradients,
    GridParams,
    PixelSizes,
    bar_evidence,
    best_run,
    nanmedian0,
    relaxed,
    shifted,
)


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


def _relaxed_loop(ll: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """The reference: at each lattice position, every shift within 3 sigma in turn, the first best kept."""
    r = int(np.ceil(3 * sigma / STEP_PX))
    value, delta = np.full(len(ll), -np.inf), np.zeros(len(ll))
    for c in range(len(ll)):
        best, arg = -np.inf, None
        for s in range(-r, r + 1):
            v = (ll[c + s] if 0 <= c + s < len(ll) else -np.inf) - (s * STEP_PX) ** 2 / (2 * sigma**2)
            if arg is None or v > best:
                best, arg = v, s
        value[c], delta[c] = best, arg * STEP_PX
    return value, delta


@pytest.mark.parametrize("seed", range(12))
def test_relaxed_is_the_loop_over_every_shift(seed):
    """Shifts made once for the widest sigma serve every narrower one, to the bit."""
    rng = np.random.default_rng(seed)
    ll = np.round(rng.normal(0.0, 2.0, int(rng.integers(1, 60))), 1 if seed % 2 else 6)  # rounded: ties
    widest = 4.0
    shifts = shifted(ll, int(np.ceil(3 * widest / STEP_PX)))
    for sigma in (0.5, 1.3, 2.75, widest):
        value, delta = relaxed(shifts, sigma)
        ref_value, ref_delta = _relaxed_loop(ll, sigma)
        assert np.array_equal(value, ref_value) and np.array_equal(delta, ref_delta)


def test_relaxed_refuses_shifts_shorter_than_its_reach():
    with pytest.raises(ValueError, match="reaches 6 lattice steps"):
        relaxed(shifted(np.zeros(10), 3), 1.0)


def _bar_evidence_loop(g: np.ndarray, min_bar: int, max_bar: int,
                       floor: float) -> tuple[np.ndarray, np.ndarray]:
    """The reference: at each lattice position and width in turn, the mean over the rows of
    sqrt(max(|gL|, |gR|) * max(min(|gL|, |gR|), floor * max(|gL|, |gR|)) * (1 - cos) / 2), the first best
    width kept."""
    L, M, _ = g.shape
    best, width = np.zeros(M), np.zeros(M)
    for w in range(min_bar, max_bar + 1):
        if 2 * w >= M:
            break
        for c in range(w, M - w):
            total = 0.0
            for row in range(L):
                gl, gr = g[row, c - w], g[row, c + w]
                ml, mr = np.linalg.norm(gl), np.linalg.norm(gr)
                cos = float(gl @ gr) / max(ml * mr, 1e-12)
                weak = max(min(ml, mr), floor * max(ml, mr))
                total += np.sqrt(max(ml, mr) * weak * min(max(1 - cos, 0.0), 2.0) / 2)
            if total / L > best[c]:
                best[c], width[c] = total / L, w
    return best, width


@pytest.mark.parametrize("seed", range(4))
def test_bar_evidence_is_the_loop_over_rows_positions_and_widths(seed):
    """Every floor from one pass: the same evidence and widths as each floor's loop, to rounding."""
    rng = np.random.default_rng(seed)
    image = rng.integers(0, 256, (6, 24, 3)).astype(np.uint8)
    image[:, 9:13] = 250  # a bright bar: evidence at its centre
    valid = np.ones(image.shape[:2], bool)
    valid[:, -2:] = seed % 2 == 0  # a rectified image's edge outside the view
    grad = Gradients.of(image, 0, valid)
    params = GridParams(min_pitch_m=0.5, max_pitch_m=5.0, sigma_frac=0.1, line_cost=1.0, min_bar_m=0.02,
                        max_bar_m=0.06, lsd_weight=0.5, outer_edge_floor=0.4, uniformity_scale=0.05,
                        frame_colour_scale=0.1)  # bar_evidence reads none of them: the sizes hold its widths
    sizes = PixelSizes(min_pitch=5.0, max_pitch=20.0, min_bar=2, max_bar=5)
    rows = slice(1, 5)
    floors = (0.0, 0.4)
    got = bar_evidence(grad, rows, params, sizes, floors)
    assert len(got) == len(floors)
    for floor, (e, w) in zip(floors, got, strict=True):
        ref_e, ref_w = _bar_evidence_loop(grad.on_lattice[rows], 2, 5, floor)
        assert np.allclose(e, ref_e, rtol=1e-12, atol=1e-15) and np.array_equal(w, ref_w)
    assert got[0][0].max() > 0 and np.any(got[1][0] > got[0][0])  # the floor counts the one-sided edges
