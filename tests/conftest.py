import os

import pytest

from facade_pipeline.layout import BuildingLayout

os.environ.setdefault("TQDM_DISABLE", "1")


@pytest.fixture
def layout(tmp_path):
    """A building folder under a temporary data root."""
    return BuildingLayout(tmp_path / "data", "testbuilding")
