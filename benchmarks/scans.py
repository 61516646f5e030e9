"""Real scans, no initial guess: gatv.register against Open3D on the shared real pairs.

Protocol: the five Stanford bunny pairs of ``gt_pairs.txt`` (metres) and the
UWA chef and parasaurolophus view pairs (millimetres; *pseudo* ground truth,
about ±0.1° / ±0.3 mm, made with Open3D's own FPFH + RANSAC + point-to-plane
ICP (../shared/data/README.md): on those two pairs the ``o3d-*`` rows are
judged against their own pipeline's answer, so their errors there are a
lower bound, not a fair comparison).  For each pair the source view is re-posed by a
random rotation of any size (axis uniform, angle uniform in 0..360°) and a
translation of up to a fifth of the target's extent per axis, so the true
motion is the ground truth composed with that known motion.  Each pair runs
at every clutter level: ``c`` uniform points added to each view's bounding
box, as a share ``c`` of the view's points after adding (0, 30 and 50% by
default).  With ``--overlap F`` the target is cropped by a plane of random
direction so that only the share ``F`` of the source's points lie on it
(within 5 mm after the true motion): a partial-overlap row.  The share
reached (column ``overlap``) is measured after the crop, before clutter;
a pair whose views overlap less than ``F`` to begin with keeps its own.
With ``--upsample N`` each view (after the crop, before the noise and
clutter) is resampled to ``N`` points: random points of the view, each moved
by isotropic Gaussian noise of ``--upsample-noise`` mm (default 0.5 mm, the
bunny scanner's resolution), and each row runs in a fresh process whose peak
resident memory (column ``peak MiB``: the whole process, imports and the
warm-up call included; ``VmHWM``, the process's own, not ``ru_maxrss``,
which a spawned process inherits from its parent) is reported: the
10⁶-point rows (``--upsample 1000000``).
With ``--noise 1,2,4`` each row also runs with Gaussian noise on every point
of both views (before clutter), its standard deviation the given percentage
of the source view's RMS radius about its centroid (1% is 0.56 mm on the
bunny, 0.8 mm on the chef); the column ``noise est`` is gatv's estimate
(``info["noise"]``) over the true deviation.

Methods, on the same inputs and in the same run:

* ``gatv`` — ``gatv.register(source, target, seed=trial)``: the automatic
  pipeline choice, which takes the scans pipeline here.
* ``o3d-ransac`` — Open3D RANSAC on FPFH features, then point-to-plane ICP
  (the Open3D tutorial pipeline).  Its voxel is tuned per dataset from the
  target's extent (``--o3d-voxel-share``, 1/40 of the bounding-box
  diagonal by default, which gives 2–3k points per view here).
* ``o3d-fgr`` — Open3D Fast Global Registration on the same features, then
  the same ICP.
* ``kiss`` — KISS-Matcher (``kiss-matcher`` on the package index: Faster-PFH,
  ROBIN pruning, GNC), then the same ICP.  It takes its voxel by hand; the
  scans are scaled to a 100-unit diagonal for it.  Its voxel is chosen by a
  small sweep (``--kiss-voxel-share sweep``, the default): each share of
  ``KISS_SWEEP`` of the target's diagonal on ``SWEEP_PAIRS`` (the table's
  bunny pairs with target and source swapped, not rows of the table) at 0
  and 30% clutter; the share with the most successes, then the least median
  time, runs the table (the sweep's own table is printed first).

Each method's rows run in a fresh process of its own (without
``--scheduler``), and the summary reports that process's resident peak
(``peak MiB``: its imports and all its rows), so that the methods' memory
compares.  The rows run one at a time, the methods alternating row by row
(each pair and clutter level: every method, then the next), so that a drift
in the shared machine's speed during the run falls on every method alike.

Sets sampled differently (``--pairs``, not run by default): ``res2<-bun045``
registers the bun045 scan to the bunny's reconstruction decimated to res2
(8,171 vertices; res3 1,889, res4 453), ``bun045<-res4`` the mesh to the
scan.  The reconstruction is in bun000's frame, so the ground truth is the
scan's pose in ``gt_world_from_scan.txt``.  Success: within 2° and 2 mm
(``mesh``): point-to-plane ICP started at the truth settles 0.2–0.6° off
on res3 and 1.2–1.5° off on res4, the decimated mesh's own error.  (The
``overlap`` column counts points within 5 mm of the other set's points: for
a mesh, of its vertices, which understates the surface overlap.)

Open3D is imported only here (``pip install -e '.[peers]'``); without it the
peers' rows say "not installed".

Scores: rotation error (degrees) and the error at the source's centroid
(``|T_est(c) - T_true(c)|``, mm), which does not grow with the distance of
the object from the sensor's origin.  Success: within 1° and 2 mm (bunny);
within 0.3° and 1 mm (UWA, a few times its pseudo ground truth's tolerance).
A method that returns no motion (gatv's falsy result, KISS-Matcher's
"invalid") has no error (``—``; ``answered`` false in the CSV) and its
note says "no motion": a miss, not a wrong motion.

Usage::

    python benchmarks/scans.py [--seed 0] [--clutter 0,0.3,0.5] [--overlap 0.4] [--noise 0,2,4] [--upsample N]
                               [--methods gatv,o3d-ransac,o3d-fgr,kiss] [--kiss-voxel-share sweep|S]
                               [--out benchmarks/results]
                               [--scheduler local|ADDRESS] [--stages]

``--stages`` adds a table of the CPU seconds of each stage of gatv's scans
pipeline (``info["cpu_<stage>"]``) per row; the CSV has them always.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (  # noqa: E402
    DEFAULT_OUT,
    add_scheduler_argument,
    fmt,
    map_trials,
    markdown_table,
    median,
    o3d_polish,
    parse_list,
    peak_rss_mib,
    write_csv,
)

from gatv.datasets import DataNotFoundError, load_bunny_pair, load_uwa_pair, rotation_error_deg  # noqa: E402

BUNNY_PAIRS = [("bun000", "bun045"), ("bun000", "bun315"), ("bun000", "bun090"),
               ("bun045", "bun090"), ("bun315", "bun045")]
UWA = ("chef", "parasaurolophus")
METHODS = ("gatv", "o3d-ransac", "o3d-fgr", "kiss")
#: Decimations of the bunny's reconstruction (``bun_zipper_<res>.ply``), in bun000's frame.
MESHES = ("res2", "res3", "res4")
#: The scans pipeline's stages (``gatv.scans.STAGES``): ``--stages`` prints each one's CPU seconds.
STAGES = ("prepare", "trials", "judge", "polish", "verdict")
#: Success tolerances (degrees, millimetres) per dataset.
TOLERANCE = {"bunny": (1.0, 2.0), "uwa": (0.3, 1.0), "mesh": (2.0, 2.0)}
#: KISS-Matcher's voxel, as shares of the target's bounding-box diagonal, tried by ``--kiss-voxel-share
#: sweep`` (on the bunny's 0.2 m diagonal: 2, 3, 5 and 8 mm).
KISS_SWEEP = (1 / 100, 1 / 67, 1 / 40, 1 / 25)
#: The pairs the sweep runs on: not rows of the table (the table's pairs with target and source swapped:
#: the four bunny scans are all the shared data has).
SWEEP_PAIRS = ("bun045<-bun000", "bun090<-bun045")
#: The clutter levels of the sweep.
SWEEP_CLUTTER = (0.0, 0.3)


def load(name: str):
    """``(dataset, target, source, R, t, mm)``: ``mm`` converts data units to millimetres."""
    if name in UWA:
        target, source, R, t = load_uwa_pair(name)
        return "uwa", target, source, R, t, 1.0
    tn, sn = name.split("<-")
    if tn in MESHES or sn in MESHES:
        return ("mesh", *_load_mesh_pair(tn, sn), 1000.0)
    target, source, R, t = load_bunny_pair(tn, sn)
    return "bunny", target, source, R, t, 1000.0


def _load_mesh_pair(tn: str, sn: str):
    """``(target, source, R, t)`` for a bunny scan and a decimation of the reconstruction (bun000's frame)."""
    from gatv.datasets import find_data_dir
    from gatv.io import read_points

    mesh_name, scan = (tn, sn) if tn in MESHES else (sn, tn)
    path = find_data_dir() / "stanford_bunny_reconstruction" / f"bun_zipper_{mesh_name}.ply"
    if not path.exists():
        raise DataNotFoundError(f"No {path.name} in {path.parent}.")
    _, scan_points, R, t = load_bunny_pair("bun000", scan)  # the scan's pose in bun000's frame
    mesh = read_points(path)
    if tn in MESHES:
        return mesh, scan_points, R, t
    return scan_points, mesh, R.T, -R.T @ t


def make_case(name: str, clutter: float, overlap: float | None, seed: int, noise: float = 0.0,
              upsample: int | None = None, upsample_noise_mm: float = 0.5):
    """The inputs of one row, the true motion (``p_target = R p_source + t``) and the noise's deviation."""
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation

    dataset, target, source, R, t, mm = load(name)
    rng = np.random.default_rng(seed)
    on_target = source @ R.T + t  # the source in the target's frame
    if overlap is not None:
        # Crop the target at the plane (random direction u) below which the
        # share `overlap` of the source's points have a partner on it.
        near = cKDTree(target).query(on_target, k=1)[0] < 5.0 / mm
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        h = on_target @ u
        order = np.argsort(h)
        cum = np.cumsum(near[order]) / len(source)
        if cum[-1] > overlap:
            cut = h[order[int(np.searchsorted(cum, overlap))]]
            target = target[target @ u <= cut]
    share = float(np.mean(cKDTree(target).query(on_target, k=1)[0] < 5.0 / mm))
    extent = float(np.linalg.norm(target.max(0) - target.min(0)))
    Q = Rotation.random(random_state=rng).as_matrix()
    q = rng.uniform(-0.2, 0.2, 3) * extent
    moved = source @ Q.T + q
    R_true, t_true = R @ Q.T, t - R @ Q.T @ q
    centroid = moved.mean(axis=0) if upsample else None
    if upsample:  # its own stream, so that the rows without it stay those of earlier runs
        up = np.random.default_rng([seed, upsample])
        moved, target = (pts[up.integers(0, len(pts), upsample)] + up.normal(0.0, upsample_noise_mm / mm,
                                                                                (upsample, 3))
                         for pts in (moved, target))
    sigma = noise / 100.0 * float(np.sqrt(((source - source.mean(axis=0)) ** 2).sum(axis=1).mean()))
    if sigma > 0:  # drawn only for noisy rows: the noise-free rows stay those of earlier runs
        moved = moved + rng.normal(0.0, sigma, moved.shape)
        target = target + rng.normal(0.0, sigma, target.shape)
    if centroid is None:
        centroid = moved.mean(axis=0)
    if clutter > 0:
        for which in ("source", "target"):
            pts = moved if which == "source" else target
            k = int(round(len(pts) * clutter / (1 - clutter)))
            pts = np.vstack([pts, rng.uniform(pts.min(0), pts.max(0), (k, 3))])
            if which == "source":
                moved = pts
            else:
                target = pts
    return dataset, moved, target, R_true, t_true, centroid, mm, share, sigma


def run_gatv(source, target, seed):
    from gatv.registration import register

    m = register(source, target, seed=seed)
    # Each stage's own CPU seconds (the info's are from the call's start, up to each stage's end).
    ends = [m.info.get(f"cpu_{stage}") for stage in STAGES]
    stages, last = {}, 0.0
    for stage, end in zip(STAGES, ends):
        if end is not None:
            stages[f"cpu_{stage}"], last = end - last, end
    return m.rotation, m.translation, {"pipeline": m.info.get("pipeline", ""), "noise": m.info.get("noise"),
                                       "ambiguous": m.info.get("ambiguous", False), "ok": bool(m), **stages}


def _o3d_features(points, voxel):
    import open3d as o3d

    down = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(voxel)
    down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
    return down, fpfh


def run_open3d(source, target, seed, method, voxel):
    import open3d as o3d

    reg = o3d.pipelines.registration
    o3d.utility.random.seed(int(seed))
    src_down, src_f = _o3d_features(source, voxel)
    tgt_down, tgt_f = _o3d_features(target, voxel)
    if method == "o3d-ransac":
        coarse = reg.registration_ransac_based_on_feature_matching(
            src_down, tgt_down, src_f, tgt_f, True, 1.5 * voxel,
            reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
            reg.RANSACConvergenceCriteria(100000, 0.999))
    else:
        coarse = reg.registration_fgr_based_on_feature_matching(
            src_down, tgt_down, src_f, tgt_f,
            reg.FastGlobalRegistrationOption(maximum_correspondence_distance=0.5 * voxel))
    T = np.asarray(coarse.transformation)
    R, t = o3d_polish(source, target, T[:3, :3], T[:3, 3], voxel)
    return R, t, {"ok": True}


def run_kiss(source, target, voxel):
    """KISS-Matcher (Faster-PFH, ROBIN, GNC) at Open3D's voxel, then Open3D's point-to-plane ICP.

    KISS-Matcher takes its voxel by hand and refuses millimetre voxels on
    metre-scale data, so both scans are scaled to a 100-unit diagonal for it
    (a similarity that leaves the rotation as it is) and its translation
    scaled back.
    """
    import kiss_matcher

    scale = 100.0 / float(np.linalg.norm(target.max(0) - target.min(0)))
    matcher = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(voxel * scale))
    sol = matcher.estimate(np.ascontiguousarray(source * scale), np.ascontiguousarray(target * scale))
    R, t = np.asarray(sol.rotation, dtype=np.float64), np.asarray(sol.translation, dtype=np.float64).ravel() / scale
    R, t = o3d_polish(source, target, R, t, voxel)
    return R, t, {"ok": bool(getattr(sol, "valid", True))}


