"""One run per building at a time: an advisory lock on ``<building>/.lock``.

Two runs on one building delete each other's manifests and outputs. The lock is an ``flock`` on a file that
lists its holders as ``pid@host`` (with the host because the workers of a batch on several machines share
the data root, where a pid alone names no process). An flock belongs to an open file description, which a
child process shares when it inherits the descriptor: the lock is held until the last process holding it
exits, however it exits. A doit run takes it and hands its descriptor to each stage it starts (``lock_fds``
for ``pass_fds``, named in ``FACADE_BUILDING_LOCK``), so a stage that outlives a killed doit still holds the
building, and a second run stops at once. A stage started by hand takes the lock itself. A lock whose
holders all died is free again: its file stays and is taken over.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import socket
from pathlib import Path

from facade_pipeline.errors import PipelineError

LOCK_ENV = "FACADE_BUILDING_LOCK"

#: the lock descriptors this process holds (path -> fd), for ``lock_fds``
_HELD: dict[str, int] = {}


class BuildingBusyError(PipelineError):
    """Another process runs on this building."""


def acquire(path: str | Path) -> int | None:
    """Take the lock at ``path`` and return its open descriptor (keep it open while the run lasts); None
    when the building's folder cannot be written (a read-only data root: nothing can run there, nothing to
    guard). A descriptor of this lock inherited from the parent run (``FACADE_BUILDING_LOCK``) is joined:
    this process then holds the lock too. Raises ``BuildingBusyError`` when another live process holds it."""
    path = Path(path)
    fd = _inherited(path)
    if fd is not None:
        _add_holder(fd, append=True)
        _HELD[str(path)] = fd
        return fd
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as e:
        if isinstance(e, PermissionError) or e.errno == errno.EROFS:
            return None
        raise
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        holders = ", ".join(f"pid {pid} on {host}" for pid, host in _holders(path)) or "pid ?"
        raise BuildingBusyError(
            path,
            "no other run on this building",
            f"another run ({holders}) holds this building: wait for it to finish or stop it",
        ) from None
    _add_holder(fd, append=False)
    _HELD[str(path)] = fd
    os.environ[LOCK_ENV] = f"{path}:{fd}"
    return fd


def lock_fds() -> tuple[int, ...]:
    """The lock descriptors this process holds: pass them to a child that works on the building
    (``subprocess.run(..., pass_fds=lock_fds())``) so that it holds the lock as long as it runs."""
    return tuple(_HELD.values())


def release(fd: int | None) -> None:
    """Stop holding the lock (closing this process's descriptor; the lock is free once no process that
    shares it is left). The file stays, to be taken by the next run."""
    if fd is None:
        return
    for key, held in list(_HELD.items()):
        if held == fd:
            del _HELD[key]
    with contextlib.suppress(OSError):
        _remove_holder(fd)
    with contextlib.suppress(OSError):
        os.close(fd)
    if os.environ.get(LOCK_ENV, "").endswith(f":{fd}") and not _HELD:
        del os.environ[LOCK_ENV]


def _inherited(path: Path) -> int | None:
    """The descriptor of the lock at ``path`` that the parent run passed down, if this process has it."""
    where, _, number = os.environ.get(LOCK_ENV, "").rpartition(":")
    if where != str(path) or not number.isdigit():
        return None
    fd = int(number)
    try:
        mine, there = os.fstat(fd), os.stat(path)
    except OSError:
        return None  # named but not passed down (a process the run did not start as a stage)
    if (mine.st_dev, mine.st_ino) != (there.st_dev, there.st_ino):
        return None
    try:
        # the same open file description as the holder's: this succeeds only if it is the held lock
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        return None
    return fd


def _add_holder(fd: int, append: bool) -> None:
    """Write this process's ``pid@host`` into the lock file (a new lock: alone; a joined one: after the
    others)."""
    line = f"{_me()}\n".encode()
    if append:
        os.pwrite(fd, line, os.fstat(fd).st_size)
    else:
        os.ftruncate(fd, 0)
        os.pwrite(fd, line, 0)


def _remove_holder(fd: int) -> None:
    size = os.fstat(fd).st_size
    lines = os.pread(fd, size, 0).decode(errors="replace").split()
    rest = [p for p in lines if p != _me()]
    if len(rest) != len(lines) and rest:
        text = "".join(f"{p}\n" for p in rest).encode()
        os.ftruncate(fd, 0)
        os.pwrite(fd, text, 0)


def _me() -> str:
    return f"{os.getpid()}@{socket.gethostname()}"


def _holders(path: Path) -> list[tuple[int, str]]:
    """The holders (pid, host) written in the lock file, less the processes of this host that are gone (one
    of another host cannot be asked: it is listed)."""
    try:
        words = path.read_text().split()
    except OSError:
        return []
    here = socket.gethostname()
    live = []
    for word in words:
        pid, _, host = word.partition("@")
        if not pid.isdigit():
            continue
        host = host or here
        if host == here:
            try:
                os.kill(int(pid), 0)
            except ProcessLookupError:
                continue
            except PermissionError:
                pass
        live.append((int(pid), host))
    return live
