"""gatv batch: serial on 1 and on every thread vs Dask workers, short and long batches, and the first run.

Workloads of Table-2 trials written as ``.npy`` files and a ``pairs.csv``:

* ``--pairs`` Table-2 rows (default 100: 50 inliers, outlier fraction
  ``--fraction`` 0.75; ~50 ms each);
* ``--short-pairs`` short rows (default 40: 20 inliers, f = 0.5; ~20 ms
  each), where a cluster's start costs more than the batch;
* ``--noisy-pairs`` of the Table-2 seeds with Gaussian noise ``--noise``
  (default 0: off; 1-2 s of CPU each);
* ``--long-pairs`` long rows (default 16: 200 inliers, f = 0.9, 2,000
  points a set; ~1.5 s each on one thread), where a row's work dwarfs
  Dask's cost per task and a worker's start: the rows on which 2 workers
  should approach 2x serial on one thread (issue 42 asks >= 1.8x).

Each workload runs through ``gatv.batch.run`` as: ``serial, numba 1
thread`` (the baseline of the speed-up), ``serial, numba N threads`` (this
process on every core), ``auto`` (``gatv batch``'s default: serial until
the rows' measured cost pays for a local cluster; its start included when
it starts one, and the ``where`` it reports), ``Dask, W local workers``
(a ``LocalCluster`` of ``--workers`` single-threaded processes, started and
warmed apart) and ``Dask, W-process cluster`` (``python -m dask
scheduler`` and ``--workers`` ``python -m dask worker`` processes on
127.0.0.1, reached at ``tcp://...`` as a cluster of machines is: what
``gatv batch --scheduler tcp://host:8786`` meets; numba pinned to one
thread per worker on 2 cores).  Kernels are loaded from the cache first on
every side (warm-up rows, not timed).

Then, unless ``--no-first-run``: ``gatv demo`` in a fresh process with an
empty ``NUMBA_CACHE_DIR`` (a fresh install's first run), again (the second
run), and after ``gatv warmup`` into another empty cache.

Prints the table (wall and CPU seconds, speed-up over serial on one thread
and over serial on every thread, found pairs, records equal to the serial
ones apart from times), the load average (the machine may be shared) and
writes ``batch.csv`` to ``--out``.

Usage::

    python benchmarks/batch.py [--pairs 100] [--short-pairs 40] [--noisy-pairs 0] [--long-pairs 16]
                               [--fraction 0.75] [--workers 2] [--seed 0] [--no-first-run]
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


def cpu_seconds() -> float:
    """User + system CPU seconds of the calling process so far (all its threads)."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def import_command() -> float:
    """Import the modules a register row needs; CPU seconds taken (0 when already imported)."""
    start = cpu_seconds()
    import gatv.io  # noqa: F401
    import gatv.registration  # noqa: F401

    return cpu_seconds() - start


def warm_up(source: str, target: str) -> float:
    """Register one pair (loads the numba kernels from the cache); CPU seconds taken."""
    from gatv.io import read_points
    from gatv.registration import register

    start = cpu_seconds()
    register(read_points(source), read_points(target), seed=0)
    return cpu_seconds() - start


def warm_more(pairs) -> None:
    """Register a few more pairs: kernels that the first pair did not reach load from the cache too,
    so the first timed run does not pay for them and the next ones do not gain from that."""
    for source, target in pairs:
        warm_up(source, target)


def make_pairs(folder: Path, n: int, fraction: float, seed: int, noise: float = 0.0, inliers: int = 50) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["source,target,seed"]
    for k in range(n):
        trial = table2_trial(fraction, n_inliers=inliers, noise=noise, seed=trial_seed(seed, fraction, k))
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


def sources_stamp() -> float:
    """Newest modification time of gatv's sources: the serial runs import them before the workers do."""
    import gatv

    return max(f.stat().st_mtime for f in Path(gatv.__file__).parent.rglob("*.py"))


