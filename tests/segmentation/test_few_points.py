"""A frontal view with too few coarse points in it, the stages run directly (no doit): rectify leaves it
unrectified, with the coarse mesh's scale at its centre, and lists it in its manifest; segment_panels still
segments it (in its own pixels)."""

from __future__ import annotations

import importlib
import json
import shutil

import numpy as np

from facade_pipeline.io.images import read_image
from facade_pipeline.io.meshes import make_points, read_points, write_points
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from facade_pipeline.rectification.views import view_points
from facade_pipeline.scene import ImportedScene
from facade_pipeline.segmentation.result import ViewSegmentation
from stages._runner import main

BUILDING = "synthetic64_curved"


def run_stage(name: str, layout: BuildingLayout) -> None:
    """The stage's own entry point (``python -m stages.<name>``), in this process."""
    stage = importlib.import_module(f"stages.{name}")
    assert main(stage, ["--building", BUILDING, "--data-root", str(layout.data_root)]) == 0


def test_view_with_too_few_points_passes_through(scenes, tmp_path, monkeypatch):
    src, env = scenes[BUILDING]
    monkeypatch.setenv("FACADE_CONFIG_DIR", env["FACADE_CONFIG_DIR"])
    monkeypatch.setenv("TQDM_DISABLE", "1")
    layout = BuildingLayout(tmp_path / "data", BUILDING)
    shutil.copytree(src.root / "01_import", layout.root / "01_import")
    scene = ImportedScene.load(layout)
    starved = scene.frontal_views[0]
    pts = np.asarray(read_points(layout.import_coarse_points).points)
    uv, z = starved.camera.project(pts)
    seen = (z > 0) & (uv >= 0).all(axis=1) & (uv <= [starved.camera.width, starved.camera.height]).all(axis=1)
    assert seen.sum() > 100
    keep = ~seen
    keep[np.flatnonzero(seen)[:5]] = True  # five points of the view survive: too few for a surface
    write_points(layout.import_coarse_points, make_points(pts[keep]))
    assert len(view_points(pts[keep], starved.camera)) == 5

    run_stage("rectify", layout)
    m = read_manifest(layout, "rectify").metrics
    assert list(m["views_unrectified"]) == [starved.stem] and m["n_unrectified"] == 1
    assert m["views"][starved.stem]["kind"] == "unrectified"
    assert m["views"][starved.stem]["fit"].startswith("no surface")
    assert all(v["kind"] == "cylinder" for s, v in m["views"].items() if s != starved.stem)
    mapping = json.loads(layout.path("rectify_mapping", stem=starved.stem).read_text())
    assert mapping["kind"] == "unrectified" and mapping["reason"].startswith("no surface")
    # the scale from the coarse mesh's depth: within a few percent of the fitted views' own
    fitted = [v["metres_per_px"] for s, v in m["views"].items() if s != starved.stem]
    assert abs(mapping["metres_per_px"] / np.median(fitted) - 1.0) < 0.25
    assert json.loads(layout.path("rectify_surface", stem=starved.stem).read_text())["status"].startswith(
        "no surface"
    )
    # not rectified: the image is the view, pixel for pixel
    assert np.array_equal(read_image(layout.path("rectify_image", stem=starved.stem)),
                          read_image(layout.import_frontal_image(starved.stem)))

    run_stage("segment_panels", layout)
    seg = ViewSegmentation.load(layout, starved.stem, starved.camera.width, starved.camera.height)
    assert seg.rectified is False
    for p in seg.panels:
        assert np.array_equal(p.corners_px, p.corners_rectified_px)
    assert seg.mask.shape == (starved.camera.height, starved.camera.width)
    seg = read_manifest(layout, "segment_panels").metrics
    assert seg["n_views"] == len(scene.frontal_views) and seg["views"][starved.stem]["rectified"] is False


def test_views_whose_rectified_image_is_too_large_are_skipped_with_the_reason(scenes, tmp_path, monkeypatch):
    """A config whose size cap no rectified image meets (max_size_factor = 0.01): rectify writes no image
    for the views, warns and lists them with the reason; segment_panels gives each an empty result saying
    why."""
    src, env = scenes[BUILDING]
    cfg = tmp_path / "configs"
    shutil.copytree(env["FACADE_CONFIG_DIR"], cfg)
    toml = cfg / "buildings" / f"{BUILDING}.toml"
    toml.write_text(toml.read_text() + "\n[rectify]\nmax_size_factor = 0.01\n")
    monkeypatch.setenv("FACADE_CONFIG_DIR", str(cfg))
    monkeypatch.setenv("TQDM_DISABLE", "1")
    layout = BuildingLayout(tmp_path / "data", BUILDING)
    shutil.copytree(src.root / "01_import", layout.root / "01_import")
    views = ImportedScene.load(layout).frontal_views
    run_stage("rectify", layout)
    m = read_manifest(layout, "rectify").metrics
    assert m["n_skipped"] == len(views) and set(m["views_skipped"]) == {v.stem for v in views}
    assert all("max_size_factor" in r for r in m["views_skipped"].values())
    assert not any(layout.path("rectify_image", stem=v.stem).exists() for v in views)
    run_stage("segment_panels", layout)
    seg = read_manifest(layout, "segment_panels").metrics
    assert seg["n_views_with_facade"] == 0
    for v in views:
        seg = ViewSegmentation.load(layout, v.stem, v.camera.width, v.camera.height)
        assert seg.facade_found is False and "max_size_factor" in seg.reason and seg.panels == ()
        assert not seg.mask.any()
