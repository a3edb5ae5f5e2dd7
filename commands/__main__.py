"""``python -m commands``: the ``cacc-bench`` command."""

import sys

from commands.cli import main

sys.exit(main())
