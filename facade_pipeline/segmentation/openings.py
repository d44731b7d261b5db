"""The panels between a view's frame bars (``frames``): the openings across each family and the quads
where they cross.

A panel is the opening between two consecutive mullions and two consecutive transoms; its corners are the
intersections of the four bar edges that face it, ordered bottom-left, bottom-right, top-right, top-left
(as seen from outside, which is the image's left and right). Rows count from the lowest visible row.

Panels cut by the image border: the strip between the outermost bar and the border holds a partial panel
(``complete = False``) when it is at least ``min_partial`` (of the building's pitch) wide and the bars of the
other family continue into it (by their frame colour or their edges, where the facade surface is there:
``continues``; a clipped frame colour is matched only by a centre line clipped where it is,
``EdgeLine.short``); otherwise the facade ends at that bar, except beside the bars that continue on their own
(a stepped facade, an empty or offset unit): there the opening between two such bars, or one and the border,
is a partial panel, each bar by its half facing the opening (beside a unit not installed only the other unit's
half of the bar is there: ``EdgeLine.half_present``). A strip that holds the place of its family's next bar
whole (one pitch beyond the outermost, on a plane: ``openings``), where the grid found none, is not judged in
the median: only the bars that continue on their own go on into it. Where the median carries a strip, a
bar that shows nothing of itself there on one side (a unit not installed beside it) stops the opening on
that side.
Partly occluded panels: a panel whose frame bars are present (their centre line within ``frame_colour_tol``
of the bar's median colour: a frame keeps its colour whatever the glass beside it reflects, an object in
front of it does not), or show their edge facing the panel, over less than ``MIN_EDGE_SUPPORT`` of any
side's length is kept, with ``complete = False``.
A cell beside a bar found thin and widened whose centre line and half facing the cell there show neither
the frames' colour nor a clip, with no edge of the other family's bars facing it, is no panel; so is a cell
on a plane between two mullions beside one that shows only its half away from the cell, over the cell's
rows in the view where it shows either half (a strip the border cuts too): the unit there is not installed
(``_not_a_pane``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facade_pipeline.segmentation.edges import Bars, EdgeLine
from facade_pipeline.segmentation.params import SegmentParams

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


def _presence(present: np.ndarray | None, short: np.ndarray | None, lo: float, hi: float,
              untold: np.ndarray | None = None) -> float:
    """The fraction of [lo, hi) that shows the view where ``present`` [L] is 1, not counting ``short``
    rows, leaving out ``untold`` rows; NaN where unknown."""
    if present is None:
        return np.nan
    i0, i1 = int(max(0, np.ceil(lo))), int(max(0, np.floor(hi)))
    seg = present[i0:i1]
    if short is not None:
        seg = np.where(short[i0:i1], 0.0, seg)
    if untold is not None:
        seg = np.where(untold[i0:i1], np.nan, seg)
    seg = seg[~np.isnan(seg)]
    return float(seg.mean()) if len(seg) else np.nan


def _bar_continues(
    bar: tuple[EdgeLine, EdgeLine], lo: float, hi: float, inside: tuple[float, float],
    halves_span: tuple[float, float] | None = None,
) -> tuple[float, float, tuple[float, float], float]:
    """How one bar of the other family continues over [lo, hi) along it: (the fraction of the strip's part
    that shows the view where its frame colour is present on its centre line, NaN where unknown; the
    larger ratio of its two edges' mean strength there to their mean strength over ``inside``; the same
    fraction on each half of the bar, low and high, ``EdgeLine.half_present``, over ``halves_span``, all of
    the strip where None; the first fraction over the rows where the centre line tells the frame's colour,
    not clipped in one run with what lies beyond the bar, ``EdgeLine.clip_beyond``). A centre line below
    full scale where the frame's colour is clipped (``EdgeLine.short``) is not the frame: near a clipped
    frame colour, anything bright enough (the lit box of an empty unit) is within the tolerance. One
    clipped in every channel where that colour is clipped is within it whatever it shows; where the clip
    runs on beyond the bar, it shows the frame no more than what lies beside it."""
    presence = _presence(bar[0].present, bar[0].short, lo, hi)
    told = _presence(bar[0].present, bar[0].short, lo, hi, bar[0].clip_beyond)
    h0, h1 = (lo, hi) if halves_span is None else halves_span
    halves = (_presence(bar[0].half_present, None, h0, h1), _presence(bar[1].half_present, None, h0, h1))
    seen = None if bar[0].present is None else ~np.isnan(bar[0].present)
    ratio = 0.0
    for line in bar:
        ref = _mean(line.strength, *inside, seen)
        ratio = max(ratio, _mean(line.strength, lo, hi, seen) / ref if ref > 0 else 0.0)
    return presence, ratio, halves, told


def _one_half(kept: float, gone: float, params: SegmentParams) -> bool:
    """Whether a bar shows one of its halves (``kept``, the fraction where it is present) and not the other
    (``gone``): the first over at least ``continuation_presence``, the second over no more than 1 -
    ``continuation_presence``, both measured (not NaN). Beside a unit not installed only the other unit's
    half of the bar is there."""
    return (not np.isnan(kept) and kept >= params.continuation_presence
            and not np.isnan(gone) and gone <= 1.0 - params.continuation_presence)


def _halves_on_frame(other: Bars, at: float, inside: float) -> list[bool]:
    """Whether each bar of ``other`` has its halves read on its frame at ``at`` along it: a half is read
    on the line a quarter of the bar's fitted width in from its edge, three quarters of that width from
    the other edge, which lies on the frame where the bar there is as wide as its family's bars (the
    median of their fitted widths at ``inside``, along them) only while the fitted bar is no wider than
    4/3 of that. Wider (one edge fitted off the frame, on what lies beside it), a half shown beside the
    other's edge and gone beside the fitted one is the frame beside the glass, not a unit not installed."""
    family = float(np.median([high.at(inside) - low.at(inside) for low, high in other.edges]))
    return [4.0 * family >= 3.0 * float(high.at(at) - low.at(at)) for low, high in other.edges]


