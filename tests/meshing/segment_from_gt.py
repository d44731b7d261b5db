"""03_segment files made from a synthetic building's ground truth, written by the hand-off's own writer
(``ViewSegmentation.save``), for developing and testing the 3D panel stages independently of
`segment_panels`: the true 3D corners of gt/panels.json projected through each frontal camera of
01_import/scene.json, with Gaussian pixel noise; the mask is gt's glass mask of the view."""

from __future__ import annotations

import numpy as np

from facade_pipeline.io.atomic import write_json
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import build_manifest
from facade_pipeline.scene import ImportedScene
from facade_pipeline.segmentation.result import SegmentedPanel, ViewSegmentation
from facade_pipeline.synthetic.truth import SyntheticTruth


def write_segment_from_gt(
    layout: BuildingLayout, noise_px: float = 0.3, seed: int = 0, margin_px: float = 0.5
) -> list[str]:
    """Write 03_segment/corners/{stem}.json and masks/{stem}.png for every frontal view; returns stems."""
    scene = ImportedScene.load(layout)
    truth = SyntheticTruth.load(layout, scene.georef_from_local)
    panels = truth.panels()
    rng = np.random.default_rng(seed)
    stems = []
    for v in scene.frontal_views:
        cam = v.camera
        found = []
        for p in panels:
            uv, z = cam.project(p["corners"])
            if (z <= 0).any() or not np.isfinite(uv).all():
                continue
            if (
                (uv < margin_px).any()
                or (uv[:, 0] > cam.width - margin_px).any()
                or (uv[:, 1] > cam.height - margin_px).any()
            ):
                continue
            found.append((p, uv + rng.normal(0.0, noise_px, uv.shape)))
        rows = sorted({p["row"] for p, _ in found})
        cols = sorted({(p["part"], p["col"]) for p, _ in found})
        seen = tuple(
            SegmentedPanel(rows.index(p["row"]), cols.index((p["part"], p["col"])), uv, uv, True)
            for p, uv in found
        )
        mask = truth.mask("glass", v.stem)
        ViewSegmentation(v.stem, cam.width, cam.height, False, bool(found), "", seen, mask).save(layout)
        stems.append(v.stem)
    _stand_in_manifest(layout, stems, true_pitch_m(panels))
    return stems


def true_pitch_m(panels: list[dict]) -> float:
    """The building's true panel pitch (m), what segment_panels' survey measures: the geometric mean of
    the median distance between the centres of neighbouring panels along a row and along a column."""
    centre = {(p["part"], p["row"], p["col"]): np.mean(p["corners"], axis=0) for p in panels}
    along = [[np.linalg.norm(c - centre[k[0], k[1] + dr, k[2] + dc]) for k, c in centre.items()
              if (k[0], k[1] + dr, k[2] + dc) in centre] for dr, dc in ((0, 1), (1, 0))]
    return float(np.sqrt(np.median(along[0]) * np.median(along[1])))


def _stand_in_manifest(layout: BuildingLayout, stems: list[str], pitch_m: float) -> None:
    """A manifest for 03_segment listing these files, with the building's pitch (``pitch_m``) that the
    survey would have measured, so that downstream stages accept them as the completed segment_panels
    stage they stand in for (a test fixture, never a pipeline output)."""
    outputs = [layout.path(k, stem=s) for s in stems for k in ("segment_corners", "segment_mask")]
    write_json(
        layout.manifest("segment_panels"),
        build_manifest(
            "segment_panels",
            layout,
            {"stand_in": "tests/meshing/segment_from_gt.py"},
            [],
            outputs,
            {"pitch_unit_m": pitch_m},
            {},
            0.0,
            0.0,
        ),
    )
