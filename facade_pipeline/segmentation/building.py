"""What one building's frontal views share, pooled over them: the frames' depth proud of the glass, the
bars' widths and the panel pitch per family ("x": the mullions, "y": the transoms), and which views
disagree with the building's grid. A view's own frames may not show these (a few bars, shaded side faces,
a shelf behind an empty unit taken for a transom); the building's views together do."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from facade_pipeline.errors import InputError
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from facade_pipeline.segmentation.frames import FrameBars
from facade_pipeline.segmentation.grid import STEP_PX, GridParams
from facade_pipeline.segmentation.parallax import PARALLAX_MIN_BARS, agreeing, pooled_depth_m

#: a view's pitch is another grid than the building's where it is further from it than the grid prior's
#: reach over one pitch: three standard deviations of a bar's place (``GridParams.sigma_frac``)
PITCH_REACH_SIGMAS = 3.0
#: a view's bars are another family than the building's where their median width is beyond this factor of
#: the building's either way: ``frames.widen_narrow_bars`` finds a bar under half of it again
WIDTH_RATIO = 2.0
#: the quantiles of the widths (per family) that the survey of every view found: where the lower one (the
#: bars that show little side face, near the cameras' feet: about the front face) is wider than the grid
#: model's ``max_bar``, the grid of every view accepts bars up to the upper one (a bar seen obliquely shows
#: its side face beside its front face); the few things the survey took for a bar (a shelf behind an empty
#: unit, a reflected edge beside a bar) lie beyond both
SURVEYED_BAR_QUANTILES = (0.25, 0.75)


def building_frame_parallax_m(
    found: list[FrameBars | None], max_slope: float,
) -> tuple[dict[str, float], dict[str, tuple[float, float]]]:
    """The depth (m) the mullions ("x") and the transoms ("y") stand proud of the glass: per family, the
    median of what the views' own parallax fits give (``FrameBars.frame_depths_m``); a family without any
    is left out. One facade's frames share it (mullion and transom profiles may differ), while a view's bar
    widths may not show it (side faces shaded like the glass on both sides of the camera's foot, as across a
    tight cylinder) or show it loosely. The views' exact fits (as many bars as unknowns: a few bars in a
    small view) join the median where they agree with one another (``parallax.agreeing``), and so does a
    family's one view's fit where no other view's fit gives it: its standard error is its own few bars'
    scatter, no more a building's figure than an exact fit's (three mullions widened alike by the glass
    clipped white beside them, at a brighter exposure, give a slope several of their errors above 0, and
    every view's corners would be moved by it). A family that
    no view's fit gives a depth for is fitted over the bars of every view at once
    (``parallax.pooled_depth_m``: close-ups of one unit show two bars a family each, too few for a view's
    own fit), within the largest slope a view's own fit accepts (``max_slope``). Returned with, for each
    family so fitted, its two sides' own depths (P < 0, P > 0): a side whose widths do not grow has the
    near edges of its bars displaced as well (``Parallax.with_slope``), which no view measured on its own.
    A family that neither gives a depth for while the other has one takes the other's: a facade's
    transoms butt into its mullions, their faces about one plane before the glass, so the other family's
    depth is near the truth where 0 (frames flush with the glass) is surely wrong; a family's bars show no
    depth where the side faces the views see of it are shaded like the glass (its widths do not grow) or
    where its few bars lie near the cameras' feet."""
    depths: dict[str, list[float]] = {}
    exact: dict[str, list[float]] = {}
    for f in found:
        for name, d in ({} if f is None else f.frame_depths_m()).items():
            depths.setdefault(name, []).append(d)
        for name, d in ({} if f is None else f.frame_depths_m(unjudged=True)).items():
            exact.setdefault(name, []).append(d)
    for name in [name for name, d in depths.items() if len(d) < 2]:
        exact.setdefault(name, []).extend(depths.pop(name))
    for name, d in exact.items():
        if agreeing(d):
            depths.setdefault(name, []).extend(d)
    out = {name: float(np.median(d)) for name, d in depths.items()}
    sides = {}
    for name, axis in (("x", 0), ("y", 1)):
        if name not in out:
            views = [(bars, f.parallax, f.metres_per_px) for f in found if f is not None
                     and f.parallax is not None and (bars := f.bars_v if axis == 0 else f.bars_h) is not None]
            d, sides_m = pooled_depth_m(views, axis, PARALLAX_MIN_BARS, max_slope)
            if d > 0.0:
                out[name], sides[name] = d, sides_m
    if len(out) == 1:  # one family measured: the other stands as proud (the docstring's last sentence)
        (name, d), = out.items()
        out["y" if name == "x" else "x"] = d
    return dict(sorted(out.items())), sides


def building_bar_width_m(found: list[FrameBars | None]) -> dict[str, float]:
    """The width (m) of the mullions ("x") and of the transoms ("y"): per family, the median over every
    bar of every view (``FrameBars.bar_widths_m``); a family without bars is left out."""
    widths: dict[str, list[float]] = {}
    for f in found:
        for name, w in ({} if f is None else f.bar_widths_m()).items():
            widths.setdefault(name, []).extend(w)
    return {name: float(np.median(w)) for name, w in sorted(widths.items()) if w}


def surveyed_bar_max_m(widths: list[dict[str, list[float]]], max_bar_m: float) -> dict[str, float]:
    """The widest bar (m) the grid is to accept across the mullions ("x") and the transoms ("y") where the
    frames are wider than the grid model's ``max_bar`` (``max_bar_m``, m): per family whose lower
    ``SURVEYED_BAR_QUANTILES`` of the widths of every bar the views' surveys found (each view's
    ``FrameBars.bar_widths_m`` of ``frames.survey_frames``, which seeks bars at sizes relative to the view
    alone) is wider than ``max_bar_m``, their upper quantile; the other families are left out. A grid
    that does not accept the frames' front faces finds every bar at its widest width, which hides the
    frames' parallax; where the front faces fit, the side faces seen beside them are the parallax's
    business (``parallax``, ``frames.widen_narrow_bars``), not the grid's."""
    pooled: dict[str, list[float]] = {}
    for view in widths:
        for name, w in view.items():
            pooled.setdefault(name, []).extend(w)
    low, high = SURVEYED_BAR_QUANTILES
    return {name: float(np.quantile(w, high)) for name, w in sorted(pooled.items())
            if w and float(np.quantile(w, low)) > max_bar_m}


def building_pitch_m(found: list[FrameBars | None]) -> dict[str, float]:
    """The panel pitch (m) across the mullions ("x") and the transoms ("y"): per family, the median of the
    views' grids (``FrameBars.pitches_m``); a family no view found is left out."""
    pitches: dict[str, list[float]] = {}
    for f in found:
        for name, p in ({} if f is None else f.pitches_m()).items():
            pitches.setdefault(name, []).append(p)
    return {name: float(np.median(p)) for name, p in sorted(pitches.items())}


def survey_unit_m(pitches: list[dict[str, float]]) -> float | None:
    """The building's panel pitch (m), the unit of segment_panels' lengths: the geometric mean of the
    mullions' ("x") and the transoms' ("y") pitch, each the median over the views' surveys
    (``frames.survey_frames``; ``FrameBars.pitches_m`` per view); the one family's where the other was
    found nowhere, None where neither was. A facade's pitch is the one length its views all show, whatever
    its scale and whatever they frame of it."""
    by_family: dict[str, list[float]] = {}
    for p in pitches:
        for name, v in p.items():
            by_family.setdefault(name, []).append(v)
    medians = [float(np.median(v)) for v in by_family.values()]
    return float(np.exp(np.mean(np.log(medians)))) if medians else None


def surveyed_pitch_m(layout: BuildingLayout, needed: bool = True) -> float:
    """The building's panel pitch (m) that segment_panels' survey measured (``survey_unit_m``, in its
    manifest): the unit of regularize_corners' and correct_mesh's lengths. Where it holds none (no view
    showed a grid, or no frontal view), NaN if not ``needed``, else ``InputError`` naming the manifest."""
    pitch = read_manifest(layout, "segment_panels").metrics.get("pitch_unit_m")
    if pitch is not None and np.isfinite(pitch) and pitch > 0:
        return float(pitch)
    if needed:
        raise InputError(layout.manifest("segment_panels"), "the building's panel pitch "
                         "(metrics.pitch_unit_m) that segment_panels' survey measured",
                         f"{pitch!r} (rerun segment_panels: `doit segment_panels`)")
    return float("nan")


def pitch_range_m(pitch_m: dict[str, float], grid: GridParams) -> dict[str, tuple[float, float]]:
    """The pitches (m, per family) that are the building's grid (``PITCH_REACH_SIGMAS``)."""
    reach = PITCH_REACH_SIGMAS * grid.sigma_frac
    return {name: (p * (1.0 - reach), p * (1.0 + reach)) for name, p in pitch_m.items()}


def within(pitch_m: dict[str, float], wanted: dict[str, tuple[float, float]], step_m: float) -> bool:
    """Is each family's pitch of ``wanted`` found (``pitch_m``) inside its range by more than a step of
    the pitch lattice (``step_m``)? A grid sought within a range whose best pitch is at one of its ends
    is the view's own grid held in by the range, not the building's found in the view."""
    return all(name in pitch_m and lo + step_m < pitch_m[name] < hi - step_m
               for name, (lo, hi) in wanted.items())


def retry_ranges(own_m: dict[str, float], wanted: dict[str, tuple[float, float]]
                 ) -> list[dict[str, tuple[float, float]]]:
    """The pitch ranges (m, per family) a view off the building's grid is sought again at, in order:
    both families at the building's pitch (``pitch_range_m``: ``wanted``), then each family whose own
    pitch (``own_m``; a family not found has none) lies outside it alone, the other at any pitch. A family
    may show the building's pitch where the other does not (a unit set off its neighbours' line, an empty
    unit's box taken for the transoms), and one wrong bar of a family spoils the other's search (on a
    plane the transoms must have the mullions' colour): with the mullions at the building's pitch, the
    transoms are found at their own."""
    off = [name for name, (lo, hi) in wanted.items() if not (name in own_m and lo <= own_m[name] <= hi)]
    return [dict(wanted)] + ([{name: wanted[name]} for name in off] if len(wanted) > 1 else [])


def sought_again(own_m: dict[str, float], wanted: dict[str, tuple[float, float]],
                 seek: Callable[[dict[str, tuple[float, float]]], FrameBars | None]
                 ) -> tuple[FrameBars | None, str]:
    """The grid a view off the building's grid takes, and what the building's grid gave (for the
    manifest): ``seek`` (the view's frames sought at pitch ranges, m per family) at each of
    ``retry_ranges``, in order, until both families are found, those sought at the building's pitch
    inside their range (``within``); None where no try gives that (the view keeps its own)."""
    for ranges in retry_ranges(own_m, wanted):
        again = seek(ranges)
        if again is None or len(again.pitches_m()) < 2 or not within(
                again.pitches_m(), ranges, STEP_PX * again.metres_per_px):
            continue
        return again, (": the building's grid taken" if len(ranges) == len(wanted) else
                       f": the building's pitch {next(iter(ranges))} taken, the other's own kept")
    return None, ": none at the building's pitch, own kept"


def disagreement(found: FrameBars | None, pitch_m: dict[str, float], width_m: dict[str, float],
                 grid: GridParams) -> dict[str, str]:
    """Why a view's grid is not the building's, by kind ("grid": none found, "pitch" or "width": a family's
    pitch or median bar width beyond the building's, ``pitch_range_m``, ``WIDTH_RATIO``); empty where it is
    the building's or the view was not segmented (None)."""
    if found is None:
        return {}
    own = found.pitches_m()
    if not own:
        return {"grid": "no grid found"}
    why = {}
    off = [f"{name} {own[name]:.4g} m, the building's {pitch_m[name]:.4g} m"
           for name, (lo, hi) in pitch_range_m(pitch_m, grid).items()
           if name in own and not lo <= own[name] <= hi]
    if off:
        why["pitch"] = "pitch " + ", ".join(off)
    widths = {name: float(np.median(w)) for name, w in found.bar_widths_m().items() if w}
    off = [f"{name} {widths[name]:.4g} m, the building's {w:.4g} m" for name, w in width_m.items()
           if name in widths and not 1.0 / WIDTH_RATIO <= widths[name] / w <= WIDTH_RATIO]
    if off:
        why["width"] = "bar width " + ", ".join(off)
    return why
