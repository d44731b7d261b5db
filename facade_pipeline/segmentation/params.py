"""The parameters of the ``segment_panels`` stage (``[segment_panels]``), apart from the segmentation that
uses them (OpenCV), so that reading them costs no heavy import: doit reads every stage's parameters to
build its task list."""

from __future__ import annotations

from dataclasses import dataclass

from facade_pipeline.config import Fraction, NonNeg, PosInt, Positive
from facade_pipeline.segmentation.grid import GridParams


@dataclass(frozen=True)
class SegmentParams:
    upsample: PosInt
    """LSD runs on the image upsampled by this factor (-)."""
    grid: GridParams
    """The MAP grid model (``[segment_panels.grid]``); its lengths, and this table's, are fractions of the
    building's panel pitch, which the survey measures first (``frames.survey_frames``)."""
    min_partial: NonNeg
    """A border strip narrower than this (-, of the building's pitch) holds no partial panel."""
    work_bar_px: Positive
    """The image is segmented at a scale where the narrowest bar (``grid.min_bar``) spans at least this
    many px, downsampled to it when finer (the grid search's cost grows with the pixel count, its precision
    is a fraction of a pixel at any scale) (px)."""
    continuation_ratio: Fraction
    """Bars continuing into a border strip with this fraction of their inside strength: partial panels (-)."""
    continuation_presence: Fraction
    """... or whose frame colour is present over this fraction of the strip (median over the bars) (-)."""
    surface_tolerance: Positive
    """The facade surface is there where the view's ray meets the coarse mesh within this distance (-, of
    the building's pitch) of the rectified surface: border strips beyond the facade's end hold no partial
    panel."""
    frame_colour_tol: NonNeg
    """A frame bar is present where its centre line is within this RGB distance (0-1) of its median colour."""
    mirror_max_score: Positive
    """A unit whose median score over its views (summed absolute log colour ratio to what the other views'
    panes mirror along the same reflected rays) is above this is no pane (``segmentation.mirror``) (-)."""
    parallax_max_slope: NonNeg
    """Largest frame parallax d / Z accepted (frames d proud of glass, their front Z away); 0: none."""