def continues(other: Bars, lo: float, hi: float, inside: tuple[float, float], support: float,
               params: SegmentParams, whole: bool = True,
               halves_span: tuple[float, float] | None = None,
               sides: bool = True) -> frozenset[tuple[int, int]] | None:
    """Which bars of ``other`` continue over [lo, hi) along them: None for all of them (the facade goes on
    across the whole strip), else the sides of those that do on their own, as (index, side: 0 low, 1 high)
    (an empty set: the facade ends).

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
    unit, a unit set off its neighbours' line), and the openings beside such a bar go on. Not ``whole``
    (the strip holds the grid's next bar's place, and no bar was found there): the bars continue on their
    own only, the median over them left out, since the facade's panes do not go on across the whole strip
    (the lit box of an empty unit behind several openings, clipped to the frames' colour, carries some of
    the bars' centre lines in the median). A bar whose centre line does not show its colour continues on
    its own on one side where that half of the bar shows it and the other half does not (over no more
    than 1 - ``continuation_presence`` of the strip; ``EdgeLine.half_present``): beside a unit not
    installed only the other unit's half of the bar is there, and its centre line, the halves' meeting,
    shows the frame's colour nowhere or only in part; the opening on the missing half's side does not go
    on, by the edges' strength either (the remaining half keeps its edge with the glass it frames), nor by
    the centre line where it does show the colour (brighter, the missing unit's lit box clips to the frames'
    white up to the halves' meeting: the halves tell the sides apart where the centre line cannot). Halves
    alike carry nothing the centre line does not (a lit box clipped to the frames' white over part of the
    strip shows in both). The halves are judged over ``halves_span`` (all of the strip where
    None): ``openings`` leaves out the bar width beside the strip's bar, where the two families' bars meet
    and their corners, not a unit's frame, part the halves. Where the median carries the strip, a bar
    whose centre line, edges and half facing an opening all fail there stops that opening (beside a unit
    not installed, the median over its neighbours' bars carries the strip across it), where its halves
    are read on its frame (``_halves_on_frame``); its centre line there is read only where it is not
    clipped in one run with what lies beyond the bar (``EdgeLine.clip_beyond``: glass mirroring a sky
    clipped beside a frame clipped, a fringe between them, read as the frame whatever the bar is, while
    its half facing the opening shows the unit not installed's box); not ``sides``
    (``frames._goes_on``: whether the facade goes on across the whole strip, for the grid's next bar), the
    median alone answers."""
    if support < 0.5:
        return frozenset()
    found = [_bar_continues(e, lo, hi, inside, halves_span) for e in other.edges]

    def shown(p: float) -> bool:
        return not np.isnan(p) and p >= params.continuation_presence

    def split(halves: tuple[float, float], side: int) -> bool:  # this side's half there, the other's gone
        return _one_half(halves[side], halves[1 - side], params)

    presence = [p for p, _, _, _ in found if not np.isnan(p)]
    if whole and (presence and float(np.median(presence)) >= params.continuation_presence
                  or found and float(np.median([r for _, r, _, _ in found])) >= params.continuation_ratio):
        gone = {(i, s) for i, (_, r, h, told) in enumerate(found) for s in (0, 1)
                if split(h, 1 - s) and not shown(told) and r < params.continuation_ratio} if sides else set()
        if gone:
            read = _halves_on_frame(other, 0.5 * sum(halves_span or (lo, hi)), 0.5 * sum(inside))
            gone = {(i, s) for i, s in gone if read[i]}
        if not gone:
            return None
        return frozenset((i, side) for i in range(len(found)) for side in (0, 1)) - gone

    return frozenset(
        (i, side) for i, (p, r, halves, _) in enumerate(found) for side in (0, 1)
        if split(halves, side)
        or ((shown(p) or r >= params.continuation_ratio) and not split(halves, 1 - side))
    )


