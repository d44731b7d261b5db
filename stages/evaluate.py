"""Stage ``evaluate``: render and measure every trained variant, and write the report.

Renders the held-out views (every ``test_every``-th, as ``07_train/split.json`` lists them) and, on request,
the training views of the pipeline's model (``07_train``) and of every variant saved under
``variants/<name>/``; measures PSNR, SSIM and LPIPS against the imported photos over the facade mask and
separately on glass and on frames (masks baked from the corrected mesh, 06_bake_normals). On synthetic
buildings it also measures geometry against gt/ (read here for evaluation only): surface distance and
normal error of the coarse mesh, the corrected mesh and the Gaussians, and the panel corner error. Writes
``metrics.json``, the renders and photo | render | error comparisons, and the report (Markdown and a
self-contained HTML page) into 08_evaluate/.
"""

from __future__ import annotations

import hashlib
import json
import sys
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from facade_pipeline.config import Fraction, PosInt, Positive, RunSettings
from facade_pipeline.errors import ConfigError, InputError
from facade_pipeline.evaluation.geometry_eval import (
    Truth,
    load_truth,
    mesh_errors,
    panel_corner_errors,
    point_errors,
)
from facade_pipeline.evaluation.image_eval import (
    LpipsSetting,
    error_heatmap,
    mean_metrics,
    region_masks,
    side_by_side,
    view_metrics,
)
from facade_pipeline.evaluation.lpips import (
    UNAVAILABLE_TEXT,
    LpipsConvention,
    LpipsUnavailable,
    convention_spec,
    find_lpips_weights,
)
from facade_pipeline.evaluation.render_views import (
    TrainedModel,
    TrainedVariant,
    align_trained,
    load_trained,
    render_trained,
    variant_from_dir,
)
from facade_pipeline.evaluation.report import ARCHITECTURE_KEYS, build_html, build_markdown
from facade_pipeline.evaluation.video import (
    CLIP_FRAMES,
    CLIP_WIDTH_PX,
    VideoParams,
    merge_films,
    orbit_path,
    render_path,
    write_clip,
    write_mp4,
)
from facade_pipeline.geometry.bake import bake_view
from facade_pipeline.geometry.raycast import MeshRaycaster
from facade_pipeline.io.atomic import write_json, write_text
from facade_pipeline.io.images import read_image, read_mask, write_image
from facade_pipeline.io.meshes import read_mesh
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from facade_pipeline.meshing.correct import FRAME, read_labels
from facade_pipeline.panels import PanelSet
from facade_pipeline.scene import ImportedScene, View
from facade_pipeline.training.corrections import AlignParams
from facade_pipeline.training.trainer import resolve_device
from stages._runner import StageReport, main

NAME = "evaluate"
DOC = "render held-out views of every trained variant; PSNR/SSIM/LPIPS per region, geometry vs gt; the report"
UPSTREAM: tuple[str, ...] = ("train_gs", "bake_normals", "correct_mesh", "import_photogrammetry")
MAIN_VARIANT = "07_train"
#: comparison images per variant embedded in the report; the others are written as PNG beside it
REPORT_VIEWS = 4


