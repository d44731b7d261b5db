"""Training data in memory: the views with their images, masks and normal priors, the held-out split, the
facade bounds, the initial geometry and what the I/O stack estimates before training (the views' exposure
gains, ``training.exposure``). Built by the stage from the upstream hand-offs; tests build it from gt/.
Training itself needs torch alone: whatever needs open3d, OpenEXR or pycolmap is done when the data is
built, so that a bundle of it (``save_bundle``) trains on a machine without them."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

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
    clipped: np.ndarray | None = None
    """[H, W, 3] bool: channels the photo clipped (``clipped_channels``), or of a block holding one after
    ``downscale_view``; None: none clipped"""

    def __post_init__(self) -> None:
        h, w = self.camera.height, self.camera.width
        for name, shape in (
            ("image", (h, w, 3)),
            ("facade_mask", (h, w)),
            ("glass_mask", (h, w)),
            ("normal_prior", (h, w, 3)),
            ("normal_valid", (h, w)),
            ("clipped", (h, w, 3)),
        ):
            arr = getattr(self, name)
            if arr is None:
                continue
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


#: The scene extent is at least this fraction of the facade's size: a tenth, so that a single view (no
#: spread) still has a scale of the facade's
EXTENT_MIN_FRACTION = 0.1


@dataclass(frozen=True, eq=False)
class TrainData:
    views: tuple[TrainView, ...]
    train_idx: tuple[int, ...]
    test_idx: tuple[int, ...]
    init: InitGeometry
    exposure: ExposureEstimate | None = None
    """the views' exposure gains estimated from the photos (``training.exposure.with_exposure_estimate``);
    None: not estimated"""

    @cached_property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The facade's axis-aligned bounds (m): those of the corrected mesh (kept once made: every training
        step reads them, through the near plane and the rates' extent, and the mesh has 10^5 vertices)."""
        v = self.init.mesh_vertices
        return v.min(axis=0), v.max(axis=0)

    @cached_property
    def extent(self) -> float:
        """The scene extent 2DGS scales its rates and sizes by: 1.1 x the largest distance of a camera
        centre from their mean (m), at least ``EXTENT_MIN_FRACTION`` of the facade's size (the diagonal of
        its bounds), which binds only when the cameras hardly spread (a single view)."""
        c = np.array([v.camera.center for v in self.views])
        lo, hi = self.bounds
        floor = EXTENT_MIN_FRACTION * float(np.linalg.norm(hi - lo))
        return float(max(1.1 * np.linalg.norm(c - c.mean(axis=0), axis=1).max(), floor))


#: A channel at or above this (0-1) is clipped: it carries a lower bound of the light, not its colour. JPEG
#: photos scatter a sensor's clipped white a few levels below 255, hence not exactly 1.
CLIP_LEVEL = 250.0 / 255.0


def clipped_channels(image: np.ndarray) -> np.ndarray:
    """[H, W, 3] bool: the channels of ``image`` ([H, W, 3] in [0, 1]) at or above ``CLIP_LEVEL``."""
    return np.asarray(image) >= CLIP_LEVEL


def pixel_budget_factor(width: int, height: int, max_pixels: int) -> int:
    """The smallest integer factor f >= 1 with (width // f) (height // f) <= ``max_pixels`` (0: 1, no
    budget): how many photo pixels a side of a trained (and measured) pixel spans."""
    f = 1
    while max_pixels > 0 and (width // f) * (height // f) > max_pixels and f < min(width, height):
        f += 1
    return f


def block_reduce(a: np.ndarray, f: int, how: str = "mean") -> np.ndarray:
    """``a`` [H, W, ...] reduced over f x f pixel blocks ("mean", "any" or "all"); the last H % f rows and
    W % f columns are dropped (``scaled_camera`` drops them too)."""
    if f == 1:
        return a
    h, w = a.shape[0] // f, a.shape[1] // f
    blocks = a[: h * f, : w * f].reshape(h, f, w, f, *a.shape[2:])
    if how == "any":
        return blocks.any(axis=(1, 3))
    if how == "all":
        return blocks.all(axis=(1, 3))
    return blocks.mean(axis=(1, 3), dtype=np.float64).astype(a.dtype if a.dtype.kind == "f" else np.float64)


def scaled_camera(camera: PinholeCamera, f: int) -> PinholeCamera:
    """``camera`` with pixels f times larger (``block_reduce``'s image of its photo): the same pose, K's
    first two rows divided by f (pixel centres at +0.5 stay so)."""
    if f == 1:
        return camera
    K = np.array(camera.K, float)
    K[:2] /= f
    return PinholeCamera(K, camera.cam_from_world, camera.width // f, camera.height // f)


def downscale_view(view: TrainView, f: int) -> TrainView:
    """``view`` at f x f photo pixels per pixel: the photo averaged over each block (a camera's pixel
    integrates its area), masks where at least half the block has them, the normal prior averaged where
    the whole block has it, a channel clipped where any of the block's is."""
    if f == 1:
        return view
    n = block_reduce(np.where(view.normal_valid[..., None], view.normal_prior, 0.0), f)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    valid = block_reduce(view.normal_valid, f, "all") & (norm[..., 0] > 0)
    clipped = None if view.clipped is None else block_reduce(view.clipped, f, "any")
    return TrainView(
        view.stem,
        scaled_camera(view.camera, f),
        block_reduce(view.image, f).astype(np.float32),
        block_reduce(view.facade_mask.astype(np.float32), f) >= 0.5,
        block_reduce(view.glass_mask.astype(np.float32), f) >= 0.5,
        np.where(valid[..., None], n / np.maximum(norm, 1e-12), 0.0).astype(np.float32),
        valid,
        clipped,
    )


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
        if v.clipped is not None:
            arrays[f"v{i}_clipped"] = v.clipped
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
                          ("image", "facade_mask", "glass_mask", "normal_prior", "normal_valid")),
                          z[f"v{i}_clipped"] if f"v{i}_clipped" in z else None)
            )  # fmt: skip
        glass = z["init_mesh_glass"] if "init_mesh_glass" in z else None
        init = InitGeometry(*(z[f"init_{k}"] for k in INIT_FIELDS), mesh_glass=glass)
        exposure = None
        if "exposure_log_gain" in z:
            exposure = ExposureEstimate(z["exposure_log_gain"], z["exposure_samples"])
        return TrainData(tuple(views), tuple(int(i) for i in z["train_idx"]),
                         tuple(int(i) for i in z["test_idx"]), init, exposure)  # fmt: skip
