"""The frame bars of a (rectified) frontal view: LSD segments and the MAP grid of each family (``grid``),
then the sub-pixel edges of each bar (``edges``), with the frames' parallax fitted (``parallax``), at a
working scale where the narrowest bar spans ``work_bar_px`` pixels; and the building's bar width applied to
the bars a view found too thin."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from facade_pipeline.segmentation.edges import (
    CLIPPED_BAR_KNOWN,
    Bars,
    EdgeLine,
    bar_colour_ref,
    bar_edges,
    centre_colour,
    clipped_beyond,
    frame_presence,
)
from facade_pipeline.segmentation.evidence import (
    CLIPPED_LEVEL,
    Gradients,
    bar_evidence,
    log_likelihood,
    lsd_evidence,
    nanmedian0,
)
from facade_pipeline.segmentation.grid import (
    EDGE_SEARCH_PX,
    STEP_PX,
    FamilyFit,
    PixelSizes,
    map_family,
    pitch_hypotheses,
)
from facade_pipeline.segmentation.lines import detect_segments, group_segments, support_profile
from facade_pipeline.segmentation.openings import continues, strip_support
from facade_pipeline.segmentation.parallax import (
    PARALLAX_MIN_BARS,
    Parallax,
    ParallaxField,
    faces_found,
    fit_parallax,
    slope_of,
    widest_side_face,
)
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


def _family(
    grad: Gradients,
    segments: np.ndarray | Callable[[], np.ndarray],
    axis: int,
    span: slice,
    params: SegmentParams,
    sizes: PixelSizes,
    frame_colour: np.ndarray | None = None,
    pool: Executor | None = None,
    surface: np.ndarray | None = None,
    unknown_floor: float = 0.0,
) -> FamilyFit | None:
    """MAP bars of one family (axis 0: mullions; ``grad`` its gradients) with evidence taken over ``span``
    along the bars; with ``frame_colour`` [3] (the other family's bars), bars of another colour are
    penalised. ``segments`` (the family's LSD segments) may be a function that waits for them: they are
    needed only once the gradient evidence is made. With a ``pool``, the uniformity and part of the bar
    evidence are computed on it. ``surface`` [L, N] (the family's layout; None: everywhere): where the
    facade surface is, for the bars the grid places where the view shows nothing (``clipped_place``).
    ``unknown_floor``: a bar's edge between two clipped pixels counts at least this fraction of its other
    edge (``evidence.bar_evidence``; 0: as absent)."""
    uniformity = pool.submit(grad.uniformity, span) if pool is not None else None
    (e_grad, widths), (e_out, w_out) = bar_evidence(grad, span, params.grid, sizes,
                                                    (0.0, params.grid.outer_edge_floor), pool,
                                                    unknown_floor)
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
    # an outer frame meets the background on one side, and the centre line of a one-sided bar found at its
    # glass-side edge is not reliably on the frame; the narrowest bar's width beside that edge is the frame
    # whatever lies beyond it: the colour prior is taken there, on the side of the run (``glass_side``)
    lsd_out = lsd_evidence(support, w_out, hi - lo)
    ll_out = (log_likelihood(e_out, lsd_out, uniformity, params.grid) if dist is None else np.stack([
        log_likelihood(e_out, lsd_out, uniformity, params.grid, glass_side(dist, w_out, sizes.min_bar, s))
        for s in (1, -1)]))
    return map_family(ll, widths, grad.size, params.grid, sizes, (ll_out, w_out),
                      lambda c, w: clipped_place(grad, span, c, w, surface))


def glass_side(values: np.ndarray, widths: np.ndarray, narrow: int, sign: int) -> np.ndarray:
    """[M] ``values`` [M] (on the lattice) taken, for a bar at each position of ``widths`` [M] (px), in
    the middle of the narrowest bar's width (``narrow`` px) beside its edge on the ``sign`` side (+1: its
    high edge; beyond the first bar of a run the glass lies on that side, beyond the last on the other)."""
    M = len(values)
    # (w - narrow) / 2 px is (w - narrow) lattice steps (``STEP_PX``: half a pixel)
    shift = np.maximum(np.asarray(widths, float) - narrow, 0.0).astype(int)
    return values[np.clip(np.arange(M) + sign * shift, 0, M - 1)]


def clipped_place(grad: Gradients, span: slice, c: float, width: float,
                  support: np.ndarray | None = None) -> bool:
    """Whether a bar centred at ``c`` of ``width`` (px) shows nothing either way over ``span``: its edges
    known (``Gradients.known``) over at most ``CLIPPED_BAR_KNOWN`` of it (the frame clipped with the glass
    beside it; of a bar cut by the view's border, the edge in the view), on the facade surface over at
    least half of it (``support`` [L, N] in the family's layout, None: everywhere; the sky beyond a
    facade's end clips too)."""
    known = grad.known_on_lattice
    if known is None:
        return False
    known = known[span]
    M = known.shape[1]
    # an edge beyond the view's border is unknown: a bar cut by the border is judged by its edge inside
    inside = [x for x in (c - width / 2, c + width / 2) if 1.0 <= x <= grad.size - 1.0]
    if not inside:
        return False
    i, j = (int(np.clip(np.rint(x / STEP_PX), 0, M - 1)) for x in (inside[0], inside[-1]))
    both = known[:, i] * known[:, j] if len(inside) == 2 else known[:, i]
    if len(inside) == 1:  # the middle of the bar's part in the view
        c = 0.5 * (max(c - width / 2, 1.0) + min(c + width / 2, grad.size - 1.0))
    col = int(np.clip(np.floor(c), 0, grad.size - 1))
    seen = grad.valid[span, col]
    if not seen.any() or float(both[seen].mean()) > CLIPPED_BAR_KNOWN:
        return False
    return support is None or float(support[span, col].mean()) >= 0.5


def with_clipped_ends(fit: FamilyFit, grad: Gradients, span: slice,
                      support: np.ndarray | None = None, cut: bool = False) -> FamilyFit:
    """``fit`` extended by one bar at either end, one pitch beyond it at the run's median width, where
    that bar lies whole in the view and its place shows nothing either way (``clipped_place``: clipped
    with the glass beside it, no evidence either way, and the grid places it), the bars so placed added to
    ``FamilyFit.placed``. With ``cut``, only where that bar is cut by the view's border instead, its edge
    toward the run in the view."""
    if grad.known_on_lattice is None:
        return fit
    width = float(np.median(fit.widths))
    centres, widths, placed = list(fit.centres), list(fit.widths), set(fit.placed)
    added = 0
    for sign in (1.0, -1.0):
        c = (centres[-1] if sign > 0 else centres[0]) + sign * fit.pitch
        whole = c - width / 2 >= 1.0 and c + width / 2 <= grad.size - 1.0
        if cut and (whole or not 1.0 <= c - sign * width / 2 <= grad.size - 1.0):
            continue
        if not cut and not whole:
            continue
        if not clipped_place(grad, span, c, width, support):
            continue
        added += 1
        if sign > 0:
            centres.append(c)
            widths.append(width)
            placed.add(len(centres) - 1)
        else:
            centres.insert(0, c)
            widths.insert(0, width)
            placed = {k + 1 for k in placed} | {0}
    if not added:
        return fit
    return FamilyFit(np.array(centres), np.array(widths), fit.pitch, fit.score, frozenset(placed))


def _goes_on(bars_v: Bars | None, bars_h: Bars | None, h: FamilyFit, cut: FamilyFit, H: int,
             support: np.ndarray | None, params: SegmentParams) -> bool:
    """Whether the facade goes on across the whole border strip beyond each end of the transoms ``h``
    where ``cut`` adds a bar (``openings.continues`` of the mullions into it, whole)."""
    if bars_v is None or bars_h is None:
        return False
    inside = (h.centres[0], h.centres[-1])
    across = (bars_v.fit.centres[0], bars_v.fit.centres[-1])
    strips = []
    if cut.centres[0] != h.centres[0]:
        strips.append((0.0, bars_h.edges[0][0].a))
    if cut.centres[-1] != h.centres[-1]:
        strips.append((bars_h.edges[-1][1].a, float(H)))
    return all(continues(bars_v, lo, hi, inside, strip_support(support, 1, lo, hi, across), params,
                         sides=False) is None
               for lo, hi in strips)


def bar_colour(grad: Gradients, fit: FamilyFit, span: slice) -> np.ndarray:
    """[3] median colour (0-1) of one family's bars (``grad`` of that family): along their centre lines
    over ``span``."""
    colour = grad.line_colour(span)
    idx = np.clip(np.rint(fit.centres / STEP_PX).astype(int), 0, len(colour) - 1)
    return nanmedian0(colour[idx])


def _runs_beyond(fit: FamilyFit, span: slice) -> bool:
    """Does a bar of ``fit`` lie more than half its pitch beyond ``span`` (the along-bar range the other
    family was sought over, from the first to the last bar of another pass)? Nearer, it is that pass's
    outermost bar found again a little off, not a bar the pass missed."""
    reach = fit.pitch / 2
    return bool((fit.centres < span.start - reach).any() or (fit.centres > span.stop - 1 + reach).any())


def extent(fit: FamilyFit | None, size: int) -> slice:
    """Along-bar range of the other family: from the first to the last bar centre of ``fit``."""
    if fit is None:
        return slice(0, size)
    return slice(int(max(0, np.floor(fit.centres[0]))), int(min(size, np.ceil(fit.centres[-1]) + 1)))


def _edges(fit: FamilyFit, grad: Gradients, span: slice, params: SegmentParams) -> Bars | None:
    """The edges of each bar of ``fit``; a bar placed by the grid (``FamilyFit.placed``) whose edges are
    not both found keeps the straight edges of its place: it clips with the glass beside it, and the one
    edge found there is as often where the clip ends in the glass (``bar_edges``' ``place_unknown`` is
    for the bars the grid found by their edges). An edge's parting from the other is weighed against the
    family's median width (``bar_edges``' ``family_px``)."""
    family = float(np.median(fit.widths))
    found = [
        bar_edges(grad, c, w, span, EDGE_SEARCH_PX, k not in fit.placed, family)
        for k, (c, w) in enumerate(zip(fit.centres, fit.widths, strict=True))
    ]
    edges = []
    mid = 0.5 * (span.indices(grad.img.shape[0])[0] + span.indices(grad.img.shape[0])[1])
    for k, e in enumerate(found):
        if e is None and k in fit.placed:
            c, w, L = fit.centres[k], fit.widths[k], grad.img.shape[0]
            e = (EdgeLine(c - w / 2, 0.0, mid, np.zeros(L)), EdgeLine(c + w / 2, 0.0, mid, np.zeros(L)))
        if e is None:
            continue
        edges.append(with_presence(grad, e, span, params))
    return Bars(edges, fit) if edges else None


def placed_bars(bars: Bars) -> set[int]:
    """Which of ``bars.edges`` are the bars the grid placed (``FamilyFit.placed``): each the one whose
    centre is nearest a placed bar's (``_edges`` leaves out the bars it finds no edges for, never a placed
    one, so the edges are not indexed as the fit's bars)."""
    if bars.fit is None or not bars.fit.placed or not bars.edges:
        return set()
    centres = np.array([0.5 * (lo.a + hi.a) for lo, hi in bars.edges])
    return {int(np.argmin(np.abs(centres - bars.fit.centres[k]))) for k in bars.fit.placed}


def _halves(bar: tuple[EdgeLine, EdgeLine]) -> tuple[tuple[EdgeLine, EdgeLine], tuple[EdgeLine, EdgeLine]]:
    """The two halves of ``bar`` as bars of their own, each from one of its edges to its centre line (the
    line halfway between the edges): a unitised facade's bar is the frames of the two units beside it."""
    centre = dataclasses.replace(bar[0], a=0.5 * (bar[0].a + float(bar[1].at(bar[0].mid))),
                                 b=0.5 * (bar[0].b + bar[1].b))
    return (bar[0], centre), (centre, bar[1])


def with_presence(grad: Gradients, bar: tuple[EdgeLine, EdgeLine], span: slice,
                  params: SegmentParams) -> tuple[EdgeLine, EdgeLine]:
    """The two edges of ``bar`` with where its frame colour is present on its centre line over ``span``,
    where that is unknown and where it is short (``frame_presence`` within ``frame_colour_tol``) and
    where it is clipped in one run with what lies beyond the bar (``clipped_beyond``), set on both; and
    each with where it is present on its own half of the bar (``EdgeLine.half_present``), judged against
    its own median over ``span`` (one unit's frame may be lit or shaded unlike the other's) where that is
    within the tolerance of the bar's colour on its centre line, else against the bar's colour: there the
    half lies off the frame over the span (the bar shows only its other half, and its fitted edge lies on
    the glass beside it), its median is the glass's, and the frame's colour beyond the span would read as
    absent."""
    tol = params.frame_colour_tol
    ref = bar_colour_ref(grad, bar[0], bar[1], span)
    present, unknown, short = frame_presence(grad, bar[0], bar[1], span, tol, ref)
    halves = []
    for half in _halves(bar):
        own = bar_colour_ref(grad, *half, span)
        if own is not None and ref is not None:
            own = np.where((np.linalg.norm(own - ref, axis=-1) <= tol)[..., None], own, ref)
        seen, _, clipped_short = frame_presence(grad, *half, span, tol, own)
        halves.append(seen if clipped_short is None else np.where(clipped_short, 0.0, seen))
    beyond = clipped_beyond(grad, bar[0], bar[1])
    low, high = (dataclasses.replace(line, present=present, unknown=unknown, short=short, half_present=h,
                                     clip_beyond=beyond)
                 for line, h in zip(bar, halves, strict=True))
    return low, high


def find_bars(
    image: np.ndarray,
    params: SegmentParams,
    sizes: tuple[PixelSizes, PixelSizes],
    valid: np.ndarray | None = None,
    parallax: ParallaxField | None = None,
    planar: bool = True,
    support: np.ndarray | None = None,
    predicted: bool = False,
) -> tuple[Bars | None, Bars | None, dict, dict[str, Parallax], tuple[Gradients, Gradients]]:
    """Mullions and transoms of an RGB image [H, W, 3]: MAP passes for the transoms over the whole image,
    then for each family over the other's extent only (on a ``planar`` surface the transoms must have the
    mullions' colour, ``frame_colour_scale``), both again where the transoms found with that colour run
    beyond the rows the mullions were sought over (``_runs_beyond``), a mullion clipped white with the
    glass beside it one pitch beyond either end placed by the grid (``with_clipped_ends``; a transom only
    where its place is cut by the view's border and the mullions go on across the strip beyond), then
    sub-pixel edges, with their frames' parallax fitted in the image's ``parallax`` field ({"x":
    mullions, "y": transoms}; none without a field), not yet corrected, and the two families' gradients.
    ``sizes``: the grid model's sizes of the mullions and the transoms; ``support`` [H, W]: where the
    facade surface is (None: everywhere).
    ``predicted``: the mullions' pitches sought are the building's (``sizes_v``), which predicts where each
    of them lies: an edge between two clipped pixels there is unknown, not absent, and the bar's other
    edge counts as an outer frame's does (``outer_edge_floor``): a frame clipped with what lies beside it
    meets a background of its own colour. Without that prediction, a one-sided edge beside a clip (a
    reflection's) would take a bar's place at any pitch. Mullions only, as for the bars placed where they
    clip (``with_clipped_ends``): a horizontal edge beside a clip is as often an empty unit's lit ceiling
    or shelf, seen through its open frame, as a transom."""
    floor_v = params.grid.outer_edge_floor if predicted else 0.0
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
        # on a curved surface the transoms' shading turns along them (``Gradients.block_px``): judged over
        # blocks of the smallest pitch sought, a reflection changes within one and the shading hardly does;
        # blocks a frame's own colour tolerance apart are an edge crossing the position, not shading
        gv = Gradients.of(image, 0, valid)
        gh = Gradients.of(image, 1, valid, None if planar else float(sizes_h.min_pitch),
                          params.frame_colour_tol)
        ahead = [pool.submit(gv.prepare)]
        ahead += [pool.submit(pitch_hypotheses, g.size, z) for g, z in ((gh, sizes_h), (gv, sizes_v))]
        # a mullion pass over the whole height would serve nothing: the first transom pass takes the whole
        # width
        support_h = None if support is None else support.T  # the transoms' layout: along them first
        h_first = _family(gh, lambda: lsd.result().segments[lsd.result().horizontal], 1, slice(0, W),
                          params, sizes_h, pool=pool, surface=support_h)
        fam = lsd.result()
        vseg, hseg = fam.segments[fam.vertical], fam.segments[fam.horizontal]
        for done in ahead:
            done.result()
        # frames are one material: the transoms must have the mullions' colour. Mullions are the reference:
        # they run the facade's full height, while the long straight lines that reflections bring (horizon,
        # roofs, kerbs) and the shelves seen through an empty frame cell are horizontal.
        # A second pass where the transoms found with the mullions' colour run beyond the rows the mullions
        # were sought over (the first pass missed a transom clipped with the glass beside it, and took the
        # rows of an empty unit, where the mullions between its openings do not run, for the facade's): the
        # mullions are sought again over the whole run the panels are made of, and the transoms with their
        # colour. Only with the colour prior: without it the transoms sought over the mullions' extent are
        # the first pass's, narrowed
        rows = h_first
        for again in (False, True):
            v = _family(gv, vseg, 0, extent(rows, H), params, sizes_v, pool=pool, surface=support,
                        unknown_floor=floor_v)
            colour_h = None
            if v is not None and params.grid.frame_colour_scale > 0 and planar:
                colour_h = bar_colour(gv, v, extent(rows, H))
            h = _family(gh, hseg, 1, extent(v, W), params, sizes_h, colour_h, pool, support_h)
            if again or colour_h is None or h is None or not _runs_beyond(h, extent(h_first, H)):
                break
            rows = h
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
        # mullions only: a clipped horizontal stretch beyond the transoms is as often the lit ceiling or
        # shelf of an empty unit seen through its open frame as a transom. A transom is placed only where
        # an end bay's bar was found off the grid's clipped place (``grid._with_end_bays``), or where the
        # grid's place is cut by the view's border, clipped where it shows, and the mullions go on across
        # the whole strip beyond the run (``openings.continues``, as a border strip's panels are judged):
        # the facade goes on beyond the run there. Where an empty unit's lit box fills the strip, the
        # mullions do not go on across it in the median, and no transom makes its cell a pane
        v = with_clipped_ends(v, gv, extent(h, H), support)
        cut = with_clipped_ends(h, gh, extent(v, W), support_h, cut=True)
        edges_h = pool.submit(_edges, h, gh, extent(v, W), params)
        bars_v = _edges(v, gv, extent(h, H), params)
        bars_h = edges_h.result()
        if cut is not h and _goes_on(bars_v, bars_h, h, cut, H, support, params):
            h = cut
            edges_h = pool.submit(_edges, h, gh, extent(v, W), params)
            bars_v = _edges(v, gv, extent(h, H), params)
            bars_h = edges_h.result()
        metrics["bars_placed_x"] = len(v.placed)
        metrics["bars_placed_y"] = len(h.placed)
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


def working_scale(params: SegmentParams, metres_per_px: float, unit_m: float) -> float:
    """Ratio (<= 1) of the working image's size to the given image's (``work_bar_px``; ``unit_m``: the
    building's pitch, the unit of the params' lengths)."""
    return min(1.0, metres_per_px * params.work_bar_px / (params.grid.min_bar * unit_m))


@dataclass(frozen=True, eq=False)
class FrameBars:
    """The frame bars of one image at the working scale (``find_frames``), their parallax fitted but not
    yet corrected: what ``segment_frames`` makes the panels from."""

    bars_v: Bars | None
    bars_h: Bars | None
    fits: dict[str, Parallax]
    parallax: ParallaxField | None
    size: tuple[int, int]
    scale: tuple[float, float]
    metres_per_px: float
    support: np.ndarray | None
    metrics: dict
    grads: tuple[Gradients, Gradients]
    unit_m: float = 1.0
    """The building's pitch (m) the bars were sought at: the unit of the params' lengths."""
    planar: bool = True
    """Whether the surface is a plane (``find_bars``)."""

    def bar_widths_m(self) -> dict[str, list[float]]:
        """The widths (m) of the bars found, per family ("x": mullions, "y": transoms), but for the bars the
        grid placed where the view shows nothing either way (``placed_bars``): a clip shows no frame's
        width, and without the facade surface (the survey's, made before the pitch that sets its
        tolerance is known) the sky beyond a facade's end is such a place too."""
        widths = {}
        for name, bars in (("x", self.bars_v), ("y", self.bars_h)):
            if bars is not None:
                placed = placed_bars(bars)
                widths[name] = [(hi.a - lo.a) * self.metres_per_px for k, (lo, hi) in enumerate(bars.edges)
                                if k not in placed]
        return widths

    def pitches_m(self) -> dict[str, float]:
        """The pitch (m) of the grid found, per family ("x": across the mullions, "y": the transoms); none
        where no grid was found."""
        return {name: self.metrics[f"pitch_{name}_px"] * self.metres_per_px for name in ("x", "y")
                if f"pitch_{name}_px" in self.metrics}

    def frame_depths_m(self, unjudged: bool = False) -> dict[str, float]:
        """The frame depth d = k D (m) each family's own parallax fit gives ("x": the mullions, "y": the
        transoms; ``parallax.slope_of``), where it has one and the camera's distance D to the surface is
        known; with
        ``unjudged``, the depths of the exact fits instead (``Parallax.unjudged``, the larger side slope)."""
        D = np.nan if self.parallax is None else self.parallax.distance_m
        k = {n: float(np.nanmax(f.slopes)) if unjudged else f.k for n, f in self.fits.items()
             if f.unjudged == unjudged and (unjudged or f.k > 0.0)}
        return {n: v * D for n, v in k.items() if np.isfinite(D)}


def find_frames(
    image: np.ndarray,
    params: SegmentParams,
    metres_per_px: float,
    unit_m: float,
    valid: np.ndarray | None = None,
    parallax: ParallaxField | None = None,
    support: np.ndarray | None = None,
    planar: bool = True,
    pitch_m: dict[str, tuple[float, float]] | None = None,
    bar_max_m: dict[str, float] | None = None,
    predicted: bool = False,
    side_depth_m: dict[str, float] | None = None,
) -> FrameBars:
    """The frame bars of an RGB image [H, W, 3] of a facade at ``metres_per_px`` (a rectified frontal view),
    found at the working scale (``work_bar_px``); ``unit_m`` is the building's panel pitch (m), the unit of
    the params' lengths (``building.survey_unit_m``); ``support`` [H, W] marks where the facade surface is
    (``rectification.facade_support``; None: all); ``valid`` [H, W] marks the pixels that show the view (a
    rectified image has none outside the original); ``parallax`` is the image's parallax coordinate, in
    which the frames' parallax is fitted (None: not); ``planar``: the surface is a plane (``find_bars``);
    ``pitch_m`` narrows the pitches (m) sought across the mullions ("x") or the transoms ("y") to a range
    (the building's grid, ``building.pitch_range_m``; the grid model's range where None); ``bar_max_m``
    widens the bars sought across the mullions ("x") or the transoms ("y") to at least that width (m; the
    widths the survey saw where wider than the grid model's, ``building.surveyed_bar_max_m``); with
    ``predicted``, the ranges of ``pitch_m`` are the building's grid, which predicts where the bars lie
    (``find_bars``: the mullions, where ``pitch_m`` holds theirs); ``side_depth_m`` is the frames' depth
    (m) the views' surveys measured per family (``building.building_frame_parallax_m`` of
    ``survey_frames``): a family of ``bar_max_m`` is sought wider still by the widest side face its bars
    show in this view at the slope that depth gives from this camera (``parallax.widest_side_face``)."""
    H, W = image.shape[:2]
    q = working_scale(params, metres_per_px, unit_m)
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
    sizes = PixelSizes.of(params.grid, m, unit_m)
    family_sizes = tuple(
        sizes if name not in (pitch_m or {}) else dataclasses.replace(
            sizes, min_pitch=max(sizes.min_pitch, pitch_m[name][0] / m),
            max_pitch=min(sizes.max_pitch, pitch_m[name][1] / m))
        for name in ("x", "y")
    )
    # a bar seen obliquely shows its side face beside the surveyed width: the widest it shows in this view,
    # at the slope the surveys measured, is sought too, so that a far bar is found with its side face, as
    # the parallax fit reads it; a family whose slope no survey measured is sought as surveyed
    slopes = {name: slope_of(d, parallax.distance_m) for name, d in (side_depth_m or {}).items()
              if parallax is not None}
    family_sizes = tuple(
        z if name not in (bar_max_m or {}) else dataclasses.replace(
            z, max_bar=max(z.max_bar, int(round(bar_max_m[name] / m + (
                widest_side_face(parallax, axis, (Ww, Hw), slopes[name]) if slopes.get(name, 0.0) > 0.0
                else 0.0)))))
        for axis, (name, z) in enumerate(zip(("x", "y"), family_sizes, strict=True))
    )
    image = normalise_exposure(image, valid)
    bars_v, bars_h, metrics, fits, grads = find_bars(
        image, params, family_sizes, valid, parallax, planar, support,
        predicted and "x" in (pitch_m or {}))
    metrics.update({"working_scale": round(float(np.sqrt(qx * qy)), 4), "working_metres_per_px": m})
    return FrameBars(bars_v, bars_h, fits, parallax, (Ww, Hw), (qx, qy), m, support, metrics, grads, unit_m,
                     planar)


#: the survey, which measures the building's pitch before any length is known, seeks each family's pitch
#: between the view's extent across it divided by this and that extent: a frontal view frames one to ten
#: panels across (gcw_dev's about two, demo's about five)
SURVEY_PITCHES = 10.0
#: ... and bars between the view's size (the geometric mean of its extents) divided by the first and by the
#: second (gcw_dev's and demo's bars are a 27th and a 44th of it); the first sets the survey's working scale
#: with ``work_bar_px`` (about 225 working px across the view's size)
SURVEY_BARS = (75.0, 15.0)


def survey_frames(
    image: np.ndarray,
    params: SegmentParams,
    metres_per_px: float,
    valid: np.ndarray | None = None,
    parallax: ParallaxField | None = None,
    support: np.ndarray | None = None,
    planar: bool = True,
) -> FrameBars:
    """The frame bars of an image (as ``find_frames``) sought before the building's pitch is known, at
    sizes relative to the view alone: each family's pitch between the image's extent across it over
    ``SURVEY_PITCHES`` and that extent, the bars' widths and the working scale relative to the image's size
    (the geometric mean of its extents, ``SURVEY_BARS``). Every size is then a number of the image's
    pixels, whatever its metres per pixel: a facade at another scale, seen in the same pixels, gives the
    same bars, and their pitches (``FrameBars.pitches_m``) scale with it."""
    H, W = image.shape[:2]
    size_m = float(np.sqrt(W * H)) * metres_per_px
    n = SURVEY_PITCHES
    grid = dataclasses.replace(
        params.grid, min_pitch=min(W, H) * metres_per_px / n / size_m,
        max_pitch=max(W, H) * metres_per_px / size_m,
        min_bar=1.0 / SURVEY_BARS[0], max_bar=1.0 / SURVEY_BARS[1])
    ranges = {"x": (W * metres_per_px / n, W * metres_per_px),
              "y": (H * metres_per_px / n, H * metres_per_px)}
    return find_frames(image, dataclasses.replace(params, grid=grid), metres_per_px, size_m, valid, parallax,
                       support, planar, ranges)


def _pitch_side(bars: Bars, k: int, pitch_px: float | None, within: float | None = None,
                place: float | None = None) -> float:
    """On which side of bar ``k`` (-1: low, +1: high, 0: neither) the bar's centre lies: at ``place`` (px,
    at the bar's centre lines' middles) where given, else where the building's pitch ``pitch_px`` from the
    nearest other bar of ``bars`` puts it (0 without a pitch or another bar); 0 where it lies within
    ``within`` px of its centre as found (half its width where None: within the bar)."""
    c = 0.5 * (bars.edges[k][0].a + bars.edges[k][1].a)
    if place is None:
        if pitch_px is None or pitch_px <= 0 or len(bars.edges) < 2:
            return 0.0
        centres = np.array([0.5 * (low.a + high.a) for low, high in bars.edges])
        others = np.delete(centres, k)
        near = others[np.argmin(np.abs(others - c))]
        place = near + np.rint((c - near) / pitch_px) * pitch_px
    half = 0.5 * (bars.edges[k][1].a - bars.edges[k][0].a) if within is None else within
    return 0.0 if abs(place - c) <= half else float(np.sign(place - c))


def _bar_score(bar: tuple[EdgeLine, EdgeLine], rows: slice = slice(None)) -> float:
    """How strongly a bar's weaker edge is found over ``rows``: the geometric mean of its two edges' mean
    strengths there, as the bar evidence of ``grid``."""
    return float(np.sqrt(bar[0].strength[rows].mean() * bar[1].strength[rows].mean()))


def _place_beyond(grad: Gradients, thin: tuple[EdgeLine, EdgeLine], width_px: float,
                  span: slice) -> float | None:
    """The centre (px, at ``thin``'s lines' middles) of the bar of ``width_px`` that holds the line
    ``thin`` as one of its halves, found beyond ``span`` (the other family's extent: the view's rows
    beyond its outer bars), or None. A bar is straight through the view, and where the line is the one
    half of a frame beside a unit not installed, the cells beyond that unit's row are as often glazed on
    both sides, the bar whole there. Of the two bars of ``width_px`` sharing an edge with the line, on either
    side of ``span``, the one whose weaker edge is strongest there (as ``widen_narrow_bars`` scores them),
    found at least three quarters of ``width_px`` wide (a thinner one is the same half again) and with its
    edges there at least as strong as the line's within ``span``: a line the grid took in the glass (an
    edge reflected) has weak edges beyond as within, where the pitch tells more."""
    low, high = thin
    size = len(low.strength)
    start, stop, _ = span.indices(size)
    width = high.a - low.a
    best, score = None, _bar_score(thin, span)
    for rows in (slice(0, start), slice(stop, size)):
        if rows.stop - rows.start < 2:  # no line is fitted through fewer rows
            continue
        for sign in (-1.0, 1.0):
            e = bar_edges(grad, 0.5 * (low.a + high.a) + sign * 0.5 * (width_px - width), width_px, rows,
                          EDGE_SEARCH_PX)
            if e is None or e[1].a - e[0].a < 0.75 * width_px:
                continue
            sc = _bar_score(e, rows)
            if sc > score:
                best, score = 0.5 * float(e[0].at(low.mid) + e[1].at(high.mid)), sc
    return best


def widen_narrow_bars(bars: Bars, grad: Gradients, span: slice, width_px: float,
                      params: SegmentParams,
                      side_face: Callable[[EdgeLine, EdgeLine], tuple | None] | None = None,
                      pitch_px: float | None = None, frames_colour: np.ndarray | None = None,
                      ) -> tuple[Bars, int]:
    """``bars`` with every bar narrower than half of ``width_px`` (the building's width of the family) and a
    whole width away from the image border found again at that width, and how many were: a thin line that
    keeps one edge of the bar (its shaded side face, a reflection meeting it) can take the grid's place of a
    frame whose face has little contrast against the glass beside it. Of the four bars of ``width_px`` that
    share an edge with the thin one, the one whose weaker edge is strongest is kept (the geometric mean of its
    edges' strengths, as the bar evidence of ``grid``), of the two on the side of the line where the
    building's pitch ``pitch_px`` from the nearest other bar puts the bar (``_pitch_side``; all four where it
    puts it within the line): beside a frame clipped with what lies beyond it (an empty unit's lit shelf over
    a transom, the sky a pane reflects beside a mullion) the bar's edge there is between clipped pixels,
    unknown rather than weak, and a weak edge in the glass on the other side would take the bar's place by its
    strength. Only where the view shows a bar of the family at least half that wide: a part whose frames are
    all thinner than the building's (another style) keeps them. With ``side_face`` (``parallax.side_face`` of
    a bar's edges: its near edge, the width its side face shows and its front face's growth), a bar at least
    half that wide found as its side face alone (``parallax.faces_found``, a side face lit unlike the front
    face) is joined to the front face of ``width_px`` found beyond it, away from the camera's foot: its near
    edge is where the glass meets the frame, and the far edge is the front face's. A thinner one only where
    its width is within half the side face's of it: a thin line is as often the side face with the shadow it
    casts on the glass beside it (a transom's underside seen from below), found again as above. Nor where
    the building's pitch puts the bar on the line's near side, the face beyond shows the frames' colour
    neither and the bar on the near side shows it (``_frame_on_near_side``): the line is then the frame's
    edge facing the glass (a transom clipped white with an empty unit's lit shelf above it, as wide as the
    side face by chance), found again as above, and the face beyond it is the glass.
    ``frames_colour`` ([3], the other family's bars' colour, ``bar_colour``): a thin bar widened, joined to
    a front face or found again at the width, records where its centre line shows it
    (``EdgeLine.frames_colour``): the line it was found by may be an edge of what lies beyond the frames (an
    empty unit's lit ceiling) over part of its length, whether the frames' depth is known or not."""
    size = grad.d.shape[1] + 1
    if not any(high.a - low.a >= 0.5 * width_px for low, high in bars.edges):
        return bars, 0
    colour = (frames_colour if frames_colour is not None or bars.fit is None
              else bar_colour(grad, bars.fit, span))
    edges, n = [], 0
    for k, (low, high) in enumerate(bars.edges):
        seen = None if side_face is None else side_face(low, high)
        width = high.a - low.a
        side = _pitch_side(bars, k, pitch_px)
        if (seen is not None and low.a >= width_px and high.a <= size - width_px
                and faces_found(width, seen, width_px) == "side"
                and (width >= 0.5 * width_px or abs(width - seen[1]) <= 0.5 * seen[1])):
            near, far = (low, high) if seen[0] == 0 else (high, low)
            sign = 1.0 if seen[0] == 0 else -1.0
            e = bar_edges(grad, far.a + sign * 0.5 * width_px, width_px, span, EDGE_SEARCH_PX)
            # a clip on the near side is the frame clipped with what lies beyond it as often as the lit box
            # of an empty unit beside a set-off unit's frame (whose join is right): the colours alone do not
            # tell them apart, the side the building's pitch puts the bar on does
            if (e is not None and e[1].a - e[0].a >= 0.5 * width_px
                    and not (side == -sign and _frame_on_near_side(
                        grad, e, near.a - sign * 0.5 * width_px, width_px, span, frames_colour, params))):
                joined = with_presence(grad, (near, e[1]) if seen[0] == 0 else (e[0], near), span, params)
                edges.append(_with_frames_colour(grad, joined, frames_colour, params)
                             if width < 0.5 * width_px else joined)
                n += 1
                continue
        if width >= 0.5 * width_px or low.a < width_px or high.a > size - width_px:
            # a bar found at the width of its one half (at least half the building's width, short of the
            # three quarters where the whole bar's half beside it would begin beyond the line) is read on
            # the bar of the building's width that holds it as its half away from the bar's place (where
            # it is found whole beyond the other family's bars, else the pitch's), where that place is
            # nearer that one's centre, (width_px - width) / 2 off, than the line's
            toward = (_pitch_side(bars, k, pitch_px, 0.25 * (width_px - width),
                                  _place_beyond(grad, (low, high), width_px, span))
                      if 0.5 * width_px <= width < 0.75 * width_px and low.a >= width_px
                      and high.a <= size - width_px else 0.0)
            edges.append(_halves_at_place(grad, (low, high), (low, high), width_px, span, colour, params,
                                          toward))
            continue
        # on the pitch's side a bar whose edge there is unknown (no strength) is still the bar's place
        best, score = (low, high), (0.0 if side == 0 else -1.0)
        for c in (low.a - 0.5 * width_px, low.a + 0.5 * width_px, high.a - 0.5 * width_px,
                  high.a + 0.5 * width_px):
            if side * (c - 0.5 * (low.a + high.a)) < 0:
                continue
            e = bar_edges(grad, c, width_px, span, EDGE_SEARCH_PX)
            if e is None or e[1].a - e[0].a < 0.5 * width_px:
                continue
            sc = _bar_score(e)
            if sc > score:
                best, score = e, sc
        if best[0] is not low:
            best = _with_frames_colour(grad, with_presence(grad, best, span, params), frames_colour, params)
            # read where it lies beside the thin one rather than over it (their centres more than half of
            # ``width_px`` apart)
            mid = low.mid
            off = 0.5 * float(best[0].at(mid) + best[1].at(mid) - low.at(mid) - high.at(mid))
            best = _halves_at_place(grad, best, (low, high), width_px, span, colour, params,
                                    float(np.sign(off)) if abs(off) > 0.5 * width_px else 0.0)
            n += 1
        edges.append(best)
    return Bars(edges, bars.fit), n


def _halves_at_place(grad: Gradients, bar: tuple[EdgeLine, EdgeLine], thin: tuple[EdgeLine, EdgeLine],
                     width_px: float, span: slice, colour: np.ndarray | None, params: SegmentParams,
                     toward: float) -> tuple[EdgeLine, EdgeLine]:
    """``bar`` (the thin bar ``thin`` widened to ``width_px``, or ``thin`` itself) with its halves read on
    the bar of ``width_px`` that holds the thin one as its half away from ``toward`` (-1: its low side, +1:
    its high side; 0: not read): the thin one's far edge its far edge, each half against the thin one's
    colour (``EdgeLine.half_at_place``). A thin line is as often the one half of the bar that is there
    beside a unit not installed as an edge beside the bar: widened beside it, the bar lies on that unit's
    box, and both its halves read the box; found at the width of that half and kept, both its halves read
    the half. Read on the bar the thin half belongs to, the half toward the box is gone and the thin one
    is there. Centred on the thin line instead, a bar of ``width_px`` has its half lines on the thin half's
    two edges. Only where the thin one shows the frames' ``colour`` or a clip (``_colour_shown``) over at
    least ``continuation_presence`` of ``span``: a half of a frame is the frames' material, while a thin
    line beside a bar may be the shadow it casts on the glass, whose bar-side half would read gone beside a
    pane. As it is without ``colour``."""
    if colour is None or not toward or not _shows_colour(grad, thin, colour, span, params):
        return bar
    below = toward < 0
    far, sign = (thin[1], -1.0) if below else (thin[0], 1.0)
    ref = bar_colour_ref(grad, *thin, span)
    reads = []
    for q in (0.25, 0.75):  # the thin one's half, the half beyond it toward ``toward``
        line = dataclasses.replace(far, a=far.a + sign * q * width_px)
        seen, _, short = frame_presence(grad, line, line, span, params.frame_colour_tol, ref)
        reads.append(seen if short is None else np.where(short, 0.0, seen))
    halves = reads[::-1] if below else reads
    low, high = (dataclasses.replace(line, half_at_place=h) for line, h in zip(bar, halves, strict=True))
    return low, high


def _frame_on_near_side(grad: Gradients, front: tuple[EdgeLine, EdgeLine], c: float, width_px: float,
                        span: slice, colour: np.ndarray | None, params: SegmentParams) -> bool:
    """Whether a thin line's front face ``front``, found beyond it away from the camera's foot, shows the
    frames' ``colour`` or a clip (``_colour_shown``) over less than ``continuation_presence`` of ``span``
    while the bar of ``width_px`` centred at ``c``, beyond the line toward the foot, shows it over at least
    that: the line is then the frame's edge facing the glass, not its side face (a transom clipped white
    with what lies beyond it shows no edge but that one), and the face beyond it is the glass. False
    without ``colour``, or where no bar is found at ``c``."""
    if colour is None or _shows_colour(grad, front, colour, span, params):
        return False
    e = bar_edges(grad, c, width_px, span, EDGE_SEARCH_PX)
    if e is None or e[1].a - e[0].a < 0.5 * width_px:
        return False
    return _shows_colour(grad, e, colour, span, params)


def _shows_colour(grad: Gradients, bar: tuple[EdgeLine, EdgeLine], colour: np.ndarray, span: slice,
                  params: SegmentParams) -> bool:
    """Whether the centre line of ``bar`` shows ``colour`` or a clip (``_colour_shown``) over at least
    ``continuation_presence`` of ``span``'s rows that show the view."""
    return float(np.nanmean(_colour_shown(grad, bar, colour, params)[span])) >= params.continuation_presence


def _colour_shown(grad: Gradients, bar: tuple[EdgeLine, EdgeLine], colour: np.ndarray,
                  params: SegmentParams) -> np.ndarray:
    """[L] 1 where the centre line of ``bar`` is within ``frame_colour_tol`` of ``colour`` or clipped white
    (unknown, not absent), 0 where not, NaN where it does not show the view."""
    centre, ok = centre_colour(grad, *bar)
    near = (np.linalg.norm(centre - colour, axis=1) <= params.frame_colour_tol) | (
        centre.max(axis=1) >= CLIPPED_LEVEL)
    return np.where(ok, near.astype(float), np.nan)


def _with_frames_colour(grad: Gradients, bar: tuple[EdgeLine, EdgeLine], colour: np.ndarray | None,
                        params: SegmentParams) -> tuple[EdgeLine, EdgeLine]:
    """``bar`` with where its centre line or the middle of the edge's own half of the bar is within
    ``frame_colour_tol`` of ``colour`` or clipped white (unknown, not absent) set on each edge
    (``EdgeLine.frames_colour``, ``_colour_shown``); as it is without ``colour``. Beside a unit not
    installed only the installed unit's half of the bar is there, and the centre line, the halves'
    meeting, runs along the end of that half: the half facing the other unit's cell shows the frame."""
    if colour is None:
        return bar
    shown = _colour_shown(grad, bar, colour, params)
    low, high = (dataclasses.replace(e, frames_colour=np.fmax(shown, _colour_shown(grad, h, colour, params)))
                 for e, h in zip(bar, _halves(bar), strict=True))
    return low, high
