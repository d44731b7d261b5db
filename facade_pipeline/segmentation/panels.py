"""Glass panels of a (rectified) frontal view: LSD segments -> MAP grid of frame bars (``grid``) -> sub-pixel
bar edges (``edges``) -> panels with four corners, row and column indices, and completeness.

A panel is the opening between two consecutive mullions and two consecutive transoms; its corners are the
intersections of the four bar edges that face it, ordered bottom-left, bottom-right, top-right, top-left
(as seen from outside, which is the image's left and right). Rows count from the lowest visible row.

Panels cut by the image border: the strip between the outermost bar and the border holds a partial panel
(``complete = False``) when it is at least ``min_partial_m`` wide and the bars of the other family continue
into it (by their frame colour or their edges, where the facade surface is there: ``_continues``); otherwise
the facade ends at that bar, except beside the bars that continue on their own (a stepped facade, an empty
or offset unit): there the opening between two such bars, or one and the border, is a partial panel.
Partly occluded panels: a panel whose frame bars are present (their centre line within ``frame_colour_tol``
of the bar's median colour: a frame keeps its colour whatever the glass beside it reflects, an object in
front of it does not), or show their edge facing the panel, over less than ``MIN_EDGE_SUPPORT`` of any
side's length is kept, with ``complete = False``.

Parallax of proud frames: frames stand d in front of the glass, so the front face of a bar is seen shifted
away from the camera along the surface by d tan(a), a the angle of the line of sight from the surface normal
(in the plane of the normal and the direction across the bar); its front face hides a strip of the glass
beyond it of that width, while on its side towards the camera the bar's side face shows. In pixels the shift
is k' P, with P the view's parallax coordinate (``ParallaxField``: D tan(a) / m, D the camera's distance to
the surface, m the scale) and k' = d / D = k / (1 + k). Seen straight on to a plane, P = u - c, the distance
from the camera's foot c; across an unrolled cylinder P grows faster than the distance (the surface turns
away from the camera), and for the horizontal bars it changes along the bar. A bar's apparent width thus
grows as w = B + k P, with P at its far (front-face) edge; on a side of c where the side faces are shaded
like the glass, the near edge found is the front face's as well, and the width does not grow there. k and
those sides are fitted per family and view (``fit_parallax``); where both sides' side faces are shaded the
widths show no k at all, so a rectified view takes k from the building's frame depth per family (the median
of the views' fits, ``segment_frames``). The front-face edges are moved back by k P / (1 + k) along their
length, where the glass meets the frame: corners are the glass panel's corners, and masks are the panels'
quads, hidden strips included (``parallax_max_slope = 0`` keeps the visible glass instead).

Masks: a pixel belongs to a panel when its centre lies inside the panel's quad, the way the views are
sampled (one ray through each pixel centre); a centre exactly on a quad's edge is decided by the half-open
rule (inside on the left and top edges, outside on the right and bottom ones), so that a panel whose edge
falls on pixel centres takes the same pixels as the truth does and two panels sharing an edge never share a
pixel.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np

from facade_pipeline.segmentation.edges import EdgeLine, bar_edges, frame_presence
from facade_pipeline.segmentation.grid import (
    EDGE_SEARCH_PX,
    STEP_PX,
    FamilyFit,
    Gradients,
    PixelSizes,
    bar_evidence,
    log_likelihood,
    lsd_evidence,
    map_family,
    nanmedian0,
    pitch_hypotheses,
)
from facade_pipeline.segmentation.lines import detect_segments, group_segments, support_profile
from facade_pipeline.segmentation.params import SegmentParams
from facade_pipeline.segmentation.photometry import normalise_exposure
from facade_pipeline.threads import usable_cores

# Image-precision constants of the segmentation. The view is resampled so that the narrowest frame bar spans
# ``work_bar_px`` pixels (SegmentParams), so these hold at any facade scale and photo size; no building ever
# needed other values, and the segmentation benchmarks (benchmarks/RESULTS.md) were measured with them.
#: shortest LSD segment kept (px of the view): shorter ones are texture and noise, not frame edges
MIN_SEGMENT_PX = 3.0
#: the dominant vertical and horizontal angles are searched this far (deg) from 90 and 0 deg: rectified
#: views are fronto-parallel, so only a small residual tilt is left
ORIENTATION_SEARCH_DEG = 10.0
#: a segment belongs to a family within this angle (deg) of its dominant angle
ORIENTATION_TOLERANCE_DEG = 3.0
#: smoothing of the LSD line-support profile (px)
LSD_SIGMA_PX = 0.75
#: a family with fewer whole frame bars than this is not corrected for parallax: three points are the
#: fewest that tell a slope from one bar's error
PARALLAX_MIN_BARS = 3
#: a view's parallax slope counts where it stands this many standard errors above 0 (from the fit's own
#: residual): a fit through few bars measured in a real photo scatters by more than the slope of frames
#: nearly flush with the glass, and a slope from noise would shift every corrected edge
PARALLAX_MIN_T = 3.0
#: a panel side whose frame is present over less than this fraction of its length marks the panel occluded
MIN_EDGE_SUPPORT = 0.6


@dataclass(frozen=True)
class Panel:
    """One panel in the segmented image's pixels: corners [4, 2] (bottom-left, bottom-right, top-right,
    top-left), indices, and whether it is whole (``reason``: "", "border" or "occluded")."""

    row: int
    col: int
    corners: np.ndarray
    complete: bool
    reason: str


@dataclass
class Segmentation:
    facade_found: bool
    panels: list[Panel]
    metrics: dict = field(default_factory=dict)
    reason: str = ""
    """without panels: which evidence was missing"""


@dataclass(frozen=True)
class _Bars:
    """One family's bars: edge lines (low, high) per bar, along-bar length, and the fit."""

    edges: list[tuple[EdgeLine, EdgeLine]]
    fit: FamilyFit


