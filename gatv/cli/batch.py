"""``gatv batch PAIRS.csv --out DIR``: one command on every row of a table of pairs (:func:`gatv.batch.run`).

Rows run here one after the other until their measured cost says that a
local Dask cluster (``--workers`` processes) would finish the rest sooner,
its start included (``--scheduler auto``, the default; the output says
which ran); ``--scheduler local`` starts the cluster at once, ``--scheduler
ADDRESS`` uses a running scheduler, ``--scheduler serial`` never uses Dask.  One JSON per row in DIR
(the schema of ``gatv register --out``) and ``summary.csv``; a second run
skips the rows already done.

Exit status: 0 when every row ran (found or not); 1 when a row failed (its
error is in its JSON and in ``summary.csv``), with one line counting them;
2 on bad input (a table without ``source``/``target``, an unknown
``--command``, an unreachable scheduler), with nothing written in DIR.
"""

from __future__ import annotations

import sys
from pathlib import Path

from ._common import (
    EXIT_FAILED,
    EXIT_OK,
    PROG,
    UsageError,
    add_verbosity,
    guarded,
    progress_printer,
)

__all__ = ["NAME", "add_parser", "parse_settings", "run"]

NAME = "batch"


def add_parser(subparsers):
    """Add the ``batch`` subcommand to an ``argparse`` subparsers object."""
    from ..batch import COMMANDS, ROW_OPTIONS, TASK_SECONDS

    columns = "; ".join(f"{c}: {', '.join(o)}" for c, o in ROW_OPTIONS.items())
    p = subparsers.add_parser(
        NAME,
        help="run register, segment, instances or nonrigid on every row of a CSV of pairs (Dask)",
        description=(
            "Run a command on every row of PAIRS (a CSV with the columns source and target; "
            "relative paths are relative to the CSV's folder; optional columns: name, and the "
            f"command's options — {columns}). Rows run here until their cost says that a local Dask "
            "cluster pays for its start (--scheduler auto), or as Dask tasks (short rows grouped, "
            "see --chunk) on a local cluster or an existing scheduler (--scheduler). Writes DIR/<name>.json per row "
            "(the schema of `gatv register --out`) and DIR/summary.csv; rows already done are "
            "skipped on a second run."
        ),
    )
    p.add_argument("pairs", type=Path, metavar="PAIRS.csv", help="CSV of pairs (source,target,...)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    p.add_argument("--command", choices=COMMANDS, default="register", dest="batch_command",
                   help="command run on each row (default: register)")
    p.add_argument("--scheduler", default="auto", metavar="ADDRESS",
                   help="'auto' (the default: rows run here until their measured cost says that a local "
                        "Dask cluster would finish the rest sooner, its start included; the summary line "
                        "says which ran), 'local' (a Dask LocalCluster here at once), a scheduler address "
                        "(tcp://host:8786), or 'serial' (no Dask, one row after the other)")
    p.add_argument("--workers", type=int, metavar="N",
                   help="worker processes of the local cluster (default: one per core)")
    p.add_argument("--seed", type=int, default=0, help="seed of rows without a seed cell (default: 0)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="settings",
                   help="default of a per-row option for rows that leave it empty, e.g. "
                        "--set model=similarity (repeatable)")
    p.add_argument("--retries", type=int, default=1, metavar="N",
                   help="re-runs of a task that raised on a worker (default: 1); a killed "
                        "worker's task is re-run regardless")
    p.add_argument("--chunk", type=int, metavar="N",
                   help="rows per Dask task (default: sized as the batch runs, so that a task takes "
                        f"about {TASK_SECONDS:g} s: short rows are grouped, long ones run alone)")
    p.add_argument("--connect-timeout", type=float, default=10.0, metavar="SECONDS",
                   help="how long to wait for a --scheduler address (default: 10)")
    add_verbosity(p)
    p.set_defaults(handler=run)
    return p


def parse_settings(items) -> dict:
    """``["key=value", ...]`` -> ``{"key": "value"}``; UsageError for an item without ``=``."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise UsageError(f"expected --set KEY=VALUE, got {item!r}.")
        out[key.strip()] = value.strip()
    return out


@guarded
def run(args) -> int:
    """Run ``gatv batch`` on parsed ``args``; return the exit status."""
    from ..batch import read_pairs
    from ..batch import run as run_batch

    if args.workers is not None and args.workers < 1:
        raise UsageError(f"expected --workers >= 1, got {args.workers}.")
    if not args.connect_timeout > 0:
        raise UsageError(f"expected --connect-timeout > 0, got {args.connect_timeout}.")
    if args.chunk is not None and args.chunk < 1:
        raise UsageError(f"expected --chunk >= 1, got {args.chunk}.")
    if args.retries < 0:
        raise UsageError(f"expected --retries >= 0, got {args.retries}.")
    if args.seed < 0:
        raise UsageError(f"expected --seed >= 0, got {args.seed}.")
    settings = parse_settings(args.settings)
    n_rows = len(read_pairs(args.pairs, command=args.batch_command, seed=args.seed, defaults=settings))
    progress = progress_printer(args, total=n_rows, unit="row")
    try:
        result = run_batch(args.pairs, args.out, command=args.batch_command, scheduler=args.scheduler,
                           workers=args.workers, seed=args.seed, defaults=settings,
                           retries=args.retries, progress=progress, timeout=args.connect_timeout,
                           chunk=args.chunk)
    finally:
        if progress is not None:
            progress.close()
    counts = result.counts()
    if not args.quiet:
        reused = f", {counts['reused']} already done" if counts["reused"] else ""
        print(f"{PROG} batch: {len(result)} rows ({args.batch_command}): {counts['found']} found, "
              f"{counts['not found']} not found, {counts['failed']} failed{reused}; "
              f"{result.seconds:.1f} s")
        print(f"ran on:          {result.where}")
        print(f"wrote {result.summary}")
    if result.failed:
        first = result.failed[0]
        print(f"{PROG}: error: {counts['failed']} of {len(result)} rows failed (first: {first.name}: "
              f"{first.error}); see {result.summary}", file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK
