"""Frame rate of the web viewer's renders (``facade_pipeline/view.py``) on a trained building, on the CPU:
every frame as the viewer makes it (the facade mask cast from the corrected mesh, then the model rendered
with its reflection model), along the fly-through orbit, at two sizes.

    python benchmarks/bench_viewer.py [--building demo] [--frames 12] [--no-record]

The building must have run through train_gs (``make run`` for demo).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
from _common import machine, record_results

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from facade_pipeline.evaluation.video import orbit_path  # noqa: E402
from facade_pipeline.view import load_scene, render_image  # noqa: E402

WIDTHS = (256, 512)  # demo's views are 4:3: 256 x 192 and 512 x 384


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--building", default="demo")
    ap.add_argument("--data-root", default=None)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--no-record", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(2)
    scene = load_scene(args.building, args.data_root, None, "cpu")
    cams = [vc.camera for vc in scene.cameras]
    rows = []
    for w in WIDTHS:
        path = orbit_path(cams, args.frames, scale=w / cams[0].width)
        render_image(scene, path[0], "final")  # warm-up: kernel build, caches
        t0 = time.perf_counter()
        for cam in path:
            render_image(scene, cam, "final")
        dt = (time.perf_counter() - t0) / len(path)
        rows.append(f"| {path[0].width} x {path[0].height} | {len(path)} | {1000 * dt:.0f} | {1 / dt:.2f} |")
        print(rows[-1], flush=True)
    text = (
        f"\n## Viewer frame rate on {args.building} (CPU)\n\n{machine()} Command: "
        f"`python benchmarks/bench_viewer.py --building {args.building}`. Mode \"final\" (reflection model "
        "and facade mask cast per frame), frames along the fly-through orbit.\n\n"
        "| size | frames | ms per frame | frames per second |\n| --- | --- | --- | --- |\n"
        + "\n".join(rows)
        + "\n"
    )
    print(text)
    if not args.no_record:
        record_results(text)


if __name__ == "__main__":
    main()