def strip_support(support: np.ndarray | None, axis: int, lo: float, hi: float,
                   across: tuple[float, float]) -> float:
    """Mean of ``support`` [H, W] over a border strip: [lo, hi) along ``axis`` (0: x), ``across`` on the
    other axis (the other family's outer bars); 1 without a support mask. Along the strip, a gap with the
    surface on both sides counts as surface: a coarse mesh has holes (glass is hard to reconstruct), and
    what lies beyond a facade's end (the sky, the ground) leaves no surface on the strip's far side."""
    if support is None:
        return 1.0
    a0, a1 = int(max(0, np.floor(lo))), int(max(0, np.ceil(hi)))
    b0, b1 = int(max(0, np.floor(across[0]))), int(max(0, np.ceil(across[1])))
    block = support[b0:b1, a0:a1] if axis == 0 else support[a0:a1, b0:b1].T
    if not block.size:
        return 0.0
    # block [along the strip, across it]: each line across keeps what lies between its first and last
    # surface pixel along the strip
    filled = np.maximum.accumulate(block, axis=0) & np.maximum.accumulate(block[::-1], axis=0)[::-1]
    return float(filled.mean())


@dataclass(frozen=True)
class Opening:
    """One opening across a family's bars: its low and high edge lines, the indices of the bars bounding
    it (None: the image border), and for a strip cut by the border the sides of the bars of the other
    family that continue into it (None: all of them; ``continues``)."""

    low: EdgeLine
    high: EdgeLine
    bounds: tuple[int | None, int | None]
    cut: bool = False
    continuing: frozenset[tuple[int, int]] | None = None

    def admits(self, bounds: tuple[int | None, int | None]) -> bool:
        """Does the opening of the other family bounded by the bars ``bounds`` (low, high) go on into this
        one? Each bar by its side facing that opening: the low bar's high side, the high bar's low side."""
        return self.continuing is None or all(
            b is None or (b, side) in self.continuing for b, side in zip(bounds, (1, 0), strict=True)
        )


def openings(
    bars: Bars, other: Bars, size: int, length: int, params: SegmentParams, min_partial_px: float,
    axis: int, support: np.ndarray | None = None, grid_ends: bool = True,
) -> list[Opening]:
    """Openings across one family's bars (``axis`` 0: mullions), low to high. ``grid_ends``: a border strip
    that holds the grid's next bar's place whole, where none was found, ends the facade's panes there (on a
    plane; on a cylinder the surface turns away across the view, its far bars are foreshortened and
    blurred in the rectified view, and the run may stop short of bars that are there)."""
    e = bars.edges
    inside = (bars.fit.centres[0], bars.fit.centres[-1])
    across = (other.fit.centres[0], other.fit.centres[-1])
    out = []
    lo, top = e[0][0].a, e[-1][1].a
    # the grid's next bar one pitch beyond the outermost, where it would lie whole in the view: the run and
    # its end bays found none there, so the facade's panes do not go on across the whole strip
    fit = bars.fit
    w = float(np.median(fit.widths))
    next_inside = (grid_ends and fit.centres[0] - fit.pitch - w / 2 >= 1.0,
                   grid_ends and fit.centres[-1] + fit.pitch + w / 2 <= size - 1.0)
    if lo >= min_partial_px:
        going = continues(other, 0, lo, inside, strip_support(support, axis, 0, lo, across), params,
                           not next_inside[0], (0.0, lo - w))
        if going is None or going:
            out.append(Opening(_border(0, length), e[0][0], (None, 0), True, going))
    out += [Opening(e[k][1], e[k + 1][0], (k, k + 1)) for k in range(len(e) - 1)]
    if size - top >= min_partial_px:
        going = continues(other, top, size, inside, strip_support(support, axis, top, size, across), params,
                           not next_inside[1], (top + w, float(size)))
        if going is None or going:
            out.append(Opening(e[-1][1], _border(size, length), (len(e) - 1, None), True, going))
    return out


