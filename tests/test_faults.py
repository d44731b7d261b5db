"""What a real machine does to a run: folders on other disks (symlinks), a person's own files in a stage
folder, outputs damaged after the run, two runs at once, a full disk, a damaged checkpoint, metrics that
cannot be computed. Each gives a correct run or one clear line; nothing outside a stage's outputs is lost."""

from __future__ import annotations

import errno
import json
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import types
from pathlib import Path

import pytest

from facade_pipeline.config import config_dir, default_params, default_run_settings
from facade_pipeline.errors import InputError
from facade_pipeline.io.lock import acquire, lock_fds, release
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import build_manifest, damaged_outputs, read_manifest
from stages import import_photogrammetry as imp
from stages._runner import StageReport, execute, main
from tests.helpers import make_raw, process_alive, synthetic_reconstruction

REPO = Path(__file__).resolve().parents[1]
PARAMS = default_params("import_photogrammetry", imp.Params)


def _doit(args, env, data_root, check=True):
    cmd = [sys.executable, "-m", "doit", "-f", str(REPO / "dodo.py"), *args, f"data_root={data_root}"]
    out = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    if check:
        assert out.returncode == 0, out.stdout + out.stderr
    return out


@pytest.fixture
def real(tmp_path):
    cfg = tmp_path / "configs"
    shutil.copytree(config_dir(), cfg)
    (cfg / "buildings" / "faults.toml").write_text('[building]\nkind = "real"\ndescription = "test"\n')
    layout = BuildingLayout(tmp_path / "data", "faults")
    make_raw(layout, frontal=True)
    env = {**os.environ, "FACADE_CONFIG_DIR": str(cfg), "TQDM_DISABLE": "1"}
    return layout, env, cfg


def test_symlinked_photos_and_stage_folder_work_and_keep_a_persons_files(layout, tmp_path):
    """raw/images and 01_import on 'another disk'; a note of the user's in the stage folder survives reruns,
    a stale output of the stage does not."""
    make_raw(layout)
    other = tmp_path / "other_disk"
    other.mkdir()
    shutil.move(layout.raw_images_dir, other / "images")
    layout.raw_images_dir.symlink_to(other / "images")
    (other / "01_import").mkdir()
    layout.stage_dir("import_photogrammetry").symlink_to(other / "01_import")
    note = other / "01_import" / "notes.txt"
    note.write_text("mine")
    execute(imp, layout, PARAMS)
    m = read_manifest(layout, "import_photogrammetry")
    assert all(not rel.startswith("..") for rel in [*m.inputs, *m.outputs])
    assert any(rel.startswith("raw/images/") for rel in m.inputs)
    execute(imp, layout, PARAMS)
    assert note.read_text() == "mine"
    assert layout.stage_dir("import_photogrammetry").is_symlink()


def test_a_persons_file_named_like_an_output_survives_a_rerun(layout):
    """A copy a person keeps beside the outputs, under a name of the stage's own patterns, is not the
    stage's: only what its last manifest listed is deleted."""
    make_raw(layout)
    execute(imp, layout, PARAMS)
    backup = layout.import_image("frontal_0001_backup")
    backup.write_bytes(b"a person's copy")
    execute(imp, layout, PARAMS)
    assert backup.read_bytes() == b"a person's copy"


def test_stale_sweep_removes_what_the_last_manifest_listed(layout):
    make_raw(layout)
    execute(imp, layout, PARAMS)
    m = read_manifest(layout, "import_photogrammetry")
    odd = layout.stage_dir("import_photogrammetry") / "extra" / "odd.bin"  # matches no pattern of the stage
    odd.parent.mkdir()
    odd.write_bytes(b"x")
    data = m.data | {"outputs": {**m.outputs, "01_import/extra/odd.bin": "0" * 64}}
    m.path.write_text(json.dumps(data))  # as if an earlier run had written it
    execute(imp, layout, PARAMS)
    assert not odd.exists() and not odd.parent.exists()


