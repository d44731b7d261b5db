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


def _cmd(args: list[str], data_root: Path) -> list[str]:
    return [sys.executable, "-m", "doit", "-f", str(REPO / "dodo.py"), *args, f"data_root={data_root}"]


def doit(args: list[str], env: dict, data_root: Path) -> str:
    cmd = _cmd(args, data_root)
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
    buildings = ("synthetic64", "synthetic64_curved")
    # the two buildings' DAGs share nothing (each has its own folder and .doit.db): run them side by side
    procs = [
        subprocess.Popen(
            _cmd(["segment_panels", f"building={b}"], tmp / "data"),
            cwd=REPO,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for b in buildings
    ]
    for proc in procs:
        log = proc.communicate(timeout=900)[0]
        assert proc.returncode == 0, log
    return {b: (BuildingLayout(tmp / "data", b), env) for b in buildings}
