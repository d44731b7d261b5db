"""The compiled CPU backend: csrc/surfel_raster.cpp (C++17 + OpenMP), built with the system C++ compiler on
first use into a cache folder and called through ctypes on contiguous tensors.

Why not torch.utils.cpp_extension: the kernel needs no torch headers, and a plain shared library builds in a
few seconds instead of about a minute, which matters on a fresh CI machine. The build is keyed on the source,
the flags, the compiler and the CPU, written under a temporary name and renamed into place (safe when several
test processes build at once). If it cannot be built, ``load`` returns None and callers fall back to the torch
backend (render.resolve_backend logs a warning).

The cache folder is ``$FACADE_KERNEL_CACHE`` or ``~/.cache/facade_pipeline/kernels``.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path

import torch

from facade_pipeline.splatting.types import (
    LOWPASS_SIGMA_PX,
    TILE_SIZE,
    PixelWindow,
    TileBins,
    lowpass_inv_var,
)

log = logging.getLogger(__name__)

SOURCE = Path(__file__).resolve().parent / "csrc" / "surfel_raster.cpp"
FLAGS = ["-O3", "-march=native", "-fopenmp", "-shared", "-fPIC", "-std=c++17"]
CACHE_ENV = "FACADE_KERNEL_CACHE"

_lib: ctypes.CDLL | None = None
_error: str | None = None
_tried = False


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") or line.startswith("flags"):
                return line
    except OSError:
        pass
    return platform.processor()


def _cache_dir() -> Path:
    env = os.environ.get(CACHE_ENV)
    return Path(env) if env else Path.home() / ".cache" / "facade_pipeline" / "kernels"


def _build(compiler: str) -> Path:
    """Compile the kernel if the cache lacks it; returns the shared library's path."""
    version = subprocess.run([compiler, "--version"], capture_output=True, text=True, check=True).stdout
    key = hashlib.sha256(
        SOURCE.read_bytes() + " ".join(FLAGS).encode() + version.encode() + _cpu_model().encode()
    ).hexdigest()[:16]
    target = _cache_dir() / f"surfel_raster_{key}.so"
    if target.is_file():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=target.parent, suffix=".so.tmp")
    os.close(fd)
    try:
        subprocess.run([compiler, *FLAGS, "-o", tmp, str(SOURCE)], capture_output=True, text=True, check=True)
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return target


def _declare(lib: ctypes.CDLL) -> None:
    p, i64, f64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double, ctypes.c_int
    for suffix in ("f32", "f64"):
        fwd = getattr(lib, f"surfel_forward_{suffix}")
        fwd.argtypes = [p] * 5 + [i64] * 2 + [p] * 2 + [i64] * 6 + [f64] * 3 + [i32] + [p] * 10
        fwd.restype = None
        bwd = getattr(lib, f"surfel_backward_{suffix}")
        bwd.argtypes = [p] * 5 + [i64] * 2 + [p] * 2 + [i64] * 6 + [f64] * 3 + [i32] + [p] * 15
        bwd.restype = None
        count = getattr(lib, f"surfel_bin_count_{suffix}")
        count.argtypes = [p, p, i64, f64, f64] + [i64] * 6 + [i32] + [p] * 3
        count.restype = None
    lib.surfel_bin_fill.argtypes = [p, i64, p, i64, p, p]
    lib.surfel_bin_fill.restype = None


def load() -> ctypes.CDLL | None:
    """The kernel library, built on first call; None if it cannot be built or loaded (see load_error)."""
    global _lib, _error, _tried
    if _tried:
        return _lib
    _tried = True
    compiler = os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++")
    try:
        if compiler is None:
            raise FileNotFoundError("no C++ compiler (g++ or c++) on PATH")
        lib = ctypes.CDLL(str(_build(compiler)))
        _declare(lib)
        _lib = lib
    except (OSError, subprocess.CalledProcessError, AttributeError) as exc:
        detail = getattr(exc, "stderr", "") or ""
        _error = f"{type(exc).__name__}: {exc} {detail[-2000:]}".strip()
        log.warning("could not build the C++ splatting kernel: %s", _error)
    return _lib


def load_error() -> str | None:
    return _error


def _ptr(t: torch.Tensor) -> int:
    return t.data_ptr()


def _suffix(dtype: torch.dtype) -> str:
    if dtype == torch.float32:
        return "f32"
    if dtype == torch.float64:
        return "f64"
    raise ValueError(f"the cpp backend takes float32 or float64 tensors, got {dtype}")


def _geometry(bins: TileBins) -> list[int]:
    w = bins.window
    return [w.x0, w.y0, w.width, w.height, bins.tiles_x, bins.tiles_y]


