"""``python -m gatv``: the ``gatv`` command line (see :mod:`gatv.cli`)."""

from __future__ import annotations

import sys

from gatv.cli import main

if __name__ == "__main__":
    sys.exit(main())
