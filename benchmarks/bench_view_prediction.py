"""What a held-out view's appearance can be predicted from, without training: the training photos warped
into the held-out view through a plane, scored as the evaluation scores a model (PSNR over the facade and
the glass masks), as imported and aligned.

    .venv/bin/python benchmarks/bench_view_prediction.py --bundle gcw.npz --building gcw_dev

The plane is the corrected mesh's glass (a plane fitted to its glass triangles) moved d metres behind
itself, away from the cameras. At d = 0 the warp carries what lies on the glass (the frames, dirt, the
glass's own colour); at d > 0 what stands d behind it: an interior, or a reflection, since a plane
mirror's image of a point d in front of the glass behaves as a point d behind it; d = inf carries the
directions alone (a distant scene seen through, or mirrored in, the glass). The last rows take two layers:
the pixels off the view's glass mask from d = 0, those on it from d = inf. Each held-out view is predicted
from its nearest training photo (camera centres), from the best single training photo (an oracle: the one
with the highest glass PSNR at that d) and from the mean of every training photo that sees the pixel (what
a layer at that depth, one colour per point, learns at best from these views). A training photo is brought
to the model's exposure by its estimated gain (the bundle's), as training does; pixels the warp leaves
uncovered take the photo's mean facade colour. *Aligned*: the held-out view's pose and a gain per colour
channel fitted to the nearest photo's prediction at that d first (``training.corrections.align_view`` with
the building's ``[evaluate.align]``, as the evaluate stage aligns a view to a model), then every source's
prediction made from that pose with that gain.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _common import machine, record_results  # noqa: E402

from facade_pipeline.config import load_building_config  # noqa: E402
from facade_pipeline.evaluation.image_eval import region_masks  # noqa: E402
from facade_pipeline.evaluation.metrics import psnr  # noqa: E402
from facade_pipeline.training.corrections import align_view  # noqa: E402
from facade_pipeline.training.data import (  # noqa: E402
    TrainData,
    downscale_view,
    load_bundle,
    pixel_budget_factor,
)
from facade_pipeline.training.params import AlignParams  # noqa: E402

#: float32, as the evaluation renders
DTYPE = torch.float32
#: depths behind the glass (m); inf: directions only
DEPTHS = (0.0, 0.03, 0.3, 3.0, math.inf)
#: two layers: the frames (off the glass mask) from the glass plane, the glass from directions alone
TWO_LAYERS = (0.0, math.inf)


def _depth(depth) -> str:
    return f"{depth[0]:g} off the glass, {depth[1]:g} on it" if isinstance(depth, tuple) else f"{depth:g}"


def glass_plane(data: TrainData) -> tuple[np.ndarray, float]:
    """The plane n . x = c fitted to the vertices of the corrected mesh's glass triangles (least squares), n
    pointing away from the cameras."""
    init = data.init
    tri = init.mesh_triangles if init.mesh_glass is None else init.mesh_triangles[init.mesh_glass]
    p = init.mesh_vertices[np.unique(tri)]
    mean = p.mean(axis=0)
    n = np.linalg.svd(p - mean, full_matrices=False)[2][-1]
    cams = np.array([v.camera.center for v in data.views])
    if float(((cams - mean) @ n).mean()) > 0:
        n = -n
    return n, float(n @ mean)


class Warp:
    """Training photo ``src`` seen from a camera through the plane n . x = c + d (or along directions,
    d = inf), differentiable in the camera's pose (for ``align_view``)."""

    def __init__(self, data: TrainData, src: int, plane: tuple[np.ndarray, float], depth: float):
        v = data.views[src]
        gain = 1.0 if data.exposure is None else np.exp(data.exposure.log_gain[src])
        self.image = torch.as_tensor(v.image / gain, dtype=DTYPE).permute(2, 0, 1)[None]
        self.K = torch.as_tensor(v.camera.K, dtype=DTYPE)
        self.T = torch.as_tensor(v.camera.cam_from_world, dtype=DTYPE)
        self.size = (v.camera.width, v.camera.height)
        self.n = torch.as_tensor(plane[0], dtype=DTYPE)
        self.c = plane[1] + (0.0 if math.isinf(depth) else depth)
        self.inf = math.isinf(depth)
        m = v.facade_mask
        facade = self.image[0].permute(1, 2, 0).numpy()[m]
        self.fill = torch.as_tensor(facade.mean(0) if m.any() else [0.5] * 3)

    def __call__(self, K: torch.Tensor, cam_from_world: torch.Tensor, hw: tuple[int, int]):
        """[H, W, 3] the prediction and [H, W] bool where the source photo covers it."""
        h, w = hw
        ys, xs = torch.meshgrid(torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij")
        pix = torch.stack([xs, ys, torch.ones_like(xs)], -1).to(DTYPE).reshape(-1, 3)
        R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
        d = pix @ torch.linalg.inv(K).T @ R  # world directions (rows: R^T d_cam)
        if self.inf:
            xc = d @ self.T[:3, :3].T
        else:
            o = -R.T @ t
            s = (self.c - self.n @ o) / (d @ self.n)
            x = o + s[:, None] * d
            xc = x @ self.T[:3, :3].T + self.T[:3, 3]
            xc = torch.where((s > 0)[:, None], xc, torch.full_like(xc, -1.0))
        z = xc[:, 2]
        uv = (xc @ self.K.T)[:, :2] / z.clamp_min(1e-9)[:, None]
        sw, sh = self.size
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= sw) & (uv[:, 1] >= 0) & (uv[:, 1] <= sh)
        grid = torch.stack([2 * uv[:, 0] / sw - 1, 2 * uv[:, 1] / sh - 1], -1).reshape(1, h, w, 2)
        grid = torch.where(ok.reshape(1, h, w, 1), grid, torch.zeros_like(grid))
        rgb = torch.nn.functional.grid_sample(self.image, grid, align_corners=False)[0].permute(1, 2, 0)
        ok = ok.reshape(h, w)
        return torch.where(ok[..., None], rgb, self.fill), ok


