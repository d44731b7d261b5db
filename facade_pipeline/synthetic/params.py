"""Parameters of the ``synthesize`` stage: one frozen dataclass per ``[synthesize.*]`` table.

Units are in the field names: metres (``_m``), degrees (``_deg``, configs only; code uses radians), pixels
(``_px``); colours are linear RGB triples in [0, 1]. The cross-field checks in ``SynthesizeParams`` raise
``ConfigError`` naming the key, e.g. ``synthesize.parts[1].radius_m``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal

from facade_pipeline.config import AnyInt, Count, Fraction, NonNeg, PosInt, Positive, Range, Real
from facade_pipeline.errors import ConfigError

Effect = Literal[
    "curved",  # cylindrical facade parts
    "near_field_reflection",  # glass reflects the ray-traced scene (one bounce); else only the sky lookup
    "fresnel",  # Schlick's F (Eq. 8); else F = F0
    "coarse_mesh_distortion",  # bumpy, holed glass in raw/coarse_mesh.ply, frames with small noise
    "coarse_points_glass_artifacts",  # missing points on glass and ghost (mirrored) points behind it
    "sensor_noise",  # Gaussian pixel noise in raw images
    "exposure_change",  # a per-view exposure gain in raw images
    "pose_noise",  # raw COLMAP poses perturbed (gt/ keeps the true ones)
    "exposure_spread",  # views' exposures spread over noise.exposure_spread_stops, highlights clipped
    "lens_distortion",  # frontal raw images through a radial lens (noise.lens_k1_k2); gt/ undistorted
    "unglazed_units",  # facade.unglazed_units: openings without glass onto a room lit through them
    "masts_and_cranes",  # poles and a tower crane in front of the facade, reflected across its bars
]
ALL_EFFECTS: tuple[str, ...] = Effect.__args__  # type: ignore[attr-defined]

RGB = tuple[Fraction, Fraction, Fraction]
SHELVES_MAX = 3  # the shelf heights a room behind an unglazed unit has (facade.SHELF_HEIGHTS) (-)
FieldOfView = Annotated[float, Range(1.0, 170.0)]
"""a camera's horizontal field of view (deg)"""
Elevation = Annotated[float, Range(-10.0, 90.0, high_open=True)]
"""a view's elevation above the horizontal (deg): from slightly below it up to, not including, the zenith"""
Oblique = Annotated[float, Range(0.0, 90.0, high_open=True)]
"""the largest turn of a view from the facade's normal, either sign (deg): 90 would be edge-on"""


@dataclass(frozen=True)
class FacadePart:
    """One facade part (``[[synthesize.parts]]``). Facade frame (``world_from_facade``): origin at the
    bottom centre of the glass surface, z up, y the outward normal there (toward the cameras), x = y cross z
    (so +x points to the LEFT of a viewer outside; columns are indexed left to right as that viewer sees
    them, i.e. toward -x)."""

    name: str
    """Unique name, used in panels.json."""
    kind: Literal["planar", "cylindrical"]
    """A plane, or a section of a vertical cylinder that is convex toward the cameras."""
    origin_m: tuple[Real, Real, Real]
    """World position of the facade frame origin (m)."""
    facing_deg: Real
    """Azimuth of the outward normal at the origin, counter-clockwise from world +x (deg)."""
    width_m: Positive
    """Length along the glass surface, frames included (m); the arc length for a cylindrical part."""
    height_m: Positive
    """Height, frames included (m)."""
    rows: PosInt
    """Panel rows (bottom to top)."""
    cols: PosInt
    """Panel columns (left to right seen from outside)."""
    radius_m: NonNeg = 0.0
    """Radius of the glass cylinder (m); cylindrical parts only, 0 for planar ones."""


