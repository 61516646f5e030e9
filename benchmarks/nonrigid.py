"""Non-rigid registration at real scale: gatv.nonrigid vs Coherent Point Drift, BCPD and FilterReg.

Rows (``--cases`` picks groups by name; ``--fractions`` the outlier shares,
default 0 and 0.5; outliers uniform in each set's bounding box):

* ``face``: the real face expressions of ``shared/data/nonrigid_bcpd_face``,
  all 23,728 rows, x → y and x → g.y, the same rows in both (exact truth);
  and x → y *differently sampled* (each set an independent 80% of the rows).
* ``face-sizes``: the face x → y at 10k, 25k, 100k points per set (``--sizes`` ≥ 10,000), each set
  an independent 80% of rows: a random subset of the 23,728 vertices, or all of them plus points
  drawn on the mesh's triangles with the same barycentric coordinates in both expressions.
* ``twist``: a 10 × 10 plane (jittered grid) twisted by 90° (Fig. 13) at
  2k, 10k, 25k and 100k points per set with the same rows, and at 10k and
  25k differently sampled (independent 80% subsets of 12.5k / 31k points).
* ``elastic``: the plane under a smooth random warp (6 Gaussian bumps,
  amplitude 1), 10k and 100k points, the same rows.
* ``body``: the articulated body of ``shared/data/nonrigid_bcpd_human`` (6,890
  rows, two poses: the arms turn by about 50° at the shoulders), each set an
  independent 80% of the rows (the truth: the rows both share), the target
  as given and turned by a random rotation of 60° and of 180°.
* ``bunny``: ``shared/data/nonrigid_bcpd_bunny`` x → y (rotated about 93°,
  scaled about 0.83, deformed; 8,171 rows) and bunny-x-co → y (the 1,600-point
  outlier blob in the source), with the similarity model as pre-alignment
  (``prealign=True, model="similarity"``); outliers are not added to these; both again with each
  set an independent 80% of the 8,171 rows (the blob stays whole).
* ``bunny-sizes``: the bunny x → y at 10k, 25k, 100k points per set (``--sizes`` ≥ 10,000), each set an
  independent 80% of the rows.  The bcpd bunny's 8,171 rows are the vertices of the Stanford
  ``bun_zipper_res2.ply`` mesh in the same order (a similarity maps one onto the other to 3e-5 of the
  extent; checked to 1e-4 when the rows are built), so its 16,301 triangles (in
  ``shared/data/stanford_bunny_reconstruction``) hold for both bunny-x and bunny-y: the rows are all
  8,171 vertices plus points drawn on the triangles (area-weighted in x, uniform barycentric
  coordinates) with the *same* coordinates in x and y, the deformation interpolated linearly within
  each triangle (the piecewise-linear truth of a smooth warp); then each set an independent 80%.
* ``two-motion``: a twisted plate and a bent bar, side by side, moving
  independently (``gatv.nonrigid.segment``; peers register the whole scene).
* ``two-real`` (not in the default groups): the body and 6,000 rows of the face side by side
  (the face scaled to the body's spacing), each with its own real deformation, each set an
  independent 80%; run it with ``--fractions 0.3`` for the 30% outliers.
* ``small``: the 400-point planes and the 600-row faces of the first
  non-rigid benchmark (twist 30/60/90°, bend, elastic, hinge).

Each row also reports the child's CPU time (``time.process_time``) and the
1-minute load average when it ended: the machine is shared, and wall time
alone drifts with the load.

Methods: ``gatv`` (``gatv.nonrigid.register`` defaults on every row; ``segment``
on the two-motion rows), ``gatv+sim`` (bunny rows only: gatv told the
bunny's per-dataset options, ``prealign=True, model="similarity"``, a row of
its own), ``cpd`` (pycpd ``DeformableRegistration``, 150 iterations), ``lrcpd``
(rustcpd's low-rank deformable CPD: a rank-300 pivoted-Cholesky kernel, 150 iterations,
normalised coordinates),
``bcpd`` (probreg ``registration_bcpd``, 50 iterations), ``filterreg``
(probreg ``registration_filterreg``, rigid, for reference).  Same
information: gatv is told neither the outlier share nor the inliers, so by
default (``--peer-info blind``) the peers get ``w = PEER_W`` (0.1, CPD's
reference default) on every row and their pairing gate from the target as
given; ``--peer-info oracle`` gives them the true share and the true
inliers' spacing, rows labelled "told f".  Same warm-up: each child makes one
untimed call of its method on a small twisted plane first (imports,
compilation, set-up; ``warm_s`` in the notes), then the timed call.

Each method runs in its own child process: its **peak RSS** is that
process's ``ru_maxrss`` (interpreter, imports and the warm-up included,
about 0.2 GB), and a run past ``--timeout`` seconds (warm-up included) is
reported as such.  A peer
whose dense M×N / M×M matrices would exceed ``--peer-memory-gb`` is not run
and is reported "would need X GB"; a peer that is not installed is reported
"not installed" — no row is skipped silently.

Scores (every method, every row):

* **exact P / R**: correspondence precision and recall counting only exact
  ``(source row, target row)`` truth pairs (:func:`gatv.datasets.correspondence_stats`);
  for differently sampled rows the truth is the rows both subsets share.
* **≤1 sp**: share of reported pairs whose target is within one target
  spacing of the source point's true position (pairs with an outlier source
  count as wrong); **R ≤1 sp**: those pairs over the source inliers that
  have a target inlier within half a spacing of their true position (the
  sampling gate: only such a point can be matched).
* **warp err / sp**: mean distance from the moved source inliers to their
  true positions, in target spacings.
* Peers report no correspondences of their own; theirs are the nearest
  target of each moved source point within the sampling gate (half the
  target's median spacing, measured on the target as given), one-to-one —
  the rule gatv applies to its own final matches.

Usage::

    python benchmarks/nonrigid.py [--cases face,twist,elastic,body,bunny,two-motion] [--sizes 2000,10000,25000]
                                  [--methods gatv,cpd,bcpd,filterreg] [--fractions 0,0.5] [--trials 1]
                                  [--timeout 600] [--peer-memory-gb 4] [--scheduler ADDRESS]

writes ``nonrigid.csv`` (every trial) and ``nonrigid.md`` (the table) to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (
    add_common_arguments,
    add_scheduler_argument,
    fmt,
    map_trials,
    markdown_table,
    median,
    parse_list,
    trial_seed,
    write_csv,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
METHODS = ("gatv", "gatv+sim", "cpd", "lrcpd", "bcpd", "filterreg")
#: Methods told something about the data that the others are not, and the rows they run on:
#: ``gatv+sim`` is gatv with the bunny's per-dataset options (``prealign=True,
#: model="similarity"``: the shape is known to be rotated and scaled); ``gatv`` runs the
#: defaults everywhere.
TOLD = {"gatv+sim": ("bunny", "bunny-n")}
#: Outlier share the peers are given (``w``) when they are not told the truth
#: (``--peer-info blind``, the default): CPD's own default in Myronenko's reference
#: code (``opt.outliers = 0.1``), the same for every row, as gatv is told nothing.
PEER_W = 0.1
GROUPS = ("face", "face-sizes", "twist", "elastic", "body", "bunny", "bunny-sizes", "two-motion", "two-real",
          "small")
DEFAULT_GROUPS = ("face", "face-sizes", "twist", "elastic", "body", "bunny", "bunny-sizes", "two-motion")
DEFAULT_SIZES = (2000, 10000, 25000)
PEER_MODULE = {"cpd": "pycpd", "lrcpd": "rustcpd", "bcpd": "probreg", "filterreg": "probreg"}


# ------------------------------------------------------------------ trials
@dataclass(frozen=True)
class Case:
    """One row: how to build its trial (picklable: names and numbers only)."""

    name: str
    kind: str  # "plane", "face", "face-n", "body", "bunny", "bunny-n", "two", "small-plane", "small-face"
    n: int = 0  # points per set (planes) or rows drawn (small faces)
    warp: str = ""  # twist90, elastic, face-y, face-g.y, ...
    sampled: bool = False  # independent 80% subsets
    outliers_ok: bool = True  # outliers are added at f > 0
    turn: float = 0.0  # the target also turned by a random rotation of this many degrees


@dataclass(frozen=True)
class Trial:
    """Inputs with their truth: exact pairs and each source inlier's true position."""

    source: np.ndarray
    target: np.ndarray
    true_pairs: np.ndarray  # exact (source row, target row)
    inliers: np.ndarray  # source rows with a known true position
    true_positions: np.ndarray  # (len(inliers), 3)
    target_inliers: np.ndarray  # target rows that are not outliers
    spacing: float  # target inliers' median spacing
    labels: np.ndarray | None = None  # two-motion rows: motion of each source inlier (0/1)


