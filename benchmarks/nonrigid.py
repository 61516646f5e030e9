"""Non-rigid registration: gatv.nonrigid vs the rigid mode vs Coherent Point Drift.

Cases (each with 0% and 50% outliers added to both sets, uniform in each
set's bounding box, shuffled):

* a 10 × 10 plane sampled with 400 points (jittered grid), twisted by 30°,
  60° and 90° over its length (the paper's Fig. 13);
* the plane bent by 90° around a cylinder (a 3D *curve* in the joint space);
* the plane with smooth random elastic warps (6 Gaussian bumps) of growing
  amplitude;
* the plane folded about a hinge (piecewise rigid);
* the real face expressions of ``shared/data/nonrigid_bcpd_face`` (x → y and
  x → g.y), the same ``--face-points`` rows drawn from both (exact row
  correspondence); skipped when the data is absent.

Methods on the same inputs: ``gatv.nonrigid.register`` (defaults),
``gatv.register`` (the rigid mode, ``max_triples=5000`` to bound its time;
its warp is its rigid motion), and non-rigid CPD (``pycpd``
``DeformableRegistration``, w = the true outlier fraction, 150 iterations;
its correspondences are the pairs whose posterior exceeds 0.5, made
one-to-one).  Reported: correspondence precision and recall, mean warp error
of the source inliers against their true positions, median time.

Precision and recall (:func:`gatv.datasets.correspondence_stats`) count a
found pair as correct only when it is *exactly* a true ``(source index,
target index)`` pair — no distance tolerance, for every method and every row.
On the face rows the truth is the row correspondence of the data set (row
``i`` of ``face-x`` ↔ row ``i`` of ``face-y``), so a pair with a neighbouring
target row counts as wrong even when it is within a millimetre; at 600 rows
the point spacing (~4.5 mm) is about the median non-rigid displacement
(~3.8 mm), so nearest-neighbour matching alone is ~65% correct.  A method
that reports nothing has precision 0.  ``--trials`` draws new planes,
warps, outliers and face rows per trial; the table gives medians.

Usage::

    python benchmarks/nonrigid.py [--trials 1] [--seed 0] [--out benchmarks/results]
                                  [--methods gatv-nonrigid,gatv-rigid,cpd] [--fractions 0,0.5]
                                  [--cases twist,face] [--face-points 600]

writes ``nonrigid.csv`` (every trial) and ``nonrigid.md`` (the table) to ``--out``.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import Timer, add_common_arguments, fmt, markdown_table, median, trial_seed, write_csv  # noqa: E402

from gatv.datasets import correspondence_stats  # noqa: E402
from gatv.nonrigid import deformations as deform  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "nonrigid_bcpd_face"
METHODS = ("gatv-nonrigid", "gatv-rigid", "cpd")


def _plane(seed):
    return deform.sample_plane(400, 10.0, seed=seed)


def synthetic_cases():
    yield "twist 30°", lambda x, rng: deform.twist(x, 30.0)
    yield "twist 60°", lambda x, rng: deform.twist(x, 60.0)
    yield "twist 90°", lambda x, rng: deform.twist(x, 90.0)
    yield "bend 90° (curve)", lambda x, rng: deform.bend(x, 90.0)
    for amp in (0.5, 1.0, 2.0):
        yield f"elastic {amp:g}", lambda x, rng, amp=amp: deform.elastic(x, amp, seed=rng)
    yield "hinge 30° (piecewise)", lambda x, rng: deform.piecewise_rigid(x, 30.0)


def face_pairs(n_points):
    """The face expressions as (name, x, y, rows drawn per trial)."""
    if not (DATA / "face-x.txt").is_file():
        return []
    x = np.loadtxt(DATA / "face-x.txt")
    out = []
    for name in ("face-y.txt", "face-g.y.txt"):
        y = np.loadtxt(DATA / name)
        n = min(n_points, len(x))
        out.append((f"face x→{name[5:-4]} ({n} pts)", x, y, n))
    return out


# ------------------------------------------------------------------ methods
def run_nonrigid(src, tgt, f):
    from gatv.nonrigid import register

    m = register(src, tgt)
    return m.correspondences, m.warp


def run_rigid(src, tgt, f):
    from gatv import register

    m = register(src, tgt, max_triples=5000)
    return m.correspondences, m.transform


def run_cpd(src, tgt, f):
    from pycpd import DeformableRegistration

    reg = DeformableRegistration(X=np.asarray(tgt), Y=np.asarray(src), w=min(f, 0.99), max_iterations=150)
    TY, _ = reg.register()
    P = reg.P  # (M source, N target) posteriors
    j = np.argmax(P, axis=1)
    p = P[np.arange(len(j)), j]
    cand = np.flatnonzero(p > 0.5)
    pairs = np.stack([cand, j[cand]], axis=1)
    from gatv.candidates import one_to_one

    pairs = pairs[one_to_one(pairs, -p[cand])] if len(pairs) else np.empty((0, 2), np.int64)
    def warp(pts):  # CPD's motion field v(z) = G(z, Y) W at any point
        pts = np.asarray(pts, dtype=float)
        d2 = ((pts[:, None, :] - reg.Y[None]) ** 2).sum(axis=2)
        return pts + np.exp(-d2 / (2.0 * reg.beta**2)) @ reg.W

    return pairs, warp


RUNNERS = {"gatv-nonrigid": run_nonrigid, "gatv-rigid": run_rigid, "cpd": run_cpd}


def evaluate(method, trial, f):
    with Timer() as timer:
        try:
            pairs, warp = RUNNERS[method](trial.source, trial.target, f)
            error = ""
        except Exception as exc:  # a failed run is scored, not fatal
            pairs, warp, error = np.empty((0, 2), np.int64), None, f"{type(exc).__name__}: {exc}"[:160]
    precision, recall = correspondence_stats(pairs, trial.true_pairs)
    werr = trial.warp_error(warp) if warp is not None else float("nan")
    return precision, recall, werr, timer.seconds, error


def _write(args, argv, headers, rows, csv_rows):
    table = markdown_table(headers, rows, "lllrrrrr")
    args.out.mkdir(parents=True, exist_ok=True)
    command = shlex.join(argv if argv is not None else sys.argv[1:])
    (args.out / "nonrigid.md").write_text(
        f"`python benchmarks/nonrigid.py {command}` ({args.trials} trial(s) per row, medians)\n\n{table}\n")
    path = write_csv(args.out / "nonrigid.csv",
                     ["case", "f", "method", "trial", "precision", "recall", "warp_error", "time_s", "error"],
                     csv_rows)
    return table, path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_common_arguments(parser, trials=1)
    parser.add_argument("--face-points", type=int, default=600, help="rows drawn from each face (default: 600)")
    parser.add_argument("--cases", default=None, metavar="TEXT,TEXT,...",
                        help="only the cases whose name contains one of these texts (default: all)")
    args = parser.parse_args(argv)
    fractions = args.fractions if args.fractions is not None else [0.0, 0.5]
    methods = args.methods if args.methods is not None else list(METHODS)
    unknown = set(methods) - set(METHODS)
    if unknown:
        parser.error(f"unknown methods {sorted(unknown)}; choose from {', '.join(METHODS)}")
    if "cpd" in methods:
        try:
            import pycpd  # noqa: F401
        except ImportError:
            print("pycpd is not installed (.venv/bin/pip install pycpd): CPD skipped")
            methods = [m for m in methods if m != "cpd"]

    # warm up numba (not timed)
    from gatv.nonrigid import register

    x = deform.sample_plane(60, seed=0)
    register(x, deform.twist(x, 30.0))

    cases = []
    for name, make in synthetic_cases():
        cases.append((name, make))
    faces = face_pairs(args.face_points)
    if not faces:
        print(f"face data not found in {DATA}: face rows skipped")

    headers = ["case", "outliers", "method", "precision", "recall", "warp error", "time (s)", "errors"]
    rows, csv_rows = [], []
    for f in fractions:
        jobs = [(name, make) for name, make in cases] + [(name, face) for name, *face in faces]
        if args.cases:
            jobs = [(name, make) for name, make in jobs if any(t in name for t in args.cases.split(","))]
        for name, make in jobs:
            results = {m: [] for m in methods}
            for k in range(args.trials):
                rng = np.random.default_rng(trial_seed(args.seed, f, k))
                if isinstance(make, list):  # face rows: the same rows of both sets, drawn per trial
                    x, y, n = make
                    drawn = rng.choice(len(x), size=n, replace=False)
                    points, moved = x[drawn], y[drawn]
                else:
                    points = _plane(rng)
                    moved = make(points, rng)
                trial = deform.nonrigid_trial(points, moved, f, seed=rng)
                for m in methods:
                    r = evaluate(m, trial, f)
                    results[m].append(r)
                    csv_rows.append([name, f, m, k, *r])
            for m in methods:
                res = results[m]
                row = [name, f"{100 * f:.0f}%", m, fmt(median(r[0] for r in res)), fmt(median(r[1] for r in res)),
                       fmt(median(r[2] for r in res), 3), fmt(median(r[3] for r in res), 2),
                       sum(bool(r[4]) for r in res)]
                rows.append(row)
                print(" | ".join(map(str, row)), flush=True)
            _write(args, argv, headers, rows, csv_rows)  # after every row: a cut-short run keeps what it did
    table, path = _write(args, argv, headers, rows, csv_rows)
    print()
    print(table)
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