def load() -> float:
    return os.getloadavg()[0]


def run_serial(table: Path, out: Path, threads: int | None = None) -> dict:
    import numba

    before = numba.get_num_threads()
    if threads:
        numba.set_num_threads(threads)
    try:
        l0, c0 = load(), cpu_seconds()
        result = batch.run(table, out, scheduler="serial")
        return {"result": result, "wall": result.seconds, "cpu": cpu_seconds() - c0, "load": (l0, load())}
    finally:
        numba.set_num_threads(before)


def run_dask(client, table: Path, out: Path, chunk: int | None) -> dict:
    """``batch.run`` on ``client``: wall, CPU (workers, this process), Dask tasks, the workers' busy share."""
    from distributed import get_task_stream

    l0 = load()
    w0, c0 = sum(client.run(cpu_seconds).values()), cpu_seconds()
    with get_task_stream(client) as stream:
        t0 = time.perf_counter()
        result = batch.run(table, out, scheduler=client, chunk=chunk)
        wall = time.perf_counter() - t0
    c1, w1 = cpu_seconds(), sum(client.run(cpu_seconds).values())
    computing = [ss["stop"] - ss["start"] for t in stream.data if str(t["key"]).startswith("gatv-")
                 for ss in t["startstops"] if ss["action"] == "compute"]
    return {"result": result, "wall": wall, "cpu": (w1 - w0) + (c1 - c0), "workers_cpu": w1 - w0,
            "client_cpu": c1 - c0, "load": (l0, load()), "tasks": len(computing),
            "busy": sum(computing) / (wall * len(client.nthreads()))}


def same_records(runs: list[dict]) -> int:
    """Rows whose record equals the first run's in every run (apart from times)."""
    base = runs[0]["result"].rows
    return sum(all(_strip_times(json.loads(r["result"].rows[k].path.read_text()))
                   == _strip_times(json.loads(base[k].path.read_text())) for r in runs[1:])
               for k in range(len(base)))


def run_auto(table: Path, out: Path, workers: int) -> dict:
    """``batch.run(..., scheduler="auto")``: the whole call, a local cluster's start included."""
    l0, c0 = load(), cpu_seconds()
    result = batch.run(table, out, scheduler="auto", workers=workers)
    return {"result": result, "wall": result.seconds, "cpu": cpu_seconds() - c0, "load": (l0, load()),
            "where": result.where}


