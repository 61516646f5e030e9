"""Table 2 of Reyes, Medioni & Bayro (IJCV 2007): gatv under outliers, any motion.

Protocol (section 4): 50 points uniform in a 10×10×10 cube, a rigid motion
with angle uniform in 0..360° about a uniform axis and translation uniform
in [−10, 10]³, and the same number of uniform outliers added to each set
inside its bounding box; f = 0.75, 0.83, 0.85, 0.88, 0.90, 0.93 (the paper)
and 0.95 (beyond it); 20 trials each. A trial succeeds when at least half
the true correspondences are output (one-to-one).

Methods: ``gatv`` (``gatv.register(source, target, seed=trial)``, the
default), and on request (``--methods gatv,F-ICP,ICP``) the baselines from
the identity, which are not expected to work on large motions.

Usage::

    python benchmarks/table2.py [--trials 20] [--seed 0] [--out benchmarks/results]
                                [--methods gatv] [--fractions 0.75,0.9] [--no-plot]

Prints a markdown table and writes ``table2.csv``, ``table2_trials.csv``
and ``table2.png`` (success rate against f, with the paper's) to ``--out``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (  # noqa: E402
    TrialRecord,
    add_common_arguments,
    fmt,
    markdown_table,
    run_method,
    summarise,
    trial_seed,
    write_csv,
)

from gatv.baselines import fitzgibbon_icp, icp  # noqa: E402
from gatv.datasets import table2_trial  # noqa: E402

#: Outlier fractions of Table 2 and the paper's tensor-voting success rates (%).
PAPER_TV = {0.75: 100, 0.83: 90, 0.85: 85, 0.88: 80, 0.90: 80, 0.93: 70, 0.95: None}


def available_methods() -> tuple[dict, str | None]:
    """Name → ``fn(source, target, trial_index)``, and why gatv is missing (or None)."""
    methods = {
        "F-ICP": lambda s, t, k: fitzgibbon_icp(s, t),
        "ICP": lambda s, t, k: icp(s, t),
    }
    try:
        from gatv.registration import register
    except ImportError as exc:
        return methods, f"gatv.registration cannot be imported ({exc})"
    methods["gatv"] = lambda s, t, k: register(s, t, seed=k)
    return methods, None


def plot(path: Path, fractions, series: dict) -> Path | None:
    """Success rate (%) against f, one line per method and the paper's.

    Drawn off-screen with PyVista's chart API; returns None (with a message)
    when no picture can be made.
    """
    try:
        import pyvista as pv
    except ImportError:  # pragma: no cover - pyvista is a dependency
        print("note: pyvista is not available; no plot written.", file=sys.stderr)
        return None
    colours = ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple"]
    chart = pv.Chart2D(x_label="outlier fraction f", y_label="success rate (%)")
    chart.title = "Table 2 protocol: success rate against outliers"
    for (name, values), colour in zip(series.items(), colours):
        xs = [f for f, v in zip(fractions, values) if v is not None]
        ys = [v for v in values if v is not None]
        if not xs:
            continue
        style = "--" if name.startswith("paper") else "-"
        chart.line(xs, ys, color=colour, width=2.0, style=style, label=name)
        chart.scatter(xs, ys, color=colour, size=8, style="o")
    chart.y_range = [0, 105]
    lo, hi = min(fractions), max(fractions)
    pad = 0.02 if hi > lo else 0.05
    chart.x_range = [lo - pad, hi + pad]
    try:
        with pv.vtk_verbosity("off"):
            plotter = pv.Plotter(off_screen=True, window_size=(900, 600))
            try:
                plotter.add_chart(chart)
                plotter.screenshot(str(path))
            finally:
                plotter.close()
    except Exception as exc:  # no OpenGL context etc.: the table is still valid
        print(f"note: could not render the plot ({type(exc).__name__}: {exc}); skipped.", file=sys.stderr)
        return None
    return path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_common_arguments(parser, trials=20)
    parser.add_argument("--no-plot", action="store_true", help="do not write table2.png")
    args = parser.parse_args(argv)
    methods, missing = available_methods()
    names = args.methods or ["gatv"]
    if missing and "gatv" in names:
        print(f"note: {missing}; skipping method gatv.", file=sys.stderr)
        names = [n for n in names if n != "gatv"]
        if not names:
            print("nothing to run (use --methods F-ICP,ICP for the baselines).", file=sys.stderr)
            return 1
    unknown = [n for n in names if n not in methods]
    if unknown:
        parser.error(f"unknown method(s) {unknown}; available: {sorted(methods)}")
    fractions = args.fractions or list(PAPER_TV)

    records: list[TrialRecord] = []
    for f in fractions:
        for k in range(args.trials):
            trial = table2_trial(f, seed=trial_seed(args.seed, f, k))
            for name in names:
                fn = methods[name]
                records.append(run_method(name, lambda s, t, fn=fn, k=k: fn(s, t, k), trial, f, k))
            print(f"  f={f:.2f} trial {k + 1}/{args.trials} done", file=sys.stderr, flush=True)

    headers = ["f", "outliers/set", "method", "success %", "paper TV %", "median precision",
               "median rot. error (deg)", "median time (ms)"]
    rows, csv_rows = [], []
    series = {name: [] for name in names}
    for f in fractions:
        n_out = int(round(50 * f / (1 - f)))
        for name in names:
            cell = summarise([r for r in records if r.fraction == f and r.method == name])
            paper = PAPER_TV.get(round(f, 2))
            series[name].append(cell["success_pct"])
            rows.append([
                f"{f:.2f}", str(n_out), name, f"{cell['success_pct']:.0f}",
                "—" if paper is None else str(paper), fmt(cell["precision"], 2),
                fmt(cell["rotation_error_deg"], 3), fmt(cell["time_ms"], 1),
            ])
            csv_rows.append([f, n_out, name, cell["trials"], cell["success_pct"], paper,
                             cell["precision"], cell["recall"], cell["rotation_error_deg"],
                             cell["time_ms"], cell["errors"]])
    series["paper (tensor voting)"] = [PAPER_TV.get(round(f, 2)) for f in fractions]

    print(f"Table 2 protocol: {args.trials} trials per row, seed {args.seed}, 50 inliers, "
          f"angle 0..360 deg, translation [-10, 10]^3\n")
    print(markdown_table(headers, rows, align="lrlrrrrr"))
    out1 = write_csv(args.out / "table2.csv",
                     ["f", "outliers_per_set", "method", "trials", "success_pct", "paper_tv_pct",
                      "median_precision", "median_recall", "median_rotation_error_deg",
                      "median_time_ms", "errors"], csv_rows)
    out2 = write_csv(args.out / "table2_trials.csv", TrialRecord.HEADERS, [r.row() for r in records])
    written = [out1, out2]
    if not args.no_plot:
        png = plot(args.out / "table2.png", fractions, series)
        if png is not None:
            written.append(png)
    failed = [r for r in records if r.error]
    if failed:
        print(f"\n{len(failed)} trial(s) raised; first: {failed[0].method} f={failed[0].fraction}: "
              f"{failed[0].error}", file=sys.stderr)
    print("\nwrote " + ", ".join(map(str, written)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
