"""The trained Gaussians as a 3DGS-style binary PLY that common splat viewers open.

Standard properties: ``x y z``, ``nx ny nz`` (the surfel normal), ``f_dc_0..2``, ``f_rest_*`` (channel-major:
all coefficients of red, then green, then blue), ``opacity`` (logit), ``scale_0..2`` (log; 2D Gaussians are
flat, so ``scale_2`` is the log of a tiny thickness, which viewers for 3D Gaussians draw as a disk),
``rot_0..3`` (w, x, y, z). Extra properties: ``reflectivity`` and ``f0_0..2`` (activated, in [0, 1]).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from facade_pipeline.errors import InputError
from facade_pipeline.io.atomic import atomic_path
from facade_pipeline.training.model import GaussianModel, inverse_sigmoid

FLAT_LOG_SCALE = math.log(1e-7)
"""``scale_2`` of every splat: a surfel has no thickness."""


def model_columns(model: GaussianModel) -> dict[str, np.ndarray]:
    """Name -> [N] float32 column, in file order."""
    with torch.no_grad():
        rest = model.sh_rest.transpose(1, 2).reshape(model.n, -1)  # [N, 3 * (K - 1)] channel-major
        cols = {
            **{a: model.means[:, i] for i, a in enumerate("xyz")},
            **{f"n{a}": model.normals()[:, i] for i, a in enumerate("xyz")},
            **{f"f_dc_{i}": model.sh_dc[:, 0, i] for i in range(3)},
            **{f"f_rest_{i}": rest[:, i] for i in range(rest.shape[1])},
            "opacity": model.opacity_logits,
            "scale_0": model.log_scales[:, 0],
            "scale_1": model.log_scales[:, 1],
            "scale_2": torch.full((model.n,), FLAT_LOG_SCALE),
            **{f"rot_{i}": model.unit_quats()[:, i] for i in range(4)},
            "reflectivity": model.reflectivity(),
            **{f"f0_{i}": model.f0()[:, i] for i in range(3)},
        }
        return {k: v.detach().to("cpu", torch.float32).numpy() for k, v in cols.items()}


def write_ply(path: str | Path, model: GaussianModel) -> None:
    """Write the model as a binary little-endian PLY, atomically."""
    cols = model_columns(model)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {model.n}"]
    header += [f"property float {name}" for name in cols] + ["end_header"]
    data = np.stack(list(cols.values()), axis=1).astype("<f4")
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(data.tobytes())


def read_ply(path: str | Path) -> dict[str, np.ndarray]:
    """Read a PLY written by ``write_ply``: name -> [N] float32 column."""
    path = Path(path)
    raw = path.read_bytes()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise InputError(path, "a binary PLY of Gaussians", "no PLY header")
    lines = raw[:end].decode("ascii").splitlines()
    n = next(int(line.split()[2]) for line in lines if line.startswith("element vertex"))
    names = [line.split()[2] for line in lines if line.startswith("property float")]
    body = raw[end + len(b"end_header\n") :]
    if len(body) != 4 * n * len(names):
        raise InputError(path, f"{n} x {len(names)} float32 values", f"{len(body)} bytes")
    data = np.frombuffer(body, dtype="<f4").reshape(n, len(names))
    return {name: data[:, i] for i, name in enumerate(names)}


def model_from_ply(cols: dict[str, np.ndarray], device: torch.device | str = "cpu") -> GaussianModel:
    """The model back from ``read_ply``'s columns (reflectivity and F0 from their activated values)."""
    n = len(cols["x"])
    rest_names = sorted((k for k in cols if k.startswith("f_rest_")), key=lambda k: int(k.split("_")[-1]))
    t = {k: torch.as_tensor(np.array(v)) for k, v in cols.items()}
    rest = torch.stack([t[k] for k in rest_names], 1) if rest_names else torch.zeros(n, 0)
    return GaussianModel.from_state(
        {
            "means": torch.stack([t["x"], t["y"], t["z"]], 1),
            "quats": torch.stack([t[f"rot_{i}"] for i in range(4)], 1),
            "log_scales": torch.stack([t["scale_0"], t["scale_1"]], 1),
            "opacity_logits": t["opacity"],
            "sh_dc": torch.stack([t[f"f_dc_{i}"] for i in range(3)], 1).unsqueeze(1),
            "sh_rest": rest.reshape(n, 3, -1).transpose(1, 2),
            "refl_logits": inverse_sigmoid(t["reflectivity"]),
            "f0_logits": inverse_sigmoid(torch.stack([t[f"f0_{i}"] for i in range(3)], 1)),
        },
        device,
    )
