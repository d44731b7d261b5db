"""The gsplat CUDA backend: an adapter from our conventions to ``gsplat.rasterization_2dgs`` (gsplat >= 1.4,
the optional ``gpu`` extra). gsplat is imported inside ``render`` only, which runs only for CUDA tensors when
``torch.cuda.is_available()``: its first import compiles the CUDA extension (minutes), and where nvcc cannot
build it raises ImportError; no CPU code path may trigger that.

Conventions: gsplat's ``viewmats`` is our ``cam_from_world`` (OpenCV axes), its ``Ks`` our ``K``, quaternions
(w, x, y, z) in both, scales padded with a zero third axis (a surfel), pixel centres at +0.5 in both. A crop
window is rendered by shifting the principal point by the window origin (exact for a pinhole camera). gsplat
returns world-space normals (it rotates its camera-space normals by the inverse view rotation).

Documented differences from the torch/cpp backends (the reference 2DGS semantics):
- depth: gsplat blends the splat centre's depth, not the ray-splat intersection's, so expected and median
  depths differ on slanted splats (equal on splats parallel to the image plane);
- distortion: gsplat's is an L1 form on its own depth mapping, not the 2DGS L2 form on NDC depth; only the
  fact that it is zero for a single surface carries over;
- ``far`` is not a culling plane in our API, so gsplat gets far_plane = 1e10 (it culls beyond its far plane);
- the low-pass filter: gsplat's kernel has 2DGS's sigma (sqrt(2)/2 px) built in, so ``render_2dgs`` never
  sends it another ``lowpass_sigma_px`` (refused for ``backend="gsplat"``, the torch backend for "auto");
- support: gsplat bounds each splat by a fixed-sigma screen radius, ours by the exact alpha >= 1/255 support,
  so faint splat rims (alpha close to 1/255) can differ, most on splats seen nearly edge-on. Measured on an
  H100 with gsplat 1.5.3 (tests/splatting/test_gsplat.py, benchmarks/RESULTS.md): fronto-parallel splats
  agree to 5e-3 per pixel; randomly tilted ones to 5e-4 on average, 1.1e-2 at the 99th percentile.
"""

from __future__ import annotations

import importlib.util

import torch

from facade_pipeline.splatting.types import PixelWindow, SurfelRender

GSPLAT_FAR = 1e10


def available() -> bool:
    """Whether gsplat is installed (checked without importing it)."""
    return importlib.util.find_spec("gsplat") is not None


def render(
    means: torch.Tensor,  # [N, 3]
    quats: torch.Tensor,  # [N, 4]
    scales: torch.Tensor,  # [N, 2]
    opacities: torch.Tensor,  # [N]
    features: torch.Tensor,  # [N, F]
    cam_from_world: torch.Tensor,  # [4, 4]
    K: torch.Tensor,  # [3, 3]
    window: PixelWindow,
    near: float,
    far: float,
) -> SurfelRender:
    """render_2dgs on CUDA through gsplat (module docstring for the differences). ``far`` is unused (see
    above) and kept for the common signature."""
    del far
    if means.device.type != "cuda" or not torch.cuda.is_available():
        raise ValueError(f"the gsplat backend needs CUDA tensors and a CUDA device, got {means.device}")
    from gsplat import rasterization_2dgs  # lazy: compiles gsplat's CUDA code on first use

    K_win = K.clone()
    K_win[0, 2] -= window.x0
    K_win[1, 2] -= window.y0
    scales3 = torch.cat([scales, torch.zeros_like(scales[:, :1])], dim=-1)  # [N, 3]
    # features as [C=1, N, F]: gsplat 1.5 takes post-activation colours per camera ([N, F] only with SH)
    colors, alphas, normals, _, distort, median, _ = rasterization_2dgs(
        means, quats, scales3, opacities, features[None], cam_from_world[None], K_win[None], window.width,
        window.height, near_plane=near, far_plane=GSPLAT_FAR, render_mode="RGB+ED", distloss=True,
    )  # fmt: skip
    alpha = alphas[0, ..., 0]  # [H, W]
    return SurfelRender(
        features=colors[0, ..., :-1],
        alpha=alpha,
        depth_expected=torch.where(alpha > 0, colors[0, ..., -1], torch.zeros_like(alpha)),
        depth_median=median[0, ..., 0],
        normal=normals[0],
        distortion=distort[0, ..., 0],
    )
