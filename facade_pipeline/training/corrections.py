"""Per-view corrections of pose and exposure: the pose corrections training learns with the splats
(``pose_refinement``), and ``align_view``, which fits a pose and an exposure gain to one view against a
frozen model (how the evaluation aligns held-out views).

Photogrammetric poses carry errors of centimetres and hundredths of a degree, and UAV cameras expose each
photo on their own. A pose correction is a small rotation and translation applied in the camera frame,
``cam_from_world' = [exp(omega) | t] @ cam_from_world``; an exposure correction multiplies the rendered
colour by ``exp(g)``, one ``g`` per colour channel (a gain and a white balance). Views never trained on
keep a zero correction: their poses stay as imported.

A held-out view is compared with a model that never saw its pose error or its exposure, so part of its
error is the camera's, not the model's. Evaluations of methods trained from noisy poses therefore fit each
test view's pose against the frozen model before measuring it; ``align_view`` does that, with the gain,
and the evaluation reports the figures with and without it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from facade_pipeline.training.optimizers import adam
from facade_pipeline.training.params import AlignParams

#: Below this squared angle (rad^2) the rotation uses its Taylor series (exact to float64 rounding).
_SMALL = 1e-8


def so3_exp(omega: Tensor) -> Tensor:  # [..., 3] axis-angle (rad) -> [..., 3, 3]
    """Rodrigues' formula, finite in value and gradient at omega = 0 (exactly the identity there)."""
    t2 = (omega * omega).sum(-1, keepdim=True).unsqueeze(-1)  # [..., 1, 1]
    small = t2 < _SMALL
    t2_safe = torch.where(small, torch.ones_like(t2), t2)
    t = t2_safe.sqrt()
    a = torch.where(small, 1.0 - t2 / 6.0, torch.sin(t) / t)
    b = torch.where(small, 0.5 - t2 / 24.0, (1.0 - torch.cos(t)) / t2_safe)
    x, y, z = omega.unbind(-1)
    zero = torch.zeros_like(x)
    K = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*omega.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(K)
    return eye + a * K + b * (K @ K)


class ViewCorrections(nn.Module):
    """Per view, a rotation (axis-angle, rad) and translation (m) when ``pose``, a log gain per colour
    channel when ``exposure``; all zero at the start. The parameters of a correction not asked for do not
    exist (``rotation`` / ``translation`` / ``log_gain`` are None)."""

    rotation: nn.Parameter | None
    translation: nn.Parameter | None
    log_gain: nn.Parameter | None

    def __init__(self, n_views: int, device: torch.device | str, pose: bool = True, exposure: bool = False):
        super().__init__()
        for name, on in (("rotation", pose), ("translation", pose), ("log_gain", exposure)):
            value = nn.Parameter(torch.zeros(n_views, 3, device=device)) if on else None
            self.register_parameter(name, value)

    def cam_from_world(self, index: int, cam_from_world: Tensor) -> Tensor:  # [4, 4] -> [4, 4]
        """View ``index``'s corrected pose (the given one, unchanged, without pose corrections)."""
        if self.rotation is None or self.translation is None:
            return cam_from_world
        top = torch.cat([so3_exp(self.rotation[index]), self.translation[index, :, None]], dim=1)
        bottom = torch.zeros_like(top[:1])
        bottom[0, 3] = 1.0  # filled on the device: no copy from the host in a training step
        return torch.cat([top, bottom]).to(cam_from_world.dtype) @ cam_from_world

    def expose(self, index: int, rgb: Tensor) -> Tensor:  # [..., 3] -> [..., 3]
        """A rendered colour as view ``index``'s camera exposed it (unchanged without exposure)."""
        if self.log_gain is None:
            return rgb
        return rgb * self.log_gain[index].exp().to(rgb.dtype)

    def optimizer(self, lr_rotation: float, lr_translation: float, lr_exposure: float) -> torch.optim.Adam:
        """Adam with a named group per correction present."""
        rates = {"rotation": lr_rotation, "translation": lr_translation, "log_gain": lr_exposure}
        groups = [{"params": [t], "lr": rates[n], "name": f"view_{n}"} for n, t in self.named_parameters()]
        return adam(groups)


@dataclass(frozen=True)
class Alignment:
    """One view's fitted correction: the pose, the gain per channel and what they changed."""

    cam_from_world: Tensor  # [4, 4], detached
    gain: Tensor  # [3], detached
    rotation_deg: float
    translation_m: float
    loss_before: float | None
    """mean L1 over the mask at the given pose (None: nothing was fitted)"""
    loss_after: float | None

    def summary(self) -> dict[str, float | list[float] | None]:
        """What the fit changed, as plain numbers for logs and JSON."""
        return {
            "align_rotation_deg": self.rotation_deg,
            "align_translation_m": self.translation_m,
            "align_gain": [float(g) for g in self.gain],
            "align_l1_before": self.loss_before,
            "align_l1_after": self.loss_after,
        }


def align_view(
    render: Callable[[Tensor], Tensor],
    cam_from_world: Tensor,
    image: Tensor,
    mask: Tensor,
    params: AlignParams,
    frozen: Iterable[Tensor] = (),
) -> Alignment:
    """Fit a pose and exposure correction to one view with the model frozen: ``params.steps`` Adam steps on
    the mean L1 error over ``mask`` between ``image`` [H, W, 3] and ``render(cam_from_world)`` [H, W, 3].
    ``frozen`` (the model's tensors) get no gradient meanwhile. The correction with the lowest loss seen is
    returned, so the fitted view never explains its photo worse than the given pose does; a view with an
    empty mask, or no steps, keeps its pose and a gain of 1."""
    cam_from_world = cam_from_world.detach()  # a start: the fit never reaches into how it was computed
    dev = cam_from_world.device
    corr = ViewCorrections(1, dev, pose=True, exposure=params.exposure)
    best = (math.inf, {k: v.detach().clone() for k, v in corr.state_dict().items()})
    first = None
    if params.steps > 0 and bool(mask.any()):
        opt = corr.optimizer(params.lr_rotation, params.lr_translation, params.lr_exposure)
        frozen = [t for t in frozen if t.requires_grad]
        for t in frozen:
            t.requires_grad_(False)
        try:
            with torch.enable_grad():
                for k in range(params.steps + 1):
                    rgb = corr.expose(0, render(corr.cam_from_world(0, cam_from_world)))
                    loss = (rgb - image).abs().mean(-1)[mask].mean()
                    value = float(loss.detach())
                    if k == 0:
                        first = value
                    if not math.isfinite(value):
                        break
                    if value < best[0]:
                        best = (value, {n: v.detach().clone() for n, v in corr.state_dict().items()})
                    if k == params.steps:
                        break
                    loss.backward()
                    opt.step()
                    opt.zero_grad(set_to_none=True)
        finally:
            for t in frozen:
                t.requires_grad_(True)
    corr.load_state_dict(best[1])
    with torch.no_grad():
        return Alignment(
            corr.cam_from_world(0, cam_from_world).detach(),
            corr.expose(0, torch.ones(3, device=dev)).detach(),
            math.degrees(float(corr.rotation[0].norm())),
            float(corr.translation[0].norm()),
            first,
            best[0] if math.isfinite(best[0]) else first,
        )
