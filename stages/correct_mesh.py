"""Stage ``correct_mesh``: geometric correction of the coarse facade mesh with the 3D panels (the paper,
section 3.1.3, Fig. 6b).

Reads ``01_import/coarse_mesh.ply`` and ``04_regularize/panels.json``; writes
``05_correct_mesh/corrected_mesh.ply`` (inserted glass coloured ``panel_color``, coarse vertices keep theirs),
``triangle_labels.npy`` (glass / frame / other per triangle, for the bake's masks) and ``overlay.png`` (shaded
renders of the coarse and the corrected mesh from the first frontal camera).
On synthetic buildings the manifest compares the corrected and the coarse mesh with gt/ (surface distance on
glass and frames, normal error on glass) and says whether the targets are met (gt is read for metrics only).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np

from facade_pipeline.config import Fraction, NonNeg, PosInt, Positive, Range, RunSettings
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from facade_pipeline.meshing.correct import FRAME, LABEL_NAMES, correct_mesh, label_triangles, write_labels
from facade_pipeline.panels3d.model import PanelSet
from facade_pipeline.scene import ImportedScene
from stages._runner import StageReport, main

NAME = "correct_mesh"
DOC = "replace the coarse mesh inside each panel's cuboid by the shrunk 3D panel, keeping the frames"
UPSTREAM: tuple[str, ...] = ("regularize_corners", "import_photogrammetry")
OVERLAY_MIN_WIDTH_PX = 480  # renders of small views are upscaled to at least this width
Scale = Annotated[float, Range(0.0, 1.0, low_open=True)]
"""a factor a panel is scaled by about its centre: 0 would leave nothing of it"""


@dataclass(frozen=True)
class Params:
    shrink_factor: Scale
    """Each panel is shrunk in its surface about its centre by this factor (0-1) before insertion."""
    insert_factor: Scale
    """The panel put in the cuboid's place is the 3D panel scaled about its centre by this factor (0-1):
    1 puts the whole glass back, running on under the kept frames, so no gap is left around it."""
    cuboid_half_depth: Positive
    """The coarse mesh within this distance (of the building's panel pitch, as segment_panels' survey
    measured it) of a shrunk panel along its normal is removed."""
    max_facet_deg: Annotated[float, Range(0.0, 180.0, low_open=True)]
    """Panels on cylindrical parts are split into flat facets spanning at most this angle (deg)."""
    panel_color: tuple[Fraction, Fraction, Fraction]
    """Vertex colour of the inserted glass (0-1)."""
    frame_half_depth: NonNeg
    """Kept coarse triangles inside a part's facade outline and within this distance (of the building's
    panel pitch) of the glass surface are labelled frame (the rest: other)."""
    metric_samples: PosInt | None = None
    """Points sampled on a mesh for the metrics against gt/ (-). Synthetic buildings only (configs/
    synthetic.toml); None: no truth to measure against."""
    metric_max_match_m: Positive | None = None
    """Samples farther than this (m) from every true surface are left out of the metrics."""


def inputs(layout: BuildingLayout, params: Params) -> list[Path]:
    read_manifest(layout, "regularize_corners")
    files = [layout.import_scene, layout.import_coarse_mesh, layout.path("regularize_panels")]
    PanelSet.load(files[-1])
    return files


def truth_metrics(
    layout: BuildingLayout,
    params: Params,
    meshes: dict[str, tuple[np.ndarray, np.ndarray]],
    panel_width_m: float,
) -> dict:
    """Coarse vs corrected against gt/ (synthetic buildings only; metrics, never used to build a mesh)."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.meshing.metrics import surface_errors
    from facade_pipeline.synthetic.truth import SyntheticTruth

    if params.metric_samples is None or params.metric_max_match_m is None:
        return {}
    if not SyntheticTruth.available(layout, "glass_mesh", "frame_mesh"):
        return {}
    gt = SyntheticTruth.load(layout)
    truth = [gt.raycaster("glass_mesh"), gt.raycaster("frame_mesh")]
    body = gt.raycaster("body_mesh") if SyntheticTruth.available(layout, "body_mesh") else None
    out: dict = {
        name: surface_errors(v, f, *truth, params.metric_samples, params.metric_max_match_m, other=body)
        for name, (v, f) in meshes.items()
    }
    out["panel_width_m"] = round(panel_width_m, 4)  # the scale of benchmarks/bench_bake.py's targets
    return {"truth": out}


