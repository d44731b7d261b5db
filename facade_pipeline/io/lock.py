"""One run per building at a time: an advisory lock on ``<building>/.lock``.

Two runs on one building delete each other's manifests and outputs. The lock is an ``flock`` on a file that
holds the holder's pid: the kernel drops it when the holder dies, however it dies, so the lock of a killed run
is simply taken over. A doit run holds it for all of its stages; it hands them the right to run through the
environment (``FACADE_BUILDING_LOCK``), since a stage is a child process that cannot take the lock its parent
holds. A stage started by hand takes the lock itself.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path

from facade_pipeline.errors import PipelineError

LOCK_ENV = "FACADE_BUILDING_LOCK"


class BuildingBusyError(PipelineError):
    """Another process runs on this building."""


def acquire(path: Path) -> int | None:
    """Take the lock at ``path`` and return its open descriptor (keep it open while the run lasts); None
    when the building's folder cannot be written (a read-only data root: nothing can run there, nothing to
    guard). Raises ``BuildingBusyError`` when another live process holds it."""
    path = Path(path)
    inherited = os.environ.get(LOCK_ENV)
    holder = _holder(path)
    if inherited and holder is not None and holder == _parse(inherited, path):
        return None  # our parent doit run holds it for us
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except (PermissionError, OSError) as e:
        if isinstance(e, PermissionError) or e.errno == 30:  # EROFS
            return None
        raise
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        holder = _holder(path)
        raise BuildingBusyError(
            path,
            "no other run on this building",
            f"another run (pid {holder if holder else '?'}) holds this building: wait for it to finish "
            "or stop it",
        ) from None
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    os.environ[LOCK_ENV] = f"{path}:{os.getpid()}"
    return fd


def release(fd: int | None) -> None:
    """Give the lock back (closing its descriptor); the file stays, to be taken by the next run."""
    if fd is not None:
        with contextlib.suppress(OSError):
            os.close(fd)
        if os.environ.get(LOCK_ENV, "").endswith(f":{os.getpid()}"):
            del os.environ[LOCK_ENV]


def _holder(path: Path) -> int | None:
    """The pid written in the lock file, if it is still locked by a live process."""
    try:
        text = path.read_text().strip()
        pid = int(text)
    except (OSError, ValueError):
        return None
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return None
    except PermissionError:
        pass
    return pid


def _parse(value: str, path: Path) -> int | None:
    where, _, pid = value.rpartition(":")
    if where != str(path):
        return None
    try:
        return int(pid)
    except ValueError:
        return None
