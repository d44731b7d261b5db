"""facade-batch: buildings on a LocalCluster give the serial DAG's outputs; a worker killed mid-stage and
a building with a broken raw/ leave the rest of the batch to complete; the pieces those rest on (the
guard that ends a dead worker's stage, the one-line errors, the Slurm jobs) one by one."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from facade_pipeline.batch import record, task
from facade_pipeline.batch.task import check_data_root, error_line
from facade_pipeline.config import config_dir, load_building_config
from facade_pipeline.errors import ConfigError
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import damaged_outputs, read_manifest
from tests.helpers import process_alive

REPO = Path(__file__).resolve().parents[2]


def batch(args, env, **kw):
    return subprocess.run([sys.executable, "-m", "facade_pipeline.batch", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=900, **kw)


@pytest.fixture
def configs(tmp_path):
    """A copy of configs/ with a real building whose raw/ is broken (no COLMAP model)."""
    cfg = tmp_path / "configs"
    shutil.copytree(config_dir(), cfg)
    (cfg / "buildings" / "broken.toml").write_text('[building]\nkind = "real"\ndescription = "test"\n')
    env = {**os.environ, "FACADE_CONFIG_DIR": str(cfg), "TQDM_DISABLE": "1", "PYTHONPATH": str(REPO)}
    return cfg, env


def test_the_guard_ends_its_command_when_its_parent_dies(tmp_path):
    """A worker killed with SIGKILL runs no code: the guard it started must kill the stage's whole process
    group (doit and the stage), or they would go on holding the building."""
    pidfile = tmp_path / "grandchild"
    parent = subprocess.Popen([
        sys.executable, "-c",
        "import subprocess, sys; subprocess.run([sys.executable, '-m', 'facade_pipeline.batch.guard', "
        f"'sh', '-c', 'sleep 300 & echo $! > {pidfile}; wait'])",
    ], cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    deadline = time.monotonic() + 60
    while not (pidfile.is_file() and pidfile.read_text().strip()):
        assert time.monotonic() < deadline
        time.sleep(0.1)
    sleeper = int(pidfile.read_text())
    os.kill(sleeper, 0)  # running
    parent.kill()
    parent.wait()
    deadline = time.monotonic() + 30
    while process_alive(sleeper):
        assert time.monotonic() < deadline, "the guarded command outlived its worker"
        time.sleep(0.1)


def test_the_error_line_is_the_stages_own():
    text = ("-- synthesize\nWARNING facade_pipeline: something\n"
            "import_photogrammetry: /d/b/raw/sparse/0: expected a COLMAP model, found no files\n")
    assert error_line(text, "import_photogrammetry", 2) == (
        "import_photogrammetry: /d/b/raw/sparse/0: expected a COLMAP model, found no files")
    crash = "Traceback (most recent call last):\n  File x\nZeroDivisionError: division by zero\n#####\n"
    assert error_line(crash, "rectify", 1) == "ZeroDivisionError: division by zero"
    assert error_line("", "rectify", 137) == "exit code 137, no output"


def test_a_stage_runs_at_the_budget_the_batch_chose_not_the_workers_own(tmp_path, monkeypatch):
    seen = {}

    def fake_run(command, env, **kw):
        seen.update(env)
        return subprocess.CompletedProcess(command, 0)

    monkeypatch.setenv("FACADE_BUDGET", "cpu")  # the worker's own shell
    monkeypatch.setattr(task.subprocess, "run", fake_run)
    code = task._run_doit("demo", "train_gs", str(tmp_path), str(config_dir()), None, None,
                          tmp_path / "log.txt", "gpu")
    assert code == 0 and seen["FACADE_BUDGET"] == "gpu"


def test_a_worker_that_cannot_see_the_data_root_says_which_path_and_worker(tmp_path):
    missing = tmp_path / "not_mounted"
    line = check_data_root(str(missing))
    assert str(missing) in line and "on " in line and "process" in line  # outside a worker: its process
    assert "\n" not in line
    assert check_data_root(str(tmp_path)) is None


def test_status_says_done_running_and_failed(tmp_path):
    a, b = BuildingLayout(tmp_path, "a"), BuildingLayout(tmp_path, "b")
    for lay in (a, b):
        record.start(lay, ["synthesize", "import_photogrammetry", "rectify"])
    record.update(a, "synthesize", "done", ran=True)
    record.update(a, "import_photogrammetry", "running")
    record.update(b, "synthesize", "failed", error="synthesize: x.toml: expected y, found z")
    assert record.recorded_buildings(tmp_path) == ["a", "b"]
    line = record.building_status(a).line()
    assert line.startswith("a: running import_photogrammetry (pid ") and "(1 of 3 stages done)" in line
    assert record.building_status(b).line() == (
        "b: failed at synthesize: synthesize: x.toml: expected y, found z (0 of 3 stages done)")
    # a stage recorded as running by a process of this host that is gone (a killed batch) failed
    stages = record.read_record(a)
    dead = subprocess.Popen(["true"])
    dead.wait()
    stages["import_photogrammetry"]["pid"] = dead.pid
    record.write_record(a, stages)
    assert record.building_status(a).line().startswith("a: failed at import_photogrammetry: its process")


def test_slurm_jobs_come_from_the_batch_table_which_no_building_sets(tmp_path, configs):
    cfg, _ = configs
    from facade_pipeline.batch.cluster import slurm_cluster

    cluster = slurm_cluster()
    try:
        script = cluster.job_script()
    finally:
        cluster.close()
    assert "--cpus-per-task=8" in script and "--gres=gpu:1" in script and "-t 24:00:00" in script
    assert "--nthreads 2" in script and "--resources stage=1,GPU=1" in script
    (cfg / "buildings" / "broken.toml").write_text(
        '[building]\nkind = "real"\ndescription = "test"\n[batch.slurm]\ncores = 4\n')
    with pytest.raises(ConfigError, match=r"broken.toml: expected \[batch\] only in default.toml"):
        load_building_config("broken", cfg)


def _outputs(root: Path, building: str, stages: list[str]) -> dict[str, dict[str, str]]:
    return {s: read_manifest(BuildingLayout(root, building), s).outputs for s in stages}


@pytest.mark.slow
def test_two_buildings_on_two_workers_give_the_serial_dags_outputs(tmp_path, configs):
    _, env = configs
    stages = ["synthesize", "import_photogrammetry", "rectify"]
    out = batch(["run", "synthetic64", "synthetic64_curved", "--workers", "2", "--until", "rectify",
                 "--data-root", str(tmp_path / "batch")], env)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "2 of 2 buildings done" in out.stdout
    for b in ("synthetic64", "synthetic64_curved"):
        serial = subprocess.run([sys.executable, "-m", "doit", "-f", str(REPO / "dodo.py"), "rectify",
                                 f"building={b}", f"data_root={tmp_path / 'serial'}"],
                                cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
        assert serial.returncode == 0, serial.stdout + serial.stderr
        assert _outputs(tmp_path / "batch", b, stages) == _outputs(tmp_path / "serial", b, stages)
    # a second batch finds everything up to date
    again = batch(["run", "synthetic64", "synthetic64_curved", "--workers", "2", "--until", "rectify",
                   "--data-root", str(tmp_path / "batch")], env)
    assert again.returncode == 0 and again.stdout.count("up to date") == 6, again.stdout + again.stderr


@pytest.mark.slow
def test_a_killed_worker_is_retried_and_a_broken_building_fails_alone(tmp_path, configs):
    """synthetic64's worker is killed while synthesize runs: the stage is retried and the building
    completes, its outputs whole; 'broken' (no COLMAP model in raw/) fails with its one line."""
    _, env = configs
    root = tmp_path / "data"
    (root / "broken" / "raw" / "images").mkdir(parents=True)
    proc = subprocess.Popen([sys.executable, "-m", "facade_pipeline.batch", "run", "synthetic64", "broken",
                             "--workers", "2", "--until", "import_photogrammetry", "--data-root", str(root)],
                            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    layout = BuildingLayout(root, "synthetic64")
    deadline = time.monotonic() + 300
    # into the stage's doit run: synthesize has written its first file (the truth comes before the
    # cameras, the coarse model and the rendered views), so the kill finds it midway
    while not (record.read_record(layout).get("synthesize", {}).get("state") == "running"
               and layout.gt("scene").is_file()):  # fmt: skip
        assert time.monotonic() < deadline and proc.poll() is None, proc.communicate()
        time.sleep(0.01)
    killed = record.read_record(layout)["synthesize"]["pid"]
    os.kill(killed, signal.SIGKILL)
    stdout, stderr = proc.communicate(timeout=900)
    assert proc.returncode == 1, stdout + stderr  # one building failed
    assert "1 of 2 buildings done" in stdout
    said = [line for line in stderr.splitlines() if line.startswith("facade-batch: broken failed: ")]
    assert len(said) == 1 and "raw" in said[0], stderr
    entry = record.read_record(layout)["synthesize"]
    assert entry["state"] == "done" and entry["pid"] != killed
    for stage in ("synthesize", "import_photogrammetry"):
        read_manifest(layout, stage)
        assert damaged_outputs(layout, stage, full_hash=True) == []
    assert not [p for p in layout.root.rglob(".tmp-*")]
    status = batch(["status", "--data-root", str(root)], env).stdout
    assert "synthetic64: done (2 of 2 stages done)" in status
    assert "broken: failed at import_photogrammetry: import_photogrammetry: " in status
    assert json.loads(BuildingLayout(root, "broken").path("batch_record").read_text())["stages"][
        "import_photogrammetry"]["state"] == "failed"
