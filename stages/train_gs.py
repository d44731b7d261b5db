"""Stage ``train_gs``: reflection-aware 2D Gaussian Splatting (the paper's section 3.2).

Reads the imported views at their registered poses (04_regularize/poses.json) and the coarse points
(01_import), the corrected mesh and its triangle labels (05_correct_mesh) and, per UAV view, the baked
normal prior and the facade/glass masks (06_bake_normals).
Trains on every view but the held-out ones (every ``test_every``-th), checkpointing atomically so that a
killed run resumes where it stopped, and writes the Gaussians (3DGS-style PLY with reflectivity and F0),
the reflection module's weights, the train/test split and the training log into 07_train/.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from facade_pipeline.config import RunSettings, to_dict
from facade_pipeline.errors import InputError
from facade_pipeline.evaluation.params import LpipsSetting
from facade_pipeline.io.atomic import write_text
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest, sha256_file, sources_digest
from facade_pipeline.meshing.correct import GLASS, read_labels
from facade_pipeline.panels3d.poses import registered_scene
from facade_pipeline.scene import View
from facade_pipeline.training.data import (
    InitGeometry,
    TrainData,
    TrainView,
    clipped_channels,
    downscale_view,
    pixel_budget_factor,
    split_views,
)
from facade_pipeline.training.params import TrainParams
from stages._runner import PACKAGE_DIR, StageReport, main

if TYPE_CHECKING:  # names for annotations only: the functions that use them import them
    from facade_pipeline.bake.maps import BakedMap
    from facade_pipeline.training.trainer import Trainer

NAME = "train_gs"
DOC = "train reflection-aware 2D Gaussians (deferred shading, reflection MLP, normal prior) on the UAV views"
UPSTREAM: tuple[str, ...] = ("bake_normals", "correct_mesh", "regularize_corners", "import_photogrammetry")
Params = TrainParams
BAKED: tuple[BakedMap, ...] = ("normal_map", "facade_mask", "glass_mask")  # no depth: not trained on


def _baked(layout: BuildingLayout, stem: str) -> dict[str, Path]:
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.bake.maps import BakedPrior

    return BakedPrior.paths(layout, stem, BAKED)


def inputs(layout: BuildingLayout, params: Params) -> list[Path]:
    """The imported scene, images and points, the corrected mesh and every view's baked maps (checked)."""
    for stage in ("bake_normals", "correct_mesh", "regularize_corners"):
        read_manifest(layout, stage)
    scene = registered_scene(layout)
    files = [
        layout.import_scene,
        layout.path("regularize_poses"),
        layout.import_coarse_points,
        layout.path("correct_mesh"),
        layout.path("correct_mesh_labels"),
    ]
    for view in scene.uav_views:
        files += [layout.root / view.image, *_baked(layout, view.stem).values()]
    for f in files:
        if not f.is_file():
            raise InputError(f, "a file written by an upstream stage", "no file")
    if not scene.uav_views:
        raise InputError(layout.import_scene, "at least one UAV view", "none")
    return files


def targets(layout: BuildingLayout, params: Params) -> list[Path]:
    return [
        layout.path(k)
        for k in ("train_ply", "train_reflection", "train_log", "train_split", "train_checkpoint")
    ]


