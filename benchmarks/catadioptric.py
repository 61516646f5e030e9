"""Catadioptric corner matching on the unit sphere (paper section 5.1, Fig. 15).

Synthetic rows: two views of a room (:func:`catadioptric.synthetic_views`),
mirror parameter xi in {0.8, 1.0}, rotation 30 or 90 degrees about a random
axis, translation 0, 10% or 20% of the median scene depth in a random
direction, 1 px corner noise, 0% and 50% outlier corners in each view.

Real rows (skipped when the shared data are absent): the para-catadioptric
images of ``omni_mei_paracatadioptric``. ``board`` rows match the 48
provided board corners of two images (ground truth: the index; the board
moved, so the rays move non-rigidly, and the grid is regular, which makes
a shifted grid an equally good match for any method without appearance;
:func:`catadioptric.match` then finds a rival with other partners nearly
as strong as its answer and reports nothing, reason "ambiguous (repeated
structure)").
``detected`` rows match the corners of :func:`catadioptric.detect_corners`;
ground truth there is the identity for corners of the static corridor
(same pixel within 1.5 px in both images, away from the board in both)
and the index for detected corners within 2 px of a provided board corner.
Precision counts the found pairs with at least one end in the ground
truth; board recall is reported apart. ``t_dir_err_deg``: median angle
between the recovered translation direction (``SphereMatch.translation``,
epipolar strategy) and the true one, over the trials that recovered one.

Run: ``python benchmarks/catadioptric.py [--trials 2]``; writes
``results/catadioptric.csv``, ``results/catadioptric.md`` and a picture
``results/catadioptric_real_001_002.png``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from _common import DEFAULT_OUT, markdown_table, write_csv

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


def _synthetic(trials: int, seed: int):
    rows = []
    for xi in (0.8, 1.0):
        for rot in (30.0, 90.0):
            for tpct in (0.0, 10.0, 20.0):
                for out in (0.0, 0.5):
                    ps, rs, ts, found, true, strat, terr = [], [], [], [], [], [], []
                    for k in range(trials):
                        rng = np.random.default_rng([seed, int(xi * 10), int(rot), int(tpct), int(out * 10), k])
                        probe = synthetic_views(200, xi=xi, rotation_deg=0.0, translation=(0, 0, 0),
                                                noise_px=0.0, seed=int(rng.integers(2**31)))
                        depth = float(np.median(np.linalg.norm(probe.points, axis=1)))
                        d = rng.normal(size=3)
                        t = tpct / 100.0 * depth * d / np.linalg.norm(d)
                        v = synthetic_views(200, xi=xi, rotation_deg=rot, translation=t, noise_px=1.0,
                                            outlier_fraction=out, seed=int(rng.integers(2**31)))
                        t0 = time.perf_counter()
                        m = match(v.pixels1, v.pixels2, v.camera1, noise_px=1.0)
                        ts.append(time.perf_counter() - t0)
                        p, r = correspondence_stats(m.correspondences, v.pairs)
                        ps.append(p)
                        rs.append(r)
                        found.append(m.support)
                        true.append(len(v.pairs))
                        strat.append(m.strategy)
                        if tpct > 0 and m.translation is not None:
                            c = float(m.translation @ t) / float(np.linalg.norm(t))
                            terr.append(float(np.degrees(np.arccos(min(1.0, max(-1.0, c))))))
                    rows.append(["synthetic", xi, rot, tpct, out, np.mean(true), np.mean(found),
                                 np.mean(ps), np.mean(rs), "", np.median(terr) if terr else "",
                                 "/".join(sorted(set(strat))),
                                 np.median(ts)])
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


def _real(out_dir: Path):
    if not MEI.is_dir():
        print(f"real rows skipped: {MEI} absent", flush=True)
        return []
    cam = UnifiedCamera.from_json(MEI / "calibration_mei_opencv.json")
    rows = []
    pairs = [(k, k + 1) for k in range(1, 10)]
    for i, j in pairs:
        b1, b2 = _board(i), _board(j)
        perm = np.random.default_rng(i).permutation(48)
        t0 = time.perf_counter()
        m = match(b1, b2[perm], cam, noise_px=1.0)
        dt = time.perf_counter() - t0
        truth = np.column_stack([np.arange(48), np.argsort(perm)])
        p, r = correspondence_stats(m.correspondences, truth)
        rows.append([f"real board {i:03d}-{j:03d}", cam.xi, "", "", 0.0, 48, m.support, p, r, r, "",
                     m.strategy, dt])
        print(*map(_fmt, rows[-1]), flush=True)
    for i, j in pairs:
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
        bg, board = _detected_truth(d1, d2, _board(i), _board(j))
        truth = np.vstack([bg, board])
        known1 = np.zeros(len(d1), bool)
        known1[truth[:, 0]] = True
        known2 = np.zeros(len(d2), bool)
        known2[truth[:, 1]] = True
        c = m.correspondences
        judged = c[known1[c[:, 0]] | known2[c[:, 1]]] if len(c) else c
        p, r = correspondence_stats(judged, truth)
        _, rb = correspondence_stats(c, board) if len(board) else (0.0, float("nan"))
        rows.append([f"real detected {i:03d}-{j:03d}", cam.xi, "", "", "", len(truth), m.support, p, r,
                     rb if len(board) else "", "", m.strategy, dt])
        print(*map(_fmt, rows[-1]), f"(board truth {len(board)})", flush=True)
        if (i, j) == (1, 2):
            from catadioptric._render import render_matches

            render_matches(img1, img2, d1, d2, c, out_dir / "catadioptric_real_001_002.png",
                           title=f"img_para_001 / 002: {m.support} matches ({m.strategy})")
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
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = _synthetic(args.trials, args.seed)
    if not args.skip_real:
        rows += _real(args.out)
    write_csv(args.out / "catadioptric.csv", HEADERS, rows)
    table = markdown_table(HEADERS, [[_fmt(v) for v in r] for r in rows])
    (args.out / "catadioptric.md").write_text(
        "# Catadioptric corner matching on the unit sphere\n\n"
        f"`python benchmarks/catadioptric.py --trials {args.trials}`; synthetic rows: mean of "
        f"{args.trials} trials (time: median, seconds; t_dir_err_deg: median).\n\n" + table + "\n", encoding="utf-8")
    print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
