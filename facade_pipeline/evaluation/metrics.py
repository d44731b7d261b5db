"""Image metrics over a mask (PSNR, SSIM) and geometry metrics (surface distance, normal angle, corner error).

Everything is computed in float64 (numpy; PSNR through the training package's ``losses.psnr``, the one
PSNR of the project); torch tensors are accepted and copied to the CPU.

Images are ``[H, W]`` or ``[H, W, C]`` arrays with values in ``[0, data_range]`` (``data_range`` is 1 for our
renders). A mask is a bool array ``[H, W]`` (True = the pixel counts), the same for every channel; ``None``
means every pixel. No metric ever returns NaN: when there is nothing to average (an empty mask, no point, no
corner) it raises ``EmptyMaskError`` (a ``ValueError``). Identical images give PSNR = +inf, as scikit-image.

PSNR over a mask
    MSE = sum over masked pixels p and channels c of (x_pc - y_pc)^2 / (n_masked * C);
    PSNR = 10 log10(data_range^2 / MSE). Pixels outside the mask do not enter at all.

SSIM over a mask (Wang et al. 2004, "Image quality assessment: from error visibility to structural
similarity", Eq. 13 with the Gaussian-weighted statistics of their Sec. III-B)
    An 11x11 Gaussian window w (sigma 1.5, normalised to sum 1), K1 = 0.01, K2 = 0.03,
    C1 = (K1 R)^2, C2 = (K2 R)^2, population (not sample) covariances. The mask enters the local statistics
    as well as the final average: at a window centre p, with m the mask (1 inside, 0 outside),
        W_p    = sum_q w_(q-p) m_q
        mu_x   = sum_q w_(q-p) m_q x_q / W_p              (and mu_y likewise)
        s_x^2  = sum_q w_(q-p) m_q x_q^2 / W_p - mu_x^2   (and s_y^2, s_xy likewise)
        SSIM_p = (2 mu_x mu_y + C1)(2 s_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(s_x^2 + s_y^2 + C2)),
    i.e. the Gaussian weights of each window are renormalised over the masked pixels it covers, so a pixel
    outside the mask changes nothing (a plain "SSIM map, then mean over the mask" would still see unmasked
    pixels through the windows that straddle the mask's edge). The map is averaged over channels, then over
    the masked window centres. With a full mask W_p = 1 and this is the standard SSIM.

    Border windows (``border``):
    - ``"valid"`` (default): only centres whose whole 11x11 window lies inside the image count, i.e. a 5 px
      frame is dropped. This is exactly what ``skimage.metrics.structural_similarity(gaussian_weights=True,
      sigma=1.5, use_sample_covariance=False)`` averages (it filters with reflect padding, then crops 5 px,
      so the padding never reaches the values it keeps): with a full mask the two agree to rounding.
    - ``"renormalize"``: every masked pixel is a centre; the part of a window that falls off the image counts
      as outside the mask and the weights are renormalised over what is left. This keeps masks that touch
      the image border; it differs from scikit-image only in those 5 px.
    We never zero-pad the images themselves (as ``conv2d(padding=5)`` SSIM implementations do): that biases
    the border towards black.

Geometry
    Surface distance: unsigned distance from points (sampled uniformly by area on a source mesh, or given,
    e.g. Gaussian centres) to the closest point of a target mesh, with open3d's ``RaycastingScene``; mean,
    95th percentile (linear interpolation, numpy's default) and max, in the meshes' unit (metres).
    Normal angle error: angle between two normals, atan2(|a x b|, a . b) in degrees (0..180, orientation
    matters), over a validity mask. Corner error: Euclidean distance between corresponding panel corners in
    pixels of the rectified facade image, and in metres through its pixel size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch

from facade_pipeline.evaluation.errors import EmptyMaskError, MetricInputError
from facade_pipeline.training import losses

SSIM_WINDOW_PX = 11
SSIM_SIGMA_PX = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03

SsimBorder = Literal["valid", "renormalize"]


# --------------------------------------------------------------------------------------------- input checks


def _as_f64(a: Any, name: str) -> np.ndarray:
    """A float64 numpy copy of an array or torch tensor."""
    if hasattr(a, "detach"):  # a torch tensor
        a = a.detach().cpu().numpy()
    arr = np.asarray(a)
    if arr.dtype == bool or not np.issubdtype(arr.dtype, np.number):
        raise MetricInputError(f"{name} as a numeric array", f"dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise MetricInputError(f"finite values in {name}", f"{int((~np.isfinite(arr)).sum())} NaN or Inf")
    return arr


def _as_mask(mask: Any, shape: tuple[int, ...], name: str = "mask") -> np.ndarray:
    """A bool mask of ``shape`` (``None`` -> all True); 0/1 numbers are accepted, other values are not."""
    if mask is None:
        return np.ones(shape, dtype=bool)
    if hasattr(mask, "detach"):
        mask = mask.detach().cpu().numpy()
    m = np.asarray(mask)
    if m.shape != shape:
        raise MetricInputError(f"{name} of shape {shape}", f"shape {m.shape}")
    if m.dtype != bool:
        if not np.isin(m, (0, 1)).all():
            raise MetricInputError(f"{name} as bool or 0/1 values", f"other values (dtype {m.dtype})")
        m = m.astype(bool)
    return m


def _image_pair(img0: Any, img1: Any, mask: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two float64 images [H, W, C] (a channel axis added to [H, W]) and a bool mask [H, W]."""
    x, y = _as_f64(img0, "img0"), _as_f64(img1, "img1")
    if x.shape != y.shape:
        raise MetricInputError("two images of the same shape", f"{x.shape} and {y.shape}")
    if x.ndim not in (2, 3):
        raise MetricInputError("images [H, W] or [H, W, C]", f"shape {x.shape}")
    if x.ndim == 2:
        x, y = x[..., None], y[..., None]
    return x, y, _as_mask(mask, x.shape[:2])


