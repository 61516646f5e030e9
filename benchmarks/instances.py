"""Every instance of a model in a scene, and a model tracked through frames (issue 41).

Protocol (the synthetic one of ECC, CVPR 2022, with the meshes of
``../shared/data``): the vertices of a mesh (the Stanford bunny
reconstruction at res4, PyVista's ant, airplane and nut), subsampled to
``--model-points`` points, are the model.  A scene holds ``k`` copies of it
(``--instances``, 1 to 20), each at a random pose (rotation uniform, centres
at least one model size apart in a cube that grows with ``k``), each a
*partial* copy: ``--cut`` (30%) of its points cut away by a plane of random
direction.  Clutter: uniform points in the scene's bounding box, a share
``c`` of the scene's points after adding (``--clutter``, 0 / 30 / 50%).

Scores (ECC's mean-hit): a found instance *hits* a true one when its
rotation is within 5° and the moved model's centroid within 5% of the
model's size (bounding-box diagonal) of the truth; found and true instances
are paired one-to-one (Hungarian on the pose distance).  Per scene, recall =
hits / true instances, precision = hits / found (1 when nothing is found
and nothing was there), F1 their harmonic mean; the table gives the means
over the scenes and the median and max time per scene.  The nut has a
six-fold symmetry: a copy found in a symmetric pose is a miss by this
score, as in ECC's.

Sequences (``--frames``, 0 to skip): ``--frames`` frames of 1 to 3 copies
moving independently (each turns by up to 20° and moves by up to a third of
its size between frames: no motion model could predict it), Gaussian noise
of ``--noise`` (2%) of the model's size on every scene point, 30% clutter;
:func:`gatv.motions.track` on the frames.  Scored: F1 per frame as above,
and whether an identity ever moved to another true copy (a swap).

Peers, in the same run, only when installed: ``o3d-seq`` (sequential Open3D
RANSAC on FPFH features: register, remove the scene points within the
gate, repeat until the fit keeps fewer than 10% of the model) and
``kiss-seq`` (KISS-Matcher the same way).  Without them their rows say
"not installed".

Usage::

    python benchmarks/instances.py [--meshes bunny,ant,airplane,nut] [--instances 1,5,10,20]
                                   [--clutter 0,0.3,0.5] [--scenes 3] [--frames 10] [--seed 0]
                                   [--methods gatv,o3d-seq,kiss-seq] [--out benchmarks/results]

Prints markdown tables; writes ``instances.csv`` and ``instances_tracks.csv``.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from _common import DEFAULT_OUT, markdown_table, parse_list, write_csv
from gatv.io import read_points
from gatv.motions import instances, track
from gatv.motions.instance_search import model_size

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
MESHES = {
    "bunny": DATA / "stanford_bunny_reconstruction" / "bun_zipper_res4.ply",
    "ant": DATA / "pyvista_example_meshes" / "ant.ply",
    "airplane": DATA / "pyvista_example_meshes" / "airplane.ply",
    "nut": DATA / "pyvista_example_meshes" / "nut.ply",
}
#: ECC's hit: within 5 degrees and 5% of the model's size.
HIT_DEG, HIT_SIZE = 5.0, 0.05
METHODS = ("gatv", "o3d-seq", "kiss-seq")


# ------------------------------------------------------------------ scenes
def load_model(name: str, n_points: int, seed: int = 0) -> np.ndarray:
    """The mesh's vertices, duplicates dropped, subsampled to ``n_points`` (a fixed draw)."""
    pts = np.unique(read_points(MESHES[name]), axis=0)
    if pts.shape[0] > n_points:
        pts = pts[np.sort(np.random.default_rng(seed).choice(pts.shape[0], n_points, replace=False))]
    return pts


def random_poses(model, k: int, rng) -> list:
    """``k`` poses: uniform rotations, moved centroids at least one model size apart."""
    size, centre = model_size(model), model.mean(axis=0)
    side = size * 1.6 * max(1.0, k ** (1.0 / 3.0))
    centres: list = []
    while len(centres) < k:
        c = rng.uniform(0.0, side, 3)
        if all(np.linalg.norm(c - d) >= size for d in centres):
            centres.append(c)
        else:
            side *= 1.01  # crowded: widen the cube a little
    rots = Rotation.random(k, random_state=rng).as_matrix().reshape(k, 3, 3)
    return [(R, c - R @ centre) for R, c in zip(rots, centres)]


