"""Stage ``evaluate``: render and measure every trained variant, and write the report.

Renders the held-out views (every ``test_every``-th, as ``07_train/split.json`` lists them) and, on request,
the training views of the pipeline's model (``07_train``) and of every variant saved under
``variants/<name>/``; measures PSNR, SSIM and LPIPS against the imported photos over the facade mask and
separately on glass and on frames (masks baked from the corrected mesh, 06_bake_normals). On synthetic
buildings it also measures geometry against gt/ (read here for evaluation only): surface distance and
normal error of the coarse mesh, the corrected mesh and the Gaussians, and the panel corner error. Writes
``metrics.json``, the renders and photo | render | error comparisons, and the report (Markdown and a
self-contained HTML page) into 08_evaluate/. On the CPU every render (a view as imported or aligned, a
fly-through frame) is one task of the stage's fan-out (``batch.fanout.map_views``: the batch's workers or
``[run] view_workers`` processes), with the same outputs as one process.
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from facade_pipeline.config import RunSettings
from facade_pipeline.errors import InputError
from facade_pipeline.evaluation.params import EvaluateParams
from facade_pipeline.evaluation.video import video_path
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from facade_pipeline.panels3d.poses import registered_scene
from stages._runner import StageReport, main

NAME = "evaluate"
DOC = "render held-out views of every trained variant; PSNR/SSIM/LPIPS per region, geometry vs gt; the report"
UPSTREAM: tuple[str, ...] = (
    "train_gs", "bake_normals", "correct_mesh", "regularize_corners", "import_photogrammetry"
)
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
    scene = registered_scene(layout)
    files = [layout.import_scene, layout.path("regularize_poses")]
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
    import torch

    from facade_pipeline.batch.fanout import map_views
    from facade_pipeline.evaluation.building import (
        RenderTask,
        body_file,
        gaussian_geometry,
        load_model,
        measures_geometry,
        metrics_header,
        run_task,
        scene_geometry,
        split_result,
        split_views,
        summary,
        trained_models,
        truth_files,
        variant_entry,
        write_fly_through,
        write_reports,
    )
    from facade_pipeline.evaluation.geometry_eval import load_truth
    from facade_pipeline.training.data import pixel_budget_factor, scaled_camera
    from facade_pipeline.training.trainer import resolve_device

    scene = registered_scene(layout)
    device = resolve_device(settings.device)
    truth = (
        load_truth(*truth_files(layout), scene.georef_from_local, body_file(layout))
        if measures_geometry(layout, params)
        else None
    )
    found = trained_models(layout, params)
    metrics = metrics_header(layout, params, found[0].params["test_every"])
    # the fly-through at the size the pipeline's model was trained at (a pixel budget, not the photos')
    budget = int(found[0].params.get("max_view_pixels", 0))
    cams = [(v.stem, v.camera) for v in scene.uav_views]
    cams = [(s, scaled_camera(c, pixel_budget_factor(c.width, c.height, budget))) for s, c in cams]
    path = video_path(params.video, cams)
    aligned = (False, True) if params.align.steps > 0 else (False,)  # as imported, and aligned
    tasks = [RenderTask(v, camera=c) for v in found for c in path] + [
        RenderTask(v, split, view, a)
        for v in found
        for split in params.splits
        for a in aligned
        for view in split_views(layout, v, scene, split)
    ]
    # every render, of every model, is one task of the stage's fan-out (processes or the batch's
    # workers) on the CPU; on a GPU they stay in this process, whose device renders them
    fn = functools.partial(run_task, layout, params, str(device), settings.raster_backend,
                           torch.get_num_threads())  # fmt: skip
    with tqdm(total=len(tasks), desc="evaluate", unit="view", file=sys.stderr) as bar:
        results = map_views(fn, tasks, settings.view_workers, lambda _: bar.update(), device.type == "cpu")
    outputs: list[Path] = []
    films: list[list[np.ndarray]] = []
    for v in found:
        mine = [(t, r) for t, r in zip(tasks, results, strict=True) if t.variant is v]
        if path:
            films.append([r for t, r in mine if t.camera is not None])
        tm = load_model(v, str(device), settings.raster_backend)
        entry = variant_entry(v, tm)
        for split in params.splits:
            rows = {a: [r for t, r in mine if t.split == split and t.aligned == a] for a in aligned}
            entry |= split_result(params, split, [row for row, _ in rows[False]],
                                  [row for row, _ in rows[True]] if True in rows else None)  # fmt: skip
            outputs += [f for _, files in rows[False] for f in files]
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