@dataclass(frozen=True)
class FacadeStyle:
    """``[synthesize.facade]``: frames and materials shared by every part."""

    frame_width_m: Positive
    """Width of mullions and transoms (m)."""
    frame_depth_m: Positive
    """How far frames stand proud of the glass (m)."""
    frame_back_m: NonNeg
    """How far frames reach behind the glass plane (m)."""
    body_depth_m: Positive
    """Depth of the opaque building body behind the glass (m)."""
    curve_max_facet_deg: Positive
    """Largest angle (deg) a flat facet of a cylindrical part's glass, frames and body turns through: the
    simulated surface is a cylinder to within an eighth of this in normal on average (its flat facets
    are the renderer's normals and the truth's)."""
    glass_reflectivity: Fraction
    """refl of Eq. 7 on glass (0-1)."""
    glass_f0: RGB
    """Schlick F0 of glass (Eq. 8) (0-1)."""
    glass_tint: RGB
    """Transmission tint multiplying the interior colour (0-1)."""
    interior_color: RGB
    """Colour seen through the glass (diffuse D of Eq. 7) (0-1)."""
    interior_variation: Fraction
    """Relative per-panel brightness variation of the interior (0-1)."""
    frame_color: RGB
    """Albedo of frames (0-1)."""
    wall_color: RGB
    """Albedo of the building body (0-1)."""
    unglazed_units: tuple[tuple[Count, Count, Count], ...]
    """(part index, row, col) of units without glass ("unglazed_units"): the opening shows a room."""
    room_depth_m: Positive
    """Depth of the room behind an unglazed unit ("unglazed_units") (m)."""
    room_albedo: tuple[Fraction, Fraction]
    """Range of the albedo of a room's walls, drawn per unglazed unit ("unglazed_units"): dark concrete
    at the low end, light paint at the high end (0-1)."""
    room_texture: tuple[Fraction, Fraction]
    """Range of a room's texture, drawn per unglazed unit ("unglazed_units"): 0 a plain painted box with
    bare boards for shelves and a plain cloth, 1 mottled concrete, shelves of things of mixed colours and
    a printed cloth (0-1)."""
    room_shelves: tuple[Count, Count]
    """Range of the number of shelves along a room's back wall, drawn per unglazed unit ("unglazed_units"),
    uniform over the whole numbers in it, at as many of the three shelf heights drawn at random (0-3)."""
    room_cloth: tuple[Fraction, Fraction]
    """Chances (front, back), drawn per unglazed unit ("unglazed_units"), that a room's cloth hangs in its
    front half, folded, from the ceiling over part of its width, or at its back wall, from the floor over
    most of its width; no cloth the rest of the time (front + back <= 1)."""
    room_posts: tuple[Count, Count]
    """Range of the number of posts standing from a room's floor to its ceiling, drawn per unglazed unit
    ("unglazed_units"), uniform over the whole numbers in it, each at a point drawn over the room's
    floor (-)."""


@dataclass(frozen=True)
class EnvironmentParams:
    """``[synthesize.environment]``: the near field in front of the facade, in the site frame (origin at the
    mean of the parts' origins on the ground, y the mean outward normal, z up)."""

    ground_half_size_m: Positive
    """Half the side of the square ground (m)."""
    ground_tile_m: Positive
    """Side of the ground mesh tiles (m)."""
    grass_color: RGB
    paving_color: RGB
    road_color: RGB
    marking_color: RGB
    court_color: RGB
    road_distance_m: Real
    """Site y of the road's centre line (m); the road runs parallel to the facade."""
    road_width_m: NonNeg
    plaza_depth_m: NonNeg
    """Paved strip in front of the facade, site y in [0, this] (m)."""
    court_center_m: tuple[Real, Real]
    """Site (x, y) of the sports court centre (m)."""
    court_size_m: tuple[NonNeg, NonNeg]
    """Court length along site x and width along site y (m)."""
    fountain_center_m: tuple[Real, Real]
    """Site (x, y) of the fountain (m)."""
    fountain_radius_m: Positive
    fountain_height_m: Positive
    """Height of the basin wall (m)."""
    stone_color: RGB
    water_color: RGB
    building_count: Count
    building_distance_m: tuple[Positive, Positive]
    """Site y range of the nearby buildings' front faces (m)."""
    building_width_m: tuple[Positive, Positive]
    building_depth_m: tuple[Positive, Positive]
    building_height_m: tuple[Positive, Positive]
    building_colors: tuple[RGB, ...]
    """Wall colours the buildings pick from (0-1)."""
    window_color: RGB
    tree_count: Count
    tree_distance_m: tuple[Positive, Positive]
    """Site y range of tree trunks (m)."""
    tree_height_m: tuple[Positive, Positive]
    trunk_color: RGB
    crown_color: RGB
    sky_zenith_color: RGB
    sky_horizon_color: RGB
    sun_azimuth_deg: Real
    """Counter-clockwise from world +x (deg)."""
    sun_elevation_deg: Annotated[float, Range(-90.0, 90.0)]
    sun_disc_deg: Annotated[float, Range(0.0, 90.0)]
    """Angular radius of the sun disc in the sky (deg)."""
    sun_color: tuple[NonNeg, NonNeg, NonNeg]
    """Radiance of the sun disc (may exceed 1: it saturates)."""
    sun_intensity: NonNeg
    """Lambert term scale of direct sun light (-)."""
    ambient: NonNeg
    """Ambient light level (-)."""
    pole_count: Count
    """Poles (lamp posts, masts) in front of the facade ("masts_and_cranes")."""
    pole_distance_m: tuple[Positive, Positive]
    """Site y range of the poles (m)."""
    pole_height_m: Positive
    crane_distance_m: Positive
    """Site y of a tower crane's mast ("masts_and_cranes") (m)."""
    crane_height_m: Positive
    """Height of the crane's jib (m); the jib reaches as far across site x."""
    mast_color: RGB
    crane_color: RGB

    def __post_init__(self) -> None:
        for key in ("building_width_m", "building_depth_m"):
            low, high = getattr(self, key)
            if low > high:
                _fail(f"environment.{key}", "(low, high) with low <= high", (low, high))


