"""The pipeline DAG for doit. Task creators only build metadata; every stage runs through its own CLI.

    doit                                   # the whole DAG for the default building (demo)
    doit train_gs building=shatin          # one stage and everything it needs
    doit list building=synthetic64         # the stages, in pipeline order
    doit -s import_photogrammetry building=shatin   # one stage alone, upstream not checked
    doit building=shatin data_root=/mnt/uav
    doit building=shatin verify=1          # also hash every output against its manifest (finds damage)

Each stage task declares: the exact files it reads as ``file_dep`` (computed by a hidden ``_inputs:<stage>``
task through doit's ``calc_dep``, from raw/ and the upstream manifests, since they are only known once the
upstream stage ran), its own source files, its targets (the outputs known in advance and its manifest),
``config_changed`` of its parameters, the output hashes its upstream manifests list, and that the outputs its
own manifest lists are still what it wrote (a file whose size or time changed is hashed; one that was damaged
or deleted reruns the stage). An upstream manifest is a dependency through its output hashes only, never its
bytes (which hold wall time and peak memory): an upstream stage that reruns and writes the same outputs
reruns nothing after it. doit's state is kept
per building in ``<building>/.doit.db``. A run holds ``<building>/.lock`` so that a second one stops at once.

A bad config or building name stops here with one line and exit code 2; a stage that stops on bad input
prints its own line and doit exits 2 too, adding nothing (``OneLineReporter``).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import tempfile
from typing import NoReturn

from doit import get_var
from doit.dependency import Dependency, SqliteDB
from doit.exceptions import BaseFail, TaskError, TaskFailed
from doit.reporter import ConsoleReporter
from doit.tools import config_changed

from facade_pipeline.config import load_building_config, to_dict
from facade_pipeline.errors import PipelineError
from facade_pipeline.io.lock import acquire, lock_fds
from facade_pipeline.layout import BuildingLayout
from facade_pipeline.manifest import read_manifest, rerun_reason
from stages import PIPELINE, load_stage
from stages._runner import source_files

#: doit commands that change nothing: they run without the building's lock
READ_ONLY_COMMANDS = {"list", "info", "help", "dumpdb", "tabcompletion"}
DOIT_COMMANDS = READ_ONLY_COMMANDS | {"run", "clean", "forget", "ignore", "auto", "strace", "reset-dep"}


def _stop(message: str) -> NoReturn:
    """One line, no traceback, exit code 2 (doit's code for an error that is not a failed task)."""
    print(f"doit: {message}", file=sys.stderr)
    raise SystemExit(2)


def _command(argv: list[str]) -> str:
    return next((a for a in argv if a in DOIT_COMMANDS), "run")


BUILDING = get_var("building", "demo")
VERIFY = get_var("verify", "0") not in ("0", "", "false", "no")
try:
    LAYOUT = BuildingLayout.for_building(BUILDING, get_var("data_root", None))
    CONFIG = load_building_config(BUILDING)
except (PipelineError, ValueError) as e:
    _stop(str(e))
SYNTHETIC = CONFIG.building.kind == "synthetic"
STAGES = [name for name in PIPELINE if SYNTHETIC or name != "synthesize"]

try:
    LAYOUT.root.mkdir(parents=True, exist_ok=True)
except OSError as e:
    _stop(f"{LAYOUT.root}: expected a building folder that can be made, found {e.strerror}")
DEP_FILE = LAYOUT.doit_db
if not os.access(LAYOUT.root, os.W_OK):
    # a read-only data root (an archive, a colleague's share): say what is up to date from a copy of
    # doit's state; a stage that would have to run fails writing and names the folder
    copy = os.path.join(tempfile.mkdtemp(prefix="facade-doit-"), DEP_FILE.name)
    if DEP_FILE.is_file():
        shutil.copyfile(DEP_FILE, copy)
    DEP_FILE = copy
elif _command(sys.argv[1:]) not in READ_ONLY_COMMANDS:
    try:
        _LOCK = acquire(LAYOUT.lock)  # held until doit exits
    except PipelineError as e:
        _stop(str(e))


def _interrupt(signum, frame) -> NoReturn:
    """Ctrl-C outside a stage: one line, exit code 130; doit writes the state of the stages that completed
    on its way out (SystemExit passes through its task loop, KeyboardInterrupt would end in a traceback)."""
    print("doit: interrupted", file=sys.stderr, flush=True)
    raise SystemExit(130)


_SIGINT_WHILE_A_STAGE_RAN: list[int] = []
if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not ignored (a background job)
    signal.signal(signal.SIGINT, _interrupt)


def _save_state_per_stage() -> None:
    """doit writes its state once, on its way out: a full disk then loses the record of every stage that
    completed in this run (they all rerun) and ends in a traceback. Here each completed stage is written at
    once, and a state that cannot be written is one line naming the file and the free space."""
    save_success = Dependency.save_success
    dump = SqliteDB.dump

    def save_now(self, task, result_hash=None):
        save_success(self, task, result_hash)
        if isinstance(self.backend, SqliteDB):
            try:
                dump(self.backend)  # writes and closes; the next stage reopens it
            except (sqlite3.Error, OSError) as e:
                _say_unsaved(self.backend.name, e)
                with contextlib.suppress(sqlite3.Error):
                    self.backend._conn.close()  # its rows stay marked unsaved, for the next try
            self.backend._conn = self.backend._sqlite3(self.backend.name)

    def dump_or_say(self):
        try:
            dump(self)
        except (sqlite3.Error, OSError) as e:
            if self._dirty:  # (else only the record of a failed stage could not be deleted: it reruns anyway)
                _say_unsaved(self.name, e)

    Dependency.save_success = save_now
    SqliteDB.dump = dump_or_say


def _say_unsaved(path: str, e: Exception) -> None:
    if _UNSAVED_SAID:
        return
    _UNSAVED_SAID.append(path)
    free = shutil.disk_usage(os.path.dirname(path) or ".").free / 2**20
    print(f"doit: {path}: could not write doit's state ({e}; {free:.0f} MiB free): a stage that completed "
          "since it was last written runs again", file=sys.stderr, flush=True)  # fmt: skip


_UNSAVED_SAID: list[str] = []
_save_state_per_stage()


class StageStopped(TaskError):
    """A stage stopped on bad input or config: one line says which file or key and what to do. ``said`` is
    true when the stage's own process already printed that line."""

    def __init__(self, message: str, said: bool):
        super().__init__(message)
        self.said = said


class OneLineReporter(ConsoleReporter):
    """doit's console report, except that a stage stopped on bad input shows only its one line (on stderr),
    not doit's TaskError block with the task's captured output (empty for a stage writing to the terminal)."""

    def add_failure(self, task, fail: BaseFail):
        if isinstance(fail, StageStopped):
            if not fail.said:
                print(fail.message, file=sys.stderr, flush=True)
            return
        super().add_failure(task, fail)


DOIT_CONFIG = {
    "dep_file": str(DEP_FILE),
    "backend": "sqlite3",
    "default_tasks": STAGES,
    "verbosity": 2,  # stages draw progress bars on stderr
    "sort": "definition",  # `doit list` in pipeline order
    "reporter": OneLineReporter,
}


# stages whose inputs include a folder a person adds files to, so the list of files must be made anew each run
RESCANNED = ("import_photogrammetry", "evaluate")


def _inputs_action(stage, params):
    """calc_dep action: the files the stage will read, now that its upstream ran."""

    def compute():
        try:
            return {"file_dep": [str(p) for p in stage.inputs(LAYOUT, params)]}
        except PipelineError as e:
            return StageStopped(f"{stage.NAME}: {e}", said=False)

    return compute


def _run_stage(name):
    """The stage as a child process writing straight to the terminal, so that its progress bar is live
    (doit's command actions pass output on line by line, and a progress bar redraws one line)."""
    command = [
        sys.executable,
        "-m",
        "stages",
        name,
        "--building",
        BUILDING,
        "--data-root",
        str(LAYOUT.data_root),
    ]

    def action():
        if _SIGINT_WHILE_A_STAGE_RAN:  # a Ctrl-C that came while the last stage completed
            _interrupt(signal.SIGINT, None)
        # Ctrl-C reaches the stage too (the terminal signals the whole job): it says so and exits 130; this
        # process waits for it rather than leaving it half-stopped
        previous = signal.getsignal(signal.SIGINT)
        if previous is not signal.SIG_IGN:
            signal.signal(signal.SIGINT, lambda signum, frame: _SIGINT_WHILE_A_STAGE_RAN.append(signum))
        try:
            # the stage shares the building's lock: should this doit die, the stage still holds it
            code = subprocess.run(command, pass_fds=lock_fds()).returncode
        finally:
            signal.signal(signal.SIGINT, previous)
        if code in (130, -signal.SIGINT):  # the stage said it was interrupted
            raise SystemExit(130)
        if code == 2:  # bad input or config: the stage said which in one line
            return StageStopped(f"{name} stopped on bad input", said=True)
        if code != 0:
            return TaskFailed(f"{name} failed (exit code {code})")
        return None

    return action


def _outputs_intact(stage):
    editable = getattr(stage, "EDITABLE", ())

    def check(task, values):
        reason = rerun_reason(LAYOUT, stage.NAME, full_hash=VERIFY, editable=editable)
        if reason:
            print(reason, file=sys.stderr, flush=True)
        return reason is None

    return check


class upstream_outputs_unchanged:
    """doit ``uptodate``: true while the upstream manifests list the same output hashes as when the stage last
    ran (a missing or unreadable manifest counts as a change)."""

    KEY = "_upstream_outputs"

    def __init__(self, upstream: list[str]):
        self.upstream = upstream

    def digest(self) -> str:
        listed = {}
        for u in self.upstream:
            try:
                listed[u] = read_manifest(LAYOUT, u).outputs
            except PipelineError:
                listed[u] = None
        return hashlib.sha256(json.dumps(listed, sort_keys=True).encode()).hexdigest()

    def configure_task(self, task):
        # saved after a successful run, when the upstream outputs are still those the stage read
        task.value_savers.append(lambda: {self.KEY: self.digest()})

    def __call__(self, task, values):
        return values.get(self.KEY) == self.digest()


def _stage_tasks(name):
    stage = load_stage(name)
    try:
        params = CONFIG.section(name, stage.Params)
    except PipelineError as e:
        _stop(str(e))
    upstream = list(stage.UPSTREAM) + (
        ["synthesize"] if SYNTHETIC and name == "import_photogrammetry" else []
    )
    yield {
        "basename": f"_inputs:{name}",
        "doc": f"(hidden) list the files {name} reads",
        "actions": [_inputs_action(stage, params)],
        "file_dep": [str(LAYOUT.manifest(u)) for u in upstream],
        # folders a person adds files to are rescanned on every run (it costs milliseconds): raw/ (the
        # first stage) and variants/ (trained models that evaluate compares)
        "uptodate": [False] if name in RESCANNED else [],
        "verbosity": 0,
    }
    yield {
        "basename": name,
        "doc": stage.DOC,
        "actions": [_run_stage(name)],
        "calc_dep": [f"_inputs:{name}"],
        "file_dep": [str(p) for p in source_files(stage)],
        "targets": [str(p) for p in stage.targets(LAYOUT, params)] + [str(LAYOUT.manifest(name))],
        "uptodate": [
            # [run] is not in params: a run setting reruns nothing
            config_changed(to_dict(params)),
            upstream_outputs_unchanged(upstream),
            _outputs_intact(stage),
        ],
        "clean": True,
    }


def task_pipeline():
    for name in STAGES:
        yield from _stage_tasks(name)