def _family(
    grad: Gradients,
    segments: np.ndarray | Callable[[], np.ndarray],
    axis: int,
    span: slice,
    params: SegmentParams,
    sizes: PixelSizes,
    frame_colour: np.ndarray | None = None,
    pool: Executor | None = None,
) -> FamilyFit | None:
    """MAP bars of one family (axis 0: mullions; ``grad`` its gradients) with evidence taken over ``span``
    along the bars; with ``frame_colour`` [3] (the other family's bars), bars of another colour are
    penalised. ``segments`` (the family's LSD segments) may be a function that waits for them: they are
    needed only once the gradient evidence is made. With a ``pool``, the uniformity and part of the bar
    evidence are computed on it."""
    uniformity = pool.submit(grad.uniformity, span) if pool is not None else None
    (e_grad, widths), (e_out, w_out) = bar_evidence(grad, span, params.grid, sizes,
                                                    (0.0, params.grid.outer_edge_floor), pool)
    uniformity = uniformity.result() if uniformity is not None else grad.uniformity(span)
    if callable(segments):
        segments = segments()
    lo, hi, _ = span.indices(grad.d.shape[0])
    t = 0.5 * (segments[:, 1 - axis] + segments[:, 3 - axis]) if len(segments) else np.zeros(0)
    inside = segments[(t >= lo) & (t <= hi)]
    support = support_profile(inside, axis, grad.size, STEP_PX, LSD_SIGMA_PX)[: len(e_grad)]
    dist = None
    if frame_colour is not None:
        # a difference within the tolerance of frame_presence is the frames' own shading (a curved facade
        # turns its transoms through many normals): only what lies beyond it costs
        dist = np.linalg.norm(grad.line_colour(span) - frame_colour, axis=1)[: len(e_grad)]
        dist = np.maximum(dist - params.frame_colour_tol, 0.0)
    ll = log_likelihood(e_grad, lsd_evidence(support, widths, hi - lo), uniformity, params.grid, dist)
    # outer frames are judged without the colour prior: one side meets the background, and the centre line
    # of a one-sided bar found at its glass-side edge is not reliably on the frame
    ll_out = log_likelihood(e_out, lsd_evidence(support, w_out, hi - lo), uniformity, params.grid)
    return map_family(ll, widths, grad.size, params.grid, sizes, (ll_out, w_out))


def bar_colour(grad: Gradients, fit: FamilyFit, span: slice) -> np.ndarray:
    """[3] median colour (0-1) of one family's bars (``grad`` of that family): along their centre lines
    over ``span``."""
    colour = grad.line_colour(span)
    idx = np.clip(np.rint(fit.centres / STEP_PX).astype(int), 0, len(colour) - 1)
    return nanmedian0(colour[idx])


def _span(fit: FamilyFit | None, size: int) -> slice:
    """Along-bar range of the other family: from the first to the last bar centre of ``fit``."""
    if fit is None:
        return slice(0, size)
    return slice(int(max(0, np.floor(fit.centres[0]))), int(min(size, np.ceil(fit.centres[-1]) + 1)))


def _edges(fit: FamilyFit, grad: Gradients, span: slice, params: SegmentParams) -> _Bars | None:
    found = [
        bar_edges(grad, c, w, span, EDGE_SEARCH_PX)
        for c, w in zip(fit.centres, fit.widths, strict=True)
    ]
    edges = []
    for e in found:
        if e is None:
            continue
        present = frame_presence(grad, e[0], e[1], span, params.frame_colour_tol)
        edges.append(tuple(dataclasses.replace(line, present=present) for line in e))
    return _Bars(edges, fit) if edges else None


@dataclass(frozen=True, eq=False)
class ParallaxField:
    """The parallax coordinate P (px; module docstring) of a view's image, sampled on a grid: ``p``
    [Gy, Gx, 2] (P across the mullions, i.e. along x, and across the transoms, along y) at image positions
    ``xs`` [Gx], ``ys`` [Gy] (px, increasing); read between samples bilinearly, beyond them by the nearest."""

    xs: np.ndarray
    ys: np.ndarray
    p: np.ndarray
    distance_m: float = float("nan")
    """D, the camera's distance to the surface (m); NaN where no surface is known (a view not rectified)."""

    @classmethod
    def about(cls, centre: tuple[float, float], width: int, height: int) -> ParallaxField:
        """The field of a ``width`` x ``height`` image of a plane whose camera's foot is ``centre`` (x, y):
        P = the position less the centre (bilinear over a linear field: exact, and sampled a whole image
        beyond every border)."""
        xs, ys = np.array([-1.0, 2.0]) * width, np.array([-1.0, 2.0]) * height
        gx, gy = np.meshgrid(xs - centre[0], ys - centre[1])
        return cls(xs, ys, np.stack([gx, gy], axis=-1))

    def scaled(self, qx: float, qy: float) -> ParallaxField:
        """The field of the image resized by (qx, qy)."""
        return ParallaxField(self.xs * qx, self.ys * qy, self.p * [qx, qy], self.distance_m)

    def along(self, axis: int, pos: np.ndarray, t: np.ndarray) -> np.ndarray:
        """P across the bars of family ``axis`` (0: mullions, positions x along rows y = t; 1: transoms,
        positions y along columns x = t) at [N] points."""
        x, y = (pos, t) if axis == 0 else (t, pos)
        return self._bilinear(np.asarray(x, float), np.asarray(y, float), axis)

    def _bilinear(self, x: np.ndarray, y: np.ndarray, c: int) -> np.ndarray:
        fx = np.interp(x, self.xs, np.arange(len(self.xs)))
        fy = np.interp(y, self.ys, np.arange(len(self.ys)))
        i = np.minimum(fx.astype(int), len(self.xs) - 2) if len(self.xs) > 1 else np.zeros_like(fx, int)
        j = np.minimum(fy.astype(int), len(self.ys) - 2) if len(self.ys) > 1 else np.zeros_like(fy, int)
        u, v = fx - i, fy - j
        g = self.p[..., c]
        i1, j1 = np.minimum(i + 1, len(self.xs) - 1), np.minimum(j + 1, len(self.ys) - 1)
        return (1 - v) * ((1 - u) * g[j, i] + u * g[j, i1]) + v * ((1 - u) * g[j1, i] + u * g[j1, i1])