def partial_copy(model, pose, cut: float, rng) -> np.ndarray:
    """The model at ``pose`` with the share ``cut`` of its points cut away by a random plane."""
    R, t = pose
    pts = model @ R.T + t
    if cut <= 0:
        return pts
    normal = rng.normal(size=3)
    d = model @ (normal / np.linalg.norm(normal))
    return pts[d > np.quantile(d, cut)]


def make_scene(model, poses, cut: float, clutter: float, noise: float, rng) -> np.ndarray:
    """Partial copies at ``poses``, Gaussian ``noise`` (data units), then clutter (a share of the scene)."""
    pts = np.vstack([partial_copy(model, p, cut, rng) for p in poses]) if poses else np.empty((0, 3))
    if noise > 0:
        pts = pts + rng.normal(0.0, noise, pts.shape)
    n_clutter = int(round(clutter / (1.0 - clutter) * pts.shape[0])) if clutter < 1 else 0
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    scene = np.vstack([pts, rng.uniform(lo, hi, (n_clutter, 3))])
    return scene[rng.permutation(scene.shape[0])]


# ------------------------------------------------------------------ scores
def pose_errors(R, t, pose, centre) -> tuple[float, float]:
    """Rotation error (degrees) and the moved centroid's error."""
    Rt, tt = pose
    cos = (np.trace(Rt.T @ R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1)))), float(np.linalg.norm(R @ centre + t - Rt @ centre - tt))


def score(found, poses, model) -> dict:
    """Hits, recall, precision, F1 of ``found`` (a list of ``(R, t)``) against the true ``poses``."""
    centre, size = model.mean(axis=0), model_size(model)
    n_true, n_found = len(poses), len(found)
    hits = 0
    if n_true and n_found:
        hit = np.zeros((n_found, n_true), bool)
        cost = np.zeros((n_found, n_true))
        for i, (R, t) in enumerate(found):
            for j, p in enumerate(poses):
                a, d = pose_errors(R, t, p, centre)
                hit[i, j] = a <= HIT_DEG and d <= HIT_SIZE * size
                cost[i, j] = np.radians(a) + d / size + (0.0 if hit[i, j] else 1e3)
        rows, cols = linear_sum_assignment(cost)
        hits = int(hit[rows, cols].sum())
    recall = hits / n_true if n_true else 1.0
    precision = hits / n_found if n_found else (1.0 if not n_true else 0.0)
    f1 = 2 * recall * precision / (recall + precision) if recall + precision > 0 else 0.0
    return {"hits": hits, "found": n_found, "true": n_true, "recall": recall, "precision": precision, "f1": f1}


# ------------------------------------------------------------------ methods
def run_gatv(model, scene, seed: int) -> list:
    found = instances(model, scene, seed=seed)
    return [(m.rotation, m.translation) for m in found]


def _installed(module: str) -> bool:
    return importlib.util.find_spec(module) is not None


def run_o3d_sequential(model, scene, seed: int) -> list:
    """Sequential Open3D RANSAC+FPFH: register, remove the scene points within the gate, repeat."""
    import open3d as o3d

    size = model_size(model)
    voxel = size / 25.0
    reg = o3d.pipelines.registration

    def cloud(pts):
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        return pc, reg.compute_fpfh_feature(pc, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))

    src, fs = cloud(model)
    left = scene.copy()
    out = []
    o3d.utility.random.seed(seed)
    while left.shape[0] >= 10:
        tgt, ft = cloud(left)
        res = reg.registration_ransac_based_on_feature_matching(
            src, tgt, fs, ft, True, 1.5 * voxel, reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
            reg.RANSACConvergenceCriteria(100000, 0.999))
        T = np.asarray(res.transformation)
        moved = model @ T[:3, :3].T + T[:3, 3]
        near = np.isfinite(cKDTree(moved).query(left, distance_upper_bound=1.5 * voxel)[0])
        if near.sum() < 0.1 * model.shape[0]:
            break
        out.append((T[:3, :3], T[:3, 3]))
        left = left[~near]
    return out


