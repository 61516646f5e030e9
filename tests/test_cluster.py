"""A real Dask cluster (issue 42): a scheduler and two workers as separate processes on
127.0.0.1, a batch through `gatv batch --scheduler tcp://...` as a user on a cluster runs
it, equal to the serial results; numba pinned to the worker's share of its host's cores."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from gatv import batch
from gatv.datasets import table2_trial
from gatv.io import write_points

distributed = pytest.importorskip("distributed")

pytestmark = pytest.mark.slow


def _strip(record: dict) -> dict:
    out = {k: v for k, v in record.items() if k != "time_s"}
    out["info"] = {k: v for k, v in (record.get("info") or {}).items() if k != "time_s"}
    return out


@pytest.fixture(scope="module")
def cluster():
    from gatv._dask import process_cluster

    with process_cluster(2, threads=1) as address:
        yield address


@pytest.fixture(scope="module")
def table(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pairs")
    lines = ["source,target,seed"]
    for k in range(12):
        trial = table2_trial(0.75, seed=300 + k)
        write_points(folder / f"s{k}.npy", trial.source)
        write_points(folder / f"t{k}.npy", trial.target)
        lines.append(f"s{k}.npy,t{k}.npy,{k}")
    path = folder / "pairs.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_two_process_cluster_batch_equals_serial(tmp_path, cluster, table):
    assert cluster.startswith("tcp://127.0.0.1:")
    done = subprocess.run([sys.executable, "-m", "gatv", "batch", str(table), "--out", str(tmp_path / "cluster"),
                           "--scheduler", cluster], capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr
    assert f"the Dask scheduler at {cluster} of 2 workers, 2 threads" in done.stdout
    serial = batch.run(table, tmp_path / "serial", scheduler="serial")
    assert serial.counts()["found"] == 12
    for row in serial.rows:
        there = json.loads((tmp_path / "cluster" / row.path.name).read_text())
        assert _strip(there) == _strip(json.loads(row.path.read_text()))
    assert (tmp_path / "cluster" / "summary.csv").read_text().count("\n") == 13


def test_workers_run_numba_on_their_share_of_the_cores(cluster):
    with distributed.Client(cluster) as client:
        plan = batch.numba_plan(client)
        cores = client.run(batch._cores)
        assert sorted(plan) == sorted(client.nthreads())
        assert set(plan.values()) == {max(1, min(cores.values()) // 2)}  # two 1-thread workers on one host
        pinned = client.gather(client.map(batch._pin_numba, [plan] * 4, pure=False))
        assert set(pinned) == {max(1, min(cores.values()) // 2)}
