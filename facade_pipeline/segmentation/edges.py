"""Sub-pixel frame edges: the two edges of each MAP bar, located per row and fitted as straight lines.

Positions follow the pixel-centre convention (pixel i spans [i, i + 1], centre i + 0.5); a forward difference
``d[i] = I[i + 1] - I[i]`` sits at the boundary position i + 1. Along a bar, the edge position in each row is
the sub-pixel peak (centroid of the peak and its neighbours) of the gradient projected on the edge's mean
gradient direction (which fixes
the polarity, so the bar's other edge is never taken). The per-row positions are fitted by weighted least
squares (weights: peak strength) as ``x = a + b (y - mid)`` with two rounds of outlier rejection.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facade_pipeline.segmentation.evidence import CLIPPED_LEVEL, Gradients, local_median
from facade_pipeline.segmentation.grid import FamilyFit


@dataclass(frozen=True)
class EdgeLine:
    """A straight edge ``pos = a + b (t - mid)``: ``pos`` across the bars, ``t`` along them (px).
    ``strength`` [L] is the per-row peak strength along the bar (0 where no edge was found)."""

    a: float
    b: float
    mid: float
    strength: np.ndarray
    present: np.ndarray | None = None
    """[L] float: 1 where the bar's own colour is seen on its centre line, 0 where not, NaN outside the
    view (None: not measured)."""
    unknown: np.ndarray | None = None
    """[L] bool: where the bar's centre line is clipped white away from the bar's own colour (``present``
    0 there): what it shows lies somewhere above full scale, a highlight on the frame or the lit box of an
    empty unit beside it as much as an object in front (None: nowhere, or not measured)."""
    short: np.ndarray | None = None
    """[L] bool: where the bar's centre line is within the tolerance of its own colour (``present`` 1
    there), clipped in one channel and below full scale in another where that colour is clipped: as bright
    as the frame (above full scale), yet of another hue (the lit box of an empty unit), where the frame
    shaded would fall below full scale in its clipped channels together (None: nowhere, or not
    measured)."""
    half_present: np.ndarray | None = None
    """[L] float: as ``present``, on the line halfway between this edge and the bar's centre line (the
    half of the bar on this edge's side), 0 where ``short`` there; judged against the bar's colour where
    that line's own colour is not within the tolerance of it (``frames.with_presence``). A unitised
    facade's bar is the frames of the two units beside it, side by side: beside a unit not installed only
    the other unit's half is there (None: not measured)."""
    half_at_place: np.ndarray | None = None
    """[L] float: as ``half_present``, for a bar found thin and widened (``frames.widen_narrow_bars``) to
    one beside the thin one rather than over it, or found at the width of one half of the building's bar
    (from a half to three quarters of it) and kept where the bar's place (where the view shows it whole
    beyond the other family's bars, else the building's pitch's) lies beside it: the same half of the bar
    of the building's width that holds the thin one as its half away from the widened bar, or from that
    place, read against the thin one's colour (``frames._halves_at_place``; None elsewhere). Beside a unit
    not installed the thin one is the half that is there, and the widened bar, or the bar's place, lies on
    that unit's box."""
    clip_beyond: np.ndarray | None = None
    """[L] bool: where the bar's centre line is clipped white in every channel, in one clipped run with what
    lies a bar's width beyond one of its edges (``clipped_beyond``). A frame clipped alone is bounded by
    what lies beside it; in one run with it (glass mirroring a sky clipped, a fringe beside it) the centre
    line's white tells nothing of the frame: where the bar's colour is clipped too it reads ``present``
    there, as anything clipped would (None: nowhere, or not measured)."""
    frames_colour: np.ndarray | None = None
    """[L] float, 1 / 0 / NaN outside the view: where the centre line of a bar found thin and widened to the
    building's width (``frames.widen_narrow_bars``), or the middle of this edge's half of it, shows the
    other family's colour, or is clipped white (unknown, not absent), 0 where neither does (None: a bar
    found at its width)."""

    def at(self, t: np.ndarray | float) -> np.ndarray:
        return self.a + self.b * (np.asarray(t, dtype=np.float64) - self.mid)


