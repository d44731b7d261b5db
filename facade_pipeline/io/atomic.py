"""Atomic output files: write to a temporary name in the same folder, then ``os.replace``.

A crash, ``kill -9`` or Ctrl-C therefore leaves either the old file, the complete new file, or a stray
temporary file (``.tmp-*``) that no reader trusts and that the next run of the stage removes. ``read_json``
is ``write_json``'s counterpart: whatever is wrong with the file comes back as one ``InputError`` naming it.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TypeVar

from facade_pipeline.errors import InputError

T = TypeVar("T")

TMP_PREFIX = ".tmp-"


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it to ``path``, on error delete it.

    The temporary name keeps the suffix so that writers that pick a format from the extension work.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=TMP_PREFIX + path.stem + "-", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        try:
            yield tmp_path
        except Exception as e:
            # a writer that fails on a full disk says so in its own words (torch: "file write failed", a
            # plain write: no file name); name the file, so that the stage's one line does
            if not (isinstance(e, OSError) and e.filename) and _out_of_space(path.parent):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path)) from e
            raise
        if not tmp_path.exists() or (tmp_path.stat().st_size == 0 and not _allow_empty(path)):
            if _out_of_space(path.parent):  # a writer that reports failure by a return value (OpenCV)
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
            raise OSError(f"{path}: writer produced no data in {tmp_path}")
        os.chmod(tmp_path, 0o666 & ~_umask())  # mkstemp makes 0600 files; give outputs the usual mode
        _fsync(tmp_path)
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def _out_of_space(folder: Path) -> bool:
    try:
        return shutil.disk_usage(folder).free < 1 << 20
    except OSError:
        return False


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _allow_empty(path: Path) -> bool:
    return path.suffix in {".txt", ".log"}


def _fsync(path: Path) -> None:
    with open(path, "rb") as f:
        os.fsync(f.fileno())


def write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    write_bytes(path, text.encode("utf-8"))


def write_json(path: str | Path, obj: object) -> None:
    """Write ``obj`` as indented JSON to ``path`` atomically (NaN and Inf are refused)."""
    write_text(path, json.dumps(obj, indent=2, sort_keys=False, allow_nan=False) + "\n")


def read_json(path: str | Path, what: str, parse: Callable[[dict], T], version: int | None = None) -> T:
    """``parse`` applied to the JSON object in ``path`` (``what``: what the file should be, for the message).
    With ``version``, the object's ``"version"`` must equal it: a file of another format version is refused
    before it is parsed. A missing, unreadable or malformed file (a key missing, a value of the wrong type)
    raises ``InputError`` naming the file; ``parse``'s own ``InputError`` passes through."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
        if version is not None and d["version"] != version:
            raise InputError(path, f"{what}, version {version}", f"version {d['version']}")
        return parse(d)
    except FileNotFoundError:
        raise InputError(path, what, "no file") from None
    except (OSError, json.JSONDecodeError, KeyError, IndexError, TypeError, ValueError) as e:
        raise InputError(path, what, f"{type(e).__name__}: {e}") from None


def remove_stale_temporaries(folder: str | Path) -> int:
    """Delete temporary files left by an interrupted writer under ``folder``; return how many."""
    folder = Path(folder)
    if not folder.exists():
        return 0
    count = 0
    for p in folder.rglob(TMP_PREFIX + "*"):
        if p.is_file():
            p.unlink()
            count += 1
    return count
