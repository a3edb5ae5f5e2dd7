"""``python -m benchmark``: the ``cacc-bench`` command."""

import sys

from benchmark.cli import main

sys.exit(main())
