"""The parameters of the ``regularize_corners`` stage (``[regularize_corners]``), apart from the
reconstruction that uses them (open3d's ray casting), so that reading them costs no heavy import: doit
reads every stage's parameters to build its task list."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from facade_pipeline.config import Degrees, Fraction, NonNeg, PosInt, Positive, Range


@dataclass(frozen=True)
class RegularizeConfig:
    """Parameters of the 3D panel reconstruction (the ``[regularize_corners]`` config section). Its lengths
    are fractions of the building's panel pitch (``unit_m``), read in metres through the ``*_m``
    properties."""

    grazing_max_deg: Annotated[float, Range(0.0, 90.0)]
    """A corner ray hitting the mesh more than this angle (deg) from its normal is rejected."""
    ghost_max: Positive
    """A hit farther than this (of the pitch) from the part's fitted surface is ghost geometry: rejected."""
    part_max_angle_deg: Degrees
    """Two neighbouring panels belong to the same part when their normals differ by less than this (deg)."""
    planar_max_sagitta: NonNeg
    """A part is cylindrical when its fitted circle bulges more than this (of the pitch) over its width."""
    outlier_floor: NonNeg
    """A corner within this distance (of the pitch) of its row or column line (or of its part's surface)
    is never an outlier, however small the robust sigma (``OUTLIER_MAD_FACTOR``)."""
    depth_window: Positive
    """Evidence within this distance (of the pitch) of the corner surface is searched for the glass."""
    depth_bandwidth: Positive
    """Kernel width (of the pitch) of the coarse-point density along the normal."""
    depth_min_points: PosInt
    """Fewer coarse points than this in a part's panels falls back to the coarse mesh median (-)."""
    min_visible_fraction: Fraction
    """A quad whose corners span less than this fraction of a panel's width and of its height (a speck
    in the mask, a panel's corner at the image's corner) is left out of the grid (0-1)."""
    require_panels: bool
    """Frontal views that yield no panel at all stop the run (false: go on without mesh correction)."""
    unit_m: Positive | None = None
    """The building's panel pitch (m), the unit of the lengths above: no config sets it, the stage does,
    to what segment_panels' survey measured (``segmentation.building.surveyed_pitch_m``)."""

    def _unit(self) -> float:
        # NaN where no pitch was measured: a building without panels never reads a length
        return float("nan") if self.unit_m is None else self.unit_m

    @property
    def ghost_max_m(self) -> float:
        return self.ghost_max * self._unit()

    @property
    def planar_max_sagitta_m(self) -> float:
        return self.planar_max_sagitta * self._unit()

    @property
    def outlier_floor_m(self) -> float:
        return self.outlier_floor * self._unit()

    @property
    def depth_window_m(self) -> float:
        return self.depth_window * self._unit()

    @property
    def depth_bandwidth_m(self) -> float:
        return self.depth_bandwidth * self._unit()