@dataclass(frozen=True)
class Params:
    """``[evaluate]``: what is rendered and measured, and how the report shows it."""

    render_training_views: bool
    """also render and measure the training views"""
    include_saved_variants: bool
    """evaluate the variants saved under variants/<name>/ beside 07_train"""
    lpips_conventions: tuple[LpipsConvention, ...]
    """LPIPS figures to compute; the first is the one the tables show"""
    lpips_weights_dir: str
    """folder or file of the LPIPS weights; "" searches $FACADE_LPIPS_DIR, then ../shared/lpips"""
    heatmap_max_error: Positive
    """absolute error (0-1, mean over RGB) at the top of the heat-map colour ramp"""
    align: AlignParams
    """``[evaluate.align]``: each measured view is also measured after its pose and exposure are fitted
    against the frozen model (``<split>_aligned`` in metrics.json); steps = 0 turns it off"""
    video: VideoParams
    """``[evaluate.video]``: the fly-through of each model (frames = 0: none)"""
    geometry_samples: PosInt | None = None
    """points sampled by area on each mesh for the geometry metrics against gt/. This and the next two:
    synthetic buildings only (configs/synthetic.toml); None: no truth to measure against"""
    geometry_max_match_m: Positive | None = None
    """samples farther than this (m) from both true glass and frames are left out"""
    gaussian_min_opacity: Fraction | None = None
    """Gaussians less opaque than this are left out of the geometry metrics"""

    def __post_init__(self) -> None:
        if not self.lpips_conventions:
            raise ConfigError(None, "at least one convention in evaluate.lpips_conventions", "none")
        for c in self.lpips_conventions:
            convention_spec(c)


def _truth_files(layout: BuildingLayout) -> list[Path]:
    return [layout.gt("glass_mesh"), layout.gt("frame_mesh"), layout.gt("panels")]


def measures_geometry(layout: BuildingLayout, params: Params) -> bool:
    """Whether the geometry is measured: the config has the metrics' settings (a synthetic building's) and
    gt/ holds the truth they need."""
    return params.geometry_samples is not None and all(p.is_file() for p in _truth_files(layout))


def variants(layout: BuildingLayout, params: Params) -> list[TrainedVariant]:
    """``07_train`` (with the parameters its manifest records) and, if asked, every saved variant."""
    man = read_manifest(layout, "train_gs")
    found = [
        TrainedVariant(
            MAIN_VARIANT,
            layout.path("train_ply"),
            layout.path("train_reflection"),
            layout.path("train_split"),
            man.params,
        )
    ]
    root = layout.path("variant_dir", variant="x").parent
    if params.include_saved_variants and root.is_dir():
        found += [variant_from_dir(d) for d in sorted(root.iterdir()) if d.is_dir()]
    if sum(v.name == MAIN_VARIANT for v in found) > 1:
        raise InputError(
            root / MAIN_VARIANT, "a saved variant named other than the pipeline's model", "its name"
        )
    return found


def _views_of(
    layout: BuildingLayout, variant: TrainedVariant, scene: ImportedScene, split: str
) -> list[View]:
    by_stem = {v.stem: v for v in scene.uav_views}
    stems = variant.split_stems()[split]
    missing = [s for s in stems if s not in by_stem]
    if missing:
        raise InputError(
            variant.split, f"views of {layout.import_scene.name}", f"unknown stems {missing[:3]}"
        )
    return [by_stem[s] for s in stems]


def _view_files(layout: BuildingLayout, view: View) -> list[Path]:
    return [
        layout.root / view.image,
        layout.path("bake_facade_mask", stem=view.stem),
        layout.path("bake_glass_mask", stem=view.stem),
    ]


def inputs(layout: BuildingLayout, params: Params) -> list[Path]:
    """The trained variants, the imported scene, the photos and baked masks of the views they are
    measured on; on synthetic buildings the meshes, panels and gt/ truth. Missing files raise."""
    for stage in ("bake_normals", "correct_mesh", "regularize_corners"):
        read_manifest(layout, stage)
    scene = ImportedScene.load(layout)
    files = [layout.import_scene]
    for v in variants(layout, params):
        files += v.files
        splits = ("test", "train") if params.render_training_views else ("test",)
        for split in splits:
            for view in _views_of(layout, v, scene, split):
                files += _view_files(layout, view)
    if params.video.frames > 0:  # each frame's facade mask is cast from the corrected mesh
        files += [layout.path("correct_mesh"), layout.path("correct_mesh_labels")]
    if measures_geometry(layout, params):
        files += [
            layout.import_coarse_mesh,
            layout.path("correct_mesh"),
            layout.path("regularize_panels"),
            *_truth_files(layout),
        ]
    for f in files:
        if not f.is_file():
            raise InputError(f, "a file written by an upstream stage", "no file")
    return sorted(set(files))