@dataclass(frozen=True)
class Parallax:
    """One family's frame parallax (module docstring): the family's ``axis`` (0: mullions), slope ``k``,
    and per side of the camera's foot (P < 0, P > 0) whether the bars' near edges are displaced like their
    far edges; bars narrower than ``min_width_px`` (cut by the border) are left as found."""

    axis: int
    k: float = 0.0
    near_displaced: tuple[bool, bool] = (False, False)
    min_width_px: float = 0.0
    slopes: tuple[float, float] = (float("nan"), float("nan"))
    """The width's growth with P on either side (NaN: not measured there)."""
    unjudged: bool = False
    """A fit through as many bars as unknowns, its slope within range: exact, so without a residual to
    judge it by; such slopes count where those of the building's views agree (``agreeing``)."""

    def with_slope(self, k: float) -> Parallax:
        """This family's parallax with the slope ``k`` (the building's frame depth, ``slope_of``): a side
        whose widths grow by less than half of it has its near edges displaced."""
        near = tuple(bool(np.isfinite(g) and g < 0.5 * k) for g in self.slopes)
        return dataclasses.replace(self, k=k, near_displaced=near)  # type: ignore[arg-type]


def _coord(field: ParallaxField, axis: int, line: EdgeLine) -> float:
    """P at the middle of an edge line of family ``axis``."""
    return float(field.along(axis, np.array([line.a]), np.array([line.mid]))[0])


def fit_parallax(bars: _Bars, field: ParallaxField, axis: int, min_bars: int, max_slope: float) -> Parallax:
    """The frame parallax of one family (module docstring), from the bars' apparent widths.

    Fits w_i = B + k_low s_low,i + k_high s_high,i, s the extent (px of P) of a bar beyond the camera's
    foot on either side (at glass level: a second fit divides by 1 + k), leaving out bars narrower than
    half the median (cut by the border). k is the larger side slope. A side whose slope is under half of k
    has its bars' near edges displaced as well (a shaded side face looks like the glass, so the edge found
    is the front face's). No correction (k = 0) with fewer than ``min_bars`` usable bars, k outside
    (0, ``max_slope``], or k less than ``PARALLAX_MIN_T`` standard errors above 0; a fit through as many
    bars as unknowns has no residual to judge it by: it is ``unjudged``, and corrects nothing on its own."""
    lows = np.array([e[0].a for e in bars.edges])
    highs = np.array([e[1].a for e in bars.edges])
    p_low = np.array([_coord(field, axis, e[0]) for e in bars.edges])
    p_high = np.array([_coord(field, axis, e[1]) for e in bars.edges])
    w = highs - lows
    min_width = 0.5 * float(np.median(w))
    ok = w >= min_width
    s = np.stack([np.maximum(-p_low, 0.0), np.maximum(p_high, 0.0)], axis=1)[ok]  # [n, 2]
    sides = [j for j in (0, 1) if np.ptp(s[:, j]) >= 1.0] if ok.sum() >= min_bars else []
    if not sides:
        return Parallax(axis, min_width_px=min_width)
    k = 0.0
    for _ in range(2):
        A = np.concatenate([np.ones((len(s), 1)), s[:, sides] / (1.0 + k)], axis=1)
        coef = np.linalg.lstsq(A, w[ok], rcond=None)[0]
        slopes = dict(zip(sides, coef[1:], strict=True))
        k = float(max(slopes.values()))
    measured = tuple(float(slopes.get(j, np.nan)) for j in (0, 1))
    if not 0.0 < k <= max_slope:
        return Parallax(axis, min_width_px=min_width, slopes=measured)  # type: ignore[arg-type]
    error = _slope_error(A, w[ok] - A @ coef, sides, slopes)
    if not np.isfinite(error):
        return Parallax(axis, min_width_px=min_width, slopes=measured, unjudged=True)  # type: ignore[arg-type]
    if k < PARALLAX_MIN_T * error:
        return Parallax(axis, min_width_px=min_width, slopes=measured)  # type: ignore[arg-type]
    return Parallax(axis, min_width_px=min_width, slopes=measured).with_slope(k)  # type: ignore[arg-type]


def _slope_error(A: np.ndarray, residual: np.ndarray, sides: list[int], slopes: dict[int, float]) -> float:
    """The standard error of the larger side slope of the least-squares fit ``A`` with ``residual``
    (inf where the fit has no residual to judge it by: as many bars as unknowns)."""
    dof = len(residual) - A.shape[1]
    if dof < 1:
        return np.inf
    j = 1 + sides.index(max(slopes, key=lambda side: slopes[side]))
    variance = float(residual @ residual) / dof * np.linalg.pinv(A.T @ A)[j, j]
    return float(np.sqrt(max(variance, 0.0)))


def slope_of(frame_depth_m: float, distance_m: float) -> float:
    """The parallax slope k = d / (D - d) of frames ``frame_depth_m`` proud of a surface ``distance_m``
    from the camera (0 where that is not finite and positive)."""
    k = frame_depth_m / (distance_m - frame_depth_m)
    return float(k) if np.isfinite(k) and k > 0.0 else 0.0


