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

* ``noise=N% K=k f=50%``: ``k`` = 2..4 motions of 30–60 points each, 50%
  outliers, Gaussian noise on every moved point with standard deviation
  ``N`` = 1, 2 or 4% of each object's RMS radius (its points are uniform in
  the 10-cube: radius 5); ``segment`` is not told the noise.
* ``scans: A+B(+C)``: real-scan scenes composed from ``../shared/data``
  (:func:`gatv.motions.scan_scene`): bunny scan pairs and the UWA chef and
  parasaurolophus pairs (in metres), each object moved by its own random
  motion, 40k points per scene, 20% uniform clutter and a static plane
  patch (the last motion, the identity).  No row holds one scan twice (two
  bunny pairs with the target bun000): its two copies make the scene
  ambiguous, either source object fitting either copy as well.  Methods ``auto`` and
  ``o3d-seq`` (sequential Open3D RANSAC on FPFH + point-to-plane ICP,
  peeling the explained points and repeating while a motion explains at
  least 5% of the remaining source points and 500 points).  Scores: exact
  K (objects + static patch), worst per-object pose error (degrees, mm),
  objects within 1° and 3 mm, spurious motions (found motions matching no
  true one within 5° and 10 mm), source-label accuracy against the truth
  (a point's motion where the other scene sees its surface, else -1),
  static patch labelled static, median and max time, and the peak RSS of
  the benchmark process so far (an upper bound for each scene).
  ``--scan-noise 2,4`` adds the rows ``<row> +2% noise``: the same scenes
  with Gaussian noise on every point of both, its deviation that share of
  the first object's RMS radius (1% is 0.58 mm on a bunny).

Methods: ``auto`` (:func:`gatv.motions.segment` as a user calls it: the
pipeline and grouping chosen from the data), ``graph`` (``grouping="graph"``), ``greedy``
(``segment(grouping="greedy")``) and ``ransac`` (sequential RANSAC on
three-pair samples of all candidate pairs, :func:`gatv.motions.ransac_segment`).

Metrics: exactly-K rate; per-motion rotation/translation error (found
motions matched to true ones by shared correspondences); correspondence
precision, recall and F1 over all motions (a found pair is right when it
is a true pair of the motion it was matched to); point-label accuracy
over all source and target points (outliers must stay ``-1``); median time.

Usage::

    python benchmarks/motions.py [--trials 20] [--seed 0] [--rows fig12,K=2,...]
                                 [--methods auto,graph,greedy,ransac,o3d-seq] [--out benchmarks/results]
                                 [--scheduler local|ADDRESS]

Rows are point-set rows or scan rows; each method runs on the rows of its
kind (``auto`` and ``o3d-seq`` on both, ``graph``/``greedy``/``ransac`` on
point-set rows only; ``o3d-seq`` on point sets: see :func:`o3d_sequential`).
Point-set rows also report an F1 ceiling (:func:`f1_ceiling`): what the true
motions themselves reach with per-pair gating at the row's noise, one-to-one
by the maximum-weight matching gatv itself uses
(:func:`gatv.motions.peeling.assign_pairs`); and an exact-K ceiling
(:func:`k_ceiling`): the share of scenes whose every motion, counted at its
true pose, beats the chance level a search must beat, family-wise over the
matches that round's search would score (:func:`search_tests`, from the
scene's own points); and that share again when each motion kept takes out
every point within its gate at its true pose (chance pairs too, as a peel
that cannot tell them from true ones must: the "peel ceiling",
``k_ceiling(takes="gated")``).  ``o3d-seq`` on point-set rows runs FPFH where there is
no surface: its rows there are marked "(out of domain)", not a loss.

Prints a markdown table; writes ``motions.csv`` and ``motions_trials.csv``.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (
    DEFAULT_OUT,
    Timer,
    add_scheduler_argument,
    fmt,
    map_trials,
    markdown_table,
    median,
    parse_list,
    write_csv,
)
from scipy.optimize import linear_sum_assignment

from gatv.datasets import rotation_error_deg, translation_error
from gatv.ga import Rotor
from gatv.motions import (
    fig12_scene,
    multi_motion_scene,
    ransac_segment,
    scan_scene,
    segment,
)


def _random_axis(rng):
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _random_motions(rng, k):
    rots = [Rotor.from_axis_angle(_random_axis(rng), np.radians(rng.uniform(10, 180))).as_matrix()
            for _ in range(k)]
    return rots, rng.uniform(-5, 5, size=(k, 3))


def _outliers(n_in, f):
    return round(n_in * f / (1.0 - f)) if f > 0 else 0


#: RMS radius of an object whose points are uniform in the 10-cube (sqrt(3 * 10² / 12)).
RMS_RADIUS = 5.0

#: Scan rows: objects of each scene ("T<-S" a bunny pair, else a UWA object).
SCAN_ROWS = {
    "scans: chef + parasaurolophus": ("chef", "parasaurolophus"),
    "scans: bun000<-045 + chef": ("bun000<-bun045", "chef"),
    "scans: bun000<-315 + parasaurolophus": ("bun000<-bun315", "parasaurolophus"),
    "scans: bun000<-045 + chef + parasaurolophus": ("bun000<-bun045", "chef", "parasaurolophus"),
}


def _load_object(name):
    from gatv.datasets import load_bunny_pair, load_uwa_pair

    if "<-" in name:
        return load_bunny_pair(*name.split("<-"))
    target, source, R, t = load_uwa_pair(name)
    return target / 1000.0, source / 1000.0, R, t / 1000.0  # millimetres -> metres


#: Suffix of a noisy scan row: ``"scans: chef + parasaurolophus +2% noise"`` (``--scan-noise 2``).
NOISE_SUFFIX = "% noise"


def scan_row(name):
    """``(scan row, noise %)`` of a row name, or ``(None, 0)`` for a point-set row."""
    if name in SCAN_ROWS:
        return name, 0.0
    base, _, pct = name.rpartition(" +")
    if base in SCAN_ROWS and pct.endswith(NOISE_SUFFIX):
        return base, float(pct[: -len(NOISE_SUFFIX)])
    return None, 0.0


def make_scan_scene(name, rng):
    """A scan row's scene; a noisy row adds Gaussian noise to every point of both scenes, its deviation
    the given share of the first object's RMS radius in the source scene (1% is 0.58 mm on a bunny)."""
    base, pct = scan_row(name)
    scene = scan_scene([_load_object(o) for o in SCAN_ROWS[base]], n_points=40000, clutter=0.2,
                       static_patch=0.1, seed=rng)
    if pct > 0:
        first = scene.source[scene.source_labels == 0]
        sigma = pct / 100.0 * float(np.sqrt(((first - first.mean(axis=0)) ** 2).sum(axis=1).mean()))
        scene = dataclasses.replace(scene, source=scene.source + rng.normal(0.0, sigma, scene.source.shape),
                                    target=scene.target + rng.normal(0.0, sigma, scene.target.shape))
    return scene


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
    for pct in (1, 2, 4):
        for k in (2, 3, 4):
            def noisy(rng, k=k, pct=pct):
                rots, ts = _random_motions(rng, k)
                sizes = rng.integers(30, 61, k)
                return multi_motion_scene(rots, ts, sizes, n_outliers=_outliers(sizes.sum(), 0.5),
                                          noise=pct / 100.0 * RMS_RADIUS, seed=rng)
            rows[f"noise={pct}% K={k} f=50%"] = noisy

    return rows


def o3d_sequential(source, target, seed=0, max_motions=8, *, points=False):
    """Sequential Open3D baseline: RANSAC on FPFH + ICP, peel the explained points, repeat.

    Scans: voxel 1/40 of the target's bounding-box diagonal (as
    benchmarks/scans.py), point-to-plane ICP, a motion explains the source
    points within 3 target spacings of a target point; it stops when a motion
    explains fewer than 5% of the remaining source points or 500 points.
    Point sets (``points=True``, a few hundred points, no surface): the voxel is
    the target's median spacing (no downsampling), point-to-point ICP, a motion
    explains the source points within half a spacing (one-to-one nearest), and
    the floor is gatv's default smallest motion, 3% of the source points.
    Returns ``(motions, source_labels, pairs)`` with motions as ``(R, t)`` and
    each motion's one-to-one ``(source, target)`` pairs.
    """
    import open3d as o3d
    from scipy.spatial import cKDTree

    from gatv.candidates import median_spacing

    reg = o3d.pipelines.registration
    o3d.utility.random.seed(int(seed))
    spacing = float(median_spacing(target))
    if points:
        voxel, gate, floor = spacing, 0.5 * spacing, int(np.ceil(0.03 * len(source)))
    else:
        voxel = float(np.linalg.norm(target.max(axis=0) - target.min(axis=0))) / 40.0
        gate, floor = 3.0 * spacing, 500

    def features(pts):
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        down = pcd if points else pcd.voxel_down_sample(voxel)
        down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        fpfh = reg.compute_fpfh_feature(down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
        return pcd, down, fpfh

    free_s = np.ones(len(source), bool)
    free_t = np.ones(len(target), bool)
    labels = np.full(len(source), -1)
    motions, pairs = [], []
    while len(motions) < max_motions and free_s.sum() > max(100 if not points else 3, floor) \
            and free_t.sum() > max(100 if not points else 3, floor):
        src, src_down, src_f = features(source[free_s])
        tgt, tgt_down, tgt_f = features(target[free_t])
        coarse = reg.registration_ransac_based_on_feature_matching(
            src_down, tgt_down, src_f, tgt_f, True, 1.5 * voxel, reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
            reg.RANSACConvergenceCriteria(100000, 0.999))
        if points:
            fine = reg.registration_icp(src, tgt, gate, coarse.transformation,
                                        reg.TransformationEstimationPointToPoint(False))
        else:
            tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
            fine = reg.registration_icp(src, tgt, 0.4 * voxel, coarse.transformation,
                                        reg.TransformationEstimationPointToPlane())
        T = np.asarray(fine.transformation)
        R, t = T[:3, :3], T[:3, 3]
        idx_s, idx_t = np.flatnonzero(free_s), np.flatnonzero(free_t)
        d, j = cKDTree(target[idx_t]).query(source[idx_s] @ R.T + t, distance_upper_bound=gate)
        ok = np.flatnonzero(np.isfinite(d))
        if points:  # one-to-one pairs, scored as correspondences: each target's nearest source
            ok = ok[np.argsort(d[ok], kind="stable")]
            ok = ok[np.unique(j[ok], return_index=True)[1]]
        inl = idx_s[ok]
        if inl.size < max(floor, 0.05 * idx_s.size):
            break
        d2, _ = cKDTree(source[inl] @ R.T + t).query(target[idx_t], distance_upper_bound=gate)
        labels[inl] = len(motions)
        free_s[inl] = False
        free_t[idx_t[np.isfinite(d2)]] = False
        motions.append((R, t))
        pairs.append(np.column_stack([inl, idx_t[j[ok]]]))
    return motions, labels, pairs


@dataclass(frozen=True)
class _Found:
    """A baseline's motion, as :func:`score` reads it."""

    rotation: np.ndarray
    translation: np.ndarray
    correspondences: np.ndarray


@dataclass(frozen=True)
class _Baseline:
    """A baseline's segmentation of a point-set row, as :func:`score` reads it."""

    motions: tuple
    source_labels: np.ndarray
    target_labels: np.ndarray

    def __len__(self) -> int:
        return len(self.motions)


def _baseline_segmentation(n_target, motions, labels, pairs) -> _Baseline:
    tl = np.full(n_target, -1)
    for k, p in enumerate(pairs):
        tl[p[:, 1]] = k
    return _Baseline(tuple(_Found(R, t, p) for (R, t), p in zip(motions, pairs)), np.asarray(labels), tl)


#: Gates of :func:`f1_ceiling`, in residual deviations.
CEILING_GATES = tuple(np.arange(2.0, 4.51, 0.25))


def _residual_deviation(scene) -> float:
    """RMS per coordinate of the true pairs' residuals under their true motions."""
    res = [scene.target[p[:, 1]] - (scene.source[p[:, 0]] @ R.T + t)
           for p, R, t in zip(scene.true_pairs, scene.rotations, scene.translations)]
    return float(np.sqrt(np.mean(np.square(np.vstack(res)))))


def f1_ceiling(scene, gates=CEILING_GATES, matching: str = "optimal") -> float:
    """Correspondence F1 of the true motions, their pairs within the best gate taken one-to-one.

    An upper reference for :func:`score`'s F1 under noise: the true poses,
    the residual deviation ``s`` measured on the true pairs, every target
    within ``g · s`` of each source point under each true motion, taken
    one-to-one over all motions by gatv's own rule, the best ``g`` of
    ``gates`` (with the truth).  ``matching="optimal"`` (the ceiling):
    :func:`gatv.motions.peeling.assign_pairs`, the maximum-weight matching
    that gatv's pooled re-gating uses, each pair's gain ``(g s)² − r²`` (its
    log-likelihood ratio times ``2σ²``, as in :func:`gatv.motions.peeling.pool_noise`);
    ``"greedy"``: each point's nearest target under each motion, cheapest
    first (what this ceiling was before; a lower bound of the optimal one,
    kept for comparison).  Uniform outliers that a motion brings within the
    gate of a free target, and true partners beyond it, are what no per-pair
    rule can tell apart.
    """
    from scipy.spatial import cKDTree

    from gatv.candidates import one_to_one
    from gatv.motions.peeling import assign_pairs

    if matching not in ("optimal", "greedy"):
        raise ValueError(f"matching must be 'optimal' or 'greedy', got {matching!r}")
    true = set()
    for p in scene.true_pairs:
        true |= set(map(tuple, p.tolist()))
    s = _residual_deviation(scene)
    if s == 0.0:
        return 1.0
    tree = cKDTree(scene.target)
    moved = [scene.source @ R.T + t for R, t in zip(scene.rotations, scene.translations)]
    best = 0.0
    for g in gates:
        r = g * s
        pairs, cost = [], []
        for m in moved:
            if matching == "optimal":
                near = tree.query_ball_point(m, r)
                c = np.array([(i, j) for i, js in enumerate(near) for j in js], np.int64).reshape(-1, 2)
                d = np.linalg.norm(scene.target[c[:, 1]] - m[c[:, 0]], axis=1)
            else:
                d, j = tree.query(m, distance_upper_bound=r)
                i = np.flatnonzero(np.isfinite(d))
                c, d = np.column_stack([i, j[i]]).astype(np.int64), d[i]
            pairs.append(c)
            cost.append(d)
        pairs, cost = np.vstack(pairs), np.concatenate(cost)
        keep = assign_pairs(pairs, r**2 - cost**2) if matching == "optimal" else one_to_one(pairs, cost)
        found = set(map(tuple, pairs[keep].tolist()))
        hits = len(found & true)
        if hits:
            p, rec = hits / len(found), hits / len(true)
            best = max(best, 2 * p * rec / (p + rec))
    return best


#: Gates of :func:`k_ceiling`, as multiples of the true per-point tolerance.
CEILING_FACTORS = (0.75, 1.0)


def search_tests(problem, n_source: int) -> float:
    """Matches a round of ``segment``'s peel scores on ``problem``: the ``n_tests`` of its density test.

    The noisy peel (what ``segment`` runs on noisy point sets) screens each
    trial against ``model.chance(..., budget · max_matches)``
    (:func:`gatv.stages.search` with ``judged_wrong=None``), the budget from
    :func:`gatv.motions.peeling.search_budget` for the smallest motion the
    round wants (``min_inlier_share`` of the ``n_source`` points, at least the
    judge's chance level), over the tolerances the automatic choice searches
    on noisy sets.  Taken here with every all-inlier sample listed
    (``listed=1``): the least budget, so the most lenient level a round can
    have on these points.
    """
    from gatv import stages
    from gatv.motions.peeling import MAX_SAMPLES, N_JUDGED, search_budget
    from gatv.motions.segmentation import NOISY_FROM

    model = problem.model
    policy = model.search_policy()
    levels = stages.tolerance_levels(problem, None, tuple(r for r in policy.schedule if r >= NOISY_FROM))
    smallest = max(0.03 * n_source, float(stages.sample_points(model)),
                   float(problem.chance(stages.gate(min(levels)), N_JUDGED)))
    cap = int(min(3 * stages.sample_space(model, problem.source.shape[0]), MAX_SAMPLES))
    budget, _ = search_budget(problem, levels, smallest, 0.999, cap, policy.max_matches, listed=1.0)
    return float(max(budget, 1) * policy.max_matches)


def k_ceiling(scene, n_tests=None, factors=CEILING_FACTORS, takes: str = "true") -> tuple[bool, float]:
    """Whether every true motion beats the chance level at its true pose (an exact-K ceiling).

    What the count test of :func:`gatv.motions.segment` allows with a perfect
    search: each true motion placed at its *true* pose, counted as the
    search counts a trial (source points with a target within the gate)
    among the points the motions kept so far leave (with the whole scene's
    volume and spacing, as the peel's rounds keep them), against
    ``Problem.chance(gate, n_tests)`` there (family-wise at
    :data:`gatv.stats.ALPHA` over ``n_tests`` matches); the motion with the
    largest margin is kept first, its true pairs leave.  ``n_tests``: by
    default the matches that round's own search scores (:func:`search_tests`,
    its least budget), else the number given.  The gate is
    ``gatv.stages.gate`` of each of ``factors`` times the true per-point
    tolerance (the true pairs' residual deviation over sqrt 2, as in
    ``gate``'s convention), the best one for each motion, with the truth.
    Optimistic on every count: true poses and noise, the best gate, only
    true pairs taken out, the least budget.  ``takes="gated"``: each motion
    kept takes out, as a peel must (it cannot tell its chance pairs from its
    true ones), every source point with a target within the gate it was
    tested at, at its true pose, one to one, nearest first: chance pairs
    too, often another motion's points (the "peel ceiling").  Returns
    ``(ok, n_tests of the first round)``; ``ok`` False: some motion cannot be
    told from chance even then.
    """
    if takes not in ("true", "gated"):
        raise ValueError(f"takes must be 'true' or 'gated', got {takes!r}")
    from scipy.spatial import cKDTree

    from gatv.stages import Problem, prepare
    from gatv.stages import gate as gate_of

    tau = _residual_deviation(scene) / np.sqrt(2.0)
    if tau == 0.0:
        return True, float("nan")
    full = prepare(scene.source, scene.target)
    used_s = np.zeros(len(scene.source), bool)
    used_t = np.zeros(len(scene.target), bool)
    left = list(range(scene.n_motions))
    first_tests = float("nan")
    while left:
        src, tgt = np.flatnonzero(~used_s), np.flatnonzero(~used_t)
        Y = scene.target[tgt]
        sub = Problem(scene.source[src], Y, full.model, cKDTree(Y), full.spacing, full.extent, full.volume)
        tests = search_tests(sub, len(scene.source)) if n_tests is None else float(n_tests)
        if np.isnan(first_tests):
            first_tests = tests
        margin, best, best_gate = -np.inf, None, None
        for k in left:
            moved = sub.source @ scene.rotations[k].T + scene.translations[k]
            for c in factors:
                g = gate_of(c * tau)
                d, _ = sub.tree.query(moved, distance_upper_bound=g)
                m = int(np.isfinite(d).sum()) - sub.chance(g, tests)
                if m > margin:
                    margin, best, best_gate = m, k, g
        if margin < 0:
            return False, first_tests
        if takes == "true":
            p = scene.true_pairs[best]
            used_s[p[:, 0]] = True
            used_t[p[:, 1]] = True
        else:
            moved = sub.source @ scene.rotations[best].T + scene.translations[best]
            d, j = sub.tree.query(moved, distance_upper_bound=best_gate)
            taken = np.zeros(len(tgt), bool)
            for i in np.argsort(d, kind="stable"):
                if not np.isfinite(d[i]):
                    break
                if not taken[j[i]]:
                    taken[j[i]] = True
                    used_s[src[i]] = True
                    used_t[tgt[j[i]]] = True
        left.remove(best)
    return True, first_tests


METHODS = {
    "auto": lambda s, t: segment(s, t),
    "graph": lambda s, t: segment(s, t, grouping="graph"),
    "greedy": lambda s, t: segment(s, t, grouping="greedy"),
    "ransac": lambda s, t: ransac_segment(s, t),
}
SCAN_METHODS = ("auto", "o3d-seq")
#: Methods that run on both kinds of rows.
BOTH = ("auto", "o3d-seq")
#: (method, kind of row) outside the method's domain: Open3D's FPFH describes the local surface
#: around a point (normals, then their angles), and the point-set rows are uniform points with no
#: surface; its rows there are reported, marked, and not read as a loss.
OUT_OF_DOMAIN = {("o3d-seq", "points"): "FPFH features on points with no surface"}


def in_domain(method: str, scans: bool) -> bool:
    """Whether ``method`` runs within its own domain on a scan row (``scans``) or a point-set row."""
    return (method, "scans" if scans else "points") not in OUT_OF_DOMAIN


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


def score_scans(scene, motions, labels) -> dict:
    """Compare ``[(R, t)]`` and source labels with a scan scene's truth (metres; errors in degrees and mm)."""
    K = scene.n_motions
    cost = np.array([[rotation_error_deg(R, scene.rotations[k]) + 1000.0 * translation_error(t, scene.translations[k])
                      for k in range(K)] for R, t in motions]).reshape(len(motions), K)
    match = {}
    if motions:
        r, c = linear_sum_assignment(cost)
        for a, b in zip(r, c):
            R, t = motions[a]
            if rotation_error_deg(R, scene.rotations[b]) < 5.0 and 1000 * translation_error(
                    t, scene.translations[b]) < 10.0:
                match[int(a)] = int(b)
    rot = {b: rotation_error_deg(motions[a][0], scene.rotations[b]) for a, b in match.items()}
    tr = {b: 1000.0 * translation_error(motions[a][1], scene.translations[b]) for a, b in match.items()}
    objects = [k for k in range(K) if not (scene.static and k == K - 1)]
    within = [k in match.values() and rot[k] < 1.0 and tr[k] < 3.0 for k in objects]
    remap = np.full(len(motions) + 1, -1)
    for a, b in match.items():
        remap[a] = b
    lab = remap[np.asarray(labels)]
    static_ok = True
    if scene.static:
        on_patch = scene.source_labels == K - 1
        static_ok = bool((K - 1) in match.values()) and float(np.mean(lab[on_patch] == K - 1)) > 0.9
    return {
        "exact_k": len(motions) == K, "n_found": len(motions), "spurious": len(motions) - len(match),
        "objects_ok": float(np.mean(within)) if within else 0.0,
        "rot_err_deg": max(rot.values()) if rot else float("nan"),
        "trans_err": max(tr.values()) if tr else float("nan"),
        "label_acc": float(np.mean(lab == scene.source_labels)), "static_ok": static_ok,
        "precision": float("nan"), "recall": float("nan"), "f1": float("nan"),
    }


def _peak_rss_gb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB -> GiB (Linux)


@functools.cache
def warm_up() -> None:
    """Untimed small calls, once a process, so that no trial's time holds the kernels' compilation.

    The first search of a process compiles gatv's kernels (a minute or more
    on a clean clone) or loads them from numba's cache: a small noisy
    two-motion scene through ``segment`` and a small noisy ``register``.
    """
    from gatv import register
    from gatv.datasets import table2_trial

    rng = np.random.default_rng(12345)
    rots, trans = _random_motions(rng, 2)
    obj = [rng.uniform(-5, 5, (30, 3)) for _ in range(2)]
    source = np.concatenate(obj)
    target = np.concatenate([o @ R.T + t for o, R, t in zip(obj, rots, trans)])
    target = target + rng.normal(scale=0.01 * RMS_RADIUS, size=target.shape)
    segment(source, target)
    trial = table2_trial(0.5, noise=0.01, seed=12345)
    register(trial.source, trial.target, seed=0)


@functools.cache
def warm_up_scans() -> None:
    """:func:`warm_up` for the scans path (tensor voting, the surface matcher): a small scene of two
    samplings of one bumpy surface, one moved, through ``segment`` (3,000 points a scan, so that the
    automatic choice takes the scans pipeline)."""
    rng = np.random.default_rng(12345)

    def bumpy(n):
        u = rng.normal(size=(n, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        r = 1.0 + 0.2 * np.sin(2.1 * u[:, 0] + 1.3 * u[:, 1]) + 0.1 * np.cos(3.0 * u[:, 2])
        return 0.05 * u * r[:, None]

    rots, _ = _random_motions(rng, 1)
    segment(bumpy(3000), bumpy(3000) @ rots[0].T + 0.01)


def run_task(task: tuple) -> list[dict]:
    """One trial of one row, every method on the same scene (module level: picklable for map_trials)."""
    name, row_index, trial, seed, methods = task
    seq = np.random.SeedSequence([seed, row_index, trial])
    scans = scan_row(name)[0] is not None
    if scans:
        warm_up_scans()
    else:
        warm_up()
    try:
        scene = make_scan_scene(name, np.random.default_rng(seq)) if scans else make_rows()[name](
            np.random.default_rng(seq))
    except FileNotFoundError as exc:  # DataNotFoundError: no real data here
        return [{"row": name, "method": m, "trial": trial, "K": 0, "n_points": 0, "time_s": float("nan"), "cpu_s": float("nan"), "load": float("nan"),
                 "error": f"no data: {exc}", "exact_k": False, "n_found": 0, "precision": 0.0, "recall": 0.0,
                 "f1": 0.0, "rot_err_deg": float("nan"), "trans_err": float("nan"), "label_acc": 0.0,
                 "spurious": 0, "objects_ok": 0.0, "static_ok": False, "peak_rss_gb": _peak_rss_gb()}
                for m in methods]
    out = []
    ceiling = float("nan") if scans else f1_ceiling(scene)
    greedy_ceiling = float("nan") if scans else f1_ceiling(scene, matching="greedy")
    k_ok, k_tests = (float("nan"), float("nan")) if scans else k_ceiling(scene)
    peel_ok = float("nan") if scans else float(k_ceiling(scene, takes="gated")[0])
    for method in methods:
        if scans != (method in SCAN_METHODS) and method not in BOTH:
            continue
        cpu0 = time.process_time()
        with Timer() as timer:
            try:
                if method == "o3d-seq":
                    motions, labels, pairs = o3d_sequential(scene.source, scene.target, seed=trial,
                                                            points=not scans)
                    seg = None if scans else _baseline_segmentation(len(scene.target), motions, labels, pairs)
                else:
                    seg = METHODS[method](scene.source, scene.target)
                    motions = [(m.rotation, m.translation) for m in seg]
                    labels = seg.source_labels
                error = ""
            except ImportError as exc:
                seg, motions, labels, error = None, [], np.full(len(scene.source), -1), f"not installed: {exc}"
            except Exception as exc:  # noqa: BLE001 - scored as a failure
                seg, motions, labels, error = None, [], np.full(len(scene.source), -1), f"{type(exc).__name__}: {exc}"
        rec = {"row": name, "method": method, "trial": trial, "K": scene.n_motions,
               "n_points": len(scene.source), "time_s": timer.seconds, "cpu_s": time.process_time() - cpu0,
               "load": os.getloadavg()[0], "error": error, "in_domain": in_domain(method, scans)}
        if scans:
            rec.update(score_scans(scene, motions, labels))
            rec["reason"] = seg.info.get("reason", "") if seg is not None else ""
        elif seg is None:
            rec.update(exact_k=False, n_found=0, precision=0.0, recall=0.0, f1=0.0,
                       rot_err_deg=float("nan"), trans_err=float("nan"), label_acc=0.0)
        else:
            rec.update(score(scene, seg))
        if not scans:
            rec["f1_ceiling"] = ceiling
            rec["f1_ceiling_greedy"] = greedy_ceiling
            rec["k_ceiling"] = float(k_ok)
            rec["k_ceiling_tests"] = k_tests
            rec["peel_ceiling"] = peel_ok
        rec["peak_rss_gb"] = _peak_rss_gb()
        out.append(rec)
    print(f"  {name} trial {trial}: " + ", ".join(
        f"{r['method']} {r['n_found']}/{r['K']} F1 {r['f1']:.3f} acc {r['label_acc']:.3f} {r['time_s']:.2f}s "
        f"(cpu {r['cpu_s']:.2f}s, load {r['load']:.1f})"
        for r in out), file=sys.stderr, flush=True)
    return out


def run(args) -> list[dict]:
    rows = make_rows()
    every = list(rows) + list(SCAN_ROWS)
    names = args.rows or list(rows)
    names += [f"{n} +{pct:g}{NOISE_SUFFIX}" for pct in args.scan_noise for n in names if n in SCAN_ROWS]
    unknown = [n for n in names if n not in every and scan_row(n)[0] is None]
    if unknown:
        raise SystemExit(f"unknown rows {unknown}; choose from {every}")
    # A noisy scan row draws the scene of its noise-free row (same seeds), then the noise.
    tasks = [(name, every.index(scan_row(name)[0] or name), trial, args.seed, tuple(args.methods))
             for name in names for trial in range(args.trials)]
    return [rec for recs in map_trials(run_task, tasks, scheduler=args.scheduler) for rec in recs]


def _mean(values):
    vals = [v for v in values if not np.isnan(v)]
    return float(np.mean(vals)) if vals else float("nan")


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
                "k_ceiling_pct": 100.0 * _mean(r.get("k_ceiling", float("nan")) for r in rs),
                "peel_ceiling_pct": 100.0 * _mean(r.get("peel_ceiling", float("nan")) for r in rs),
                "rot_err_deg": median(r["rot_err_deg"] for r in rs),
                "trans_err": median(r["trans_err"] for r in rs),
                "precision": _mean(r["precision"] for r in rs),
                "recall": _mean(r["recall"] for r in rs),
                "f1": _mean(r["f1"] for r in rs),
                "f1_ceiling": _mean(r.get("f1_ceiling", float("nan")) for r in rs),
                "f1_ceiling_greedy": _mean(r.get("f1_ceiling_greedy", float("nan")) for r in rs),
                "k_ceiling_tests": median(r.get("k_ceiling_tests", float("nan")) for r in rs),
                "in_domain": all(r.get("in_domain", True) for r in rs),
                "label_acc": float(np.mean([r["label_acc"] for r in rs])),
                "spurious": int(sum(r.get("spurious", 0) for r in rs)),
                "objects_ok_pct": 100.0 * _mean(r.get("objects_ok", float("nan")) for r in rs),
                "static_ok_pct": 100.0 * _mean(float(r["static_ok"]) if "static_ok" in r else float("nan")
                                               for r in rs),
                "time_s": median(r["time_s"] for r in rs),
                "max_time_s": float(np.nanmax([r["time_s"] for r in rs])),
                "cpu_s": median(r["cpu_s"] for r in rs),
                "max_cpu_s": float(np.nanmax([r["cpu_s"] for r in rs])),
                "load": float(np.mean([r["load"] for r in rs])),
                "peak_rss_gb": float(max(r.get("peak_rss_gb", 0.0) for r in rs)),
                "errors": sum(bool(r["error"]) for r in rs),
            })
    return out


def _method_cell(x) -> str:
    return x["method"] if x.get("in_domain", True) else f"{x['method']} (out of domain)"


def _pct(x):
    return "–" if np.isnan(x) else (fmt(x, 0) if x % 1 else str(int(x)))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--rows", type=parse_list(str), default=None, metavar="R,R,...")
    parser.add_argument("--scan-noise", type=parse_list(float), default=[], metavar="N,N",
                        help="also run each scan row with Gaussian noise of N%% of its first object's RMS radius "
                             "on every point of both scenes (rows named '<row> +N%% noise')")
    parser.add_argument("--methods", type=parse_list(str), default=["auto", "graph", "greedy", "ransac"],
                        metavar="M,M,...")
    add_scheduler_argument(parser)
    args = parser.parse_args(argv)
    bad = [m for m in args.methods if m not in METHODS and m not in SCAN_METHODS]
    if bad:
        parser.error(f"unknown methods {bad}; choose from {list(METHODS) + ['o3d-seq']}")
    records = run(args)
    names = list(dict.fromkeys(r["row"] for r in records))
    summary = summarise(records, names, args.methods)
    point_rows = [x for x in summary if scan_row(x["row"])[0] is None]
    scan_rows = [x for x in summary if scan_row(x["row"])[0] is not None]
    if point_rows:
        headers = ["row", "method", "trials", "K", "points", "exact K %", "exact K ceiling %", "peel ceiling %",
                   "rot err (deg)",
                   "t err", "precision", "recall", "F1", "F1 ceiling", "label acc", "median s", "max s",
                   "median cpu s", "max cpu s", "load"]
        table = [[x["row"], _method_cell(x), x["trials"], x["K"], x["points"], _pct(x["exact_k_pct"]),
                  _pct(x["k_ceiling_pct"]), _pct(x["peel_ceiling_pct"]), fmt(x["rot_err_deg"], 2), fmt(x["trans_err"], 2), fmt(x["precision"]),
                  fmt(x["recall"]), fmt(x["f1"]), fmt(x["f1_ceiling"]), fmt(x["label_acc"]),
                  fmt(x["time_s"], 2), fmt(x["max_time_s"], 1), fmt(x["cpu_s"], 2), fmt(x["max_cpu_s"], 1),
                  fmt(x["load"], 1)] for x in point_rows]
        print(markdown_table(headers, table, align="ll" + "r" * (len(headers) - 2)))
        print("\nrot/t err: median over trials of the worst matched motion; precision, recall, F1, label acc: "
              "mean over trials; F1 ceiling: the true motions' F1 with their pairs within the best gate taken "
              "one-to-one by gatv's maximum-weight matching (f1_ceiling, assign_pairs), mean over trials; exact K "
              "ceiling: scenes whose every true motion beats, at its true pose, the chance level of the matches its "
              "round's search scores (k_ceiling, search_tests); peel ceiling: the same when each motion kept takes "
              "out every point within its gate at its true pose, chance pairs too, as a peel must "
              "(k_ceiling(takes='gated')); cpu s: process CPU time (all threads); load: mean "
              "1-minute load average at the end of each trial.")
        ceil = [x for x in point_rows if not np.isnan(x["f1_ceiling"])]
        if ceil:
            print("F1 ceiling with greedy nearest-neighbour matching instead (the earlier ceiling, a lower bound): "
                  + "; ".join(f"{x['row']} {fmt(x['f1_ceiling_greedy'])}" for x in ceil
                              if x["method"] == ceil[0]["method"])
                  + ".  Matches scored a round (the exact K ceiling's n_tests, median over trials): "
                  + "; ".join(f"{x['row']} {x['k_ceiling_tests']:.3g}" for x in ceil
                              if x["method"] == ceil[0]["method"] and not np.isnan(x["k_ceiling_tests"])) + ".")
        for (m, kind), why in OUT_OF_DOMAIN.items():
            if kind == "points" and any(x["method"] == m for x in point_rows):
                print(f"(out of domain): {m} on point sets runs {why}; reported for completeness, not a loss.")
    if scan_rows:
        headers = ["scene", "method", "K", "points", "exact K %", "objects ok %", "worst rot (deg)",
                   "worst t (mm)", "spurious", "static ok %", "label acc", "median s", "max s", "median cpu s",
                   "max cpu s", "load", "peak RSS GB"]
        table = [[x["row"], x["method"], x["K"], x["points"], _pct(x["exact_k_pct"]), _pct(x["objects_ok_pct"]),
                  fmt(x["rot_err_deg"], 3), fmt(x["trans_err"], 2), x["spurious"], _pct(x["static_ok_pct"]),
                  fmt(x["label_acc"]), fmt(x["time_s"], 1), fmt(x["max_time_s"], 1), fmt(x["cpu_s"], 1),
                  fmt(x["max_cpu_s"], 1), fmt(x["load"], 1), fmt(x["peak_rss_gb"], 2)]
                 for x in scan_rows]
        print()
        print(markdown_table(headers, table, align="ll" + "r" * (len(headers) - 2)))
        print("\nK counts the static patch; objects ok: within 1 deg and 3 mm; spurious: found motions matching "
              "no true one within 5 deg and 10 mm (total over trials); peak RSS: of the benchmark process so far; "
              "cpu s: process CPU time (all threads); load: mean 1-minute load average at the end of each trial.")
    errors = sorted({r["error"] for r in records if r["error"]})
    for e in errors[:5]:
        print(f"error: {e}")
    keys = list(summary[0]) if summary else []
    write_csv(args.out / "motions.csv", keys, [[x[k] for k in keys] for x in summary])
    tkeys = sorted({k for r in records for k in r}, key=lambda k: (k not in records[0], k)) if records else []
    write_csv(args.out / "motions_trials.csv", tkeys, [[r.get(k, "") for k in tkeys] for r in records])
    print(f"\nwrote {args.out / 'motions.csv'} and {args.out / 'motions_trials.csv'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