@dataclass(frozen=True)
class CameraParams:
    """``[synthesize.cameras]``: UAV views (raw/images) and close-range frontal views (raw/frontal)."""

    width_px: PosInt
    height_px: PosInt
    fov_deg: FieldOfView
    """Horizontal field of view of UAV views (deg)."""
    uav_count: PosInt
    uav_distance_m: tuple[Positive, Positive]
    """Range of camera-to-target distances (m)."""
    uav_elevation_deg: tuple[Elevation, Elevation]
    """Range of view elevations above the facade's horizontal (deg)."""
    uav_azimuth_deg: Annotated[float, Range(0.0, 90.0, high_open=True)]
    """Largest azimuth from the facade normal (deg); azimuths are spread over +- this (near 90: grazing)."""
    uav_min_height_m: NonNeg
    """Lowest camera height above the ground (m)."""
    uav_max_tries: PosInt
    """Random draws per view before giving up on an unoccluded one."""
    frontal_fov_deg: FieldOfView
    frontal_distance_m: Positive
    """Distance of frontal views from the glass along its local normal (m)."""
    frontal_margin_px: NonNeg
    """Every panel of a frontal view's block lies this far inside its image (px)."""
    frontal_oblique_deg: tuple[Oblique, Oblique]
    """Largest yaw (about the up axis) and pitch (about the facade's horizontal) of frontal views from the
    local normal (deg): view k turns by a fixed low-discrepancy fraction of each, either sign, about the
    centre of its block (0, 0: fronto-parallel). Oblique views may cut the block's panels at the border."""
    frontal_width_px: Count
    """Width of frontal views (px); 0: ``width_px`` (the UAV views')."""
    frontal_height_px: Count
    """Height of frontal views (px); 0: ``height_px``."""

    @property
    def frontal_size_px(self) -> tuple[int, int]:
        """(width, height) of frontal views (px)."""
        return (self.frontal_width_px or self.width_px, self.frontal_height_px or self.height_px)


@dataclass(frozen=True)
class RenderParams:
    """``[synthesize.render]``."""

    supersample: PosInt
    """Sub-pixel grid per pixel side (1: one ray through each pixel centre)."""
    chunk_rays: PosInt
    """Rays cast per batch: bounds memory by this, not by image or view count."""
    ray_offset_m: Positive
    """Offset of secondary ray origins along the normal, against self-intersection (m)."""
    frontal_supersample: Count
    """The same for frontal views; 0: ``supersample``. An odd grid has a ray through the pixel centre, as
    the truth maps do, so a panel edge crossing a pixel is on the same side of its centre in both."""

    def supersample_for(self, kind: str) -> int:
        """Sub-pixel grid per pixel side of a view of ``kind`` ("uav" or "frontal")."""
        return (self.frontal_supersample or self.supersample) if kind == "frontal" else self.supersample


@dataclass(frozen=True)
class CoarseParams:
    """``[synthesize.coarse]``: the photogrammetry-like raw/coarse_mesh.ply and raw/coarse_points.ply."""

    mesh_resolution_m: Positive
    """Grid step of the coarse mesh over each part (m)."""
    glass_bump_m: NonNeg
    """Largest deviation of glass from the truth along the normal (m) (coarse_mesh_distortion)."""
    glass_bump_scale_m: Positive
    """Feature size of the glass bumps (m)."""
    glass_hole_fraction: Fraction
    """Fraction of glass triangles removed as holes (0-1) (coarse_mesh_distortion)."""
    frame_noise_m: NonNeg
    """Largest deviation of frames from the truth along the normal (m) (coarse_mesh_distortion)."""
    points_per_m2: Positive
    """Facade point density of the coarse point cloud (1/m^2)."""
    glass_points_keep_fraction: Fraction
    """Fraction of glass points kept (0-1) (coarse_points_glass_artifacts)."""
    ghost_points_per_part: Count
    """Mirrored environment points put behind each part's glass (coarse_points_glass_artifacts)."""
    environment_points: Count
    """Points sampled on the environment near the facade."""
    environment_radius_m: Positive
    """Environment points lie within this distance of the site origin (m)."""
    sparse_points: Count
    """Points of the coarse cloud copied into the raw COLMAP model."""