def _plane_pair(case: Case, rng):
    from gatv.nonrigid import deformations as D

    total = round(case.n / 0.8) if case.sampled else case.n
    x = D.sample_plane(total, 10.0, seed=rng)
    if case.warp == "twist90":
        y = D.twist(x, 90.0)
    elif case.warp == "elastic":
        y = D.elastic(x, 1.0, seed=rng)
    else:
        raise ValueError(case.warp)
    return x, y


def _load(name):
    return np.loadtxt(DATA / name)


def _subsets(x, y, rng, sampled: bool, share: float = 0.8):
    """Same rows in both, or two independent ``share`` subsets; returns x_rows, y_rows."""
    n = x.shape[0]
    if not sampled:
        rows = np.arange(n)
        return rows, rows
    k = round(share * n)
    return np.sort(rng.choice(n, k, replace=False)), np.sort(rng.choice(n, k, replace=False))


def _face_rows(x, y, total: int, rng):
    """``total`` rows of the face pair: a random subset of its 23,728 vertices, or all of them and
    points drawn on its triangles (area-weighted, uniform barycentric coordinates) with the same
    coordinates in both expressions, the deformation interpolated linearly within each triangle."""
    n = x.shape[0]
    if total <= n:
        rows = np.sort(rng.choice(n, total, replace=False))
        return x[rows], y[rows]
    tri = np.loadtxt(DATA / "nonrigid_bcpd_face/face-g-triangles.txt", dtype=np.int64)
    return _triangle_rows(x, y, tri, total, rng)


