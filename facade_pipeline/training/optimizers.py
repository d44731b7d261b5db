"""The optimisers of training: Adam over the splat attributes (``gaussian_optimizer``) and over the
reflection module (``reflection_optimizer``), and ``set_learning_rates``, which moves their rates along
the schedules of ``training.schedule`` at every step. Here apart from the loop because the rates are
constants and parameters of their own, which the loop only applies."""

from __future__ import annotations

import torch
from torch import nn

from facade_pipeline.training.model import PARAM_NAMES, GaussianModel
from facade_pipeline.training.params import TrainParams
from facade_pipeline.training.schedule import position_lr, reflection_lr

# Adam rates of the splat attributes that 2DGS shares with 3DGS (their training defaults; DESIGN.md). They
# are per-attribute rates on activation-space parameters, not tied to a scene's size, and were never tuned
# here: the splat geometry and colour train as the reference does. The position rate decays from
# ``lr.position_init`` to ``schedule.POSITION_LR_FINAL``, times the scene extent, as in 3DGS.
SH_DC_LR = 2.5e-3
SH_REST_LR = SH_DC_LR / 20.0  # 3DGS: the higher SH bands at a twentieth of the DC rate
OPACITY_LR = 0.05
SCALING_LR = 5e-3
ROTATION_LR = 1e-3
#: Adam rate of the splats' Fresnel F0 logits: this pipeline's, at the reflectivity's default, never tuned
LR_F0 = 0.01


def adam(groups: list[dict], **options) -> torch.optim.Adam:
    """torch's Adam over ``groups``; on a GPU its fused kernel (one launch per group and step instead of a
    dozen: a step there is launch-bound), elsewhere its default. The same update to float rounding."""
    on_gpu = all(prm.is_cuda for g in groups for prm in g["params"])
    return torch.optim.Adam(groups, fused=True if on_gpu else None, **options)


def gaussian_optimizer(model: GaussianModel, p: TrainParams, extent: float) -> torch.optim.Adam:
    """Adam over the splat attributes, one named group per attribute (densification edits them by name);
    the position rate at its start, times the scene extent ``extent`` (m)."""
    lr = p.lr
    rates = {
        "means": lr.position_init * extent,
        "quats": ROTATION_LR,
        "log_scales": SCALING_LR,
        "opacity_logits": OPACITY_LR,
        "sh_dc": SH_DC_LR,
        "sh_rest": SH_REST_LR,
        "refl_logits": lr.reflectivity,
        "f0_logits": LR_F0,
    }
    groups = [{"params": [getattr(model, n)], "lr": rates[n], "name": n} for n in PARAM_NAMES]
    return adam(groups, lr=0.0, eps=1e-15)


def reflection_optimizer(p: TrainParams, module: nn.Module) -> torch.optim.Adam:
    """Adam over the reflection module, one group per rate: the proxy feature maps (``proxy``) apart from
    the network's weights (``reflection``)."""
    proxy = [prm for name, prm in module.named_parameters() if name.startswith("proxy.")]
    rest = [prm for name, prm in module.named_parameters() if not name.startswith("proxy.")]
    groups = [{"params": rest, "name": "reflection"}]
    if proxy:
        groups.append({"params": proxy, "name": "proxy"})
    for g in groups:
        g["lr"] = reflection_lr(p, 0, g["name"])
    return adam(groups)


def set_learning_rates(
    opt: torch.optim.Adam, opt_refl: torch.optim.Adam | None, p: TrainParams, extent: float, it: int
) -> None:
    """The decaying rates (splat positions, the reflection module) at iteration ``it``."""
    for g in opt.param_groups:
        if g["name"] == "means":
            g["lr"] = position_lr(p, extent, it)
    if opt_refl is not None:
        for g in opt_refl.param_groups:
            g["lr"] = reflection_lr(p, it, g["name"])
