"""Glass panels of a (rectified) frontal view: LSD segments -> MAP grid of frame bars (``grid``) -> sub-pixel
bar edges (``edges``) -> panels with four corners, row and column indices, and completeness.

The steps: the frame bars (``frames``), corrected for their parallax (``parallax``), the panels between
them (``openings``); masks are the panels' quads (``quads``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from facade_pipeline.segmentation.frames import FrameBars, bar_colour, extent, find_frames, widen_narrow_bars
from facade_pipeline.segmentation.openings import Panel, build_panels
from facade_pipeline.segmentation.parallax import ParallaxField, correct_parallax, side_face, slope_of
from facade_pipeline.segmentation.params import SegmentParams


@dataclass
class Segmentation:
    facade_found: bool
    panels: list[Panel]
    metrics: dict = field(default_factory=dict)
    reason: str = ""
    """without panels: which evidence was missing"""


def segment_frames(
    found: FrameBars,
    params: SegmentParams,
    frame_depth_m: dict[str, float] | None = None,
    bar_width_m: dict[str, float] | None = None,
    frame_sides_m: dict[str, tuple[float, float]] | None = None,
    pitch_m: dict[str, float] | None = None,
) -> Segmentation:
    """The panels between the frame bars ``found`` (``find_frames``), corners in the given image's pixels.
    The bars are corrected for their parallax: a family with a depth in ``frame_depth_m`` ("x": mullions,
    "y": transoms; m proud of the glass, the building's, measured over all its views: a view's own widths
    may not show it) with the slope of that depth where the camera's distance to the surface is known,
    else with its own fit. A family with a width in ``bar_width_m`` (m, the building's) has its bars
    narrower than half of it found again at it, and a bar found as its side face alone (as wide as the
    parallax shows the side face, lit unlike the front face) joined to its front face
    (``widen_narrow_bars``). A family with its sides' depths
    in ``frame_sides_m`` (m, P < 0 and P > 0, the building's where no view measured its own) whose fit
    measured neither side takes them: which side's near edges are displaced. ``pitch_m``: the building's
    panel pitch (m) per family, which side of a thin bar it is widened to (``widen_narrow_bars``). On a side
    no parallax fit measured, a bar as wide as ``bar_width_m`` alone is its front face, its near edge moved
    too (``correct_parallax``)."""
    metrics = dict(found.metrics)
    bars_v, bars_h, m = found.bars_v, found.bars_h, found.metres_per_px
    if bars_v is None or bars_h is None:
        g, u = params.grid, found.unit_m
        missing = " nor ".join(
            name for name, key in (("vertical (mullions)", "mullions_found"),
                                   ("horizontal (transoms)", "transoms_found"))
            if not metrics.get(key)
        )  # fmt: skip
        return Segmentation(False, [], metrics, (
            f"no regular {missing} frame bars {g.min_bar * u:.3g}-{g.max_bar * u:.3g} m wide at a pitch of "
            f"{g.min_pitch * u:.3g}-{g.max_pitch * u:.3g} m (the image at {1000 * m:.3g} mm per working "
            "pixel)"
        ))  # fmt: skip
    (Ww, Hw), (qx, qy) = found.size, found.scale
    fits = dict(found.fits)
    for name, depth in (frame_depth_m or {}).items():
        k = 0.0 if found.parallax is None else slope_of(depth, found.parallax.distance_m)
        if name in fits and 0.0 < k <= params.parallax_max_slope:
            fits[name] = fits[name].with_slope(k, (frame_sides_m or {}).get(name))
    metrics.update({f"parallax_slope_{name}": round(f.k, 5) for name, f in fits.items()})

    def faces(name: str, axis: int):  # a bar's near edge and side face (``parallax.side_face``), if any
        if name not in fits or fits[name].k <= 0.0:
            return None
        return lambda low, high: side_face(found.parallax, axis, low, high, fits[name].k)

    width_px = {name: width / m for name, width in (bar_width_m or {}).items()}  # the building's bars
    for name, width in width_px.items():
        pitch = (pitch_m or {}).get(name)
        pitch = None if pitch is None else pitch / m
        if name == "x":
            bars_v, n = widen_narrow_bars(bars_v, found.grads[0], extent(bars_h.fit, Hw), width, params,
                                          faces("x", 0), pitch)
        else:
            # frames are one material, the mullions the reference (``frames.find_bars``' colour prior)
            colour = (bar_colour(found.grads[0], bars_v.fit, extent(bars_h.fit, Hw)) if found.planar
                      else None)
            bars_h, n = widen_narrow_bars(bars_h, found.grads[1], extent(bars_v.fit, Ww), width, params,
                                          faces("y", 1), pitch, colour)
        metrics[f"bars_widened_{name}"] = n
    if fits:
        bars_v = correct_parallax(bars_v, fits["x"], found.parallax, width_px.get("x"))
        bars_h = correct_parallax(bars_h, fits["y"], found.parallax, width_px.get("y"))
    panels = build_panels(bars_v, bars_h, Ww, Hw, params, params.min_partial * found.unit_m / m,
                           found.support, found.planar)
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
    unit_m: float,
    valid: np.ndarray | None = None,
    parallax: ParallaxField | None = None,
    support: np.ndarray | None = None,
    frame_depth_m: dict[str, float] | None = None,
    bar_width_m: dict[str, float] | None = None,
    planar: bool = True,
) -> Segmentation:
    """The panels of one image (``find_frames`` then ``segment_frames``, same arguments; ``unit_m``: the
    facade's panel pitch, m, the unit of the params' lengths)."""
    found = find_frames(image, params, metres_per_px, unit_m, valid, parallax, support, planar)
    return segment_frames(found, params, frame_depth_m, bar_width_m)