def _supported(line: EdgeLine, lo: float, hi: float) -> float:
    """Fraction of [lo, hi] (along the line, 1 px kept clear of the corners) where its frame bar is present
    or the edge itself (the bar's side facing the panel) is found at half its median strength or more: an
    object in front hides both, while a bar that shows its shaded side face beside an empty unit keeps the
    sharp edge where it meets the glass; 1 for the image border. Rows where the bar is clipped white away
    from its colour (``EdgeLine.unknown``) are left out: unknown, not absent."""
    if line.present is None:
        return 1.0
    i0, i1 = int(max(0, np.ceil(lo + 1))), int(max(0, np.floor(hi - 1)))
    present = line.present[i0:i1]
    found = line.strength[i0:i1]
    seen = ~np.isnan(present)
    if line.unknown is not None:
        seen &= ~line.unknown[i0:i1]
    if not seen.any():
        return 1.0
    ref = np.median(line.strength[line.strength > 0]) if (line.strength > 0).any() else np.inf
    return float(((present[seen] > 0) | (found[seen] >= 0.5 * ref)).mean())


def _edge_found(line: EdgeLine, lo: float, hi: float) -> float:
    """Fraction of [lo, hi] along ``line`` where its edge is found at half its median strength or more (0
    for the image border)."""
    i0, i1 = int(max(0, np.ceil(lo))), int(max(0, np.floor(hi)))
    if i1 <= i0 or not (line.strength > 0).any():
        return 0.0
    ref = np.median(line.strength[line.strength > 0])
    return float((line.strength[i0:i1] >= 0.5 * ref).mean())


def _half(line: EdgeLine) -> np.ndarray | None:
    """Where the half of a bar on ``line``'s side is present: on the bar its thin half belongs to where it
    was found thin and widened beside it, or found at one half's width with the bar's place beside it
    (``EdgeLine.half_at_place``), else on the bar as fitted."""
    return line.half_present if line.half_at_place is None else line.half_at_place


def _halves_told(kept: np.ndarray | None, gone: np.ndarray | None, lo: float,
                 hi: float) -> tuple[float, float, int]:
    """The fractions of the rows [lo, hi) where a bar shows either of its halves (``kept`` [L], ``gone``
    [L], ``EdgeLine.half_present``) that show each, and how many rows those are (NaN, NaN, 0 where there
    are none). Where it shows neither, neither unit beside it is there (the row above a unit's top, not
    installed on either side) or what lies in front hides both: that tells nothing of which side of the
    bar a unit stands."""
    if kept is None or gone is None:
        return np.nan, np.nan, 0
    i0, i1 = int(max(0, np.ceil(lo))), int(max(0, np.floor(hi)))
    a, b = kept[i0:i1], gone[i0:i1]
    told = ~np.isnan(a) & ~np.isnan(b) & ((a > 0) | (b > 0))
    if not told.any():
        return np.nan, np.nan, 0
    return float(a[told].mean()), float(b[told].mean()), int(told.sum())


