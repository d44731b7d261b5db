"""The segmentation grid's array helpers against slow, obviously correct references: numpy's NaN median and
norm, a scalar loop over every run of lattice values, one over every shift of the prior's relaxation (at every
position or some), one over every row, position and width of the bar evidence (and its plain array
expressions, to the bit), and the MAP search that takes the relaxation in full at every pitch."""

from __future__ import annotations

import warnings
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from facade_pipeline.segmentation.evidence import Gradients, bar_evidence, local_median, nanmedian0, norm_last
from facade_pipeline.segmentation.grid import (
    SIGMA_MIN_PX,
    STEP_PX,
    GridParams,
    PixelSizes,
    best_run,
    map_family,
    reach,
    relaxed_at,
    relaxed_bound,
    shift_windows,
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


@pytest.mark.parametrize("shape", [(5, 3), (40, 30, 3), (7, 9, 2), (6, 1), (4, 9)])
def test_norm_last_is_numpys_norm_over_the_last_axis_to_the_bit(shape):
    """Magnitudes spread over six decades (where the order of the sum shows), NaN, and the lattice's layout
    (the last axis innermost, the first next)."""
    rng = np.random.default_rng(shape[-1] * 10 + len(shape))
    a = rng.normal(size=shape) * 10.0 ** rng.integers(-3, 3, shape)
    a.flat[0] = np.nan
    lattice = np.moveaxis(np.ascontiguousarray(np.moveaxis(a, 0, -2)), -2, 0) if a.ndim == 3 else a
    for x in (a, lattice):
        ref = np.linalg.norm(x, axis=-1)
        got = norm_last(x)
        assert np.array_equal(got, ref, equal_nan=True)


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
def test_relaxed_at_is_the_loop_at_those_positions(seed):
    """Shift windows made once for the widest sigma, some positions taken in any order, repeats and none."""
    rng = np.random.default_rng(seed)
    ll = np.round(rng.normal(0.0, 2.0, int(rng.integers(1, 60))), 1 if seed % 2 else 6)  # rounded: ties
    widest = 4.0
    windows = shift_windows(ll, int(np.ceil(3 * widest / STEP_PX)))
    for sigma in (0.5, 1.3, 2.75, widest):
        ref_value, ref_delta = _relaxed_loop(ll, sigma)
        for at in (np.arange(len(ll)), rng.integers(0, len(ll), 7), np.zeros(0, int)):
            value, delta = relaxed_at(windows, sigma, at)
            assert np.array_equal(value, ref_value[at]) and np.array_equal(delta, ref_delta[at])
    with pytest.raises(ValueError, match="reaches 6 lattice steps"):
        relaxed_at(shift_windows(np.zeros(10), 3), 1.0, np.arange(3))


@pytest.mark.parametrize("seed", range(6))
def test_reach_is_the_largest_value_within_each_radius(seed):
    rng = np.random.default_rng(seed)
    ll = np.round(rng.normal(0.0, 2.0, int(rng.integers(1, 40))), 1)
    R = 9
    got = reach(shift_windows(ll, R))
    assert got.shape == (R + 1, len(ll))
    for r in range(R + 1):
        for c in range(len(ll)):
            assert got[r, c] == max(ll[max(0, c - r) : c + r + 1])


@pytest.mark.parametrize("seed", range(8))
def test_relaxed_bound_is_above_the_relaxation_and_near_it(seed):
    """Above (or equal to) the loop's value at every position and sigma; within the penalty of one band of
    it where l is flat (there the relaxation is l itself)."""
    rng = np.random.default_rng(seed)
    ll = np.round(rng.normal(0.0, 2.0, int(rng.integers(1, 80))), 1 if seed % 2 else 6)
    sigmas = np.array([0.5, 0.8, 1.3, 2.0, 2.75, 4.0, 6.1])
    bound = relaxed_bound(reach(shift_windows(ll, int(np.ceil(3 * sigmas[-1] / STEP_PX)))), sigmas)
    assert bound.shape == (len(sigmas), len(ll))
    for sigma, b in zip(sigmas, bound, strict=True):
        assert np.all(b >= _relaxed_loop(ll, sigma)[0])
    flat = relaxed_bound(reach(shift_windows(np.full(30, 1.5), 40)), sigmas)
    assert np.all(flat == 1.5)


def _map_family_search(ll: np.ndarray, widths: np.ndarray, size: int, params: GridParams,
                       sizes: PixelSizes) -> tuple[float, np.ndarray, np.ndarray, float] | None:
    """The reference: at every pitch the relaxation at every position, every phase's gain, and the exact run
    of the 8 phases of highest gain in turn while their gain passes the best score so far."""
    M = len(ll)
    best = None
    for pitch in np.arange(sizes.min_pitch, min(size, sizes.max_pitch) + STEP_PX, STEP_PX):
        sigma = max(SIGMA_MIN_PX, params.sigma_frac * pitch)
        value, delta = _relaxed_loop(ll, sigma)
        k = np.arange(int(size / pitch) + 2)
        pos = np.arange(0.0, pitch, STEP_PX)[:, None] + k[None, :] * pitch
        idx = np.rint(pos / STEP_PX).astype(int)
        vals = np.where(idx < M, value[np.minimum(idx, M - 1)] - params.line_cost, -np.inf)
        gain = np.where(vals > 0, vals, 0.0).sum(axis=1)
        for p in gain.argsort()[::-1][:8]:
            if best is not None and gain[p] <= best[0]:
                break
            score, lo, hi = _best_run_loop(vals[p])
            if hi - lo >= 2 and (best is None or score > best[0]):
                best = (score, pos[p, lo:hi] + delta[idx[p, lo:hi]], pitch)
    if best is None or best[0] <= 0:
        return None
    score, centres, pitch = best
    return score, centres, widths[np.clip(np.rint(centres / STEP_PX).astype(int), 0, M - 1)], pitch


@pytest.mark.parametrize("seed", range(10))
def test_map_family_is_the_search_with_the_relaxation_in_full(seed):
    """Bars at a regular pitch with jitter, gaps and noise (and a view of noise alone): the bounded search
    finds the reference's grid, score and widths to the bit."""
    rng = np.random.default_rng(seed)
    size = int(rng.integers(60, 160))
    M = 2 * size + 1
    x = np.arange(M) * STEP_PX
    ll = rng.normal(-1.5, 0.6, M)
    if seed < 8:
        pitch, phase = rng.uniform(9.0, 30.0), rng.uniform(0.0, 9.0)
        for c in np.arange(phase, size, pitch):
            if rng.random() < 0.85:  # some bars missing
                ll += rng.uniform(2.0, 5.0) * np.exp(-0.5 * ((x - c - rng.normal(0, 0.4)) / 0.8) ** 2)
    ll = np.round(ll, 2 if seed % 2 else 8)  # rounded: equal gains and scores occur
    widths = rng.integers(2, 6, M).astype(float)
    params = GridParams(min_pitch=0.5, max_pitch=5.0, sigma_frac=0.04, line_cost=1.2, min_bar=0.02,
                        max_bar=0.06, lsd_weight=0.5, outer_edge_floor=0.4, uniformity_scale=0.05,
                        frame_colour_scale=0.1)  # map_family reads sigma_frac, line_cost; the sizes the rest
    sizes = PixelSizes(min_pitch=6.3, max_pitch=45.0, min_bar=2, max_bar=5)
    fit = map_family(ll, widths, size, params, sizes)
    ref = _map_family_search(ll, widths, size, params, sizes)
    if ref is None:
        assert fit is None
        return
    score, centres, bar_widths, pitch = ref
    assert fit is not None and fit.score == score and fit.pitch == pitch
    assert np.array_equal(fit.centres, centres) and np.array_equal(fit.widths, bar_widths)
    if seed < 8:
        assert len(fit.centres) >= 3


def _bar_evidence_loop(
    g: np.ndarray, min_bar: int, max_bar: int, floor: float, known: np.ndarray | None = None,
    unknown_floor: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The reference: at each lattice position and width in turn, the mean over the rows of
    sqrt(max(|gL|, |gR|) * max(min(|gL|, |gR|), floor * max(|gL|, |gR|)) * (1 - cos) / 2), the first best
    width kept. With ``known`` (1 where an edge is readable), an edge that is not stands aside for the
    other one's sqrt(unknown_floor s^2 / 2), s its magnitude, where that is the larger."""
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
                two = max(ml, mr) * weak * min(max(1 - cos, 0.0), 2.0)
                one = 0.0
                if known is not None:
                    one = max((1 - known[row, c - w]) * unknown_floor * mr * mr,
                              (1 - known[row, c + w]) * unknown_floor * ml * ml)
                total += np.sqrt(max(two, one) / 2)
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
    params = GridParams(min_pitch=0.5, max_pitch=5.0, sigma_frac=0.1, line_cost=1.0, min_bar=0.02,
                        max_bar=0.06, lsd_weight=0.5, outer_edge_floor=0.4, uniformity_scale=0.05,
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


def test_an_unknown_edge_counts_the_known_one_as_a_one_sided_bars():
    """Where a bar's edge lies between two clipped pixels (``Gradients.known``), the known edge alone
    gives sqrt(s (f s) / 2) (an unknown polarity: 1 - cos averages 1) with s its magnitude and f the
    floor, whichever the larger with the two-sided product; where neither edge is unknown, as before."""
    rng = np.random.default_rng(3)
    image = rng.integers(0, 200, (8, 30, 3)).astype(np.uint8)
    image[:5, 6:14] = 255  # a frame clipped with a lit box beside it over five rows
    image[:, 14] = 40  # the glass beside the frame
    grad = Gradients.of(image, 0)
    params = GridParams(min_pitch=0.5, max_pitch=5.0, sigma_frac=0.1, line_cost=1.0, min_bar=0.02,
                        max_bar=0.06, lsd_weight=0.5, outer_edge_floor=0.4, uniformity_scale=0.05,
                        frame_colour_scale=0.1)
    sizes = PixelSizes(min_pitch=5.0, max_pitch=20.0, min_bar=2, max_bar=5)
    rows = slice(0, 8)
    g, known = grad.on_lattice[rows], grad.known_on_lattice[rows]
    for floors in ((0.0,), (0.0, 0.4)):
        (plain, _), *_ = bar_evidence(grad, rows, params, sizes, floors)
        got = bar_evidence(grad, rows, params, sizes, floors, None, 0.5)
        for floor, (e, width) in zip(floors, got, strict=True):
            best, ref_w = _bar_evidence_loop(g, 2, 5, floor, known, 0.5)
            assert np.allclose(e, best, rtol=1e-6, atol=1e-9) and np.array_equal(width, ref_w)
        # the frame's right edge (at 14 px) with its left edge unknown: more evidence than as absent
        assert got[0][0][2 * 12] > plain[2 * 12]


def _bar_evidence_plain(g: np.ndarray, min_bar: int, max_bar: int,
                        floor: float) -> tuple[np.ndarray, np.ndarray]:
    """The reference to the bit: the plain expressions over arrays of rows, sqrt(s max(w, f s) (1 - cos)
    / 2) with s, w the stronger and weaker edge, averaged over the rows at each width, the first best width
    kept."""
    L, M, _ = g.shape
    mag = np.linalg.norm(g, axis=2)
    best, width = np.zeros(M), np.zeros(M)
    for w in range(min_bar, max_bar + 1):
        if 2 * w >= M:
            break
        gl, gr, ml, mr = g[:, : M - 2 * w], g[:, 2 * w :], mag[:, : M - 2 * w], mag[:, 2 * w :]
        dot = gl[..., 0] * gr[..., 0] + gl[..., 1] * gr[..., 1] + gl[..., 2] * gr[..., 2]
        cos = dot / np.maximum(ml * mr, 1e-12)
        strong, weak = np.maximum(ml, mr), np.minimum(ml, mr)
        e = np.sqrt(strong * np.maximum(weak, floor * strong) * np.clip(1 - cos, 0.0, 2.0) / 2).mean(axis=0)
        e = np.pad(e, (w, w))
        better = e > best
        best[better], width[better] = e[better], w
    return best, width


@pytest.mark.parametrize("axis", [0, 1])
def test_bar_evidence_is_the_plain_expressions_to_the_bit(axis):
    """Hundreds of rows (numpy sums them pairwise where they lie side by side in memory, as the lattice
    lays them out), bars of either polarity, a one-sided edge, the edge of a rectified image's view; the
    same with half the widths evaluated on a thread pool."""
    rng = np.random.default_rng(7 + axis)
    image = rng.integers(0, 256, (300, 280, 3)).astype(np.uint8)
    image[:, 40:46] = 250
    image[:, 100:104] = 10
    image[:, 200:] = image[:, 197:198]  # a one-sided edge: the background on one side has the frame's colour
    image = image if axis == 0 else image.transpose(1, 0, 2).copy()
    valid = np.ones(image.shape[:2], bool)
    valid[:, :5] = False
    grad = Gradients.of(image, axis, valid)
    params = GridParams(min_pitch=0.5, max_pitch=5.0, sigma_frac=0.1, line_cost=1.0, min_bar=0.02,
                        max_bar=0.06, lsd_weight=0.5, outer_edge_floor=0.4, uniformity_scale=0.05,
                        frame_colour_scale=0.1)
    sizes = PixelSizes(min_pitch=5.0, max_pitch=20.0, min_bar=2, max_bar=9)
    floors = (0.0, 0.4, 1.5)
    with ThreadPoolExecutor(max_workers=2) as pool:
        for rows in (slice(0, 300), slice(17, 260)):
            alone = bar_evidence(grad, rows, params, sizes, floors)
            shared = bar_evidence(grad, rows, params, sizes, floors, pool)  # half the widths on the pool
            for floor, (e, w), (e_pool, w_pool) in zip(floors, alone, shared, strict=True):
                ref_e, ref_w = _bar_evidence_plain(grad.on_lattice[rows], 2, 9, floor)
                assert np.array_equal(e, ref_e) and np.array_equal(w, ref_w)
                assert np.array_equal(e_pool, ref_e) and np.array_equal(w_pool, ref_w)



def test_block_medians_follow_shading_but_not_an_edge_crossing_the_bar():
    """A transom along a cylinder: lane 0 is the frame, its shading turning from 0.3 to 0.6 along the bar;
    lane 1 is where a rectified bar that is not quite straight shows frame in its first half and glass
    (0.05) in its second. Against block medians each block of lane 1 looks uniform; with the step rule
    lane 1 is judged against its whole length, as a bar's position with an edge across it must be, and
    lane 0 keeps its blocks."""
    L, block = 240, 20.0
    shade = np.linspace(0.3, 0.6, L)
    lane0 = np.repeat(shade[:, None], 3, axis=1)
    lane1 = np.where(np.arange(L)[:, None] < L // 2, lane0, 0.05)
    a = np.stack([lane0, lane1], axis=1)  # [L, 2 lanes, 3]
    blocks = local_median(a, block)
    stepped = local_median(a, block, max_step=0.12)
    assert np.array_equal(stepped[:, 0], blocks[:, 0])  # smooth shading: each block its own colour
    assert np.abs(stepped[:, 0] - a[:, 0]).max() < 0.02
    assert np.allclose(stepped[:, 1], nanmedian0(a[:, 1]))  # the edge: one colour for the whole lane
    # what the uniformity sees: lane 1 uniform against its blocks, not against its whole length
    assert np.median(norm_last(a[:, 1] - blocks[:, 1])) < 0.02 < np.median(norm_last(a[:, 1] - stepped[:, 1]))
    img = (255 * np.concatenate([a, a[:, ::-1]], axis=1)).astype(np.uint8)  # rows along x: a transom's lanes
    g_blocks = Gradients.of(img.transpose(1, 0, 2), 1, None, block)
    g_step = Gradients.of(img.transpose(1, 0, 2), 1, None, block, 0.12)
    rows = slice(0, L)
    v_blocks, v_step = g_blocks.uniformity(rows), g_step.uniformity(rows)
    # a position between lanes 0 and 1 sees the edge only with the rule
    assert v_step.max() > 0.2 > v_blocks.max()


@pytest.mark.parametrize("clipped", [True, False])
def test_an_end_bay_off_the_grids_clipped_place_gives_way_to_the_grids_bar(clipped):
    """Bars every 40 px from 80 to 160 and a stronger two-sided bar at 48, 0.8 of a pitch before the first
    (the lit ceiling of an empty unit behind its frame), nothing at 40. Where the grid's place at 40 shows
    nothing either way (the bar clipped with the sky beside it), the grid's bar is placed there, at the
    run's width, and marked placed; where it is seen, the empty place is evidence against a bar there and
    the end bay at 48 is kept, as found."""
    size = 200
    M = 2 * size + 1
    x = np.arange(M) * STEP_PX
    ll = np.full(M, -1.5)
    for c, a in ((80.0, 4.0), (120.0, 4.0), (160.0, 4.0), (48.0, 5.0)):
        ll += (a + 1.5) * np.exp(-0.5 * ((x - c) / 0.8) ** 2)
    widths = np.where(np.abs(x - 48.0) < 2.0, 3.0, 4.0)
    params = GridParams(min_pitch=0.5, max_pitch=2.0, sigma_frac=0.04, line_cost=1.2, min_bar=0.02,
                        max_bar=0.06, lsd_weight=0.5, outer_edge_floor=0.4, uniformity_scale=0.05,
                        frame_colour_scale=0.1)
    sizes = PixelSizes(min_pitch=20.0, max_pitch=80.0, min_bar=2, max_bar=5)
    seen = []

    def clipped_at(c: float, w: float) -> bool:
        seen.append((c, w))
        return clipped and abs(c - 40.0) < w

    fit = map_family(ll, widths, size, params, sizes, (ll, widths), clipped_at)
    assert fit is not None and abs(fit.pitch - 40.0) <= STEP_PX
    assert np.allclose(fit.centres[1:], [80.0, 120.0, 160.0], atol=STEP_PX)
    assert seen and all(abs(c - (fit.centres[1] - fit.pitch)) < 1e-9 and w == 4.0 for c, w in seen)
    if clipped:
        assert fit.centres[0] == fit.centres[1] - fit.pitch and fit.widths[0] == 4.0
        assert fit.placed == frozenset({0})
    else:
        assert abs(fit.centres[0] - 48.0) <= STEP_PX and fit.widths[0] == 3.0 and not fit.placed
    # without a say on the places, as before: the bar found
    before = map_family(ll, widths, size, params, sizes, (ll, widths))
    assert abs(before.centres[0] - 48.0) <= STEP_PX and not before.placed
