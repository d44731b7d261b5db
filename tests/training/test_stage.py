"""The train_gs stage under the contract, on synthetic64 with upstream outputs built from gt/ (the true
mesh as the corrected mesh, true normals and masks as the baked maps)."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
import torch

from facade_pipeline.bake.maps import BakedPrior
from facade_pipeline.config import RunSettings, available_buildings, load_building_config
from facade_pipeline.errors import InputError, UpstreamMissingError
from facade_pipeline.io.atomic import write_json
from facade_pipeline.io.images import write_mask
from facade_pipeline.io.meshes import make_mesh, write_mesh
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from facade_pipeline.meshing.correct import FRAME, GLASS, write_labels
from facade_pipeline.panels3d.poses import RegisteredPoses
from facade_pipeline.scene import ImportedScene
from facade_pipeline.synthetic.truth import SyntheticTruth
from facade_pipeline.training.params import TrainParams, replace_keys
from facade_pipeline.training.ply import read_ply
from stages import train_gs
from stages._runner import execute
from tests.training.conftest import run_settings, small_params


def _fake_manifest(layout: BuildingLayout, stage: str) -> None:
    write_json(
        layout.manifest(stage), {"stage": stage, "params": {}, "inputs": {}, "outputs": {}, "metrics": {}}
    )


@pytest.fixture
def upstream(synth64, tmp_path) -> BuildingLayout:
    layout = BuildingLayout(tmp_path / "data", "synthetic64")
    shutil.copytree(synth64.root, layout.root)
    layout.path("correct_mesh").parent.mkdir(parents=True)
    layout.path("regularize_poses").parent.mkdir(parents=True)
    RegisteredPoses(()).save(layout.path("regularize_poses"))  # no frontal view registered: poses as imported
    _fake_manifest(layout, "regularize_corners")
    truth = SyntheticTruth.load(layout)
    (gv, gf), (fv, ff) = truth.mesh("glass_mesh"), truth.mesh("frame_mesh")
    both = make_mesh(np.concatenate([gv, fv]), np.concatenate([gf, ff + len(gv)]))
    write_mesh(layout.path("correct_mesh"), both)
    labels = [GLASS] * len(gf) + [FRAME] * len(ff)
    write_labels(layout.path("correct_mesh_labels"), np.array(labels, np.uint8))
    _fake_manifest(layout, "correct_mesh")
    for v in ImportedScene.load(layout).uav_views:
        normal, valid = truth.normal_map(v.stem)
        facade, glass = truth.mask("facade", v.stem), truth.mask("glass", v.stem)
        BakedPrior(v.stem, normal.astype(np.float32), valid, facade=facade, glass=glass).save(layout)
    _fake_manifest(layout, "bake_normals")
    return layout


def test_every_building_has_valid_train_gs_params():
    for building in available_buildings():
        p = load_building_config(building).section("train_gs", TrainParams)
        assert p.__dataclass_params__.frozen and p.iterations > 0
    ci = load_building_config("synthetic64").section("train_gs", TrainParams)
    # the CI run stays short
    assert ci.iterations <= 500 and ci.reflection.mlp.width <= 128 and ci.patch_px > 0


def test_stage_trains_writes_outputs_and_resumes_at_the_end(upstream):
    p, run = small_params(iterations=6), run_settings(raster_backend="auto")
    manifest = execute(train_gs, upstream, p, run)
    m = read_manifest(upstream, "train_gs")
    assert set(m.outputs) == {upstream.relative(t) for t in train_gs.targets(upstream, p)}
    metrics = m.metrics
    assert metrics["iterations"] == 6 and metrics["resumed_from_iteration"] == 0
    assert np.isfinite(metrics["test_psnr"]) and metrics["n_test_views"] == 2
    cols = read_ply(upstream.path("train_ply"))
    assert len(cols["x"]) == metrics["n_gaussians"] and np.all(
        (cols["reflectivity"] >= 0) & (cols["reflectivity"] <= 1)
    )
    split = json.loads(upstream.path("train_split").read_text())
    assert split["test"] == ["uav_0000", "uav_0008"] and len(split["train"]) == 8
    assert "exposure_gain" not in split  # one exposure for all views
    lines = [json.loads(x) for x in upstream.path("train_log").read_text().splitlines()]
    assert [x["iteration"] for x in lines[:-1]] == [5, 6] and "evaluation" in lines[-1]
    refl = torch.load(upstream.path("train_reflection"), weights_only=True)
    assert refl["model"] == "mlp" and refl["config"]["width"] == p.reflection.mlp.width and refl["state_dict"]
    ply_bytes = upstream.path("train_ply").read_bytes()
    # a rerun with the same parameters and inputs resumes from the final checkpoint: same outputs
    again = execute(train_gs, upstream, p, run)
    assert again["metrics"]["resumed_from_iteration"] == 6
    assert upstream.path("train_ply").read_bytes() == ply_bytes
    assert again["outputs"] == manifest["outputs"]
    # settings of how the run goes ([run]: backend, logging, saving) are no parameter, so neither the
    # checkpoint's fingerprint nor doit's config_changed sees them: the checkpoint is resumed
    assert not {f.name for f in dataclasses.fields(RunSettings)} & set(manifest["params"])
    other_run = run_settings(raster_backend="torch", log_every=3, checkpoint_every=2)
    assert execute(train_gs, upstream, p, other_run)["metrics"]["resumed_from_iteration"] == 6
    # any setting that changes the result changes the fingerprint, in the nested tables too
    for change in ({"reflection.model": "envmap"}, {"reflection.proxy.cell": 0.03}, {"lr.proxy": 0.2},
                   {"densify.grad_threshold": 1e-3}, {"hf_steps": 2}):  # fmt: skip
        assert train_gs.fingerprint(upstream, replace_keys(p, change)) != train_gs.fingerprint(upstream, p)
    # other parameters: the old checkpoint is not trusted, training starts over
    other = execute(train_gs, upstream, dataclasses.replace(p, iterations=3, exposure_estimate=True), run)
    assert other["metrics"]["resumed_from_iteration"] == 0 and other["metrics"]["iterations"] == 3
    gains = json.loads(upstream.path("train_split").read_text())["exposure_gain"]
    assert sorted(gains) == sorted(split["train"]) and all(len(g) == 3 and g[0] > 0 for g in gains.values())


def test_stage_rejects_bad_or_missing_inputs(upstream):
    p = small_params(iterations=2)
    stem = ImportedScene.load(upstream).uav_views[3].stem
    bad = upstream.path("bake_glass_mask", stem=stem)
    write_mask(bad, np.ones((10, 12), bool))
    with pytest.raises(InputError, match=stem):
        execute(train_gs, upstream, p)
    upstream.path("bake_normal_map", stem=stem).unlink()
    with pytest.raises(InputError, match="normals"):
        train_gs.inputs(upstream, p)
    upstream.manifest("bake_normals").unlink()
    with pytest.raises(UpstreamMissingError, match="bake_normals"):
        train_gs.inputs(upstream, p)
