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

import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from facade_pipeline.config import RunSettings
from facade_pipeline.errors import InputError
from facade_pipeline.evaluation.params import EvaluateParams
from facade_pipeline.evaluation.video import render_path, video_path
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from facade_pipeline.scene import ImportedScene
from stages._runner import StageReport, main

NAME = "evaluate"
DOC = "render held-out views of every trained variant; PSNR/SSIM/LPIPS per region, geometry vs gt; the report"
UPSTREAM: tuple[str, ...] = ("train_gs", "bake_normals", "correct_mesh", "import_photogrammetry")
Params = EvaluateParams
#: the runner deletes the targets (the report, its metrics and video) before the manifest, before anything
#: else: an earlier run's report must never be readable without the manifest that vouches for it, while
#: this run works or after it is killed
REMOVE_TARGETS_FIRST = True


def inputs(layout: BuildingLayout, params: Params) -> list[Path]:
    """The trained variants, the imported scene, the photos and baked masks of the views they are
    measured on; on synthetic buildings the meshes, panels and gt/ truth. Missing files raise."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.evaluation.building import (
        body_file,
        measures_geometry,
        split_views,
        trained_models,
        truth_files,
        view_files,
    )

    for stage in ("bake_normals", "correct_mesh", "regularize_corners"):
        read_manifest(layout, stage)
    scene = ImportedScene.load(layout)
    files = [layout.import_scene]
    for v in trained_models(layout, params):
        files += v.files
        for split in params.splits:
            for view in split_views(layout, v, scene, split):
                files += view_files(layout, view)
    if params.video.frames > 0:  # each frame's facade mask is cast from the corrected mesh
        files += [layout.path("correct_mesh"), layout.path("correct_mesh_labels")]
    if measures_geometry(layout, params):
        files += [
            layout.import_coarse_mesh,
            layout.path("correct_mesh"),
            layout.path("regularize_panels"),
            *truth_files(layout),
        ]
        body = body_file(layout)
        files += [body] if body is not None else []
    for f in files:
        if not f.is_file():
            raise InputError(f, "a file written by an upstream stage", "no file")
    return sorted(set(files))


def targets(layout: BuildingLayout, params: Params) -> list[Path]:
    video = ("eval_video", "eval_clip") if params.video.frames > 0 else ()
    return [layout.path(k) for k in ("eval_metrics", "eval_report_md", "eval_report_html", *video)]


def run(layout: BuildingLayout, params: Params, settings: RunSettings) -> StageReport:
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.evaluation.building import (
        body_file,
        evaluate_split,
        facade_masker,
        gaussian_geometry,
        measures_geometry,
        metrics_header,
        renderer,
        scene_geometry,
        split_views,
        summary,
        trained_models,
        truth_files,
        variant_entry,
        write_fly_through,
        write_reports,
    )
    from facade_pipeline.evaluation.geometry_eval import load_truth
    from facade_pipeline.evaluation.render_views import load_trained
    from facade_pipeline.training.data import pixel_budget_factor, scaled_camera
    from facade_pipeline.training.trainer import resolve_device

    scene = ImportedScene.load(layout)
    device = resolve_device(settings.device)
    truth = (
        load_truth(*truth_files(layout), scene.georef_from_local, body_file(layout))
        if measures_geometry(layout, params)
        else None
    )
    found = trained_models(layout, params)
    metrics = metrics_header(layout, params, found[0].params["test_every"])
    outputs: list[Path] = []
    jobs = {v.name: [(s, split_views(layout, v, scene, s)) for s in params.splits] for v in found}
    # the fly-through at the size the pipeline's model was trained at (a pixel budget, not the photos')
    budget = int(found[0].params.get("max_view_pixels", 0))
    cams = [(v.stem, v.camera) for v in scene.uav_views]
    cams = [(s, scaled_camera(c, pixel_budget_factor(c.width, c.height, budget))) for s, c in cams]
    path = video_path(params.video, cams)
    facade_mask = facade_masker(layout) if path else None
    films: list[list[np.ndarray]] = []
    measures = 2 if params.align.steps > 0 else 1  # as imported, and aligned
    n_views = measures * sum(len(views) for j in jobs.values() for _, views in j) + len(path) * len(found)
    with tqdm(total=n_views, desc="evaluate", unit="view", file=sys.stderr) as bar:
        for v in found:
            tm = load_trained(v, device, settings.raster_backend)
            if path:
                films.append(render_path(path, renderer(tm), facade_mask, bar.update))
            entry = variant_entry(v, tm)
            for split, views in jobs[v.name]:
                max_pixels = int(v.params.get("max_view_pixels", 0))  # measured as it was trained
                measured, written = evaluate_split(layout, params, tm, views, split, bar.update, max_pixels)
                entry |= measured
                outputs += written
            if truth is not None:
                entry["geometry"] = gaussian_geometry(tm, truth, params)
            metrics["variants"][v.name] = entry
    if truth is not None:
        metrics["geometry"] = scene_geometry(layout, params, scene, truth)
    if films:
        metrics["video"] = write_fly_through(layout, params.video, films, [v.name for v in found])
    write_reports(layout, params, metrics)
    return StageReport(outputs + targets(layout, params), summary(metrics))


if __name__ == "__main__":
    raise SystemExit(main(sys.modules[__name__]))