_WARM = []
_UPSAMPLE_NOISE = [0.5]


def _row_with_noise(task_noise):
    task, noise_mm = task_noise
    _UPSAMPLE_NOISE[0] = noise_mm
    return run_row(task)


def _fresh_process(task, noise_mm):
    """``run_row(task)`` in a new process, so that its peak memory is the row's own."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(_row_with_noise, (task, noise_mm)).result()


def rows_by_method(tasks: list) -> tuple[list, dict]:
    """Every method's rows in a fresh process of its own, the rows run one at a time in the order of ``tasks``
    (methods alternating row by row, so that the machine's drift in speed falls on every method alike):
    the rows in that order and each method's peak resident memory (MiB: the whole process, its imports and
    all its rows)."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    methods = list(dict.fromkeys(task[4] for task in tasks))
    pools = {m: ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) for m in methods}
    try:
        rows = [pools[task[4]].submit(run_row, task).result() for task in tasks]
        peak = {m: pools[m].submit(peak_rss_mib).result() for m in methods}
    finally:
        for pool in pools.values():
            pool.shutdown()
    return rows, peak


def sweep_kiss_voxel(seed: int) -> tuple[float, list]:
    """KISS-Matcher's voxel share chosen on :data:`SWEEP_PAIRS` at :data:`SWEEP_CLUTTER`: the share of
    :data:`KISS_SWEEP` with the most successes, then the least median time.  Returns the share and the
    sweep's table rows."""
    table, best = [], None
    for share in KISS_SWEEP:
        rows = [run_row((name, clutter, None, 0.0, "kiss", seed + k, share, None))
                for clutter in SWEEP_CLUTTER for k, name in enumerate(SWEEP_PAIRS)]
        if any("not installed" in r.get("error", "") for r in rows):
            return 1 / 40, []
        wins = sum(bool(r.get("success")) for r in rows)
        t = median([r["time_s"] for r in rows if "time_s" in r])
        table.append([f"1/{round(1 / share)}", f"{wins}/{len(rows)}", fmt(t, 2)])
        if best is None or (wins, -(t or 0.0)) > (best[1], -(best[2] or 0.0)):
            best = (share, wins, t)
    return best[0], table


