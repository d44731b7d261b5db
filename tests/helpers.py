"""Small raw/ datasets for tests, made from pycolmap's own synthetic reconstructions and hand-made meshes."""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

import numpy as np
import pycolmap

from facade_pipeline.io.images import write_image
from facade_pipeline.io.meshes import make_mesh, make_points, write_mesh, write_points
from facade_pipeline.layout import BuildingLayout


def synthetic_reconstruction(
    n_images: int = 6,
    width: int = 96,
    height: int = 72,
    model: str = "SIMPLE_RADIAL",
    params=(120.0, 48.0, 36.0, 0.05),
    seed: int = 0,
) -> pycolmap.Reconstruction:
    pycolmap.set_random_seed(seed)
    o = pycolmap.SyntheticDatasetOptions()
    o.num_rigs, o.num_cameras_per_rig, o.num_frames_per_rig = 1, 1, n_images
    o.num_points3D = 40
    o.camera_width, o.camera_height = width, height
    o.camera_model_id = getattr(pycolmap.CameraModelId, model)
    o.camera_params = list(params)
    return pycolmap.synthesize_dataset(o)


def make_raw(
    layout: BuildingLayout,
    rec: pycolmap.Reconstruction | None = None,
    offset=(0.0, 0.0, 0.0),
    with_points: bool = True,
    frontal: bool = False,
    seed: int = 0,
) -> pycolmap.Reconstruction:
    """Write a complete raw/ for ``layout``: COLMAP model, textured images of the right size, a hand-made
    mesh (a quad spanning the points) and the point cloud, all moved by ``offset`` (georeferencing)."""
    rec = rec or synthetic_reconstruction(seed=seed)
    offset = np.asarray(offset, dtype=np.float64)
    rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(np.eye(3)), offset))
    rng = np.random.default_rng(seed)
    models = [(layout.raw_sparse_dir, layout.raw_images_dir)]
    if frontal:
        models.append((layout.raw_frontal_sparse_dir, layout.raw_frontal_images_dir))
    for model_dir, image_dir in models:
        model_dir.mkdir(parents=True, exist_ok=True)
        rec.write(str(model_dir))
        for im in rec.images.values():
            cam = im.camera
            write_image(image_dir / im.name, rng.integers(0, 256, (cam.height, cam.width, 3), dtype=np.uint8))
    xyz = np.array([p.xyz for p in rec.points3D.values()])
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    quad = np.array(
        [[lo[0], lo[1], lo[2]], [hi[0], lo[1], lo[2]], [hi[0], hi[1], hi[2]], [lo[0], hi[1], hi[2]]]
    )
    write_mesh(layout.raw_coarse_mesh_candidates[0], make_mesh(quad, np.array([[0, 1, 2], [0, 2, 3]])))
    if with_points:
        write_points(layout.raw_coarse_points, make_points(xyz))
    return rec


def tree_digest(folder: Path) -> dict[str, str]:
    """SHA-256 and mtime of every file under ``folder`` (to prove nothing was modified)."""
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            out[p.relative_to(folder).as_posix()] = hashlib.sha256(p.read_bytes()).hexdigest() + str(
                p.stat().st_mtime_ns
            )
    return out


def as_real_building(toml_text: str) -> str:
    """A synthetic building's config turned into a real building's: kind "real" and no simulator tables,
    which a real building may not set."""
    text = re.sub(r'(?m)^kind = "synthetic"', 'kind = "real"', toml_text)
    return "".join(t for t in re.split(r"(?m)^(?=\[)", text) if not re.match(r"\[\[?synthesize", t))


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` still runs: a zombie that no parent has reaped yet (its parent killed) is
    gone too."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[-1][0] not in "ZX"
    except (OSError, IndexError):
        return False
