"""Float maps (normals, depth, reflectivity) as OpenEXR files, float32, ZIP-compressed (lossless: a
round trip is bit-exact). A map has named channels; a vector map is stored as ``<name>.X/Y/Z``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR

from facade_pipeline.errors import InputError
from facade_pipeline.io.atomic import atomic_path

_AXES = ("X", "Y", "Z", "W")


def write_exr(path: str | Path, channels: dict[str, np.ndarray]) -> None:
    """Write float maps atomically. ``channels``: name -> [H, W] or [H, W, C] (C <= 4, split into
    ``name.X``, ``name.Y``...). NaN and Inf are refused: invalid pixels are marked by a validity channel."""
    flat: dict[str, np.ndarray] = {}
    shape = None
    for name, arr in channels.items():
        arr = np.asarray(arr, dtype=np.float32)
        if not np.isfinite(arr).all():
            raise ValueError(f"{path}: channel {name!r} has NaN or Inf; mark invalid pixels with a mask")
        if arr.ndim == 3:
            for c in range(arr.shape[2]):
                flat[f"{name}.{_AXES[c]}"] = np.ascontiguousarray(arr[..., c])
        elif arr.ndim == 2:
            flat[name] = np.ascontiguousarray(arr)
        else:
            raise ValueError(f"{path}: channel {name!r} must be [H, W] or [H, W, C], got {arr.shape}")
        if shape is not None and arr.shape[:2] != shape:
            raise ValueError(f"{path}: channel {name!r} is {arr.shape[:2]}, others {shape}")
        shape = arr.shape[:2]
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp, OpenEXR.File(header, flat) as f:
        f.write(str(tmp))


def read_exr(path: str | Path) -> dict[str, np.ndarray]:
    """Read an EXR written by ``write_exr``: vector channels come back stacked as [H, W, C] float32."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "an EXR file", "no file")
    try:
        with OpenEXR.File(str(path)) as f:
            raw = {k: np.array(v.pixels, dtype=np.float32) for k, v in f.channels().items()}
    except Exception as e:  # OpenEXR raises several types for damaged files
        raise InputError(path, "a readable OpenEXR file", f"{type(e).__name__}: {e}") from None
    groups: dict[str, dict[str, np.ndarray]] = {}
    out: dict[str, np.ndarray] = {}
    for key, arr in raw.items():
        if "." in key:
            base, axis = key.rsplit(".", 1)
            if axis in _AXES:
                groups.setdefault(base, {})[axis] = arr
                continue
        out[key] = arr
    for base, parts in groups.items():
        out[base] = np.stack([parts[a] for a in _AXES if a in parts], axis=-1)
    return out