def _triangle_rows(x, y, tri, total: int, rng):
    """All rows of ``x``, ``y`` and ``total − len(x)`` points drawn on the triangles ``tri`` (area-weighted
    in ``x``, uniform barycentric coordinates), the same coordinates in both sets: the deformation
    interpolated linearly within each triangle."""
    n = x.shape[0]
    area = 0.5 * np.linalg.norm(np.cross(x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]]), axis=1)
    pick = rng.choice(tri.shape[0], total - n, p=area / area.sum())
    u, v = rng.uniform(size=(2, total - n))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    w = np.column_stack([1 - u - v, u, v])[:, :, None]
    return np.vstack([x, np.sum(w * x[tri[pick]], axis=1)]), np.vstack([y, np.sum(w * y[tri[pick]], axis=1)])


#: The Stanford mesh whose vertices, in order, are the bcpd bunny's rows (up to a similarity).
BUNNY_MESH = "stanford_bunny_reconstruction/bun_zipper_res2.ply"


def bunny_triangles(x) -> np.ndarray:
    """The (16,301, 3) triangles of the bcpd bunny's rows: those of :data:`BUNNY_MESH`, after checking
    that a similarity maps the mesh's vertices onto ``x`` row by row (to 1e-4 of its extent)."""
    import pyvista as pv

    from gatv.fitting import umeyama

    mesh = pv.read(str(DATA / BUNNY_MESH))
    v = np.asarray(mesh.points, dtype=float)
    if v.shape != x.shape:
        raise ValueError(f"{BUNNY_MESH} has {v.shape[0]} vertices, the bunny {x.shape[0]} rows")
    s, R, t = umeyama(v, x)
    off = np.linalg.norm(s * v @ R.T + t - x, axis=1).max()
    if off > 1e-4 * np.ptp(x, axis=0).max():
        raise ValueError(f"{BUNNY_MESH}'s vertices are not the bunny's rows in order (off by {off:.3g})")
    return np.asarray(mesh.faces, np.int64).reshape(-1, 4)[:, 1:]


def _bunny_sampled(x, y, rng) -> Trial:
    """The bcpd bunny with each set an independent 80% of its 8,171 rows (the truth: the rows both
    share); bunny-x-co's outlier blob (its rows past 8,171) stays whole in the source."""
    from gatv.candidates import median_spacing

    n_true = y.shape[0]
    xr, yr = _subsets(x[:n_true], y, rng, True)
    src = np.vstack([x[xr], x[n_true:]])
    tgt = y[yr]
    ps, pt = rng.permutation(src.shape[0]), rng.permutation(tgt.shape[0])
    inv_s, inv_t = np.argsort(ps), np.argsort(pt)
    _, ix, iy = np.intersect1d(xr, yr, return_indices=True)
    pairs = np.column_stack([inv_s[ix], inv_t[iy]])
    pairs = pairs[np.argsort(pairs[:, 0])]
    inl = inv_s[: xr.size]
    order = np.argsort(inl)
    return Trial(src[ps], tgt[pt], pairs, inl[order], y[xr][order], np.arange(tgt.shape[0]), median_spacing(tgt))


