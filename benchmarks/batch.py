"""gatv batch: Table-2 pairs serially vs as Dask tasks on local workers, in one run.

Writes ``--pairs`` Table-2 trials (50 inliers, outlier fraction ``--fraction``,
seeds from ``--seed``) as ``.npy`` files and a ``pairs.csv``, then runs
``gatv.batch.run`` on them twice: ``scheduler="serial"`` (this process, numba
on every core) and on a ``LocalCluster`` of ``--workers`` single-threaded
processes (what ``gatv batch --workers N`` runs), and serially once more with numba
on one thread (what each worker gets).  Both sides are warmed up
first (numba kernels loaded from the cache: one pair here, one per worker),
and the cluster's start-up is reported apart.

Prints the wall times, their ratio (the issue's target: >= 1.7x with two
workers on a 2-core machine), the peak resident memory of this process and
of each worker (``ru_maxrss``), and whether every row's record equals the
serial one apart from times; writes ``batch.csv`` to ``--out``.

Usage::

    python benchmarks/batch.py [--pairs 100] [--fraction 0.75] [--workers 2] [--seed 0]
                               [--out benchmarks/results]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import DEFAULT_OUT, markdown_table, trial_seed, write_csv

from gatv import batch
from gatv.datasets import table2_trial
from gatv.io import write_points


def peak_rss_mib() -> float:
    """Peak resident memory of the calling process, MiB (Linux: ru_maxrss is KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def cpu_seconds() -> float:
    """User + system CPU seconds of the calling process so far (all its threads)."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def warm_up(source: str, target: str) -> float:
    """Register one pair (loads the numba kernels); seconds taken."""
    from gatv.io import read_points
    from gatv.registration import register

    start = time.perf_counter()
    register(read_points(source), read_points(target), seed=0)
    return time.perf_counter() - start


def make_pairs(folder: Path, n: int, fraction: float, seed: int) -> Path:
    lines = ["source,target,seed"]
    for k in range(n):
        trial = table2_trial(fraction, seed=trial_seed(seed, fraction, k))
        write_points(folder / f"s{k:04d}.npy", trial.source)
        write_points(folder / f"t{k:04d}.npy", trial.target)
        lines.append(f"s{k:04d}.npy,t{k:04d}.npy,{k}")
    table = folder / "pairs.csv"
    table.write_text("\n".join(lines) + "\n")
    return table


def _strip_times(record: dict) -> dict:
    out = {k: v for k, v in record.items() if k != "time_s"}
    out["info"] = {k: v for k, v in (record.get("info") or {}).items() if k != "time_s"}
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=100, help="Table-2 pairs (default: 100)")
    parser.add_argument("--fraction", type=float, default=0.75, help="outlier fraction (default: 0.75)")
    parser.add_argument("--workers", type=int, default=2, help="local Dask workers (default: 2)")
    parser.add_argument("--seed", type=int, default=0, help="base seed of the trials (default: 0)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"CSV folder (default: {DEFAULT_OUT})")
    args = parser.parse_args(argv)
    if args.pairs < 1 or args.workers < 1:
        parser.error("--pairs and --workers must be >= 1")

    with tempfile.TemporaryDirectory(prefix="gatv-batch-bench-") as tmp:
        folder = Path(tmp)
        table = make_pairs(folder, args.pairs, args.fraction, args.seed)
        first = (str(folder / "s0000.npy"), str(folder / "t0000.npy"))

        warm_serial = warm_up(*first)
        load = [os.getloadavg()[0]]
        cpu0 = cpu_seconds()
        serial = batch.run(table, folder / "serial", scheduler="serial")
        cpu_serial = cpu_seconds() - cpu0
        rss_serial = peak_rss_mib()
        load.append(os.getloadavg()[0])

        import numba

        threads = numba.get_num_threads()
        numba.set_num_threads(1)  # the same pairs serially with what one worker gets: one thread
        cpu0 = cpu_seconds()
        single = batch.run(table, folder / "single", scheduler="serial")
        cpu_single = cpu_seconds() - cpu0
        numba.set_num_threads(threads)
        load.append(os.getloadavg()[0])

        t0 = time.perf_counter()
        with batch.connect("local", workers=args.workers) as client:
            started = time.perf_counter() - t0
            warm = client.run(warm_up, *first)
            cpu1 = sum(client.run(cpu_seconds).values())
            t1 = time.perf_counter()
            dask = batch.run(table, folder / "dask", scheduler=client)
            dask_batch = time.perf_counter() - t1
            cpu_dask = sum(client.run(cpu_seconds).values()) - cpu1
            load.append(os.getloadavg()[0])
            rss_workers = sorted(client.run(peak_rss_mib).values())
        same = sum(_strip_times(json.loads(a.path.read_text())) == _strip_times(json.loads(b.path.read_text()))
                   == _strip_times(json.loads(c.path.read_text()))
                   for a, b, c in zip(serial.rows, dask.rows, single.rows))

    ratio = serial.seconds / dask_batch
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    print(f"gatv batch: {args.pairs} Table-2 pairs, f = {args.fraction}, seed {args.seed}; "
          f"{cores} cores; serial in-process (numba on every core) vs {args.workers} local Dask workers "
          f"(1 thread each)\n")
    rows = [
        ["serial", f"{serial.seconds:.1f}", "1.00", f"{cpu_serial:.1f}", f"{cpu_serial / serial.seconds:.2f}",
         f"{load[0]:.1f} -> {load[1]:.1f}", f"{rss_serial:.0f}", f"{serial.counts()['found']}/{args.pairs}",
         f"warm-up {warm_serial:.1f} s"],
        ["serial, numba 1 thread", f"{single.seconds:.1f}", f"{serial.seconds / single.seconds:.2f}",
         f"{cpu_single:.1f}", f"{cpu_single / single.seconds:.2f}", f"{load[1]:.1f} -> {load[2]:.1f}", "",
         f"{single.counts()['found']}/{args.pairs}", ""],
        [f"Dask, {args.workers} workers", f"{dask_batch:.1f}", f"{ratio:.2f}", f"{cpu_dask:.1f}",
         f"{cpu_dask / dask_batch:.2f}", f"{load[2]:.1f} -> {load[3]:.1f}",
         " / ".join(f"{m:.0f}" for m in rss_workers), f"{dask.counts()['found']}/{args.pairs}",
         f"cluster start {started:.1f} s, warm-up {max(warm.values()):.1f} s"],
    ]
    print(markdown_table(["run", "wall (s)", "speed-up", "CPU (s)", "cores used", "load avg",
                          "peak RSS (MiB)", "found", "not timed"], rows, align="lrrrrrrrl"))
    print("\ncores used = CPU seconds / wall seconds; the load average (1 min) shows what else ran: "
          "on a shared machine the ratio measures the cores this run got, not only gatv.")
    print(f"\nrecords equal to the serial ones (apart from times; all three runs): {same}/{args.pairs}")
    print(f"Dask vs serial with numba on one thread: {single.seconds / dask_batch:.2f}x")
    print(f"speed-up including the cluster's start and warm-up: "
          f"{(serial.seconds + warm_serial) / (dask_batch + started + max(warm.values())):.2f}")
    out = write_csv(args.out / "batch.csv",
                    ["pairs", "fraction", "workers", "serial_s", "dask_s", "speedup", "serial_cpu_s",
                     "dask_cpu_s", "serial_1thread_s", "serial_1thread_cpu_s", "load_before", "load_serial",
                     "load_1thread", "load_after", "cluster_start_s",
                     "serial_peak_rss_mib", "worker_peak_rss_mib", "records_equal"],
                    [[args.pairs, args.fraction, args.workers, serial.seconds, dask_batch, ratio, cpu_serial,
                      cpu_dask, single.seconds, cpu_single, *load, started, rss_serial, max(rss_workers), same]])
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
