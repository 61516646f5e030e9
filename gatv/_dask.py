"""Dask helpers of :mod:`gatv.batch` (imported only when a batch runs on Dask): the worker
plugin that sets ``sys.path``, and :func:`process_cluster`, a scheduler and workers as
separate processes."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator, Sequence

from distributed.diagnostics.plugin import WorkerPlugin

__all__ = ["SysPath", "process_cluster"]


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


@contextlib.contextmanager
def process_cluster(workers: int = 2, *, threads: int = 1, host: str = "127.0.0.1", timeout: float = 120.0,
                    env: dict | None = None) -> Iterator[str]:
    """A Dask scheduler and ``workers`` workers as separate processes, as on a real cluster.

    Runs ``python -m dask scheduler --host HOST --port 0`` and ``workers``
    times ``python -m dask worker ADDRESS --nthreads THREADS`` (each its own
    process, listening on ``host`` only), waits until every worker has
    joined, and yields the scheduler's address (``tcp://127.0.0.1:PORT``).
    The processes are stopped on exit (terminated, then killed).  What
    ``gatv batch --scheduler ADDRESS`` meets on a cluster of machines, here
    on one (the tests and ``benchmarks/batch.py`` use it).
    """
    import json
    import os
    import subprocess
    import sys
    import tempfile
    import time

    from distributed import Client

    procs = []
    run_env = dict(os.environ, **(env or {}))
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    with tempfile.TemporaryDirectory(prefix="gatv-cluster-") as tmp:
        info = os.path.join(tmp, "scheduler.json")
        try:
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "dask", "scheduler", "--host", host, "--port", "0", "--no-dashboard",
                 "--scheduler-file", info], env=run_env, **quiet))
            deadline = time.monotonic() + timeout
            while not os.path.exists(info) or not os.path.getsize(info):
                if procs[0].poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError("the Dask scheduler did not start")
                time.sleep(0.1)
            time.sleep(0.1)  # the file is written in one go, but give it a moment
            with open(info, encoding="utf-8") as fh:
                address = json.load(fh)["address"]
            for _ in range(workers):
                procs.append(subprocess.Popen(
                    [sys.executable, "-m", "dask", "worker", address, "--host", host, "--nthreads", str(threads),
                     "--no-dashboard", "--nworkers", "1"], env=run_env, **quiet))
            with Client(address, timeout=f"{timeout}s") as client:
                client.wait_for_workers(workers, timeout=timeout)
            yield address
        finally:
            if len(procs) > 1:
                with contextlib.suppress(Exception):  # workers and scheduler close themselves at once
                    with Client(address, timeout="5s") as client:
                        client.shutdown()
            for proc in reversed(procs):
                if proc.poll() is None:
                    proc.terminate()
            for proc in reversed(procs):
                try:
                    proc.wait(timeout=3)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
