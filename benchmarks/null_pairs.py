"""Pairs with no true motion: how often each pipeline says "found" (it should say no).

"No motion" is an answer, and every reported motion must beat what wrong
but plausible motions collect on the same data (``gatv.verdict``).  This
benchmark feeds each public pipeline pairs where no rigid (or non-rigid)
motion relates the two sets, and counts the "found" answers; beside them it
runs true pairs, which must still succeed.

Null pairs (``--pairs``):

* ``objects``: two different real objects scaled to one size (RMS radius
  about the centroid) and re-posed at random: the bunny scans against the
  UWA chef and parasaurolophus views, and the two UWA objects against each
  other (``../shared/data``; skipped when absent).
* ``halves``: the two halves of one bunny scan, split at its median x (no
  overlap), one re-posed.
* ``random``: two independent uniform clouds in a 10-wide cube
  (``--sizes``, default 1,000 and 20,000 points; 100,000 with ``--sizes``).
* ``planes``: two independent samplings of a square (a degenerate surface:
  every slide fits as well).
* ``blobs``: four pairs of independent Gaussian clouds (deviation 3 a
  coordinate, 116-371 points a set: the point-set pipelines), denser at
  their centres than through their box, where a search that maximises
  support lays one core onto the other.
* ``structured``: unrelated sets drawn alike with structure the Poisson
  levels do not model (the point-set pipelines; 120-400 points a set):
  half on a plane and half in a blob placed at random, random sites of a
  lattice, and thin Gaussian clouds of random shape; two pairs of each
  (``STRUCTURED_SEEDS``).  Laid plane on plane, site on site or core on
  core they hold far more pairs than evenly spread points would.
* ``cropped`` (not in the default run): the four object pairs with the
  target cropped at a random plane to 40% and 50% of its points, at 0 and
  30% uniform clutter on both, and one bunny and one chef view split at a
  random plane into disjoint parts (45/55), one re-posed, at 0 and 30%
  clutter: 20 partial-overlap nulls (their own stream of ``--seed``).

Pipelines (``--methods``): ``register`` (``gatv.register``, its automatic
pipeline choice), ``segment`` (``gatv.motions.segment``, found = at least
one motion; both of ``--model``, default ``rigid``: ``similarity`` runs
the point-set kinds ``random``, ``blobs`` and ``structured`` at
``--sizes`` up to 2,000, without true pairs; ``affine2d`` the same kinds
in the plane: a line and a blob, a planar lattice, thin 2D clouds),
``nonrigid`` (``gatv.nonrigid.register`` on at most 5,000 points a set) and ``catadioptric`` (``catadioptric.match`` on two
independent uniform pixel sets of the Mei camera's image; found = any
motion).

True pairs (``--true``, default on): the bunny and UWA pairs of
``benchmarks/scans.py`` at clutter 0 and 0.5, re-posed by a random motion,
for ``register``: success within 1° and 2 mm (bunny) or 0.3° and 1 mm
(UWA).

Columns: ``found`` (null rows: should be 0; true rows: success), the
verdict's support and level (``info["verdict"]``), the wrong draws it
polished (scans pipeline: ``info["verdict_gates"]["polished"]``, of 16; the
sequential verdict stops early on a clear pass) and the seconds.

Usage::

    python benchmarks/null_pairs.py [--methods register,segment,nonrigid,catadioptric]
                                    [--pairs objects,halves,random,planes,blobs,structured,cropped]
                                    [--sizes 1000,20000] [--model rigid|similarity|affine2d]
                                    [--true/--no-true] [--seed 0] [--out benchmarks/results]
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import DEFAULT_OUT, markdown_table, parse_list, write_csv  # noqa: E402

from gatv.datasets import DataNotFoundError, load_bunny_pair, load_uwa_pair  # noqa: E402

METHODS = ("register", "segment", "nonrigid", "catadioptric")
PAIRS = ("objects", "halves", "random", "planes", "blobs", "structured", "cropped")
#: The kinds run by default (``cropped`` adds 20 slower pairs).
DEFAULT_PAIRS = ("objects", "halves", "random", "planes", "blobs", "structured")
#: Seeds of the ``blobs`` pairs (``np.random.default_rng(seed)`` draws the sizes, then the points):
#: four of the eight where ``segment`` kept 1-3 motions before it tested trials at the landing density.
BLOB_SEEDS = (1001, 1009, 1013, 1015)
#: ``(kind, seed)`` of the ``structured`` pairs (``np.random.default_rng(seed)`` draws the sizes, then the
#: source, then the target): pairs where ``segment`` kept 1-9 motions and ``register`` one, before
#: they compared a motion with its turned and shifted copies (``gatv.registration.rival_draws``).
STRUCTURED_SEEDS = (("plane and blob", 2002), ("plane and blob", 2004), ("lattice", 2002), ("lattice", 2004),
                    ("thin cloud", 2003), ("thin cloud", 2004))


def _plane_and_blob(rng: np.random.Generator, n: int, dim: int = 3) -> np.ndarray:
    """Half the points on a plane (a line in 2D), half in a blob."""
    m = n // 2
    plane = np.column_stack([rng.uniform(-6, 6, (m, dim - 1)), rng.normal(0, 0.05, m)])
    return np.vstack([plane, rng.normal(0, 1.5, (n - m, dim)) + rng.uniform(-4, 4, dim)])


def _lattice(rng: np.random.Generator, n: int, dim: int = 3) -> np.ndarray:
    return rng.integers(-4, 5, (n, dim)).astype(float) * 1.5 + rng.normal(0, 0.05, (n, dim))


def _thin_cloud(rng: np.random.Generator, n: int, dim: int = 3) -> np.ndarray:
    shape = rng.normal(0, 1, (dim, dim)) * (np.array([6.0, 2.0, 0.4]) if dim == 3 else np.array([6.0, 0.4]))
    return rng.normal(0, 1, (n, dim)) @ shape.T


STRUCTURES = {"plane and blob": _plane_and_blob, "lattice": _lattice, "thin cloud": _thin_cloud}


def _rms_radius(points: np.ndarray) -> float:
    return float(np.sqrt(((points - points.mean(axis=0)) ** 2).sum(axis=1).mean()))


def _like(points: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``points`` scaled and moved to the size and centroid of ``reference``."""
    return (points - points.mean(axis=0)) * (_rms_radius(reference) / _rms_radius(points)) + reference.mean(axis=0)


