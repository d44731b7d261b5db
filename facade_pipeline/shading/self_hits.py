"""Reflected rays that meet the facade itself: the glass beside a proud frame bar mirrors the bar.

Frames stand proud of the glass (about 0.1 m); seen obliquely, the glass next to a bar reflects the bar's
side and front rather than the surroundings, and at the foot of a concave part one panel reflects another.
A network that only sees the surface point X_r and the direction w_r (the paper's MLP), or the environment
proxy's features where the ray would meet the surroundings (``shading.proxy``), cannot tell these rays
from their neighbours that pass the bar: it blurs the two, and the glass near every frame is wrong.

The corrected mesh (``correct_mesh``) has the frames' relief, so each reflected ray is cast against it
(open3d, through ``geometry.raycast``). The reflection MLP gets, per ray, a hit flag, the unit normal of
the hit triangle facing the ray (the side of the bar that is seen, which sets how it is lit), and the hit
distance over the facade's diagonal; all zero where the ray escapes. Where a ray hits, the proxy's
features are zeroed: that ray does not reach the surroundings.

The mesh must be wound outward (as ``correct_mesh`` writes it), and which triangles are glass matters:

- a ray whose first hit is the back of a glass triangle started behind the glass it leaves (the rendered
  X_r lies a little behind it): it goes on through it once;
- the back of a frame triangle counts as a hit. The corrected mesh has no side faces on its frames: the
  coarse surface's frame strips reach a little over the edges of the panels inserted under them (measured
  on demo: of the reflected rays of glass pixels that meet the mesh, 96 % meet a frame strip from behind,
  near where the true rays meet a bar's side), so a ray that passes under a strip stands for one that
  meets the bar.

With no labels every triangle is taken for glass (only front hits count).

No gradient flows through the cast: the hit is a step function of the ray, and X_r and w_r learn from
every other term. The mesh is kept as buffers of the module, out of its state dict (``train_gs`` saves it
beside the weights in ``reflection.pt``), and the ray-casting scene is built on first use, on the host.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

#: values per ray: hit flag, hit normal (3), hit distance over the facade diagonal
SELF_HIT_DIM = 5
#: the mesh's buffers, as ``reflection.pt`` stores them (``shading.reflection.reflection_record``)
MESH_FIELDS = ("vertices", "triangles", "glass")
#: a ray that meets a triangle's back goes on from this far past it (m)
_PASS_M = 1e-3


class FacadeHits(nn.Module):
    """First hits of reflected rays on the facade mesh, as MLP features (see the module docstring)."""

    def __init__(
        self,
        vertices: Tensor,
        triangles: Tensor,
        glass: Tensor | None,
        offset_m: float,
        max_distance_m: float,
    ):
        """``vertices`` [V, 3] (m), ``triangles`` [T, 3] and glass labels [T] bool (None: unknown) of the
        corrected mesh; rays start ``offset_m`` along w_r from X_r (off the surface they leave); hits
        farther than ``max_distance_m`` count as misses (0: none do)."""
        super().__init__()
        v = torch.as_tensor(vertices).detach().float().reshape(-1, 3)
        f = torch.as_tensor(triangles).detach().long().reshape(-1, 3)
        g = torch.ones(len(f), dtype=torch.bool) if glass is None else torch.as_tensor(glass).bool().ravel()
        if len(g) != len(f):
            raise ValueError(f"self hits need a glass label per triangle, got {len(g)} for {len(f)}")
        if len(f) == 0 or not bool(torch.isfinite(v).all()):
            raise ValueError(
                f"self hits need a mesh with triangles and finite vertices, got {len(v)} vertices, "
                f"{len(f)} triangles"
            )
        if offset_m < 0 or max_distance_m < 0:
            raise ValueError(
                f"self-hit offset and maximum distance must be >= 0, got {offset_m} m, {max_distance_m} m"
            )
        self.register_buffer("vertices", v.clone(), persistent=False)
        self.register_buffer("triangles", f.clone(), persistent=False)
        self.register_buffer("glass", g.clone(), persistent=False)
        self.offset_m = float(offset_m)
        self.max_distance_m = float(max_distance_m)
        self.scale_m = float((v.max(0).values - v.min(0).values).norm().clamp_min(1e-6))
        self._caster = None
        self._glass_host: np.ndarray | None = None  # the labels on the host, with the scene

    def _cast(self, origins: np.ndarray, dirs: np.ndarray):
        if self._caster is None:
            try:
                from facade_pipeline.geometry.raycast import MeshRaycaster
            except ImportError as e:
                raise ImportError(
                    f"the reflection MLP's self hits cast rays with open3d, which is not importable ({e}); "
                    "install it or train with mlp_self_hits = false"
                ) from e
            self._caster = MeshRaycaster(self.vertices.cpu().numpy(), self.triangles.cpu().numpy())
            self._glass_host = self.glass.cpu().numpy()
        return self._caster.cast(origins, dirs)

    @torch.no_grad()
    def forward(self, x: Tensor, w: Tensor) -> Tensor:  # x [P, 3] m, w [P, 3] unit -> [P, SELF_HIT_DIM]
        out = torch.zeros(x.shape[0], SELF_HIT_DIM, dtype=x.dtype, device=x.device)
        if x.shape[0] == 0:
            return out
        o = (x + self.offset_m * w).double().cpu().numpy()
        d = w.double().cpu().numpy()
        ok = np.isfinite(o).all(1) & np.isfinite(d).all(1) & (np.linalg.norm(d, axis=1) > 0.5)
        d = np.where(ok[:, None], d, [0.0, 0.0, 1.0])
        o = np.where(ok[:, None], o, 0.0)
        hits = self._cast(o, d)
        t, normal = hits.t.copy(), hits.normal.copy()
        # A first hit on a glass triangle's back (the mesh is wound outward): the ray started behind the
        # glass it leaves. Cast once more from just past that hit (see the module docstring).
        glass = self._glass_host
        back = np.isfinite(t) & ((normal * d).sum(1) > 0) & glass[np.maximum(hits.prim, 0)]
        if back.any():
            step = t[back] + _PASS_M
            again = self._cast(o[back] + step[:, None] * d[back], d[back])
            front = (again.normal * d[back]).sum(1) < 0
            t[back] = np.where(
                again.hit & (front | ~glass[np.maximum(again.prim, 0)]), again.t + step, np.inf
            )
            normal[back] = again.normal
        hit = ok & np.isfinite(t)
        if self.max_distance_m > 0:
            hit &= t <= self.max_distance_m
        # the side of the hit triangle that faces the ray's origin
        n = normal * -np.sign((normal * d).sum(1, keepdims=True) + 1e-12)
        feats = np.zeros((len(t), SELF_HIT_DIM), np.float32)
        feats[:, 0] = hit
        feats[:, 1:4] = np.where(hit[:, None], n, 0.0)
        feats[:, 4] = np.where(hit, np.minimum(np.nan_to_num(t, posinf=0.0) / self.scale_m, 1.0), 0.0)
        return out.copy_(torch.from_numpy(feats))