def _unparallax(line: EdgeLine, field: ParallaxField, axis: int, k: float) -> EdgeLine:
    """A front-face edge moved to where the glass-level edge is seen: by k P / (1 + k) at every point
    along it where it was found (P changes along a transom of a curved facade, fastest toward the
    silhouette), refitted as a straight line weighted by the edge's strength."""
    t = np.arange(len(line.strength)) + 0.5  # the rows (columns) the edge was fitted over, by strength
    w = np.asarray(line.strength, float)
    if not (w > 0).sum() >= 2:
        t, w = np.array([line.mid - 0.5, line.mid + 0.5]), np.ones(2)
    pos = line.at(t)
    moved = pos - k / (1.0 + k) * field.along(axis, pos, t)
    A = np.stack([np.ones_like(t), t - line.mid], axis=1) * w[:, None]
    a, b = np.linalg.lstsq(A, moved * w, rcond=None)[0]
    return dataclasses.replace(line, a=float(a), b=float(b))


def correct_parallax(bars: _Bars, par: Parallax, field: ParallaxField) -> _Bars:
    """Bars whose front-face edges are moved by the parallax to where the glass meets the frame: each
    bar's edge on the far side from the camera's foot, both edges of a bar over it, and the near edges
    on a side where they are displaced too (``par.near_displaced``)."""
    if par.k <= 0.0:
        return bars
    k, axis = par.k, par.axis
    edges = []
    for low, high in bars.edges:
        if high.a - low.a < par.min_width_px:
            edges.append((low, high))
            continue
        p_low, p_high = _coord(field, axis, low), _coord(field, axis, high)
        below, above = p_high <= 0.0, p_low >= 0.0  # the bar lies wholly on the low / high side
        new_low, new_high = low, high
        if p_low < 0.0 or (above and par.near_displaced[1]):
            new_low = _unparallax(low, field, axis, k)
        if p_high > 0.0 or (below and par.near_displaced[0]):
            new_high = _unparallax(high, field, axis, k)
        edges.append((new_low, new_high))
    return _Bars(edges, bars.fit)


def find_bars(
    image: np.ndarray,
    params: SegmentParams,
    sizes: tuple[PixelSizes, PixelSizes],
    valid: np.ndarray | None = None,
    parallax: ParallaxField | None = None,
    planar: bool = True,
) -> tuple[_Bars | None, _Bars | None, dict, dict[str, Parallax], tuple[Gradients, Gradients]]:
    """Mullions and transoms of an RGB image [H, W, 3]: MAP passes for the transoms over the whole image,
    then for each family over the other's extent only (on a ``planar`` surface the transoms must have the
    mullions' colour, ``frame_colour_scale``), then sub-pixel edges, with their frames' parallax fitted in the
    image's ``parallax`` field ({"x": mullions, "y": transoms}; none without a field), not yet corrected,
    and the two families' gradients. ``sizes``: the grid model's sizes of the mullions and the transoms."""
    sizes_v, sizes_h = sizes
    H, W = image.shape[:2]
    # numpy and OpenCV let go of the GIL: threads share a view's work among the cores. LSD runs beside the
    # first transom pass's gradient evidence (which does not need its segments) and the making of what the
    # later passes take (the mullions' lattice, each family's pitch hypotheses); each pass's evidence is
    # shared out (``_family``), and the two families' edges are fitted side by side
    with ThreadPoolExecutor(max_workers=usable_cores()) as pool:
        lsd = pool.submit(
            lambda: group_segments(
                detect_segments(image, params.upsample, MIN_SEGMENT_PX),
                ORIENTATION_TOLERANCE_DEG,
                ORIENTATION_SEARCH_DEG,
            )
        )
        gv, gh = Gradients.of(image, 0, valid), Gradients.of(image, 1, valid)
        ahead = [pool.submit(gv.prepare)]
        ahead += [pool.submit(pitch_hypotheses, g.size, z) for g, z in ((gh, sizes_h), (gv, sizes_v))]
        # a mullion pass over the whole height would serve nothing: the first transom pass takes the whole
        # width
        h = _family(gh, lambda: lsd.result().segments[lsd.result().horizontal], 1, slice(0, W), params,
                    sizes_h, pool=pool)
        fam = lsd.result()
        vseg, hseg = fam.segments[fam.vertical], fam.segments[fam.horizontal]
        for done in ahead:
            done.result()
        v = _family(gv, vseg, 0, _span(h, H), params, sizes_v, pool=pool)
        # frames are one material: the transoms must have the mullions' colour. Mullions are the reference:
        # they run the facade's full height, while the long straight lines that reflections bring (horizon,
        # roofs, kerbs) and the shelves seen through an empty frame cell are horizontal
        colour_h = None
        if v is not None and params.grid.frame_colour_scale > 0 and planar:
            colour_h = bar_colour(gv, v, _span(h, H))
        h = _family(gh, hseg, 1, _span(v, W), params, sizes_h, colour_h, pool)
        metrics = {
            "n_segments": len(fam.segments),
            "n_vertical_segments": len(vseg),
            "n_horizontal_segments": len(hseg),
            "vertical_angle_deg": float(np.degrees(fam.angle_vertical)),
            "horizontal_angle_deg": float(np.degrees(fam.angle_horizontal)),
            "mullions_found": v is not None,
            "transoms_found": h is not None,
        }
        if v is None or h is None:
            return None, None, metrics, {}, (gv, gh)
        edges_h = pool.submit(_edges, h, gh, _span(v, W), params)
        bars_v = _edges(v, gv, _span(h, H), params)
        bars_h = edges_h.result()
    metrics.update(
        {"pitch_x_px": v.pitch, "pitch_y_px": h.pitch, "map_score_x": v.score, "map_score_y": h.score}
    )
    fits = {}
    if parallax is not None and params.parallax_max_slope > 0:
        fits = {
            name: fit_parallax(bars, parallax, axis, PARALLAX_MIN_BARS, params.parallax_max_slope)
            for name, bars, axis in (("x", bars_v, 0), ("y", bars_h, 1))
        }
    return bars_v, bars_h, metrics, fits, (gv, gh)


