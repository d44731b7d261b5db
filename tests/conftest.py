import os

import pytest
import torch

from facade_pipeline.config import BUDGET_ENV
from facade_pipeline.layout import BuildingLayout

os.environ.setdefault("TQDM_DISABLE", "1")
# The tests check the shipped configs as a fresh shell resolves them: a compute budget chosen in the
# developer's shell would move demo's training keys under them.
os.environ.pop(BUDGET_ENV, None)


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