def targets(layout: BuildingLayout, params: Params) -> list[Path]:
    video = ("eval_video", "eval_clip") if params.video.frames > 0 else ()
    return [layout.path(k) for k in ("eval_metrics", "eval_report_md", "eval_report_html", *video)]


def lpips_status(params: Params) -> dict[str, str]:
    """Per convention, where its weights are or that LPIPS is unavailable (a bad explicit path raises)."""
    out = {}
    for c in params.lpips_conventions:
        found = find_lpips_weights(convention_spec(c).net, params.lpips_weights_dir or None)
        out[c] = UNAVAILABLE_TEXT if isinstance(found, LpipsUnavailable) else f"weights {found.name}"
    return out


def evaluate_split(
    layout: BuildingLayout,
    params: Params,
    tm: TrainedModel,
    views: list[View],
    split: str,
    setting: LpipsSetting,
    bar: tqdm,
) -> tuple[dict[str, dict[str, Any]], list[Path]]:
    """Render and measure ``views``; writes each render and its comparison image. Returns
    ``{split: {"views", "mean"}}`` and, when ``params.align`` has steps, ``{split}_aligned`` with the
    views measured after alignment (each with what the alignment changed)."""
    per_view, aligned, written = [], [], []
    for view in views:
        truth = read_image(layout.root / view.image).astype(np.float64) / 255.0
        masks = region_masks(
            read_mask(layout.path("bake_facade_mask", stem=view.stem)),
            read_mask(layout.path("bake_glass_mask", stem=view.stem)),
        )
        if truth.shape[:2] != masks["facade"].shape:
            raise InputError(
                layout.root / view.image,
                f"an image of {masks['facade'].shape} px (its masks)",
                f"{truth.shape[:2]}",
            )
        r = render_trained(tm, view.camera, masks["facade"])
        names = {"variant": tm.name, "split": split, "stem": view.stem}
        render_path, comp_path = layout.path("eval_render", **names), layout.path("eval_comparison", **names)
        write_image(render_path, np.round(r.rgb * 255).astype(np.uint8))
        heat = error_heatmap(r.rgb, truth, masks["facade"], params.heatmap_max_error)
        write_image(comp_path, side_by_side(truth, r.rgb, heat))
        written += [render_path, comp_path]
        per_view.append({"view": view.stem, "metrics": view_metrics(r.rgb, truth, masks, setting)})
        if params.align.steps > 0:
            a = align_trained(tm, view.camera, truth, masks["facade"], params.align)
            aligned.append(
                {
                    "view": view.stem,
                    "metrics": view_metrics(a.render.rgb, truth, masks, setting),
                    "alignment": a.alignment.summary(),
                }
            )
        bar.update(1)
    out = {split: {"views": per_view, "mean": mean_metrics(per_view, setting.conventions)}}
    if aligned:
        out[f"{split}_aligned"] = {"views": aligned, "mean": mean_metrics(aligned, setting.conventions)}
    return out, written


def gaussian_geometry(tm: TrainedModel, truth: Truth, params: Params) -> dict[str, Any]:
    """Geometry of a variant's Gaussians (centres and normals of those at least ``gaussian_min_opacity``)."""
    keep = (tm.model.opacities() >= params.gaussian_min_opacity).detach().cpu().numpy()
    pts = tm.model.means.detach().cpu().numpy()[keep]
    nrm = tm.model.normals().detach().cpu().numpy()[keep]
    out = point_errors(pts, nrm, truth, params.geometry_max_match_m) if len(pts) else {}
    return {**out, "gaussians": int(keep.size), "gaussians_measured": int(keep.sum())}


