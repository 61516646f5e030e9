"""gatv batch: Table-2 pairs serially vs as Dask tasks on local workers, in one run.

Two workloads of Table-2 trials (50 inliers, outlier fraction ``--fraction``,
seeds from ``--seed``, written as ``.npy`` files and a ``pairs.csv``):

* the issue's: ``--pairs`` noise-free pairs (default 100; ~50 ms each);
* ``--noisy-pairs`` of the same seeds with Gaussian noise ``--noise`` (default
  30 pairs at 1% of the extent; 1-2 s of CPU each), where a registration
  costs enough for the batch's fixed costs to vanish (0 skips it).

Each workload runs through ``gatv.batch.run`` as: ``serial`` (this process,
numba on every core: the baseline), ``serial, numba 1 thread`` (what each
worker gets), ``Dask, N workers`` (a ``LocalCluster`` of ``--workers``
single-threaded processes with the default task sizing: what ``gatv batch
--workers N`` runs) and, for the noise-free pairs, the same cluster with one
row per task (``chunk=1``).  Both sides are warmed up first (numba kernels
loaded from the cache: pairs 1-3 of each workload here and on each worker,
after pair 0, whose cost is reported), and the cluster's
start-up is reported apart, as the issue's ratio is of the batch itself.

Prints one table (wall and CPU seconds — for Dask the workers' plus this
process's, which holds the client and the scheduler —, the load average
before and after each run, found pairs, and whether every record equals the
serial one apart from times), then where the Dask time goes (cluster start,
worker imports and numba cache, Dask's cost per task, measured with no-op
tasks) and the bound on the ratio that the single-thread CPU time sets.
Writes ``batch.csv`` to ``--out``.  On 2 idle cores it should take 2-4
minutes (estimated from the runs' CPU seconds), several times that on a loaded machine.

Usage::

    python benchmarks/batch.py [--pairs 100] [--noisy-pairs 30] [--noise 0.01] [--fraction 0.75]
                               [--workers 2] [--seed 0] [--out benchmarks/results]
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


def noop(x):
    return x


def make_pairs(folder: Path, n: int, fraction: float, seed: int, noise: float = 0.0) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["source,target,seed"]
    for k in range(n):
        trial = table2_trial(fraction, noise=noise, seed=trial_seed(seed, fraction, k))
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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=100, help="noise-free Table-2 pairs (default: 100)")
    parser.add_argument("--noisy-pairs", type=int, default=30,
                        help="noisy Table-2 pairs, the same seeds (default: 30; 0 skips them)")
    parser.add_argument("--noise", type=float, default=0.01,
                        help="noise of the noisy pairs, fraction of the extent (default: 0.01)")
    parser.add_argument("--fraction", type=float, default=0.75, help="outlier fraction (default: 0.75)")
    parser.add_argument("--workers", type=int, default=2, help="local Dask workers (default: 2)")
    parser.add_argument("--seed", type=int, default=0, help="base seed of the trials (default: 0)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"CSV folder (default: {DEFAULT_OUT})")
    args = parser.parse_args(argv)
    if args.pairs < 1 or args.workers < 1 or args.noisy_pairs < 0:
        parser.error("--pairs and --workers must be >= 1, --noisy-pairs >= 0")

    workloads = [("noise-free", args.pairs, 0.0)]
    if args.noisy_pairs:
        workloads.append((f"noise {args.noise:g}", args.noisy_pairs, args.noise))
    runs, fixed = {}, {}
    stamp = sources_stamp()
    with tempfile.TemporaryDirectory(prefix="gatv-batch-bench-") as tmp:
        folder = Path(tmp)
        tables = {name: make_pairs(folder / f"w{k}", n, args.fraction, args.seed, noise)
                  for k, (name, n, noise) in enumerate(workloads)}
        first = [str(tables["noise-free"].parent / f"{x}0000.npy") for x in "st"]
        more = [tuple(str(t.parent / f"{x}{k:04d}.npy") for x in "st")
                for t in tables.values() for k in range(1, 4) if (t.parent / f"s{k:04d}.npy").exists()]
        c0 = cpu_seconds()
        import_command()
        fixed["serial import"] = cpu_seconds() - c0
        fixed["serial warm-up"] = warm_up(*first)
        warm_more(more)
        for name, table in tables.items():
            runs[name, "serial"] = run_serial(table, folder / name / "serial")
            runs[name, "serial, numba 1 thread"] = run_serial(table, folder / name / "single", threads=1)

        t0 = time.perf_counter()
        with batch.connect("local", workers=args.workers) as client:
            fixed["cluster start"] = time.perf_counter() - t0
            fixed["worker start"] = max(client.run(cpu_seconds).values())
            fixed["worker import"] = max(client.run(import_command).values())
            fixed["worker warm-up"] = max(client.run(warm_up, *first).values())
            client.run(warm_more, more)
            dask_run = f"Dask, {args.workers} workers"
            for name, table in tables.items():
                runs[name, dask_run] = run_dask(client, table, folder / name / "dask", chunk=None)
                if name == "noise-free":
                    runs[name, dask_run + ", 1 row/task"] = run_dask(client, table, folder / name / "dask1", chunk=1)
            # Dask's own cost per task: no-op tasks carrying a row's Task
            tasks = batch.read_pairs(tables["noise-free"])
            w0, c0, t1 = sum(client.run(cpu_seconds).values()), cpu_seconds(), time.perf_counter()
            client.gather(client.map(noop, tasks, pure=False))
            noop_wall = time.perf_counter() - t1
            noop_cpu = sum(client.run(cpu_seconds).values()) - w0 + cpu_seconds() - c0
            rss_workers = sorted(client.run(peak_rss_mib).values())
        rss_serial = peak_rss_mib()
        equal = {name: same_records([r for (w, _), r in runs.items() if w == name]) for name in tables}

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    print(f"gatv batch: Table-2 pairs, f = {args.fraction}, seed {args.seed}; {cores} cores; serial in-process "
          f"(numba on every core) vs {args.workers} local Dask workers (1 thread each)\n")
    rows, csv_rows = [], []
    order = [name for name, *_ in workloads]
    for (name, run), r in sorted(runs.items(), key=lambda item: order.index(item[0][0])):
        n = len(r["result"])
        serial = runs[name, "serial"]
        cpu = f"{r['cpu']:.1f}" if "workers_cpu" not in r else \
            f"{r['cpu']:.1f} ({r['workers_cpu']:.1f} + {r['client_cpu']:.1f})"
        rows.append([name, n, run, f"{r['wall']:.1f}", f"{serial['wall'] / r['wall']:.2f}", cpu,
                     f"{r['cpu'] / r['wall']:.2f}", r.get("tasks", ""),
                     f"{100 * r['busy']:.0f}%" if "busy" in r else "",
                     f"{r['load'][0]:.1f} -> {r['load'][1]:.1f}",
                     f"{r['result'].counts()['found']}/{n}", f"{equal[name]}/{n}"])
        csv_rows.append([name, n, args.fraction, args.workers, run, r["wall"], serial["wall"] / r["wall"], r["cpu"],
                         r.get("workers_cpu", ""), r.get("client_cpu", ""), r.get("tasks", ""), r.get("busy", ""),
                         *r["load"], r["result"].counts()["found"], equal[name]])
    print(markdown_table(["pairs", "n", "run", "wall (s)", "speed-up", "CPU (s)", "cores used", "tasks", "busy",
                          "load avg", "found", "= serial"], rows, align="llrrrrrrrrrr"))
    print("\nspeed-up = serial wall / this wall; CPU of a Dask run = workers + this process (client and "
          "scheduler); cores used = CPU / wall; tasks: Dask tasks the rows ran as; busy: share of the workers' wall time "
          "spent computing rows (the rest: Dask's own work, waiting, the first and last tasks); load avg = 1-minute load before -> after the run: on a shared "
          "machine the ratio measures the cores this run got, not only gatv.  '= serial': records equal to the "
          "serial run's apart from times.")

    print("\nWhere the Dask time goes (noise-free pairs):")
    single, dask = runs["noise-free", "serial, numba 1 thread"], runs["noise-free", dask_run]
    n = len(single["result"])
    print(f"- not timed: cluster start {fixed['cluster start']:.1f} s wall; per worker before its first row "
          f"(CPU): process start {fixed['worker start']:.2f} s, importing gatv's register modules "
          f"{fixed['worker import']:.2f} s, numba kernels from the cache (one pair) {fixed['worker warm-up']:.2f} s "
          f"(this process: {fixed['serial import']:.2f} s + {fixed['serial warm-up']:.2f} s)")
    print(f"- Dask's cost per task, {n} no-op tasks: {1000 * noop_cpu / n:.1f} ms CPU per task "
          f"({noop_wall:.2f} s wall for all)")
    extra = dask["cpu"] - single["cpu"]
    print(f"- the batch on Dask took {dask['cpu']:.1f} s CPU vs {single['cpu']:.1f} s serially on one thread: "
          f"{extra:+.1f} s ({1000 * extra / n:+.0f} ms per row) for the workers' and scheduler's own work")
    bound = runs["noise-free", "serial"]["wall"] / (single["cpu"] / args.workers)
    print(f"- bound: {args.workers} single-thread workers cannot finish before {single['cpu'] / args.workers:.1f} s "
          f"(one-thread CPU / {args.workers}) even with no Dask cost, so the ratio cannot exceed "
          f"{bound:.2f} here; serial keeps {runs['noise-free', 'serial']['cpu'] / runs['noise-free', 'serial']['wall']:.2f} "
          f"cores busy through numba's parallel kernels")
    for name, *_ in workloads[1:]:
        s1 = runs[name, "serial, numba 1 thread"]
        print(f"- {name}: the same bound is {runs[name, 'serial']['wall'] / (s1['cpu'] / args.workers):.2f}")
    print(f"\npeak RSS: this process {rss_serial:.0f} MiB, workers "
          f"{' / '.join(f'{m:.0f}' for m in rss_workers)} MiB")
    print(f"speed-up of the noise-free batch including the cluster's start and the workers' warm-up: "
          f"{runs['noise-free', 'serial']['wall'] / (dask['wall'] + fixed['cluster start'] + fixed['worker import'] + fixed['worker warm-up']):.2f}")
    out = write_csv(args.out / "batch.csv",
                    ["pairs", "n", "fraction", "workers", "run", "wall_s", "speedup", "cpu_s", "workers_cpu_s",
                     "client_cpu_s", "tasks", "busy", "load_before", "load_after", "found", "records_equal"], csv_rows)
    if sources_stamp() != stamp:
        print("\nWARNING: gatv's source files changed during this run; the workers may have imported other "
              "code than the serial runs, so records can differ for that reason alone.")
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