def _checked(path: Path, arr: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    if arr.shape != shape:
        raise InputError(path, f"a map of shape {shape} (the view's camera)", f"shape {arr.shape}")
    return arr


def load_view(layout: BuildingLayout, view: View, max_pixels: int = 0) -> TrainView:
    """One view's image, masks and normal prior, checked against its camera's size, with its clipped
    channels; reduced to at most ``max_pixels`` pixels (``data.pixel_budget_factor``; 0: as it is)."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.bake.maps import BakedPrior
    from facade_pipeline.io.images import read_image

    cam = view.camera
    hw = (cam.height, cam.width)
    img_path = layout.root / view.image
    image = _checked(img_path, read_image(img_path), (*hw, 3)).astype(np.float32) / 255.0
    prior = BakedPrior.load(layout, view.stem, hw, BAKED)
    full = TrainView(
        view.stem, cam, image, prior.facade, prior.glass, prior.normal, prior.valid, clipped_channels(image)
    )
    return downscale_view(full, pixel_budget_factor(cam.width, cam.height, max_pixels))


def load_train_data(layout: BuildingLayout, params: Params) -> TrainData:
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.io.meshes import read_mesh, read_points

    scene = registered_scene(layout)  # every view, held-out ones too, at its registered pose
    views = tuple(load_view(layout, v, params.max_view_pixels) for v in scene.uav_views)
    mesh = read_mesh(layout.path("correct_mesh"))
    pcd = read_points(layout.import_coarse_points)
    pts = np.asarray(pcd.points)
    colors = np.asarray(pcd.colors) if pcd.has_colors() else np.full_like(pts, 0.5)
    labels = read_labels(layout.path("correct_mesh_labels"), len(mesh.triangles))
    init = InitGeometry(pts, colors, np.asarray(mesh.vertices), np.asarray(mesh.triangles), labels == GLASS)
    train_idx, test_idx = split_views(len(views), params.test_every)
    if params.mask_by_facade:
        # a view whose rays miss the facade has nothing to learn from (its loss is over no pixel) nor to be
        # measured on: left out of both lists and counted
        empty = {i for i, v in enumerate(views) if not v.facade_mask.any()}
        if len(empty) == len(views):
            raise InputError(
                layout.stage_dir("bake_normals") / "masks" / "facade",
                "facade pixels in some training view (where the corrected mesh's facade is seen)",
                f"none in {len(views)} views: check that the coarse mesh covers the facade, or set "
                "[train_gs] mask_by_facade = false to train on whole images",
            )
        train_idx = tuple(i for i in train_idx if i not in empty)
        test_idx = tuple(i for i in test_idx if i not in empty)
        if not train_idx:
            raise InputError(
                layout.stage_dir("bake_normals") / "masks" / "facade",
                "facade pixels in some training view",
                f"only in held-out views ({len(views) - len(empty)} of {len(views)}): change "
                "[train_gs] test_every",
            )
    data = TrainData(views, train_idx, test_idx, init)
    if params.exposure_estimate:
        from facade_pipeline.training.exposure import with_exposure_estimate

        data = with_exposure_estimate(data, params.seed)
    return data


def fingerprint(layout: BuildingLayout, params: Params) -> str:
    """What a checkpoint must match to be resumed: the parameters, the inputs' contents and the code (not
    the run settings, which ``params`` does not hold: a run begun on the CPU resumes on a GPU)."""
    h = hashlib.sha256(json.dumps(to_dict(params), sort_keys=True).encode())
    for f in inputs(layout, params):
        h.update(sha256_file(f).encode())
    code = [p for d in ("training", "shading", "splatting") for p in (PACKAGE_DIR / d).rglob("*.py")]
    h.update(sources_digest(code).encode())
    return h.hexdigest()


def _save_outputs(layout: BuildingLayout, tr: Trainer, evaluation: dict) -> list[Path]:
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.training.batches import exposure_gains
    from facade_pipeline.training.trained import TrainedModelFiles

    views = tr.data.views
    split = {
        "train": [views[i].stem for i in tr.data.train_idx],
        "test": [views[i].stem for i in tr.data.test_idx],
    }
    gains = exposure_gains(tr.gains, tr.data)
    if gains:
        split["exposure_gain"] = gains
    files = TrainedModelFiles.pipeline(layout, to_dict(tr.params))
    strategy = tr.params.reflection_strategy(tr.data.bounds)
    files.save(tr.state.model, tr.state.reflection, strategy, tr.data.bounds, split)
    lines = [json.dumps(rec) for rec in tr.state.log] + [json.dumps({"evaluation": evaluation})]
    write_text(layout.path("train_log"), "\n".join(lines) + "\n")
    return targets(layout, tr.params)


def held_out_evaluation(tr: Trainer, backend: str) -> dict:
    """The held-out views measured by the evaluation core (no LPIPS): the headline means and a row per
    view."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.evaluation.core import evaluate_views, headline, views_of
    from facade_pipeline.evaluation.render_views import from_trainer
    from facade_pipeline.training.trained import PIPELINE_MODEL

    views = views_of(tr.data, tr.data.test_idx, tr.params.mask_by_facade)
    result = evaluate_views(from_trainer(tr, PIPELINE_MODEL, backend), views, LpipsSetting(()))
    return {**headline(result), "views": result["views"]}


