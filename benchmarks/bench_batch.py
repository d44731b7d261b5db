"""N buildings one after the other with doit, then together with ``facade-batch run`` on a LocalCluster of
this machine: wall time of each, and whether every stage's outputs came out the same.

    python benchmarks/bench_batch.py [--buildings 2] [--workers 2] [--until STAGE] [--no-record]

The buildings are copies of synthetic64 under other names (another seed each, so no two are the same
scene), made in a temporary config folder; each timed run starts from an empty data root.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import machine, record_results

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from facade_pipeline.config import config_dir  # noqa: E402
from facade_pipeline.errors import PipelineError  # noqa: E402
from facade_pipeline.layout import BuildingLayout  # noqa: E402
from facade_pipeline.manifest import read_manifest  # noqa: E402
from stages import PIPELINE  # noqa: E402


def _configs(tmp: Path, n: int) -> tuple[Path, list[str]]:
    cfg = tmp / "configs"
    shutil.copytree(config_dir(), cfg)
    text = (cfg / "buildings" / "synthetic64.toml").read_text()
    names = [f"bench{i}" for i in range(n)]
    for i, name in enumerate(names):
        (cfg / "buildings" / f"{name}.toml").write_text(re.sub(r"(?m)^seed = \d+", f"seed = {100 + i}", text))
    return cfg, names


def _outputs(root: Path, names: list[str]) -> dict[tuple[str, str], dict[str, str]]:
    """(building, stage) -> the output hashes its manifest lists, for every stage that completed."""
    out = {}
    for b in names:
        for stage in PIPELINE:
            try:
                out[(b, stage)] = read_manifest(BuildingLayout(root, b), stage).outputs
            except PipelineError:
                continue
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--buildings", type=int, default=2)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--until", default=None, help="each DAG up to this stage (default: the whole DAG)")
    ap.add_argument("--no-record", action="store_true")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench-batch-"))
    try:
        cfg, names = _configs(tmp, args.buildings)
        env = {**os.environ, "FACADE_CONFIG_DIR": str(cfg), "TQDM_DISABLE": "1", "PYTHONPATH": str(ROOT)}
        target = [args.until] if args.until else []
        t0 = time.perf_counter()
        for b in names:
            print(f"serial: {b}", file=sys.stderr, flush=True)
            doit = [sys.executable, "-m", "doit", "-f", str(ROOT / "dodo.py"), *target, f"building={b}"]
            subprocess.run(doit + [f"data_root={tmp / 'serial'}"], cwd=ROOT, env=env, check=True,
                           stdout=subprocess.DEVNULL)
        serial = time.perf_counter() - t0
        print(f"serial: {serial:.1f} s; batch:", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "facade_pipeline.batch", "run", *names, "--workers",
                        str(args.workers), "--data-root", str(tmp / "batch")]
                       + (["--until", args.until] if args.until else []), cwd=ROOT, env=env, check=True)
        batch = time.perf_counter() - t0
        a, b = _outputs(tmp / "serial", names), _outputs(tmp / "batch", names)
        same = sum(a[k] == b.get(k) for k in a)
        differ = sorted(f"{k[0]} {k[1]}" for k in a if a[k] != b.get(k))
        same_text = f"{same} of {len(a)}" + (f" (differ: {', '.join(differ)})" if differ else "")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    command = f"python benchmarks/bench_batch.py --buildings {args.buildings} --workers {args.workers}" + (
        f" --until {args.until}" if args.until else "")
    what = f"up to {args.until}" if args.until else "the whole DAG"
    text = f"""## Many buildings

{args.buildings} copies of synthetic64 (other seeds), {what}: one `doit` after the other, then all at once
with `facade-batch run` on a LocalCluster of {args.workers} workers (the LocalCluster's start included).
Outputs compared stage by stage through the manifests' hashes.

{machine()}
`{command}`

| buildings | serial `doit` wall s | `facade-batch` wall s | serial / batch | stages with the same outputs |
| --- | --- | --- | --- | --- |
| {args.buildings} | {serial:.1f} | {batch:.1f} | {serial / batch:.2f} | {same_text} |
"""
    print(text)
    if not args.no_record:
        record_results(text)


if __name__ == "__main__":
    main()