class _CppBlend(torch.autograd.Function):
    @staticmethod
    def forward(ctx, Tm, opac, feat, nrm, bins: TileBins, near: float, far: float, k_lp: float, threads: int):
        lib = load()
        assert lib is not None
        Tm, opac, feat, nrm = (x.detach().contiguous() for x in (Tm, opac, feat, nrm))
        H, W, F = bins.window.height, bins.window.width, feat.shape[1]
        bounds = bins.bounds.contiguous()
        out_feat = Tm.new_empty(H, W, F)
        out_T, out_depth, out_median, out_dist, out_M1, out_M2 = (Tm.new_empty(H, W) for _ in range(6))
        out_normal = Tm.new_empty(H, W, 3)
        out_last = torch.empty(H, W, dtype=torch.int32)
        out_median_id = torch.empty(H, W, dtype=torch.int64)
        getattr(lib, f"surfel_forward_{_suffix(Tm.dtype)}")(
            _ptr(Tm), _ptr(opac), _ptr(feat), _ptr(nrm), _ptr(bounds), F, Tm.shape[0],
            _ptr(bins.offsets), _ptr(bins.splat_ids), *_geometry(bins), near, far, k_lp, threads,
            _ptr(out_feat), _ptr(out_T), _ptr(out_depth), _ptr(out_normal), _ptr(out_median), _ptr(out_dist),
            _ptr(out_M1), _ptr(out_M2), _ptr(out_last), _ptr(out_median_id),
        )  # fmt: skip
        ctx.bins, ctx.near, ctx.far, ctx.k_lp, ctx.threads = bins, near, far, k_lp, threads
        ctx.save_for_backward(Tm, opac, feat, nrm, out_T, out_M1, out_M2, out_last, out_median_id)
        return out_feat, out_T, out_depth, out_normal, out_median, out_dist

    @staticmethod
    def backward(ctx, gF, gT, gD, gN, gMed, gDist):
        Tm, opac, feat, nrm, out_T, out_M1, out_M2, out_last, out_median_id = ctx.saved_tensors
        bins: TileBins = ctx.bins
        grads = [torch.zeros_like(out_T) if g is None else g.contiguous().to(Tm.dtype)
                 for g in (gF, gT, gD, gN, gMed, gDist)]
        if gF is None:
            grads[0] = Tm.new_zeros(out_T.shape + (feat.shape[1],))
        if gN is None:
            grads[3] = Tm.new_zeros(out_T.shape + (3,))
        dTm, dop, dfeat, dnrm = (torch.zeros_like(x) for x in (Tm, opac, feat, nrm))
        getattr(load(), f"surfel_backward_{_suffix(Tm.dtype)}")(
            _ptr(Tm), _ptr(opac), _ptr(feat), _ptr(nrm), _ptr(bins.bounds.contiguous()), feat.shape[1],
            Tm.shape[0], _ptr(bins.offsets), _ptr(bins.splat_ids), *_geometry(bins), ctx.near, ctx.far,
            ctx.k_lp, ctx.threads, _ptr(out_T), _ptr(out_M1), _ptr(out_M2), _ptr(out_last),
            _ptr(out_median_id),
            *(_ptr(g) for g in grads), _ptr(dTm), _ptr(dop), _ptr(dfeat), _ptr(dnrm),
        )  # fmt: skip
        return dTm, dop, dfeat, dnrm, None, None, None, None, None


def bin_splats_cpp(
    ray_transform: torch.Tensor,  # [N, 3, 3]
    opacities: torch.Tensor,  # [N]
    depth: torch.Tensor,  # [N] centre depth, the sort key
    window: PixelWindow,
    near: float,
    threads: int | None = None,
    lowpass_sigma_px: float = LOWPASS_SIGMA_PX,
) -> TileBins:
    """binning.pixel_support_bounds + binning.bin_splats in the compiled kernel (a counting sort over tiles of
    the splats taken front to back): the same bins, without a sort of the pairs."""
    lib = load()
    if lib is None:
        raise RuntimeError(f"the C++ kernel is unavailable: {load_error()}")
    T = ray_transform.detach().reshape(-1, 9).contiguous()
    opac = opacities.detach().contiguous()
    n = T.shape[0]
    tiles_x, tiles_y = -(-window.width // TILE_SIZE), -(-window.height // TILE_SIZE)
    bounds = torch.empty(n, 4, dtype=torch.float64)
    rect = torch.empty(n, 4, dtype=torch.int64)
    counts = torch.zeros(tiles_x * tiles_y, dtype=torch.int64)
    getattr(lib, f"surfel_bin_count_{_suffix(T.dtype)}")(
        _ptr(T), _ptr(opac), n, near, lowpass_inv_var(lowpass_sigma_px), window.x0, window.y0, window.width,
        window.height, tiles_x, tiles_y, threads or torch.get_num_threads(), _ptr(bounds), _ptr(rect),
        _ptr(counts))
    offsets = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.int64)
    torch.cumsum(counts, 0, out=offsets[1:])
    order = torch.sort(depth.detach().to(torch.float64), stable=True).indices.contiguous()
    ids = torch.empty(int(offsets[-1]), dtype=torch.int64)
    cursor = offsets[:-1].clone()
    lib.surfel_bin_fill(_ptr(order), n, _ptr(rect), tiles_x, _ptr(cursor), _ptr(ids))
    return TileBins(offsets=offsets, splat_ids=ids, bounds=bounds, window=window, tiles_x=tiles_x,
                    tiles_y=tiles_y)


def blend_cpp(
    ray_transform: torch.Tensor,  # [N, 3, 3]
    opacities: torch.Tensor,  # [N]
    features: torch.Tensor,  # [N, F]
    normals: torch.Tensor,  # [N, 3]
    bins: TileBins,
    near: float,
    far: float,
    threads: int | None = None,
    lowpass_sigma_px: float = LOWPASS_SIGMA_PX,
) -> tuple[torch.Tensor, ...]:
    """Same contract as blend_torch.blend_torch, computed by the compiled kernel on ``threads`` OpenMP
    threads (default: torch.get_num_threads())."""
    if load() is None:
        raise RuntimeError(f"the C++ kernel is unavailable: {load_error()}")
    n_threads = threads or torch.get_num_threads()
    return _CppBlend.apply(
        ray_transform.reshape(-1, 9), opacities, features, normals, bins, near, far,
        lowpass_inv_var(lowpass_sigma_px), n_threads,
    )