def _border(pos: float, length: int) -> EdgeLine:
    """The image border at ``pos`` as an edge line (no strength)."""
    return EdgeLine(float(pos), 0.0, 0.0, np.zeros(length))


def intersect(v: EdgeLine, h: EdgeLine) -> np.ndarray:
    """Intersection [2] (x, y) of a vertical edge x = a + b (y - mid) and a horizontal y = a + b (x - mid)."""
    x = (v.a + v.b * (h.a - h.b * h.mid - v.mid)) / (1.0 - v.b * h.b)
    return np.array([x, h.a + h.b * (x - h.mid)])


def _mean(a: np.ndarray, lo: float, hi: float, seen: np.ndarray | None) -> float:
    """Mean of a [L] over the rows [lo, hi) that show the view (``seen``; all if None)."""
    i0, i1 = int(max(0, np.ceil(lo))), int(max(0, np.floor(hi)))
    seg = a[i0:i1] if seen is None else a[i0:i1][seen[i0:i1]]
    return float(seg.mean()) if len(seg) else 0.0


def _bar_continues(bar: tuple[EdgeLine, EdgeLine], lo: float, hi: float,
                   inside: tuple[float, float]) -> tuple[float, float]:
    """How one bar of the other family continues over [lo, hi) along it: (the fraction of the strip's part
    that shows the view where its frame colour is present on its centre line, NaN where unknown; the
    larger ratio of its two edges' mean strength there to their mean strength over ``inside``)."""
    presence = np.nan
    if bar[0].present is not None:
        seg = bar[0].present[int(max(0, np.ceil(lo))) : int(max(0, np.floor(hi)))]
        seg = seg[~np.isnan(seg)]
        if len(seg):
            presence = float(seg.mean())
    seen = None if bar[0].present is None else ~np.isnan(bar[0].present)
    ratio = 0.0
    for line in bar:
        ref = _mean(line.strength, *inside, seen)
        ratio = max(ratio, _mean(line.strength, lo, hi, seen) / ref if ref > 0 else 0.0)
    return presence, ratio


def _continues(other: _Bars, lo: float, hi: float, inside: tuple[float, float], support: float,
               params: SegmentParams) -> frozenset[int] | None:
    """Which bars of ``other`` continue over [lo, hi) along them: None for all of them (the facade goes on
    across the whole strip), else the indices of those that do on their own (an empty set: the facade ends).

    Only where the facade surface is there (``support``: the fraction of the strip where the coarse mesh
    lies on the fitted surface, 1 without a mesh) over at least half of the strip: that keeps out the ground
    or paving beyond the facade's end, which may have the frames' colour. There the bars continue where their
    frame colour is present on the centre line (``frame_presence``) over at least ``continuation_presence``
    of the strip's part that shows the view, in the median over the bars, or where their edges keep
    ``continuation_ratio`` of their strength over ``inside``, in the median over the bars (either edge: an
    outer frame shows only its glass side wherever the background beside it changes colour). Colour
    survives what takes the edges away: a specular highlight on the glass beside a bar, the blur of a far,
    upsampled part of an oblique rectified photo. Where the median fails, a bar that passes either test on
    its own still continues: a partly installed or stepped facade ends over part of a strip only (an empty
    unit, a unit set off its neighbours' line), and the openings beside such a bar go on."""
    if support < 0.5:
        return frozenset()
    found = [_bar_continues(e, lo, hi, inside) for e in other.edges]
    presence = [p for p, _ in found if not np.isnan(p)]
    if presence and float(np.median(presence)) >= params.continuation_presence:
        return None
    if found and float(np.median([r for _, r in found])) >= params.continuation_ratio:
        return None
    return frozenset(
        i for i, (p, r) in enumerate(found)
        if (not np.isnan(p) and p >= params.continuation_presence) or r >= params.continuation_ratio
    )


def _strip_support(support: np.ndarray | None, axis: int, lo: float, hi: float,
                   across: tuple[float, float]) -> float:
    """Mean of ``support`` [H, W] over a border strip: [lo, hi) along ``axis`` (0: x), ``across`` on the
    other axis (the other family's outer bars); 1 without a support mask."""
    if support is None:
        return 1.0
    a0, a1 = int(max(0, np.floor(lo))), int(max(0, np.ceil(hi)))
    b0, b1 = int(max(0, np.floor(across[0]))), int(max(0, np.ceil(across[1])))
    block = support[b0:b1, a0:a1] if axis == 0 else support[a0:a1, b0:b1]
    return float(block.mean()) if block.size else 0.0


@dataclass(frozen=True)
class Opening:
    """One opening across a family's bars: its low and high edge lines, the indices of the bars bounding
    it (None: the image border), and for a strip cut by the border the bars of the other family that
    continue into it (None: all of them)."""

    low: EdgeLine
    high: EdgeLine
    bounds: tuple[int | None, int | None]
    cut: bool = False
    continuing: frozenset[int] | None = None

    def admits(self, bounds: tuple[int | None, int | None]) -> bool:
        """Does the opening of the other family bounded by the bars ``bounds`` go on into this one?"""
        return self.continuing is None or all(b is None or b in self.continuing for b in bounds)


