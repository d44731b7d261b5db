"""Shared fixtures of the evaluation tests: the LPIPS weights (skipped where absent), example images and a
tiny random LPIPS network with the real layout (for tests that must not depend on the weights), and a tiny
trained run of synthetic64 (for the report, the video and the viewer)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from facade_pipeline.bake.maps import BakedPrior
from facade_pipeline.evaluation.lpips import LAYERS, LpipsUnavailable, _Conv, find_lpips_weights
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.training.render import splatting_rasterizer
from facade_pipeline.training.trainer import build_trainer, train
from stages import load_stage
from stages._runner import execute, load_params
from tests.training.conftest import gt_train_data, small_params

#: tolerances keyed on dtype (STYLE 11)
TOL = {np.float64: 1e-10, torch.float64: 1e-10, torch.float32: 1e-5}

SKIP_REASON = ("LPIPS {net} weights not found: set FACADE_LPIPS_DIR or place shared/lpips/ beside the "
               "checkout (see facade_pipeline/evaluation/lpips.py for how to obtain them)")


def weights_or_skip(net: str) -> Path:
    found = find_lpips_weights(net)
    if isinstance(found, LpipsUnavailable):
        pytest.skip(SKIP_REASON.format(net=net))
    return found


@pytest.fixture(scope="session")
def example_images():
    """(ref, p0, p1): the upstream LPIPS example images beside the weights, [3, 64, 64] float64 in [0, 1]."""
    from PIL import Image

    folder = weights_or_skip("alex").parent
    if not (folder / "ex_ref.png").is_file():
        pytest.skip(f"LPIPS example images not in {folder}")

    def read(name):
        a = np.array(Image.open(folder / name).convert("RGB"), dtype=np.float64) / 255.0
        return torch.from_numpy(a).permute(2, 0, 1)

    return read("ex_ref.png"), read("ex_p0.png"), read("ex_p1.png")


def tiny_state_dict(net: str, seed: int = 0, width: int = 4) -> dict[str, torch.Tensor]:
    """Random weights with the real layout (kernel sizes, keys) and ``width`` channels everywhere."""
    g = torch.Generator().manual_seed(seed)
    sd, c_in, taps = {}, 3, []
    for layer in LAYERS[net]:
        if isinstance(layer, _Conv):
            k = layer.kernel
            w = torch.randn(width, c_in, k, k, generator=g) / (k * c_in**0.5)
            sd[f"features.{layer.index}.weight"] = w
            sd[f"features.{layer.index}.bias"] = 0.1 * torch.randn(width, generator=g)
            c_in = width
            if layer.tap:
                taps.append(width)
    for i, c in enumerate(taps):
        sd[f"lin{i}.weight"] = torch.rand(1, c, 1, 1, generator=g)
    return sd


@pytest.fixture(scope="session")
def tiny(tmp_path_factory):
    """synthetic64 imported, five views (0 and 4 held out), 10 training steps of a small MLP model."""
    torch.set_num_threads(1)
    layout = BuildingLayout(tmp_path_factory.mktemp("data"), "synthetic64")
    for name in ("synthesize", "import_photogrammetry"):
        s = load_stage(name)
        execute(s, layout, load_params(s, "synthetic64"))
    data = gt_train_data(layout, test_every=4, max_views=5)
    p = small_params(iterations=10)
    tr = build_trainer(p, data, splatting_rasterizer("auto"), "cpu")
    train(tr)
    for v in data.views:  # the gt masks stand in for bake_normals' masks
        BakedPrior(v.stem, facade=v.facade_mask, glass=v.glass_mask).save(layout)
    return layout, data, tr
