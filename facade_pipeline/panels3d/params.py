"""The parameters of the ``regularize_corners`` stage (``[regularize_corners]``), apart from the
reconstruction that uses them (open3d's ray casting), so that reading them costs no heavy import: doit
reads every stage's parameters to build its task list."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from facade_pipeline.config import Degrees, Fraction, NonNeg, PosInt, Positive, Range


@dataclass(frozen=True)
class RegularizeConfig:
    """Parameters of the 3D panel reconstruction (the ``[regularize_corners]`` config section)."""

    grazing_max_deg: Annotated[float, Range(0.0, 90.0)]
    """A corner ray hitting the mesh more than this angle (deg) from its normal is rejected."""
    ghost_max_m: Positive
    """A hit farther than this (m) from the part's fitted surface is ghost geometry and rejected."""
    part_max_angle_deg: Degrees
    """Two neighbouring panels belong to the same part when their normals differ by less than this (deg)."""
    planar_max_sagitta_m: NonNeg
    """A part is cylindrical when its fitted circle bulges more than this (m) over the part's width."""
    outlier_floor_m: NonNeg
    """A corner within this distance (m) of its row or column line (or of its part's surface) is never an
    outlier, however small the robust sigma (``OUTLIER_MAD_FACTOR``)."""
    depth_window_m: Positive
    """Evidence within this distance (m) of the corner surface is searched for the glass."""
    depth_bandwidth_m: Positive
    """Kernel width (m) of the coarse-point density along the normal."""
    depth_min_points: PosInt
    """Fewer coarse points than this in a part's panels falls back to the coarse mesh median (-)."""
    min_visible_fraction: Fraction
    """A quad whose corners span less than this fraction of a panel's width and of its height (a speck
    in the mask, a panel's corner at the image's corner) is left out of the grid (0-1)."""
    require_panels: bool
    """Frontal views that yield no panel at all stop the run (false: go on without mesh correction)."""
