"""``python -m t42_transfer.cli``: the ``t42`` command (how tests and ``t42 up`` start node processes)."""

import sys

from t42_transfer.cli import main

sys.exit(main())