def make_trial(case: Case, f: float, rng) -> Trial:
    """Build the trial of ``case`` at outlier share ``f`` (shuffled, outliers in each box)."""
    from gatv.candidates import median_spacing
    from gatv.datasets import outlier_count
    from gatv.nonrigid import deformations as D

    labels = None
    if case.kind == "plane":
        x, y = _plane_pair(case, rng)
    elif case.kind == "face":
        x, y = _load("nonrigid_bcpd_face/face-x.txt"), _load(f"nonrigid_bcpd_face/{case.warp}.txt")
    elif case.kind == "face-n":
        x, y = _load("nonrigid_bcpd_face/face-x.txt"), _load(f"nonrigid_bcpd_face/{case.warp}.txt")
        x, y = _face_rows(x, y, round(case.n / 0.8) if case.sampled else case.n, rng)
    elif case.kind == "body":
        x, y = _load("nonrigid_bcpd_human/female-x.txt"), _load("nonrigid_bcpd_human/female-y.txt")
    elif case.kind == "bunny-n":
        x, y = _load(f"nonrigid_bcpd_bunny/{case.warp}.txt"), _load("nonrigid_bcpd_bunny/bunny-y.txt")
        total = round(case.n / 0.8) if case.sampled else case.n
        if total <= x.shape[0]:
            rows = np.sort(rng.choice(x.shape[0], total, replace=False))
            x, y = x[rows], y[rows]
        else:
            x, y = _triangle_rows(x, y, bunny_triangles(x), total, rng)
    elif case.kind == "small-face":
        x, y = _load("nonrigid_bcpd_face/face-x.txt"), _load(f"nonrigid_bcpd_face/{case.warp}.txt")
        drawn = rng.choice(len(x), size=case.n, replace=False)
        x, y = x[drawn], y[drawn]
    elif case.kind == "small-plane":
        x = D.sample_plane(400, 10.0, seed=rng)
        y = {"twist30": lambda p: D.twist(p, 30.0), "twist60": lambda p: D.twist(p, 60.0),
             "twist90": lambda p: D.twist(p, 90.0), "bend90": lambda p: D.bend(p, 90.0),
             "elastic1": lambda p: D.elastic(p, 1.0, seed=rng),
             "hinge30": lambda p: D.piecewise_rigid(p, 30.0)}[case.warp](x)
    elif case.kind == "bunny":
        x, y = _load(f"nonrigid_bcpd_bunny/{case.warp}.txt"), _load("nonrigid_bcpd_bunny/bunny-y.txt")
        # bunny-x-co: rows 8171.. are the outlier blob (no true position)
        n_true = y.shape[0]
        if case.sampled:
            return _bunny_sampled(x, y, rng)
        ps, pt = rng.permutation(x.shape[0]), rng.permutation(n_true)
        inv_s, inv_t = np.argsort(ps), np.argsort(pt)
        pairs = np.column_stack([inv_s[:n_true], inv_t])
        order = np.argsort(pairs[:, 0])  # row m of the truth is original row order[m]
        return Trial(x[ps], y[pt], pairs[order], pairs[order, 0], y[order], np.arange(n_true),
                     median_spacing(y))
    elif case.kind == "two-real":
        # the body (two poses) and a face (two expressions) side by side, each with its own
        # deformation: the face's rows subsampled to case.n, scaled to the body's spacing
        from gatv.candidates import median_spacing as _spacing

        bx, by = _load("nonrigid_bcpd_human/female-x.txt"), _load("nonrigid_bcpd_human/female-y.txt")
        fx, fy = _load("nonrigid_bcpd_face/face-x.txt"), _load("nonrigid_bcpd_face/face-y.txt")
        rows = np.sort(rng.choice(fx.shape[0], case.n, replace=False))
        fx, fy = fx[rows], fy[rows]
        scale = _spacing(bx) / _spacing(fx)
        c = fx.mean(axis=0)
        shift = np.array([bx[:, 0].max() + 0.5 * np.ptp(bx[:, 0]), bx[:, 1].mean(), bx[:, 2].mean()])
        shift[0] += scale * (c[0] - fx[:, 0].min())
        fx, fy = (fx - c) * scale + shift, (fy - c) * scale + shift
        x, y = np.vstack([bx, fx]), np.vstack([by, fy])
        labels = np.r_[np.zeros(len(bx), np.int64), np.ones(len(fx), np.int64)]
    elif case.kind == "two":
        n = case.n
        plate = D.sample_plane(n, 10.0, seed=rng)
        bar = D.sample_plane(n, 10.0, seed=rng) * [1.0, 0.3, 1.0] + [13.0, 0.0, 0.0]
        x = np.vstack([plate, bar])
        y = np.vstack([D.twist(plate, 60.0), D.rigid(D.bend(bar, 60.0, axis=(0, 1, 0)), 20.0,
                                                       axis=(0, 0, 1), translation=(1.0, 2.0, 1.0))])
        labels = np.r_[np.zeros(n, np.int64), np.ones(n, np.int64)]
    else:
        raise ValueError(case.kind)
    if case.turn:
        from gatv.ga import Rotor

        axis = rng.normal(size=3)
        R = Rotor.from_axis_angle(axis / np.linalg.norm(axis), np.radians(case.turn)).as_matrix()
        y = y @ R.T
    xr, yr = _subsets(x, y, rng, case.sampled)
    X, Yt, Y = x[xr], y[xr], y[yr]  # source, its true positions, target
    n_out = outlier_count(f, X.shape[0]) if case.outliers_ok else 0
    src = np.vstack([X, rng.uniform(X.min(0), X.max(0), (n_out, 3))])
    tgt = np.vstack([Y, rng.uniform(Y.min(0), Y.max(0), (n_out, 3))])
    ps, pt = rng.permutation(src.shape[0]), rng.permutation(tgt.shape[0])
    inv_s, inv_t = np.argsort(ps), np.argsort(pt)
    _, ix, iy = np.intersect1d(xr, yr, return_indices=True)
    pairs = np.column_stack([inv_s[ix], inv_t[iy]])
    pairs = pairs[np.argsort(pairs[:, 0])]
    inl = inv_s[: X.shape[0]]
    order = np.argsort(inl)
    lab = labels[xr][order] if labels is not None else None
    return Trial(src[ps], tgt[pt], pairs, inl[order], Yt[order], np.sort(inv_t[: Y.shape[0]]),
                 median_spacing(Y), lab)


# ------------------------------------------------------------------ methods (run in a child)
def nearest_pairs(moved, target, gate):
    """Nearest target of each moved source point within ``gate``, one-to-one (closest first)."""
    from scipy.spatial import cKDTree

    from gatv.candidates import one_to_one

    d, j = cKDTree(target).query(moved, k=1, distance_upper_bound=gate)
    ok = np.flatnonzero(np.isfinite(d))
    cand = np.column_stack([ok, j[ok]]).astype(np.int64)
    return cand[one_to_one(cand, d[ok])] if ok.size else cand


def run_gatv_sim(src, tgt, f, spacing, kind):
    """gatv with the bunny's per-dataset options (a labelled method of its own)."""
    from gatv.nonrigid import register

    m = register(src, tgt, prealign=True, model="similarity")
    info = {k: m.info.get(k) for k in ("hypothesis", "placement", "coarse_hypothesis", "n_eq41_rejected", "reason")
            if k in m.info}
    return m.correspondences, m.warp(src), info