def _overlay(layout: BuildingLayout, coarse: tuple, fixed: tuple, labels) -> None:
    """Shaded coarse (left) and corrected (right, by label) renders from the first frontal (else UAV) view."""
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.geometry.raycast import MeshRaycaster
    from facade_pipeline.io.images import write_image
    from facade_pipeline.meshing.overlay import scaled_camera, shaded_render, side_by_side, upscale_factor

    scene = ImportedScene.load(layout)
    views = scene.frontal_views or scene.uav_views
    cam = views[0].camera
    cam = scaled_camera(cam, upscale_factor(cam.width, OVERLAY_MIN_WIDTH_PX))
    left = shaded_render(MeshRaycaster(*coarse), cam, None)
    right = shaded_render(MeshRaycaster(*fixed), cam, labels)
    write_image(layout.path("correct_mesh_overlay"), side_by_side(left, right))


NO_PANELS = "no panels: no mesh correction (the coarse mesh is the facade)"


def run(layout: BuildingLayout, params: Params, settings: RunSettings) -> StageReport:
    # imported here, not at the top: doit loads every stage module to build its task list
    from facade_pipeline.io.meshes import make_mesh, read_mesh, write_mesh
    from facade_pipeline.segmentation.building import surveyed_pitch_m

    coarse = read_mesh(layout.import_coarse_mesh)
    panels = PanelSet.load(layout.path("regularize_panels"))
    # the lengths' unit is needed only where there are panels to put in
    pitch = surveyed_pitch_m(layout, needed=bool(panels.panels))
    v, f = np.asarray(coarse.vertices), np.asarray(coarse.triangles)
    fixed = correct_mesh(
        v,
        f,
        panels,
        params.shrink_factor,
        params.cuboid_half_depth * pitch,
        params.max_facet_deg,
        params.insert_factor,
    )
    labels = label_triangles(
        fixed.vertices, fixed.triangles, fixed.is_panel, panels, params.frame_half_depth * pitch
    )
    if not panels.panels:
        # nothing says where the facade is: the coarse mesh is taken for it, opaque, so that training has the
        # pixels it covers (glass is then learnt only through reflectivity, without the panels' geometry)
        labels[:] = FRAME
    colors = np.tile(np.asarray(params.panel_color), (len(fixed.vertices), 1))
    if coarse.has_vertex_colors():
        colors[: len(v)] = np.asarray(coarse.vertex_colors)
    mesh = make_mesh(fixed.vertices, fixed.triangles, colors)
    mesh.remove_unreferenced_vertices()  # keeps the triangles and their order: the labels stay aligned
    mesh.compute_vertex_normals()
    assert len(mesh.triangles) == len(labels)
    out = layout.path("correct_mesh")
    write_mesh(out, mesh)
    write_labels(layout.path("correct_mesh_labels"), labels)
    _overlay(layout, (v, f), (fixed.vertices, fixed.triangles), labels)
    width = float(np.median([p.width_m for p in panels.panels])) if panels.panels else 0.0
    metrics = {
        **({} if panels.panels else {"note": NO_PANELS}),
        "n_panels_inserted": len(panels.panels),
        "coarse_triangles_removed": fixed.n_removed,
        "panel_triangles": int(fixed.is_panel.sum()),
        "triangles": len(mesh.triangles),
        **{f"triangles_{name}": int((labels == k).sum()) for k, name in LABEL_NAMES.items()},
        **truth_metrics(
            layout, params, {"coarse": (v, f), "corrected": (fixed.vertices, fixed.triangles)}, width
        ),
    }
    return StageReport(
        [out, layout.path("correct_mesh_labels"), layout.path("correct_mesh_overlay")], metrics
    )


def targets(layout: BuildingLayout, params: Params) -> list[Path]:
    return [layout.path(k) for k in ("correct_mesh", "correct_mesh_labels", "correct_mesh_overlay")]


if __name__ == "__main__":
    raise SystemExit(main(sys.modules[__name__]))
