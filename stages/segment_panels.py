"""Stage ``segment_panels``: glass panels of each frontal view by MAP estimation of the panel grid (paper,
3.1.2), on the rectified image, with the corners mapped back to the original view through the inverse warp.

Reads ``02_rectify`` (rectified image and warps per view) and ``01_import`` (the views' sizes, the original
images for the overlays). Writes the ``03_segment`` hand-off of data_layout.md ("Hand-off formats"):
``corners/{stem}.json``, the authoritative ``masks/{stem}.png`` (255 on panel glass) and
``overlays/{stem}.png``. A view with no facade in it gets ``facade_found: false``, an empty mask,
and is listed in the manifest.
"""

from __future__ import annotations

import os

# Many small dense problems; OpenBLAS threads only contend for the cores there (see stages/rectify.py).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from facade_pipeline.errors import UpstreamMissingError  # noqa: E402
from facade_pipeline.geometry.rectification import ViewRectification, valid_region  # noqa: E402
from facade_pipeline.io.atomic import write_json  # noqa: E402
from facade_pipeline.io.images import read_image, write_image, write_mask  # noqa: E402
from facade_pipeline.layout import BuildingLayout  # noqa: E402
from facade_pipeline.manifest import read_manifest  # noqa: E402
from facade_pipeline.scene import ImportedScene, View  # noqa: E402
from facade_pipeline.segmentation.panels import (  # noqa: E402
    Panel,
    SegmentParams,
    inside_quads,
    segment_image,
)
from stages._runner import StageReport, main  # noqa: E402

NAME = "segment_panels"
DOC = "find the glass panels of each frontal view (MAP panel grid): corners, panel mask, overlay"
UPSTREAM: tuple[str, ...] = ("rectify", "import_photogrammetry")


@dataclass(frozen=True)
class Params(SegmentParams):
    overlay_scale: int
    """The overlay is drawn this many times the view's size (-)."""


def _view_inputs(layout: BuildingLayout, stem: str) -> list[Path]:
    return [
        layout.path("rectify_image", stem=stem),
        layout.path("rectify_mapping", stem=stem),
        layout.import_frontal_image(stem),
    ]


def inputs(layout: BuildingLayout, params: Params) -> list[Path]:
    """The rectified images and warps of a completed rectify run, the frontal views and scene.json."""
    written = set(read_manifest(layout, "rectify").outputs)
    scene = ImportedScene.load(layout)
    files = [layout.import_scene]
    for v in scene.frontal_views:
        for f in _view_inputs(layout, v.stem):
            if f.parent.parent.name == "02_rectify" and layout.relative(f) not in written:
                raise UpstreamMissingError(
                    f,
                    "an output listed in the rectify manifest (run `doit rectify`)",
                    "a view that rectify did not write",
                )
            if not f.is_file():
                raise UpstreamMissingError(f, "a file written by an upstream stage", "no file")
            files.append(f)
    return files


def targets(layout: BuildingLayout, params: Params) -> list[Path]:
    return []  # per-view outputs are only known once the import ran; the manifest lists them


def _to_view(panel: Panel, rect: ViewRectification, width: int, height: int) -> dict:
    """The panel as in data_layout.md, corners mapped back to the original view and kept inside it."""
    back = panel.corners if rect.kind != "curved" else rect.inverse(panel.corners)
    back = np.clip(back, [0.0, 0.0], [float(width), float(height)])
    return {
        "row": panel.row,
        "col": panel.col,
        "corners_px": np.round(back, 3).tolist(),
        "corners_rectified_px": np.round(panel.corners, 3).tolist(),
        "complete": panel.complete,
    }


def panel_labels(panels: list[Panel], rect: ViewRectification, width: int, height: int) -> np.ndarray:
    """Panel index [H, W] of each original pixel (its centre mapped into the rectified image), -1: none."""
    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1)
    if rect.kind == "curved":
        pts = rect.forward(pts)
    return inside_quads([p.corners for p in panels], pts[:, 0], pts[:, 1]).reshape(height, width)