def clipped_fraction(data: TrainData) -> float | None:
    """The fraction of the training views' facade pixels with a clipped channel (left to the camera's
    clipping in the loss); None when no view records its clipping."""
    views = [data.views[i] for i in data.train_idx if data.views[i].clipped is not None]
    n = sum(int(v.facade_mask.sum()) for v in views)
    if not n:
        return None
    return round(sum(int((v.clipped.any(-1) & v.facade_mask).sum()) for v in views) / n, 4)


def run(layout: BuildingLayout, params: Params, settings: RunSettings) -> StageReport:
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.training.batches import exposure_gains
    from facade_pipeline.training.render import training_rasterizer
    from facade_pipeline.training.trainer import (
        TrainingDivergedError,
        build_trainer,
        load_checkpoint,
        resolve_device,
        train,
    )

    data = load_train_data(layout, params)
    device = resolve_device(settings.device)
    rasterize = training_rasterizer(settings.raster_backend, params.lowpass_sigma_px, device)
    fp = fingerprint(layout, params)
    ckpt = layout.path("train_checkpoint")
    tr = load_checkpoint(ckpt, params, data, rasterize, device, fp, settings.compile)
    resumed_from = 0 if tr is None else tr.state.iteration
    tr = tr or build_trainer(params, data, rasterize, device, settings.compile)
    with tqdm(
        total=params.iterations, initial=tr.state.iteration, desc="train_gs", unit="it", file=sys.stderr
    ) as bar:

        def progress(it: int, total: int, out: dict) -> None:
            bar.update(it - bar.n)
            if "loss" in out:  # the figures of the last log line ([run] log_every)
                # the whole views' at that check
                view = tr.state.log[-1].get("view_psnr") if tr.state.log else None
                figures = {"loss": f"{out['loss']:.4f}", "psnr": f"{out['psnr']:.2f}", "view": view}
                bar.set_postfix(**figures, n=out["n"], refresh=False)

        try:
            train(
                tr,
                ckpt,
                fp,
                progress,
                log_every=settings.log_every,
                checkpoint_every=settings.checkpoint_every,
            )
        except TrainingDivergedError as e:  # one line: the iteration, the cause, the checkpoint kept
            kept = f"; {ckpt} (the last good state) is kept" if ckpt.is_file() else ""
            raise TrainingDivergedError(None, e.expected, e.found + kept) from None
    metrics = held_out_evaluation(tr, settings.raster_backend)
    outputs = _save_outputs(layout, tr, metrics)
    last = tr.state.log[-1] if tr.state.log else {}
    surroundings = getattr(getattr(tr.state.reflection, "proxy", None), "surroundings", None)
    # cells of the proxy's surface model above the ground (0: the coarse points hold no surroundings)
    cells = None if surroundings is None else int((surroundings.heights[1] > 0).sum())
    return StageReport(
        outputs,
        {
            "iterations": tr.state.iteration,
            "resumed_from_iteration": resumed_from,
            "n_gaussians": tr.state.model.n,
            "reflection_model": params.reflection.model,
            "device": str(device),
            "n_train_views": len(data.train_idx),
            "n_test_views": len(data.test_idx),
            "n_views_without_facade": len(data.views) - len(data.train_idx) - len(data.test_idx),
            "final_train_loss": last.get("loss"),
            "final_train_psnr": last.get("psnr"),
            "view_psnr": [r.get("view_psnr") for r in tr.state.log],
            "view_size_px": [data.views[0].camera.width, data.views[0].camera.height],
            "clipped_fraction": clipped_fraction(data),
            "exposure_gain": exposure_gains(tr.gains, tr.data),
            "test_psnr": metrics["psnr"],
            "test_ssim": metrics["ssim"],
            "test_psnr_glass": metrics["psnr_glass"],
            "test_psnr_glass_interior": metrics["psnr_glass_interior"],
            "test_normal_error_glass_deg": metrics["normal_error_glass_deg"],
            "test_views": metrics["views"],
            "proxy_surroundings_cells": cells,
        },
    )


if __name__ == "__main__":
    raise SystemExit(main(sys.modules[__name__]))
