"""The evidence of the MAP grid model (``grid``'s module docstring): a view's colour gradients across one
family's bars on the hypotheses' lattice (``Gradients``), the two-edge bar response E_g (``bar_evidence``),
the LSD line support E_l (``lsd_evidence``), and the log-likelihood ratio l(c) of a bar at each position
(``log_likelihood``)."""

from __future__ import annotations

from concurrent.futures import Executor
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from facade_pipeline.segmentation.grid import STEP_PX, GridParams, PixelSizes

# An image-precision constant of the grid model, as grid.py's: the view is segmented at a fixed bar width in
# pixels (``SegmentParams.work_bar_px``)
#: LSD line support (fraction of the grid's length covered by segments) that counts as strong (-)
LSD_SCALE = 0.25
#: a pixel whose brightest channel is at or above this (0-1, after the view's exposure is taken out:
#: ``photometry``) is clipped: what it showed lies somewhere above full scale, so an edge between two such
#: pixels is unknown, not absent (a frame and the sky reflected beside it may both clip)
CLIPPED_LEVEL = 250 / 255

def nanmedian0(a: np.ndarray) -> np.ndarray:
    """The median over axis 0 of ``a`` [L, ...] leaving out NaNs (NaN where all are): ``np.nanmedian(a,
    axis=0)``, by one sort (NaNs sort last) instead of numpy's masked-array path, which is many times
    slower on the few hundred rows of a view. Each position's values are sorted side by side in memory, so
    that counting them is a pass along contiguous lanes (a reduction along a strided axis 0 is several
    times slower)."""
    if a.shape[0] == 0:
        return np.full(a.shape[1:], np.nan)
    s = np.sort(np.moveaxis(a, 0, -1), axis=-1)  # [..., L], a new array with contiguous lanes
    n = (~np.isnan(s)).sum(axis=-1)
    lo = np.take_along_axis(s, np.maximum((n - 1) // 2, 0)[..., None], axis=-1)[..., 0]
    hi = np.take_along_axis(s, (n // 2)[..., None], axis=-1)[..., 0]
    return np.where(n > 0, 0.5 * (lo + hi), np.nan)


def local_median(a: np.ndarray, block: float, max_step: float | None = None) -> np.ndarray:
    """``a`` [L, ..., 3] (colours) replaced by the median (NaNs left out) of its block along axis 0: about
    ``block`` rows each, the L rows split evenly (one block where L is no longer than ``block``). With
    ``max_step``, a lane whose neighbouring blocks' medians differ by more than that colour distance takes
    its median along the whole of axis 0 instead: shading turns smoothly from block to block, while a step
    is an edge crossing the lane (a rectified bar that is not quite straight leaves its frame colour in some
    blocks and the glass in others, and each block alone would look uniform)."""
    cuts = np.linspace(0, len(a), max(1, int(round(len(a) / block))) + 1).astype(int)
    med = [nanmedian0(a[i:j]) for i, j in zip(cuts[:-1], cuts[1:], strict=True)]
    out = np.concatenate([np.broadcast_to(m, (j - i,) + a.shape[1:])
                          for m, i, j in zip(med, cuts[:-1], cuts[1:], strict=True)])
    if max_step is None or len(med) < 2:
        return out
    step = norm_last(np.diff(np.stack(med), axis=0))  # [B - 1, ...]; NaN beside a block outside the view
    stepped = (np.where(np.isfinite(step), step, 0.0) > max_step).any(axis=0)
    return np.where(stepped[None, ..., None], nanmedian0(a)[None], out)


def norm_last(x: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(x, axis=-1)`` to the bit for a short last axis (fewer than 8: colour channels):
    numpy sums the squares left to right there, which this does channel by channel, several times faster
    than numpy's reduction over a short strided axis."""
    if not 0 < x.shape[-1] < 8:
        return np.linalg.norm(x, axis=-1)
    total = x[..., 0] * x[..., 0]
    for c in range(1, x.shape[-1]):
        total += x[..., c] * x[..., c]
    return np.sqrt(total, out=total)


@dataclass(frozen=True, eq=False)
class Gradients:
    """An RGB float image [L, N, 3] transposed so one family's bars are vertical, with its forward
    differences ``d`` [L, N - 1, 3] (``d[:, i]`` sits at the boundary position i + 1, px) set to 0 next to
    invalid pixels (outside the original view in a rectified image); L rows run along the bars."""

    img: np.ndarray
    d: np.ndarray
    valid: np.ndarray  # [L, N] bool
    known: np.ndarray | None = None
    """[L, N - 1] float, 1 where the boundary's edge is known, 0 where both of its pixels clip
    (``CLIPPED_LEVEL``); None where no pixel of the view clips."""
    block_px: float | None = None
    """The length (rows) along the bars over which a frame's own colour is taken as constant, where it is
    not along the whole bar: a transom following a curved surface turns through the surface's normals, and
    its shading with them (a 12 m cylinder lit from one side: from 0.29 to 0.55 across a view), which a
    colour constant along it takes for a reflection or an object in front. Its uniformity
    (``uniformity``) and presence (``edges.frame_presence``) are then judged against the median of each
    block (``local_median``), within which the shading hardly turns and a reflection does change, except
    where neighbouring blocks differ by more than ``block_step`` (an edge, not shading). None: against the
    median along the whole bar."""
    block_step: float | None = None
    # line colours by row span: a MAP pass's uniformity and colour prior and the bars' colour take the same
    _line_colours: dict[tuple[int, int, int], np.ndarray] = field(default_factory=dict, repr=False)

    @classmethod
    def of(cls, image: np.ndarray, axis: int, valid: np.ndarray | None = None,
           block_px: float | None = None, block_step: float | None = None) -> Gradients:
        """axis 0: vertical bars (mullions, positions along x); axis 1: horizontal bars (transoms)."""
        img = np.asarray(image, dtype=np.float32) / 255.0
        ok = np.ones(img.shape[:2], bool) if valid is None else np.asarray(valid, bool)
        if axis == 1:
            img, ok = img.transpose(1, 0, 2), ok.T
        d = np.diff(img, axis=1)
        d[~(ok[:, 1:] & ok[:, :-1])] = 0.0
        clipped = img.max(axis=2) >= CLIPPED_LEVEL
        known = None
        if clipped.any():
            known = (~(clipped[:, 1:] & clipped[:, :-1])).astype(np.float32)
        return cls(img, d, ok, known, block_px, block_step)

    @property
    def size(self) -> int:
        return self.d.shape[1] + 1

    def _interp(self, a: np.ndarray, first: float) -> np.ndarray:
        """a [L, n, ...] sampled at positions first + i, linearly interpolated at the lattice, 0 outside."""
        n = a.shape[1]
        f = np.arange(int(self.size / STEP_PX) + 1) * STEP_PX - first
        i0 = np.clip(np.floor(f).astype(int), 0, n - 1)
        i1 = np.clip(i0 + 1, 0, n - 1)
        t = np.clip(f - i0, 0.0, 1.0).reshape((1, -1) + (1,) * (a.ndim - 2))
        out = (1 - t) * a[:, i0] + t * a[:, i1]
        out[:, (f < 0) | (f > n - 1)] = 0.0
        return out

    # both are taken over several row spans of one image (the MAP passes, the bars' colour): kept once made
    @cached_property
    def on_lattice(self) -> np.ndarray:
        """[L, M, 3] gradients at the lattice positions ``j * STEP_PX``."""
        return self._interp(self.d, 1.0)

    @cached_property
    def known_on_lattice(self) -> np.ndarray | None:
        """[L, M] ``known`` at the lattice positions (``on_lattice``'s), None where nothing clips."""
        return None if self.known is None else self._interp(self.known, 1.0)

    @cached_property
    def _samples(self) -> np.ndarray:
        """[L, M, 3] the image at each lattice position (interpolated between pixel centres), NaN outside
        the view."""
        return self._interp(np.where(self.valid[..., None], self.img, np.nan), 0.5)

    def prepare(self) -> Gradients:
        """Make the lattice arrays the MAP passes read (kept once made), so that they may be made ahead,
        beside other work."""
        _ = self.on_lattice, self._samples, self.known_on_lattice
        return self

    def _line_samples(self, rows: slice) -> np.ndarray:
        """[L', M, 3] ``_samples`` over ``rows``."""
        return self._samples[rows]

    def line_colour(self, rows: slice) -> np.ndarray:
        """[M, 3] median colour over ``rows`` of the image at each lattice position (NaN outside the view);
        read-only, kept for the span."""
        key = rows.indices(self.img.shape[0])
        if key not in self._line_colours:
            colour = nanmedian0(self._line_samples(rows))
            colour.flags.writeable = False
            self._line_colours[key] = colour
        return self._line_colours[key]

    def uniformity(self, rows: slice) -> np.ndarray:
        """v(c) [M]: median over ``rows`` of the colour distance of the image at position c (interpolated
        between pixel centres) from its median along the rows (``local_median``: over its block of
        ``block_px`` rows where set); small along a uniform frame bar."""
        col = self._line_samples(rows)  # [L, M, 3]
        if self.block_px is None:
            ref = self.line_colour(rows)[None]
        else:
            ref = local_median(col, self.block_px, self.block_step)
        v = nanmedian0(norm_last(col - ref))
        return np.where(np.isfinite(v), v, 1.0)  # positions outside the view (rectified images) are all NaN


def bar_evidence(
    grad: Gradients, rows: slice, params: GridParams, sizes: PixelSizes,
    weak_edge_floors: tuple[float, ...] = (0.0,), pool: Executor | None = None,
    unknown_floor: float = 0.0,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Gradient bar evidence E_g [M] on the lattice (mean over ``rows``) and the best width [M] (px), one
    pair per floor of ``weak_edge_floors`` (the edges and their agreement are computed once for all).

    Per row, edges gL, gR (colour vectors) at the two sides of the bar give sqrt((|gL||gR| - gL.gR) / 2):
    |gL||gR| for opposite polarity (frame brighter or darker than both sides), less as the colour changes
    agree, 0 for equal changes (a ramp, not a bar). The weaker edge counts at least its floor's fraction
    of the stronger: 0 inside the grid, where both edges must be seen; ``outer_edge_floor`` for the outer
    frame bars.

    With s, w the stronger and weaker edge magnitude and f the floor, s max(w, f s) is computed as the
    larger of |gL||gR| and of m (f m) over the two edges' magnitudes m: rounding is monotone, so that is
    the product the plain expression rounds to, with m (f m) made once per position for every width.
    With a ``pool``, the wider half of the widths is evaluated on it while the caller takes the narrower
    (numpy lets go of the GIL); the best width is then taken over the widths in order as without it.

    An edge between two clipped pixels (``Gradients.known``) is unknown, not absent: where one of a bar's
    edges is, its known edge counts as a one-sided bar's, the unknown one at least ``unknown_floor`` of
    it, whatever the floor (a frame clipped with the glass beside it meets a background of its own
    colour there, as an outer frame may meet the sky)."""
    g = grad.on_lattice[rows]
    mag = norm_last(g)
    unknown = None
    if unknown_floor > 0 and grad.known_on_lattice is not None:
        unknown = (1.0 - grad.known_on_lattice[rows], mag * (unknown_floor * mag))
    channels = []  # [rows, M] each, laid out as the magnitudes (the lattice runs along the rows)
    for c in range(g.shape[2]):
        channels.append(np.empty_like(mag))
        np.copyto(channels[-1], g[..., c])
    M = g.shape[1]
    # an edge's magnitude times the floor's share of it; None for a floor of 0 or less, where s max(w, f s)
    # is s w = |gL||gR| itself
    floored = [mag * (floor * mag) if floor > 0 else None for floor in weak_edge_floors]
    widths = [w for w in range(sizes.min_bar, sizes.max_bar + 1) if 2 * w < M]  # w: half width in steps

    def evidence(ws: list[int]) -> list[list[np.ndarray]]:
        return [_width_evidence(mag, channels, floored, w, unknown) for w in ws]

    half = (len(widths) + 1) // 2
    wide = pool.submit(evidence, widths[half:]) if pool is not None else None
    found = evidence(widths[:half] if wide is not None else widths)
    if wide is not None:
        found += wide.result()
    out = [(np.zeros(M), np.zeros(M)) for _ in weak_edge_floors]
    for w, per_floor in zip(widths, found, strict=True):
        for e, (best, width) in zip(per_floor, out, strict=True):
            better = e > best
            best[better], width[better] = e[better], w
    return out


def _width_evidence(mag: np.ndarray, channels: list[np.ndarray], floored: list[np.ndarray | None],
                    h: int, unknown: tuple[np.ndarray, np.ndarray] | None = None) -> list[np.ndarray]:
    """E_g [M] at one width of ``bar_evidence`` (h: its half width in lattice steps), per floor;
    ``unknown``: how unknown each edge is (1 - ``Gradients.known``) and its floored product, where an edge
    may be."""
    M = mag.shape[1]
    left, right = slice(0, M - 2 * h), slice(2 * h, M)
    product = mag[:, left] * mag[:, right]
    # done in place, channel by channel, as the sum of the products over the channels would add them, so
    # that the values are those of the plain expressions
    dot = channels[0][:, left] * channels[0][:, right]
    for c in channels[1:]:
        dot += c[:, left] * c[:, right]
    cos = np.divide(dot, np.maximum(product, 1e-12), out=dot)
    disagree = np.clip(np.subtract(1.0, cos, out=cos), 0.0, 2.0, out=cos)
    one_sided = None
    if unknown is not None:
        # the known edge's own floored product where its partner is unknown; the unknown edge's polarity is
        # unknown too (1 - cos averages 1 over its directions): a few levels' difference between clipped
        # pixels has no direction to speak of
        u, uq = unknown
        one_sided = np.maximum(u[:, left] * uq[:, right], u[:, right] * uq[:, left])
    out = []
    for q in floored:
        # an outer frame may border a background of its own colour on one side. e2 is laid out in memory
        # as the magnitudes are (the lattice's layout), which sets the order of the sum over the rows below
        e2 = np.empty_like(product)
        if q is None:
            np.multiply(product, disagree, out=e2)
        else:
            np.maximum(product, np.maximum(q[:, left], q[:, right]), out=e2)
            e2 *= disagree
        if one_sided is not None:
            np.maximum(e2, one_sided, out=e2)
        e2 /= 2
        out.append(np.pad(np.sqrt(e2, out=e2).mean(axis=0), (h, h)))
    return out


def lsd_evidence(support: np.ndarray, width: np.ndarray, length_px: float) -> np.ndarray:
    """E_l [M]: geometric mean of the line support at the two edges of a bar of ``width`` [M], per length."""
    M = len(support)
    idx = np.arange(M)
    h = np.maximum(width.astype(int), 1)
    left = support[np.clip(idx - h, 0, M - 1)]
    right = support[np.clip(idx + h, 0, M - 1)]
    return np.sqrt(left * right) / max(length_px, 1.0)


def log_likelihood(
    e_grad: np.ndarray, e_lsd: np.ndarray, uniformity: np.ndarray, params: GridParams,
    colour_distance: np.ndarray | None = None,
) -> np.ndarray:
    """l(c) [M] of the module docstring; ``colour_distance`` [M] (to the other family's frame colour) costs
    ``frame_colour_scale`` per nat."""
    background = float(np.median(e_grad)) + 1e-6
    ll = (
        np.log1p(e_grad / background)
        + params.lsd_weight * np.log1p(e_lsd / LSD_SCALE)
        - uniformity / params.uniformity_scale
    )
    if colour_distance is not None and params.frame_colour_scale > 0:
        ll = ll - np.where(np.isfinite(colour_distance), colour_distance, 0.0) / params.frame_colour_scale
    return ll
