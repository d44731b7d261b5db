"""Evaluating a building's trained models (what the ``evaluate`` stage runs): its parameters, which models
there are (``07_train`` and the saved variants), the views they are measured on, the measurement of each
view through the evaluation core (``core.measure_view``) with its render and comparison image, the
geometry against gt/ on synthetic buildings, and ``metrics.json`` with the report. ``run_task`` is one
render of the stage (a view, or a fly-through frame) in whichever process the stage's fan-out runs it.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from facade_pipeline.bake.maps import BakedPrior, bake_view
from facade_pipeline.batch.fanout import shared
from facade_pipeline.errors import InputError
from facade_pipeline.evaluation.core import EvalView, measure_view
from facade_pipeline.evaluation.geometry_eval import Truth, mesh_errors, panel_corner_errors, point_errors
from facade_pipeline.evaluation.image_eval import error_heatmap, mean_metrics, side_by_side
from facade_pipeline.evaluation.lpips import (
    UNAVAILABLE_TEXT,
    LpipsUnavailable,
    convention_spec,
    find_lpips_weights,
)
from facade_pipeline.evaluation.params import EvaluateParams
from facade_pipeline.evaluation.render_views import TrainedModel, load_trained, render_trained
from facade_pipeline.evaluation.report import ARCHITECTURE_KEYS, build_html, build_markdown
from facade_pipeline.evaluation.video import (
    CLIP_FRAMES,
    CLIP_WIDTH_PX,
    VideoParams,
    merge_films,
    to_frame,
    write_clip,
    write_mp4,
)
from facade_pipeline.geometry.camera import PinholeCamera
from facade_pipeline.geometry.raycast import MeshRaycaster
from facade_pipeline.io.atomic import write_json, write_text
from facade_pipeline.io.images import read_image, write_image
from facade_pipeline.io.meshes import read_mesh
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from facade_pipeline.meshing.correct import FRAME, read_labels
from facade_pipeline.panels3d.model import PanelSet
from facade_pipeline.scene import ImportedScene, View
from facade_pipeline.training.data import block_reduce, clipped_channels, pixel_budget_factor, scaled_camera
from facade_pipeline.training.params import flat_params
from facade_pipeline.training.trained import PIPELINE_MODEL, TrainedModelFiles

#: comparison images per variant embedded in the report; the others are written as PNG beside it
REPORT_VIEWS = 4


def truth_files(layout: BuildingLayout) -> list[Path]:
    """The gt/ files the geometry metrics need (``load_truth``'s first three arguments)."""
    return [layout.gt("glass_mesh"), layout.gt("frame_mesh"), layout.gt("panels")]


def body_file(layout: BuildingLayout) -> Path | None:
    """gt/'s building body, which the mesh errors leave out, where synthesize wrote it."""
    path = layout.gt("body_mesh")
    return path if path.is_file() else None


def measures_geometry(layout: BuildingLayout, params: EvaluateParams) -> bool:
    """Whether the geometry is measured: the config has the metrics' settings (a synthetic building's) and
    gt/ holds the truth they need."""
    return params.geometry_samples is not None and all(p.is_file() for p in truth_files(layout))


def trained_models(layout: BuildingLayout, params: EvaluateParams) -> list[TrainedModelFiles]:
    """``07_train`` (with the parameters its manifest records) and, if asked, every saved variant."""
    found = [TrainedModelFiles.pipeline(layout)]
    root = layout.path("variant_dir", variant="x").parent
    if params.include_saved_variants and root.is_dir():
        found += [TrainedModelFiles.from_dir(d) for d in sorted(root.iterdir()) if d.is_dir()]
    if sum(v.name == PIPELINE_MODEL for v in found) > 1:
        raise InputError(
            root / PIPELINE_MODEL, "a saved variant named other than the pipeline's model", "its name"
        )
    return found


def split_views(
    layout: BuildingLayout, variant: TrainedModelFiles, scene: ImportedScene, split: str
) -> list[View]:
    """The imported views of ``split`` of the split ``variant`` was trained on."""
    by_stem = {v.stem: v for v in scene.uav_views}
    stems = variant.split_stems()[split]
    missing = [s for s in stems if s not in by_stem]
    if missing:
        raise InputError(
            variant.split, f"views of {layout.import_scene.name}", f"unknown stems {missing[:3]}"
        )
    return [by_stem[s] for s in stems]


def view_files(layout: BuildingLayout, view: View) -> list[Path]:
    """What a view is measured from: its photo and its baked facade and glass masks."""
    return [
        layout.root / view.image,
        *BakedPrior.paths(layout, view.stem, ("facade_mask", "glass_mask")).values(),
    ]


def load_eval_view(layout: BuildingLayout, view: View, max_pixels: int = 0) -> EvalView:
    """A view's photo (in [0, 1]) and baked masks, checked to be of one size, at most ``max_pixels`` pixels
    as its model was trained (``[train_gs] max_view_pixels``, ``training.data.downscale_view``)."""
    truth = read_image(layout.root / view.image).astype(np.float64) / 255.0
    prior = BakedPrior.load(layout, view.stem, None, ("facade_mask", "glass_mask"))
    facade, glass = prior.facade, prior.glass
    if truth.shape[:2] != facade.shape:
        raise InputError(
            layout.root / view.image, f"an image of {facade.shape} px (its masks)", f"{truth.shape[:2]}"
        )
    cam = view.camera
    clipped = clipped_channels(truth).any(axis=-1)
    f = pixel_budget_factor(cam.width, cam.height, max_pixels)
    if f > 1:  # as training's views (``downscale_view``): a pixel clipped where any of its block is
        truth = block_reduce(truth, f)
        facade, glass = (block_reduce(np.asarray(m, np.float32), f) >= 0.5 for m in (facade, glass))
        clipped = block_reduce(clipped, f, "any")
    facade, glass = np.asarray(facade, bool), np.asarray(glass, bool)
    return EvalView(view.stem, scaled_camera(cam, f), truth, facade, glass, clipped=clipped)


def lpips_status(params: EvaluateParams) -> dict[str, str]:
    """Per convention, where its weights are or that LPIPS is unavailable (a bad explicit path raises)."""
    out = {}
    for c in params.lpips_conventions:
        found = find_lpips_weights(convention_spec(c).net, params.lpips_weights_dir or None)
        out[c] = UNAVAILABLE_TEXT if isinstance(found, LpipsUnavailable) else f"weights {found.name}"
    return out


def measure_one(
    layout: BuildingLayout,
    params: EvaluateParams,
    tm: TrainedModel,
    view: View,
    split: str,
    aligned: bool,
    max_pixels: int = 0,
) -> tuple[dict[str, Any], list[Path]]:
    """Render and measure one view of ``split`` (``core.measure_view``) at the size ``max_pixels`` allows
    (``load_eval_view``): as imported, writing its render and comparison image, or ``aligned`` first (with
    what the alignment changed; nothing written). Returns its row and the files written."""
    ev = load_eval_view(layout, view, max_pixels)
    m = measure_view(tm, ev, params.lpips, params.align if aligned else None)
    if aligned:
        return m.row, []
    names = {"variant": tm.name, "split": split, "stem": view.stem}
    render_path, comp_path = layout.path("eval_render", **names), layout.path("eval_comparison", **names)
    write_image(render_path, np.round(m.rgb * 255).astype(np.uint8))
    heat = error_heatmap(m.rgb, ev.image, ev.facade_mask, params.heatmap_max_error)
    write_image(comp_path, side_by_side(ev.image, m.rgb, heat))
    return m.row, [render_path, comp_path]


def split_result(
    params: EvaluateParams, split: str, rows: list[dict[str, Any]], aligned: list[dict[str, Any]] | None
) -> dict[str, dict[str, Any]]:
    """``{split: {"views", "mean"}}`` of the rows as imported and, where the views were also measured
    aligned, ``{split}_aligned`` of those."""
    conv = params.lpips.conventions
    out = {split: {"views": rows, "mean": mean_metrics(rows, conv)}}
    if aligned is not None:
        out[f"{split}_aligned"] = {"views": aligned, "mean": mean_metrics(aligned, conv)}
    return out


def evaluate_split(
    layout: BuildingLayout,
    params: EvaluateParams,
    tm: TrainedModel,
    views: list[View],
    split: str,
    advance: Callable[[int], Any] = lambda n: None,
    max_pixels: int = 0,
) -> tuple[dict[str, dict[str, Any]], list[Path]]:
    """``views`` measured one by one in this process (``measure_one``), as imported and, when
    ``params.align`` has steps, aligned: ``split_result`` and the files written. ``advance(1)`` is called
    after each view as imported and after each as aligned."""
    rows, aligned, written = [], [], []
    for view in views:
        row, files = measure_one(layout, params, tm, view, split, False, max_pixels)
        rows.append(row)
        written += files
        advance(1)
    if params.align.steps > 0:
        for view in views:
            aligned.append(measure_one(layout, params, tm, view, split, True, max_pixels)[0])
            advance(1)
    return split_result(params, split, rows, aligned if params.align.steps > 0 else None), written


@dataclass(frozen=True)
class RenderTask:
    """One render of the evaluation, done wherever ``run_task`` runs it: a view of ``split`` measured as
    imported or ``aligned``, or (``camera`` given) a frame of the fly-through."""

    variant: TrainedModelFiles
    split: str = ""
    view: View | None = None
    aligned: bool = False
    camera: PinholeCamera | None = None


def load_model(variant: TrainedModelFiles, device: str, backend: str) -> TrainedModel:
    """``render_views.load_trained``, once per process while the model's files stay the same
    (``batch.fanout.shared``)."""
    v = variant
    params = json.dumps(v.params, sort_keys=True)
    return shared(_load_model, v.ply, v.reflection, v.split, v.name, params, device, backend)


def _load_model(ply: Path, reflection: Path, split: Path, name: str, params: str, device: str,
                backend: str) -> TrainedModel:  # fmt: skip
    return load_trained(TrainedModelFiles(name, ply, reflection, split, json.loads(params)), device, backend)


def run_task(
    layout: BuildingLayout, params: EvaluateParams, device: str, backend: str, threads: int, task: RenderTask
) -> np.ndarray | tuple[dict[str, Any], list[Path]]:
    """A fly-through frame (uint8 [H, W, 3]) or a view's ``measure_one``, on ``threads`` torch threads
    (the stage's own count: a reduction split over another number of threads sums in another order, and
    a fitted pose then differs in its last bits)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        tm = load_model(task.variant, device, backend)
        if task.camera is not None:
            mask = shared(_facade_masker, layout.path("correct_mesh"), layout.path("correct_mesh_labels"))
            return to_frame(render_trained(tm, task.camera, mask(task.camera)).rgb)
        assert task.view is not None
        max_pixels = int(task.variant.params.get("max_view_pixels", 0))  # measured as it was trained
        return measure_one(layout, params, tm, task.view, task.split, task.aligned, max_pixels)
    finally:
        torch.set_num_threads(previous)


def gaussian_geometry(tm: TrainedModel, truth: Truth, params: EvaluateParams) -> dict[str, Any]:
    """Geometry of a variant's Gaussians (centres and normals of those at least ``gaussian_min_opacity``)."""
    keep = (tm.model.opacities() >= params.gaussian_min_opacity).detach().cpu().numpy()
    pts = tm.model.means.detach().cpu().numpy()[keep]
    nrm = tm.model.normals().detach().cpu().numpy()[keep]
    out = point_errors(pts, nrm, truth, params.geometry_max_match_m) if len(pts) else {}
    return {**out, "gaussians": int(keep.size), "gaussians_measured": int(keep.sum())}


def scene_geometry(
    layout: BuildingLayout, params: EvaluateParams, scene: ImportedScene, truth: Truth
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


def variant_entry(v: TrainedModelFiles, tm: TrainedModel) -> dict[str, Any]:
    """What metrics.json says of a variant before its figures: model, architecture, ablation group, files."""
    p = flat_params(v.params)
    arch = {k: p[k] for k in ARCHITECTURE_KEYS if k in p} if p["reflection_model"] == "mlp" else None
    return {
        "reflection_model": p["reflection_model"],
        "architecture": arch,
        "ablation_group": ablation_group(p),
        "iterations": p["iterations"],
        "n_gaussians": tm.model.n,
        "files": [str(f) for f in v.files],
    }


def metrics_header(layout: BuildingLayout, params: EvaluateParams, test_every: int) -> dict[str, Any]:
    """What ``metrics.json`` says before any variant: the building, the split rule, the LPIPS conventions
    and whether their weights were found, the heat-map scale; ``variants`` is filled in by the stage."""
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


def _facade_masker(mesh_path: Path, labels_path: Path) -> Callable[[PinholeCamera], np.ndarray]:
    """camera -> its facade mask [H, W] bool, cast from the corrected mesh as bake_normals casts it."""
    mesh = read_mesh(mesh_path)
    rc = MeshRaycaster(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    labels = read_labels(labels_path, len(mesh.triangles))
    return lambda cam: bake_view(rc, cam, 1 << 18, None, labels).label >= FRAME


def write_fly_through(
    layout: BuildingLayout, vp: VideoParams, films: list[list[np.ndarray]], names: list[str]
) -> dict[str, Any]:
    """The fly-through of every variant side by side (``names``, one film each) as MP4 and a looping clip;
    returns what metrics.json says of it."""
    frames = merge_films(films) if len(films) > 1 else films[0]
    write_mp4(layout.path("eval_video"), frames, vp.fps)
    write_clip(layout.path("eval_clip"), frames, CLIP_FRAMES, CLIP_WIDTH_PX, vp.fps)
    return {
        "variants": names,
        "frames": len(frames),
        "size_px": [int(frames[0].shape[1]), int(frames[0].shape[0])],
        "fps": vp.fps,
        "path": vp.path if vp.path == "orbit" else list(vp.path),
        "file": layout.path("eval_video").name,
        "clip": layout.path("eval_clip").name,
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


def write_reports(layout: BuildingLayout, params: EvaluateParams, metrics: dict[str, Any]) -> list[Path]:
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
    """The manifest's metrics: held-out facade PSNR/SSIM/LPIPS and glass-interior PSNR per variant (the
    full set is metrics.json)."""
    conv = metrics["lpips"]["conventions"][0]
    out: dict[str, Any] = {"variants": len(metrics["variants"]), "lpips_convention": conv}
    for name, v in metrics["variants"].items():
        mean = v["test"]["mean"]
        f = mean["facade"] or {}
        out[f"{name}_test_psnr"] = f.get("psnr")
        out[f"{name}_test_ssim"] = f.get("ssim")
        out[f"{name}_test_lpips"] = (f.get("lpips") or {}).get(conv)
        out[f"{name}_test_psnr_glass_interior"] = (mean.get("glass_interior") or {}).get("psnr")
        if "test_aligned" in v:
            out[f"{name}_test_aligned_psnr"] = (v["test_aligned"]["mean"]["facade"] or {}).get("psnr")
    return out