def _not_a_pane(sides: tuple[tuple[EdgeLine, EdgeLine], tuple[EdgeLine, EdgeLine]],
                spans: tuple[tuple[float, float], tuple[float, float]], params: SegmentParams,
                far: tuple[EdgeLine | None, EdgeLine | None] | None = None,
                clear: tuple[float, float] = (0.0, 0.0), pitch: float = 0.0) -> bool:
    """Whether a cell (``sides``: its mullions' lines, its transoms' lines; ``spans``: its rows, its
    columns) is no pane: a bar bounding it, found thin and widened, shows the frames' colour over less than
    ``continuation_presence`` of the cell's side (``EdgeLine.frames_colour``), and neither bar of the other
    family beside it shows its edge facing the cell over more than 1 - ``continuation_presence`` of its
    side. The line the thin bar was found by is then an edge of what lies beyond the facade (the back edge
    of an empty unit's lit ceiling, where the unit's frame runs higher than its neighbours'), and nothing
    beside the cell shows glass against a frame: a clipped box beside the frames leaves their edges
    unknown, which is no sign of a pane either.

    Or, for a cell on a plane between two mullions, no border cutting its columns (``far``: its mullions'
    edges away from it, None for one whose halves are read neither on its frame, ``_halves_on_frame``, nor on
    the bar its thin half belongs to), a mullion beside it shows its half away from the cell and not its half
    facing it (``EdgeLine.half_present``: at least ``continuation_presence`` of the cell's rows where it
    shows either half against no more than 1 - ``continuation_presence`` of them, ``_halves_told``,
    ``clear`` px (top, bottom) clear of the transoms, where the two families' bars meet and their corners,
    not a unit's frame, part the halves; a mullion found thin and widened onto what lies beside it, or found
    at one half's width and kept, is read on the bar its thin half belongs to, ``EdgeLine.half_at_place``).
    A cell is read over its rows in the view where the mullion shows either half, where they are more than
    1 - ``continuation_presence`` of the ``pitch``: a pane's own half may be missing over that much of a
    whole cell (by a corner, a clip) without the rule firing, and a shorter part may be no more than such a
    stretch. Where it shows neither it tells nothing of the sides: a strip the border cuts beyond the top
    of its row's units, whose row above is not installed on either side of the bar, shows the bar over its
    units' rows alone. Nor is a column the border cuts: it may be a sliver beside its
    one mullion, which reads its half facing the sliver absent beside glass there. A unitised facade's bar is
    the frames of the two units beside it, and a pane's own unit frames it on every side: a mullion without
    the cell's half is beside a unit not installed.
    A facade whose glass is missing but whose frames stand (stick-built) keeps both halves and its cells. One
    mullion is enough: the other is as often found at the width of the one half that is there, both its halves
    on that unit's frame. The transoms are not read: on real photos their half facing a pane reads absent over
    most of the cell's width as well (benchmarks/RESULTS.md). Nor is a cylinder's cell: there the bars turn
    away across the view and show their side faces, shaded unlike their fronts, and a bar corrected for its
    parallax lies on the side face it shows, the half facing a pane with it."""
    rows = (spans[0][0] + clear[0], spans[0][1] - clear[1])
    for near, away in zip(sides[0] if far is not None else (), far or (), strict=True):
        if away is None:
            continue
        kept, gone, told = _halves_told(_half(away), _half(near), *rows)
        if told > (1.0 - params.continuation_presence) * pitch and _one_half(kept, gone, params):
            return True
    for k in (0, 1):
        shown = [_presence(line.frames_colour, None, *spans[1 - k]) for line in sides[1 - k]]
        if all(np.isnan(p) or p >= params.continuation_presence for p in shown):
            continue
        if all(_edge_found(line, *spans[k]) <= 1.0 - params.continuation_presence for line in sides[k]):
            return True
    return False


def build_panels(bars_v: Bars, bars_h: Bars, width: int, height: int, params: SegmentParams,
                 min_partial_px: float, support: np.ndarray | None = None,
                 grid_ends: bool = True) -> list[Panel]:
    """Panels of every opening of the grid (module docstring), rows counted from the bottom; ``support``
    [H, W] marks where the facade surface is (border strips without it hold no partial panel);
    ``grid_ends``: the surface is a plane (``openings``, ``_not_a_pane``)."""
    cols = openings(bars_v, bars_h, width, height, params, min_partial_px, 0, support, grid_ends)
    rows = openings(bars_h, bars_v, height, width, params, min_partial_px, 1, support, grid_ends)  # top down
    clear = float(np.median(bars_h.fit.widths))
    inside = 0.5 * (bars_h.fit.centres[0] + bars_h.fit.centres[-1])  # between the transoms
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
            read = _halves_on_frame(bars_v, 0.5 * (y0 + y1), inside)
            far = (None if cut_c or not grid_ends
                   else tuple(None if not read[k] and bars_v.edges[k][side].half_at_place is None
                              else bars_v.edges[k][side] for side, k in enumerate(col.bounds)))
            ends = tuple(0.0 if k is None else clear for k in row.bounds)
            if _not_a_pane(((left, right), (top, bottom)), ((y0, y1), (x0, x1)), params, far, ends,
                           bars_h.fit.pitch):
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
