"""Triangle meshes and point clouds (PLY, OBJ) through open3d, with checks that turn a bad file into one
clear ``InputError``. Coordinates stay float64 in memory (georeferenced inputs need it)."""

from __future__ import annotations

import contextlib
import ctypes
import io
import os
import re
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import open3d as o3d

from facade_pipeline.errors import InputError
from facade_pipeline.io.atomic import atomic_path

_LIBC = ctypes.CDLL(None)


@contextlib.contextmanager
def _reader_messages(path: Path, expected: str) -> Iterator[None]:
    """Keep open3d's reader messages off the terminal (its PLY parser, RPly, prints one line per bad element
    to the process's stderr from C; open3d prints its warnings through Python's stdout) and turn a failed
    read into one ``InputError`` quoting the first."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = {fd: os.dup(fd) for fd in (1, 2)}
    logged = io.StringIO()  # open3d's Python module prints its warnings through Python's sys.stdout
    with tempfile.TemporaryFile() as caught:
        for fd in saved:
            os.dup2(caught.fileno(), fd)
        try:
            with contextlib.redirect_stdout(logged):
                yield
        finally:
            _LIBC.fflush(None)  # C's buffered streams: their lines must land here, not after
            for fd, copy in saved.items():
                os.dup2(copy, fd)
                os.close(copy)
        caught.seek(0)
        text = caught.read().decode(errors="replace") + logged.getvalue()
    text = re.sub(r"\x1b\[[0-9;]*m", "", text)  # colour codes
    failed = [ln.strip() for ln in text.splitlines() if ln.startswith("RPly") or "failed" in ln.lower()]
    if failed:
        more = f" and {len(failed) - 1} more" if len(failed) > 1 else ""
        raise InputError(path, expected, f"a damaged or truncated file ({failed[0]}{more})")


def read_mesh(path: str | Path) -> o3d.geometry.TriangleMesh:
    """Read a triangle mesh and check it has faces and finite vertices."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "a triangle mesh (PLY or OBJ)", "no file")
    with _reader_messages(path, "a readable triangle mesh (PLY or OBJ)"):
        mesh = o3d.io.read_triangle_mesh(str(path), enable_post_processing=False, print_progress=False)
    n_v, n_f = len(mesh.vertices), len(mesh.triangles)
    if n_v == 0:
        raise InputError(
            path, "a triangle mesh with vertices (PLY or OBJ)", "no vertex (empty or unreadable file)"
        )
    if n_f == 0:
        raise InputError(path, "a triangle mesh with faces", f"{n_v} vertices and no face")
    v = np.asarray(mesh.vertices)
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise InputError(path, "finite vertex coordinates", f"{int(bad.sum())} vertices with NaN or Inf")
    tri = np.asarray(mesh.triangles)
    if tri.min() < 0 or tri.max() >= n_v:
        raise InputError(path, f"face indices in [0, {n_v})", f"indices from {tri.min()} to {tri.max()}")
    return mesh


def read_points(path: str | Path) -> o3d.geometry.PointCloud:
    """Read a point cloud (PLY) and check it has finite points."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "a point cloud (PLY)", "no file")
    with _reader_messages(path, "a readable point cloud (PLY)"):
        pcd = o3d.io.read_point_cloud(str(path), print_progress=False)
    if len(pcd.points) == 0:
        raise InputError(path, "a point cloud with points", "no point (empty or unreadable file)")
    p = np.asarray(pcd.points)
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        raise InputError(path, "finite point coordinates", f"{int(bad.sum())} points with NaN or Inf")
    return pcd


def write_mesh(path: str | Path, mesh: o3d.geometry.TriangleMesh) -> None:
    """Write a mesh as binary PLY atomically."""
    with atomic_path(path) as tmp:
        if not o3d.io.write_triangle_mesh(
            str(tmp), mesh, write_ascii=False, compressed=False, print_progress=False
        ):
            raise OSError(f"{path}: open3d could not write the mesh")


def write_points(path: str | Path, pcd: o3d.geometry.PointCloud) -> None:
    """Write a point cloud as binary PLY atomically."""
    with atomic_path(path) as tmp:
        if not o3d.io.write_point_cloud(str(tmp), pcd, write_ascii=False, print_progress=False):
            raise OSError(f"{path}: open3d could not write the point cloud")


def make_mesh(
    vertices: np.ndarray, triangles: np.ndarray, colors: np.ndarray | None = None
) -> o3d.geometry.TriangleMesh:
    """open3d mesh from [V, 3] vertices, [F, 3] triangle indices and optional [V, 3] colours in [0, 1]."""
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(vertices, np.float64)),
        o3d.utility.Vector3iVector(np.asarray(triangles, np.int32)),
    )
    if colors is not None:
        mesh.vertex_colors = o3d.utility.Vector3dVector(np.asarray(colors, np.float64))
    return mesh


def make_points(xyz: np.ndarray, colors: np.ndarray | None = None) -> o3d.geometry.PointCloud:
    """open3d point cloud from [P, 3] positions and optional [P, 3] colours in [0, 1]."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(xyz, np.float64)))
    if colors is not None:
        pcd.colors = o3d.utility.Vector3dVector(np.asarray(colors, np.float64))
    return pcd
