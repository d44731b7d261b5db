"""Stage ``bake_normals``: the geometry prior of every training (UAV) view (Eq. 11's normal prior).

Reads ``05_correct_mesh/corrected_mesh.ply`` and ``triangle_labels.npy`` and the imported scene at its
registered poses (``04_regularize/poses.json``); writes
per view a world-space normal map and a depth map (EXR float32, each with a ``valid`` channel; no NaN) by
ray casting the corrected mesh, and the facade and glass masks (PNG) from the same rays: a pixel is glass
when its ray first hits a triangle labelled glass in ``05_correct_mesh/triangle_labels.npy``, facade when
glass or frame, so frames in front of the glass hide it. One view at a time, ``chunk_rays`` rays at a time:
memory does not grow with the number of views. On synthetic buildings the manifest compares the maps with
gt/ (metrics only).
"""

from __future__ import annotations

import functools
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from facade_pipeline.batch.fanout import map_views, shared
from facade_pipeline.config import PosInt, RunSettings
from facade_pipeline.errors import InputError
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from facade_pipeline.meshing.correct import FRAME, GLASS, read_labels
from facade_pipeline.panels3d.poses import registered_scene
from facade_pipeline.scene import ImportedScene, View
from stages._runner import StageReport, main

if TYPE_CHECKING:  # names for annotations only: the functions that use them import them
    from facade_pipeline.geometry.raycast import MeshRaycaster
    from facade_pipeline.synthetic.truth import SyntheticTruth

NAME = "bake_normals"
DOC = "bake world-space normal and depth maps (EXR) and facade/glass masks (PNG) for every training view"
UPSTREAM: tuple[str, ...] = ("correct_mesh", "regularize_corners", "import_photogrammetry")


@dataclass(frozen=True)
class Params:
    chunk_rays: PosInt
    """Rays cast per batch; bounds memory (-)."""


def inputs(layout: BuildingLayout, params: Params) -> list[Path]:
    read_manifest(layout, "correct_mesh")
    read_manifest(layout, "regularize_corners")
    files = [
        layout.import_scene,
        layout.path("regularize_poses"),
        layout.path("correct_mesh"),
        layout.path("correct_mesh_labels"),
    ]
    registered_scene(layout)
    return files


def _truth(
    truth: SyntheticTruth | None,
    view: View,
    normal: np.ndarray,
    valid: np.ndarray,
    glass: np.ndarray,
    facade: np.ndarray,
) -> tuple[np.ndarray, float, float] | None:
    """Normal angle errors (deg) on true glass pixels and the glass- and facade-mask IoU of one view
    (metrics only)."""
    if truth is None or not truth.layout.gt("normal_map", view.stem).is_file():
        return None
    true_n, true_valid = truth.normal_map(view.stem)
    gt_glass = truth.mask("glass", view.stem)
    sel = gt_glass & valid & true_valid
    err = np.degrees(np.arccos(np.clip(np.sum(normal[sel] * true_n[sel], axis=1), -1.0, 1.0)))
    gt_facade = truth.mask("facade", view.stem)
    iou = (glass & gt_glass).sum() / max(1, (glass | gt_glass).sum())
    iou_f = (facade & gt_facade).sum() / max(1, (facade | gt_facade).sum())
    return err, float(iou), float(iou_f)


def _bake_inputs(
    layout: BuildingLayout, mesh_path: Path, labels_path: Path, scene_path: Path
) -> tuple[MeshRaycaster, np.ndarray, SyntheticTruth | None]:
    """A ray caster of the corrected mesh, its triangle labels and, on a synthetic building, the truth."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.geometry.raycast import MeshRaycaster
    from facade_pipeline.io.meshes import read_mesh
    from facade_pipeline.synthetic.truth import SyntheticTruth

    mesh = read_mesh(mesh_path)
    rc = MeshRaycaster(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    labels = read_labels(labels_path, len(mesh.triangles))
    georef = ImportedScene.load(layout).georef_from_local
    truth = SyntheticTruth.load(layout, georef) if layout.gt_dir.is_dir() else None
    return rc, labels, truth


def bake_one(layout: BuildingLayout, params: Params, v: View) -> dict:
    """Bake one view and write its maps (in whichever process ``map_views`` runs it); returns its outputs,
    ray counts, cast time and its figures against the truth."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.bake.maps import BakedPrior, bake_view

    mesh, labels = layout.path("correct_mesh"), layout.path("correct_mesh_labels")
    rc, labels, truth = shared(_bake_inputs, layout, mesh, labels, layout.import_scene)
    t0 = time.perf_counter()
    baked = bake_view(rc, v.camera, params.chunk_rays, None, labels)
    seconds = time.perf_counter() - t0
    glass, facade = baked.label == GLASS, baked.label >= FRAME
    outputs = BakedPrior(v.stem, baked.normal, baked.valid, baked.depth, facade, glass).save(layout)
    against = _truth(truth, v, baked.normal, baked.valid, glass, facade)
    return {"outputs": outputs, "rays": baked.valid.size, "valid": int(baked.valid.sum()), "seconds": seconds,
            "against": against}


def run(layout: BuildingLayout, params: Params, settings: RunSettings) -> StageReport:
    # each view at the pose it trains with: a mask cast from the imported pose would miss the frames by
    # the pose's error
    scene = registered_scene(layout)
    views = scene.uav_views
    outputs: list[Path] = []
    errs, ious, ious_f, n_rays, n_valid, t_cast = [], {}, [], 0, 0, 0.0
    total = sum(v.camera.width * v.camera.height for v in views)
    with tqdm(total=total, desc="bake: rays", unit="ray", unit_scale=True, file=sys.stderr) as bar:
        one = functools.partial(bake_one, layout, params)
        results = map_views(one, views, settings.view_workers, lambda r: bar.update(r["rays"]))
    for v, r in zip(views, results, strict=True):
        outputs += r["outputs"]
        n_rays += r["rays"]
        n_valid += r["valid"]
        t_cast += r["seconds"]
        against = r["against"]
        if against is not None:
            errs.append(against[0])
            ious[v.stem] = round(against[1], 4)
            ious_f.append(against[2])
    if views and n_valid == 0:
        raise InputError(
            layout.path("correct_mesh"),
            "a mesh the training views see (their rays meet it)",
            f"no ray of {len(views)} views meets it: check 05_correct_mesh/overlay.png and the import's "
            "uav_views_seeing_mesh",
        )
    metrics = {
        "n_views": len(views),
        "rays": n_rays,
        "valid_fraction": round(n_valid / max(1, n_rays), 4),
        "rays_per_s": round(n_rays / max(t_cast, 1e-9)),
    }
    if ious:
        e = np.concatenate(errs)
        metrics["truth"] = {
            "glass_normal_error_mean_deg": round(float(e.mean()), 4) if len(e) else None,
            "glass_normal_error_p95_deg": round(float(np.percentile(e, 95)), 4) if len(e) else None,
            "glass_mask_iou_mean": round(float(np.mean(list(ious.values()))), 4),
            "glass_mask_iou_min": min(ious.values()),
            "glass_mask_iou": ious,
            "facade_mask_iou_mean": round(float(np.mean(ious_f)), 4),
        }
    return StageReport(outputs, metrics)


def targets(layout: BuildingLayout, params: Params) -> list[Path]:
    return []  # one set of maps per view: the views are known only once the import ran


if __name__ == "__main__":
    raise SystemExit(main(sys.modules[__name__]))
