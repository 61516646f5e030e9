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
                                [--scheduler local|ADDRESS]
    python benchmarks/table2.py --noise 0,0.01,0.02,0.04 [--fractions 0.5,0.75,0.9] [--trials 20]

Prints a markdown table and writes ``table2.csv``, ``table2_trials.csv``
and ``table2.png`` (success rate against f, with the paper's) to ``--out``.

Before the table each method makes one untimed call (and gatv's
:func:`warm_up`), so that no trial's time holds imports or the compilation of
gatv's kernels.

``--noise`` runs the noisy variant instead: isotropic Gaussian noise on every
inlier coordinate of both sets, its standard deviation the given share of
the inlier set's RMS radius (5 for the 10-cube), at f = 0.5, 0.75, 0.9, 0.95
by default; ``gatv.register`` gets no ``noise=``.  Success: at least half the
true pairs and a rotation error below 2°.  Reports success, the same
success of the maximum-likelihood estimate started at the true pose with
the true noise (:func:`maximum_likelihood`, the "ML %" column: what the
data allow, computed on the same trials in the same run), the share of
trials whose true pose, refined at some level's gate, beats the search's
final chance level there (the "count ceiling %" column,
:func:`gatv.registration.count_ceiling`: what a search that keeps no wrong
motion could keep, whatever its trial motions), the same with the
likelihood-ratio test beside the count (the "LR ceiling %" column,
``count_ceiling(..., likelihood=True)``: what a final test that weighs each
pair by its likelihood ratio would keep; the search does not use it), the
family-wise level at which the count test would keep the true pose in 5
points fewer trials than ML keeps (the "count α for ML − 5" column,
:func:`gatv.registration.count_alpha`: how far the ML column lies beyond a
test held to ``gatv.stats.ALPHA``), median and
maximum time per call (wall and CPU), and the median ratio of the noise ``gatv`` measured
(``info["noise"]``) to the true one; writes ``table2_noise.csv`` and
``table2_noise_trials.csv``.  Each process first makes two untimed small
calls (:func:`warm_up`), so that no trial's time holds the compilation of
gatv's kernels.
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (  # noqa: E402
    TrialRecord,
    add_common_arguments,
    add_scheduler_argument,
    fmt,
    map_trials,
    markdown_table,
    median,
    parse_list,
    run_method,
    summarise,
    trial_seed,
    write_csv,
)

from gatv.baselines import fitzgibbon_icp, icp  # noqa: E402
from gatv.datasets import table2_trial  # noqa: E402
from gatv.stats import ALPHA  # noqa: E402

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


#: Outlier fractions of the noisy variant (``--noise``).
NOISE_FRACTIONS = (0.5, 0.75, 0.9, 0.95)
#: Largest rotation error (degrees) of a success in the noisy variant.
NOISE_MAX_ANGLE = 2.0


@functools.cache
def warm_up() -> None:
    """One untimed call on a small exact and a small noisy trial, once a process.

    The first ``register`` of a process compiles gatv's kernels (a minute or
    more) or loads them from numba's cache; without this, the first trial of
    a table carries that time, on the clean clone the most of all.
    """
    import numpy as np

    from gatv.registration import register

    for noise in (0.0, 0.01):
        trial = table2_trial(0.5, noise=noise, seed=np.random.SeedSequence([12345, 1]))
        register(trial.source, trial.target, seed=0)


def maximum_likelihood(trial, sigma: float):
    """The maximum-likelihood pose and pairs, started at the true pose with the true noise ``sigma``.

    What the data allow, not a method: the soft-assignment EM of
    :func:`gatv.stages.weighted_pose` (the likelihood of a Gaussian mixture
    with a uniform outlier term, the rigid EM of Coherent Point Drift within
    the final gate) from the true motion, then the one-to-one nearest pairs
    within :data:`gatv.stages.FINAL_GATE` ``sigma``, as ``register`` reports
    them.  A trial this estimator fails is beyond any search's reach.
    Returns ``(rotation, pairs)``.
    """
    import numpy as np

    from gatv import stages
    from gatv.models.base import homogeneous, split_matrix

    P = stages.prepare(trial.source, trial.target)
    start = stages.Fit(homogeneous(trial.rotation, trial.translation), np.empty((0, 2), np.int64))
    fit = stages.regate(P, start, stages.FINAL_GATE * sigma)
    fit = stages.weighted_pose(P, fit, sigma)
    fit = stages.regate(P, fit, stages.FINAL_GATE * sigma)
    return split_matrix(fit.matrix)[0], fit.correspondences


def noise_trial(task: tuple) -> dict:
    """One call of ``gatv.register`` on a noisy Table-2 trial ``(f, noise, seed, k)``, scored."""
    import time

    import numpy as np

    from gatv import stages
    from gatv.datasets import correspondence_stats, paper_success, rotation_error_deg
    from gatv.models.base import homogeneous
    from gatv.registration import count_alpha, count_ceiling, register

    warm_up()
    f, noise, seed, k = task
    trial = table2_trial(f, noise=noise, seed=np.random.SeedSequence([seed, round(1000 * f),
                                                                      round(10000 * noise), k]))
    centred = trial.source[trial.true_pairs[:, 0]]
    centred = centred - centred.mean(axis=0)
    rms_radius = float(np.sqrt(np.mean(np.sum(centred**2, axis=1))))  # of the noisy inliers: ~0.1% high
    start, cpu = time.perf_counter(), time.process_time()
    m = register(trial.source, trial.target, seed=k)
    seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
    precision, recall = correspondence_stats(m.correspondences, trial.true_pairs)
    angle = rotation_error_deg(m.rotation, trial.rotation) if m else float("nan")
    ok = bool(m) and paper_success(m.correspondences, trial.true_pairs) and angle < NOISE_MAX_ANGLE
    sigma = noise * rms_radius
    estimate = m.info.get("noise") if m else None
    ml_ok = count_ok = lr_ok = 0
    truth_alpha = float("nan")
    if sigma > 0:
        ml_rotation, ml_pairs = maximum_likelihood(trial, sigma)
        ml_ok = int(paper_success(ml_pairs, trial.true_pairs)
                    and rotation_error_deg(ml_rotation, trial.rotation) < NOISE_MAX_ANGLE)
        P = stages.prepare(trial.source, trial.target)
        truth = homogeneous(trial.rotation, trial.translation)
        count_ok = int(count_ceiling(P, truth))
        lr_ok = int(count_ok or count_ceiling(P, truth, likelihood=True))
        truth_alpha = count_alpha(P, truth)
    return {"f": f, "noise": noise, "trial": k, "success": int(ok), "ml_success": ml_ok, "count_ceiling": count_ok,
            "lr_ceiling": lr_ok, "count_alpha": truth_alpha,
            "precision": precision, "recall": recall,
            "rotation_error_deg": angle, "time_s": seconds, "cpu_s": cpu,
            "noise_ratio": (estimate / sigma) if (estimate is not None and sigma > 0) else float("nan"),
            "pipeline": m.info.get("pipeline", ""), "reason": m.info.get("reason", "") if not m else ""}


def ml_alpha(alphas, ml_pct: float, points: float = 5.0) -> float:
    """The smallest level at which the count test keeps the true pose in ``ml_pct − points`` % of the trials.

    ``alphas``: each trial's :func:`gatv.registration.count_alpha`.  0 when
    that share is none.

    >>> ml_alpha([1e-9, 1e-3, 0.5, 40.0], 80.0)
    0.5
    >>> ml_alpha([1e-9, 1e-3], 5.0)
    0.0
    """
    import math

    import numpy as np

    ordered = np.sort(np.asarray(alphas, dtype=float))
    need = math.ceil(round(max(0.0, ml_pct - points) / 100.0 * ordered.size, 9))
    return 0.0 if need == 0 else float(ordered[need - 1])


def noise_table(args) -> int:
    """The noisy variant: success and time per (f, noise) cell."""
    import numpy as np

    fractions = args.fractions or list(NOISE_FRACTIONS)
    tasks = [(f, nz, args.seed, k) for f in fractions for nz in args.noise for k in range(args.trials)]
    print(f"running {len(tasks)} calls ({args.trials} per cell)...", file=sys.stderr, flush=True)
    rows = map_trials(noise_trial, tasks, scheduler=args.scheduler)
    headers = ["f", "noise (% of RMS radius)", "success %", "ML %", "count ceiling %", "LR ceiling %",
               "count α for ML − 5", "median time (s)",
               "max time (s)",
               "median CPU (s)", "max CPU (s)", "median noise estimate / truth", "median recall",
               "failures' reason"]
    table, csv_rows = [], []
    for f in fractions:
        for nz in args.noise:
            cell = [r for r in rows if r["f"] == f and r["noise"] == nz]
            times = [r["time_s"] for r in cell]
            reasons = sorted({r["reason"] for r in cell if r["reason"]})
            success = 100.0 * np.mean([r["success"] for r in cell])
            ml = 100.0 * np.mean([r["ml_success"] for r in cell]) if nz > 0 else float("nan")
            ceiling = 100.0 * np.mean([r["count_ceiling"] for r in cell]) if nz > 0 else float("nan")
            lr_ceiling = 100.0 * np.mean([r["lr_ceiling"] for r in cell]) if nz > 0 else float("nan")
            alpha_needed = ml_alpha([r["count_alpha"] for r in cell], ml) if nz > 0 else float("nan")
            cpus = [r["cpu_s"] for r in cell]
            table.append([f"{f:.2f}", f"{100 * nz:g}", f"{success:.0f}", "—" if nz == 0 else f"{ml:.0f}",
                          "—" if nz == 0 else f"{ceiling:.0f}", "—" if nz == 0 else f"{lr_ceiling:.0f}",
                          "—" if nz == 0 else f"{alpha_needed:.2g}", fmt(median(times), 2),
                          fmt(max(times), 2), fmt(median(cpus), 2), fmt(max(cpus), 2),
                          fmt(median(r["noise_ratio"] for r in cell), 2),
                          fmt(median(r["recall"] for r in cell), 2), "; ".join(reasons)[:60] or "—"])
            csv_rows.append([f, nz, len(cell), success, ml, ceiling, lr_ceiling, alpha_needed, median(times),
                             max(times),
                             median(r["noise_ratio"] for r in cell), median(r["recall"] for r in cell)])
    print(f"Table 2 protocol with Gaussian noise on the inliers: {args.trials} trials per cell, seed "
          f"{args.seed}; success = at least half the true pairs and rotation error < {NOISE_MAX_ANGLE:g} deg; "
          "no noise= given; ML %: the maximum-likelihood pose from the true pose at the true noise, "
          "scored the same way (what the data allow); count ceiling %: the true pose, refined at some "
          "level's gate, beats the search's final chance level there (what a search that keeps no wrong "
          "motion could keep, `gatv.registration.count_ceiling`); LR ceiling %: the same with the "
          "likelihood-ratio test beside the count (`count_ceiling(..., likelihood=True)`); count α for "
          "ML − 5: the family-wise level (gatv's is `gatv.stats.ALPHA` = "
          f"{ALPHA:g}) at which the count test keeps the true pose in 5 points fewer trials than ML "
          "(`gatv.registration.count_alpha`; above 1 it bounds how many of the search's wrong motions "
          "would be kept with it)\n")
    print(markdown_table(headers, table, align="rrrrrrrrrrrrrl"))
    print("\nCPU: process time of the call (numba's threads added up), a figure the machine's load "
          "changes less than the wall time.")
    out1 = write_csv(args.out / "table2_noise.csv",
                     ["f", "noise", "trials", "success_pct", "ml_success_pct", "count_ceiling_pct", "lr_ceiling_pct",
                      "count_alpha_ml_minus_5", "median_time_s",
                      "max_time_s",
                      "median_noise_ratio", "median_recall"], csv_rows)
    keys = list(rows[0]) if rows else []
    out2 = write_csv(args.out / "table2_noise_trials.csv", keys, [[r[k] for k in keys] for r in rows])
    print(f"\nwrote {out1}, {out2}")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_common_arguments(parser, trials=20)
    add_scheduler_argument(parser)
    parser.add_argument("--no-plot", action="store_true", help="do not write table2.png")
    parser.add_argument("--noise", type=parse_list(float), default=None, metavar="S,S,...",
                        help="run the noisy variant at these noise levels (shares of the inlier RMS radius)")
    args = parser.parse_args(argv)
    if args.noise is not None:
        if any(not (0.0 <= nz < 1.0) for nz in args.noise):
            parser.error(f"--noise takes shares in [0, 1) of the RMS radius, got {args.noise}")
        return noise_table(args)
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

    # Every method warmed up the same way before the timed table: gatv's kernels compiled (or
    # loaded from numba's cache) by warm_up, each method's first call made once, untimed.
    if "gatv" in names:
        warm_up()
    warm = table2_trial(0.5, seed=trial_seed(args.seed + 1, 0.5, 0))
    for name in names:
        methods[name](warm.source, warm.target, 0)

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