def _row_peaks(q: np.ndarray, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel peak positions [L] (px) and values [L] of q [L, N - 1] within columns [lo, hi): the
    centroid of the positive differences at the peak and its two neighbours. A step box-filtered over the
    pixel it crosses gives two differences in the ratio of the pixel's two parts, whose centroid is the
    step's position exactly (a parabola through them pulls it toward pixel centres and boundaries)."""
    win = q[:, lo:hi]
    i = np.argmax(win, axis=1)
    L, n = win.shape
    rows = np.arange(L)
    val = win[rows, i]
    num = np.zeros(L)
    den = np.zeros(L)
    for k in (-1, 0, 1):
        j = i + k
        ok = (j >= 0) & (j < n)
        w = np.where(ok, np.maximum(win[rows, np.clip(j, 0, n - 1)], 0.0), 0.0)
        num += w * k
        den += w
    off = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    return lo + i + 1.0 + off, val


def fit_edge(grad: Gradients, position: float, sign: float, rows: slice, search_px: float) -> EdgeLine | None:
    """The edge near ``position`` (px) whose gradient, times ``sign``, points along the rows' mean gradient
    there; None if there is no such edge."""
    d = grad.d
    n = d.shape[1]
    j = int(np.clip(round(position - 1.0), 0, n - 1))
    direction = sign * d[rows, j].mean(axis=0)
    if np.linalg.norm(direction) < 1e-6:
        return None
    q = (d @ (direction / np.linalg.norm(direction))).astype(np.float64)  # [L, N - 1]
    lo = int(max(0, np.floor(position - 1.0 - search_px)))
    hi = int(min(n, np.ceil(position - 1.0 + search_px) + 1))
    if hi - lo < 1:
        return None
    pos, val = _row_peaks(q, lo, hi)
    t = np.arange(len(q)) + 0.5
    use = np.zeros(len(q), bool)
    use[rows] = True
    use &= val > 0
    if use.sum() < 2:
        return None
    mid = float(t[use].mean())
    a, b = float(np.average(pos[use], weights=val[use])), 0.0
    for tol in (1.0, 0.5):
        res = np.abs(pos - (a + b * (t - mid)))
        keep = use & (res <= tol)
        if keep.sum() < 2:
            break
        A = np.stack([np.ones(keep.sum()), t[keep] - mid], axis=1) * val[keep, None]
        a, b = np.linalg.lstsq(A, pos[keep] * val[keep], rcond=None)[0]
    strength = np.where(np.abs(pos - (a + b * (t - mid))) <= 1.0, np.maximum(val, 0.0), 0.0)
    return EdgeLine(float(a), float(b), mid, strength)


#: a bar's edge whose place is known (``Gradients.known``) over at most this fraction of its length lies
#: between clipped pixels there: the frame and what lies beside it clip together, which leaves no edge to
#: find (a bar one pitch beyond either end of a family's run is placed by the grid where both edges are:
#: the frames are regular across a curtain wall, ``frames.with_clipped_ends``)
CLIPPED_BAR_KNOWN = 0.5


def bar_edges(
    grad: Gradients, centre: float, width: float, rows: slice, search_px: float, place_unknown: bool = True,
    family_px: float | None = None,
) -> tuple[EdgeLine, EdgeLine] | None:
    """The (low, high) edges of the bar centred at ``centre`` with ``width`` (px), or None. Each edge takes
    the polarity of the mean gradient at its expected position. With ``place_unknown``, an edge not fitted
    whose place is unknown in every row (``known_share`` 0: a frame clipped with what lies beside it, or
    cut by the view's border) is no evidence against the bar: it is placed ``width`` from the other edge,
    parallel to it, with no strength; and an edge fitted where its place is mostly unknown is made
    parallel to the other where the two part by more than ``family_px`` (the width of the family's bars;
    None: ``width``) along the bar (``_parallel_where_clipped``)."""
    low = fit_edge(grad, centre - width / 2, 1.0, rows, search_px)
    high = fit_edge(grad, centre + width / 2, 1.0, rows, search_px)
    if place_unknown and (low is None) != (high is None):
        seen, side = (high, -1.0) if low is None else (low, 1.0)
        if known_share(grad, centre + side * width / 2, rows, search_px) == 0.0:
            placed = EdgeLine(seen.a + side * float(width), seen.b, seen.mid, np.zeros_like(seen.strength))
            low, high = (placed, high) if low is None else (low, placed)
    elif place_unknown and low is not None and high is not None:
        low, high = _parallel_where_clipped(grad, low, high, width if family_px is None else family_px,
                                            rows, search_px)
    if low is None or high is None or high.a <= low.a:
        return None
    return low, high


def _parallel_where_clipped(grad: Gradients, low: EdgeLine, high: EdgeLine, width: float, rows: slice,
                            search_px: float) -> tuple[EdgeLine, EdgeLine]:
    """``low`` and ``high`` with an edge whose place is known over at most ``CLIPPED_BAR_KNOWN`` of
    ``rows`` (``known_share``), where the other's is known over more, made parallel to the other through
    its own fitted line at the middle of the rows it was found in, where the two part by more than
    ``width`` (px, the family's bars') over ``rows``: the few rows it is known in lie where the frame's
    clip ends in what lies beside it (an empty unit's lit shelf slanting away from a transom), and their
    slope, carried along the whole bar, would part its edges by more than a bar's width from one end to
    the other. A frame's two edges are parallel. The family's width, not the bar's own: the edges of a
    bar the grid takes thin part by its width at a slope of a few hundredths, within a fit's scatter."""
    length = len(range(*rows.indices(len(low.strength))))
    share = [known_share(grad, line.at(line.mid), rows, search_px) for line in (low, high)]
    for k, (edge, other) in enumerate(((low, high), (high, low))):
        if share[k] > CLIPPED_BAR_KNOWN or share[1 - k] <= CLIPPED_BAR_KNOWN:
            continue
        w = edge.strength
        if w.sum() <= 0 or abs(edge.b - other.b) * length <= width:
            continue
        t = float(np.average(np.arange(len(w)) + 0.5, weights=w))
        parallel = EdgeLine(float(edge.at(t)) + other.b * (other.mid - t), other.b, other.mid, w)
        return (parallel, high) if k == 0 else (low, parallel)
    return low, high


def known_share(grad: Gradients, position: float, rows: slice, search_px: float) -> float:
    """The fraction of ``rows`` in which a boundary within ``search_px`` of ``position`` (px; ``fit_edge``'s
    search) is known: in the others each lies between two clipped pixels (``Gradients.known``) or beside a
    pixel outside the view, where an edge may be as well as not."""
    n = grad.d.shape[1]
    lo = int(max(0, np.floor(position - 1.0 - search_px)))
    hi = int(min(n, np.ceil(position - 1.0 + search_px) + 1))
    if hi - lo < 1:
        return 0.0
    known = grad.valid[rows, lo:hi] & grad.valid[rows, lo + 1 : hi + 1]
    if grad.known is not None:
        known &= grad.known[rows, lo:hi] > 0
    return float(known.any(axis=1).mean()) if len(known) else 0.0


def centre_colour(grad: Gradients, low: EdgeLine, high: EdgeLine) -> tuple[np.ndarray, np.ndarray]:
    """[L, 3] the image on the centre line between ``low`` and ``high`` (the pixel whose span holds it) and
    [L] bool where that pixel shows the view."""
    L, N = grad.img.shape[:2]
    t = np.arange(L) + 0.5
    centre = 0.5 * (low.at(t) + high.at(t))
    col = np.clip(np.floor(centre).astype(int), 0, N - 1)
    return grad.img[np.arange(L), col], grad.valid[np.arange(L), col]


def bar_colour_ref(grad: Gradients, low: EdgeLine, high: EdgeLine, rows: slice) -> np.ndarray | None:
    """The bar's own colour, [3] or [L, 3] (each block's, ``Gradients.block_px``): the median over ``rows``
    of its centre line between ``low`` and ``high``; None where no row of them shows the view."""
    colour, ok = centre_colour(grad, low, high)
    ref_rows = np.zeros(len(colour), bool)
    ref_rows[rows] = True
    ref_rows &= ok
    if not ref_rows.any():
        return None
    if grad.block_px is None:
        return np.median(colour[ref_rows], axis=0)
    # each block's own colour (``Gradients.block_px``)
    ref = local_median(np.where(ref_rows[:, None], colour, np.nan), grad.block_px, grad.block_step)
    return np.where(np.isnan(ref), np.median(colour[ref_rows], axis=0), ref)


def frame_presence(grad: Gradients, low: EdgeLine, high: EdgeLine, rows: slice, tol: float,
                   ref: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """[L] float, 1 / 0 / NaN outside the view: where the bar between ``low`` and ``high`` shows its own
    colour on its centre line (within ``tol``, RGB distance on 0-1, of its median over ``rows``,
    ``bar_colour_ref``; or of ``ref`` where given, the colour of a bar of which this line is a part). A
    frame keeps its colour whatever the glass beside it reflects; an object in front of it (a tree) does
    not, which is what marks a panel occluded. With it, [L] bool: where the centre line is not the bar's
    colour and clipped white (``EdgeLine.unknown``), and [L] bool: where it is within ``tol`` of the bar's
    colour, clipped, and below full scale in a channel where that colour is clipped (``EdgeLine.short``),
    each None where it is nowhere."""
    colour, ok = centre_colour(grad, low, high)
    if ref is None:
        ref = bar_colour_ref(grad, low, high, rows)
    if ref is None:
        return np.where(ok, 1.0, np.nan), None, None
    near = np.linalg.norm(colour - ref, axis=1) <= tol
    clipped = colour.max(axis=1) >= CLIPPED_LEVEL
    unknown = ok & ~near & clipped
    ref_clipped = np.broadcast_to(ref, colour.shape) >= CLIPPED_LEVEL
    short = ok & near & clipped & (ref_clipped & (colour < CLIPPED_LEVEL)).any(axis=1)
    return (np.where(ok, near.astype(float), np.nan), (unknown if unknown.any() else None),
            (short if short.any() else None))


def clipped_beyond(grad: Gradients, low: EdgeLine, high: EdgeLine) -> np.ndarray | None:
    """[L] bool: where the pixel on the centre line between ``low`` and ``high`` is clipped white in every
    channel and the run of such pixels across the bar through it reaches the bar's width (its fitted
    width in that row) beyond either edge (``EdgeLine.clip_beyond``); None where it is nowhere. A run cut
    by the view's border short of that is not counted: what lies beyond is not seen."""
    L, N = grad.img.shape[:2]
    t = np.arange(L) + 0.5
    lo, hi = low.at(t), high.at(t)
    width = hi - lo
    # only the columns a bar's width either side of the bar: a run reaching the window's end reaches that
    c0 = int(np.clip(np.floor((lo - width).min()) - 1, 0, N - 1))
    c1 = int(np.clip(np.ceil((hi + width).max()) + 2, c0 + 1, N))
    col = np.clip(np.floor(0.5 * (lo + hi)).astype(int), c0, c1 - 1) - c0
    clipped = (grad.img[:, c0:c1] >= CLIPPED_LEVEL).all(axis=2) & grad.valid[:, c0:c1]  # [L, c1 - c0]
    cols = np.arange(c0, c1)
    # each row's last column at or before each column that is not clipped, and its first at or after
    before = np.maximum.accumulate(np.where(clipped, c0 - 1, cols), axis=1)
    after = np.minimum.accumulate(np.where(clipped, c1, cols)[:, ::-1], axis=1)[:, ::-1]
    rows = np.arange(L)
    beyond = clipped[rows, col] & ((before[rows, col] + 1 <= lo - width) | (after[rows, col] >= hi + width))
    return beyond if beyond.any() else None


@dataclass(frozen=True)
class Bars:
    """One family's bars: edge lines (low, high) per bar, along-bar length, and the fit."""

    edges: list[tuple[EdgeLine, EdgeLine]]
    fit: FamilyFit