def scene_geometry(
    layout: BuildingLayout, params: Params, scene: ImportedScene, truth: Truth
) -> dict[str, Any]:
    """Coarse and corrected mesh against the truth; the panel corner error (m, and px in the UAV views)."""
    out: dict[str, Any] = {}
    for key, path in (
        ("coarse_mesh", layout.import_coarse_mesh),
        ("corrected_mesh", layout.path("correct_mesh")),
    ):
        m = read_mesh(path)
        out[key] = mesh_errors(
            np.asarray(m.vertices),
            np.asarray(m.triangles),
            truth,
            params.geometry_samples,
            params.geometry_max_match_m,
        )
    panels = PanelSet.load(layout.path("regularize_panels"))
    out["panel_corners"] = panel_corner_errors(panels, truth, [v.camera for v in scene.uav_views])
    return out


def ablation_group(params: dict[str, Any]) -> str:
    """A digest of the training parameters other than the MLP architecture: variants with the same one
    differ only in L, depth, width, skip, the environment proxy and the self hits, and form a Table 3
    ablation."""
    rest = {k: v for k, v in params.items() if k not in ARCHITECTURE_KEYS}
    return hashlib.sha256(json.dumps(rest, sort_keys=True).encode()).hexdigest()[:16]


def _variant_entry(v: TrainedVariant, tm: TrainedModel) -> dict[str, Any]:
    p = v.params
    arch = {k: p[k] for k in ARCHITECTURE_KEYS if k in p} if p["reflection_model"] == "mlp" else None
    return {
        "reflection_model": p["reflection_model"],
        "architecture": arch,
        "ablation_group": ablation_group(p),
        "iterations": p["iterations"],
        "n_gaussians": tm.model.n,
        "files": [str(f) for f in v.files],
    }


def _report_images(layout: BuildingLayout, metrics: dict[str, Any], n: int) -> list[tuple[str, Path]]:
    out = []
    for name, v in metrics["variants"].items():
        for row in v["test"]["views"][:n]:
            facade = row["metrics"]["facade"]
            psnr = "-" if facade is None else facade["psnr"]
            caption = f"{name}, held-out view {row['view']} (facade PSNR {psnr} dB)"
            out.append(
                (caption, layout.path("eval_comparison", variant=name, split="test", stem=row["view"]))
            )
    return out


def metrics_header(layout: BuildingLayout, params: Params, test_every: int) -> dict[str, Any]:
    """What ``metrics.json`` says before any variant: the building, the split rule, the LPIPS conventions
    and whether their weights were found, the heat-map scale; ``variants`` is filled in by ``run``."""
    try:
        note = read_manifest(layout, "correct_mesh").metrics.get("note")
    except InputError:  # a model trained outside the DAG
        note = None
    return {
        "building": layout.building,
        "test_every": test_every,
        "lpips": {"conventions": list(params.lpips_conventions), "status": lpips_status(params)},
        "heatmap_max_error": params.heatmap_max_error,
        # what the reader must know before the figures (e.g. that no panels corrected the mesh)
        "notes": [note] if note else [],
        "variants": {},
    }