def openings(
    bars: _Bars, other: _Bars, size: int, length: int, params: SegmentParams, min_partial_px: float,
    axis: int, support: np.ndarray | None = None,
) -> list[Opening]:
    """Openings across one family's bars (``axis`` 0: mullions), low to high."""
    e = bars.edges
    inside = (bars.fit.centres[0], bars.fit.centres[-1])
    across = (other.fit.centres[0], other.fit.centres[-1])
    out = []
    lo, top = e[0][0].a, e[-1][1].a
    if lo >= min_partial_px:
        going = _continues(other, 0, lo, inside, _strip_support(support, axis, 0, lo, across), params)
        if going is None or going:
            out.append(Opening(_border(0, length), e[0][0], (None, 0), True, going))
    out += [Opening(e[k][1], e[k + 1][0], (k, k + 1)) for k in range(len(e) - 1)]
    if size - top >= min_partial_px:
        going = _continues(other, top, size, inside, _strip_support(support, axis, top, size, across), params)
        if going is None or going:
            out.append(Opening(e[-1][1], _border(size, length), (len(e) - 1, None), True, going))
    return out


def _supported(line: EdgeLine, lo: float, hi: float) -> float:
    """Fraction of [lo, hi] (along the line, 1 px kept clear of the corners) where its frame bar is present
    or the edge itself (the bar's side facing the panel) is found at half its median strength or more: an
    object in front hides both, while a bar that shows its shaded side face beside an empty unit keeps the
    sharp edge where it meets the glass; 1 for the image border."""
    if line.present is None:
        return 1.0
    i0, i1 = int(max(0, np.ceil(lo + 1))), int(max(0, np.floor(hi - 1)))
    present = line.present[i0:i1]
    found = line.strength[i0:i1]
    seen = ~np.isnan(present)
    if not seen.any():
        return 1.0
    ref = np.median(line.strength[line.strength > 0]) if (line.strength > 0).any() else np.inf
    return float(((present[seen] > 0) | (found[seen] >= 0.5 * ref)).mean())


def build_panels(bars_v: _Bars, bars_h: _Bars, width: int, height: int, params: SegmentParams,
                 min_partial_px: float, support: np.ndarray | None = None) -> list[Panel]:
    """Panels of every opening of the grid (module docstring), rows counted from the bottom; ``support``
    [H, W] marks where the facade surface is (border strips without it hold no partial panel)."""
    cols = openings(bars_v, bars_h, width, height, params, min_partial_px, 0, support)
    rows = openings(bars_h, bars_v, height, width, params, min_partial_px, 1, support)  # top to bottom
    panels = []
    for i, row in enumerate(rows):
        top, bottom, cut_r = row.low, row.high, row.cut
        for j, col in enumerate(cols):
            left, right, cut_c = col.low, col.high, col.cut
            if not (row.admits(col.bounds) and col.admits(row.bounds)):
                continue
            c = np.array(
                [
                    intersect(left, bottom),
                    intersect(right, bottom),
                    intersect(right, top),
                    intersect(left, top),
                ]
            )
            x0, x1, y0, y1 = c[:, 0].min(), c[:, 0].max(), c[:, 1].min(), c[:, 1].max()
            if x1 - x0 < 1 or y1 - y0 < 1:
                continue
            support = min(
                _supported(left, y0, y1),
                _supported(right, y0, y1),
                _supported(top, x0, x1),
                _supported(bottom, x0, x1),
            )
            reason = "border" if cut_r or cut_c else ("occluded" if support < MIN_EDGE_SUPPORT else "")
            panels.append(Panel(len(rows) - 1 - i, j, c, reason == "", reason))
    return panels


def working_scale(params: SegmentParams, metres_per_px: float) -> float:
    """Ratio (<= 1) of the working image's size to the given image's (``work_bar_px``)."""
    return min(1.0, metres_per_px * params.work_bar_px / params.grid.min_bar_m)


@dataclass(frozen=True, eq=False)
class FrameBars:
    """The frame bars of one image at the working scale (``find_frames``), their parallax fitted but not
    yet corrected: what ``segment_frames`` makes the panels from."""

    bars_v: _Bars | None
    bars_h: _Bars | None
    fits: dict[str, Parallax]
    parallax: ParallaxField | None
    size: tuple[int, int]
    scale: tuple[float, float]
    metres_per_px: float
    support: np.ndarray | None
    metrics: dict
    grads: tuple[Gradients, Gradients]

    def bar_widths_m(self) -> dict[str, list[float]]:
        """The widths (m) of the bars found, per family ("x": mullions, "y": transoms)."""
        return {name: [(hi.a - lo.a) * self.metres_per_px for lo, hi in bars.edges]
                for name, bars in (("x", self.bars_v), ("y", self.bars_h)) if bars is not None}

    def pitches_m(self) -> dict[str, float]:
        """The pitch (m) of the grid found, per family ("x": across the mullions, "y": the transoms); none
        where no grid was found."""
        return {name: self.metrics[f"pitch_{name}_px"] * self.metres_per_px for name in ("x", "y")
                if f"pitch_{name}_px" in self.metrics}

    def frame_depths_m(self, unjudged: bool = False) -> dict[str, float]:
        """The frame depth d = k D / (1 + k) (m) each family's own parallax fit gives ("x": the mullions,
        "y": the transoms), where it has one and the camera's distance D to the surface is known; with
        ``unjudged``, the depths of the exact fits instead (``Parallax.unjudged``, the larger side slope)."""
        D = np.nan if self.parallax is None else self.parallax.distance_m
        k = {n: float(np.nanmax(f.slopes)) if unjudged else f.k for n, f in self.fits.items()
             if f.unjudged == unjudged and (unjudged or f.k > 0.0)}
        return {n: v / (1.0 + v) * D for n, v in k.items() if np.isfinite(D)}


