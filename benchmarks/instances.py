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

Real scans (``--real``, ``''`` to skip): ``--real-instances`` copies of one
real view at random poses (centroids at least 1.2 model sizes apart) among
``--real-clutter`` (30%) uniform clutter, another real view of the object as
the model: the bunny (copies of bun045, the model bun000, ground truth from
``bun.conf``) and the UWA chef and parasaurolophus (copies of view002, the
model view001, the data's pseudo ground truth); ``null``: copies of the
parasaurolophus with the chef as the model, where every instance found is
spurious.  Scored: copies within 1° and 3 mm (the moved model's centroid),
spurious instances, the worst error when every copy is hit, the time.

Sequences (``--frames``, 0 to skip): ``--frames`` frames of 1 to 3 copies
moving independently (each turns by up to 20° and moves by up to a third of
its size between frames: no motion model could predict it), Gaussian noise
of ``--noise`` (2%) of the model's RMS radius (as the other benchmarks'
noise; ``--noise-of size``: of its bounding-box diagonal) on every scene
point, 30% clutter; :func:`gatv.motions.track` on the frames, and each peer
on each frame with identities given as ``track`` gives them.  Scored: F1
per frame as above, and whether an identity ever moved to another true copy
(a swap).

Peers, in the same run, only when installed: ``o3d-seq`` (sequential Open3D
RANSAC on FPFH features: register, remove the scene points within the
gate, repeat until the fit keeps fewer than 10% of the model) and
``kiss-seq`` (KISS-Matcher the same way); voxel: the model's size over 25;
on sets over :data:`DENSE_POINTS` points (the real scans) features on a
voxel subsample and each pose polished at full resolution.  Without them
their rows say "not installed".

Usage::

    python benchmarks/instances.py [--meshes bunny,ant,airplane,nut] [--instances 1,5,10,20]
                                   [--clutter 0,0.3,0.5] [--scenes 3] [--frames 10] [--seed 0]
                                   [--real bunny,chef,parasaurolophus,null] [--real-instances 2,3]
                                   [--real-scenes 1] [--noise 0.02] [--noise-of rms|size]
                                   [--methods gatv,o3d-seq,kiss-seq] [--out benchmarks/results]

Prints markdown tables; writes ``instances.csv``, ``instances_real.csv`` and
``instances_tracks.csv``.
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

from _common import DEFAULT_OUT, markdown_table, o3d_polish, parse_list, write_csv
from gatv.io import read_points
from gatv.motions import instances, track
from gatv.motions.instance_search import model_size
from gatv.motions.tracking import assign_identities

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


def noise_scale(model, of: str) -> float:
    """The length the sequences' ``--noise`` is a share of: the model's RMS radius (``rms``, as the other
    benchmarks' noise) or its bounding-box diagonal (``size``, this benchmark's first runs)."""
    if of == "size":
        return model_size(model)
    return float(np.sqrt(np.mean(np.sum((model - model.mean(axis=0)) ** 2, axis=1))))


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


#: Points in a set beyond which the peers match features on a voxel subsample (the real scans) and
#: polish each pose at full resolution, as ``benchmarks/scans.py`` runs them.
DENSE_POINTS = 5000


def _sequential(model, scene, estimate, voxel):
    """Register with ``estimate(left) -> (R, t)`` (``None``: none), remove the scene points within the gate, repeat.

    The gate is 1.5 voxels; the loop ends when a pose keeps fewer than 10%
    of the model's points there.  On dense sets (:data:`DENSE_POINTS`) each
    pose is polished at full resolution first.
    """
    dense = max(model.shape[0], scene.shape[0]) > DENSE_POINTS
    left = scene.copy()
    out = []
    while left.shape[0] >= 10:
        pose = estimate(left)
        if pose is None:
            break
        R, t = pose
        if dense:
            R, t = o3d_polish(model, left, R, t, voxel)
        moved = model @ R.T + t
        near = np.isfinite(cKDTree(moved).query(left, distance_upper_bound=1.5 * voxel)[0])
        if near.sum() < 0.1 * model.shape[0]:
            break
        out.append((R, t))
        left = left[~near]
    return out


def run_o3d_sequential(model, scene, seed: int) -> list:
    """Sequential Open3D RANSAC+FPFH: register, remove the scene points within the gate, repeat."""
    import open3d as o3d

    voxel = model_size(model) / 25.0
    reg = o3d.pipelines.registration
    dense = max(model.shape[0], scene.shape[0]) > DENSE_POINTS

    def cloud(pts):
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        if dense:
            pc = pc.voxel_down_sample(voxel)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        return pc, reg.compute_fpfh_feature(pc, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))

    src, fs = cloud(model)
    o3d.utility.random.seed(seed)

    def estimate(left):
        tgt, ft = cloud(left)
        res = reg.registration_ransac_based_on_feature_matching(
            src, tgt, fs, ft, True, 1.5 * voxel, reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
            reg.RANSACConvergenceCriteria(100000, 0.999))
        T = np.asarray(res.transformation)
        return T[:3, :3], T[:3, 3]

    return _sequential(model, scene, estimate, voxel)