def predict(warps: list[Warp], K: torch.Tensor, cam_from_world: torch.Tensor, hw) -> torch.Tensor:
    """The mean over ``warps`` of the photos that cover each pixel (one photo: its warp)."""
    if len(warps) == 1:
        return warps[0](K, cam_from_world, hw)[0]
    acc = torch.zeros(*hw, 3, dtype=DTYPE)
    cnt = torch.zeros(*hw, 1, dtype=DTYPE)
    for wp in warps:
        rgb, ok = wp(K, cam_from_world, hw)
        acc = acc + rgb * ok[..., None]
        cnt = cnt + ok[..., None]
    return torch.where(cnt > 0, acc / cnt.clamp_min(1), warps[0].fill)


def score(rgb: np.ndarray, view) -> tuple[float, float]:
    m = region_masks(view.facade_mask, view.glass_mask)
    return psnr(rgb, view.image, m["facade"]), psnr(rgb, view.image, m["glass"])


def predictor(data: TrainData, sources: list[int], plane, depth, glass: np.ndarray):
    """A prediction from ``sources`` at ``depth`` (m; a pair: the first for the pixels off ``glass`` [H, W],
    the second for those on it, two layers), as a function of the camera (K, cam_from_world, (H, W))."""
    near, far = depth if isinstance(depth, tuple) else (depth, depth)
    layers = [[Warp(data, s, plane, d) for s in sources] for d in dict.fromkeys((near, far))]
    on_glass = torch.as_tensor(glass)[..., None]

    def run(K: torch.Tensor, cam_from_world: torch.Tensor, hw) -> torch.Tensor:
        rgb = [predict(w, K, cam_from_world, hw) for w in layers]
        return rgb[0] if len(rgb) == 1 else torch.where(on_glass, rgb[1], rgb[0])

    return run


def measure(data: TrainData, tgt: int, sources: list[int], plane, depth, fitted=None):
    """(facade, glass) PSNR of the held-out view ``tgt`` predicted from ``sources`` at ``depth``
    (``predictor``), from its imported camera or, with ``fitted`` (``align``'s pose and gain), from that."""
    v = data.views[tgt]
    run = predictor(data, sources, plane, depth, v.glass_mask)
    K = torch.as_tensor(v.camera.K, dtype=DTYPE)
    hw = (v.camera.height, v.camera.width)
    if fitted is None:
        rgb = run(K, torch.as_tensor(v.camera.cam_from_world, dtype=DTYPE), hw)
    else:
        rgb = run(K, fitted[0], hw) * fitted[1]
    return score(rgb.clamp(0, 1).detach().numpy(), v)