def agreeing(depths: list[float]) -> bool:
    """Do measurements without error bars of their own (``Parallax.unjudged``) agree on a depth above 0:
    two or more, their mean above 0 by the two-sided 95 % quantile of Student's t times its standard error
    (frames seen alike in every view give one depth; the scatter of a few bars in real photos does not)."""
    # imported here: only a building with such fits needs it. scipy.special's quantile of Student's t is the
    # one scipy.stats computes, at half of scipy.stats' import time (about a second)
    from scipy.special import stdtrit

    n = len(depths)
    if n < 2:
        return False
    error = float(np.std(depths, ddof=1)) / np.sqrt(n)
    return float(np.mean(depths)) > (stdtrit(n - 1, 0.975) * error if error > 0 else 0.0)


def find_frames(
    image: np.ndarray,
    params: SegmentParams,
    metres_per_px: float,
    valid: np.ndarray | None = None,
    parallax: ParallaxField | None = None,
    support: np.ndarray | None = None,
    planar: bool = True,
    pitch_m: dict[str, tuple[float, float]] | None = None,
) -> FrameBars:
    """The frame bars of an RGB image [H, W, 3] of a facade at ``metres_per_px`` (a rectified frontal view),
    found at the working scale (``work_bar_px``); ``support`` [H, W] marks where the facade surface is
    (``rectification.facade_support``; None: all); ``valid`` [H, W] marks the pixels that show the view (a
    rectified image has none outside the original); ``parallax`` is the image's parallax coordinate, in
    which the frames' parallax is fitted (None: not); ``planar``: the surface is a plane (``find_bars``);
    ``pitch_m`` narrows the pitches (m) sought across the mullions ("x") or the transoms ("y") to a range
    (the building's grid, ``building.pitch_range_m``; the grid model's range where None)."""
    H, W = image.shape[:2]
    q = working_scale(params, metres_per_px)
    Ww, Hw = max(1, int(round(W * q))), max(1, int(round(H * q)))
    qx, qy = Ww / W, Hw / H
    if (Ww, Hw) != (W, H):
        image = cv2.resize(image, (Ww, Hw), interpolation=cv2.INTER_AREA)
        if valid is not None:  # a working pixel shows the view only where all of its source pixels do
            valid = cv2.resize(valid.astype(np.float32), (Ww, Hw), interpolation=cv2.INTER_AREA) > 0.999
        if support is not None:
            support = cv2.resize(support.astype(np.uint8), (Ww, Hw), interpolation=cv2.INTER_NEAREST) > 0
        if parallax is not None:
            parallax = parallax.scaled(qx, qy)
    m = metres_per_px / np.sqrt(qx * qy)
    sizes = PixelSizes.of(params.grid, m)
    family_sizes = tuple(
        sizes if name not in (pitch_m or {}) else dataclasses.replace(
            sizes, min_pitch=max(sizes.min_pitch, pitch_m[name][0] / m),
            max_pitch=min(sizes.max_pitch, pitch_m[name][1] / m))
        for name in ("x", "y")
    )
    image = normalise_exposure(image, valid)
    bars_v, bars_h, metrics, fits, grads = find_bars(image, params, family_sizes, valid, parallax, planar)
    metrics.update({"working_scale": round(float(np.sqrt(qx * qy)), 4), "working_metres_per_px": m})
    return FrameBars(bars_v, bars_h, fits, parallax, (Ww, Hw), (qx, qy), m, support, metrics, grads)


def widen_narrow_bars(bars: _Bars, grad: Gradients, span: slice, width_px: float,
                      params: SegmentParams) -> tuple[_Bars, int]:
    """``bars`` with every bar narrower than half of ``width_px`` (the building's width of the family) and
    a whole width away from the image border found again at that width, and how many were: a thin line
    that keeps one edge of the bar (its shaded side face, a reflection meeting it) can take the grid's
    place of a frame whose face has little contrast against the glass beside it. Of the four bars of
    ``width_px`` that share an edge with the thin one, the one whose weaker edge is strongest is kept (the
    geometric mean of its edges' strengths, as the bar evidence of ``grid``). Only where the view shows a
    bar of the family at least half that wide: a part whose frames are all thinner than the building's
    (another style) keeps them."""
    size = grad.d.shape[1] + 1
    if not any(high.a - low.a >= 0.5 * width_px for low, high in bars.edges):
        return bars, 0
    edges, n = [], 0
    for low, high in bars.edges:
        if high.a - low.a >= 0.5 * width_px or low.a < width_px or high.a > size - width_px:
            edges.append((low, high))
            continue
        best, score = (low, high), 0.0
        for c in (low.a - 0.5 * width_px, low.a + 0.5 * width_px, high.a - 0.5 * width_px,
                  high.a + 0.5 * width_px):
            e = bar_edges(grad, c, width_px, span, EDGE_SEARCH_PX)
            if e is None or e[1].a - e[0].a < 0.5 * width_px:
                continue
            sc = float(np.sqrt(e[0].strength.mean() * e[1].strength.mean()))
            if sc > score:
                best, score = e, sc
        if best[0] is not low:
            present = frame_presence(grad, best[0], best[1], span, params.frame_colour_tol)
            best = tuple(dataclasses.replace(line, present=present) for line in best)
            n += 1
        edges.append(best)
    return _Bars(edges, bars.fit), n