def test_a_rerun_interrupted_before_its_manifest_keeps_the_list_of_what_to_remove(layout, monkeypatch):
    """Run A lists a file; a rerun is interrupted after deleting A's manifest; the next run still removes
    A's file (the list was kept beside the manifest) and leaves the person's file."""
    make_raw(layout)
    execute(imp, layout, PARAMS)
    m = read_manifest(layout, "import_photogrammetry")
    odd = layout.stage_dir("import_photogrammetry") / "odd.bin"
    odd.write_bytes(b"x")
    mine = layout.stage_dir("import_photogrammetry") / "mine.bin"
    mine.write_bytes(b"y")
    m.path.write_text(json.dumps(m.data | {"outputs": {**m.outputs, "01_import/odd.bin": "0"}}))

    def interrupted(*args):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(imp, "run", interrupted)
        with pytest.raises(KeyboardInterrupt):
            execute(imp, layout, PARAMS)
    assert not m.path.exists() and layout.previous_outputs("import_photogrammetry").is_file()
    execute(imp, layout, PARAMS)
    assert not odd.exists() and mine.read_bytes() == b"y"
    assert not layout.previous_outputs("import_photogrammetry").exists()


def test_a_listed_path_outside_the_stage_folder_is_never_deleted(layout):
    make_raw(layout)
    execute(imp, layout, PARAMS)
    m = read_manifest(layout, "import_photogrammetry")
    photo = next(layout.raw_images_dir.iterdir())
    outside = {layout.relative(photo): "0", "01_import/../raw/coarse_mesh.ply": "0"}
    m.path.write_text(json.dumps(m.data | {"outputs": {**m.outputs, **outside}}))
    before = {p: p.read_bytes() for p in layout.raw_dir.rglob("*") if p.is_file()}
    execute(imp, layout, PARAMS)
    assert {p: p.read_bytes() for p in layout.raw_dir.rglob("*") if p.is_file()} == before


def test_a_stage_folder_on_a_disk_that_is_not_there_stops_before_any_work(layout, tmp_path, monkeypatch):
    make_raw(layout)
    layout.stage_dir("import_photogrammetry").symlink_to(tmp_path / "unmounted" / "01_import")
    monkeypatch.setattr(imp, "inputs", lambda *a: pytest.fail("the stage started its work"))
    with pytest.raises(InputError) as e:
        execute(imp, layout, PARAMS)
    assert "01_import: expected a stage folder" in str(e.value) and "unmounted/01_import" in str(e.value)
    assert "not mounted" in str(e.value)


def test_an_unreadable_mesh_is_one_line_and_nothing_on_the_terminal(tmp_path, capfd):
    """open3d's PLY reader prints a line per bad element from C++ (40 for a cut-short mesh): kept off the
    terminal, the first one is quoted in the error."""
    from facade_pipeline.io.meshes import read_mesh, read_points, write_mesh

    good = tmp_path / "mesh.ply"
    import open3d as o3d

    write_mesh(good, o3d.geometry.TriangleMesh.create_sphere(resolution=20))
    cut = tmp_path / "cut.ply"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    capfd.readouterr()
    for read in (read_mesh, read_points):
        with pytest.raises(InputError, match=r"cut.ply: expected .*found a damaged or truncated file \(RPly"):
            read(cut)
    assert read_mesh(good).has_triangles()
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def test_damaged_outputs_are_found_cheaply_or_by_hash(layout):
    make_raw(layout)
    execute(imp, layout, PARAMS)
    assert damaged_outputs(layout, "import_photogrammetry") == []
    scene = layout.import_scene
    st = os.stat(scene)
    text = scene.read_bytes()
    scene.write_bytes(text.replace(b"0", b"1", 1))  # same size
    os.utime(scene, ns=(st.st_atime_ns, st.st_mtime_ns))  # and the same time: only a hash sees it
    assert damaged_outputs(layout, "import_photogrammetry") == []
    assert damaged_outputs(layout, "import_photogrammetry", full_hash=True) == ["01_import/scene.json"]
    scene.write_bytes(text)  # touched but the same bytes: not damage
    assert damaged_outputs(layout, "import_photogrammetry") == []
    layout.import_coarse_mesh.write_bytes(b"truncated")
    assert damaged_outputs(layout, "import_photogrammetry") == ["01_import/coarse_mesh.ply"]
    layout.import_coarse_points.unlink()
    assert "01_import/coarse_points.ply" in damaged_outputs(layout, "import_photogrammetry")
    assert damaged_outputs(layout, "import_photogrammetry", editable=("import_coarse_mesh",)) == [
        "01_import/coarse_points.ply"
    ]


