"""``python -m pipeline.cli``: the ``cscsr`` command line (workers on a cluster start so)."""

import sys

from pipeline.cli import main

sys.exit(main())
