"""The Dask cluster a batch runs on: a ``LocalCluster`` on this machine (the default), a running scheduler
at an address, or Slurm jobs through ``dask-jobqueue`` (``[batch.slurm]`` of configs/default.toml).

Every worker runs one stage at a time (the Dask resource ``stage``; the stage's thread pools use the
worker's cores), and the views that stages fan out (``fanout``) on a second thread; a worker with GPUs
declares the resource ``GPU``, which train_gs and evaluate ask for when the building's ``[run] device``
wants CUDA. Workers that declare no ``stage`` (started by hand without it) run one task per thread, and
their stages keep their views to themselves. A task whose worker dies is retried once (the scheduler's
``allowed-failures``), then fails its building."""

from __future__ import annotations

import shutil
import subprocess
from contextlib import ExitStack
from dataclasses import dataclass

from facade_pipeline.threads import usable_cores

#: the Dask resource of a worker's one stage at a time; a worker has one thread more than stages, on which
#: the views that the stages fan out run. (A stage task that left its thread while it waits, ``secede``,
#: looked idle to the scheduler, which then queued every stage on one worker behind the resource.)
STAGE = "stage"
#: Dask threads of a worker: its one stage, and the views fanned out to it
WORKER_THREADS = 2
#: a task is retried once after its worker died (then ``KilledWorker``); set before a scheduler starts
ALLOWED_FAILURES = 1
#: how long to try reaching a scheduler (s)
CONNECT_TIMEOUT_S = 30


@dataclass
class Cluster:
    client: object
    """the ``distributed.Client``"""
    threads: int | None
    """threads per stage where this process knows the workers' cores (a LocalCluster), else None"""
    stack: ExitStack

    def workers_with(self, resource: str) -> int:
        """Workers that declare at least one of ``resource``."""
        info = self.client.scheduler_info(n_workers=-1)["workers"]
        return sum(1 for w in info.values() if w.get("resources", {}).get(resource, 0) >= 1)

    def close(self) -> None:
        self.stack.close()


def local_gpus() -> int:
    """CUDA devices on this machine (``nvidia-smi -L``: no torch import for a count)."""
    smi = shutil.which("nvidia-smi")
    if smi is None:
        return 0
    try:
        out = subprocess.run([smi, "-L"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return 0
    return sum(line.startswith("GPU ") for line in out.splitlines())


def connect(scheduler: str, workers: int | None) -> Cluster:
    """``scheduler``: "local", "slurm" or a scheduler's address (``tcp://host:8786``)."""
    import dask
    from distributed import Client, LocalCluster

    dask.config.set({"distributed.scheduler.allowed-failures": ALLOWED_FAILURES})
    stack = ExitStack()
    threads = None
    if scheduler == "local":
        n = workers or max(1, min(usable_cores(), 4))
        gpus = local_gpus()
        cluster = stack.enter_context(
            LocalCluster(
                n_workers=n,
                threads_per_worker=WORKER_THREADS,
                processes=True,
                resources={STAGE: 1, **({"GPU": 1} if gpus else {})},
                dashboard_address=None,
            )
        )
        threads = max(1, usable_cores() // n)
    elif scheduler == "slurm":
        if shutil.which("sbatch") is None:
            raise BatchError("--scheduler slurm: expected Slurm's sbatch on this machine's PATH, found none: "
                             "run facade-batch on a Slurm login node")
        cluster = stack.enter_context(slurm_cluster())
        cluster.scale(jobs=workers or cluster.jobs)
        threads = cluster.job_cpu
    else:
        cluster = scheduler
    try:
        client = stack.enter_context(Client(cluster, timeout=CONNECT_TIMEOUT_S))
    except (OSError, TimeoutError) as e:
        stack.close()
        found = f"none ({e})"
        raise BatchError(f"--scheduler {scheduler}: expected a Dask scheduler there, found {found}") from None
    return Cluster(client, threads, stack)


class BatchError(Exception):
    """A batch cannot start: one line says why and what to do."""


def slurm_cluster():
    """A ``dask_jobqueue.SLURMCluster`` of ``[batch.slurm]``'s jobs (none started yet: ``scale``), one
    worker process per job."""
    from dask_jobqueue import SLURMCluster

    from facade_pipeline.batch.params import BatchSettings
    from facade_pipeline.config import default_params

    s = default_params("batch", BatchSettings).slurm
    cluster = SLURMCluster(
        queue=s.queue or None,
        cores=WORKER_THREADS,  # Dask threads: one stage at a time (which uses every core), views beside it
        job_cpu=s.cores,
        processes=1,
        memory=s.memory,
        walltime=s.walltime,
        job_extra_directives=[f"--gres=gpu:{s.gpus}"] if s.gpus else [],
        worker_extra_args=["--resources", f"{STAGE}=1" + (f",GPU={s.gpus}" if s.gpus else "")],
    )
    cluster.job_cpu, cluster.jobs = s.cores, s.jobs
    return cluster
