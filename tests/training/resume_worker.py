"""A training process for the kill -9 test: trains synthetic64 (gt-built data) with frequent checkpoints,
resuming from the checkpoint when one exists, and saves the final state.

    python -m tests.training.resume_worker DATA_ROOT CHECKPOINT OUT ITERATIONS
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from facade_pipeline.layout import BuildingLayout
from facade_pipeline.training.render import splatting_rasterizer
from facade_pipeline.training.trainer import build_trainer, load_checkpoint, train
from tests.training.conftest import gt_train_data, small_params


def main(data_root: str, checkpoint: str, out: str, iterations: str) -> None:
    torch.set_num_threads(1)
    data = gt_train_data(BuildingLayout(Path(data_root), "synthetic64"))
    p = small_params(iterations=int(iterations))
    raster = splatting_rasterizer("auto")
    tr = load_checkpoint(checkpoint, p, data, raster, "cpu", "worker")
    print(f"resumed from {0 if tr is None else tr.state.iteration}", flush=True)
    tr = tr or build_trainer(p, data, raster)
    train(tr, Path(checkpoint), "worker", log_every=5, checkpoint_every=2)
    torch.save(
        {
            "model": tr.state.model.state(),
            "reflection": tr.state.reflection.state_dict(),
            "log": tr.state.log,
            "opt": tr.state.opt.state_dict(),
        },
        out,
    )


if __name__ == "__main__":
    main(*sys.argv[1:])
