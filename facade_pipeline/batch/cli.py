"""``facade-batch``: run many buildings' DAGs on a Dask cluster, and say where each one stands.

    facade-batch run synthetic64 synthetic64_curved          # a LocalCluster on this machine
    facade-batch run shatin hkust_library --scheduler tcp://head:8786 --data-root /mnt/uav
    facade-batch run shatin hkust_library --scheduler slurm --workers 8
    facade-batch run demo --until rectify                   # each building's DAG up to one stage
    facade-batch status [BUILDING...] [--data-root DIR]

Exit code 0 when every building is done, 1 when one failed (the others went on), 2 when the batch could
not start (a bad building name or config, a worker that cannot see the data root).
"""

from __future__ import annotations

import argparse
import sys
import time
import uuid

from facade_pipeline.config import chosen_budget, config_dir, load_building_config
from facade_pipeline.errors import PipelineError
from facade_pipeline.layout import BuildingLayout, resolve_data_root
from stages import PIPELINE

from . import record

#: stages that render or train on the GPU when the building's [run] device wants one
GPU_STAGES = ("train_gs", "evaluate")


def building_stages(building: str, until: str | None) -> list[str]:
    """The building's stages in pipeline order (``synthesize`` for synthetic buildings only), up to
    ``until``."""
    synthetic = load_building_config(building).building.kind == "synthetic"
    stages = [s for s in PIPELINE if synthetic or s != "synthesize"]
    if until is not None:
        if until not in stages:
            raise PipelineError(None, f"--until one of {', '.join(stages)} (building {building})",
                                f"'{until}'")
        stages = stages[: stages.index(until) + 1]
    return stages


def wants_gpu(building: str, stage: str, gpu_workers: int) -> bool:
    """train_gs and evaluate ask for a GPU when ``[run] device`` is "cuda", or "auto" and a worker has one."""
    device = load_building_config(building).run.device
    return stage in GPU_STAGES and (device == "cuda" or (device == "auto" and gpu_workers > 0))


def run(args: argparse.Namespace) -> int:
    from distributed import as_completed

    from .cluster import STAGE, BatchError, connect
    from .task import check_data_root, run_stage

    data_root = resolve_data_root(args.data_root)
    try:
        plans = {b: building_stages(b, args.until) for b in dict.fromkeys(args.buildings)}
        for b in plans:
            BuildingLayout(data_root, b)  # the name's rules
    except (PipelineError, ValueError) as e:
        print(f"facade-batch: {e}", file=sys.stderr)
        return 2
    if args.scheduler == "local":  # on one machine a missing data root is made, as doit makes it
        try:
            data_root.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            print(f"facade-batch: {data_root}: expected a data root that can be made, found {e.strerror}",
                  file=sys.stderr)
            return 2
    print(f"facade-batch: starting the cluster ({args.scheduler})", file=sys.stderr, flush=True)
    try:
        cluster = connect(args.scheduler, args.workers)
    except BatchError as e:
        print(f"facade-batch: {e}", file=sys.stderr)
        return 2
    try:
        client = cluster.client
        try:
            client.wait_for_workers(1, timeout=args.wait_workers)
        except TimeoutError:
            wait = f"{args.wait_workers:g} s"
            print(f"facade-batch: --scheduler {args.scheduler}: expected a worker within {wait}, found none: "
                  "start workers (or wait longer: --wait-workers)", file=sys.stderr)
            return 2
        unseen = [line for line in client.run(check_data_root, str(data_root)).values() if line]
        if unseen:
            for line in unseen:
                print(f"facade-batch: {line}", file=sys.stderr)
            return 2
        gpus = cluster.workers_with("GPU")
        slots = cluster.workers_with(STAGE) > 0
        address = client.scheduler.address if slots else None
        for b, stages in plans.items():
            for s in stages:
                if wants_gpu(b, s, gpus) and gpus == 0:
                    print(f"facade-batch: {config_dir() / 'buildings' / (b + '.toml')}: [run] device = "
                          f"\"cuda\" needs a worker with a GPU, found none: run on GPU workers or set "
                          f"device = \"auto\"", file=sys.stderr)
                    return 2
        token = uuid.uuid4().hex[:8]
        futures, total = [], sum(len(s) for s in plans.values())
        for b, stages in plans.items():
            previous = None
            for i, s in enumerate(stages):
                resources = ({STAGE: 1} if slots else {}) | ({"GPU": 1} if wants_gpu(b, s, gpus) else {})
                previous = client.submit(
                    run_stage, b, s, str(data_root), str(config_dir()), cluster.threads,
                    stages if i == 0 else None, address, previous,
                    budget=chosen_budget(), key=f"{b}/{s}-{token}", pure=False, resources=resources or None,
                )
                futures.append(previous)
        n_workers = len(client.scheduler_info()["workers"])
        print(f"facade-batch: {len(plans)} buildings, {total} stages on {n_workers} workers", file=sys.stderr,
              flush=True)
        t0, finished, failed = time.perf_counter(), 0, {}
        for future in as_completed(futures):
            finished += 1
            b, s = future.key.rsplit("-", 1)[0].split("/")
            if future.status == "finished":
                r = future.result()
                what = f"ran in {r['seconds']:.1f} s" if r["ran"] else "up to date"
                print(f"[{finished}/{total}] {b} {s}: {what} ({r['worker']})", flush=True)
            elif b not in failed:
                failed[b] = _one_line(future.exception(), s)
                print(f"[{finished}/{total}] {b} {s}: failed: {failed[b]}", flush=True)
        wall = time.perf_counter() - t0
        print(f"facade-batch: {len(plans) - len(failed)} of {len(plans)} buildings done in {wall:.1f} s",
              flush=True)
        for b, line in failed.items():
            print(f"facade-batch: {b} failed: {line}", file=sys.stderr)
        return 1 if failed else 0
    finally:
        cluster.close()


