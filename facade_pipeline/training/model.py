"""The Gaussian model: per-splat 2DGS parameters plus SH diffuse colour, reflectivity and Fresnel F0
(section 3.2.1). Raw tensors are kept unconstrained; activations give the physical values."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from facade_pipeline.shading.sh import num_sh_coeffs

#: name -> (trailing shape builder); the order is the order of optimiser groups and checkpoints.
PARAM_NAMES = (
    "means",
    "quats",
    "log_scales",
    "opacity_logits",
    "sh_dc",
    "sh_rest",
    "refl_logits",
    "f0_logits",
)


def inverse_sigmoid(x: Tensor) -> Tensor:
    x = x.clamp(1e-6, 1.0 - 1e-6)
    return torch.log(x / (1.0 - x))


@dataclass
class GaussianModel:
    """N surfels. Every field is an ``nn.Parameter`` with N rows (densification replaces them)."""

    means: nn.Parameter  # [N, 3] world centres p
    quats: nn.Parameter  # [N, 4] (w, x, y, z) rotation; tangents t_u, t_v are its first two columns
    log_scales: nn.Parameter  # [N, 2] log s_u, log s_v
    opacity_logits: nn.Parameter  # [N]
    sh_dc: nn.Parameter  # [N, 1, 3] degree-0 SH coefficients
    sh_rest: nn.Parameter  # [N, K - 1, 3] higher bands, K = (degree + 1)^2
    refl_logits: nn.Parameter  # [N] reflectivity r = sigmoid(.)
    f0_logits: nn.Parameter  # [N, 3] Fresnel f0 = sigmoid(.)

    @property
    def n(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return int(round((self.sh_rest.shape[1] + 1) ** 0.5)) - 1

    def params(self) -> dict[str, nn.Parameter]:
        return {name: getattr(self, name) for name in PARAM_NAMES}

    def replace(self, tensors: dict[str, Tensor]) -> None:
        for name in PARAM_NAMES:
            setattr(
                self,
                name,
                tensors[name]
                if isinstance(tensors[name], nn.Parameter)
                else nn.Parameter(tensors[name].detach().contiguous()),
            )

    # --- activations ---
    def unit_quats(self) -> Tensor:  # [N, 4]
        return self.quats / self.quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    def scales(self) -> Tensor:  # [N, 2]
        return self.log_scales.exp()

    def opacities(self) -> Tensor:  # [N]
        return torch.sigmoid(self.opacity_logits)

    def reflectivity(self) -> Tensor:  # [N]
        return torch.sigmoid(self.refl_logits)

    def f0(self) -> Tensor:  # [N, 3]
        return torch.sigmoid(self.f0_logits)

    def sh_coeffs(self) -> Tensor:  # [N, K, 3]
        return torch.cat([self.sh_dc, self.sh_rest], dim=1)

    def normals(self) -> Tensor:  # [N, 3] unit t_u x t_v (the rotation's third column)
        return quat_to_rotmat(self.unit_quats())[:, :, 2]

    def state(self) -> dict[str, Tensor]:
        return {name: t.detach().clone() for name, t in self.params().items()}

    @classmethod
    def from_state(cls, state: dict[str, Tensor], device: torch.device | str) -> GaussianModel:
        return cls(**{name: nn.Parameter(state[name].to(device).contiguous()) for name in PARAM_NAMES})

    @classmethod
    def create(
        cls,
        means: Tensor,
        quats: Tensor,
        scales: Tensor,
        colors: Tensor,
        opacity: float,
        reflectivity: float | Tensor,
        f0: float,
        sh_degree: int,
    ) -> GaussianModel:
        """A model from initial centres [N, 3], rotations [N, 4], scales [N, 2] (m) and colours [N, 3];
        ``reflectivity`` one value for all or one per splat [N]."""
        from facade_pipeline.shading.sh import rgb_to_sh_dc

        n = means.shape[0]
        k = num_sh_coeffs(sh_degree)
        dt, dev = means.dtype, means.device
        return cls.from_state(
            {
                "means": means,
                "quats": quats,
                "log_scales": scales.clamp_min(1e-7).log(),
                "opacity_logits": inverse_sigmoid(torch.full((n,), opacity, dtype=dt, device=dev)),
                "sh_dc": rgb_to_sh_dc(colors).unsqueeze(1),
                "sh_rest": torch.zeros(n, k - 1, 3, dtype=dt, device=dev),
                "refl_logits": inverse_sigmoid(
                    torch.as_tensor(reflectivity, dtype=dt, device=dev).expand(n).clone()
                ),
                "f0_logits": inverse_sigmoid(torch.full((n, 3), f0, dtype=dt, device=dev)),
            },
            dev,
        )


def quat_to_rotmat(q: Tensor) -> Tensor:  # [N, 4] unit (w, x, y, z) -> [N, 3, 3]
    """Rotation matrices of unit quaternions; column 0 and 1 are the splat tangents, column 2 its normal."""
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).view(-1, 3, 3)


def quat_from_normal(normals: Tensor) -> Tensor:  # [N, 3] unit -> [N, 4]
    """A unit quaternion whose rotation maps +z to ``normals`` (the shortest arc), so the splat lies in the
    plane with that normal; a normal of -z gets the rotation by pi about x."""
    z = torch.zeros_like(normals)
    z[:, 2] = 1.0
    w = 1.0 + (z * normals).sum(-1)  # 1 + cos
    xyz = torch.cross(z, normals, dim=-1)
    q = torch.cat([w.unsqueeze(-1), xyz], dim=-1)
    flip = w < 1e-6
    q[flip] = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=q.dtype, device=q.device)
    return q / q.norm(dim=-1, keepdim=True)