def run_kiss_sequential(model, scene, seed: int) -> list:
    """Sequential KISS-Matcher: register, remove the scene points within the gate, repeat.

    KISS-Matcher takes its voxel by hand and refuses millimetre voxels on
    metre-scale data (``benchmarks/scans.py``), so both sets are scaled to a
    100-unit model diagonal for it and its translation scaled back.
    """
    import kiss_matcher

    size = model_size(model)
    voxel, scale = size / 25.0, 100.0 / size
    src = np.ascontiguousarray(model * scale)

    def solve(left):
        matcher = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(voxel * scale))
        sol = matcher.estimate(src, np.ascontiguousarray(left * scale))
        return np.asarray(sol.rotation, dtype=np.float64), np.asarray(sol.translation, dtype=np.float64).ravel() / scale

    def estimate(left):
        # KISS-Matcher 1.x crashes the process (SIGSEGV) on some small leftovers of a scene (a 188-point
        # one here): each call runs in a forked child, and a crash ends the loop as "no more instances".
        return _in_child(solve, left)

    return _sequential(model, scene, estimate, voxel)


def _in_child(fn, *args):
    """``fn(*args)`` in a forked child process; ``None`` when the child dies (a crash in a peer's C++ code)."""
    import os
    import pickle

    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: compute, send, leave without running the parent's exit handlers
        os.close(read)
        try:
            data = pickle.dumps(fn(*args))
            with os.fdopen(write, "wb") as pipe:
                pipe.write(data)
        finally:
            os._exit(0)
    os.close(write)
    with os.fdopen(read, "rb") as pipe:
        data = pipe.read()
    _, status = os.waitpid(pid, 0)
    return pickle.loads(data) if data and os.WIFEXITED(status) else None


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


#: Real-scan scenes: ``name -> (model view, copied view)``; the bunny scans (metres) and the UWA views (mm).
#: ``null``: copies of another object (parasaurolophus view002) with the chef's view001 as the model.
REAL = {"bunny": ("bun000", "bun045"), "chef": ("view001", "view002"), "parasaurolophus": ("view001", "view002"),
        "null": ("chef view001", "parasaurolophus view002")}
#: The issue's bar on real scans: every instance within 1 degree and 3 mm.
REAL_DEG, REAL_MM = 1.0, 3.0


def real_scene(name: str, k: int, clutter: float, rng) -> tuple:
    """``(model, scene, poses, mm)``: ``k`` copies of one real view at random poses among clutter.

    The model is another real view of the object (``REAL``); each pose maps
    the model onto one copy through the data's (pseudo) ground truth between
    the two views, ``p_model = R p_view + t``.  Copies lie apart (centroids at
    least 1.2 model sizes), as parts on a table; clutter is uniform in the
    copies' bounding box, the share ``clutter`` of the scene.
    """
    from gatv.datasets import load_bunny_pair, load_uwa_pair

    if name == "bunny":
        model, view, R, t = load_bunny_pair(*REAL[name])
        mm = 1000.0
    elif name == "null":  # the model is not in the scene: every instance found is spurious
        model, view, R, t = load_uwa_pair("chef")[0], load_uwa_pair("parasaurolophus")[1], None, None
        mm = 1.0
    else:
        model, view, R, t = load_uwa_pair(name)
        mm = 1.0
    size = model_size(model)
    centres: list = []
    side = 1.6 * size * max(1.0, k ** (1.0 / 3.0))
    while len(centres) < k:
        c = rng.uniform(0.0, side, 3)
        if all(np.linalg.norm(c - d) >= 1.2 * size for d in centres):
            centres.append(c)
        else:
            side *= 1.01
    rots = Rotation.random(k, random_state=rng).as_matrix().reshape(k, 3, 3)
    centre = view.mean(axis=0)
    copies, poses = [], []
    for Q, c in zip(rots, centres):
        q = c - Q @ centre  # the view at pose (Q, q); the model at Q R^T, q - Q R^T t
        copies.append(view @ Q.T + q)
        if R is not None:
            poses.append((Q @ R.T, q - Q @ R.T @ t))
    pts = np.vstack(copies)
    n_clutter = int(round(clutter / (1.0 - clutter) * pts.shape[0]))
    scene = np.vstack([pts, rng.uniform(pts.min(axis=0), pts.max(axis=0), (n_clutter, 3))])
    return model, scene[rng.permutation(scene.shape[0])], poses, mm


