"""``python -m facade_pipeline.batch``: the ``facade-batch`` command."""

from facade_pipeline.batch.cli import main

raise SystemExit(main())