@dataclass(frozen=True)
class NoiseParams:
    """``[synthesize.noise]``: amounts of the image and pose effects."""

    pose_rotation_deg: NonNeg
    """Std of the raw pose rotation error (deg) (pose_noise)."""
    pose_translation_m: NonNeg
    """Std of the raw camera centre error per axis (m) (pose_noise)."""
    sensor_std: NonNeg
    """Std of Gaussian pixel noise on [0, 1] intensities (sensor_noise)."""
    exposure_stops: NonNeg
    """Per-view exposure gain 2^u with u uniform in +- this (exposure_change)."""
    exposure_spread_stops: tuple[Real, Real]
    """Range of the views' exposures (stops), spread evenly over the views of each kind (exposure_spread);
    above 0 the glass's reflected sky and the frames clip."""
    lens_k1_k2: tuple[Real, Real]
    """Radial distortion of frontal views (OpenCV k1, k2 of the normalised radius) (lens_distortion)."""


@dataclass(frozen=True)
class SynthesizeParams:
    """``[synthesize]``: a synthetic building. Only the declared ``effects`` are simulated."""

    seed: AnyInt
    """Same seed, same parameters -> bit-identical files."""
    effects: tuple[Effect, ...]
    parts: tuple[FacadePart, ...]
    facade: FacadeStyle
    environment: EnvironmentParams
    cameras: CameraParams
    render: RenderParams
    coarse: CoarseParams
    noise: NoiseParams

    def __post_init__(self) -> None:
        _check_effects(self)
        for i, part in enumerate(self.parts):
            _check_part(part, i, self.facade, "curved" in self.effects)
        _check_ranges(self)

    def has(self, effect: str) -> bool:
        """Whether ``effect`` is declared."""
        assert effect in ALL_EFFECTS, effect
        return effect in self.effects


def _fail(key: str, expected: str, found: object) -> None:
    raise ConfigError(None, f"'synthesize.{key}' {expected}", repr(found))


def _check_effects(p: SynthesizeParams) -> None:
    if len(set(p.effects)) != len(p.effects):
        _fail("effects", "without repeated effects", list(p.effects))
    if not p.parts:
        _fail("parts", "at least one facade part", [])
    names = [part.name for part in p.parts]
    if len(set(names)) != len(names):
        _fail("parts", "parts with unique names", names)
    curved = any(part.kind == "cylindrical" for part in p.parts)
    if curved and "curved" not in p.effects:
        _fail("effects", "to declare 'curved' (a part is cylindrical)", list(p.effects))
    if "curved" in p.effects and not curved:
        _fail("effects", "to declare 'curved' only with a cylindrical part", list(p.effects))
    units = p.facade.unglazed_units
    if units and "unglazed_units" not in p.effects:
        _fail("facade.unglazed_units", "empty unless effect 'unglazed_units' is declared", list(units))
    for k, (part, row, col) in enumerate(units):
        if part >= len(p.parts) or row >= p.parts[part].rows or col >= p.parts[part].cols:
            _fail(f"facade.unglazed_units[{k}]", "(part index, row, col) of a unit of the facade",
                  [part, row, col])
    if "unglazed_units" in p.effects:
        if not units:
            _fail("facade.unglazed_units", "at least one (part, row, col) with effect 'unglazed_units'", [])
        for key in ("room_albedo", "room_texture"):
            low, high = getattr(p.facade, key)
            if not 0.0 <= low <= high <= 1.0:
                _fail(f"facade.{key}", "(low, high) with 0 <= low <= high <= 1", (low, high))
        low, high = p.facade.room_shelves
        if not low <= high <= SHELVES_MAX:
            _fail("facade.room_shelves", f"(low, high) with 0 <= low <= high <= {SHELVES_MAX}", (low, high))
        if sum(p.facade.room_cloth) > 1.0:
            _fail("facade.room_cloth", "(front, back) chances with front + back <= 1", p.facade.room_cloth)
        low, high = p.facade.room_posts
        if not low <= high:
            _fail("facade.room_posts", "(low, high) with 0 <= low <= high", (low, high))
        if p.facade.room_depth_m > p.facade.body_depth_m - p.facade.frame_back_m:
            _fail("facade.room_depth_m", "within the body (body_depth_m - frame_back_m)",
                  p.facade.room_depth_m)