def run_kiss_sequential(model, scene, seed: int) -> list:
    """Sequential KISS-Matcher: register, remove the scene points within the gate, repeat."""
    import kiss_matcher

    size = model_size(model)
    voxel = size / 25.0
    left = scene.copy()
    out = []
    while left.shape[0] >= 10:
        matcher = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(voxel))
        sol = matcher.estimate(model, left)
        R, t = np.asarray(sol.rotation), np.asarray(sol.translation).ravel()
        moved = model @ R.T + t
        near = np.isfinite(cKDTree(moved).query(left, distance_upper_bound=1.5 * voxel)[0])
        if near.sum() < 0.1 * model.shape[0]:
            break
        out.append((R, t))
        left = left[~near]
    return out


RUNNERS = {"gatv": (run_gatv, None), "o3d-seq": (run_o3d_sequential, "open3d"),
           "kiss-seq": (run_kiss_sequential, "kiss_matcher")}


# ------------------------------------------------------------------ runs
def scene_rows(args) -> list[dict]:
    records = []
    for mesh in args.meshes:
        model = load_model(mesh, args.model_points)
        for k in args.instances:
            for clutter in args.clutter:
                for s in range(args.scenes):
                    rng = np.random.default_rng([args.seed, k, int(round(100 * clutter)), s, len(mesh)])
                    poses = random_poses(model, k, rng)
                    scene = make_scene(model, poses, args.cut, clutter, 0.0, rng)
                    for method in args.methods:
                        fn, module = RUNNERS[method]
                        if module is not None and not _installed(module):
                            records.append({"mesh": mesh, "k": k, "clutter": clutter, "scene": s,
                                            "method": method, "status": "not installed"})
                            continue
                        t0 = time.perf_counter()
                        found = fn(model, scene, args.seed + s)
                        seconds = time.perf_counter() - t0
                        rec = {"mesh": mesh, "k": k, "clutter": clutter, "scene": s, "method": method,
                               "status": "ran", "n_scene": int(scene.shape[0]), "time_s": seconds,
                               **score(found, poses, model)}
                        records.append(rec)
                        print(f"# {mesh} k={k} clutter={clutter:.0%} scene {s} {method}: "
                              f"{rec['hits']}/{k} hits, {rec['found']} found, {seconds:.1f} s",
                              file=sys.stderr, flush=True)
    return records


def sequence_rows(args) -> list[dict]:
    records = []
    for mesh in args.meshes:
        model = load_model(mesh, args.model_points)
        size = model_size(model)
        for k in (1, 2, 3):
            rng = np.random.default_rng([args.seed, 7, k, len(mesh)])
            poses = random_poses(model, k, rng)
            truth, frames = [], []
            for f in range(args.frames):
                if f:
                    poses = [(Rotation.from_rotvec(_capped(rng, np.radians(20.0))).as_matrix() @ R,
                              t + _capped(rng, size / 3.0)) for R, t in poses]
                truth.append(poses)
                frames.append(make_scene(model, poses, 0.0, 0.3, args.noise * size, rng))
            t0 = time.perf_counter()
            out = track(model, frames, seed=args.seed)
            seconds = time.perf_counter() - t0
            f1 = [score([(m.rotation, m.translation) for m in fr], truth[f], model)["f1"]
                  for f, fr in enumerate(out.frames)]
            swaps = _swaps(out, truth, model)
            rec = {"mesh": mesh, "k": k, "frames": args.frames, "f1": float(np.mean(f1)),
                   "identities": out.n_identities, "swaps": swaps, "time_s": seconds,
                   "time_per_frame_s": seconds / args.frames}
            records.append(rec)
            print(f"# sequence {mesh} k={k}: F1 {rec['f1']:.3f}, {out.n_identities} identities, {swaps} swaps, "
                  f"{seconds:.1f} s", file=sys.stderr, flush=True)
    return records


def _capped(rng, bound: float) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v) * rng.uniform(0.0, bound)


