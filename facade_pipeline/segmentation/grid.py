"""Maximum a posteriori panel grid of a (rectified) frontal view (paper, 3.1.2, after its reference [14]).

Model. A curtain wall seen frontally is a grid of frame bars: mullions (vertical) and transoms (horizontal).
Both families are estimated the same way, in 1D, along the axis across the bars (x for mullions). A family
is a set of bar centres ``c_1 < ... < c_K``, each bar of width ``w`` (px), with

- prior (structural regularities of curtain walls): repeated spacing, ``c_k = c_0 + k p + delta_k`` with
  one pitch ``p`` (panels of equal size) and small deviations ``delta_k ~ N(0, sigma^2)``,
  ``sigma = max(SIGMA_MIN_PX, sigma_frac p)``; the lines of the family run across the whole grid (corners
  aligned in rows and columns); ``p`` uniform in [min_pitch, max_pitch] (fractions of the building's panel
  pitch, in pixels of the image at its scale, at most the image size); the bars form one contiguous
  run of indices ``k`` (no holes in a facade); each line costs ``line_cost`` nats (prior odds against a
  line, which also picks the number of lines);
- likelihood (line and edge evidence): a frame bar has two parallel edges ``w`` apart along its whole
  length, usually of opposite polarity. Per row (for mullions), with gL, gR the colour gradients across
  the bar at c - w/2 and c + w/2, the bar response is sqrt(|gL| |gR| (1 - cos(gL, gR)) / 2) (for an outer
  frame bar, the weaker edge counted at least ``outer_edge_floor`` of the stronger); its mean over the
  grid's rows is E_g(c).
  LSD segments of the family give the line support S(x) (summed length near x);
  E_l(c) = sqrt(S(c - w/2) S(c + w/2)) / length.
  A frame is also uniform along its length: v(c), the median colour deviation along the bar's centre line,
  is small (glass reflects a varying scene). The log-likelihood ratio of a bar at c is
  ``l(c) = log(1 + E_g(c) / median(E_g)) + lsd_weight log(1 + E_l(c) / LSD_SCALE) - v(c) / uniformity_scale``,
  ``w`` the best width in [min_bar, max_bar] (fractions of the building's pitch, in pixels at the image's
  scale).

MAP: maximise ``sum_k [max_delta (l(c_0 + k p + delta) - delta^2 / (2 sigma^2)) - line_cost]`` over ``p``,
``c_0`` and the contiguous run (exhaustive on a 0.5 px lattice; the run by Kadane's algorithm). Outer
frames: a facade's outer frame may meet a background of its own colour (paving, sky), so it shows only its
glass-side edge. The run is then extended by one bar at either end where l(c) computed with the weaker edge
counted at least ``outer_edge_floor`` of the stronger (a one-sided bar) pays for the line, one pitch beyond
the end (relaxed as above; a colour prior, where the family has one, taken beside the bar's glass-side edge,
``frames.glass_side``). Only there: everywhere else a one-sided edge is a reflection, but for mullions
sought at the building's pitch whose other edge lies between two clipped pixels, unknown rather than
absent (``frames.find_bars``' ``predicted``). End bays: a
facade's last column or row often has a pitch of its own (a wider end bay, a taller ground floor); where no
outer frame ends the run, it is extended by the best two-sided bar between half and twice the pitch beyond
its end, if that bar pays for two lines (``_with_end_bays``); where the grid's own place one pitch beyond
the end is clipped with what lies beside it (no edge either way) and that bar lies off it, the grid's bar
is placed there instead. Reflections
of buildings and trees in the glass, the main distractor, are single edges (no opposite-polarity partner at
the bar width), cover only parts of the grid and are not periodic: they lose against the prior.

Refinement: each bar's two edges are then located per row (sub-pixel, parabolic peak of the gradient
magnitude) and fitted by robust weighted least squares as straight lines ``x = a + b (y - y_mid)``; panel
corners are intersections of these edge lines (``openings.py``).

This module holds the model's parameters and the MAP search; the evidence it searches over (the gradients,
E_g, E_l and l(c)) is made in ``evidence.py``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from facade_pipeline.config import Fraction, NonNeg, Positive
from facade_pipeline.errors import ConfigError

STEP_PX = 0.5  # lattice of bar-centre hypotheses (px)
# Image-precision constants of the grid model, which hold at any facade scale since the view is segmented
# at a fixed bar width in pixels (``SegmentParams.work_bar_px``); no building ever needed other values, and
# the segmentation benchmarks (benchmarks/RESULTS.md) were measured with these.
#: a bar's deviation from the regular grid has a std of at least this (px): the lattice step, whatever the
#: pitch
SIGMA_MIN_PX = 0.5
#: a bar edge is searched this far (px) around its MAP position: the lattice step and one pixel
EDGE_SEARCH_PX = 1.5


@dataclass(frozen=True)
class GridParams:
    """The grid model's parameters. Its lengths are fractions of the building's panel pitch (``unit_m`` of
    ``PixelSizes.of``: the geometric mean of the mullions' and the transoms' pitch that the survey of every
    view measures, ``building.survey_unit_m``), so that one config holds at any scale."""

    min_pitch: Positive
    """Smallest panel pitch considered (-, of the building's pitch)."""
    max_pitch: Positive
    """Largest panel pitch considered (-, of the building's pitch)."""
    sigma_frac: NonNeg
    """Std of a bar's deviation from the regular grid, as a fraction of the pitch (-)."""
    line_cost: NonNeg
    """Prior cost of one grid line (nats): the evidence a bar must bring to be accepted."""
    min_bar: Positive
    """Narrowest frame bar (-, of the building's pitch; at least 2 px in the image segmented)."""
    max_bar: Positive
    """Widest frame bar (-, of the building's pitch)."""
    lsd_weight: NonNeg
    """Weight of the LSD line-support term against the gradient term (-)."""
    outer_edge_floor: Fraction
    """The weaker edge of an outer frame bar, one pitch beyond either end of the MAP run, counts at least
    this fraction of the stronger (an outer frame may meet a background of its colour) (-)."""
    uniformity_scale: Positive
    """Colour deviation along a bar (0-1 RGB) that costs one nat: frames are uniform along their length."""
    frame_colour_scale: NonNeg
    """Colour distance (0-1 RGB) of a bar of one family from the median colour of the other family's bars
    that costs one nat: mullions and transoms are one material (0: not used; used on planar surfaces
    only, where every bar faces one way and is shaded alike)."""

    def __post_init__(self) -> None:
        for low, high in (("min_pitch", "max_pitch"), ("min_bar", "max_bar")):
            if getattr(self, low) > getattr(self, high):
                raise ConfigError(
                    None,
                    f"'segment_panels.grid.{low}' <= {high}",
                    f"{getattr(self, low)} > {getattr(self, high)}",
                )


@dataclass(frozen=True)
class PixelSizes:
    """The metric sizes of the grid model in pixels of the image being segmented (``of``)."""

    min_pitch: float
    max_pitch: float
    min_bar: int
    max_bar: int

    @classmethod
    def of(cls, params: GridParams, metres_per_px: float, unit_m: float) -> PixelSizes:
        """Sizes at ``metres_per_px`` of a facade whose lengths' unit is ``unit_m`` (the building's pitch,
        m); a bar spans at least 2 px (two distinct edges)."""
        px = unit_m / metres_per_px
        lo = max(2, int(round(params.min_bar * px)))
        hi = max(lo, int(round(params.max_bar * px)))
        return cls(params.min_pitch * px, params.max_pitch * px, lo, hi)



def _radius(sigma_px: float) -> int:
    """Lattice steps the prior's relaxation reaches at ``sigma_px``: 3 sigma."""
    return int(np.ceil(3 * sigma_px / STEP_PX))


def shift_windows(ll: np.ndarray, radius: int) -> np.ndarray:
    """[M, 2 radius + 1], a read-only view: column radius + s holds l(c + s lattice steps) at c, -inf beyond
    the ends (one position's shifts side by side). Made once for a family, it serves the relaxation at every
    pitch (``relaxed_at``)."""
    padded = np.pad(ll, radius, constant_values=-np.inf)
    return np.lib.stride_tricks.sliding_window_view(padded, 2 * radius + 1)


def relaxed_at(windows: np.ndarray, sigma_px: float, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The prior's relaxation at the lattice positions ``at`` [N]: max over delta of l(c + delta) - delta^2 /
    (2 sigma^2), |delta| <= 3 sigma, and the best delta (px, the first of equal ones), from
    ``shift_windows(ll, radius)`` with a radius of at least 3 sigma."""
    r, R = _radius(sigma_px), (windows.shape[1] - 1) // 2
    if r > R:
        raise ValueError(f"relaxed_at: sigma {sigma_px} px reaches {r} lattice steps, the shifts only {R}")
    shifts = np.arange(-r, r + 1)
    cand = windows[at, R - r : R + r + 1] - ((shifts * STEP_PX) ** 2 / (2 * sigma_px**2))[None, :]
    k = np.argmax(cand, axis=1)
    return cand[np.arange(len(k)), k], shifts[k] * STEP_PX


def reach(windows: np.ndarray) -> np.ndarray:
    """[R + 1, M]: row r holds the largest l(c + s) over |s| <= r at c, from ``shift_windows(ll, R)``."""
    R = (windows.shape[1] - 1) // 2
    pairs = np.maximum(windows[:, R:], windows[:, R::-1])  # column s: the larger of l(c + s) and l(c - s)
    return np.ascontiguousarray(np.maximum.accumulate(pairs, axis=1).T)


#: the relaxation's shifts fall in this many bands of reach for its upper bound (``relaxed_bound``): more
#: bands bound it closer, each at the cost of one pass over the lattice
BOUND_BANDS = 4
#: a penalty in the bound counts this fraction less than the relaxation's own: the bound then stays above
#: the relaxation whatever rounding the penalties' two computations take
BOUND_PENALTY_SLACK = 1e-9


def relaxed_bound(reaches: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
    """[S, M] an upper bound of ``relaxed``'s values at each of the ``sigmas`` [S] (px), from ``reach``: the
    shifts of a band (r_{j-1}, r_j] of the reach r = 3 sigma in lattice steps (``BOUND_BANDS`` bands) cost
    at least the penalty at r_{j-1} + 1, and l there is at most the reach of r_j."""
    sigmas = np.asarray(sigmas, float)
    r = np.array([_radius(sigma) for sigma in sigmas], dtype=int)
    bound = np.full((len(sigmas), reaches.shape[1]), -np.inf)
    first = np.zeros(len(sigmas), int)  # the band's nearest shift
    for j in range(1, BOUND_BANDS + 1):
        last = -(-r * j // BOUND_BANDS)  # ceil(r j / bands)
        penalty = (first * STEP_PX) ** 2 / (2 * sigmas**2) * (1.0 - BOUND_PENALTY_SLACK)
        np.maximum(bound, reaches[last] - penalty[:, None], out=bound)
        first = np.maximum(first, last + 1)
    return bound


@dataclass(frozen=True)
class FamilyFit:
    """MAP bar centres [K] (px) of one family, their widths [K] (px), pitch (px) and the MAP score (nats)."""

    centres: np.ndarray
    widths: np.ndarray
    pitch: float
    score: float
    placed: frozenset[int] = frozenset()
    """Indices of the bars placed by the grid where the view shows nothing either way (clipped with what
    lies beside them): their edges, where not found, are those of their place."""


def best_run(values: np.ndarray) -> tuple[float, int, int]:
    """The best sum of a contiguous run of >= 2 terms of one row of values (-inf = unusable) and its
    [lo, hi): of the runs of the same sum, the one that starts first, then ends first. Each run's sum is
    accumulated from its first term on, left to right. A scalar loop over Python floats: a row holds a few
    dozen terms at most, where numpy's per-call cost outweighs the arithmetic."""
    v = values.tolist()
    inf = math.inf
    best, lo, hi = -inf, 0, 0
    for i in range(len(v) - 1):
        total = v[i]
        for j in range(i + 1, len(v)):
            total += v[j]
            if not -inf < total < inf:  # an unusable term (or NaN): so is every longer run from i
                break
            if total > best:
                best, lo, hi = total, i, j + 1
    return best, lo, hi


@dataclass(frozen=True, eq=False)
class _PitchLattice:
    """The grid hypotheses of every pitch of ``map_family`` for one image size: per pitch, the positions
    ``pos`` [P, K] (px) of line k at phase p, whether their lattice index lies on the lattice (``inside``)
    and the index kept on it (``clipped``), stored flat, pitch after pitch (from ``start``); the flat
    hypotheses' index into an array [S, M] over the pitches (``by_pitch``), where each phase starts among
    them (``phase_start``) and where each pitch starts among the phases (``pitch_phase_start``)."""

    pitches: np.ndarray
    shapes: list[tuple[int, int]]
    start: np.ndarray
    pos: np.ndarray
    inside: np.ndarray
    clipped: np.ndarray
    by_pitch: np.ndarray
    phase_start: np.ndarray
    pitch_phase_start: np.ndarray

    def of_pitch(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """pos, inside, clipped [P, K] of pitch i."""
        a, b = self.start[i], self.start[i + 1]
        return tuple(x[a:b].reshape(self.shapes[i]) for x in (self.pos, self.inside, self.clipped))


@lru_cache(maxsize=8)  # the MAP passes over one family of a view share it
def _pitch_lattice(size: int, M: int, min_pitch: float, max_pitch: float) -> _PitchLattice:
    """The hypotheses of an image ``size`` px across with a lattice of M positions, pitches from
    ``min_pitch`` to ``max_pitch`` (px), made as ``map_family`` made them pitch by pitch."""
    pitches = np.arange(min_pitch, min(size, max_pitch) + STEP_PX, STEP_PX)
    pos, shapes = [], []
    for pitch in pitches:
        k = np.arange(int(size / pitch) + 2)
        phases = np.arange(0.0, pitch, STEP_PX)
        pos.append((phases[:, None] + k[None, :] * pitch).ravel())  # [P, K] px
        shapes.append((len(phases), len(k)))
    sizes = [len(p) for p in pos]
    flat = np.concatenate(pos) if pos else np.zeros(0)
    idx = np.rint(flat / STEP_PX).astype(int)
    clipped = np.minimum(idx, M - 1)
    start = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    pitch_of = np.repeat(np.arange(len(pitches)), sizes)
    phase_start = [start[i] + K * np.arange(P) for i, (P, K) in enumerate(shapes)]
    pitch_phase_start = np.concatenate([[0], np.cumsum([P for P, _ in shapes])[:-1]]).astype(int)
    return _PitchLattice(
        pitches, shapes, start, flat, idx < M, clipped, pitch_of * M + clipped,
        np.concatenate(phase_start).astype(int) if shapes else np.zeros(0, int), pitch_phase_start,
    )


def pitch_hypotheses(size: int, sizes: PixelSizes) -> None:
    """Make (and keep) the grid hypotheses ``map_family`` takes for an image ``size`` px across, so that
    they may be made ahead, beside other work."""
    _pitch_lattice(size, int(size / STEP_PX) + 1, float(sizes.min_pitch), float(sizes.max_pitch))


#: a pitch is passed over where its bound on the gain falls this fraction below the best score: the bound's
#: sums run in another order than the gains', which rounding may set some ulps apart
BOUND_SUM_MARGIN = 1e-9


def map_family(
    ll: np.ndarray,
    widths: np.ndarray,
    size: int,
    params: GridParams,
    sizes: PixelSizes,
    outer: tuple[np.ndarray, np.ndarray] | None = None,
    clipped_at: Callable[[float, float], bool] | None = None,
) -> FamilyFit | None:
    """The MAP grid of one family from l(c) [M] on the lattice (module docstring); None without 2 lines.
    ``outer`` (l(c) [M] and widths [M] with ``outer_edge_floor``; l(c) [2, M] where it differs beyond the
    first bar and beyond the last) extends the run by the outer frames and the end bays; ``clipped_at`` (a
    bar's centre and width, px) says where a bar's place shows nothing either way (``_with_end_bays``).

    Pitches run from the smallest up; at each, the phases are ranked by their gain (the sum of their
    positive terms, which bounds any run's score) and the best few get the exact run. A pitch none of whose
    phases can gain more than the best score so far adds nothing, so one whose bound on the relaxation
    (``relaxed_bound``) already says so is passed over; elsewhere the relaxation is computed only where
    its bound lets a term be positive (no other term counts in a gain), and in full on the phases that
    get the exact run: the scores, gains and their ranking are those of the relaxation everywhere."""
    M = len(ll)
    best: tuple[float, np.ndarray, float] | None = None
    lattice = _pitch_lattice(size, M, float(sizes.min_pitch), float(sizes.max_pitch))
    pitches = lattice.pitches
    if not len(pitches):
        return None
    sigmas = [max(SIGMA_MIN_PX, params.sigma_frac * pitch) for pitch in pitches]
    # sigma grows with the pitch: the last one reaches furthest
    windows = shift_windows(ll, _radius(sigmas[-1]))
    bound = relaxed_bound(reach(windows), np.array(sigmas)) - params.line_cost  # [S, M]
    terms = np.where(lattice.inside, bound.ravel()[lattice.by_pitch], -np.inf)
    phase_gain = np.add.reduceat(np.maximum(terms, 0.0), lattice.phase_start)
    pitch_gain = np.maximum.reduceat(phase_gain, lattice.pitch_phase_start) * (1.0 + BOUND_SUM_MARGIN)
    for i, pitch in enumerate(pitches):
        if best is not None and pitch_gain[i] <= best[0]:
            continue  # no phase's gain passes the best score: the ranked loop below would stop at once
        sigma = sigmas[i]
        pos, inside, clipped = lattice.of_pitch(i)
        positive = np.flatnonzero(bound[i] > 0)
        relaxed_ll = np.full(M, -np.inf)  # only the positive terms count in a gain
        relaxed_ll[positive] = relaxed_at(windows, sigma, positive)[0]
        vals = np.where(inside, relaxed_ll[clipped] - params.line_cost, -np.inf)
        gain = np.where(vals > 0, vals, 0.0).sum(axis=1)
        top = gain.argsort()[::-1][:8]  # only the most promising phases need the exact run
        if best is not None:  # those that may beat the best score: a prefix, the gains falling
            top = top[: int(np.count_nonzero(gain[top] > best[0]))]
        if not len(top):
            continue
        value, delta = (a.reshape(len(top), -1) for a in relaxed_at(windows, sigma, clipped[top].ravel()))
        value = np.where(inside[top], value - params.line_cost, -np.inf)
        for n, p in enumerate(top):
            if best is not None and gain[p] <= best[0]:
                break  # a run scores at most the sum of its positive terms: no better run from here on
            score, lo, hi = best_run(value[n])
            if hi - lo >= 2 and (best is None or score > best[0]):
                best = (score, pos[p, lo:hi] + delta[n, lo:hi], pitch)
    if best is None or best[0] <= 0:
        return None
    score, centres, pitch = best
    lat = np.clip(np.rint(centres / STEP_PX).astype(int), 0, M - 1)
    fit = FamilyFit(centres, widths[lat].astype(float), float(pitch), float(score))
    if outer is None:
        return fit
    framed = _with_outer_frames(fit, *outer, size, params)
    ended = (framed.centres[0] != fit.centres[0], framed.centres[-1] != fit.centres[-1])
    return _with_end_bays(framed, ll, widths, size, params, sizes, ended, clipped_at)


def _with_outer_frames(
    fit: FamilyFit, ll_outer: np.ndarray, widths_outer: np.ndarray, size: int, params: GridParams
) -> FamilyFit:
    """The run extended by one bar at either end where l(c) of a one-sided bar (an outer frame meeting a
    background of its own colour: its edge on the glass side only) one pitch beyond the end, relaxed as
    in the prior, pays for the line (module docstring). ``ll_outer`` [M], or [2, M]: beyond the first bar
    and beyond the last (the glass on the bar's high side, on its low side)."""
    ll_ends = np.broadcast_to(ll_outer, (2, ll_outer.shape[-1]))
    M = ll_ends.shape[1]
    sigma = max(SIGMA_MIN_PX, params.sigma_frac * fit.pitch)
    centres, widths, score = list(fit.centres), list(fit.widths), fit.score
    for end, sign in ((-1, 1.0), (0, -1.0)):
        windows = shift_windows(ll_ends[1 if sign > 0 else 0], _radius(sigma))
        c = centres[end] + sign * fit.pitch
        i = int(np.rint(c / STEP_PX))
        if not 0 <= i < M:
            continue
        value, delta = (float(a[0]) for a in relaxed_at(windows, sigma, np.array([i])))
        if value - params.line_cost <= 0:
            continue
        c_new = c + delta
        w = float(widths_outer[int(np.clip(np.rint(c_new / STEP_PX), 0, M - 1))])
        if c_new - w / 2 < 1.0 or c_new + w / 2 > size - 1.0:  # an outer frame lies whole in the view
            continue
        score += value - params.line_cost
        if sign > 0:
            centres.append(c_new)
            widths.append(w)
        else:
            centres.insert(0, c_new)
            widths.insert(0, w)
    return FamilyFit(np.array(centres), np.array(widths), fit.pitch, float(score))


#: an end bay of its own pitch costs this many lines: a bar off the grid's spacing is less likely a priori
#: than one on it, and twice a line's cost keeps single reflected edges (which the two-sided evidence
#: already discounts) out of it
END_BAY_LINES = 2.0
#: an end bay's pitch lies within this factor of the grid's (either way): a wider end bay, a taller ground
#: floor or a lower parapet row, not a second grid
END_BAY_RATIO = 2.0


def _with_end_bays(
    fit: FamilyFit, ll: np.ndarray, widths: np.ndarray, size: int, params: GridParams, sizes: PixelSizes,
    ended: tuple[bool, bool], clipped_at: Callable[[float, float], bool] | None = None,
) -> FamilyFit:
    """The run extended by one bar at either end, at a pitch of its own (a wider end bay, a taller ground
    floor): the best two-sided bar between 1 / ``END_BAY_RATIO`` and ``END_BAY_RATIO`` pitches (within the
    pitch range) beyond the end, kept where its l(c) pays ``END_BAY_LINES`` lines and it lies whole in the
    view. Not beyond an outer frame (``ended``: the facade ends there). Where the grid's own place one
    pitch beyond the end is ``clipped_at`` (the bar and what lies beside it clipped together: no edge either
    way) and the bar found lies off it by more than the prior's deviation, the bar is placed there at the
    run's median width instead (``FamilyFit.placed``): the grid's bar, a priori likelier than an end bay's
    (``END_BAY_LINES``), cannot be told absent there, while an edge found within the bay (the lit ceiling
    of an empty unit behind its frame) may be another object's."""
    M = len(ll)
    lo = max(sizes.min_pitch, fit.pitch / END_BAY_RATIO)
    hi = min(sizes.max_pitch, fit.pitch * END_BAY_RATIO)
    if hi < lo:
        return fit
    sigma = max(SIGMA_MIN_PX, params.sigma_frac * fit.pitch)
    median_width = float(np.median(fit.widths))
    centres, bar_widths, score = list(fit.centres), list(fit.widths), fit.score
    placed = set(fit.placed)
    for end, sign, done in ((-1, 1.0, ended[1]), (0, -1.0, ended[0])):
        if done:
            continue
        c = centres[end] + sign * np.arange(lo, hi + STEP_PX, STEP_PX)
        i = np.rint(c / STEP_PX).astype(int)
        w = widths[np.clip(i, 0, M - 1)]
        ok = (i >= 0) & (i < M) & (c - w / 2 >= 1.0) & (c + w / 2 <= size - 1.0)
        if not ok.any():
            continue
        gain = np.where(ok, ll[np.clip(i, 0, M - 1)], -np.inf) - END_BAY_LINES * params.line_cost
        k = int(np.argmax(gain))
        if gain[k] <= 0:
            continue
        at, width, grid_place = float(c[k]), float(w[k]), centres[end] + sign * fit.pitch
        if (clipped_at is not None and abs(at - grid_place) > sigma
                and grid_place - median_width / 2 >= 1.0 and grid_place + median_width / 2 <= size - 1.0
                and clipped_at(grid_place, median_width)):
            at, width = grid_place, median_width
            placed.add(len(centres) if sign > 0 else -1)
        else:
            score += float(gain[k])
        if sign > 0:
            centres.append(at)
            bar_widths.append(width)
        else:
            centres.insert(0, at)
            bar_widths.insert(0, width)
            placed = {j + 1 for j in placed}
    return FamilyFit(np.array(centres), np.array(bar_widths), fit.pitch, float(score), frozenset(placed))