def _check_part(part: FacadePart, i: int, style: FacadeStyle, curved_declared: bool) -> None:
    key = f"parts[{i}]"
    if part.rows < 1 or part.cols < 1:
        _fail(f"{key}.rows", "and cols >= 1", (part.rows, part.cols))
    if part.width_m <= 0 or part.height_m <= 0:
        _fail(f"{key}.width_m", "and height_m > 0", (part.width_m, part.height_m))
    fw = style.frame_width_m
    if (part.width_m - fw) / part.cols <= 2 * fw or (part.height_m - fw) / part.rows <= 2 * fw:
        _fail(
            f"{key}.cols",
            "few enough panels for a glass opening wider than the frames",
            (part.rows, part.cols),
        )
    if part.kind == "planar" and part.radius_m != 0.0:
        _fail(f"{key}.radius_m", "0 for a planar part", part.radius_m)
    if part.kind == "cylindrical":
        if part.radius_m <= style.body_depth_m:
            _fail(f"{key}.radius_m", f"> facade.body_depth_m ({style.body_depth_m})", part.radius_m)
        if part.width_m / part.radius_m >= math.pi:
            _fail(f"{key}.width_m", f"an arc below 180 deg at radius {part.radius_m}", part.width_m)


def _check_ranges(p: SynthesizeParams) -> None:
    unit = {
        "facade.glass_reflectivity": p.facade.glass_reflectivity,
        "facade.interior_variation": p.facade.interior_variation,
        "coarse.glass_hole_fraction": p.coarse.glass_hole_fraction,
        "coarse.glass_points_keep_fraction": p.coarse.glass_points_keep_fraction,
    }
    for key, v in unit.items():
        if not 0.0 <= v <= 1.0:
            _fail(key, "in [0, 1]", v)
    positive = {
        "facade.frame_width_m": p.facade.frame_width_m,
        "facade.frame_depth_m": p.facade.frame_depth_m,
        "facade.body_depth_m": p.facade.body_depth_m,
        "cameras.width_px": p.cameras.width_px,
        "cameras.height_px": p.cameras.height_px,
        "cameras.frontal_distance_m": p.cameras.frontal_distance_m,
        "render.supersample": p.render.supersample,
        "render.chunk_rays": p.render.chunk_rays,
        "render.ray_offset_m": p.render.ray_offset_m,
        "coarse.mesh_resolution_m": p.coarse.mesh_resolution_m,
        "environment.ground_tile_m": p.environment.ground_tile_m,
        "facade.curve_max_facet_deg": p.facade.curve_max_facet_deg,
    }
    for key, v in positive.items():
        if v <= 0:
            _fail(key, "> 0", v)
    for key, v in {
        "cameras.frontal_width_px": p.cameras.frontal_width_px,
        "cameras.frontal_height_px": p.cameras.frontal_height_px,
        "render.frontal_supersample": p.render.frontal_supersample,
    }.items():
        if v < 0:
            _fail(key, ">= 0 (0: as the UAV views)", v)
    for key, v in {
        "cameras.fov_deg": p.cameras.fov_deg,
        "cameras.frontal_fov_deg": p.cameras.frontal_fov_deg,
    }.items():
        if not 1.0 <= v <= 170.0:
            _fail(key, "in [1, 170] deg", v)
    if not 0.0 <= p.cameras.uav_azimuth_deg < 90.0:
        _fail("cameras.uav_azimuth_deg", "in [0, 90) deg", p.cameras.uav_azimuth_deg)
    lo, hi = p.cameras.uav_elevation_deg
    if not -10.0 <= lo <= hi < 90.0:
        _fail("cameras.uav_elevation_deg", "(low, high) with -10 <= low <= high < 90", (lo, hi))
    for key, (a, b) in {
        "cameras.uav_distance_m": p.cameras.uav_distance_m,
        "environment.building_distance_m": p.environment.building_distance_m,
        "environment.tree_distance_m": p.environment.tree_distance_m,
        "environment.tree_height_m": p.environment.tree_height_m,
        "environment.building_height_m": p.environment.building_height_m,
    }.items():
        if not 0.0 < a <= b:
            _fail(key, "(low, high) with 0 < low <= high", (a, b))
    if p.environment.building_count > 0 and not p.environment.building_colors:
        _fail("environment.building_colors", "at least one colour", [])
    if p.environment.fountain_height_m <= 0 or p.environment.fountain_radius_m <= 0:
        _fail(
            "environment.fountain_radius_m",
            "and fountain_height_m > 0",
            (p.environment.fountain_radius_m, p.environment.fountain_height_m),
        )