def _check_data_range(data_range: float) -> float:
    if not (math.isfinite(data_range) and data_range > 0):
        raise MetricInputError("data_range > 0", str(data_range))
    return float(data_range)


# --------------------------------------------------------------------------------------------------- PSNR


def psnr(img0: Any, img1: Any, mask: Any = None, *, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB over the masked pixels (all channels): 10 log10(R^2 / MSE).

    img0, img1: [H, W] or [H, W, C]; mask: bool [H, W] or None (every pixel). +inf where the images agree on
    the mask; ``EmptyMaskError`` for an empty mask."""
    x, y, m = _image_pair(img0, img1, mask)
    r = _check_data_range(data_range)
    if not m.any():
        raise EmptyMaskError("a mask with at least one pixel for PSNR", "an empty mask")
    return losses.psnr(torch.from_numpy(x), torch.from_numpy(y), torch.from_numpy(m), r)


# --------------------------------------------------------------------------------------------------- SSIM


def gaussian_window_1d(size_px: int = SSIM_WINDOW_PX, sigma_px: float = SSIM_SIGMA_PX) -> np.ndarray:
    """The 1D Gaussian window [size_px], centred, normalised to sum 1 (the 2D window is its outer product)."""
    t = np.arange(size_px, dtype=np.float64) - (size_px - 1) / 2.0
    w = np.exp(-0.5 * (t / sigma_px) ** 2)
    return w / w.sum()


def _filter_valid(a: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Separable correlation of a [H, W, ...] with the window w [K] on axes 0 and 1, keeping only the
    centres whose whole window is inside: [H - K + 1, W - K + 1, ...]."""
    k = len(w)
    h, wd = a.shape[0] - k + 1, a.shape[1] - k + 1
    rows = sum(w[i] * a[i : i + h] for i in range(k))
    return sum(w[j] * rows[:, j : j + wd] for j in range(k))


@dataclass(frozen=True, eq=False)
class SsimMap:
    """Per-pixel SSIM ``values`` [H, W] (mean over channels) and the window centres that count, ``counted``
    [H, W] bool; ``values`` is 0 where not counted."""

    values: np.ndarray
    counted: np.ndarray


def ssim_map(img0: Any, img1: Any, mask: Any = None, *, data_range: float = 1.0,
             border: SsimBorder = "valid") -> SsimMap:
    """The masked SSIM map (module docstring: Gaussian statistics renormalised over the mask; ``border``
    says which window centres count). img0, img1: [H, W] or [H, W, C]; mask: bool [H, W] or None."""
    x, y, m = _image_pair(img0, img1, mask)
    r = _check_data_range(data_range)
    w = gaussian_window_1d()
    half = SSIM_WINDOW_PX // 2
    if border == "valid":
        if min(x.shape[:2]) < SSIM_WINDOW_PX:
            raise MetricInputError(f"images at least {SSIM_WINDOW_PX} px on each side for SSIM",
                                   f"shape {x.shape[:2]}")
        counted = np.zeros_like(m)
        counted[half:-half, half:-half] = m[half:-half, half:-half]
    elif border == "renormalize":
        # Off-image pixels are outside the mask: zero-pad everything, the weights renormalise below.
        pad = ((half, half), (half, half), (0, 0))
        x, y = np.pad(x, pad), np.pad(y, pad)
        counted = m
        m = np.pad(m, pad[:2])
    else:
        raise MetricInputError("border 'valid' or 'renormalize'", repr(border))
    mf = m.astype(np.float64)[..., None]  # [H, W, 1]
    wsum = _filter_valid(mf, w)  # [H', W', 1]; > 0 at every counted centre (its own weight is > 0)
    wsum = np.where(wsum > 0, wsum, 1.0)
    mu_x, mu_y = _filter_valid(mf * x, w) / wsum, _filter_valid(mf * y, w) / wsum
    v_x = _filter_valid(mf * x * x, w) / wsum - mu_x * mu_x
    v_y = _filter_valid(mf * y * y, w) / wsum - mu_y * mu_y
    v_xy = _filter_valid(mf * x * y, w) / wsum - mu_x * mu_y
    c1, c2 = (SSIM_K1 * r) ** 2, (SSIM_K2 * r) ** 2
    s = ((2 * mu_x * mu_y + c1) * (2 * v_xy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (v_x + v_y + c2))
    s = s.mean(axis=2)  # [H', W']
    if border == "valid":
        s = np.pad(s, half)
    return SsimMap(values=np.where(counted, s, 0.0), counted=counted)


def ssim(img0: Any, img1: Any, mask: Any = None, *, data_range: float = 1.0,
         border: SsimBorder = "valid") -> float:
    """Mean SSIM over the masked window centres (11x11 Gaussian window, sigma 1.5; module docstring).

    ``EmptyMaskError`` when no centre counts: an empty mask, or with ``border="valid"`` no masked pixel at
    least 5 px from the image border."""
    sm = ssim_map(img0, img1, mask, data_range=data_range, border=border)
    n = int(sm.counted.sum())
    if n == 0:
        where = " (5 px or more from the image border, border='valid')" if border == "valid" else ""
        raise EmptyMaskError(f"a mask with a pixel that can centre an SSIM window{where}", "none")
    return float(sm.values[sm.counted].sum() / n)


# ----------------------------------------------------------------------------------------------- geometry


@dataclass(frozen=True)
class DistanceStats:
    """Summary of unsigned distances, in the unit of the inputs (metres for our meshes)."""

    mean: float
    p95: float
    max: float
    count: int


def distance_stats(distances: Any) -> DistanceStats:
    """Mean, 95th percentile (linear interpolation) and max of distances [N]; ``EmptyMaskError`` if N = 0."""
    d = _as_f64(distances, "distances").reshape(-1)
    if d.size == 0:
        raise EmptyMaskError("at least one distance", "none")
    return DistanceStats(float(d.mean()), float(np.percentile(d, 95)), float(d.max()), int(d.size))


def _mesh_arrays(mesh: Any) -> tuple[np.ndarray, np.ndarray]:
    """(vertices [V, 3] float64, triangles [F, 3] int64) of a (vertices, triangles) pair, an open3d
    ``TriangleMesh`` or any object with ``vertices`` and ``triangles`` arrays."""
    v, f = mesh if isinstance(mesh, tuple) else (mesh.vertices, mesh.triangles)
    v, f = _as_f64(v, "mesh vertices"), np.asarray(f)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise MetricInputError("a mesh with vertices [V, 3] and at least one triangle [F, 3]",
                               f"vertices {v.shape}, triangles {f.shape}")
    if not np.issubdtype(f.dtype, np.integer) or f.min() < 0 or f.max() >= len(v):
        found = f"{f.dtype} {f.min()}..{f.max()}"
        raise MetricInputError(f"integer triangle indices in [0, {len(v)})", found)
    return v, f.astype(np.int64)


def sample_mesh_surface(mesh: Any, n_points: int, seed: int = 0) -> np.ndarray:
    """Points [n_points, 3] uniform by area on a mesh (triangle drawn by area, then a uniform barycentric
    point, reflected into the triangle); deterministic for a seed."""
    v, f = _mesh_arrays(mesh)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]  # [F, 3] each
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)  # [F]
    if not area.sum() > 0:
        raise MetricInputError("a mesh with a non-zero surface area", "only degenerate triangles")
    rng = np.random.default_rng(seed)
    tri = rng.choice(len(f), size=n_points, p=area / area.sum())
    u, w = rng.random(n_points), rng.random(n_points)
    flip = u + w > 1
    u[flip], w[flip] = 1 - u[flip], 1 - w[flip]
    return a[tri] + u[:, None] * (b[tri] - a[tri]) + w[:, None] * (c[tri] - a[tri])