def run_gatv(src, tgt, f, spacing, kind):
    if kind in ("two", "two-real"):
        from gatv.nonrigid import segment

        seg = segment(src, tgt)
        moved = src.copy()
        pairs = [m.correspondences for m in seg.motions]
        for k, m in enumerate(seg.motions):
            rows = np.flatnonzero(seg.source_labels == k)
            moved[rows] = m.warp(src[rows])
        return (np.vstack(pairs) if pairs else np.empty((0, 2), np.int64)), moved, {
            "motions": [p.tolist() for p in pairs]}
    from gatv.nonrigid import register

    m = register(src, tgt)  # the defaults on every row (gatv+sim: the bunny's options)
    info = {k: m.info.get(k) for k in ("hypothesis", "placement", "coarse_hypothesis", "n_eq41_rejected", "reason")
            if k in m.info}
    return m.correspondences, m.warp(src), info


def run_cpd(src, tgt, f, spacing, kind):
    from pycpd import DeformableRegistration

    reg = DeformableRegistration(X=np.asarray(tgt), Y=np.asarray(src), w=min(f, 0.99), max_iterations=150)
    TY, _ = reg.register()
    return nearest_pairs(TY, tgt, 0.5 * spacing), TY, {}


def run_bcpd(src, tgt, f, spacing, kind):
    from probreg import bcpd

    tf = bcpd.registration_bcpd(np.asarray(src), np.asarray(tgt), w=min(max(f, 1e-3), 0.99), maxiter=50)
    moved = np.asarray(tf.transform(np.asarray(src)))
    return nearest_pairs(moved, tgt, 0.5 * spacing), moved, {}


def run_filterreg(src, tgt, f, spacing, kind):
    from probreg import filterreg

    res = filterreg.registration_filterreg(np.asarray(src), np.asarray(tgt), w=min(f, 0.99), maxiter=50)
    moved = np.asarray(res.transformation.transform(np.asarray(src)))
    return nearest_pairs(moved, tgt, 0.5 * spacing), moved, {}


def run_lrcpd(src, tgt, f, spacing, kind):
    """Low-rank deformable CPD (rustcpd: the kernel's rank-``LRCPD_RANK`` pivoted-Cholesky factor,
    never the dense M × M kernel), the same ``w`` and pairing rule as the other peers."""
    import rustcpd

    res = rustcpd.register_deformable(np.asarray(tgt, float), np.asarray(src, float), low_rank=LRCPD_RANK,
                                      low_rank_method="pivoted_cholesky", outlier_weight=min(f, 0.99),
                                      max_iterations=150, normalize=True)
    moved = np.asarray(res.points, float)
    return nearest_pairs(moved, tgt, 0.5 * spacing), moved, {}


#: Rank of the low-rank CPD peer's kernel (rustcpd's own example for large clouds).
LRCPD_RANK = 300

RUNNERS = {"gatv": run_gatv, "gatv+sim": run_gatv_sim, "cpd": run_cpd, "bcpd": run_bcpd,
           "filterreg": run_filterreg, "lrcpd": run_lrcpd}


def warm_up(method, kind, w):
    """One untimed call of ``method`` on a small twisted plane (400 points a set, or two bodies for
    ``kind="two"``): imports, numba's compilation or cache loading, first-call set-up, for every
    method alike, so that the timed call holds none of them.  Returns its seconds."""
    from gatv.nonrigid import deformations as D

    t0 = time.perf_counter()
    a = D.sample_plane(400 if kind not in ("two", "two-real") else 200, 10.0, seed=0)
    src, tgt = a, D.twist(a, 30.0)
    if kind in ("two", "two-real"):
        src, tgt = np.vstack([a, a + [14.0, 0, 0]]), np.vstack([D.twist(a, 30.0), D.bend(a, 30.0) + [14.0, 0, 3.0]])
    try:
        RUNNERS[method](src, tgt, w, 10.0 / 20.0, kind)
    except Exception:  # noqa: BLE001 - the timed call reports its own errors
        pass
    return time.perf_counter() - t0


def peer_bytes(method, n_source, n_target) -> float:
    """Dense-matrix bytes of a peer: pycpd and probreg's BCPD hold M×N posteriors (and
    temporaries of that size) and the M×M kernel of the source.
    Measured: pycpd's deformable CPD peaked at 4.8 GB RSS for 8,171 × 8,171 points
    (about 9 float64 arrays of M×N), hence 6 M×N + 3 M×M float64.  probreg's FilterReg
    peaked at 2.4 GB for 23,728 × 23,728 points and 8.7 GB for 47,456 × 47,456: about
    4 bytes per point pair."""
    if method in ("cpd", "bcpd"):
        return 8.0 * (6.0 * n_source * n_target + 3.0 * n_source * n_source)
    if method == "filterreg":
        return 4.0 * n_source * n_target
    return 0.0