def real_rows(args) -> list[dict]:
    records = []
    for name in args.real:
        for k in args.real_instances:
            for s in range(args.real_scenes):
                rng = np.random.default_rng([args.seed, 41, k, s, len(name)])
                model, scene, poses, mm = real_scene(name, k, args.real_clutter, rng)
                centre = model.mean(axis=0)
                for method in args.methods:
                    fn, module = RUNNERS[method]
                    rec = {"object": name, "k": k, "true": len(poses), "scene": s, "method": method,
                           "n_scene": int(scene.shape[0])}
                    if module is not None and not _installed(module):
                        records.append({**rec, "status": "not installed"})
                        continue
                    t0 = time.perf_counter()
                    found = fn(model, scene, args.seed + s)
                    seconds = time.perf_counter() - t0
                    # each true copy's error by its closest found instance (one-to-one, Hungarian)
                    n_true = len(poses)
                    errs = np.full((len(found), n_true, 2), np.inf)
                    for i, (R, t) in enumerate(found):
                        for j, p in enumerate(poses):
                            a, d = pose_errors(R, t, p, centre)
                            errs[i, j] = a, d * mm
                    within = (errs[..., 0] <= REAL_DEG) & (errs[..., 1] <= REAL_MM)
                    hits, worst = 0, (np.nan, np.nan)
                    if found and n_true:
                        r, c = linear_sum_assignment(np.where(within, 0.0, 1.0) + errs[..., 0] / 1e3)
                        hits = int(within[r, c].sum())
                        if hits == n_true:
                            worst = (float(errs[r, c, 0].max()), float(errs[r, c, 1].max()))
                    rec.update(status="ran", found=len(found), hits=hits, spurious=len(found) - hits,
                               worst_deg=worst[0], worst_mm=worst[1], time_s=seconds)
                    records.append(rec)
                    print(f"# real {name} k={k} scene {s} {method}: {hits}/{len(poses)} within {REAL_DEG} deg and "
                          f"{REAL_MM} mm, {len(found)} found, {seconds:.1f} s", file=sys.stderr, flush=True)
    return records


def sequence_rows(args) -> list[dict]:
    records = []
    for mesh in args.meshes:
        model = load_model(mesh, args.model_points)
        size, scale = model_size(model), noise_scale(model, args.noise_of)
        for k in (1, 2, 3):
            rng = np.random.default_rng([args.seed, 7, k, len(mesh)])
            poses = random_poses(model, k, rng)
            truth, frames = [], []
            for f in range(args.frames):
                if f:
                    poses = [(Rotation.from_rotvec(_capped(rng, np.radians(20.0))).as_matrix() @ R,
                              t + _capped(rng, size / 3.0)) for R, t in poses]
                truth.append(poses)
                frames.append(make_scene(model, poses, 0.0, 0.3, args.noise * scale, rng))
            for method in args.methods:
                fn, module = RUNNERS[method]
                rec = {"mesh": mesh, "k": k, "frames": args.frames, "method": method}
                if module is not None and not _installed(module):
                    records.append({**rec, "status": "not installed"})
                    continue
                t0 = time.perf_counter()
                if method == "gatv":
                    out = track(model, frames, seed=args.seed)
                    found = [[(m.rotation, m.translation) for m in fr] for fr in out.frames]
                    identities = [list(ids) for ids in out.identities]
                else:  # the peer on each frame, identities by the closest pose as track gives them
                    found = [fn(model, frame, args.seed) for frame in frames]
                seconds = time.perf_counter() - t0
                if method != "gatv":
                    identities = assign_identities([_Frame(fr) for fr in found], model.mean(axis=0), size)[0]
                scores = [score(fr, truth[f], model) for f, fr in enumerate(found)]
                rec.update(status="ran", f1=float(np.mean([s["f1"] for s in scores])),
                           recall=float(np.mean([s["recall"] for s in scores])),
                           precision=float(np.mean([s["precision"] for s in scores])),
                           identities=len({i for ids in identities for i in ids}),
                           swaps=_swaps(found, identities, truth, model), time_s=seconds,
                           time_per_frame_s=seconds / args.frames)
                records.append(rec)
                print(f"# sequence {mesh} k={k} {method}: F1 {rec['f1']:.3f}, {rec['identities']} identities, "
                      f"{rec['swaps']} swaps, {seconds:.1f} s", file=sys.stderr, flush=True)
    return records


