"""``python -m stages NAME [--building B] [--data-root DIR]``: run one stage.

The thread policy (``facade_pipeline.threads``) is put in place before the stage's module imports torch,
OpenCV or open3d, whose thread pools read it when they load; so this is how doit starts a stage, and
``python -m stages.NAME`` comes back here.
"""

from __future__ import annotations

import sys

from facade_pipeline.threads import apply_thread_policy

apply_thread_policy()

from stages import PIPELINE, load_stage  # noqa: E402  (after the thread policy, on purpose)
from stages._runner import main  # noqa: E402


def cli(argv: list[str]) -> int:
    if not argv or argv[0] not in PIPELINE:
        names = ", ".join(PIPELINE)
        usage = "usage: python -m stages NAME [--building B] [--data-root DIR]"
        print(f"{usage}; NAME: {names}", file=sys.stderr)
        return 2
    return main(load_stage(argv[0]), argv[1:])


if __name__ == "__main__":
    raise SystemExit(cli(sys.argv[1:]))
