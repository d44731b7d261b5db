"""Stage ``synthesize``: make a synthetic building's raw/ (what a user would bring) and gt/ (the truth).

Runs only for synthetic buildings. It reads nothing; it refuses to write into a raw/ without a gt/ beside
it, because such a raw/ was brought by a user.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from facade_pipeline.config import RunSettings
from facade_pipeline.errors import InputError
from facade_pipeline.io.atomic import write_json
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.synthetic.cameras import View, planned_frontal_views, view_stem
from facade_pipeline.synthetic.coarse import coarse_mesh, coarse_points
from facade_pipeline.synthetic.mesh import Material, TriMesh
from facade_pipeline.synthetic.noise import rng_for
from facade_pipeline.synthetic.params import SynthesizeParams
from facade_pipeline.synthetic.scene import panels_description, scene_description
from stages._runner import StageReport, main

if TYPE_CHECKING:  # names for annotations only: the functions that use them import them
    from facade_pipeline.synthetic.render import ViewRender
    from facade_pipeline.synthetic.simulate import Simulator

NAME = "synthesize"
DOC = "Make a synthetic building: ray-traced glass facade images, COLMAP models, coarse mesh, truth"
Params = SynthesizeParams
UPSTREAM: tuple[str, ...] = ()
#: raw/ is what a user brings, even when this stage made it: an image edited by hand is taken as given
EDITABLE: tuple[str, ...] = ("raw_dir",)

#: Files pycolmap 4 writes for a binary model.
MODEL_FILES = ("cameras.bin", "images.bin", "points3D.bin", "rigs.bin", "frames.bin")
PER_VIEW_GT = (
    "clean_image",
    "normal_map",
    "depth_map",
    "reflectivity_map",
    "glass_mask",
    "frame_mask",
    "facade_mask",
)


def check_raw_is_ours(layout: BuildingLayout) -> None:
    """A raw/ without gt/ beside it belongs to a user: never overwrite it."""
    if layout.raw_dir.exists() and not layout.gt_dir.exists():
        raise InputError(
            layout.raw_dir,
            "no raw/ folder, or one made by `synthesize` (with gt/ beside it)",
            "a raw/ without gt/ (real data?); move it away or choose another building name",
        )


def inputs(layout: BuildingLayout, params: SynthesizeParams) -> list[Path]:
    check_raw_is_ours(layout)
    return []


def _view_names(params: SynthesizeParams) -> tuple[list[str], list[str]]:
    uav = [view_stem("uav", i) for i in range(params.cameras.uav_count)]
    return uav, [v.stem for v in planned_frontal_views(params)]


def targets(layout: BuildingLayout, params: SynthesizeParams) -> list[Path]:
    """Every file ``run`` writes except the manifest."""
    uav, frontal = _view_names(params)
    out = [layout.raw_image(s + ".png") for s in uav] + [
        layout.raw_frontal_image(s + ".png") for s in frontal
    ]
    for d in (
        layout.raw_sparse_dir,
        layout.raw_frontal_sparse_dir,
        layout.gt("sparse_dir"),
        layout.gt("frontal_sparse_dir"),
    ):
        out += [d / f for f in MODEL_FILES]
    out += [layout.raw_coarse_mesh_candidates[0], layout.raw_coarse_points]
    out += [layout.gt(k) for k in ("scene", "facade_mesh", "glass_mesh", "frame_mesh", "body_mesh", "panels")]
    out += [layout.gt(k, s) for s in uav + frontal for k in PER_VIEW_GT]
    return out


def _mesh(m: TriMesh, colors: np.ndarray | None = None):
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.io.meshes import make_mesh

    return make_mesh(m.vertices, m.triangles, colors)


def write_truth(layout: BuildingLayout, sim: Simulator) -> list[Path]:
    """gt/ files that do not depend on views: scene.json, panels.json, true meshes."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.io.meshes import write_mesh

    scene = sim.scene
    write_json(layout.gt("scene"), scene_description(scene))
    write_json(layout.gt("panels"), panels_description(scene))
    write_mesh(layout.gt("facade_mesh"), _mesh(scene.facade))
    write_mesh(layout.gt("glass_mesh"), _mesh(scene.glass))
    write_mesh(layout.gt("frame_mesh"), _mesh(scene.frames))
    write_mesh(layout.gt("body_mesh"), _mesh(scene.body))
    return [layout.gt(k) for k in ("scene", "panels", "facade_mesh", "glass_mesh", "frame_mesh", "body_mesh")]


