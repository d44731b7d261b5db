"""Parallax of proud frames: frames stand d in front of the glass, so the front face of a bar is seen shifted
away from the camera along the surface by d tan(a), a the angle of the line of sight from the surface normal
(in the plane of the normal and the direction across the bar); its front face hides a strip of the glass
beyond it of that width, while on its side towards the camera the bar's side face shows. In pixels the shift
is k' P, with P the view's parallax coordinate (``ParallaxField``: D tan(a) / m, D the camera's distance to
the surface, m the scale) and k' = d / (D + d) = k / (1 + k), k = d / D: the surface is the one fitted to the
coarse points, which photogrammetry finds on the frames' front rather than on the glass (a reflection gives no
points of the glass's own), so the glass lies d behind it, D + d from the camera (a surface taken for the
glass, k = d / (D - d), turns a view's slope into a depth too small by about d / D, and a depth into a slope
too large by as much). Seen straight on to a plane, P = u - c, the distance from the camera's foot c; across
an unrolled cylinder P grows faster than the distance (the surface turns away from the camera), and for the
horizontal bars it changes along the bar. A bar's apparent width thus grows as w = B + k P, with P at its far
(front-face) edge; on a side of c where the side faces are shaded like the glass, the near edge found is the
front face's as well, and the width does not grow there. k and those sides are fitted per family and view
(``fit_parallax``); where both sides' side faces are shaded the widths show no k at all, so a rectified view
takes k from the building's frame depth per family (the median of the views' fits, ``segment_frames``). The
front-face edges are moved back by k P / (1 + k) along their length, where the glass meets the frame: corners
are the glass panel's corners, and masks are the panels' quads, hidden strips included
(``parallax_max_slope = 0`` keeps the visible glass instead)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from facade_pipeline.segmentation.edges import Bars, EdgeLine

#: a family with fewer whole frame bars than this is not corrected for parallax: three points are the
#: fewest that tell a slope from one bar's error
PARALLAX_MIN_BARS = 3
#: a found bar's faces are told by its width (``faces_found``) only where the faces' widths it may be
#: differ by this much (px): the widths of one view's bars, faces alike, scatter by about half a pixel
SIDE_FACE_MIN_PX = 1.0
#: a view's parallax slope counts where it stands this many standard errors above 0 (from the fit's own
#: residual): a fit through few bars measured in a real photo scatters by more than the slope of frames
#: nearly flush with the glass, and a slope from noise would shift every corrected edge
PARALLAX_MIN_T = 3.0


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

    def with_slope(self, k: float, sides_m: tuple[float, float] | None = None) -> Parallax:
        """This family's parallax with the slope ``k`` (the building's frame depth, ``slope_of``): a side
        whose widths grow by less than half of it has its near edges displaced. Where this fit measured
        neither side, the building's sides' depths ``sides_m`` (m, ``pooled_depth_m``) are taken instead,
        as slopes in proportion to the larger."""
        slopes = self.slopes
        if sides_m is not None and not np.isfinite(slopes).any() and np.nanmax(sides_m) > 0.0:
            slopes = tuple(k * s / np.nanmax(sides_m) for s in sides_m)  # type: ignore[assignment]
        near = tuple(bool(np.isfinite(g) and g < 0.5 * k) for g in slopes)
        return dataclasses.replace(self, k=k, near_displaced=near, slopes=slopes)  # type: ignore[arg-type]


def _coord(field: ParallaxField, axis: int, line: EdgeLine) -> float:
    """P at the middle of an edge line of family ``axis``."""
    return float(field.along(axis, np.array([line.a]), np.array([line.mid]))[0])


def fit_parallax(bars: Bars, field: ParallaxField, axis: int, min_bars: int, max_slope: float) -> Parallax:
    """The frame parallax of one family (module docstring), from the bars' apparent widths.

    Fits w_i = B + k_low s_low,i + k_high s_high,i, s the extent (px of P) of a bar beyond the camera's
    foot on either side (at glass level: a second fit divides by 1 + k), leaving out bars narrower than
    half the median (cut by the border). k is the larger side slope. A side whose slope is under half of k
    has its bars' near edges displaced as well (a shaded side face looks like the glass, so the edge found
    is the front face's). No correction (k = 0) with fewer than ``min_bars`` usable bars, k outside
    (0, ``max_slope``], or k less than ``PARALLAX_MIN_T`` standard errors above 0; a fit through as many
    bars as unknowns has no residual to judge it by: it is ``unjudged``, and corrects nothing on its own.
    Such a fit with k outside that range measures neither side (its slopes NaN): it passes through every
    width, so a side's bars found with and without their side faces (a slope below 0) say nothing of the
    side's other bars."""
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
        if len(s) <= A.shape[1]:  # exact
            measured = (np.nan, np.nan)
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