def _overlay(image: np.ndarray, panels: list[Panel], rect: ViewRectification, scale: int) -> np.ndarray:
    """The view, enlarged, with each panel's outline (mapped back: curved where the facade is) and corners."""
    H, W = image.shape[:2]
    out = cv2.resize(image, (W * scale, H * scale), interpolation=cv2.INTER_NEAREST)
    t = np.linspace(0.0, 1.0, 12)[:, None]
    for p in panels:
        c = p.corners
        outline = np.concatenate([c[i] + t * (c[(i + 1) % 4] - c[i]) for i in range(4)])
        if rect.kind == "curved":
            outline = rect.inverse(outline)
        colour = (0, 255, 0) if p.complete else (255, 160, 0)
        cv2.polylines(out, [np.int32(np.rint(outline * scale))], True, colour, 1, cv2.LINE_AA)
        centre = outline.mean(axis=0) * scale
        cv2.putText(
            out,
            f"{p.row},{p.col}",
            (int(centre[0]) - 8, int(centre[1]) + 4),
            cv2.FONT_HERSHEY_PLAIN,
            0.8,
            colour,
            1,
            cv2.LINE_AA,
        )
    return out


def segment_one(layout: BuildingLayout, view: View, params: Params) -> tuple[list[Path], dict]:
    """Segment one view and write its three outputs; returns them and the view's metrics."""
    t0 = time.perf_counter()
    rect = ViewRectification.load(layout.path("rectify_mapping", stem=view.stem))
    W, H = view.camera.width, view.camera.height
    valid = valid_region(rect, W, H)
    centre = view.camera.K[:2, 2][None]  # [1, 2] the principal point, about which frames show parallax
    if rect.kind == "curved":
        centre = rect.forward(centre)
    image = read_image(layout.path("rectify_image", stem=view.stem))
    seg = segment_image(image, params, valid, (float(centre[0, 0]), float(centre[0, 1])))
    labels = panel_labels(seg.panels, rect, W, H)
    found = seg.facade_found and bool((labels >= 0).any())
    panels = seg.panels if found else []
    out = {k: layout.path(k, stem=view.stem) for k in ("segment_corners", "segment_mask", "segment_overlay")}
    write_json(
        out["segment_corners"],
        {
            "image": view.stem,
            "width": W,
            "height": H,
            "rectified": rect.kind == "curved",
            "facade_found": found,
            "panels": [_to_view(p, rect, W, H) for p in panels],
        },
    )
    write_mask(out["segment_mask"], labels >= 0 if found else np.zeros((H, W), bool))
    original = read_image(layout.import_frontal_image(view.stem))
    write_image(out["segment_overlay"], _overlay(original, panels, rect, params.overlay_scale))
    metrics = {
        "facade_found": found,
        "n_panels": len(panels),
        "n_complete": sum(p.complete for p in panels),
        "n_occluded": sum(p.reason == "occluded" for p in panels),
        "rectified": rect.kind == "curved",
        **{k: round(v, 3) if isinstance(v, float) else v for k, v in seg.metrics.items()},
        "seconds": round(time.perf_counter() - t0, 3),
    }
    return list(out.values()), metrics


def run(layout: BuildingLayout, params: Params) -> StageReport:
    views = ImportedScene.load(layout).frontal_views
    outputs: list[Path] = []
    per_view: dict[str, dict] = {}
    for view in tqdm(views, desc="segment_panels: frontal views", unit="img", file=sys.stderr):
        outs, per_view[view.stem] = segment_one(layout, view, params)
        outputs += outs
    return StageReport(
        outputs,
        {
            "n_views": len(views),
            "n_views_with_facade": sum(m["facade_found"] for m in per_view.values()),
            "views_without_facade": [s for s, m in per_view.items() if not m["facade_found"]],
            "n_panels": sum(m["n_panels"] for m in per_view.values()),
            "n_complete_panels": sum(m["n_complete"] for m in per_view.values()),
            "seconds_per_view": round(sum(m["seconds"] for m in per_view.values()) / max(1, len(views)), 3),
            "views": per_view,
        },
    )


if __name__ == "__main__":
    raise SystemExit(main(sys.modules[__name__]))
