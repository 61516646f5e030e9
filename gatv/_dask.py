"""Dask worker plugins of :mod:`gatv.batch` (imported only when a batch runs on Dask)."""

from __future__ import annotations

import sys
from collections.abc import Sequence

from distributed.diagnostics.plugin import WorkerPlugin

__all__ = ["SysPath"]


class SysPath(WorkerPlugin):
    """Put folders at the front of every worker's ``sys.path``, workers started later included.

    Scripts run as ``python benchmarks/x.py`` import helpers from their own
    folder; their workers need that folder to unpickle the tasks.
    """

    name = "gatv-sys-path"
    idempotent = False

    def __init__(self, folders: Sequence[str]):
        self.folders = list(folders)

    def setup(self, worker=None):
        for folder in reversed(self.folders):
            if folder not in sys.path:
                sys.path.insert(0, folder)