def widest_side_face(field: ParallaxField, axis: int, size: tuple[int, int], slope: float) -> float:
    """The widest side face (px) a bar of family ``axis`` (0: mullions) shows beside its front face in an
    image of ``size`` (W, H) whose parallax coordinate is ``field``: k P / (1 + k) at the frames' slope k
    (``slope``) and the largest |P| across the family in the image. A bar seen obliquely is found as its
    front and side faces together (the width ``fit_parallax`` reads k from); a grid that does not seek that
    width finds its front face alone, and the growth is lost. P is bilinear between the field's samples, so
    its largest |P| over the image lies at a sample inside it or on its border."""
    W, H = size
    xs = np.unique(np.clip(np.concatenate([[0.0, W], field.xs]), 0.0, W))
    ys = np.unique(np.clip(np.concatenate([[0.0, H], field.ys]), 0.0, H))
    gx, gy = np.meshgrid(xs, ys)
    pos, t = (gx, gy) if axis == 0 else (gy, gx)
    p = float(np.abs(field.along(axis, pos.ravel(), t.ravel())).max())
    return slope / (1.0 + slope) * p


def slope_of(frame_depth_m: float, distance_m: float) -> float:
    """The parallax slope k = d / D of frames ``frame_depth_m`` proud of the glass, their front on the
    surface ``distance_m`` from the camera (module docstring; 0 where that is not finite and positive)."""
    k = frame_depth_m / distance_m
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


def side_face(field: ParallaxField, axis: int, low: EdgeLine, high: EdgeLine,
              k: float) -> tuple[int, float, float] | None:
    """Of a bar (edges ``low``, ``high`` of family ``axis``) wholly on one side of the camera's foot: which
    edge is its near one (0: low, 1: high), the width (px) its side face shows beside it, k P / (1 + k) at
    that edge, and how much wider its front face is seen than at the foot, k / (1 + k) times the growth of
    P across it (a tight cylinder's P grows fast toward its silhouette); None for a bar over the foot (it
    shows no side face)."""
    p_low, p_high = _coord(field, axis, low), _coord(field, axis, high)
    f = k / (1.0 + k)
    if p_high <= 0.0:
        return 1, -f * p_high, f * (p_high - p_low)
    if p_low >= 0.0:
        return 0, f * p_low, f * (p_high - p_low)
    return None


def faces_found(width_px: float, seen: tuple[int, float, float], front_px: float) -> str:
    """Which faces of a proud bar a found bar ``width_px`` wide is, of its side face and the growth of its
    front face (``side_face``: ``seen``) and a front face ``front_px`` wide at the foot (the building's bar
    width): "side", "front" or "both", whichever width is nearest. The grid takes a bar of one colour: a
    side face lit unlike the front face (a transom's top face under the sky, seen from above) is found
    apart from it, as either. Where the nearest is not ``SIDE_FACE_MIN_PX`` nearer than the next, the
    faces are "unknown": one view's bars' widths scatter by about half that, so they cannot tell them
    apart (a side face under a pixel; a side face as wide as the front face)."""
    _, side, growth = seen
    front = front_px + growth
    widths = sorted((abs(width_px - w), f) for f, w in (("side", side), ("front", front),
                                                        ("both", front + side)))
    return widths[0][1] if widths[1][0] - widths[0][0] >= SIDE_FACE_MIN_PX else "unknown"


def correct_parallax(bars: Bars, par: Parallax, field: ParallaxField, front_px: float | None = None) -> Bars:
    """Bars whose front-face edges are moved by the parallax to where the glass meets the frame: each
    bar's edge on the far side from the camera's foot, both edges of a bar over it, and the near edges
    on a side where they are displaced too (``par.near_displaced``). On a side no fit measured
    (``par.slopes`` NaN there), a bar whose width is its front face's alone (``faces_found`` against
    ``front_px``, the building's bar width in px) has its near edge moved as well: its side face was not
    found with it."""
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
        near = list(par.near_displaced)
        side = 1 if above else 0
        if (above or below) and front_px is not None and not np.isfinite(par.slopes[side]):
            seen = side_face(field, axis, low, high, k)
            near[side] = seen is not None and faces_found(high.a - low.a, seen, front_px) == "front"
        if p_low < 0.0 or (above and near[1]):
            new_low = _unparallax(low, field, axis, k)
        if p_high > 0.0 or (below and near[0]):
            new_high = _unparallax(high, field, axis, k)
        edges.append((new_low, new_high))
    return Bars(edges, bars.fit)


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