class _Frame:
    """A peer's poses of one frame, as :func:`gatv.motions.tracking.assign_identities` reads them."""

    def __init__(self, poses):
        self.instances = tuple(_Pose(R, t) for R, t in poses)


class _Pose:
    def __init__(self, R, t):
        self.rotation, self.translation = np.asarray(R), np.asarray(t)


def _capped(rng, bound: float) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v) * rng.uniform(0.0, bound)


def _swaps(found, identities, truth, model) -> int:
    """Identities whose true copy (the closest hit) changed between frames where they were hit."""
    centre, size = model.mean(axis=0), model_size(model)
    owner: dict = {}
    swaps = 0
    for f, (fr, ids) in enumerate(zip(found, identities)):
        for (R, t), ident in zip(fr, ids):
            errs = [pose_errors(R, t, p, centre) for p in truth[f]]
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
    p.add_argument("--noise", type=float, default=0.02,
                   help="sequence noise, a share of the model's RMS radius (default: 0.02)")
    p.add_argument("--noise-of", choices=("rms", "size"), default="rms",
                   help="what --noise is a share of: the RMS radius (default) or the bounding-box diagonal")
    p.add_argument("--real", type=parse_list(str), default=list(REAL), metavar="O,O,...",
                   help="real-scan scenes (bunny, chef, parasaurolophus, null: another object's copies); '' for none")
    p.add_argument("--real-instances", type=parse_list(int), default=[2, 3], metavar="K,K,...")
    p.add_argument("--real-scenes", type=int, default=1, help="real-scan scenes per cell (default: 1)")
    p.add_argument("--real-clutter", type=float, default=0.3, help="real-scan clutter share (default: 0.3)")
    p.add_argument("--methods", type=parse_list(str), default=list(METHODS), metavar="M,M,...")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = p.parse_args(argv)
    args.real = [r for r in args.real if r]
    missing = [m for m in args.meshes if m not in MESHES] + [r for r in args.real if r not in REAL]
    if missing or any(m not in METHODS for m in args.methods):
        p.error(f"unknown mesh, real scene or method: {missing or args.methods}")
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
    if args.real and args.real_scenes > 0:
        real = real_rows(args)
        print("\n## Real scans (copies of one view, another view as the model)\n")
        h = ["object", "copies", "method", "scene points", f"within {REAL_DEG:g} deg, {REAL_MM:g} mm", "spurious",
             "worst deg", "worst mm", "s"]
        rows = []
        for r in real:
            if r["status"] != "ran":
                rows.append([r["object"], r["k"], r["method"], r["n_scene"], r["status"], "", "", "", ""])
                continue
            rows.append([r["object"], r["k"], r["method"], r["n_scene"], f"{r['hits']}/{r['true']}", r["spurious"],
                         f"{r['worst_deg']:.3f}", f"{r['worst_mm']:.2f}", f"{r['time_s']:.1f}"])
        print(markdown_table(h, rows, align="lrlr" + "r" * 5))
        cols = ["object", "k", "true", "scene", "method", "status", "n_scene", "found", "hits", "spurious", "worst_deg",
                "worst_mm", "time_s"]
        write_csv(args.out / "instances_real.csv", cols, [[r.get(c, "") for c in cols] for r in real])
    if args.frames > 0:
        seq = sequence_rows(args)
        print("\n## Sequences (each frame searched on its own; identities by the closest pose)\n")
        h = ["mesh", "instances", "frames", "method", "F1 per frame", "recall", "precision", "identities",
             "swaps", "s per frame"]
        rows = []
        for r in seq:
            if r["status"] != "ran":
                rows.append([r["mesh"], r["k"], r["frames"], r["method"], r["status"], "", "", "", "", ""])
                continue
            rows.append([r["mesh"], r["k"], r["frames"], r["method"], f"{r['f1']:.3f}", f"{r['recall']:.3f}",
                         f"{r['precision']:.3f}", r["identities"], r["swaps"], f"{r['time_per_frame_s']:.1f}"])
        print(markdown_table(h, rows, align="lrrl" + "r" * 6))
        cols = ["mesh", "k", "frames", "method", "status", "f1", "recall", "precision", "identities", "swaps",
                "time_s"]
        write_csv(args.out / "instances_tracks.csv", cols, [[r.get(c, "") for c in cols] for r in seq])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