def _swaps(out, truth, model) -> int:
    """Identities whose true copy (the closest hit) changed between frames where they were hit."""
    centre, size = model.mean(axis=0), model_size(model)
    owner: dict = {}
    swaps = 0
    for f, (fr, ids) in enumerate(zip(out.frames, out.identities)):
        for m, ident in zip(fr, ids):
            errs = [pose_errors(m.rotation, m.translation, p, centre) for p in truth[f]]
            best = int(np.argmin([np.radians(a) + d / size for a, d in errs]))
            a, d = errs[best]
            if a > HIT_DEG or d > HIT_SIZE * size:
                continue
            if ident in owner and owner[ident] != best:
                swaps += 1
            owner[ident] = best
    return swaps


def summarise(records) -> tuple[list, list]:
    headers = ["mesh", "instances", "clutter", "method", "scenes", "recall", "precision", "F1", "median s",
               "max s"]
    rows = []
    keys = list(dict.fromkeys((r["mesh"], r["k"], r["clutter"], r["method"]) for r in records))
    for mesh, k, clutter, method in keys:
        group = [r for r in records if (r["mesh"], r["k"], r["clutter"], r["method"]) == (mesh, k, clutter, method)]
        if group[0]["status"] != "ran":
            rows.append([mesh, k, f"{clutter:.0%}", method, len(group), group[0]["status"], "", "", "", ""])
            continue
        mean = {m: float(np.mean([r[m] for r in group])) for m in ("recall", "precision", "f1")}
        times = [r["time_s"] for r in group]
        rows.append([mesh, k, f"{clutter:.0%}", method, len(group), f"{mean['recall']:.3f}",
                     f"{mean['precision']:.3f}", f"{mean['f1']:.3f}", f"{np.median(times):.1f}",
                     f"{max(times):.1f}"])
    return headers, rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--meshes", type=parse_list(str), default=list(MESHES), metavar="M,M,...")
    p.add_argument("--instances", type=parse_list(int), default=[1, 5, 10, 20], metavar="K,K,...")
    p.add_argument("--clutter", type=parse_list(float), default=[0.0, 0.3, 0.5], metavar="C,C,...")
    p.add_argument("--scenes", type=int, default=3, help="scenes per cell (default: 3)")
    p.add_argument("--model-points", type=int, default=150, help="model points (default: 150)")
    p.add_argument("--cut", type=float, default=0.3, help="share of each copy cut away (default: 0.3)")
    p.add_argument("--frames", type=int, default=10, help="frames per sequence; 0: no sequences (default: 10)")
    p.add_argument("--noise", type=float, default=0.02, help="sequence noise, share of the model size")
    p.add_argument("--methods", type=parse_list(str), default=list(METHODS), metavar="M,M,...")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)
    missing = [m for m in args.meshes if m not in MESHES]
    if missing or any(m not in METHODS for m in args.methods):
        p.error(f"unknown mesh or method: {missing or args.methods}")
    if not all(MESHES[m].is_file() for m in args.meshes):
        print(f"the meshes are not in {DATA}: nothing to run", file=sys.stderr)
        return 1
    records = scene_rows(args)
    headers, rows = summarise(records)
    print("## Instances (synthetic, ECC's protocol)\n")
    print(markdown_table(headers, rows, align="lrrl" + "r" * (len(headers) - 4)))
    cols = ["mesh", "k", "clutter", "scene", "method", "status", "n_scene", "hits", "found", "true", "recall",
            "precision", "f1", "time_s"]
    write_csv(args.out / "instances.csv", cols, [[r.get(c, "") for c in cols] for r in records])
    if args.frames > 0:
        seq = sequence_rows(args)
        print("\n## Sequences (track: each frame searched on its own)\n")
        h = ["mesh", "instances", "frames", "F1 per frame", "identities", "swaps", "s per frame"]
        print(markdown_table(h, [[r["mesh"], r["k"], r["frames"], f"{r['f1']:.3f}", r["identities"], r["swaps"],
                                  f"{r['time_per_frame_s']:.1f}"] for r in seq], align="l" + "r" * 6))
        cols = ["mesh", "k", "frames", "f1", "identities", "swaps", "time_s"]
        write_csv(args.out / "instances_tracks.csv", cols, [[r[c] for c in cols] for r in seq])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
