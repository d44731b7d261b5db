import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from facade_pipeline.config import BUDGET_ENV
from facade_pipeline.layout import BuildingLayout

os.environ.setdefault("TQDM_DISABLE", "1")
# The tests check the shipped configs as a fresh shell resolves them: a compute budget chosen in the
# developer's shell would move demo's training keys under them.
os.environ.pop(BUDGET_ENV, None)

REPO = Path(__file__).resolve().parents[1]
#: real photos with truth, beside the checkout (tests that use them skip where they are absent)
GCW_SRC = REPO.parent / "shared" / "real" / "gcw_dev"


@pytest.fixture
def layout(tmp_path):
    """A building folder under a temporary data root."""
    return BuildingLayout(tmp_path / "data", "testbuilding")


@pytest.fixture
def cuda_device():
    """The CUDA device for the GPU tests (marked ``gpu``); skips where there is none."""
    if not torch.cuda.is_available():
        pytest.skip("needs a CUDA device")
    return torch.device("cuda")


def _digest(folder: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            h.update(p.name.encode() + p.read_bytes())
    return h.hexdigest()


@pytest.fixture(scope="session")
def gcw_dev(tmp_path_factory):
    """(layout, env): gcw_dev made from ``GCW_SRC`` by scripts/make_gcw_building.py as a user would bring
    it, and run through regularize_corners with configs/buildings/gcw_dev.toml, once per test run for every
    test on the real photos (the segmentation's and the training's). A test that needs a later stage runs
    doit on it for that stage: what is done stays done. The source folder is only read."""
    from tests.segmentation.conftest import doit

    root = tmp_path_factory.mktemp("gcw")
    before = _digest(GCW_SRC)
    env = {**os.environ, "TQDM_DISABLE": "1"}
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "make_gcw_building.py"), str(GCW_SRC),
                          "--building", "gcw_dev", "--data-root", str(root)], cwd=REPO, env=env,
                         capture_output=True, text=True)  # fmt: skip
    assert out.returncode == 0, out.stderr
    doit(["regularize_corners", "building=gcw_dev"], env, root)
    assert _digest(GCW_SRC) == before
    return BuildingLayout(root, "gcw_dev"), env