def write_coarse(layout: BuildingLayout, sim: Simulator) -> tuple[list[Path], np.ndarray, np.ndarray, dict]:
    """raw/coarse_mesh.ply and raw/coarse_points.ply; returns the points kept for the COLMAP models."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.io.images import to_uint8
    from facade_pipeline.io.meshes import make_points, write_mesh, write_points

    p = sim.scene.params
    mesh, colors = coarse_mesh(sim.scene)
    write_mesh(layout.raw_coarse_mesh_candidates[0], _mesh(mesh, colors))
    xyz, rgb = coarse_points(sim.scene)
    write_points(layout.raw_coarse_points, make_points(xyz, rgb))
    pick = np.sort(rng_for(p.seed, "sparse_points").permutation(len(xyz))[: p.coarse.sparse_points])
    stats = {"coarse_mesh_triangles": len(mesh.triangles), "coarse_points": len(xyz)}
    return (
        [layout.raw_coarse_mesh_candidates[0], layout.raw_coarse_points],
        xyz[pick],
        to_uint8(rgb[pick]),
        stats,
    )


def write_models(layout: BuildingLayout, sim: Simulator, xyz: np.ndarray, rgb: np.ndarray) -> list[Path]:
    """COLMAP models: raw/ with the declared pose noise, gt/ with the true poses."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.io.colmap import ColmapView, write_pinhole_model
    from facade_pipeline.synthetic.simulate import raw_view

    p = sim.scene.params
    out = []
    for kind, raw_dir, gt_dir in (
        ("uav", layout.raw_sparse_dir, layout.gt("sparse_dir")),
        ("frontal", layout.raw_frontal_sparse_dir, layout.gt("frontal_sparse_dir")),
    ):
        views = [v for v in sim.views if v.kind == kind]
        write_pinhole_model(raw_dir, [raw_view(p, v) for v in views], xyz, rgb)
        write_pinhole_model(gt_dir, [ColmapView(v.name, v.camera) for v in views], xyz, rgb)
        out += [d / f for d in (raw_dir, gt_dir) for f in MODEL_FILES]
    return out


def write_view(layout: BuildingLayout, params: SynthesizeParams, view: View, r: ViewRender) -> list[Path]:
    """The raw image and every gt map of one view."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.io.exr import write_exr
    from facade_pipeline.io.images import to_uint8, write_image, write_mask
    from facade_pipeline.synthetic.simulate import sensor_image

    raw = layout.raw_image(view.name) if view.kind == "uav" else layout.raw_frontal_image(view.name)
    write_image(raw, sensor_image(params, view, r.image))
    s = view.stem
    write_image(layout.gt("clean_image", s), to_uint8(np.clip(r.image, 0.0, 1.0)))
    valid = r.valid.astype(np.float32)
    write_exr(layout.gt("normal_map", s), {"N": r.normals, "valid": valid})
    write_exr(layout.gt("depth_map", s), {"depth": r.depth, "valid": valid})
    write_exr(layout.gt("reflectivity_map", s), {"reflectivity": r.reflectivity})
    glass, frame = r.material == Material.GLASS, r.material == Material.FRAME
    write_mask(layout.gt("glass_mask", s), glass)
    write_mask(layout.gt("frame_mask", s), frame)
    write_mask(layout.gt("facade_mask", s), glass | frame)
    return [raw] + [layout.gt(k, s) for k in PER_VIEW_GT]


def run(layout: BuildingLayout, params: SynthesizeParams, settings: RunSettings) -> StageReport:
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.synthetic.simulate import build_simulator, render_all

    check_raw_is_ours(layout)
    layout.gt_dir.mkdir(parents=True, exist_ok=True)  # first: marks the raw/ about to be written as ours
    t0 = time.perf_counter()
    sim = build_simulator(params)
    t_build = time.perf_counter() - t0
    outputs = write_truth(layout, sim)
    t1 = time.perf_counter()
    files, xyz, rgb, coarse_stats = write_coarse(layout, sim)
    outputs += files + write_models(layout, sim, xyz, rgb)
    t_coarse = time.perf_counter() - t1

    def sink(view: View, r: ViewRender) -> None:
        outputs.extend(write_view(layout, params, view, r))

    with tqdm(total=len(sim.views), desc=NAME, unit="view") as bar:
        timings = render_all(sim, sink, lambda done, total: bar.update(1))
    counts = sim.tracer.counts
    metrics = {
        "uav_views": sum(v.kind == "uav" for v in sim.views),
        "frontal_views": sum(v.kind == "frontal" for v in sim.views),
        "panels": len(sim.scene.panels),
        "triangles": len(sim.scene.mesh.triangles),
        "primary_rays": counts.primary,
        "secondary_rays": counts.secondary,
        "ground_truth_rays": counts.ground_truth,
        "build_s": round(t_build, 3),
        "coarse_and_models_s": round(t_coarse, 3),
        "render_s": round(timings["render_s"], 3),
        "write_views_s": round(timings["write_s"], 3),
        **coarse_stats,
    }
    return StageReport(outputs=outputs, metrics=metrics)


if __name__ == "__main__":
    raise SystemExit(main(sys.modules[__name__]))