def test_doit_reruns_a_stage_whose_output_was_damaged(real):
    layout, env, _ = real
    _doit(["import_photogrammetry", "building=faults"], env, layout.data_root)
    layout.import_coarse_mesh.write_bytes(b"damaged")
    out = _doit(["import_photogrammetry", "building=faults"], env, layout.data_root)
    assert ".  import_photogrammetry" in out.stdout
    assert layout.import_coarse_mesh.read_bytes() != b"damaged"
    # damage that keeps size and time is found with verify=1
    st = os.stat(layout.import_scene)
    text = layout.import_scene.read_bytes()
    layout.import_scene.write_bytes(text.replace(b"0", b"1", 1))
    os.utime(layout.import_scene, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert "-- import_photogrammetry" in _doit(["import_photogrammetry", "building=faults"], env,
                                               layout.data_root).stdout  # fmt: skip
    out = _doit(["import_photogrammetry", "building=faults", "verify=1"], env, layout.data_root)
    assert ".  import_photogrammetry" in out.stdout and layout.import_scene.read_bytes() == text


def test_doit_reruns_a_stage_whose_manifest_is_damaged(real):
    """A manifest that does not parse, or whose tables are not what a stage writes, is not a completed
    run (with ``verify=1`` or without): doit says so in one line and reruns the stage, which writes a good
    one."""
    layout, env, _ = real
    args = ["import_photogrammetry", "building=faults"]
    _doit(args, env, layout.data_root)
    path = layout.manifest("import_photogrammetry")
    text = path.read_text()
    half = text[: len(text) // 2]
    as_list = json.dumps(json.loads(text) | {"outputs": ["01_import/scene.json"]})
    for damaged, verify in ((half, "0"), (half, "1"), (as_list, "0")):
        path.write_text(damaged)
        out = _doit([*args, f"verify={verify}"], env, layout.data_root)
        assert ".  import_photogrammetry" in out.stdout, out.stdout + out.stderr
        said = [ln for ln in out.stderr.splitlines() if "manifest.json" in ln]
        assert len(said) == 1 and "running the stage again" in said[0] and "Traceback" not in out.stderr
        assert read_manifest(layout, "import_photogrammetry").outputs == json.loads(text)["outputs"]
    assert "-- import_photogrammetry" in _doit(args, env, layout.data_root).stdout


def test_a_manifest_that_does_not_hold_a_stages_tables_is_damaged(layout):
    make_raw(layout)
    execute(imp, layout, PARAMS)
    m = read_manifest(layout, "import_photogrammetry")
    for bad in ({"outputs": list(m.outputs)}, {"inputs": {"a": 1}}, {"stage": "evaluate"}):
        m.path.write_text(json.dumps(m.data | bad))
        assert damaged_outputs(layout, "import_photogrammetry") == ["01_import/manifest.json"]
        with pytest.raises(InputError, match="manifest.json: expected"):
            read_manifest(layout, "import_photogrammetry")
    m.path.unlink()  # not completed: doit reruns it for its missing target, nothing is damaged
    assert damaged_outputs(layout, "import_photogrammetry") == []


def test_a_second_run_stops_at_once_and_a_dead_runs_lock_is_taken_over(real):
    layout, env, _ = real
    layout.root.mkdir(parents=True, exist_ok=True)
    # it holds the lock until it is killed, however long the runs below take under load
    holder = subprocess.Popen(
        [sys.executable, "-c",
         "import sys; from facade_pipeline.io.lock import acquire; acquire(sys.argv[1]); "
         "print('held', flush=True); sys.stdin.read()", str(layout.lock)],
        cwd=REPO, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "held"
        out = _doit(["import_photogrammetry", "building=faults"], env, layout.data_root, check=False)
        assert out.returncode == 2 and "Traceback" not in out.stderr
        assert f"another run (pid {holder.pid} on {socket.gethostname()}) holds this building" in out.stderr
        assert not layout.manifest("import_photogrammetry").exists()
        # a stage run by hand is refused as well
        cli = subprocess.run(
            [sys.executable, "-m", "stages", "import_photogrammetry", "--building", "faults", "--data-root",
             str(layout.data_root)], cwd=REPO, env=env, capture_output=True, text=True, timeout=120,
        )  # fmt: skip
        assert cli.returncode == 2 and "holds this building" in cli.stderr
    finally:
        holder.kill()
        holder.wait()
    # the holder was killed: its lock file remains, with its pid, and is taken over
    assert layout.lock.read_text().strip() == f"{holder.pid}@{socket.gethostname()}"
    _doit(["import_photogrammetry", "building=faults"], env, layout.data_root)
    assert layout.manifest("import_photogrammetry").exists()


def test_a_stage_left_by_a_killed_doit_still_holds_the_building(real):
    """``kill -9`` of doit leaves its stage running: that stage holds the lock, so a second doit stops at
    once naming it; once it has finished the building is free."""
    layout, env, _ = real
    make_raw(layout, rec=synthetic_reconstruction(n_images=40, width=480, height=360))
    cmd = [sys.executable, "-m", "doit", "-f", str(REPO / "dodo.py"), "import_photogrammetry",
           "building=faults", f"data_root={layout.data_root}"]  # fmt: skip
    first = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    stage = None
    try:
        deadline = time.monotonic() + 120
        while stage is None:
            assert first.poll() is None and time.monotonic() < deadline, "the stage never took the lock"
            words = layout.lock.read_text().split() if layout.lock.is_file() else []
            pids = [int(w.split("@")[0]) for w in words]
            stage = next((p for p in pids if p != first.pid and process_alive(p)), None)
            time.sleep(0.01)
        os.kill(stage, signal.SIGSTOP)  # the orphan stays mid-run while the second doit tries
        first.kill()
        first.wait()
        second = _doit(["import_photogrammetry", "building=faults"], env, layout.data_root, check=False)
        assert second.returncode == 2 and "Traceback" not in second.stderr, second.stdout + second.stderr
        assert f"another run (pid {stage} on {socket.gethostname()}) holds this building" in second.stderr
    finally:
        if stage is not None:
            os.kill(stage, signal.SIGCONT)
        first.kill()
        first.wait()
    deadline = time.monotonic() + 300
    while process_alive(stage):
        assert time.monotonic() < deadline, "the orphaned stage did not finish"
        time.sleep(0.1)
    _doit(["import_photogrammetry", "building=faults"], env, layout.data_root)
    assert read_manifest(layout, "import_photogrammetry")


def _stage_pid(layout, name: str, doit: subprocess.Popen, timeout: float = 300) -> int:
    """The pid of stage ``name`` once doit has started it and it holds the building with doit."""
    deadline = time.monotonic() + timeout
    while True:
        assert doit.poll() is None and time.monotonic() < deadline, f"{name} never started"
        for holder in layout.lock.read_text().split() if layout.lock.is_file() else []:
            word = holder.split("@")[0]
            try:
                cmdline = Path(f"/proc/{word}/cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if cmdline[1:4] == [b"-m", b"stages", name.encode()] and process_alive(int(word)):
                return int(word)
        time.sleep(0.01)


def test_ctrl_c_during_a_stage_is_its_line_and_exit_130_and_the_completed_stages_stay_done(real):
    """Ctrl-C (SIGINT to the whole job, as a terminal sends it) while the second stage runs: that stage's
    line, exit code 130, no traceback; the first stage is not run again."""
    layout, env, _ = real
    cmd = [sys.executable, "-m", "doit", "-f", str(REPO / "dodo.py"), "rectify", "building=faults",
           f"data_root={layout.data_root}"]  # fmt: skip
    # its own process group, SIGINT handled as in a terminal (a background job would start with it ignored)
    run = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           start_new_session=True,
                           preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # fmt: skip
    try:
        stage = _stage_pid(layout, "rectify", run)
        os.kill(stage, signal.SIGSTOP)  # so that the signal finds it mid-run, however loaded the machine
        os.killpg(run.pid, signal.SIGINT)
        os.kill(stage, signal.SIGCONT)
        out, err = run.communicate(timeout=300)
    finally:
        if run.poll() is None:
            os.killpg(run.pid, signal.SIGKILL)
    assert run.returncode == 130, out + err
    assert "Traceback" not in err and "rectify: interrupted" in err, err
    assert len(err.strip().splitlines()) == 1, err
    again = _doit(["rectify", "building=faults"], env, layout.data_root)
    assert "-- import_photogrammetry" in again.stdout and ".  rectify" in again.stdout


def test_a_disk_that_fills_during_a_stage_is_one_line_and_keeps_the_completed_stages(real, tmp_path):
    """The data root on a small disk that fills while the second stage runs: the stage's one line names the
    file and the free space, doit adds no traceback, and the first stage stays done."""
    layout, env, _ = real
    disk = tmp_path / "disk"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64m", "tmpfs", str(disk)],
                      capture_output=True).returncode != 0:  # fmt: skip
        pytest.skip("a small disk needs a tmpfs mount (root with CAP_SYS_ADMIN), not permitted here")
    try:
        shutil.copytree(layout.root, disk / layout.building)
        small = BuildingLayout(disk, layout.building)
        cmd = [sys.executable, "-m", "doit", "-f", str(REPO / "dodo.py"), "rectify", "building=faults",
               f"data_root={disk}"]  # fmt: skip
        run = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True)  # fmt: skip
        try:
            stage = _stage_pid(small, "rectify", run)
            os.kill(stage, signal.SIGSTOP)
            with open(disk / "ballast", "wb") as f:  # everything that is left
                with pytest.raises(OSError):
                    while True:
                        f.write(b"\0" * (1 << 16))
                        f.flush()
            os.kill(stage, signal.SIGCONT)
            out, err = run.communicate(timeout=300)
        finally:
            run.kill()
            run.wait()
        assert run.returncode == 2 and "Traceback" not in err, out + err
        (line,) = err.strip().splitlines()
        assert line.startswith("rectify: ") and "No space left on device" in line and "MiB free" in line
        assert str(small.stage_dir("rectify")) in line
        (disk / "ballast").unlink()
        again = _doit(["rectify", "building=faults"], env, disk)
        assert "-- import_photogrammetry" in again.stdout and ".  rectify" in again.stdout
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


def test_lock_in_process(tmp_path):
    path = tmp_path / ".lock"
    script = "import sys; from facade_pipeline.io.lock import acquire; print(acquire(sys.argv[1]))"
    fd = acquire(path)
    try:
        # the holder by pid and host: the workers of a batch on several machines share the data root
        assert path.read_text().strip() == f"{os.getpid()}@{socket.gethostname()}"
        # a child handed the lock's descriptor joins it (a doit run's stages) and is listed as a holder
        child = subprocess.run([sys.executable, "-c", script, str(path)], cwd=REPO, capture_output=True,
                               text=True, pass_fds=lock_fds())  # fmt: skip
        assert child.returncode == 0 and child.stdout.strip() == str(fd), child.stderr
        # a child that was not handed it is refused, though the environment names the lock
        for env in (os.environ, {k: v for k, v in os.environ.items() if k != "FACADE_BUILDING_LOCK"}):
            other = subprocess.run([sys.executable, "-c", script, str(path)], cwd=REPO, env=env,
                                   capture_output=True, text=True)  # fmt: skip
            assert other.returncode != 0 and "BuildingBusyError" in other.stderr
            assert f"pid {os.getpid()} on {socket.gethostname()}" in other.stderr
    finally:
        release(fd)
    assert "FACADE_BUILDING_LOCK" not in os.environ
    release(acquire(path))  # free again


def test_config_errors_are_one_line_with_exit_code_2(real):
    layout, env, cfg = real
    toml = cfg / "buildings" / "faults.toml"
    for extra, words in [
        ("[train_gs]\niteratons = 3\n", "unknown key 'train_gs.iteratons'"),
        ("[train_gs]\niterations = -5\n", "'train_gs.iterations' >= 1"),
        ("[train_gs]\ndevice = \"cuda\"\n", "replaced by run.device"),
        ("[synthesize]\nseed = 1\n", 'kind = "synthetic"'),
    ]:
        toml.write_text('[building]\nkind = "real"\ndescription = "test"\n' + extra)
        out = _doit(["building=faults"], env, layout.data_root, check=False)
        assert out.returncode == 2, out.stdout + out.stderr
        assert "Traceback" not in out.stderr and words in out.stderr and "faults.toml" in out.stderr
        assert len(out.stderr.strip().splitlines()) == 1


def test_a_write_that_fails_is_one_line(layout, capsys, monkeypatch):
    """A full disk: the stage names the file and the free space, writes no manifest, exits 2."""
    make_raw(layout)

    def run(layout, params, settings):
        raise OSError(errno.ENOSPC, "No space left on device", str(layout.import_scene))

    stage = types.SimpleNamespace(**{k: getattr(imp, k) for k in ("NAME", "DOC", "Params", "inputs")})
    stage.run = run
    monkeypatch.setattr("stages._runner.load_params", lambda stage, building: PARAMS)
    monkeypatch.setattr("stages._runner.load_settings", lambda building: default_run_settings())
    code = main(stage, ["--building", layout.building, "--data-root", str(layout.data_root)])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "scene.json: No space left on device" in err and "MiB free" in err
    assert not layout.manifest("import_photogrammetry").exists()


def test_metrics_that_cannot_be_computed_are_null_with_a_reason(layout, tmp_path):
    f = layout.root / "01_import" / "x.txt"
    f.parent.mkdir(parents=True)
    f.write_text("x")
    m = build_manifest("import_photogrammetry", layout, {}, [], [f],
                       {"psnr": math.nan, "n": 3, "per_view": [{"psnr": math.inf}, {"psnr": 20.0}]},
                       {}, 1.0, 1.0)  # fmt: skip
    assert m["metrics"] == {"psnr": None, "n": 3, "per_view": [{"psnr": None}, {"psnr": 20.0}]}
    assert set(m["undefined_metrics"]) == {"psnr", "per_view[0].psnr"}
    assert m["output_stats"]["01_import/x.txt"]["size"] == 1


def test_stage_report_outputs_outside_the_building_are_refused(layout):
    """A stage's output must lie in the building (a programming error, caught before any manifest)."""
    make_raw(layout)
    stage = types.SimpleNamespace(**{k: getattr(imp, k) for k in ("NAME", "DOC", "Params", "inputs")})
    stage.run = lambda layout, params, settings: StageReport([layout.data_root / "elsewhere.txt"])
    with pytest.raises(ValueError):
        execute(stage, layout, PARAMS)
    assert not layout.manifest("import_photogrammetry").exists()


def test_an_unreadable_checkpoint_is_moved_aside_and_training_starts_afresh(tmp_path, caplog):
    from facade_pipeline.training.trainer import load_checkpoint

    ckpt = tmp_path / "checkpoint.pt"
    ckpt.write_bytes(b"PK\x03\x04 truncated by a full disk")
    assert load_checkpoint(ckpt, None, None, None, "cpu", "fingerprint") is None
    assert not ckpt.exists() and (tmp_path / "checkpoint.pt.bad").exists()
    assert "unreadable checkpoint" in caplog.text and "iteration 0" in caplog.text


def test_a_read_only_data_root_with_everything_up_to_date_exits_0(real):
    """An archive or a colleague's share: doit says what is up to date and writes nothing."""
    layout, env, _ = real
    _doit(["import_photogrammetry", "building=faults"], env, layout.data_root)
    before = {p: p.stat().st_mtime_ns for p in layout.root.rglob("*")}
    root = str(layout.data_root)
    cmd = [sys.executable, "-m", "doit", "-f", str(REPO / "dodo.py"), "import_photogrammetry",
           "building=faults", f"data_root={root}"]  # fmt: skip
    if os.geteuid() == 0:
        # root writes through permissions: make the data root a read-only mount, in a mount namespace
        if subprocess.run(["unshare", "-m", "true"], capture_output=True).returncode != 0:
            pytest.skip("a read-only data root needs a mount namespace (unshare -m), not permitted here")
        mount = f'mount --bind {root} {root} && mount -o remount,bind,ro {root} && exec "$@"'
        cmd = ["unshare", "-m", "sh", "-c", mount, "sh", *cmd]
    else:
        for p in [layout.data_root, *layout.data_root.rglob("*")]:
            p.chmod(p.stat().st_mode & ~0o222)
    try:
        out = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    finally:
        for p in [layout.data_root, *layout.data_root.rglob("*")]:
            p.chmod(p.stat().st_mode | 0o200)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "-- import_photogrammetry" in out.stdout and "Traceback" not in out.stderr
    assert {p: p.stat().st_mtime_ns for p in layout.root.rglob("*")} == before
