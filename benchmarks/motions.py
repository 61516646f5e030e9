"""Several overlapping rigid motions (paper section 5, Fig. 12): gatv.motions.segment.

Rows (20 trials each, ``--trials``):

* ``fig12``: the paper's Fig. 12 scene — three overlapping motions with
  different axes, angles and translations, 40 points each in a 10×10×10
  cube (fixed motions, new points every trial).
* ``K=k f=F``: ``k`` = 2..5 motions of 30–60 points each (random axis,
  angle 10–180°, translation in [−5, 5]³), plus uniform outliers making
  ``F`` = 0, 50 or 75% of each set.
* ``shared axis+t``: two motions with the same axis and translation,
  angles at least 20° apart (0 and 50% outliers).
* ``shared axis``: two motions with the same axis only.

All scenes are noise-free: with noise the congruent-triple stage needs far
more work per triple (many congruent matches, each scored), which this
benchmark does not cover.

Methods: ``graph`` (:func:`gatv.motions.segment`, default), ``greedy``
(``segment(grouping="greedy")``) and ``ransac`` (sequential RANSAC on
three-pair samples of all candidate pairs, :func:`gatv.motions.ransac_segment`).

Metrics: exactly-K rate; per-motion rotation/translation error (found
motions matched to true ones by shared correspondences); correspondence
precision, recall and F1 over all motions (a found pair is right when it
is a true pair of the motion it was matched to); point-label accuracy
over all source and target points (outliers must stay ``-1``); median time.

Usage::

    python benchmarks/motions.py [--trials 20] [--seed 0] [--rows fig12,K=2,...]
                                 [--methods graph,greedy,ransac] [--out benchmarks/results]

Prints a markdown table; writes ``motions.csv`` and ``motions_trials.csv``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import DEFAULT_OUT, Timer, fmt, markdown_table, median, parse_list, write_csv  # noqa: E402
from scipy.optimize import linear_sum_assignment  # noqa: E402

from gatv.datasets import rotation_error_deg, translation_error  # noqa: E402
from gatv.ga import Rotor  # noqa: E402
from gatv.motions import fig12_scene, multi_motion_scene, ransac_segment, segment  # noqa: E402


def _random_axis(rng):
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _random_motions(rng, k):
    rots = [Rotor.from_axis_angle(_random_axis(rng), np.radians(rng.uniform(10, 180))).as_matrix()
            for _ in range(k)]
    return rots, rng.uniform(-5, 5, size=(k, 3))


def _outliers(n_in, f):
    return int(round(n_in * f / (1.0 - f))) if f > 0 else 0


def make_rows():
    """Row name → ``scene(rng)``."""
    rows = {"fig12": lambda rng: fig12_scene(seed=rng)}
    for k in (2, 3, 4, 5):
        for f in (0.0, 0.5, 0.75):
            def scene(rng, k=k, f=f):
                rots, ts = _random_motions(rng, k)
                sizes = rng.integers(30, 61, k)
                return multi_motion_scene(rots, ts, sizes, n_outliers=_outliers(sizes.sum(), f), seed=rng)
            rows[f"K={k} f={int(100 * f)}%"] = scene
    for f in (0.0, 0.5):
        def shared_both(rng, f=f):
            a = _random_axis(rng)
            th1 = rng.uniform(10, 150)
            th2 = th1 + rng.uniform(20, 180 - th1 + 10)
            rots = [Rotor.from_axis_angle(a, np.radians(th)).as_matrix() for th in (th1, th2)]
            t = rng.uniform(-5, 5, 3)
            sizes = rng.integers(30, 61, 2)
            return multi_motion_scene(rots, [t, t], sizes, n_outliers=_outliers(sizes.sum(), f), seed=rng)

        def shared_axis(rng, f=f):
            a = _random_axis(rng)
            rots = [Rotor.from_axis_angle(a, np.radians(rng.uniform(10, 180))).as_matrix() for _ in range(2)]
            ts = rng.uniform(-5, 5, (2, 3))
            sizes = rng.integers(30, 61, 2)
            return multi_motion_scene(rots, ts, sizes, n_outliers=_outliers(sizes.sum(), f), seed=rng)
        rows[f"shared axis+t f={int(100 * f)}%"] = shared_both
        rows[f"shared axis f={int(100 * f)}%"] = shared_axis

    return rows


METHODS = {
    "graph": lambda s, t: segment(s, t),
    "greedy": lambda s, t: segment(s, t, grouping="greedy"),
    "ransac": lambda s, t: ransac_segment(s, t),
}


def score(scene, seg) -> dict:
    """Compare a segmentation with the truth of a scene."""
    K = scene.n_motions
    found = list(seg.motions)
    true_sets = [set(map(tuple, p.tolist())) for p in scene.true_pairs]
    found_sets = [set(map(tuple, m.correspondences.tolist())) for m in found]
    # match found motions to true motions by shared correspondences
    match = {}
    if found:
        overlap = np.array([[len(fs & ts) for ts in true_sets] for fs in found_sets])
        r, c = linear_sum_assignment(-overlap)
        match = {int(a): int(b) for a, b in zip(r, c) if overlap[a, b] > 0}
    hits = sum(len(found_sets[a] & true_sets[b]) for a, b in match.items())
    n_found = sum(len(s) for s in found_sets)
    n_true = sum(len(s) for s in true_sets)
    precision = hits / n_found if n_found else 0.0
    recall = hits / n_true if n_true else 1.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    rot_err = [rotation_error_deg(found[a].rotation, scene.rotations[b]) for a, b in match.items()]
    tr_err = [translation_error(found[a].translation, scene.translations[b]) for a, b in match.items()]
    remap = np.full(len(found) + 1, -1)
    for a, b in match.items():
        remap[a] = b
    lab_s = remap[seg.source_labels]
    lab_t = remap[seg.target_labels]
    acc = float(np.mean(np.concatenate([lab_s == scene.source_labels, lab_t == scene.target_labels])))
    return {
        "exact_k": len(found) == K, "n_found": len(found), "precision": precision, "recall": recall,
        "f1": f1, "rot_err_deg": max(rot_err) if rot_err else float("nan"),
        "trans_err": max(tr_err) if tr_err else float("nan"), "label_acc": acc,
    }


def run(args) -> list[dict]:
    rows = make_rows()
    names = args.rows or list(rows)
    unknown = [n for n in names if n not in rows]
    if unknown:
        raise SystemExit(f"unknown rows {unknown}; choose from {list(rows)}")
    records = []
    for ri, name in enumerate(names):
        for trial in range(args.trials):
            seq = np.random.SeedSequence([args.seed, list(rows).index(name), trial])
            scene = rows[name](np.random.default_rng(seq))
            for method in args.methods:
                with Timer() as timer:
                    try:
                        seg = METHODS[method](scene.source, scene.target)
                        error = ""
                    except Exception as exc:  # scored as a failure
                        seg, error = None, f"{type(exc).__name__}: {exc}"
                rec = {"row": name, "method": method, "trial": trial, "K": scene.n_motions,
                       "n_points": len(scene.source), "time_s": timer.seconds, "error": error}
                if seg is None:
                    rec.update(exact_k=False, n_found=0, precision=0.0, recall=0.0, f1=0.0,
                               rot_err_deg=float("nan"), trans_err=float("nan"), label_acc=0.0)
                else:
                    rec.update(score(scene, seg))
                records.append(rec)
            print(f"  {name} trial {trial}: " + ", ".join(
                f"{r['method']} {r['n_found']}/{r['K']} F1 {r['f1']:.3f} {r['time_s']:.2f}s"
                for r in records[-len(args.methods):]), file=sys.stderr, flush=True)
    return records


def summarise(records, names, methods):
    out = []
    for name in names:
        for method in methods:
            rs = [r for r in records if r["row"] == name and r["method"] == method]
            if not rs:
                continue
            out.append({
                "row": name, "method": method, "trials": len(rs), "K": rs[0]["K"],
                "points": int(median(r["n_points"] for r in rs)),
                "exact_k_pct": 100.0 * np.mean([r["exact_k"] for r in rs]),
                "rot_err_deg": median(r["rot_err_deg"] for r in rs),
                "trans_err": median(r["trans_err"] for r in rs),
                "precision": float(np.mean([r["precision"] for r in rs])),
                "recall": float(np.mean([r["recall"] for r in rs])),
                "f1": float(np.mean([r["f1"] for r in rs])),
                "label_acc": float(np.mean([r["label_acc"] for r in rs])),
                "time_s": median(r["time_s"] for r in rs),
                "errors": sum(bool(r["error"]) for r in rs),
            })
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--rows", type=parse_list(str), default=None, metavar="R,R,...")
    parser.add_argument("--methods", type=parse_list(str), default=list(METHODS), metavar="M,M,...")
    args = parser.parse_args(argv)
    bad = [m for m in args.methods if m not in METHODS]
    if bad:
        parser.error(f"unknown methods {bad}; choose from {list(METHODS)}")
    records = run(args)
    names = list(dict.fromkeys(r["row"] for r in records))
    summary = summarise(records, names, args.methods)
    headers = ["row", "method", "K", "points", "exact K %", "rot err (deg)", "t err", "precision",
               "recall", "F1", "label acc", "median s"]
    table = [[s["row"], s["method"], s["K"], s["points"], fmt(s["exact_k_pct"], 0) if s["exact_k_pct"] % 1
              else str(int(s["exact_k_pct"])), fmt(s["rot_err_deg"], 2), fmt(s["trans_err"], 2),
              fmt(s["precision"]), fmt(s["recall"]), fmt(s["f1"]), fmt(s["label_acc"]), fmt(s["time_s"], 2)]
             for s in summary]
    print(markdown_table(headers, table, align="ll" + "r" * (len(headers) - 2)))
    print("\nrot/t err: median over trials of the worst matched motion; precision, recall, F1, label acc: "
          "mean over trials.")
    keys = list(summary[0]) if summary else []
    write_csv(args.out / "motions.csv", keys, [[s[k] for k in keys] for s in summary])
    tkeys = list(records[0]) if records else []
    write_csv(args.out / "motions_trials.csv", tkeys, [[r[k] for k in tkeys] for r in records])
    print(f"\nwrote {args.out / 'motions.csv'} and {args.out / 'motions_trials.csv'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
