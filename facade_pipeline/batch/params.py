"""The ``[batch.slurm]`` table of configs/default.toml: the Slurm jobs that ``facade-batch run --scheduler
slurm`` starts as Dask workers."""

from __future__ import annotations

from dataclasses import dataclass

from facade_pipeline.config import Count, PosInt


@dataclass(frozen=True)
class SlurmSettings:
    queue: str
    """partition of the workers' jobs ("": the cluster's default)"""
    cores: PosInt
    """cores per worker job"""
    memory: str
    """memory per worker job, as Slurm reads it ("32GB")"""
    gpus: Count
    """GPUs per worker job (0: CPU workers)"""
    walltime: str
    """wall-clock limit of each worker job (HH:MM:SS)"""
    jobs: PosInt
    """worker jobs started"""


@dataclass(frozen=True)
class BatchSettings:
    slurm: SlurmSettings