def _reposed(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    c = points.mean(axis=0)
    return (points - c) @ Rotation.random(random_state=rng).as_matrix().T + c + rng.normal(0, 0.1, 3) * _rms_radius(points)


def _crop(points: np.ndarray, share: float, rng: np.random.Generator) -> np.ndarray:
    """The points below a random plane that keeps the share ``share`` of them."""
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    h = points @ u
    return points[h <= np.quantile(h, share)]


def _cluttered(points: np.ndarray, share: float, rng: np.random.Generator) -> np.ndarray:
    """``points`` with uniform clutter in their bounding box making up ``share`` of the result."""
    if share <= 0:
        return points
    k = int(round(len(points) * share / (1 - share)))
    return np.vstack([points, rng.uniform(points.min(0), points.max(0), (k, 3))])


def cropped_pairs(seed: int):
    """The ``cropped`` nulls: partial-overlap versions of the object pairs, and disjoint parts of one view."""
    rng = np.random.default_rng(seed)
    b0, b45, _, _ = load_bunny_pair("bun000", "bun045")
    b315 = load_bunny_pair("bun000", "bun315")[1]
    chef, para = load_uwa_pair("chef")[0], load_uwa_pair("parasaurolophus")[0]
    objects = [("bun000/chef", _like(chef, b0), b0), ("bun045/para", _like(para, b45), b45),
               ("chef/bun315", b315, _like(chef, b315)), ("para/chef", _like(para, chef), chef)]
    out = []
    for share in (0.4, 0.5):
        for c in (0.0, 0.3):
            for name, s, t in objects:
                out.append((f"{name} crop{share:g} c{c:g}", _cluttered(_reposed(s, rng), c, rng),
                            _cluttered(_crop(t, share, rng), c, rng)))
    for name, p in (("bun000", b0), ("chef", chef)):
        for c in (0.0, 0.3):
            u = rng.normal(size=3)
            u /= np.linalg.norm(u)
            h = p @ u
            a, b = p[h < np.quantile(h, 0.45)], p[h >= np.quantile(h, 0.45)]
            out.append((f"{name} parts c{c:g}", _cluttered(_reposed(a, rng), c, rng), _cluttered(b, c, rng)))
    return out


def null_pairs(kinds, sizes, rng, seed: int = 0, dim: int = 3):
    """``(name, source, target)`` of each null pair asked for."""
    out = []
    if "objects" in kinds:
        try:
            b0, b45, _, _ = load_bunny_pair("bun000", "bun045")
            b315 = load_bunny_pair("bun000", "bun315")[1]
            chef, para = load_uwa_pair("chef")[0], load_uwa_pair("parasaurolophus")[0]
            out += [("bun000 / chef", _reposed(_like(chef, b0), rng), b0),
                    ("bun045 / parasaurolophus", _reposed(_like(para, b45), rng), b45),
                    ("chef / bun315", _reposed(b315, rng), _like(chef, b315)),
                    ("parasaurolophus / chef", _reposed(_like(para, chef), rng), chef)]
        except DataNotFoundError as exc:
            print(f"objects: skipped ({exc})", file=sys.stderr)
    if "halves" in kinds:
        try:
            b0 = load_bunny_pair("bun000", "bun045")[0]
            left = b0[:, 0] < np.median(b0[:, 0])
            out.append(("bun000 halves", _reposed(b0[left], rng), b0[~left]))
        except DataNotFoundError as exc:
            print(f"halves: skipped ({exc})", file=sys.stderr)
    if "random" in kinds:
        for n in sizes:
            out.append((f"random {n}", rng.uniform(0, 10, (n, dim)), rng.uniform(0, 10, (n, dim))))
    if "planes" in kinds:
        def square(n):
            return np.column_stack([rng.uniform(0, 10, (n, 2)), np.zeros(n)])
        out.append(("planes 20000", _reposed(square(20000), rng), square(20000)))
    if "blobs" in kinds:
        for s in BLOB_SEEDS:
            r = np.random.default_rng(s)
            n1, n2 = r.integers(100, 400, 2)
            out.append((f"gaussian blobs {n1}/{n2}", r.normal(0, 3, (n1, dim)), r.normal(0, 3, (n2, dim))))
    if "structured" in kinds:
        for kind, seed in STRUCTURED_SEEDS:
            r = np.random.default_rng(seed)
            n1, n2 = r.integers(120, 400, 2)
            a = STRUCTURES[kind](r, n1, dim)
            out.append((f"{kind} {n1}/{n2}", a, STRUCTURES[kind](r, n2, dim)))
    if "cropped" in kinds:
        try:
            out += cropped_pairs(seed)
        except DataNotFoundError as exc:
            print(f"cropped: skipped ({exc})", file=sys.stderr)
    return out


def true_pairs(seed):
    """``(name, source, target, R, t, tolerance)`` of the scans benchmark's true pairs."""
    spec = importlib.util.spec_from_file_location("scans_benchmark", Path(__file__).resolve().parent / "scans.py")
    S = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(S)

    out = []
    for name in ["bun000<-bun045", "bun000<-bun315", "bun000<-bun090", "bun045<-bun090", "bun315<-bun045",
                 "chef", "parasaurolophus"]:
        for clutter in (0.0, 0.5):
            try:
                dataset, source, target, R, t, centroid, mm, *_ = S.make_case(name, clutter, None, seed)
            except DataNotFoundError as exc:
                print(f"{name}: skipped ({exc})", file=sys.stderr)
                break
            out.append((f"{name} c{clutter:g}", source, target, R, t, centroid, mm, S.TOLERANCE[dataset]))
    return out


def _verdict(info: dict) -> tuple[str, str, str]:
    """Support, level and (scans pipeline) the wrong draws polished for the verdict that decided."""
    v = info.get("verdict") or {}
    if not v:
        return "", "", ""
    polished = (info.get("verdict_gates") or {}).get("polished", "")
    return str(int(v["support"])), f"{v['chance']:.0f}", str(polished)


#: Models ``--model`` takes, and the null kinds each runs (the similarity model has no scans pipeline).
MODELS = {"rigid": PAIRS, "similarity": ("random", "blobs", "structured"),
          "affine2d": ("random", "blobs", "structured")}
#: Largest ``--sizes`` entry for a model other than the rigid one (the exact pipeline on every point).
MAX_SIZE_OTHER = 2000


def run_null(method: str, source, target, seed: int, model: str = "rigid") -> dict:
    t0 = time.perf_counter()
    if method == "register":
        from gatv import register

        m = register(source, target, seed=seed, model=model)
        found, info = bool(m), m.info
    elif method == "segment":
        from gatv.motions import segment

        s = segment(source, target, seed=seed, model=model)
        found, info = len(s.motions) > 0, dict(s.info)
        if s.motions:
            info = dict(s.motions[0].info)
    elif method == "nonrigid":
        from gatv.nonrigid import register as nonrigid_register

        rng = np.random.default_rng(seed)
        pick = [p if p.shape[0] <= 5000 else p[rng.choice(p.shape[0], 5000, replace=False)] for p in (source, target)]
        m = nonrigid_register(*pick, seed=seed)
        found, info = bool(m), m.info
    else:
        raise ValueError(method)
    support, level, polished = _verdict(info)
    return {"found": int(found), "support": support, "level": level, "polished": polished,
            "seconds": time.perf_counter() - t0,
            "reason": "" if found else str(info.get("reason", ""))[:80]}


def run_catadioptric(seed: int) -> list[dict]:
    """Two independent uniform pixel sets in the Mei camera's image, three times."""
    from catadioptric import UnifiedCamera, match

    from gatv.datasets import find_data_dir

    try:
        cam = UnifiedCamera.from_json(find_data_dir() / "omni_mei_paracatadioptric" / "calibration_mei_opencv.json")
    except (DataNotFoundError, FileNotFoundError) as exc:
        print(f"catadioptric: skipped ({exc})", file=sys.stderr)
        return []
    rows = []
    rng = np.random.default_rng(seed)
    w, h = cam.image_size if cam.image_size else (2.0 * cam.cx, 2.0 * cam.cy)
    for k in range(3):
        def pixels(n=150):
            # uniform in the mirror's disc, where pixels lift to the sphere
            c = np.array([cam.cx, cam.cy])
            r = 0.45 * min(w, h) * np.sqrt(rng.uniform(0.05, 1.0, n))
            a = rng.uniform(0, 2 * np.pi, n)
            return c + np.column_stack([r * np.cos(a), r * np.sin(a)])
        t0 = time.perf_counter()
        m = match(pixels(), pixels(), cam, noise_px=1.0, seed=seed + k)
        motions = getattr(m, "motions", None)
        found = len(motions) > 0 if motions is not None else bool(m)
        rows.append({"pipeline": "catadioptric", "pair": f"random pixels {k}", "kind": "null", "found": int(found),
                     "support": "", "level": "", "polished": "", "seconds": time.perf_counter() - t0, "reason": ""})
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--methods", type=parse_list(str), default=list(METHODS))
    parser.add_argument("--pairs", type=parse_list(str), default=list(DEFAULT_PAIRS))
    parser.add_argument("--sizes", type=parse_list(int), default=[1000, 20000])
    parser.add_argument("--true", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--model", choices=sorted(MODELS), default="rigid",
                        help="the motion model of register and segment (default: rigid)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    bad = sorted(set(args.methods) - set(METHODS)) + sorted(set(args.pairs) - set(PAIRS))
    if bad:
        parser.error(f"unknown --methods/--pairs {bad}; choose from {METHODS} and {PAIRS}")
    if args.model != "rigid":
        wrong = sorted(set(args.methods) - {"register", "segment"})
        wrong += sorted(set(args.pairs) - set(MODELS[args.model]))
        if wrong:
            parser.error(f"--model {args.model} runs --methods register,segment on --pairs "
                         f"{','.join(MODELS[args.model])}; drop {wrong}")
        if "random" in args.pairs and max(args.sizes) > MAX_SIZE_OTHER:
            parser.error(f"--model {args.model} takes --sizes up to {MAX_SIZE_OTHER}; pass e.g. --sizes 1000")
    rng = np.random.default_rng(args.seed)
    rows = []
    nulls = null_pairs(args.pairs, args.sizes, rng, args.seed, dim=2 if args.model == "affine2d" else 3)
    for method in args.methods:
        if method == "catadioptric":
            rows += run_catadioptric(args.seed)
            continue
        for name, source, target in nulls:
            if method == "nonrigid" and name.startswith("planes"):
                continue  # a non-rigid motion may fold a plane onto a plane: not a null pair for it
            r = run_null(method, source, target, args.seed, args.model)
            rows.append({"pipeline": method, "pair": name, "kind": "null", **r})
            print(f"{method:9s} {name:26s} found={r['found']} {r['seconds']:.1f}s", file=sys.stderr, flush=True)
    if args.true and "register" in args.methods and args.model == "rigid":
        from gatv import register
        from gatv.datasets import rotation_error_deg

        for name, source, target, R, t, centroid, mm, (tol_deg, tol_mm) in true_pairs(args.seed):
            t0 = time.perf_counter()
            m = register(source, target, seed=args.seed)
            dt = time.perf_counter() - t0
            ok = bool(m) and rotation_error_deg(m.rotation, R) <= tol_deg and \
                np.linalg.norm(m.rotation @ centroid + m.translation - (R @ centroid + t)) * mm <= tol_mm
            support, level, polished = _verdict(m.info)
            rows.append({"pipeline": "register", "pair": name, "kind": "true", "found": int(ok), "support": support,
                         "level": level, "polished": polished, "seconds": dt,
                         "reason": "" if m else str(m.info.get("reason", ""))[:80]})
            print(f"register  {name:26s} ok={int(ok)} {dt:.1f}s", file=sys.stderr, flush=True)
    cols = ["pipeline", "pair", "kind", "found", "support", "level", "polished", "seconds", "reason"]
    table = [[r[c] if c != "seconds" else f"{r[c]:.1f}" for c in cols] for r in rows]
    print(markdown_table(cols, table))
    null_found = sum(r["found"] for r in rows if r["kind"] == "null")
    true_rows = [r for r in rows if r["kind"] == "true"]
    print(f"\nnull pairs found: {null_found} of {sum(r['kind'] == 'null' for r in rows)}; "
          f"true pairs succeeded: {sum(r['found'] for r in true_rows)} of {len(true_rows)}")
    write_csv(args.out / "null_pairs.csv", cols, [[r[c] for c in cols] for r in rows])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
