"""Table 1 of Reyes, Medioni & Bayro (IJCV 2007): F-ICP under outliers.

Protocol (section 4): 50 points uniform in a 10×10×10 cube, a rigid motion
with angle uniform in −5..5° about a uniform axis and translation uniform
in [−1.5, 1.5]³, and the same number of uniform outliers added to each set
inside its bounding box; f = 0.50, 0.66, 0.75, 0.80, 0.83; 20 trials each.
A trial succeeds when at least half the true correspondences are output
(one-to-one).

Methods: ``F-ICP`` (LM-ICP, :func:`gatv.baselines.fitzgibbon_icp`), ``ICP``
(:func:`gatv.baselines.icp`), both from the identity, and ``gatv`` in its
small-motion mode (``register(..., max_angle=5, max_translation=1.5·√3)``)
when :mod:`gatv.registration` can be imported.

Usage::

    python benchmarks/table1.py [--trials 20] [--seed 0] [--out benchmarks/results]
                                [--methods F-ICP,ICP,gatv] [--fractions 0.5,0.75]
                                [--scheduler local|ADDRESS]

With ``--scheduler`` each (fraction, trial) is a Dask task (all methods on
that trial); the table is the same as the serial one, apart from times.

Prints a markdown table and writes ``table1.csv`` (one row per fraction and
method) and ``table1_trials.csv`` (one row per trial) to ``--out``.
"""

from __future__ import annotations

import argparse
import math
import sys
from functools import partial
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (
    TrialRecord,
    add_common_arguments,
    add_scheduler_argument,
    fmt,
    map_trials,
    markdown_table,
    run_method,
    summarise,
    trial_seed,
    write_csv,
)

from gatv.baselines import fitzgibbon_icp, icp
from gatv.datasets import table1_trial

#: Outlier fractions of Table 1 and the paper's F-ICP success rates (%).
PAPER_FICP = {0.50: 90, 0.66: 80, 0.75: 60, 0.80: 67, 0.83: 50}
MAX_ANGLE_DEG = 5.0
MAX_TRANSLATION = 1.5 * math.sqrt(3.0)


def _ficp(s, t, k):
    return fitzgibbon_icp(s, t)


def _icp(s, t, k):
    return icp(s, t)


def _gatv(s, t, k):
    from gatv.registration import register

    return register(s, t, seed=k, max_angle=MAX_ANGLE_DEG, max_translation=MAX_TRANSLATION)


def available_methods(*, quiet: bool = False) -> dict:
    """Name → ``fn(source, target, trial_index) -> RigidMotion`` (module-level: picklable)."""
    methods = {"F-ICP": _ficp, "ICP": _icp}
    try:
        import gatv.registration  # noqa: F401
    except ImportError as exc:
        if not quiet:
            print(f"note: gatv.registration cannot be imported ({exc}); running the baselines only.",
                  file=sys.stderr)
    else:
        methods["gatv"] = _gatv
    return methods


def run_trial(task: tuple) -> list[TrialRecord]:
    """Every method on one trial: ``task = (seed, fraction, trial index, method names)``."""
    seed, f, k, names = task
    methods = available_methods(quiet=True)
    trial = table1_trial(f, seed=trial_seed(seed, f, k))
    return [run_method(name, partial(methods[name], k=k), trial, f, k) for name in names]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_common_arguments(parser, trials=20)
    add_scheduler_argument(parser)
    args = parser.parse_args(argv)
    methods = available_methods()
    names = args.methods or list(methods)
    unknown = [n for n in names if n not in methods]
    if unknown:
        parser.error(f"unknown or unavailable method(s) {unknown}; available: {list(methods)}")
    fractions = args.fractions or list(PAPER_FICP)

    tasks = [(args.seed, f, k, tuple(names)) for f in fractions for k in range(args.trials)]
    records: list[TrialRecord] = [r for trial in map_trials(run_trial, tasks, scheduler=args.scheduler)
                                  for r in trial]

    headers = ["f", "method", "success %", "paper F-ICP %", "median precision",
               "median rot. error (deg)", "median time (ms)"]
    rows, csv_rows = [], []
    for f in fractions:
        for name in names:
            cell = summarise([r for r in records if r.fraction == f and r.method == name])
            paper = PAPER_FICP.get(round(f, 2))
            rows.append([
                f"{f:.2f}", name, f"{cell['success_pct']:.0f}", "—" if paper is None else str(paper),
                fmt(cell["precision"], 2), fmt(cell["rotation_error_deg"], 3), fmt(cell["time_ms"], 1),
            ])
            csv_rows.append([f, name, cell["trials"], cell["success_pct"], paper, cell["precision"],
                             cell["recall"], cell["rotation_error_deg"], cell["time_ms"], cell["errors"]])
    where = "serial" if args.scheduler is None else f"Dask tasks on {args.scheduler}"
    print(f"Table 1 protocol: {args.trials} trials per row, seed {args.seed}, 50 inliers, "
          f"angle -5..5 deg, translation [-1.5, 1.5]^3; {where}\n")
    print(markdown_table(headers, rows, align="llrrrrr"))
    out1 = write_csv(args.out / "table1.csv",
                     ["f", "method", "trials", "success_pct", "paper_ficp_pct", "median_precision",
                      "median_recall", "median_rotation_error_deg", "median_time_ms", "errors"], csv_rows)
    out2 = write_csv(args.out / "table1_trials.csv", TrialRecord.HEADERS, [r.row() for r in records])
    failed = [r for r in records if r.error]
    if failed:
        print(f"\n{len(failed)} trial(s) raised; first: {failed[0].method} f={failed[0].fraction}: "
              f"{failed[0].error}", file=sys.stderr)
    print(f"\nwrote {out1} and {out2}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