def points_to_mesh_distance(points: Any, mesh: Any) -> np.ndarray:
    """Unsigned distance [N] from points [N, 3] to the closest point of a mesh (open3d RaycastingScene).

    open3d works in float32, so both are first moved by the mesh's bounding-box centre (float64): a
    georeferenced building (coordinates ~1e6 m) keeps micrometre resolution instead of decimetres."""
    p = _as_f64(points, "points")
    if p.ndim != 2 or p.shape[1] != 3:
        raise MetricInputError("points [N, 3]", f"shape {p.shape}")
    import open3d as o3d  # here, not at the top: the image metrics (used by training) need no open3d

    v, f = _mesh_arrays(mesh)
    origin = 0.5 * (v.min(axis=0) + v.max(axis=0))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((v - origin).astype(np.float32)),
                        o3d.core.Tensor(f.astype(np.uint32)))
    if len(p) == 0:
        return np.zeros(0)
    d = scene.compute_distance(o3d.core.Tensor((p - origin).astype(np.float32)))
    return d.numpy().astype(np.float64)


def surface_distance(source: Any, target: Any, *, n_points: int = 100_000, seed: int = 0) -> DistanceStats:
    """One-sided surface distance from ``source`` to ``target`` (meshes): ``n_points`` points sampled
    uniformly on the source, distances to the target's surface, summarised (mean, p95, max). Run it both
    ways for accuracy (source = reconstruction) and completeness (source = truth)."""
    if n_points < 1:
        raise EmptyMaskError("n_points >= 1", str(n_points))
    return distance_stats(points_to_mesh_distance(sample_mesh_surface(source, n_points, seed), target))


@dataclass(frozen=True)
class AngleStats:
    """Summary of angle errors in degrees."""

    mean_deg: float
    median_deg: float
    p95_deg: float
    count: int


def normal_angle_map_deg(normals0: Any, normals1: Any, mask: Any = None) -> np.ndarray:
    """Angle in degrees [...] between normals [..., 3] (maps [H, W, 3] or lists [N, 3]), atan2(|a x b|, a . b)
    (accurate near 0 and 180 deg, unlike acos; no unit length needed). 0 outside the mask [...]; a masked
    normal of zero length raises ``MetricInputError``."""
    a, b = _as_f64(normals0, "normals0"), _as_f64(normals1, "normals1")
    if a.shape != b.shape or a.ndim < 2 or a.shape[-1] != 3:
        raise MetricInputError("two normal arrays [..., 3] of the same shape", f"{a.shape} and {b.shape}")
    m = _as_mask(mask, a.shape[:-1])
    zero = m & ((np.linalg.norm(a, axis=-1) == 0) | (np.linalg.norm(b, axis=-1) == 0))
    if zero.any():
        raise MetricInputError("non-zero normals inside the validity mask", f"{int(zero.sum())} zero normals")
    ang = np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(axis=-1)))
    return np.where(m, ang, 0.0)


def normal_angle_error_deg(normals0: Any, normals1: Any, mask: Any = None) -> AngleStats:
    """Mean, median and 95th percentile of the normal angle error in degrees over a validity mask."""
    ang = normal_angle_map_deg(normals0, normals1, mask)
    m = _as_mask(mask, ang.shape)
    if not m.any():
        raise EmptyMaskError("a validity mask with at least one normal", "an empty mask")
    e = ang[m]
    return AngleStats(float(e.mean()), float(np.median(e)), float(np.percentile(e, 95)), int(e.size))


@dataclass(frozen=True)
class CornerError:
    """Panel corner error: mean and max in pixels of the rectified facade image and in metres."""

    mean_px: float
    max_px: float
    mean_m: float
    max_m: float
    count: int


def corner_error(corners_px: Any, true_corners_px: Any,
                 metres_per_px: float | tuple[float, float]) -> CornerError:
    """Distances between corresponding corners [N, 2] (x, y pixels of the rectified facade image, row i of
    one matching row i of the other). ``metres_per_px``: the pixel size, one number or (x, y) for a
    non-square pixel; the metre error is |(dx sx, dy sy)|."""
    p, t = _as_f64(corners_px, "corners_px"), _as_f64(true_corners_px, "true_corners_px")
    if p.shape != t.shape or p.ndim != 2 or p.shape[1] != 2:
        raise MetricInputError("two corner arrays [N, 2] of the same shape", f"{p.shape} and {t.shape}")
    if len(p) == 0:
        raise EmptyMaskError("at least one corner", "none")
    s = np.broadcast_to(_as_f64(metres_per_px, "metres_per_px"), (2,))
    if not (s > 0).all():
        raise MetricInputError("metres_per_px > 0", str(metres_per_px))
    d_px = np.linalg.norm(p - t, axis=1)
    d_m = np.linalg.norm((p - t) * s, axis=1)
    return CornerError(float(d_px.mean()), float(d_px.max()), float(d_m.mean()), float(d_m.max()), len(p))