def run(layout: BuildingLayout, params: Params, settings: RunSettings) -> StageReport:
    # an earlier run's report must not pass for this one's while it runs, or after it is killed
    for path in targets(layout, params):
        path.unlink(missing_ok=True)
    scene = ImportedScene.load(layout)
    device = resolve_device(settings.device)
    setting = LpipsSetting(params.lpips_conventions, params.lpips_weights_dir or None)
    geometry = measures_geometry(layout, params)
    truth = load_truth(*_truth_files(layout), scene.georef_from_local) if geometry else None
    splits = ("test", "train") if params.render_training_views else ("test",)
    found = variants(layout, params)
    metrics = metrics_header(layout, params, found[0].params["test_every"])
    outputs: list[Path] = []
    jobs = [(v, s, _views_of(layout, v, scene, s)) for v in found for s in splits]
    path = orbit_path([v.camera for v in scene.uav_views], params.video.frames, params.video.scale)
    facade_mask = _facade_masker(layout) if path else None
    films: list[list[np.ndarray]] = []
    n_views = sum(len(j[2]) for j in jobs) + len(path) * len(found)
    with tqdm(total=n_views, desc="evaluate", unit="view", file=sys.stderr) as bar:
        for v in found:
            tm = load_trained(v, device, settings.raster_backend)
            if path:
                render = partial(_render_rgb, tm)
                films.append(render_path(path, render, facade_mask, bar.update))
            entry = _variant_entry(v, tm)
            for variant, split, views in jobs:
                if variant is v:
                    measured, written = evaluate_split(layout, params, tm, views, split, setting, bar)
                    entry |= measured
                    outputs += written
            if truth is not None:
                entry["geometry"] = gaussian_geometry(tm, truth, params)
            metrics["variants"][v.name] = entry
    if truth is not None:
        metrics["geometry"] = scene_geometry(layout, params, scene, truth)
    if films:
        frames = merge_films(films) if len(films) > 1 else films[0]
        vp = params.video
        write_mp4(layout.path("eval_video"), frames, vp.fps)
        write_clip(layout.path("eval_clip"), frames, CLIP_FRAMES, CLIP_WIDTH_PX, vp.fps)
        metrics["video"] = {
            "variants": [v.name for v in found],
            "frames": len(frames),
            "size_px": [int(frames[0].shape[1]), int(frames[0].shape[0])],
            "fps": vp.fps,
            "file": layout.path("eval_video").name,
            "clip": layout.path("eval_clip").name,
        }
    write_reports(layout, params, metrics)
    return StageReport(outputs + targets(layout, params), summary(metrics))


def _facade_masker(layout: BuildingLayout):
    """camera -> its facade mask [H, W] bool, cast from the corrected mesh as bake_normals casts it."""
    mesh = read_mesh(layout.path("correct_mesh"))
    rc = MeshRaycaster(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    labels = read_labels(layout.path("correct_mesh_labels"), len(mesh.triangles))
    return lambda cam: bake_view(rc, cam, 1 << 18, None, labels).label >= FRAME


def _render_rgb(tm, camera, facade_mask):
    return render_trained(tm, camera, facade_mask).rgb


def write_reports(layout: BuildingLayout, params: Params, metrics: dict[str, Any]) -> list[Path]:
    """``metrics.json`` and the report (Markdown linking the comparison images, HTML embedding them)."""
    images = _report_images(layout, metrics, REPORT_VIEWS)
    report_dir = layout.path("eval_report_md").parent
    write_json(layout.path("eval_metrics"), metrics)
    write_text(
        layout.path("eval_report_md"),
        build_markdown(metrics, [(c, p.relative_to(report_dir).as_posix()) for c, p in images]),
    )
    write_text(layout.path("eval_report_html"), build_html(metrics, images, layout.path("eval_clip")))
    return [layout.path(k) for k in ("eval_metrics", "eval_report_md", "eval_report_html")]


def summary(metrics: dict[str, Any]) -> dict[str, Any]:
    """The manifest's metrics: held-out facade PSNR/SSIM/LPIPS per variant (the full set is metrics.json)."""
    conv = metrics["lpips"]["conventions"][0]
    out: dict[str, Any] = {"variants": len(metrics["variants"]), "lpips_convention": conv}
    for name, v in metrics["variants"].items():
        f = v["test"]["mean"]["facade"] or {}
        out[f"{name}_test_psnr"] = f.get("psnr")
        out[f"{name}_test_ssim"] = f.get("ssim")
        out[f"{name}_test_lpips"] = (f.get("lpips") or {}).get(conv)
        if "test_aligned" in v:
            out[f"{name}_test_aligned_psnr"] = (v["test_aligned"]["mean"]["facade"] or {}).get("psnr")
    return out


if __name__ == "__main__":
    raise SystemExit(main(sys.modules[__name__]))
