"""synthetic64 and synthetic64_curved, run once per session through the real DAG (doit) up to
segment_panels."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from facade_pipeline.config import config_dir
from facade_pipeline.layout import BuildingLayout

REPO = Path(__file__).resolve().parents[2]


def doit(args: list[str], env: dict, data_root: Path) -> str:
    cmd = [sys.executable, "-m", "doit", "-f", str(REPO / "dodo.py"), *args, f"data_root={data_root}"]
    out = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout


@pytest.fixture(scope="session")
def scenes(tmp_path_factory):
    """{building: (layout, env)} with every stage up to segment_panels run."""
    tmp = tmp_path_factory.mktemp("segscenes")
    cfg = tmp / "configs"
    shutil.copytree(config_dir(), cfg)
    env = {**os.environ, "FACADE_CONFIG_DIR": str(cfg), "TQDM_DISABLE": "1"}
    out = {}
    for b in ("synthetic64", "synthetic64_curved"):
        doit(["segment_panels", f"building={b}"], env, tmp / "data")
        out[b] = (BuildingLayout(tmp / "data", b), env)
    return out
