"""Training data in memory: the views with their images, masks and normal priors, the held-out split, the
facade bounds, the initial geometry and what the I/O stack estimates before training (the views' exposure
gains, ``training.exposure``). Built by the stage from the upstream hand-offs; tests build it from gt/.
Training itself needs torch alone: whatever needs open3d, OpenEXR or pycolmap is done when the data is
built, so that a bundle of it (``save_bundle``) trains on a machine without them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facade_pipeline.geometry.camera import PinholeCamera


@dataclass(frozen=True, eq=False)
class TrainView:
    """One view. Arrays are numpy, kept on the host; the trainer moves a window to its device per step."""

    stem: str
    camera: PinholeCamera
    image: np.ndarray  # [H, W, 3] float32 in [0, 1]
    facade_mask: np.ndarray  # [H, W] bool
    glass_mask: np.ndarray  # [H, W] bool
    normal_prior: np.ndarray  # [H, W, 3] float32 world-space unit normals (baked from the corrected mesh)
    normal_valid: np.ndarray  # [H, W] bool

    def __post_init__(self) -> None:
        h, w = self.camera.height, self.camera.width
        for name, shape in (
            ("image", (h, w, 3)),
            ("facade_mask", (h, w)),
            ("glass_mask", (h, w)),
            ("normal_prior", (h, w, 3)),
            ("normal_valid", (h, w)),
        ):
            arr = getattr(self, name)
            assert arr.shape == shape, f"{self.stem}.{name}: {arr.shape} != {shape}"


@dataclass(frozen=True, eq=False)
class InitGeometry:
    """What the Gaussians start from (section 3.2): the coarse point cloud and the corrected mesh."""

    points: np.ndarray  # [P, 3] coarse points (local frame, m)
    colors: np.ndarray  # [P, 3] in [0, 1]
    mesh_vertices: np.ndarray  # [V, 3] corrected mesh
    mesh_triangles: np.ndarray  # [T, 3] int
    mesh_glass: np.ndarray | None = None  # [T] bool: glass triangles (correct_mesh's labels); None: unknown


@dataclass(frozen=True)
class ExposureEstimate:
    """Per view: the log gain per colour channel [V, 3] (geometric mean 1 over the reference views) and
    the samples it rests on [V] (``training.exposure``)."""

    log_gain: np.ndarray
    samples: np.ndarray


@dataclass(frozen=True, eq=False)
class TrainData:
    views: tuple[TrainView, ...]
    train_idx: tuple[int, ...]
    test_idx: tuple[int, ...]
    init: InitGeometry
    exposure: ExposureEstimate | None = None
    """the views' exposure gains estimated from the photos (``training.exposure.with_exposure_estimate``);
    None: not estimated"""

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The facade's axis-aligned bounds (m): those of the corrected mesh."""
        v = self.init.mesh_vertices
        return v.min(axis=0), v.max(axis=0)

    @property
    def extent(self) -> float:
        """The scene extent 2DGS scales its rates and sizes by: 1.1 x the largest distance of a camera
        centre from their mean (m), at least 1 m."""
        c = np.array([v.camera.center for v in self.views])
        return float(max(1.1 * np.linalg.norm(c - c.mean(axis=0), axis=1).max(), 1.0))


def split_views(n_views: int, test_every: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """(train, test) indices: every ``test_every``-th view (0, 8, 16, ...) is held out; 0 holds none out.
    With fewer than two views nothing is held out (there would be nothing to train on)."""
    if test_every <= 0 or n_views < 2:
        return tuple(range(n_views)), ()
    test = tuple(i for i in range(n_views) if i % test_every == 0)
    return tuple(i for i in range(n_views) if i % test_every != 0), test


INIT_FIELDS = ("points", "colors", "mesh_vertices", "mesh_triangles")


def save_bundle(data: TrainData, path) -> None:
    """Write ``data`` to one compressed ``.npz`` file (written atomically): everything training needs, so
    that a machine without the I/O stack (open3d, OpenEXR, pycolmap), a GPU machine say, can train on it."""
    from facade_pipeline.io.atomic import atomic_path

    arrays: dict[str, np.ndarray] = {
        "train_idx": np.asarray(data.train_idx, np.int64),
        "test_idx": np.asarray(data.test_idx, np.int64),
        "stems": np.asarray([v.stem for v in data.views]),
        **{f"init_{k}": getattr(data.init, k) for k in INIT_FIELDS},
    }
    if data.init.mesh_glass is not None:
        arrays["init_mesh_glass"] = data.init.mesh_glass
    if data.exposure is not None:
        arrays["exposure_log_gain"] = data.exposure.log_gain
        arrays["exposure_samples"] = data.exposure.samples
    for i, v in enumerate(data.views):
        c = v.camera
        arrays[f"v{i}_camera"] = np.concatenate([c.K.ravel(), c.cam_from_world.ravel(), [c.width, c.height]])
        for name in ("image", "facade_mask", "glass_mask", "normal_prior", "normal_valid"):
            arrays[f"v{i}_{name}"] = getattr(v, name)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)


def load_bundle(path) -> TrainData:
    """The TrainData written by ``save_bundle``."""
    with np.load(path) as z:
        views = []
        for i, stem in enumerate(z["stems"]):
            cam = z[f"v{i}_camera"]
            camera = PinholeCamera(cam[:9].reshape(3, 3), cam[9:25].reshape(4, 4), int(cam[25]), int(cam[26]))
            views.append(
                TrainView(str(stem), camera, *(z[f"v{i}_{n}"] for n in
                          ("image", "facade_mask", "glass_mask", "normal_prior", "normal_valid")))
            )  # fmt: skip
        glass = z["init_mesh_glass"] if "init_mesh_glass" in z else None
        init = InitGeometry(*(z[f"init_{k}"] for k in INIT_FIELDS), mesh_glass=glass)
        exposure = None
        if "exposure_log_gain" in z:
            exposure = ExposureEstimate(z["exposure_log_gain"], z["exposure_samples"])
        return TrainData(tuple(views), tuple(int(i) for i in z["train_idx"]),
                         tuple(int(i) for i in z["test_idx"]), init, exposure)  # fmt: skip
