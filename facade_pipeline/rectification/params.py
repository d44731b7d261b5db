"""The parameters of the ``rectify`` stage's library (``[rectify]``, ``[rectify.warp]``, ``[rectify.fit]``),
apart from the algorithms that use them (OpenCV, open3d), so that reading them costs no heavy import:
doit reads every stage's parameters to build its task list."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from facade_pipeline.config import Count, NonNeg, PosInt, Positive, Range


@dataclass(frozen=True)
class WarpParams:
    degree: PosInt
    """Total degree of the polynomial recorded for a cylinder, both directions (-); the paper uses 7."""


@dataclass(frozen=True)
class RectifyParams:
    metres_per_px: Positive | Literal["auto"]
    """Scale of the rectified image (m per px on the facade); "auto": the view's own ground sample distance
    on the surface (the median over the image of the square root of a pixel's footprint area)."""
    max_view_angle_deg: Annotated[float, Range(0.0, 90.0, high_open=True)]
    """A view whose surface normal (at the principal point's ray) is further than this (deg) from the
    optical axis sees the facade nearly edge-on: skipped."""
    max_size_factor: Positive
    """A rectified image of more than this many times the view's pixel count is refused: skipped (-)."""
    warp: WarpParams
    """Sampling of the view and the polynomial recorded for cylinders (``[rectify.warp]``)."""


@dataclass(frozen=True)
class SurfaceFitParams:
    """The robust surface fit. Its lengths are fractions of the frontal views' footprint (the median width
    a frontal view frames where its principal ray meets the coarse mesh, ``surface_map.frontal_footprint_m``),
    a length the data gives at any scale before any surface is fitted."""

    min_points: PosInt
    """Fewest points a fit accepts (-)."""
    min_spread: NonNeg
    """Points must spread at least this much (standard deviation, of the frontal views' footprint) in two
    directions: else on one line."""
    ransac_threshold: Positive
    """Distance (of the frontal views' footprint) within which a point supports a RANSAC plane: generous,
    it only drops far outliers."""
    max_normal_angle_deg: Annotated[float, Range(0.0, 90.0)]
    """A facade plane faces the camera: its normal within this angle (deg) of the direction to the camera
    (and, with ``normal_knn``, each fitted point's normal within it of the optical axis)."""
    inlier_scale: Positive
    """Scale of the soft-L1 loss (of the frontal views' footprint); points within 3x this of the surface
    are inliers."""
    normal_knn: Count
    """Neighbours of each point's normal estimate (PCA over its k nearest points, -). Given the camera's
    viewing direction, points whose normal is further than ``max_normal_angle_deg`` from it are left out
    before the fit (the ground before a facade seen from a low camera); 0: every point is kept. The same
    neighbours tell the points' separate parts (``cylinder.point_parts``): a fit across two is redone on
    the one holding most of its inliers."""
    max_tilt_deg: Annotated[float, Range(0.0, 90.0)]
    """A facade stands upright: a cylinder's axis within this angle (deg) of up, a plane's normal within it
    of horizontal; a fit beyond is not the facade (a floor, a table) and the view gets no surface."""
    min_radius_footprint: NonNeg
    """A cylinder's radius must be at least this many times the view's footprint (the width it frames at
    the surface's depth): a tighter one is a chair or a column in front of the camera (-)."""
    max_rms_footprint: Positive
    """The fit's RMS residual must be under this fraction of the footprint: a looser fit is of clutter (-)."""
    max_displacement_size: Positive
    """The map from a view to its rectified image, at the view's own scale and beyond a rotation, scale and
    shift of the whole view (``surface_map.warp_displacement_px``), may move no pixel further than this many
    times the view's larger side: a fit whose map does is not the surface the view frames (the view would
    see it nearly edge-on), and the view gets no surface (-)."""
