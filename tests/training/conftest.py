"""Fixtures for the training tests: synthetic64 made once per session, training data built from its gt/
(standing in for the bake_normals outputs) and small parameters."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from facade_pipeline.config import RunSettings, default_run_settings, load_building_config
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.training.data import InitGeometry, TrainData, TrainView, split_views
from facade_pipeline.training.params import TrainParams

# The synthetic-data fixtures import the I/O stack (open3d, OpenEXR, pycolmap) inside their bodies, so the
# GPU tests of this folder run on a machine that has only torch (and gsplat).


@pytest.fixture(scope="session")
def synth64(tmp_path_factory) -> BuildingLayout:
    """synthetic64 synthesized and imported into a session folder."""
    from stages import load_stage
    from stages._runner import execute, load_params

    layout = BuildingLayout(tmp_path_factory.mktemp("data"), "synthetic64")
    for name in ("synthesize", "import_photogrammetry"):
        stage = load_stage(name)
        execute(stage, layout, load_params(stage, "synthetic64"))
    return layout


@pytest.fixture(scope="session")
def gcw_train_data(gcw_dev):
    """The test run's gcw_dev (tests/conftest.py) run on through bake_normals, with gcw_dev.toml's training
    parameters and the training data train_gs loads: (layout, params, data)."""
    from stages.train_gs import load_train_data
    from tests.segmentation.conftest import doit

    layout, env = gcw_dev
    doit(["bake_normals", "building=gcw_dev"], env, layout.data_root)
    p = load_building_config("gcw_dev").section("train_gs", TrainParams)
    return layout, p, load_train_data(layout, p)


def gt_view(truth, view) -> TrainView:
    """A training view whose normal prior and masks are the ground truth (what bake_normals approximates),
    from ``truth`` (a ``SyntheticTruth``: local frame)."""
    from facade_pipeline.io.images import read_image

    normals, valid = truth.normal_map(view.stem)
    return TrainView(
        view.stem,
        view.camera,
        read_image(truth.layout.root / view.image).astype(np.float32) / 255.0,
        truth.mask("facade", view.stem),
        truth.mask("glass", view.stem),
        normals.astype(np.float32),
        valid,
    )


def gt_train_data(layout: BuildingLayout, test_every: int = 8, max_views: int | None = None) -> TrainData:
    """Training data from gt/: true normals and masks, the true facade mesh, the coarse points."""
    from facade_pipeline.io.meshes import read_points
    from facade_pipeline.scene import ImportedScene
    from facade_pipeline.synthetic.truth import SyntheticTruth

    scene = ImportedScene.load(layout)
    truth = SyntheticTruth.load(layout, scene.georef_from_local)
    views = tuple(gt_view(truth, v) for v in scene.uav_views[:max_views])
    vertices, triangles = truth.mesh("facade_mesh")
    pcd = read_points(layout.import_coarse_points)
    init = InitGeometry(np.asarray(pcd.points), np.asarray(pcd.colors), vertices, triangles)
    train, test = split_views(len(views), test_every)
    return TrainData(views, train, test, init)


@pytest.fixture(scope="session")
def data64(synth64) -> TrainData:
    return gt_train_data(synth64)


def small_params(**changes) -> TrainParams:
    """synthetic64's parameters made tiny: few splats, small patches, a small MLP. ``changes`` are
    [train_gs] keys, and keys of its tables by prefix: ``densify_interval``, ``mlp_width`` (of
    [train_gs.reflection.mlp]), ``proxy_channels``, ``envmap_height_px``; ``reflection_model`` is
    [train_gs.reflection] model."""
    p = load_building_config("synthetic64").section("train_gs", TrainParams)
    p = dataclasses.replace(
        p,
        iterations=20,
        init_max_points=150,
        init_mesh_samples=150,
        patch_px=16,
        mlp_max_pixels=128,
        exposure_estimate=False,  # one exposure unless a test asks (synthetic64 has no exposure change)
        pose_refinement=False,  # the imported poses unless a test asks
    )
    tables = {
        "densify": dict(interval=5, max_gaussians=400),
        "mlp": dict(width=32, depth=4, fourier_levels=4),
        "proxy": {},
        "envmap": {},
    }
    for key in list(changes):
        prefix, _, rest = key.partition("_")
        if prefix in tables and key != "mlp_max_pixels":
            tables[prefix][rest] = changes.pop(key)
    refl = p.reflection
    refl = dataclasses.replace(
        refl,
        model=changes.pop("reflection_model", refl.model),
        mlp=dataclasses.replace(refl.mlp, **tables["mlp"]),
        proxy=dataclasses.replace(refl.proxy, **tables["proxy"]),
        envmap=dataclasses.replace(refl.envmap, **tables["envmap"]),
    )
    p = dataclasses.replace(p, densify=dataclasses.replace(p.densify, **tables["densify"]), reflection=refl)
    return dataclasses.replace(p, **changes)


def run_settings(**changes) -> RunSettings:
    """default.toml's [run], logging and saving every 5 iterations (the tiny runs' checkpoints)."""
    return dataclasses.replace(default_run_settings(), **({"log_every": 5, "checkpoint_every": 5} | changes))


@pytest.fixture(autouse=True)
def one_thread():
    """Small tensors: one intra-op thread is much faster than two fighting other processes for 2 cores."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