def align(data: TrainData, tgt: int, source: int, plane, depth, params: AlignParams):
    """The held-out view's pose and gain per channel fitted to its prediction from ``source`` at ``depth``
    (``align_view``, on the view reduced to ``params.max_pixels`` as evaluate fits it)."""
    v = data.views[tgt]
    fit = downscale_view(v, pixel_budget_factor(v.camera.width, v.camera.height, params.max_pixels))
    run = predictor(data, [source], plane, depth, fit.glass_mask)
    Kf = torch.as_tensor(fit.camera.K, dtype=DTYPE)
    with torch.enable_grad():
        a = align_view(
            lambda cfw: run(Kf, cfw, (fit.camera.height, fit.camera.width)),
            torch.as_tensor(v.camera.cam_from_world, dtype=DTYPE),
            torch.as_tensor(fit.image, dtype=DTYPE),
            torch.as_tensor(fit.facade_mask),
            params,
        )
    return a.cam_from_world.to(DTYPE), a.gain


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bundle", required=True, help="training data from bench_train.py --save-bundle")
    ap.add_argument("--building", default="gcw_dev", help="whose [evaluate.align] aligns the views")
    ap.add_argument(
        "--depths",
        default=",".join(f"{d:g}" for d in DEPTHS),
        help="comma-separated depths behind the glass (m; inf: directions only); the two layers always",
    )
    ap.add_argument("--no-write", action="store_true")
    a = ap.parse_args()
    torch.set_grad_enabled(False)
    data = load_bundle(a.bundle)
    align_params = load_building_config(a.building).section("evaluate.align", AlignParams)
    plane = glass_plane(data)
    centres = np.array([v.camera.center for v in data.views])
    dist = [float(abs(centres[i] @ plane[0] - plane[1])) for i in data.test_idx]
    rows = []
    for depth in (*(float(x) for x in a.depths.split(",")), TWO_LAYERS):
        res: dict[str, list] = {}
        for t in data.test_idx:
            near = min(data.train_idx, key=lambda s: float(np.linalg.norm(centres[s] - centres[t])))
            singles = {s: measure(data, t, [s], plane, depth) for s in data.train_idx}
            best = max(singles, key=lambda s: singles[s][1])
            # one fit of the view's pose and gain (to the nearest photo's prediction) serves every source:
            # the pose error is the view's, whatever predicts it
            fitted = align(data, t, near, plane, depth, align_params)
            for name, srcs in (("nearest", [near]), ("best", [best]), ("mean", list(data.train_idx))):
                imported = singles[srcs[0]] if len(srcs) == 1 else measure(data, t, srcs, plane, depth)
                res.setdefault(name, []).append((*imported, *measure(data, t, srcs, plane, depth, fitted)))
        for name, vals in res.items():
            f = np.mean(vals, axis=0)
            rows.append((depth, name, f))
            said = f"facade {f[0]:.2f} / {f[2]:.2f}, glass {f[1]:.2f} / {f[3]:.2f}"
            print(f"d = {_depth(depth)} m, {name}: {said}", flush=True)
    stems = ", ".join(data.views[i].stem for i in data.test_idx)
    lines = [
        "\n## What a held-out view can be predicted from (no training)\n",
        f"{machine()}\n",
        f"`python benchmarks/bench_view_prediction.py --bundle {Path(a.bundle).name} "
        f"--building {a.building} --depths {a.depths}`: "
        f"held-out {stems} ({data.views[data.test_idx[0]].camera.width} x "
        f"{data.views[data.test_idx[0]].camera.height} px) from the {len(data.train_idx)} training photos "
        f"warped through the glass plane moved d behind itself (the cameras stand "
        f"{', '.join(f'{x:.3f}' for x in dist)} m in front of it). PSNR dB over the facade and the glass "
        "masks, as imported / aligned (pose and gain fitted to the nearest photo's prediction at that d, "
        "`[evaluate.align]`, and used for every source), mean "
        "over the held-out views. *nearest*: the nearest training photo; *best*: the training photo "
        "with the highest glass PSNR at that d (an oracle); *mean*: the mean of the training photos that see "
        "the pixel.\n",
        "| d behind the glass (m) | source | facade PSNR dB | glass PSNR dB |",
        "| --- | --- | --- | --- |",
    ]
    for depth, name, f in rows:
        lines.append(f"| {_depth(depth)} | {name} | {f[0]:.2f} / {f[2]:.2f} | {f[1]:.2f} / {f[3]:.2f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if not a.no_write:
        record_results(text)


if __name__ == "__main__":
    main()
