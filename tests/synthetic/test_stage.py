"""The synthesize stage under the runner's contract: every output, the manifest, bit-identical reruns,
refusal to overwrite a user's raw/, and raw/ that the import stage accepts."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from facade_pipeline.errors import InputError
from facade_pipeline.io.colmap import read_reconstruction, registered_images
from facade_pipeline.io.exr import read_exr
from facade_pipeline.io.images import image_size, read_image, read_mask
from facade_pipeline.layout import BuildingLayout
from stages import load_stage
from stages._runner import execute
from tests.synthetic.conftest import tiny

synthesize = load_stage("synthesize")


def _params():
    return tiny(uav_count=2, size_px=32)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    layout = BuildingLayout(root, "tiny")
    manifest = execute(synthesize, layout, _params())
    return layout, manifest


def test_writes_every_target_and_the_manifest_last(built):
    layout, manifest = built
    assert layout.manifest("synthesize").is_file()
    targets = {layout.relative(p) for p in synthesize.targets(layout, _params())}
    assert targets == set(manifest["outputs"])
    assert all((layout.root / rel).is_file() for rel in targets)
    on_disk = {layout.relative(p) for p in layout.root.rglob("*") if p.is_file()}
    assert on_disk == targets | {"gt/manifest.json"}
    assert synthesize.inputs(layout, _params()) == [] and manifest["inputs"] == {}
    m = manifest["metrics"]
    assert m["uav_views"] == 2 and m["frontal_views"] >= 1 and m["secondary_rays"] > 0


def test_outputs_are_consistent(built):
    layout, manifest = built
    rec = read_reconstruction(layout.raw_sparse_dir)
    names = [im.name for im in registered_images(rec)]
    assert names == ["uav_0000.png", "uav_0001.png"]
    assert all(image_size(layout.raw_image(n)) == (32, 32) for n in names)
    frontal = [im.name for im in registered_images(read_reconstruction(layout.raw_frontal_sparse_dir))]
    assert frontal and all(layout.raw_frontal_image(n).is_file() for n in frontal)
    for stem in [n[:-4] for n in names + frontal]:
        normals = read_exr(layout.gt("normal_map", stem))
        depth = read_exr(layout.gt("depth_map", stem))
        refl = read_exr(layout.gt("reflectivity_map", stem))["reflectivity"]
        for arr in (*normals.values(), *depth.values(), refl):
            assert np.isfinite(arr).all()
        valid = normals["valid"] > 0.5
        assert np.allclose(np.linalg.norm(normals["N"][valid], axis=-1), 1.0, atol=1e-5)
        assert np.all(depth["depth"][valid] > 0)
        glass, frame = read_mask(layout.gt("glass_mask", stem)), read_mask(layout.gt("frame_mask", stem))
        assert np.array_equal(read_mask(layout.gt("facade_mask", stem)), glass | frame)
        assert np.array_equal(refl > 0, glass)
        assert read_image(layout.gt("clean_image", stem)).shape == (32, 32, 3)
    panels = json.loads(layout.gt("panels").read_text())["panels"]
    assert len(panels) == 12 and len(panels[0]["corners"]) == 4
    scene = json.loads(layout.gt("scene").read_text())
    assert scene["effects"] == list(_params().effects)


def test_same_seed_is_bit_identical_and_another_seed_is_not(built, tmp_path):
    layout, manifest = built
    again = execute(synthesize, BuildingLayout(tmp_path, "tiny"), _params())
    assert again["outputs"] == manifest["outputs"]
    other = execute(synthesize, BuildingLayout(tmp_path, "other"), dataclasses.replace(_params(), seed=1))
    differing = [k for k in manifest["outputs"] if other["outputs"][k] != manifest["outputs"][k]]
    assert any(k.startswith("raw/images/") for k in differing) and "raw/coarse_mesh.ply" in differing


def test_rerun_replaces_outputs_of_an_earlier_configuration(tmp_path):
    layout = BuildingLayout(tmp_path, "tiny")
    execute(synthesize, layout, tiny(uav_count=3, size_px=32))
    manifest = execute(synthesize, layout, _params())
    assert not layout.raw_image("uav_0002.png").exists()
    assert {layout.relative(p) for p in layout.root.rglob("*") if p.is_file()} == set(manifest["outputs"]) | {
        "gt/manifest.json"
    }


def test_refuses_to_write_into_a_users_raw(tmp_path):
    layout = BuildingLayout(tmp_path, "real")
    layout.raw_images_dir.mkdir(parents=True)
    (layout.raw_images_dir / "DJI_0001.JPG").write_bytes(b"user data")
    with pytest.raises(InputError, match="raw"):
        execute(synthesize, layout, _params())
    assert (layout.raw_images_dir / "DJI_0001.JPG").read_bytes() == b"user data"
    assert not layout.gt_dir.exists()


def test_import_stage_accepts_the_raw_folder(built, tmp_path):
    import shutil

    from facade_pipeline.config import load_building_config

    shutil.copytree(built[0].root, tmp_path / "tiny")
    layout = BuildingLayout(tmp_path, "tiny")
    stage = load_stage("import_photogrammetry")
    params = load_building_config("synthetic64").section(stage.NAME, stage.Params)
    before = {p: p.read_bytes() for p in layout.raw_dir.rglob("*") if p.is_file()}
    manifest = execute(stage, layout, params)
    assert manifest["outputs"]
    assert before == {p: p.read_bytes() for p in layout.raw_dir.rglob("*") if p.is_file()}
