"""The real dodo.py on synthetic64: the 3D stages run inside the DAG after segment_panels, and a panel mask
edited by hand reruns regularize_corners and each stage after it whose inputs' content changed."""

from __future__ import annotations

import os
import re
import shutil

import pytest

from facade_pipeline.config import config_dir
from facade_pipeline.io.images import read_mask, write_mask
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest
from stages import PIPELINE
from tests.test_dodo import doit, executed

pytestmark = pytest.mark.skipif(
    "segment_panels" not in PIPELINE, reason="segment_panels is not in the pipeline"
)


def test_hand_edited_mask_reruns_exactly_the_3d_stages(tmp_path):
    cfg = tmp_path / "configs"
    shutil.copytree(config_dir(), cfg)
    toml = cfg / "buildings" / "synthetic64.toml"
    toml.write_text(re.sub(r"(?m)^uav_count = \d+", "uav_count = 3", toml.read_text()))  # fewer views: faster
    env = {**os.environ, "FACADE_CONFIG_DIR": str(cfg), "TQDM_DISABLE": "1"}
    root = tmp_path / "data"
    args = [
        "bake_normals",
        "building=synthetic64",
    ]  # the DAG up to the 3D stages: train_gs is not needed here
    first = executed(doit(args, env, root))
    assert first[-3:] == ["regularize_corners", "correct_mesh", "bake_normals"]
    layout = BuildingLayout(root, "synthetic64")
    mask_path = sorted(layout.path("segment_mask", stem="x").parent.glob("*.png"))[0]
    mask = read_mask(mask_path)
    mask[:3, :3] = ~mask[:3, :3]  # a person touches up a corner of the mask
    write_mask(mask_path, mask)
    stages = ["regularize_corners", "correct_mesh", "bake_normals"]
    before = {s: read_manifest(layout, s) for s in stages}
    rerun = executed(doit(args, env, root))
    # the stage that reads the mask reruns (segment_panels, which wrote it, does not: its code version is
    # derived from its imports, so unrelated edits elsewhere do not touch it); a stage after it reruns
    # exactly when the outputs listed by a stage it reads from changed (bake_normals reads correct_mesh's
    # mesh and regularize_corners' poses; a rerun that writes the same outputs stops there)
    assert rerun[0] == "regularize_corners" and rerun == [s for s in stages if s in rerun], rerun
    after = {s: read_manifest(layout, s) for s in stages}
    for k, stage in enumerate(stages[1:], start=1):
        upstreams = [u for u in stages[:k] if any(path in before[stage].inputs for path in before[u].outputs)]
        assert upstreams, stage  # each of these stages reads an output of one before it
        changed = any(after[u].outputs != before[u].outputs for u in upstreams)
        assert (stage in rerun) == changed, (stage, upstreams, rerun)
    assert executed(doit(args, env, root)) == []