def pooled_depth_m(
    views: list[tuple[Bars, ParallaxField, float]], axis: int, min_bars: int, max_slope: float
) -> tuple[float, tuple[float, float]]:
    """The frame depth d (m) of one family fitted over the bars of many views at once, 0 where they do not
    show one. Each view (its ``Bars`` at the working scale, its ``ParallaxField`` with the camera's distance
    D, its metres per pixel m) adds its bars' widths in metres, w = B_v + d s / (D + d), s the extent (m) of
    a bar beyond the camera's foot on either side at its found edges (``fit_parallax``'s model: there k s /
    (1 + k) in pixels, k = d / D; a second fit divides by D + d). One facade's frames share d, and on a plane
    each side of the foot
    shows the same face of every bar, lit alike in every view, so views with too few bars for a fit of
    their own (a close-up framing one unit: two bars a family) measure d together. Each view has its own
    B_v: a photo's exposure, focus and scale widen or narrow all its bars alike, so only the widths within
    a view against their extents tell d; and the bars of one view share those errors, so d's standard error
    is over the views (the cluster-robust one, G / (G - 1) for G views). Bars narrower than half their
    view's median (cut by the border), views without a distance and views with one bar left are left out;
    d is the larger side's, kept where it stands ``PARALLAX_MIN_T`` standard errors above 0, from at least
    ``min_bars`` bars and more bars than unknowns, and where its slope in the nearest of the views fitted
    (``slope_of``: the largest of theirs) is within ``max_slope``, the largest a view's own fit accepts
    (``fit_parallax``); else 0. Returned with each side's own d (P < 0, P > 0; NaN: not measured there):
    a side's faces shaded like the glass show as a side whose widths do not grow (``Parallax.with_slope``)."""
    w, x, px, view, dist = [], [], [], [], []
    for i, (bars, field, m) in enumerate(views):
        if not np.isfinite(field.distance_m) or not bars.edges:
            continue
        widths = np.array([hi.a - lo.a for lo, hi in bars.edges])
        kept = [(lo, hi, width) for (lo, hi), width in zip(bars.edges, widths, strict=True)
                if width >= 0.5 * float(np.median(widths))]
        if len(kept) < 2:
            continue
        for lo, hi, width in kept:
            s = np.maximum([-_coord(field, axis, lo), _coord(field, axis, hi)], 0.0)
            w.append(width * m)
            x.append(s * m)
            px.append(s)
            view.append(i)
            dist.append(field.distance_m)
    none = (0.0, (float("nan"), float("nan")))
    sides = [j for j in (0, 1) if len(px) and np.ptp(np.array(px)[:, j]) >= 1.0]
    ids = np.unique(view)
    if len(w) < min_bars or not sides or len(ids) < 2 or len(w) <= len(ids) + len(sides):
        return none
    own = (np.array(view)[:, None] == ids[None]).astype(float)
    d = 0.0
    for _ in range(2):
        A = np.concatenate([own, np.array(x)[:, sides] / (np.array(dist)[:, None] + d)], axis=1)
        coef = np.linalg.lstsq(A, np.array(w), rcond=None)[0]
        slopes = dict(zip(sides, coef[len(ids):], strict=True))
        side = max(slopes, key=lambda j: slopes[j])
        d = max(float(slopes[side]), 0.0)
    if d <= 0.0:
        return none
    residual = np.array(w) - A @ coef
    inv = np.linalg.pinv(A.T @ A)
    scores = [A[own[:, g] > 0].T @ residual[own[:, g] > 0] for g in range(len(ids))]
    cov = len(ids) / (len(ids) - 1) * inv @ sum(np.outer(q, q) for q in scores) @ inv
    error = float(np.sqrt(max(cov[len(ids) + sides.index(side), len(ids) + sides.index(side)], 0.0)))
    if d < PARALLAX_MIN_T * error or slope_of(d, min(dist)) > max_slope:
        return none
    return d, (float(slopes.get(0, np.nan)), float(slopes.get(1, np.nan)))
