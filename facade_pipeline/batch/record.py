"""Each building's record of a batch run (``<building>/.batch/status.json``): per stage, queued, running
(on which host, which pid), done (ran or was up to date) or failed (with the one-line error), for
``facade-batch status``. Written by the tasks on the workers, one at a time per building (its stages run in
order), always whole and atomically; the record says what happened, doit's state and the manifests decide
what runs."""

from __future__ import annotations

import json
import os
import socket
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from facade_pipeline.io.atomic import write_json
from facade_pipeline.layout import BuildingLayout

STATES = ("queued", "running", "done", "failed")


def read_record(layout: BuildingLayout) -> dict[str, dict[str, Any]]:
    """Stage -> its entry, in pipeline order; {} when no batch ran on the building (or the record is
    unreadable: the next batch writes it anew)."""
    try:
        data = json.loads(layout.path("batch_record").read_text())
        return dict(data["stages"])
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def write_record(layout: BuildingLayout, stages: dict[str, dict[str, Any]]) -> None:
    write_json(layout.path("batch_record"), {"building": layout.building, "stages": stages})


def start(layout: BuildingLayout, stages: list[str]) -> None:
    """A new batch on the building: every stage queued."""
    write_record(layout, {s: {"state": "queued"} for s in stages})


def update(layout: BuildingLayout, stage: str, state: str, **fields: Any) -> None:
    assert state in STATES, state
    stages = read_record(layout)
    stages[stage] = {"state": state, "host": socket.gethostname(), "pid": os.getpid(),
                     "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **fields}
    write_record(layout, stages)


@dataclass(frozen=True)
class BuildingStatus:
    building: str
    done: list[str]
    running: list[str]
    failed: list[tuple[str, str]]
    """(stage, its one-line error)"""
    waiting: list[str]

    def line(self) -> str:
        """One line: the building's state, then which stages are where."""
        n = len(self.done) + len(self.running) + len(self.failed) + len(self.waiting)
        if self.failed:
            stage, error = self.failed[0]
            head = f"failed at {stage}: {error}"
        elif self.running:
            head = f"running {', '.join(self.running)}"
        elif self.waiting:
            head = "waiting" if not self.done else f"stopped after {self.done[-1]}"
        else:
            head = "done"
        return f"{self.building}: {head} ({len(self.done)} of {n} stages done)"


def building_status(layout: BuildingLayout) -> BuildingStatus | None:
    """What the record says, with a stage recorded as running on this host by a process that is gone
    (its worker was killed and the batch did not retry it) counted as failed."""
    stages = read_record(layout)
    if not stages:
        return None
    done, running, failed, waiting = [], [], [], []
    here = socket.gethostname()
    for stage, entry in stages.items():
        state = entry.get("state")
        if state == "running" and entry.get("host") == here and not _alive(entry.get("pid")):
            failed.append((stage, f"its process (pid {entry.get('pid')} on {here}) is gone: rerun the batch"))
        elif state == "running":
            running.append(f"{stage} (pid {entry.get('pid')} on {entry.get('host')})")
        elif state == "done":
            done.append(stage)
        elif state == "failed":
            failed.append((stage, entry.get("error", "?")))
        else:
            waiting.append(stage)
    return BuildingStatus(layout.building, done, running, failed, waiting)


def _alive(pid: Any) -> bool:
    try:
        os.kill(int(pid), 0)
    except (TypeError, ValueError, ProcessLookupError):
        return False
    except PermissionError:
        pass
    return True


def recorded_buildings(data_root: Path) -> list[str]:
    """The buildings under ``data_root`` that a batch ran on."""
    return sorted(
        p.name for p in Path(data_root).iterdir() if p.is_dir() and BuildingLayout(p.parent, p.name)
        .path("batch_record").is_file()
    ) if Path(data_root).is_dir() else []