def first_runs(folder: Path) -> list[tuple[str, float]]:
    """``gatv demo`` wall seconds in fresh processes: empty numba cache, second run, after ``gatv warmup``."""
    import subprocess

    def timed(args, cache):
        env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "gatv", *args], env=env, check=True, capture_output=True,
                       cwd=folder)
        return time.perf_counter() - t0

    cold, warm = folder / "cache-cold", folder / "cache-warm"
    cold.mkdir()
    warm.mkdir()
    out = [("gatv demo, empty NUMBA_CACHE_DIR (first run)", timed(["demo", "-q"], cold)),
           ("gatv demo, second run", timed(["demo", "-q"], cold)),
           ("gatv warmup, empty NUMBA_CACHE_DIR", timed(["warmup", "-q"], warm))]
    out.append(("gatv demo, first run after gatv warmup", timed(["demo", "-q"], warm)))
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=100, help="Table-2 pairs, 50 inliers (default: 100)")
    parser.add_argument("--short-pairs", type=int, default=40,
                        help="short pairs, 20 inliers, f = 0.5 (default: 40; 0 skips them)")
    parser.add_argument("--noisy-pairs", type=int, default=0,
                        help="noisy Table-2 pairs, the same seeds (default: 0, skipped)")
    parser.add_argument("--noise", type=float, default=0.01,
                        help="noise of the noisy pairs, fraction of the extent (default: 0.01)")
    parser.add_argument("--long-pairs", type=int, default=16,
                        help="long pairs, 200 inliers, f = 0.9, ~1.5 s each (default: 16; 0 skips them)")
    parser.add_argument("--fraction", type=float, default=0.75, help="outlier fraction (default: 0.75)")
    parser.add_argument("--workers", type=int, default=2, help="Dask workers (default: 2)")
    parser.add_argument("--seed", type=int, default=0, help="base seed of the trials (default: 0)")
    parser.add_argument("--no-first-run", action="store_true", help="skip the first-run timings of gatv demo")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"CSV folder (default: {DEFAULT_OUT})")
    args = parser.parse_args(argv)
    if args.pairs < 1 or args.workers < 1 or min(args.noisy_pairs, args.short_pairs, args.long_pairs) < 0:
        parser.error("--pairs and --workers must be >= 1, --short-pairs, --noisy-pairs and --long-pairs >= 0")
    import numba
    from distributed import Client

    from gatv._dask import process_cluster

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    all_threads = numba.get_num_threads()
    workloads = [("Table-2", args.pairs, args.fraction, 0.0, 50)]
    if args.short_pairs:
        workloads.append(("short", args.short_pairs, 0.5, 0.0, 20))
    if args.noisy_pairs:
        workloads.append((f"noise {args.noise:g}", args.noisy_pairs, args.fraction, args.noise, 50))
    if args.long_pairs:
        workloads.append(("long", args.long_pairs, 0.9, 0.0, 200))
    one, every = "serial, numba 1 thread", f"serial, numba {all_threads} threads"
    local, procs = f"Dask, {args.workers} local workers", f"Dask, {args.workers}-process cluster (tcp)"
    runs, fixed = {}, {}
    stamp = sources_stamp()
    with tempfile.TemporaryDirectory(prefix="gatv-batch-bench-") as tmp:
        folder = Path(tmp)
        tables = {name: make_pairs(folder / f"w{k}", n, f, args.seed, noise, inliers)
                  for k, (name, n, f, noise, inliers) in enumerate(workloads)}
        first = [str(tables["Table-2"].parent / f"{x}0000.npy") for x in "st"]
        more = [tuple(str(t.parent / f"{x}{k:04d}.npy") for x in "st")
                for name, t in tables.items() for k in range(1, 2 if name == "long" else 4)
                if (t.parent / f"s{k:04d}.npy").exists()]
        import_command()
        warm_up(*first)
        warm_more(more)
        for name, table in tables.items():
            runs[name, one] = run_serial(table, folder / name / "single", threads=1)
            runs[name, every] = run_serial(table, folder / name / "serial", threads=all_threads)
            runs[name, "auto"] = run_auto(table, folder / name / "auto", args.workers)

        t0 = time.perf_counter()
        with batch.connect("local", workers=args.workers) as client:
            fixed["local cluster start"] = time.perf_counter() - t0
            client.run(warm_up, *first)
            client.run(warm_more, more)
            for name, table in tables.items():
                runs[name, local] = run_dask(client, table, folder / name / "dask", chunk=None)
        t0 = time.perf_counter()
        # the workers run with the local cluster's settings (no sampling profiler, 200 ms tick, glibc's
        # own malloc thresholds), as environment variables: what a user sets on a cluster's machines
        # (docs/batch.rst)
        dask_env = {"DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED": "False",
                    "DASK_DISTRIBUTED__ADMIN__TICK__INTERVAL": "200ms",
                    "DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON": '{"MALLOC_TRIM_THRESHOLD_": None}'}
        with process_cluster(args.workers, threads=1, env=dask_env) as address, Client(address) as client:
            fixed["process cluster start"] = time.perf_counter() - t0
            client.run(warm_up, *first)
            client.run(warm_more, more)
            fixed["process cluster numba threads"] = sorted(batch.numba_plan(client).values())
            for name, table in tables.items():
                runs[name, procs] = run_dask(client, table, folder / name / "procs", chunk=None)
        equal = {name: same_records([runs[name, one]] + [r for (w, k), r in runs.items() if w == name and k != one])
                 for name in tables}
        firsts = [] if args.no_first_run else first_runs(folder)

    print(f"gatv batch: {cores} cores (shared machine: see the load averages); serial in this process on 1 "
          f"and on {all_threads} numba threads, auto, {args.workers} local Dask workers and a "
          f"{args.workers}-process Dask cluster (1 thread and 1 numba thread each)\n")
    rows, csv_rows = [], []
    order = [name for name, *_ in workloads]
    kinds = [one, every, "auto", local, procs]
    for (name, run), r in sorted(runs.items(), key=lambda item: (order.index(item[0][0]), kinds.index(item[0][1]))):
        n = len(r["result"])
        base, base_all = runs[name, one], runs[name, every]
        cpu = f"{r['cpu']:.1f}" if "workers_cpu" not in r else \
            f"{r['cpu']:.1f} ({r['workers_cpu']:.1f} + {r['client_cpu']:.1f})"
        rows.append([name, n, run, f"{r['wall']:.2f}", f"{base['wall'] / r['wall']:.2f}",
                     f"{base_all['wall'] / r['wall']:.2f}", cpu, r.get("tasks", ""),
                     f"{r['load'][0]:.1f} -> {r['load'][1]:.1f}",
                     f"{r['result'].counts()['found']}/{n}", f"{equal[name]}/{n}"])
        csv_rows.append([name, n, args.workers, run, r["wall"], base["wall"] / r["wall"],
                         base_all["wall"] / r["wall"], r["cpu"], r.get("tasks", ""), *r["load"],
                         r["result"].counts()["found"], equal[name], r.get("where", "")])
    print(markdown_table(["rows", "n", "run", "wall (s)", "vs 1 thread", f"vs {all_threads} threads", "CPU (s)",
                          "tasks", "load avg", "found", "= serial"], rows, align="llrrrrrrrrr"))
    print("\nvs 1 thread / vs N threads: serial wall on 1 / on every numba thread over this run's wall; "
          "Dask runs exclude their cluster's start and warm-up (below), 'auto' includes whatever it started. "
          "CPU of a Dask run = workers + this process.  '= serial': records equal to serial on 1 thread's "
          "apart from times.")
    for name in tables:
        print(f"- auto on {name}: {runs[name, 'auto']['where']}")
    for name in tables:
        for run in (local, procs):
            r = runs[name, run]
            print(f"- {name}, {run}: on {args.workers} cores of their own the workers would run "
                  f"{runs[name, one]['cpu'] / (r['workers_cpu'] / args.workers):.2f}x serial on 1 thread "
                  f"(serial 1-thread CPU {runs[name, one]['cpu']:.1f} s over the workers' CPU per worker "
                  f"{r['workers_cpu'] / args.workers:.1f} s; Dask's bookkeeping and contention included, "
                  f"other processes' load excluded)")
    print(f"- not timed: local cluster start {fixed['local cluster start']:.1f} s; process cluster start "
          f"{fixed['process cluster start']:.1f} s; the process cluster's numba threads per worker: "
          f"{fixed['process cluster numba threads']}")
    if firsts:
        print()
        print(markdown_table(["first run", "wall (s)"], [[what, f"{sec:.1f}"] for what, sec in firsts],
                             align="lr"))
        csv_rows += [[what, "", "", "", sec, "", "", "", "", "", "", "", "", ""] for what, sec in firsts]
    out = write_csv(args.out / "batch.csv",
                    ["rows", "n", "workers", "run", "wall_s", "speedup_vs_1_thread", "speedup_vs_all_threads",
                     "cpu_s", "tasks", "load_before", "load_after", "found", "records_equal", "where"], csv_rows)
    if sources_stamp() != stamp:
        print("\nWARNING: gatv's source files changed during this run; the workers may have imported other "
              "code than the serial runs, so records can differ for that reason alone.")
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
