"""Catadioptric corner matching on the unit sphere (paper section 5.1, Fig. 15).

Synthetic rows: two views of a room (:func:`catadioptric.synthetic_views`),
mirror parameter xi in {0.8, 1.0}, rotation 30 or 90 degrees about a random
axis, translation 0, 10% or 20% of the median scene depth in a random
direction, 1 px corner noise, 0% and 50% outlier corners in each view.

Each synthetic row runs for every strategy of ``--strategies`` (default
``auto``, the default matcher, and ``voting``, the paper's tensor-voting
surface with the local eq. 41).

Real rows (skipped when the shared data are absent): the para-catadioptric
images of ``omni_mei_paracatadioptric``, 9 consecutive pairs, each a real
two-motion scene (static corridor, hand-moved checkerboard).
``board`` rows match the 48 provided board corners (view 2's rows
permuted); ``detected`` rows match the corners of
:func:`catadioptric.detect_corners`, where the corridor's truth is the
identity (same pixel within 1.5 px, away from the board in both images)
and the board's truth the provided corners' index (detected corners
within 2 px of one). The 9x7-square board is symmetric under a half-turn
and OpenCV's corner order may be turned in some images (data README), so
a board pair is scored both in the ground truth's labelling
(``board_correct_gt``) and turned (``board_correct_halfturn``);
``board_precision`` and ``board_recall`` use the better of the two, out
of the board pairs found and of the board truth. ``corridor_precision``:
of the found pairs with an end in the corridor's truth, the share in it.
``t_dir_err_deg``: median angle between the recovered translation
direction and the true one (synthetic rows).

Trials run through ``benchmarks/_common.map_trials``: serially, or as
Dask tasks with ``--scheduler``.

Run: ``python benchmarks/catadioptric.py [--trials 2]``; writes
``results/catadioptric.csv``, ``results/catadioptric_real.csv``,
``results/catadioptric.md`` and a picture
``results/catadioptric_real_001_002.png``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from _common import DEFAULT_OUT, add_scheduler_argument, map_trials, markdown_table, write_csv

# This script's name shadows the `catadioptric` package when run as a
# script (its folder comes first on sys.path): import the package without it.
_HERE = str(Path(__file__).resolve().parent)
sys.path[:] = [p for p in sys.path if str(Path(p or ".").resolve()) != _HERE]
sys.modules.pop("catadioptric", None)
from catadioptric import UnifiedCamera, detect_corners, match, read_image, synthetic_views  # noqa: E402
from gatv.datasets import correspondence_stats  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
MEI = DATA / "omni_mei_paracatadioptric"
HEADERS = ["case", "xi", "rotation_deg", "translation_pct_depth", "outliers", "n_true", "found",
           "precision", "recall", "board_recall", "t_dir_err_deg", "strategy", "time_s"]
REAL_HEADERS = ["pair", "corners", "motions", "found", "corridor_found", "corridor_precision",
                "board_truth", "board_found", "board_correct_gt", "board_correct_halfturn",
                "board_precision", "board_recall", "strategies", "time_s"]


def _synthetic_trial(task):
    """One synthetic trial (module level, picklable for ``map_trials``)."""
    xi, rot, tpct, out, k, seed, strategy = task
    rng = np.random.default_rng([seed, int(xi * 10), int(rot), int(tpct), int(out * 10), k])
    probe = synthetic_views(200, xi=xi, rotation_deg=0.0, translation=(0, 0, 0),
                            noise_px=0.0, seed=int(rng.integers(2**31)))
    depth = float(np.median(np.linalg.norm(probe.points, axis=1)))
    d = rng.normal(size=3)
    t = tpct / 100.0 * depth * d / np.linalg.norm(d)
    v = synthetic_views(200, xi=xi, rotation_deg=rot, translation=t, noise_px=1.0,
                        outlier_fraction=out, seed=int(rng.integers(2**31)))
    t0 = time.perf_counter()
    m = match(v.pixels1, v.pixels2, v.camera1, noise_px=1.0, strategy=strategy)
    dt = time.perf_counter() - t0
    p, r = correspondence_stats(m.correspondences, v.pairs)
    terr = None
    if tpct > 0 and m.translation is not None:
        c = float(m.translation @ t) / float(np.linalg.norm(t))
        terr = float(np.degrees(np.arccos(min(1.0, max(-1.0, c)))))
    return {"p": p, "r": r, "found": m.support, "true": len(v.pairs), "strategy": m.strategy,
            "terr": terr, "time": dt}


def _synthetic(trials: int, seed: int, strategies=("auto", "voting"), scheduler=None):
    keys = [(xi, rot, tpct, out, strategy)
            for strategy in strategies for xi in (0.8, 1.0) for rot in (30.0, 90.0)
            for tpct in (0.0, 10.0, 20.0) for out in (0.0, 0.5)]
    tasks = [(xi, rot, tpct, out, k, seed, strategy) for xi, rot, tpct, out, strategy in keys
             for k in range(trials)]
    results = map_trials(_synthetic_trial, tasks, scheduler=scheduler)
    rows = []
    for n, (xi, rot, tpct, out, strategy) in enumerate(keys):
        res = results[n * trials:(n + 1) * trials]
        terr = [x["terr"] for x in res if x["terr"] is not None]
        rows.append([f"synthetic {strategy}", xi, rot, tpct, out, np.mean([x["true"] for x in res]),
                     np.mean([x["found"] for x in res]), np.mean([x["p"] for x in res]),
                     np.mean([x["r"] for x in res]), "", np.median(terr) if terr else "",
                     "/".join(sorted({x["strategy"] for x in res})), np.median([x["time"] for x in res])])
        print(*map(_fmt, rows[-1]), flush=True)
    return rows


def _board(i: int):
    return np.loadtxt(MEI / "corners" / f"img_para_{i:03d}_corners_px.txt")


def _detected_truth(d1, d2, b1, b2):
    """Ground-truth pairs and the rows they cover, for detected corners."""
    from scipy.spatial import cKDTree

    near1 = cKDTree(b1).query(d1)[0]
    near2 = cKDTree(b2).query(d2)[0]
    # a corner near the board in either image is not background
    area1 = (near1 < 40.0) | (cKDTree(b2).query(d1)[0] < 40.0)
    area2 = (near2 < 40.0) | (cKDTree(b1).query(d2)[0] < 40.0)
    bg1, bg2 = np.flatnonzero(~area1), np.flatnonzero(~area2)
    dist, j = cKDTree(d2[bg2]).query(d1[bg1], distance_upper_bound=1.5)
    ok = np.isfinite(dist)
    bg = np.column_stack([bg1[ok], bg2[j[ok]]])
    _, k1 = cKDTree(b1).query(d1)
    _, k2 = cKDTree(b2).query(d2)
    on1 = np.flatnonzero(near1 < 2.0)
    on2 = {int(k2[r]): r for r in np.flatnonzero(near2 < 2.0)}
    board = np.array([[r, on2[int(k1[r])]] for r in on1 if int(k1[r]) in on2], dtype=np.int64).reshape(-1, 2)
    return bg, board


def _halfturn(k):
    """Index of a provided corner after a half-turn of the symmetric 9x7 board (8x6 inner corners)."""
    return 47 - k


def _real_board_trial(task):
    """The 48 provided board corners of images ``i`` and ``j`` (rows of view 2 permuted)."""
    i, j = task
    cam = UnifiedCamera.from_json(MEI / "calibration_mei_opencv.json")
    b1, b2 = _board(i), _board(j)
    perm = np.random.default_rng(i).permutation(48)
    t0 = time.perf_counter()
    m = match(b1, b2[perm], cam, noise_px=1.0)
    dt = time.perf_counter() - t0
    c = m.correspondences
    k1, k2 = c[:, 0], perm[c[:, 1]]
    gt = int(np.count_nonzero(k1 == k2))
    ht = int(np.count_nonzero(_halfturn(k1) == k2))
    best = max(gt, ht)
    return [f"board {i:03d}-{j:03d}", "48 / 48", len(m.motions), m.support, 0, "", 48, m.support, gt, ht,
            best / m.support if m.support else 0.0, best / 48.0,
            "/".join(mm.strategy for mm in m.motions) or "none", dt]


def _real_detected_trial(task):
    """Detected corners of images ``i`` and ``j``: both motions scored against the ground truth."""
    from scipy.spatial import cKDTree

    i, j = task
    cam = UnifiedCamera.from_json(MEI / "calibration_mei_opencv.json")
    img1 = read_image(MEI / "images" / f"img_para_{i:03d}.png")
    img2 = read_image(MEI / "images" / f"img_para_{j:03d}.png")
    d1 = detect_corners(img1, max_corners=400)
    d2 = detect_corners(img2, max_corners=400)
    _, ok1 = cam.lift(d1, return_mask=True)
    _, ok2 = cam.lift(d2, return_mask=True)
    d1, d2 = d1[ok1], d2[ok2]
    t0 = time.perf_counter()
    m = match(d1, d2, cam, noise_px=1.0)
    dt = time.perf_counter() - t0
    b1, b2 = _board(i), _board(j)
    bg, board = _detected_truth(d1, d2, b1, b2)
    c = m.correspondences
    # corridor: found pairs with an end among the static truth's rows
    bgset = set(map(tuple, bg.tolist()))
    in1, in2 = set(bg[:, 0].tolist()), set(bg[:, 1].tolist())
    judged = [tuple(p) for p in c.tolist() if p[0] in in1 or p[1] in in2]
    corr_p = sum(p in bgset for p in judged) / len(judged) if judged else float("nan")
    # board: found pairs with both ends on a provided corner (within 2 px)
    n1, k1 = cKDTree(b1).query(d1)
    n2, k2 = cKDTree(b2).query(d2)
    onb = (n1[c[:, 0]] < 2.0) & (n2[c[:, 1]] < 2.0) if len(c) else np.zeros(0, bool)
    ka, kb = k1[c[onb, 0]], k2[c[onb, 1]]
    gt = int(np.count_nonzero(ka == kb))
    ht = int(np.count_nonzero(_halfturn(ka) == kb))
    best = max(gt, ht)
    nb = int(onb.sum())
    if (i, j) == (1, 2):
        from catadioptric.render import render_matches

        render_matches(img1, img2, d1, d2, c, DEFAULT_OUT / "catadioptric_real_001_002.png",
                       title=f"img_para_001 / 002: {m.support} matches, {len(m.motions)} motions")
    return [f"detected {i:03d}-{j:03d}", f"{len(d1)} / {len(d2)}", len(m.motions), m.support, len(judged),
            corr_p, len(board), nb, gt, ht, best / nb if nb else float("nan"),
            best / max(len(board), 1), "/".join(mm.strategy for mm in m.motions) or "none", dt]


def _real(scheduler=None):
    if not MEI.is_dir():
        print(f"real rows skipped: {MEI} absent", flush=True)
        return []
    pairs = [(k, k + 1) for k in range(1, 10)]
    rows = map_trials(_real_board_trial, pairs, scheduler=scheduler)
    rows += map_trials(_real_detected_trial, pairs, scheduler=scheduler)
    for r in rows:
        print(*map(_fmt, r), flush=True)
    return rows


def _fmt(v):
    if isinstance(v, (float, np.floating)):
        return f"{v:.3f}" if abs(v) < 100 else f"{v:.0f}"
    return str(v)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=2, help="trials per synthetic row (default: 2)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--skip-real", action="store_true")
    parser.add_argument("--skip-synthetic", action="store_true")
    parser.add_argument("--strategies", default="auto,voting",
                        help="strategies of the synthetic rows, comma separated (default: auto,voting)")
    add_scheduler_argument(parser)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    strategies = tuple(s.strip() for s in args.strategies.split(",") if s.strip())
    rows = [] if args.skip_synthetic else _synthetic(args.trials, args.seed, strategies, args.scheduler)
    real = [] if args.skip_real else _real(args.scheduler)
    write_csv(args.out / "catadioptric.csv", HEADERS, rows)
    write_csv(args.out / "catadioptric_real.csv", REAL_HEADERS, real)
    table = markdown_table(HEADERS, [[_fmt(v) for v in r] for r in rows])
    rtable = markdown_table(REAL_HEADERS, [[_fmt(v) for v in r] for r in real])
    (args.out / "catadioptric.md").write_text(
        "# Catadioptric corner matching on the unit sphere\n\n"
        f"`python benchmarks/catadioptric.py --trials {args.trials}`; synthetic rows: mean of "
        f"{args.trials} trials (time: median, seconds; t_dir_err_deg: median).\n\n" + table + "\n\n"
        "## Real pairs (omni_mei_paracatadioptric): both motions\n\n" + rtable + "\n", encoding="utf-8")
    print(table)
    print()
    print(rtable)
    return 0


if __name__ == "__main__":
    sys.exit(main())