def segment_frames(
    found: FrameBars,
    params: SegmentParams,
    frame_depth_m: dict[str, float] | None = None,
    bar_width_m: dict[str, float] | None = None,
) -> Segmentation:
    """The panels between the frame bars ``found`` (``find_frames``), corners in the given image's pixels.
    The bars are corrected for their parallax: a family with a depth in ``frame_depth_m`` ("x": mullions,
    "y": transoms; m proud of the glass, the building's, measured over all its views: a view's own widths
    may not show it) with the slope of that depth where the camera's distance to the surface is known,
    else with its own fit. A family with a width in ``bar_width_m`` (m, the building's) has its bars
    narrower than half of it found again at it (``widen_narrow_bars``)."""
    metrics = dict(found.metrics)
    bars_v, bars_h, m = found.bars_v, found.bars_h, found.metres_per_px
    if bars_v is None or bars_h is None:
        g = params.grid
        missing = " nor ".join(
            name for name, key in (("vertical (mullions)", "mullions_found"),
                                   ("horizontal (transoms)", "transoms_found"))
            if not metrics.get(key)
        )  # fmt: skip
        return Segmentation(False, [], metrics, (
            f"no regular {missing} frame bars {g.min_bar_m:g}-{g.max_bar_m:g} m wide at a pitch of "
            f"{g.min_pitch_m:g}-{g.max_pitch_m:g} m (the image at {1000 * m:.3g} mm per working pixel)"
        ))  # fmt: skip
    (Ww, Hw), (qx, qy) = found.size, found.scale
    for name, width in (bar_width_m or {}).items():
        if name == "x":
            bars_v, n = widen_narrow_bars(bars_v, found.grads[0], _span(bars_h.fit, Hw), width / m, params)
        else:
            bars_h, n = widen_narrow_bars(bars_h, found.grads[1], _span(bars_v.fit, Ww), width / m, params)
        metrics[f"bars_widened_{name}"] = n
    fits = dict(found.fits)
    for name, depth in (frame_depth_m or {}).items():
        k = 0.0 if found.parallax is None else slope_of(depth, found.parallax.distance_m)
        if name in fits and 0.0 < k <= params.parallax_max_slope:
            fits[name] = fits[name].with_slope(k)
    metrics.update({f"parallax_slope_{name}": round(f.k, 5) for name, f in fits.items()})
    if fits:
        bars_v = correct_parallax(bars_v, fits["x"], found.parallax)
        bars_h = correct_parallax(bars_h, fits["y"], found.parallax)
    panels = build_panels(bars_v, bars_h, Ww, Hw, params, params.min_partial_m / m, found.support)
    panels = [dataclasses.replace(p, corners=p.corners / [qx, qy]) for p in panels]
    metrics.update({"n_mullions": len(bars_v.edges), "n_transoms": len(bars_h.edges)})
    for k in ("pitch_x_px", "pitch_y_px"):
        if k in metrics:
            metrics[k.replace("_px", "_m")] = metrics[k] * m
    why = "" if panels else "frame bars found, but no opening between them looks like a pane"
    return Segmentation(bool(panels), panels, metrics, why)


def segment_image(
    image: np.ndarray,
    params: SegmentParams,
    metres_per_px: float,
    valid: np.ndarray | None = None,
    parallax: ParallaxField | None = None,
    support: np.ndarray | None = None,
    frame_depth_m: dict[str, float] | None = None,
    bar_width_m: dict[str, float] | None = None,
    planar: bool = True,
) -> Segmentation:
    """The panels of one image (``find_frames`` then ``segment_frames``, same arguments)."""
    return segment_frames(find_frames(image, params, metres_per_px, valid, parallax, support, planar), params,
                          frame_depth_m, bar_width_m)


#: a point further than this (px) outside a quad's bounding box is outside the quad, whatever the rounding of
#: its edge equations (an error of some 1e-10 px at image coordinates): only the points within it are tested
QUAD_BOX_MARGIN_PX = 1e-3


def inside_quads(quads: list[np.ndarray], xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Index [...] of the convex quad (corners [4, 2] each) containing each point (xs, ys), -1 for none.

    Half-open (module docstring): a point on an edge is inside when the point moved by an infinitesimal
    step along (+1, +eps) (right, then down) is; the step is taken exactly by a tie-break on the edge
    equations, not by moving the points."""
    out = np.full(np.shape(xs), -1, dtype=np.int32)
    flat = out.reshape(-1)
    xs_all = np.asarray(xs, dtype=np.float64).reshape(-1)
    ys_all = np.asarray(ys, dtype=np.float64).reshape(-1)
    for k, q in enumerate(quads):
        q = np.asarray(q, dtype=np.float64)
        if _signed_area(q) < 0:  # orient so that the inner side of every edge has cross > 0
            q = q[::-1]
        lo, hi = q.min(axis=0) - QUAD_BOX_MARGIN_PX, q.max(axis=0) + QUAD_BOX_MARGIN_PX
        near = np.flatnonzero((xs_all >= lo[0]) & (xs_all <= hi[0]) & (ys_all >= lo[1]) & (ys_all <= hi[1]))
        xs_k, ys_k = xs_all[near], ys_all[near]
        inside = np.ones(len(near), bool)
        for i in range(4):
            (x0, y0), (x1, y1) = q[i], q[(i + 1) % 4]
            ex, ey = x1 - x0, y1 - y0
            cross = ex * (ys_k - y0) - ey * (xs_k - x0)  # > 0: on the inner side of this edge
            # d(cross)/d(step): along +x it is -ey, then along +y it is ex; the first non-zero decides a tie
            tie = np.where(ey != 0, -ey > 0, ex > 0)
            inside &= (cross > 0) | ((cross == 0) & tie)
        hit = near[inside]
        flat[hit[flat[hit] < 0]] = k
    return out


def _signed_area(q: np.ndarray) -> float:
    """Shoelace area of a polygon [n, 2]; > 0 when its vertices turn with the edge equations above
    (cross > 0 on the inner side)."""
    x, y = q[:, 0], q[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
