"""One config system: ``configs/default.toml`` holds every parameter of every stage; for a building with
``[building] kind = "synthetic"`` only, ``configs/synthetic.toml`` (the simulator's ``[synthesize]`` and the
metrics against its truth) is merged over it; a building's ``configs/buildings/<name>.toml`` overrides
either, and the building's tables for the chosen compute budget (``BUDGETS``: ``$FACADE_BUDGET``) override
the rest of its file. Each stage reads its section into one frozen dataclass. An unknown key, a missing key
or a wrong type is a ``ConfigError`` naming the key and the file; so is a simulator key in a real
building's file, and an old key (``RENAMED``), which names what replaced it.

The ``[run]`` table (``RunSettings``: device, rasterizer backend, logging, checkpoints, overlay size) says
how the stages run, never what they compute. No stage's parameters hold it, so doit's ``config_changed`` and
train_gs's checkpoint fingerprint, which read the parameters, never see it: changing it reruns nothing.

One source of defaults: the TOML files. The params dataclasses declare types and ranges, not values; the
only field defaults are ``None`` for settings that exist for synthetic buildings alone (absent for a real
one) and a planar part's ``radius_m = 0`` in an array of parts (arrays replace the default whole). Numbers
no building moves are named constants beside their use, each saying where its value comes from.

Merging: tables merge key by key; any other value (arrays of tables included) replaces the default whole.

Every number is declared with its allowed range beside it, as one of the aliases below (``PosInt``,
``Fraction``, ...) or ``Annotated[float, Range(...)]``; a value outside it is a ``ConfigError`` naming the
key, the file and the range. TOML's ``nan`` is refused everywhere, ``inf`` where the range does not allow it.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar, get_args, get_origin

from facade_pipeline.errors import ConfigError

CONFIG_DIR_ENV = "FACADE_CONFIG_DIR"
BUDGET_ENV = "FACADE_BUDGET"
BUDGETS = ("cpu", "gpu")
"""The compute budgets a building's file may tune for. Its ``[budget.<name>]`` tables hold keys for one
budget alone (demo's CPU budget: patches, fewer steps, a smaller MLP), merged over the file's other tables
when ``$FACADE_BUDGET`` names it ("cpu" when unset). A budget is a choice of what is computed, so unlike
``[run]`` it reaches the stages' parameters: switching it reruns the stages whose parameters it moves."""
T = TypeVar("T")


@dataclass(frozen=True)
class Range:
    """The allowed values of a number: ``low`` to ``high`` (None: unbounded), inclusive unless ``*_open``."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    infinite: bool = False
    """``inf`` (beyond ``high``) is allowed: it switches a limit off"""

    def __contains__(self, value: float) -> bool:
        if math.isnan(value) or (math.isinf(value) and not (self.infinite and value > 0)):
            return False
        if math.isinf(value):
            return True
        if self.low is not None and (value < self.low or (self.low_open and value == self.low)):
            return False
        return not (self.high is not None and (value > self.high or (self.high_open and value == self.high)))

    def __str__(self) -> str:
        if self.low is None and self.high is None:
            return "a finite number"
        lo = "" if self.low is None else ("> " if self.low_open else ">= ") + f"{self.low:g}"
        hi = "" if self.high is None else ("< " if self.high_open else "<= ") + f"{self.high:g}"
        text = " and ".join(x for x in (lo, hi) if x)
        return text + (" (or inf)" if self.infinite else "")


# The ranges most parameters need. A number with another range is ``Annotated[float, Range(...)]``.
PosInt = Annotated[int, Range(1)]
"""a count or size that must be at least 1 (iterations, pixels, samples)"""
Count = Annotated[int, Range(0)]
"""a count where 0 is meaningful (0 iterations between events: never)"""
AnyInt = Annotated[int, Range()]
"""an integer without bounds (a seed)"""
Positive = Annotated[float, Range(0.0, low_open=True)]
"""a length, scale, rate or tolerance that must be above 0"""
NonNeg = Annotated[float, Range(0.0)]
"""a weight, margin or threshold where 0 switches it off"""
Fraction = Annotated[float, Range(0.0, 1.0)]
"""a probability, ratio or share in [0, 1]"""
Real = Annotated[float, Range()]
"""a signed value (an offset, a log gain): any finite number"""
Degrees = Annotated[float, Range(0.0, 180.0)]
"""an angle between directions"""


def config_dir() -> Path:
    """``$FACADE_CONFIG_DIR`` or the ``configs/`` folder beside the package (the checkout)."""
    env = os.environ.get(CONFIG_DIR_ENV)
    return Path(env) if env else Path(__file__).resolve().parents[1] / "configs"


@dataclass(frozen=True)
class BuildingParams:
    """The ``[building]`` section: what kind of building this is."""

    kind: Literal["real", "synthetic"]
    """``synthetic`` buildings are made by the ``synthesize`` stage and have ground truth in gt/."""
    description: str
    """One line for people."""


#: top-level tables that only synthetic buildings have (configs/synthetic.toml): the simulator's
SYNTHETIC_TABLES = ("synthesize",)
SYNTHETIC_FILE = "synthetic.toml"
DEFAULT_FILE = "default.toml"


@dataclass(frozen=True)
class RunSettings:
    """The ``[run]`` table: how the stages run, never what they compute. No stage's parameters hold these,
    so doit's ``config_changed`` and train_gs's checkpoint fingerprint never see them: changing one reruns
    nothing and keeps a checkpoint (a run begun on the CPU resumes on a GPU)."""

    device: Literal["cpu", "cuda", "auto"]
    """where train_gs trains and evaluate renders (``auto``: CUDA when available)"""
    raster_backend: Literal["auto", "cpp", "torch", "gsplat"]
    """the rasterizer's implementation (``splatting.render_2dgs``), in training and in every render"""
    compile: bool
    """train_gs compiles a step's shading, losses and densification statistics (``training.compiling``)"""
    log_every: Count
    """iterations between train_gs's training-log lines (0: none)"""
    checkpoint_every: Count
    """iterations between train_gs's checkpoints (0: only at the end)"""
    overlay_scale: Positive
    """rectify's and segment_panels' overlay images are drawn this many times the view's size"""
    view_workers: Count
    """processes over which a stage's per-view loop runs (1: the stage's own; 0: one per core)"""


def default_run_settings(directory: Path | None = None) -> RunSettings:
    """``[run]`` of ``default.toml`` alone: what a stage runs with when no building says otherwise."""
    return default_params("run", RunSettings, directory)


@dataclass(frozen=True)
class BuildingConfig:
    """The merged configuration of one building, with the files it came from."""

    name: str
    tables: dict[str, Any]
    """The merged tables."""
    default_tables: dict[str, Any]
    """default.toml (merged with synthetic.toml for a synthetic building) alone, to tell which file a bad
    value came from."""
    files: tuple[Path, ...]
    """(default.toml, [synthetic.toml,] buildings/<name>.toml)"""

    @property
    def building(self) -> BuildingParams:
        return self.section("building", BuildingParams)

    @property
    def run(self) -> RunSettings:
        """The ``[run]`` table: how the stages run, never what they compute."""
        return self.section("run", RunSettings)

    def section(self, name: str, cls: type[T]) -> T:
        """Section ``name`` (dotted for a nested table: ``evaluate.align``) as an instance of the frozen
        dataclass ``cls``."""
        default, merged = self.default_tables, self.tables
        base_file = self._base_file(name.split(".")[0])
        for key in name.split("."):
            if not isinstance(default.get(key), dict):
                raise ConfigError(base_file, f"a [{name}] section", "none")
            default, merged = default[key], merged[key]
        _build(cls, default, name, (base_file,))
        # the base files are valid on their own, so whatever fails now came from the building's file
        # (a dataclass's own cross-field check raises without a file: name it here).
        try:
            return _build(cls, merged, name, (self.files[-1],))
        except ConfigError as e:
            if e.path is not None:
                raise
            raise ConfigError(self.files[-1], e.expected, e.found) from None

    def _base_file(self, table: str) -> Path:
        """The base file that defines top-level ``table``: synthetic.toml for [synthesize], else
        default.toml."""
        return self.files[1] if table in SYNTHETIC_TABLES and len(self.files) == 3 else self.files[0]


def available_buildings(directory: Path | None = None) -> list[str]:
    directory = directory or config_dir()
    return sorted(p.stem for p in (directory / "buildings").glob("*.toml"))


def load_building_config(building: str, directory: Path | None = None) -> BuildingConfig:
    """Read ``default.toml``, for a synthetic building ``synthetic.toml`` over it, and
    ``buildings/<building>.toml`` over both (building wins), its ``[budget.<name>]`` tables of the chosen
    budget over the rest of it (``BUDGETS``)."""
    directory = directory or config_dir()
    default_file = directory / "default.toml"
    building_file = directory / "buildings" / f"{building}.toml"
    if not building_file.is_file():
        names = ", ".join(available_buildings(directory)) or "none"
        raise ConfigError(building_file, f"a config for building {building!r} (one of: {names})", "no file")
    base = _read_toml(default_file)
    override = _read_toml(building_file)
    budgets = _budget_tables(override, building_file)
    synthetic_file = directory / SYNTHETIC_FILE
    synthetic = _read_toml(synthetic_file)
    files: tuple[Path, ...] = (default_file, building_file)
    if _declared_kind(override) == "synthetic":
        base = _merge(base, synthetic)
        files = (default_file, synthetic_file, building_file)
    for name, table in budgets.items():  # every budget's keys, the unused ones' too: a typo shows at once
        _check_known_keys(table, base, building_file, f"budget.{name}.")
    override = _merge(override, budgets.get(chosen_budget(), {}))
    if len(files) == 2:
        key = _first_key_only_in(override, synthetic, base, "")
        if key is not None:
            raise ConfigError(
                building_file,
                f"simulator keys ([synthesize], the metrics against gt/: {SYNTHETIC_FILE}) only in a "
                'building with [building] kind = "synthetic"',
                f"'{key}' in a real building's file",
            )
    _check_known_keys(override, base, building_file, "")
    return BuildingConfig(building, _merge(base, override), base, files)


def chosen_budget() -> str:
    """The budget ``$FACADE_BUDGET`` names (``BUDGETS``), "cpu" when it is unset or empty."""
    name = os.environ.get(BUDGET_ENV) or "cpu"
    if name not in BUDGETS:
        expected = f"${BUDGET_ENV} one of {', '.join(BUDGETS)}"
        raise ConfigError(None, expected, f"{name!r}: set one of them or unset it")
    return name


def _budget_tables(override: dict[str, Any], file: Path) -> dict[str, dict[str, Any]]:
    """The ``[budget.<name>]`` tables of a building's file, taken out of ``override``."""
    budgets = override.pop("budget", {})
    if not isinstance(budgets, dict):
        raise ConfigError(file, "[budget.<name>] tables", f"budget = {budgets!r}")
    for name, table in budgets.items():
        if name not in BUDGETS or not isinstance(table, dict):
            found = f"[budget.{name}]" if isinstance(table, dict) else f"budget.{name} = {table!r}"
            raise ConfigError(file, f"[budget.<name>] tables, name one of {', '.join(BUDGETS)}", found)
    return budgets


def _first_key_only_in(override: dict, synthetic: dict, default: dict, prefix: str) -> str | None:
    """The first key of ``override`` that synthetic.toml defines and default.toml does not."""
    for key, value in override.items():
        if key not in synthetic:
            continue
        if key not in default:
            return prefix + key
        if isinstance(value, dict) and isinstance(synthetic[key], dict) and isinstance(default[key], dict):
            found = _first_key_only_in(value, synthetic[key], default[key], f"{prefix}{key}.")
            if found is not None:
                return found
    return None


def _declared_kind(override: dict[str, Any]) -> Any:
    table = override.get("building")
    return table.get("kind") if isinstance(table, dict) else None


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(path, "a TOML config file", "no file") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(path, "valid TOML", f"a syntax error ({e})") from None


# Keys that were replaced or moved, with what replaces them: a config that still has one gets the
# replacement named (one mechanism for every old key).
RENAMED = {
    "rectify.warp.planar_shift_px": "none: every view is rectified (rectify.metres_per_px sets the scale)",
    **{f"segment_panels.{old}": f"segment_panels.{new} (a fraction of the building's pitch, which the "
       "survey measures)" for old, new in (
           ("min_partial_px", "min_partial"), ("min_partial_m", "min_partial"),
           ("surface_tolerance_m", "surface_tolerance"), ("grid.min_pitch_px", "grid.min_pitch"),
           ("grid.min_pitch_m", "grid.min_pitch"), ("grid.max_pitch_m", "grid.max_pitch"),
           ("grid.min_bar_px", "grid.min_bar"), ("grid.min_bar_m", "grid.min_bar"),
           ("grid.max_bar_px", "grid.max_bar"), ("grid.max_bar_m", "grid.max_bar"))},
    **{f"rectify.{old}_m": f"rectify.{old} (a fraction of the frontal views' footprint, which the coarse "
       "mesh gives)" for old in ("occlusion_margin", "fit.min_spread", "fit.ransac_threshold",
                                 "fit.inlier_scale")},
    **{f"{old}_m": f"{old} (a fraction of the building's panel pitch, which segment_panels' survey "
       "measures)" for old in ("regularize_corners.ghost_max", "regularize_corners.planar_max_sagitta",
                               "regularize_corners.outlier_floor", "regularize_corners.depth_window",
                               "regularize_corners.depth_bandwidth", "correct_mesh.cuboid_half_depth",
                               "correct_mesh.frame_half_depth")},
    "train_gs.reflection_model": "train_gs.reflection.model",
    "train_gs.fourier_levels": "train_gs.reflection.mlp.fourier_levels",
    "train_gs.mlp_depth": "train_gs.reflection.mlp.depth",
    "train_gs.mlp_width": "train_gs.reflection.mlp.width",
    "train_gs.mlp_skip": "train_gs.reflection.mlp.skip",
    "train_gs.mlp_proxy_channels": "train_gs.reflection.proxy.channels",
    "train_gs.mlp_proxy_resolution_px": "train_gs.reflection.proxy.resolution_px",
    "train_gs.mlp_proxy_levels": "train_gs.reflection.proxy.levels",
    "train_gs.mlp_proxy_cell_m": "train_gs.reflection.proxy.cell_m",
    "train_gs.envmap_height_px": "train_gs.reflection.envmap.height_px",
    "train_gs.envmap_width_px": "train_gs.reflection.envmap.width_px",
    **{
        f"train_gs.{key}": f"none: {why}; delete the key"
        for why, keys in (
            (
                "removed, it measured no gain (benchmarks/RESULTS.md)",
                ("mlp_self_hits", "mlp_self_hit_offset_m", "mlp_self_hit_max_m", "exposure_refinement",
                 "lr.exposure", "lambda_distortion", "distortion_start_fraction", "hf_residual"),
            ),
            (
                "the proxy's rays always meet the surroundings, reaching as far as the facade's size says",
                ("mlp_proxy_surroundings", "mlp_proxy_radius_m", "mlp_proxy_reach_m"),
            ),
            ("the loss is on from the start", ("normal_prior_start_fraction", "hf_start_fraction")),
            ("a constant of Eq. 12 (training/losses.py)", ("hf_eps",)),
            (
                "2DGS's value, a constant of facade_pipeline/training/losses.py",
                ("lambda_dssim", "normal_start_fraction"),
            ),
            (
                "2DGS's value, a constant of facade_pipeline/training/trainer.py",
                ("divergence_extent_factor",),
            ),
            ("2DGS's value, a constant of facade_pipeline/training/schedule.py", ("lr.position_final",)),
            (
                "2DGS's value, a constant of facade_pipeline/training/optimizers.py",
                ("lr.sh_dc", "lr.sh_rest", "lr.opacity", "lr.scaling", "lr.rotation"),
            ),
            ("2DGS's value, a constant of facade_pipeline/splatting/types.py", ("near_m",)),
            ("3DGS's value, a constant of facade_pipeline/training/init.py", ("init_opacity", "init_knn")),
            (
                "2DGS's value, a constant of facade_pipeline/training/densify.py",
                tuple(
                    f"densify.{k}"
                    for k in ("start_fraction", "end_fraction", "percent_dense", "split_count",
                              "opacity_reset_value", "prune_opacity", "prune_world_size_fraction")
                ),
            ),
            ("the estimate's numbers are fixed (ExposureParams, training/exposure.py)", ("exposure",)),
            (
                "no building tuned it: a constant of facade_pipeline/training/params.py",
                ("refl_threshold", "init_bounds_margin_m", "init_f0"),
            ),
            (
                "no building tuned it: a constant of facade_pipeline/training/schedule.py",
                ("lr.reflection_final", "lr.envmap"),
            ),
            ("no building tuned it: a constant of facade_pipeline/training/optimizers.py", ("lr.f0",)),
            (
                "no building tuned it: a constant of facade_pipeline/training/trainer.py",
                ("lr.pose_rotation", "lr.pose_translation"),
            ),
        )
        for key in keys
    },
    # run-only settings live in [run], where no stage's parameters (and so no rerun) can see them
    "train_gs.device": "run.device",
    "train_gs.raster_backend": "run.raster_backend",
    "train_gs.log_every": "run.log_every",
    "train_gs.checkpoint_every": "run.checkpoint_every",
    "evaluate.device": "run.device",
    "rectify.overlay_scale": "run.overlay_scale",
    "segment_panels.overlay_scale": "run.overlay_scale",
    # fixed choices and benchmark yardsticks, no longer parameters
    "correct_mesh.removal": "none: a coarse triangle with any vertex in a panel's cuboid is removed",
    "correct_mesh.target_normal_error_deg": "none: the target is benchmarks/bench_bake.py's",
    "correct_mesh.target_distance_fraction": "none: the target is benchmarks/bench_bake.py's",
    "segment_panels.grid.weak_edge_floor": "none: both edges of an inner frame bar count as seen "
    "(segment_panels.grid.outer_edge_floor sets the outer bars')",
    "regularize_corners.depth_refinement": "none: the glass depth is always the coarse points' mode, "
    "else the coarse mesh's median",
}
#: parameters that no building moved, now constants beside their use, by the file that holds them
FIXED = {
    "facade_pipeline/io/colmap.py": (
        "import_photogrammetry.undistort_blank_pixels",
        "import_photogrammetry.undistort_min_scale",
        "import_photogrammetry.undistort_max_scale",
    ),
    "stages/import_photogrammetry.py": (
        "import_photogrammetry.georef_threshold_m",
        "import_photogrammetry.auto_up_snap_deg",
    ),
    "facade_pipeline/rectification/cylinder.py": (
        "rectify.fit.ransac_iterations",
        "rectify.fit.seed",
        "rectify.fit.min_sagitta_rms",
    ),
    "facade_pipeline/rectification/surface_map.py": ("rectify.warp.samples_per_side",),
    "facade_pipeline/segmentation/frames.py": (
        "segment_panels.min_segment_px",
        "segment_panels.orientation_search_deg",
        "segment_panels.orientation_tolerance_deg",
        "segment_panels.lsd_sigma_px",
    ),
    "facade_pipeline/segmentation/parallax.py": ("segment_panels.parallax_min_bars",),
    "facade_pipeline/segmentation/openings.py": ("segment_panels.min_edge_support",),
    "facade_pipeline/segmentation/grid.py": (
        "segment_panels.grid.sigma_min_px",
        "segment_panels.grid.edge_search_px",
    ),
    "facade_pipeline/segmentation/evidence.py": ("segment_panels.grid.lsd_scale",),
    "facade_pipeline/panels3d/grid.py": (
        "regularize_corners.part_link_factor",
        "regularize_corners.cluster_gap_factor",
        "regularize_corners.footprint_shrink",
        "regularize_corners.border_margin_px",
    ),
    "facade_pipeline/panels3d/regularize.py": ("regularize_corners.outlier_mad_factor",),
    "stages/regularize_corners.py": (
        "regularize_corners.mask_min_region_px",
        "regularize_corners.mask_refit_iou",
    ),
    "facade_pipeline/evaluation/video.py": ("evaluate.video.clip_frames", "evaluate.video.clip_width_px"),
    "facade_pipeline/evaluation/building.py": ("evaluate.report_views",),
}
RENAMED |= {key: f"none: a constant in {where}" for where, keys in FIXED.items() for key in keys}


#: top-level tables of default.toml that describe the machines, not a building: a building's file may not
#: set them (it would change nothing)
MACHINE_TABLES = ("batch",)


def _check_known_keys(override: dict, default: dict, file: Path, prefix: str) -> None:
    """Every key of a building file must exist in default.toml (catches typos before anything runs)."""
    for key, value in override.items():
        where = f"{prefix}{key}"
        if not prefix and key in MACHINE_TABLES:
            raise ConfigError(file, f"[{key}] only in {DEFAULT_FILE} (it describes the machines)",
                              f"a [{key}] table in a building's file")
        if where in RENAMED:
            raise ConfigError(file, f"'{where}' replaced by {RENAMED[where]}", f"the old key '{where}'")
        if key not in default:
            raise ConfigError(file, "only keys that configs/default.toml defines", f"unknown key '{where}'")
        if isinstance(value, dict) and isinstance(default[key], dict):
            _check_known_keys(value, default[key], file, where + ".")


def _merge(default: dict, override: dict) -> dict:
    out = dict(default)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def from_dict(cls: type[T], table: dict[str, Any], where: str = "", file: Path | None = None) -> T:
    """Build the frozen dataclass ``cls`` from a plain dict (as read from TOML or JSON), checking types."""
    return _build(cls, table, where, (file,) if file else ())


def to_dict(params: Any) -> dict[str, Any]:
    """The plain-dict form of a params dataclass (tuples become lists), for manifests and doit."""
    return _plain(dataclasses.asdict(params))


def _plain(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    return x


def _build(cls: type, table: Any, where: str, files: tuple[Path | None, ...]) -> Any:
    file = _file_label(files)
    if not isinstance(table, dict):
        raise ConfigError(file, f"a table at '{where}'", type(table).__name__)
    hints = typing.get_type_hints(cls, include_extras=True)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for key in table:
        if key not in fields:
            raise ConfigError(
                file, f"one of the keys of [{where}] ({', '.join(fields)})", f"unknown key '{key}'"
            )
    kwargs = {}
    for name, field in fields.items():
        key = f"{where}.{name}" if where else name
        if name not in table:
            if field.default is not dataclasses.MISSING or field.default_factory is not dataclasses.MISSING:
                continue
            raise ConfigError(file, f"a value for '{key}'", "none")
        kwargs[name] = _convert(hints[name], table[name], key, files)
    return cls(**kwargs)


def _file_label(files: tuple[Path | None, ...]) -> Path | None:
    real = [f for f in files if f is not None]
    return real[-1] if real else None


def _convert(tp: Any, value: Any, key: str, files: tuple[Path | None, ...]) -> Any:
    origin = get_origin(tp)
    file = _file_label(files)
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, key, files)
    if origin is Annotated:
        inner, *extras = get_args(tp)
        out = _convert(inner, value, key, files)
        for rule in extras:
            if isinstance(rule, Range) and out not in rule:
                raise ConfigError(file, f"'{key}' {rule}", repr(value))
        return out
    if origin is Literal:
        if value not in get_args(tp):
            raise ConfigError(file, f"'{key}' one of {list(get_args(tp))}", repr(value))
        return value
    if origin in (types.UnionType, typing.Union):
        errors = []
        for arg in get_args(tp):
            try:
                return _convert(arg, value, key, files)
            except ConfigError as e:
                errors.append(e.expected)
        raise ConfigError(file, " or ".join(errors), repr(value))
    if origin is tuple:
        args = get_args(tp)
        if not isinstance(value, list | tuple):
            raise ConfigError(file, f"'{key}' an array", repr(value))
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{key}[{i}]", files) for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(file, f"'{key}' an array of {len(args)} values", f"{len(value)} values")
        return tuple(
            _convert(a, v, f"{key}[{i}]", files) for i, (a, v) in enumerate(zip(args, value, strict=True))
        )
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(file, f"'{key}' a number", repr(value))
        if math.isnan(value):
            raise ConfigError(file, f"'{key}' a number", repr(value))
        return float(value)  # inf: the key's Range says whether it may be
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(file, f"'{key}' an integer", repr(value))
        return value
    if tp is bool or tp is str:
        if not isinstance(value, tp):
            raise ConfigError(file, f"'{key}' a {tp.__name__}", repr(value))
        return value
    raise TypeError(f"config type {tp!r} of '{key}' is not supported")  # a programming error, not a user one


def default_params(section: str, cls: type[T], directory: Path | None = None) -> T:
    """Section ``section`` of ``default.toml`` alone (no building overrides), as ``cls``."""
    path = (directory or config_dir()) / "default.toml"
    table = _read_toml(path)
    if section not in table:
        raise ConfigError(path, f"a [{section}] section", "none")
    return _build(cls, table[section], section, (path,))
