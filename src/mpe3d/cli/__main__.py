"""``python -m mpe3d.cli``: the ``mpe3d`` command."""

import sys

from mpe3d.cli.main import console

sys.exit(console())