def child_main(path_in: str, path_out: str) -> int:
    """Child process: run one method on one trial, write pairs, moved points, time and peak RSS."""
    import resource

    data = np.load(path_in, allow_pickle=False)
    meta = json.loads(str(data["meta"]))
    out = {"error": "", "info": {}}
    out["warm_s"] = warm_up(meta["method"], meta["kind"], meta["w"])
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        pairs, moved, info = RUNNERS[meta["method"]](data["source"], data["target"], meta["w"],
                                                      meta["spacing"], meta["kind"])
        out["info"] = info
    except Exception as exc:  # noqa: BLE001 - scored as a failure, reported in the table
        pairs, moved = np.empty((0, 2), np.int64), np.asarray(data["source"]).copy()
        out["error"] = f"{type(exc).__name__}: {' '.join(str(exc).split())[:160]}"
    out["time_s"] = time.perf_counter() - t0
    out["cpu_s"] = time.process_time() - c0
    out["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0 ** 2
    np.savez(path_out, pairs=np.asarray(pairs, np.int64).reshape(-1, 2), moved=np.asarray(moved, float),
             meta=json.dumps(out))
    return 0


def run_isolated(method, trial: Trial, f, kind, timeout, peer_info="blind"):
    """Run ``method`` in a child process; returns (pairs, moved, time, CPU time, peak RSS GB, error, info).

    What a peer is told: ``peer_info="blind"`` (default), the outlier share :data:`PEER_W` and the
    pairing gate from the median spacing of the target as given (outliers included), as gatv,
    which is told neither, measures it; ``"oracle"``, the true share ``f`` and the spacing of the
    target's true inliers (the old protocol, reported as such)."""
    from gatv.candidates import median_spacing

    oracle = peer_info == "oracle"
    w = f if oracle else PEER_W
    spacing = trial.spacing if oracle else float(median_spacing(trial.target))
    with tempfile.TemporaryDirectory() as tmp:
        pin, pout = os.path.join(tmp, "in.npz"), os.path.join(tmp, "out.npz")
        meta = json.dumps({"method": method, "w": w, "spacing": spacing, "kind": kind})
        np.savez(pin, source=trial.source, target=trial.target, meta=meta)
        t0 = time.perf_counter()
        try:
            proc = subprocess.run([sys.executable, __file__, "--child", pin, pout], timeout=timeout,
                                  capture_output=True, text=True, check=False)
        except subprocess.TimeoutExpired:
            return (None, None, time.perf_counter() - t0, float("nan"), float("nan"),
                    f"did not finish in {timeout:.0f} s", {})
        if proc.returncode != 0 or not os.path.exists(pout):
            tail = " ".join((proc.stderr or "").split()[-20:])
            killed = proc.returncode in (-9, 137)
            why = "killed (out of memory?)" if killed else f"child failed (rc {proc.returncode}): {tail}"
            return None, None, time.perf_counter() - t0, float("nan"), float("nan"), why[:200], {}
        res = np.load(pout, allow_pickle=False)
        meta = json.loads(str(res["meta"]))
        info = dict(meta["info"], warm_s=round(meta["warm_s"], 2))
        return res["pairs"], res["moved"], meta["time_s"], meta["cpu_s"], meta["peak_rss_gb"], meta["error"], info


# ------------------------------------------------------------------ scores
def score(trial: Trial, pairs, moved):
    """exact P, exact R, share within one spacing, its recall, warp error in spacings."""
    from scipy.spatial import cKDTree

    from gatv.datasets import correspondence_stats

    nan = float("nan")
    if pairs is None:
        return nan, nan, nan, nan, nan
    prec, rec = correspondence_stats(pairs, trial.true_pairs) if len(trial.true_pairs) else (nan, nan)
    h = trial.spacing
    pos = np.full((trial.source.shape[0], 3), np.nan)
    pos[trial.inliers] = trial.true_positions
    if len(pairs):
        d = np.linalg.norm(trial.target[pairs[:, 1]] - pos[pairs[:, 0]], axis=1)
        good = np.nan_to_num(d, nan=np.inf) <= h
        within = float(good.mean())
    else:
        good, within = np.zeros(0, bool), 0.0
    tin = trial.target[trial.target_inliers]
    dm, _ = cKDTree(tin).query(trial.true_positions, k=1)
    matchable = int(np.sum(dm <= 0.5 * h))
    rec_within = float(good.sum()) / max(1, matchable)
    werr = float(np.mean(np.linalg.norm(moved[trial.inliers] - trial.true_positions, axis=1))) / h
    return prec, rec, within, rec_within, werr


def two_motion_scores(trial: Trial, info):
    """Per true motion: the found motion holding most of its exact pairs, its precision and recall."""
    if trial.labels is None or "motions" not in info:
        return ""
    lab = np.full(trial.source.shape[0], -1)
    lab[trial.inliers] = trial.labels
    true_of = {tuple(p) for p in trial.true_pairs.tolist()}
    out = []
    for k in (0, 1):
        n_true = int(np.sum(lab[trial.true_pairs[:, 0]] == k))
        best = (0.0, 0.0)
        for p in info["motions"]:
            p = np.asarray(p, np.int64).reshape(-1, 2)
            ok = np.array([tuple(q) in true_of for q in p.tolist()], bool) & (lab[p[:, 0]] == k)
            if len(p) and ok.sum() / max(1, n_true) > best[1]:
                best = (ok.sum() / len(p), ok.sum() / max(1, n_true))
        out.append(f"motion {k}: P {best[0]:.3f} R {best[1]:.3f}")
    return f"{len(info['motions'])} found; " + "; ".join(out)


# ------------------------------------------------------------------ one task
def run_task(task) -> list:
    """One (case, f, trial) through every method: CSV rows. Module-level and picklable for map_trials."""
    case, f, k, seed, methods, timeout, peer_gb, peer_info = task
    rng = np.random.default_rng(trial_seed(seed, f, k))
    trial = make_trial(case, f, rng)
    rows = []
    for method in methods:
        if method in TOLD and case.kind not in TOLD[method]:
            continue
        label = f"{method} (told f)" if peer_info == "oracle" and method in PEER_MODULE else method
        base = [case.name, f, label, k, trial.source.shape[0], trial.target.shape[0]]
        if method in PEER_MODULE:
            try:
                __import__(PEER_MODULE[method])
            except ImportError:
                rows.append(base + [np.nan] * 9 + [f"not installed ({PEER_MODULE[method]})", ""])
                continue
            need = peer_bytes(method, trial.source.shape[0], trial.target.shape[0])
            if need > peer_gb * 1024 ** 3:
                rows.append(base + [np.nan] * 9 + [f"would need {need / 1024 ** 3:.1f} GB (over {peer_gb:g} GB)", ""])
                continue
        pairs, moved, seconds, cpu, rss, error, info = run_isolated(method, trial, f, case.kind, timeout, peer_info)
        p, r, w, rw, we = score(trial, pairs, moved)
        note = two_motion_scores(trial, info) if case.kind in ("two", "two-real") and method == "gatv" else ""
        if info:
            extra = {kk: v for kk, v in info.items() if kk != "motions"}
            note = (note + " " + json.dumps(extra)).strip() if extra else note
        rows.append(base + [p, r, w, rw, we, seconds, cpu, os.getloadavg()[0], rss, error, note])
    return rows


def cases(groups, sizes):
    out = []
    if "face" in groups:
        out += [Case("face x→y (23,728)", "face", warp="face-y"),
                Case("face x→g.y (23,728)", "face", warp="face-g.y"),
                Case("face x→y, sampled 80%/80%", "face", warp="face-y", sampled=True)]
    if "face-sizes" in groups:
        out += [Case(f"face x→y {n // 1000}k, sampled 80%/80%", "face-n", n, "face-y", sampled=True)
                for n in sizes if n >= 10_000]
    if "twist" in groups:
        out += [Case(f"twist 90°, {n // 1000}k", "plane", n, "twist90") for n in sizes]
        out += [Case(f"twist 90°, {n // 1000}k sampled 80%/80%", "plane", n, "twist90", sampled=True)
                for n in sizes if 10_000 <= n <= 25_000]
    if "elastic" in groups:
        out += [Case(f"elastic 1, {n // 1000}k", "plane", n, "elastic") for n in sizes if n >= 10_000]
    if "body" in groups:
        out += [Case("body x→y, sampled 80%/80%", "body", sampled=True),
                Case("body x→y turned 60°, sampled 80%/80%", "body", sampled=True, turn=60.0),
                Case("body x→y turned 180°, sampled 80%/80%", "body", sampled=True, turn=180.0)]
    if "bunny" in groups:
        out += [Case("bunny x→y (sim. + deform)", "bunny", warp="bunny-x", outliers_ok=False),
                Case("bunny x-co→y (+1,600 blob)", "bunny", warp="bunny-x-co", outliers_ok=False),
                Case("bunny x→y, sampled 80%/80%", "bunny", warp="bunny-x", outliers_ok=False, sampled=True),
                Case("bunny x-co→y, sampled 80%/80%", "bunny", warp="bunny-x-co", outliers_ok=False,
                     sampled=True)]
    if "bunny-sizes" in groups:
        out += [Case(f"bunny x→y {n // 1000}k, sampled 80%/80%", "bunny-n", n, "bunny-x", sampled=True,
                     outliers_ok=False) for n in sizes if n >= 10_000]
    if "two-motion" in groups:
        out += [Case("two motions: twisted plate + bent bar (2×400)", "two", 400)]
    if "two-real" in groups:
        out += [Case("two real shapes: body + face (6,890 + 6,000), sampled 80%/80%", "two-real", 6000,
                     sampled=True)]
    if "small" in groups:
        out += [Case(f"small plane {w} (400)", "small-plane", 400, w)
                for w in ("twist30", "twist60", "twist90", "bend90", "elastic1", "hinge30")]
        out += [Case(f"small face x→{w[5:]} (600)", "small-face", 600, w) for w in ("face-y", "face-g.y")]
    return out


HEADERS = ["case", "outliers", "method", "N", "exact P", "exact R", "≤1 sp", "R ≤1 sp",
           "warp err / sp", "time (s)", "CPU (s)", "load", "peak RSS (GB)", "status / notes"]
CSV_HEADERS = ["case", "f", "method", "trial", "n_source", "n_target", "precision", "recall",
               "within_one_spacing", "recall_within", "warp_error_spacings", "time_s", "cpu_s", "load_1min",
               "peak_rss_gb",
               "error", "notes"]


def summary_rows(csv_rows):
    groups: dict = {}
    for r in csv_rows:
        groups.setdefault((r[0], r[1], r[2]), []).append(r)
    rows = []
    for (name, f, method), rs in groups.items():
        errs = sorted({r[15] for r in rs if r[15]})
        notes = sorted({r[16] for r in rs if r[16]})
        status = "; ".join(errs + notes)[:300]
        rows.append([name, f"{100 * f:.0f}%", method, rs[0][4],
                     *(fmt(median(r[c] for r in rs), 3) for c in (6, 7, 8, 9)),
                     fmt(median(r[10] for r in rs), 3), fmt(median(r[11] for r in rs), 1),
                     fmt(median(r[12] for r in rs), 1), fmt(median(r[13] for r in rs), 1),
                     fmt(median(r[14] for r in rs), 2), status])
    return rows


def _write(args, argv, csv_rows):
    table = markdown_table(HEADERS, summary_rows(csv_rows), "lllrrrrrrrrrrl")
    args.out.mkdir(parents=True, exist_ok=True)
    command = shlex.join(argv if argv is not None else sys.argv[1:])
    (args.out / "nonrigid.md").write_text(
        f"`python benchmarks/nonrigid.py {command}` ({args.trials} trial(s) per row, medians)\n\n{table}\n")
    write_csv(args.out / "nonrigid.csv", CSV_HEADERS, csv_rows)
    return table


def main(argv=None) -> int:
    argv_list = sys.argv[1:] if argv is None else list(argv)
    if argv_list[:1] == ["--child"]:
        return child_main(argv_list[1], argv_list[2])
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_common_arguments(parser, trials=1)
    add_scheduler_argument(parser)
    parser.add_argument("--cases", type=parse_list(str), default=None, metavar="GROUP,...",
                        help=f"groups of rows: {', '.join(GROUPS)} (default: {','.join(DEFAULT_GROUPS)})")
    parser.add_argument("--sizes", type=parse_list(int), default=None, metavar="N,...",
                        help="points per set of the synthetic size rows (default: 2000,10000,25000; "
                             "add 100000 for the 100k rows)")
    parser.add_argument("--only", default=None, metavar="TEXT",
                        help="keep only the rows whose name contains TEXT (e.g. 'sampled')")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds per method and trial (default: 600)")
    parser.add_argument("--peer-memory-gb", type=float, default=4.0,
                        help="do not run a peer whose dense matrices would need more (default: 4)")
    parser.add_argument("--peer-info", choices=("blind", "oracle"), default="blind",
                        help="blind (default): peers get w = PEER_W and the spacing of the target as given, "
                             "as gatv gets nothing; oracle: the true outlier share and the true inliers' spacing "
                             "(rows labelled 'told f')")
    args = parser.parse_args(argv_list)
    fractions = args.fractions if args.fractions is not None else [0.0, 0.5]
    methods = args.methods if args.methods is not None else list(METHODS)
    unknown = set(methods) - set(METHODS)
    if unknown:
        parser.error(f"unknown methods {sorted(unknown)}; choose from {', '.join(METHODS)}")
    groups = args.cases if args.cases is not None else list(DEFAULT_GROUPS)
    bad = set(groups) - set(GROUPS)
    if bad:
        parser.error(f"unknown case groups {sorted(bad)}; choose from {', '.join(GROUPS)}")
    sizes = args.sizes if args.sizes is not None else list(DEFAULT_SIZES)
    chosen = cases(groups, sizes)
    if args.only:
        chosen = [c for c in chosen if args.only in c.name]
    if not (DATA / "nonrigid_bcpd_face" / "face-x.txt").is_file():
        print(f"data not found in {DATA}: face and bunny rows left out")
        chosen = [c for c in chosen if c.kind not in ("face", "face-n", "small-face", "bunny", "bunny-n", "body",
                                                      "two-real")]
    elif not (DATA / "nonrigid_bcpd_human" / "female-x.txt").is_file():
        print(f"body data not found in {DATA}: body rows left out")
        chosen = [c for c in chosen if c.kind not in ("body", "two-real")]
    if not (DATA / BUNNY_MESH).is_file() and any(c.kind == "bunny-n" for c in chosen):
        print(f"{BUNNY_MESH} not found in {DATA}: bunny size rows left out")
        chosen = [c for c in chosen if c.kind != "bunny-n"]
    tasks = []
    for c in chosen:
        for f in fractions:
            if f > 0 and not c.outliers_ok:
                continue
            for k in range(args.trials):
                tasks.append((c, f, k, args.seed, tuple(methods), args.timeout, args.peer_memory_gb,
                              args.peer_info))
    csv_rows = []
    if args.scheduler is None:  # serial: print and save after every task
        for task in tasks:
            rows = run_task(task)
            csv_rows += rows
            for r in summary_rows(rows):
                print(" | ".join(map(str, r)), flush=True)
            _write(args, argv, csv_rows)
    else:
        for rows in map_trials(run_task, tasks, scheduler=args.scheduler):
            csv_rows += rows
    table = _write(args, argv, csv_rows)
    print()
    print(table)
    print(f"\nwrote {args.out / 'nonrigid.csv'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
