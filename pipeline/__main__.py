"""``python -m pipeline``: the ``pipeline`` command (how the studio starts a run)."""

import sys

from pipeline.cli import main

sys.exit(main())