def warm_up() -> None:
    """Compile gatv's kernels once per process (the main one, or each Dask worker), outside the timed rows."""
    if _WARM:
        return
    from gatv.datasets import demo_mesh
    from gatv.registration import register

    warm = demo_mesh("nut")
    register(warm, warm @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]]).T, pipeline="scans",
             scan_options={"n_points": 200})
    _WARM.append(True)


def run_row(task: tuple) -> dict:
    """One (pair, clutter, method) row: the motion found and its errors."""
    name, clutter, overlap, noise, method, seed, voxel_share, upsample = task
    row = {"pair": name, "clutter": clutter, "overlap": overlap, "noise": noise, "method": method}
    try:
        dataset, source, target, R_true, t_true, c, mm, share, sigma = make_case(name, clutter, overlap, seed,
                                                                                 noise, upsample,
                                                                                 _UPSAMPLE_NOISE[0])
    except DataNotFoundError as exc:
        return dict(row, error=f"no data ({exc})")
    row.update(dataset=dataset, overlap=share)
    if method == "gatv":
        warm_up()  # in this process (a Dask worker's too), before the clock starts
    start, cpu = time.perf_counter(), time.process_time()
    try:
        if method == "gatv":
            R, t, extra = run_gatv(source, target, seed)
        else:
            try:
                import open3d  # noqa: F401

                if method == "kiss":
                    import kiss_matcher  # noqa: F401
            except ImportError:
                return dict(row, error="not installed (pip install -e '.[peers]')")
            voxel = voxel_share * float(np.linalg.norm(target.max(0) - target.min(0)))
            if method == "kiss":
                R, t, extra = run_kiss(source, target, voxel)
            else:
                R, t, extra = run_open3d(source, target, seed, method, voxel)
    except Exception as exc:  # a method's crash is a failed row, reported
        return dict(row, error=f"{type(exc).__name__}: {' '.join(str(exc).split())[:120]}",
                    time_s=time.perf_counter() - start)
    seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
    answered = bool(extra.get("ok", True))
    # No motion (gatv's "no motion", KISS-Matcher's "invalid") has no error: its R and t are placeholders.
    rot = rotation_error_deg(R, R_true) if answered else float("nan")
    centre = mm * float(np.linalg.norm((R @ c + t) - (R_true @ c + t_true))) if answered else float("nan")
    tol_deg, tol_mm = TOLERANCE[dataset]
    estimate = extra.get("noise")
    if sigma > 0 and estimate is not None:
        row["noise_ratio"] = float(estimate) / sigma
    peak = peak_rss_mib()
    return dict(row, rotation_error_deg=rot, centroid_error_mm=centre, time_s=seconds, cpu_s=cpu, peak_mib=peak,
                points=(len(source), len(target)),
                answered=answered, success=answered and rot <= tol_deg and centre <= tol_mm,
                ambiguous=bool(extra.get("ambiguous", False)), pipeline=extra.get("pipeline", ""),
                **{k: v for k, v in extra.items() if k.startswith("cpu_")})


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--clutter", type=parse_list(float), default=[0.0, 0.3, 0.5], metavar="C,C")
    parser.add_argument("--overlap", type=float, default=None,
                        help="crop the target so that this share of the source's points lie on it "
                             "(partial-overlap rows)")
    parser.add_argument("--noise", type=parse_list(float), default=[0.0], metavar="N,N",
                        help="Gaussian noise on both views, in %% of the source view's RMS radius")
    parser.add_argument("--methods", type=parse_list(str), default=list(METHODS), metavar="M,M")
    parser.add_argument("--pairs", type=parse_list(str), default=None, metavar="P,P",
                        help="pairs to run: 'bun000<-bun045', 'chef', 'res4<-bun045' (a scan against the "
                             "decimated reconstruction), ... (default: the seven scan pairs)")
    parser.add_argument("--upsample", type=int, default=None, metavar="N",
                        help="resample each view to N points (Gaussian noise of --upsample-noise mm); each "
                             "row then runs in a fresh process and reports its peak memory")
    parser.add_argument("--upsample-noise", type=float, default=0.5, metavar="MM")
    parser.add_argument("--o3d-voxel-share", type=float, default=1 / 40,
                        help="Open3D's voxel as a share of the target's bounding-box diagonal")
    parser.add_argument("--kiss-voxel-share", default="sweep",
                        help="KISS-Matcher's voxel as a share of the target's diagonal, or 'sweep' (default): "
                             "the best of KISS_SWEEP on SWEEP_PAIRS, pairs not in the table")
    parser.add_argument("--stages", action="store_true",
                        help="also print the CPU seconds of each stage of gatv's scans pipeline per row")
    add_scheduler_argument(parser)
    args = parser.parse_args(argv)
    unknown = [m for m in args.methods if m not in METHODS]
    if unknown:
        parser.error(f"unknown method(s) {unknown}; available: {list(METHODS)}")
    names = args.pairs or [f"{t}<-{s}" for t, s in BUNNY_PAIRS] + list(UWA)
    try:
        load(names[0])
    except DataNotFoundError as exc:
        print(f"scans benchmark skipped: {exc}")
        return 0
    if "gatv" in args.methods and not args.upsample:
        warm_up()
    kiss_share, sweep = args.o3d_voxel_share, []
    if "kiss" in args.methods:
        if args.kiss_voxel_share == "sweep":
            kiss_share, sweep = sweep_kiss_voxel(args.seed)
        else:
            kiss_share = float(args.kiss_voxel_share)
    tasks = [(name, clutter, args.overlap, noise, method, args.seed + k,
              kiss_share if method == "kiss" else args.o3d_voxel_share, args.upsample)
             for noise in args.noise for clutter in args.clutter for k, name in enumerate(names)
             for method in args.methods]
    peaks: dict = {}
    if args.upsample:
        _UPSAMPLE_NOISE[0] = args.upsample_noise
        rows = [_fresh_process(task, args.upsample_noise) for task in tasks]
    elif args.scheduler is None:
        rows, peaks = rows_by_method(tasks)
    else:
        rows = map_trials(run_row, tasks, scheduler=args.scheduler)
    if sweep:
        print(f"KISS-Matcher's voxel (share of the target's diagonal) swept on {', '.join(SWEEP_PAIRS)} at "
              f"{', '.join(f'{c:.0%}' for c in SWEEP_CLUTTER)} clutter (not rows of the table): "
              f"1/{round(1 / kiss_share)} chosen\n")
        print(markdown_table(["voxel share", "successes", "median time (s)"], sweep, align="lrr"))
        print()
    for r in rows:
        if "error" in r:
            print(f"  {r['pair']} clutter {r['clutter']:.0%} {r['method']}: {r['error']}", file=sys.stderr)
    noisy = any(n > 0 for n in args.noise)
    big = bool(args.upsample)
    headers = ["pair", "overlap", *(["noise"] if noisy else []), "clutter", "method", "rotation error (deg)",
               "centroid error (mm)", "time (s)", "CPU (s)", *(["peak MiB"] if big else []), "success",
               *(["noise est"] if noisy else []), "note"]
    table = []
    for r in rows:
        note = r.get("error", "") or "; ".join(
            ([] if r.get("answered", True) else ["no motion"]) + (["ambiguous"] if r.get("ambiguous") else []))
        share = f"{r['overlap']:.0%}" if isinstance(r.get("overlap"), float) else ""
        table.append([r["pair"], share, *([f"{r['noise']:g}%"] if noisy else []), f"{r['clutter']:.0%}",
                      r["method"], fmt(r.get("rotation_error_deg"), 3), fmt(r.get("centroid_error_mm"), 2),
                      fmt(r.get("time_s"), 2), fmt(r.get("cpu_s"), 2),
                      *([fmt(r.get("peak_mib"), 0)] if big else []), "yes" if r.get("success") else "NO",
                      *([fmt(r.get("noise_ratio"), 2)] if noisy else []), note])
    overlap = ("" if args.overlap is None else f", target cropped to {args.overlap:.0%} overlap") + (
        f", each view resampled to {args.upsample:,} points (noise {args.upsample_noise:g} mm), a process a row"
        if big else "")
    print(f"Real scans re-posed by random motions, seed {args.seed}{overlap}; overlap: share of the source's "
          "points on the target (5 mm), before clutter; UWA rows against a pseudo ground truth made by Open3D's "
          "own pipeline" + ("; noise est: gatv's estimate over the true "
                                                          "deviation" if noisy else "") + "\n")
    print(markdown_table(headers, table, align="lr" + ("r" if noisy else "") + "lllrrr" + ("r" if big else "") + "l"
                         + ("r" if noisy else "") + "l"))
    print()
    summary = [["method", *(["noise"] if noisy else []), "clutter", "successes", "median time (s)", "max time (s)",
                "median CPU (s)", "peak MiB"]]
    for method in args.methods:
        for noise in args.noise:
            for clutter in args.clutter:
                cell = [r for r in rows if r["method"] == method and r["clutter"] == clutter and r["noise"] == noise]
                times = [r["time_s"] for r in cell if "time_s" in r]
                peak = peaks.get(method, max((r["peak_mib"] for r in cell if big and "peak_mib" in r), default=None))
                summary.append([method, *([f"{noise:g}%"] if noisy else []), f"{clutter:.0%}",
                                f"{sum(bool(r.get('success')) for r in cell)}/{len(cell)}", fmt(median(times), 2),
                                fmt(max(times) if times else None, 2), fmt(median(r.get("cpu_s") for r in cell), 2),
                                fmt(peak, 0)])
    print(markdown_table(summary[0], summary[1:], align="l" + ("r" if noisy else "") + "lrrrrr"))
    print("CPU: process time of the call, all threads added up (Open3D and numba both use threads).  Peak MiB: "
          + ("the row's own process" if big else "the resident peak of the method's own process (its imports and "
             "every row of the run)" if peaks else "not measured (Dask)") + ".")
    staged = [r for r in rows if "cpu_prepare" in r]
    if args.stages and staged:
        print("\nCPU seconds per stage of gatv's scans pipeline (gatv.scans.STAGES; rest: from the verdict's end "
              "to the call's)\n")
        body = [[r["pair"], f"{r['clutter']:.0%}", *(fmt(r.get(f"cpu_{s}"), 2) for s in STAGES),
                 fmt(r["cpu_s"] - sum(r.get(f"cpu_{s}", 0.0) for s in STAGES), 2), fmt(r["cpu_s"], 2)]
                for r in staged]
        print(markdown_table(["pair", "clutter", *STAGES, "rest", "call"], body, align="ll" + "r" * (len(STAGES) + 2)))
    keys = ["pair", "dataset", "clutter", "overlap", "noise", "method", "rotation_error_deg", "centroid_error_mm",
            "time_s", "cpu_s", "peak_mib", "answered", "success", "ambiguous", "pipeline", "noise_ratio",
            *(f"cpu_{s}" for s in STAGES), "error"]
    suffix = ("" if args.overlap is None else f"_overlap{round(100 * args.overlap)}") + (
        "_noise" if noisy else "") + (f"_n{args.upsample}" if big else "")
    path = write_csv(args.out / f"scans{suffix}.csv", keys, [[r.get(k, "") for k in keys] for r in rows])
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
