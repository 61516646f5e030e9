"""Benchmark of the sparse tensor-voting engine (``gatv.voting``).

Token distribution (fixed seed 0): 10 % of the tokens on a tilted plane
(normal ∝ (1, 2, 3), Gaussian thickness 0.002) through the unit cube, 90 %
uniform noise in the cube.  σ is :func:`gatv.voting.default_sigma` (k = 40),
so a median token has about 40 others within the voting radius 2σ, the radius
where the decay of eq. 44 has fallen to e⁻⁴ (at 250k: σ = 0.0173, median 39,
noise tokens 41.6 on average, plane tokens 129 since they also see the plane's
2-D density; hence the mean of ~50 in the table).

Each size runs in its own subprocess so that its peak resident memory
(``resource.getrusage(RUSAGE_SELF).ru_maxrss``) is its own; the subprocess
first votes on 2 000 tokens to load the numba cache / compile, then times
each stage ``--repeats`` times and reports medians:

* grid      building the neighbour grid (bin + counting sort by cell)
* ball      sparse ball pass (eigen-analysis fused at the end of each votee),
            recording the neighbour lists as ``extract_surfaces`` does
* σ         ``default_sigma(k=40)`` (not part of total; paid when σ is not given)
* eigen     the same eigen-analysis run on its own over the ball tensors
            (for reference; it is *inside* the ball and stick columns)
* stick     sparse stick pass over the recorded neighbour lists, saliency =
            normalised ball surfaceness (fused eigen)
* total     grid + ball + stick (the full pass)
* kdtree    ``cKDTree`` build + ``query_ball_point(r, workers=2,
            return_length=True)`` (once for n ≥ 250k): a lower bound for a cKDTree neighbour
            search, since it returns counts only, no neighbour lists

Usage::

    python benchmarks/voting.py [--sizes 10000,100000,250000,1000000] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import statistics
import subprocess
import sys
import time

import numpy as np


def tokens(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n_plane = n // 10
    normal = np.array([1.0, 2.0, 3.0]) / math.sqrt(14.0)
    a = np.cross(normal, [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    uv = rng.uniform(-0.5, 0.5, (n_plane, 2))
    plane = uv[:, :1] * a + uv[:, 1:] * b + rng.normal(0.0, 0.002, (n_plane, 1)) * normal
    noise = rng.uniform(-0.5, 0.5, (n - n_plane, 3))
    return np.vstack([plane, noise])


def worker(n: int, repeats: int) -> dict:
    from scipy.spatial import cKDTree

    from gatv.voting import default_sigma, vote
    from gatv.voting import _eigen as K
    from gatv.voting._simd import SIMD
    from gatv.voting.api import check_budget, Engine

    warm = tokens(2000, seed=1)  # compile / load the cache
    b = vote(warm)
    vote(warm, b.sigma, b.normals, saliency=b.surfaceness)
    K.eig3_top_batch(b.components.copy(), np.empty((2000, 3)), np.empty((2000, 3)), SIMD)
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss

    pts = tokens(n)
    t0 = time.perf_counter()
    sigma = default_sigma(pts)
    t_sigma = time.perf_counter() - t0

    rows = {k: [] for k in ("grid", "ball", "eigen", "stick", "total", "kdtree")}
    pairs = 0
    for _ in range(repeats):
        t0 = time.perf_counter()
        eng = Engine(pts, sigma, check_budget(pts, sigma, None))
        t1 = time.perf_counter()
        t6, vals, e1, cnt_b = eng.ball(record=True)
        t2 = time.perf_counter()
        w = vals[:, 0] - vals[:, 1]
        w = np.ascontiguousarray(w / w.max())
        t3 = time.perf_counter()
        _, _, _, cnt_s = eng.stick(e1, w)
        t4 = time.perf_counter()
        K.eig3_top_batch(t6, np.empty((n, 3)), np.empty((n, 3)), SIMD)
        t5 = time.perf_counter()
        rows["grid"].append(t1 - t0)
        rows["ball"].append(t2 - t1)
        rows["stick"].append(t4 - t3)
        rows["eigen"].append(t5 - t4)
        rows["total"].append(t4 - t0)
        pairs = int(cnt_b.sum() + cnt_s.sum())
    for _ in range(1 if n >= 250_000 else max(1, min(repeats, 3))):
        t0 = time.perf_counter()
        cKDTree(pts).query_ball_point(pts, 2.0 * sigma, workers=2, return_length=True)
        rows["kdtree"].append(time.perf_counter() - t0)
    med = {k: statistics.median(v) for k, v in rows.items()}
    med.update(
        n=n,
        sigma=sigma,
        t_sigma=t_sigma,
        neighbours=float(cnt_b.mean() - 1.0),
        votes_per_s=pairs / med["total"],
        peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        base_rss_mb=base_rss / 1024.0,
    )
    return med


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="10000,100000,250000,1000000")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--worker", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.worker, args.repeats)))
        return
    sizes = [int(float(s)) for s in args.sizes.split(",")]
    print(f"numba threads: {__import__('numba').get_num_threads()}, repeats: {args.repeats} (medians)\n")
    print("| tokens | mean nbrs | σ (s) | grid (s) | ball (s) | eigen* (s) | stick (s) | **total (s)** "
          "| votes/s | cKDTree nbrs (s) | peak RSS (MB) |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for n in sizes:
        out = subprocess.run([sys.executable, __file__, "--worker", str(n), "--repeats", str(args.repeats)],
                             capture_output=True, text=True, check=True)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"| {n:,} | {r['neighbours']:.1f} | {r['t_sigma']:.3f} | {r['grid']:.3f} | {r['ball']:.3f} "
              f"| {r['eigen']:.3f} | {r['stick']:.3f} | **{r['total']:.3f}** | {r['votes_per_s']:.3g} "
              f"| {r['kdtree']:.3f} | {r['peak_rss_mb']:.0f} (base {r['base_rss_mb']:.0f}) |", flush=True)
    print("\n*eigen: the eigen-analysis alone over the ball tensors; in the pipeline it is fused into the "
          "ball and stick passes, so total = grid + ball + stick.")


if __name__ == "__main__":
    main()