def _one_line(exc: BaseException | None, stage: str) -> str:
    from distributed import KilledWorker

    if isinstance(exc, KilledWorker):
        return f"{stage}: its worker died twice running it (killed, or out of memory): rerun the batch"
    text = str(exc).strip().splitlines()
    return text[-1] if text else type(exc).__name__


def status(args: argparse.Namespace) -> int:
    data_root = resolve_data_root(args.data_root)
    buildings = args.buildings or record.recorded_buildings(data_root)
    if not buildings:
        print(f"facade-batch: no batch ran under {data_root}")
        return 0
    for b in buildings:
        found = record.building_status(BuildingLayout(data_root, b))
        print(found.line() if found else f"{b}: no batch ran on it")
        if found and args.verbose:
            for s in found.done:
                print(f"    done     {s}")
            for s in found.running:
                print(f"    running  {s}")
            for s, line in found.failed:
                print(f"    failed   {s}: {line}")
            for s in found.waiting:
                print(f"    waiting  {s}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="facade-batch", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("run", help="run the buildings' DAGs on a Dask cluster")
    p.add_argument("buildings", nargs="+", metavar="BUILDING")
    p.add_argument("--scheduler", default="local",
                   help="local (a LocalCluster here, the default), slurm ([batch.slurm]), or a scheduler's "
                        "address (tcp://host:8786)")
    p.add_argument("--workers", type=int, default=None,
                   help="worker processes (local: default min(cores, 4)) or Slurm jobs (default: jobs)")
    p.add_argument("--data-root", default=None, help="data root (default: $FACADE_DATA_ROOT or ./data)")
    p.add_argument("--until", default=None, metavar="STAGE", help="run each DAG up to this stage")
    p.add_argument("--wait-workers", type=float, default=600.0,
                   help="seconds to wait for a first worker (a Slurm queue) (default 600)")
    p.set_defaults(func=run)
    p = sub.add_parser("status", help="where each building's last batch stands")
    p.add_argument("buildings", nargs="*", metavar="BUILDING")
    p.add_argument("--data-root", default=None, help="data root (default: $FACADE_DATA_ROOT or ./data)")
    p.add_argument("-v", "--verbose", action="store_true", help="one line per stage as well")
    p.set_defaults(func=status)
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    raise SystemExit(main())
