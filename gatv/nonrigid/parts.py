"""Articulated motions: seeds in every part, and the near-rigid parts of a non-rigid match.

An articulated body (a person, an arm, a robot) moves piecewise rigidly:
each limb turns about a joint it shares with its neighbour, and the skin
bends where two limbs meet.  Two steps of :func:`gatv.nonrigid.register`
follow from that.

**Seeds in every part** (:func:`seed_parts`).  The growth of
:func:`gatv.nonrigid.multiscale.grow` follows a smooth warp ring by ring;
from the torso it stops at a shoulder that turns by 50°, because one ring's
affine extrapolation misses there by more than the sampling gate.  Grown
*from the limb* it crosses the same joint (the limb's side of it is the
rigid one).  So once the first window's growth stops, the rows it left
uncovered are searched again: a window of ``PART_WINDOW_POINTS`` uncovered
source rows, farthest from every match first (an extremity: a hand, a foot,
the more rigid end of a limb), is registered rigidly against the uncovered
target rows (:func:`gatv.register`, the congruent-triple search of section
3.4, its gate ``PART_GATE`` window spacings), and its matches are grown
over the rows no earlier part holds (one-to-one across parts).  A window
counts when its growth reaches ``MIN_SHARE`` of the smaller set, as a
hypothesis of the direct mode must; a wrong rigid motion grows little (a
slide along the surface has no consistent continuation).  The windows run
in the one peel loop (:func:`gatv.peel_loop.peel_loop`): search a window,
judge its growth (it must also meet the earlier matches continuously,
:func:`contacts`: one non-rigid motion is continuous, a second body beside
it is another motion), take its rows, until nothing is left uncovered,
``MAX_FAILED_WINDOWS`` windows in a row did not count, or
``MAX_PART_WINDOWS`` windows were tried.

**Near-rigid parts** (:func:`rigid_parts`).  The final matches are split
into parts that each move rigidly within ``PART_TOLERANCE`` target
spacings, again by the peel loop: each round tries the local rigid motions
of seeded matches as hypotheses, keeps the one whose connected inliers are
the most, refits it (Kabsch), and removes its matches.  Between two parts
that meet, the joint is the axis and the centre of their relative rotation
(:func:`joint`): the axis of ``R_a^T R_b`` and the point nearest their
common boundary that both motions move alike, ``(R_a − R_b) c = t_b − t_a``
(the paper's section 5: motions that share an axis).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..candidates import median_spacing
from ..fitting import kabsch
from ..ga import Rotor
from ..peel_loop import Candidate, Judgement, Stop, peel_loop
from ..registration import register as rigid_register
from . import multiscale as ms
from .stages import AUTO_RIGID_TRIPLES

__all__ = [
    "MAX_FAILED_WINDOWS",
    "MAX_PART_WINDOWS",
    "MIN_CONTACTS",
    "PART_GATE",
    "PART_HYPOTHESES",
    "PART_MAX_POINTS",
    "PART_MIN_SHARE",
    "PART_TOLERANCE",
    "PART_WINDOW_POINTS",
    "UNCOVERED_REACH",
    "Part",
    "contacts",
    "hinged",
    "PartSeeds",
    "joint",
    "parts_info",
    "rigid_parts",
    "seed_parts",
]

#: Source rows of a part window: a patch of about 4.4 spacings' radius on a surface
#: (π 4.4² ≈ 60), enough shared rows for a triple search when each set is an 80% sample.
PART_WINDOW_POINTS = 60
#: Match gate of a part window's rigid search, times the window's spacing: a hand or a forearm
#: of the body moves rigidly within 0.05–0.15 of its spacing; a shoulder does not (0.4–1).
PART_GATE = 0.2
#: Part windows tried after the first growth before the search gives up.
MAX_PART_WINDOWS = 12
#: Windows in a row that do not count before the search stops (outliers left uncovered, or a
#: second body that is another motion).
MAX_FAILED_WINDOWS = 4
#: A source (target) row is uncovered when no match lies within this many spacings of it.
UNCOVERED_REACH = 3.0
#: A near-rigid part: its matches within this many target spacings of its rigid motion.
PART_TOLERANCE = 1.0
#: Smallest near-rigid part reported, as a share of the matches.
PART_MIN_SHARE = 0.02
#: Matches :func:`parts_info` splits into parts at most (a seeded subsample; the others take
#: their nearest sampled match's part): a 25k-match twist took 34 s on all of them.
PART_MAX_POINTS = 3000
#: Hypotheses (local rigid motions of seeded matches) tried per round of :func:`rigid_parts`.
PART_HYPOTHESES = 200
#: Matches of a part's growth that must meet the earlier matches continuously (:func:`contacts`).
MIN_CONTACTS = 3
#: Hypotheses of a round of :func:`rigid_parts` (most inliers first) whose connected inliers are
#: counted: after the torso, the near-identity hypotheses still count many scattered inliers.
PART_CONNECTED = 32
#: Seconds the part windows may take in all (each rigid search is bounded by triples as well).
PART_TIME = 30.0


#: Why a part window's growth, as large as a hypothesis, is not kept: it does not meet the matched
#: part (continuously or at a joint).  Every row within reach of that growth is then tried: it
#: belongs to another motion (a second body beside the first; :func:`gatv.nonrigid.segment`
#: searches it from its own seeds), and later windows there would land on the same body (two real
#: shapes at 30% outliers: four such windows on one hand took 35 s of the face's 42 s round).
_APART = "its growth does not meet the matched part at a joint"


@dataclass(frozen=True, eq=False)
class PartSeeds:
    """The matches after the part windows: ``pairs`` (K, 2), ``growth`` (K,) the index of the
    growth that made each (0: the first window's), ``windows`` one record per part window."""

    pairs: np.ndarray
    growth: np.ndarray
    windows: tuple


def _uncovered(P, rows, matched, reach: float) -> np.ndarray:
    if matched.size == 0:
        return rows
    d = cKDTree(P[matched]).query(P[rows], k=1)[0]
    return rows[d > reach]


def seed_parts(X, Y, tree_x, tree_y, rows_x, rows_y, pairs, *, gate: float, spacing: float,
               spacing_x: float, least: float, strain: float = 0.35, seed: int = 0,
               noise: float | None = None, time_limit: float = PART_TIME) -> PartSeeds:
    """Seed and grow further parts where the first growth did not reach (the module docstring).

    Parameters
    ----------
    X, Y : (N, 3), (M, 3) ndarray
    tree_x, tree_y : cKDTree
        Of ``X`` and ``Y``.
    rows_x, rows_y : ndarray of int
        The structure's rows (:func:`gatv.nonrigid.multiscale.dense_rows`): windows and the
        uncovered target are taken among them.
    pairs : (K, 2) ndarray of int
        The first growth's matches.
    gate : float or (M,) ndarray
        The growth's match gate, or one per target row
        (:func:`gatv.nonrigid.multiscale.local_gates`).
    spacing, spacing_x : float
        Target and source spacings (the uncovered reach; the growth's warp).
    least : float
        Matches a part's growth must reach to count.
    strain : float
        Local strain of the continuity test where a part meets the matches before it
        (:func:`contacts`: at least ``MIN_CONTACTS`` of its matches must meet them): one non-rigid
        motion is continuous, and a second body beside it is another motion.
    seed : int
    noise : float, optional
        Point noise (widens the windows' rigid gate).
    time_limit : float
        Seconds for all windows; no window starts after it.
    """
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    used_s = np.zeros(X.shape[0], bool)
    used_t = np.zeros(Y.shape[0], bool)
    used_s[pairs[:, 0]] = True
    used_t[pairs[:, 1]] = True
    growths = [pairs]
    tried = np.zeros(X.shape[0], bool)  # rows of windows (and their growths) that did not count
    records: list = []
    reach_s, reach_t = UNCOVERED_REACH * spacing_x, UNCOVERED_REACH * spacing

    def search():
        matched = np.vstack(growths)
        us = _uncovered(X, rows_x, matched[:, 0], reach_s)
        ut = _uncovered(Y, rows_y, matched[:, 1], reach_t)
        if min(us.size, ut.size) < max(least, PART_WINDOW_POINTS):
            return Stop("every part is covered", exhausted=True)
        free = ~tried[us]
        if not free.any():
            return Stop("no uncovered window left to try", exhausted=True)
        # farthest from every match first: an extremity, the rigid end of a limb
        d = cKDTree(X[matched[:, 0]]).query(X[us[free]], k=1)[0]
        centre = us[free][int(np.argmax(d))]
        k = min(PART_WINDOW_POINTS, us.size)
        near = cKDTree(X[us]).query(X[centre], k=k)[1]
        window = us[np.atleast_1d(near)]
        record = {"centre": [float(v) for v in X[centre]], "source": int(window.size),
                  "target": int(ut.size), "support": 0}
        records.append(record)
        hw = median_spacing(X[window])
        tolerance = max(noise or 0.0, PART_GATE * hw / 3.5)
        try:
            found = rigid_register(X[window], Y[ut], model="rigid", pipeline="exact", seed=seed,
                                   noise=tolerance, max_triples=AUTO_RIGID_TRIPLES, check_rivals=False,
                                   time_limit=max(1.0, deadline - time.perf_counter()))
        except ValueError:  # a degenerate window (collinear rows)
            found = None
        if not found:
            tried[window] = True
            return Candidate(None, 0, (record, None, window))
        c = found.correspondences
        seeds = np.column_stack([window[c[:, 0]], ut[c[:, 1]]])
        record.update(rigid_support=int(found.support), angle_deg=round(float(found.angle_deg), 2))
        return Candidate(seeds, int(seeds.shape[0]), (record, found, window))

    def accept(candidate):
        record, _, window = candidate.detail
        if candidate.motion is None or candidate.support < 3:
            return Judgement(False, "no rigid motion in the window")
        grown = ms.grow(X, Y, tree_y, candidate.motion, gate, spacing=spacing_x, tree_x=tree_x,
                        used_source=used_s, used_target=used_t)
        record["grown"] = int(grown.shape[0])
        if grown.shape[0] < least:
            tried[window] = True
            tried[grown[:, 0]] = True
            return Judgement(False, "its growth is smaller than a hypothesis must be", detail=grown)
        before = np.vstack(growths)
        record["contacts"] = n = contacts(X, Y, before, grown, strain, gate)
        if n < MIN_CONTACTS:  # a hinge: continuous only on its axis; else another body, or wrong
            hinge = hinged(X, Y, before, grown, gate)
            record["hinge_gap"] = None if hinge is None else hinge["gap"]
            if hinge is None or hinge["gap"] > hinge["gate"] or hinge["offset"] > hinge["reach"]:
                tried[window] = True
                tried[grown[:, 0]] = True
                # the rows it reached are another motion's: no later window there
                near = cKDTree(X[grown[:, 0]]).query(X[rows_x], k=1, distance_upper_bound=reach_s)[0]
                tried[rows_x[np.isfinite(near)]] = True
                return Judgement(False, _APART, detail=grown)
        return Judgement(True, detail=grown)

    def remove(candidate, judgement):
        grown = judgement.detail
        used_s[grown[:, 0]] = True
        used_t[grown[:, 1]] = True
        growths.append(grown)
        candidate.detail[0]["kept"] = True
        return [grown]

    streak = [0]

    def reject(candidate, judgement):
        streak[0] += 1
        if streak[0] >= MAX_FAILED_WINDOWS:
            return Stop(f"{MAX_FAILED_WINDOWS} windows in a row did not count")
        return None

    def keep(candidate, judgement):
        streak[0] = 0
        return remove(candidate, judgement)

    deadline = time.perf_counter() + time_limit
    peel_loop(search, accept, keep, reject=reject, deadline=deadline, max_rounds=MAX_PART_WINDOWS)
    label = np.concatenate([np.full(g.shape[0], i, np.int64) for i, g in enumerate(growths)])
    return PartSeeds(np.vstack(growths), label, tuple(records))


def contacts(X, Y, old, new, strain: float, gate: float) -> int:
    """Matches of ``new`` that meet a match of ``old`` continuously: within three matched spacings
    in the source (or, where the matches are sampled non-uniformly, among its ``GROW_NEIGHBOURS``
    nearest of ``old`` within three of its local spacings: a body's shoulder is sampled three times
    more sparsely than the median), ``y_b`` within ``strain · |x_a − x_b| + gate`` of where the local
    rigid motion of ``a`` (Kabsch on its ``MLS_NEIGHBOURS`` nearest of ``old``) takes ``x_b``:
    ``|(y_b − y_a) − R_a (x_b − x_a)|``.  Displacements compared as they are would differ by
    ``2 sin(θ/2) |x_a − x_b|`` between neighbours of one shape turned as a whole by θ, over the
    strain beyond about 20°, so that the parts of a turned body met only near their common axis;
    lengths alone would pass a part slid along the surface by twice the reach."""
    if old.shape[0] == 0 or new.shape[0] == 0:
        return 0
    xo, xn = X[old[:, 0]], X[new[:, 0]]
    yo, yn = Y[old[:, 1]], Y[new[:, 1]]
    both = np.vstack([xo, xn])
    radius = 3.0 * median_spacing(both)
    g = np.broadcast_to(np.asarray(gate, dtype=float), (Y.shape[0],))[new[:, 1]]
    local = ms.nonuniform_spacings(both, cKDTree(both))
    tree_o = cKDTree(xo)
    if local is None:  # about uniform: every old match within the radius
        lists = tree_o.query_ball_point(xn, radius)
        ii = np.repeat(np.arange(xn.shape[0]), [len(js) for js in lists])
        jj = np.fromiter((j for js in lists for j in js), np.int64, count=ii.size)
    else:
        reach = np.maximum(radius, 3.0 * local[xo.shape[0]:])
        k = min(ms.GROW_NEIGHBOURS, xo.shape[0])
        dist, js = tree_o.query(xn, k=k, distance_upper_bound=float(reach.max()))
        dist, js = dist.reshape(xn.shape[0], k), js.reshape(xn.shape[0], k)
        ii, kk = np.nonzero(dist <= reach[:, None])
        jj = js[ii, kk]
    if ii.size == 0:
        return 0
    # the local rigid motion of each old match that some new match reaches
    near = np.unique(jj)
    R = np.tile(np.eye(3), (xo.shape[0], 1, 1))
    m = min(ms.MLS_NEIGHBOURS, xo.shape[0])
    if m >= 3:
        nb = tree_o.query(xo[near], k=m)[1].reshape(near.size, m)
        R[near] = kabsch(xo[nb], yo[nb])[0]
    dx = xn[ii] - xo[jj]
    off = np.linalg.norm(yn[ii] - yo[jj] - np.einsum("nij,nj->ni", R[jj], dx), axis=1)
    close = off <= strain * np.linalg.norm(dx, axis=1) + g[ii]
    return int(np.unique(ii[close]).size)


def hinged(X, Y, old, new, gate: float) -> dict | None:
    """Whether ``new`` meets ``old`` at a joint: the rigid motions of the matches on each side of
    their contact (within three matched spacings of the other side, and their ``MLS_NEIGHBOURS``
    nearest on their own side) share a point near the contact (:func:`joint`).  A hinge moves
    continuously only along its axis, so :func:`contacts` finds few matches there.

    Returns :func:`joint`'s record plus ``offset`` (the centre's distance from the contact's
    centroid) and ``reach`` (the contact's radius plus three spacings), or None with fewer than 3
    matches on a side of the contact."""
    xo, xn = X[old[:, 0]], X[new[:, 0]]
    radius = 3.0 * median_spacing(np.vstack([xo, xn]))
    to, tn = cKDTree(xo), cKDTree(xn)
    near_o = np.flatnonzero(np.isfinite(to.query(xn, k=1, distance_upper_bound=radius)[0]))
    near_n = np.flatnonzero(np.isfinite(tn.query(xo, k=1, distance_upper_bound=radius)[0]))
    if near_o.size < 3 or near_n.size < 3:
        return None
    contact = np.vstack([xn[near_o], xo[near_n]])
    m = contact.mean(axis=0)
    k = ms.MLS_NEIGHBOURS
    side_o = np.unique(to.query(xo[near_n], k=min(k, xo.shape[0]))[1])
    side_n = np.unique(tn.query(xn[near_o], k=min(k, xn.shape[0]))[1])
    Ro, to_ = kabsch(xo[side_o], Y[old[side_o, 1]])
    Rn, tn_ = kabsch(xn[side_n], Y[new[side_n, 1]])
    record = joint(Part(side_o, Ro, to_, 0.0), Part(side_n, Rn, tn_, 0.0), contact)
    record["offset"] = float(np.linalg.norm(np.asarray(record["centre"]) - m))
    record["gate"] = float(np.median(np.asarray(gate)[new[side_n, 1]])) if np.ndim(gate) else float(gate)
    record["reach"] = float(np.max(np.linalg.norm(contact - m, axis=1))) + radius
    return record


# ------------------------------------------------------------ near-rigid parts
@dataclass(frozen=True, eq=False)
class Part:
    """One near-rigid part: ``rows`` (indices into the matches), ``rotation`` (3, 3) and
    ``translation`` (3,) with ``target ≈ source @ rotation.T + translation``, ``rms`` of its
    matches' residuals."""

    rows: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    rms: float


def _graph(xs, radius):
    a, b = ms.neighbour_pairs(xs, radius)
    return a, b, xs.shape[0]


def rigid_parts(source_points, target_points, *, tolerance: float, seed: int = 0,
                min_size: int | None = None, radius: float | None = None) -> list[Part]:
    """Split matches into connected parts that each move rigidly within ``tolerance``.

    The peel loop (:func:`gatv.peel_loop.peel_loop`): each round takes
    ``PART_HYPOTHESES`` seeded matches among those left, fits the rigid
    motion of each one's 12 nearest matches (its local motion), and counts
    the matches within ``tolerance`` of it that are connected to the seed in
    the source (matches closer than ``radius``, default three median matched
    spacings, or among the nearest within three local spacings where the sampling is
    non-uniform: :func:`gatv.nonrigid.multiscale.neighbour_pairs`).  The best is refitted on its inliers (Kabsch) and counted
    again; it is kept when it holds ``min_size`` matches (default
    ``max(8, PART_MIN_SHARE · K)``) and its matches are removed.  Same seed,
    same parts.

    Returns
    -------
    list of Part
        Largest first.
    """
    xs = np.asarray(source_points, dtype=np.float64)
    ys = np.asarray(target_points, dtype=np.float64)
    K = xs.shape[0]
    if min_size is None:
        min_size = max(8, int(np.ceil(PART_MIN_SHARE * K)))
    if K < max(min_size, 4):
        return []
    radius = 3.0 * median_spacing(xs) if radius is None else float(radius)
    a, b, _ = _graph(xs, radius)
    rng = np.random.default_rng(seed)
    left = np.ones(K, bool)
    kn = min(ms.MLS_NEIGHBOURS, K)

    def component(inlier, start):
        ok = inlier[a] & inlier[b]
        g = coo_matrix((np.ones(int(ok.sum())), (a[ok], b[ok])), shape=(K, K))
        _, lab = connected_components(g, directed=False)
        return inlier & (lab == lab[start])

    def search():
        rows = np.flatnonzero(left)
        if rows.size < min_size:
            return Stop("fewer matches left than a part holds", exhausted=True)
        starts = rows if rows.size <= PART_HYPOTHESES else np.sort(
            rng.choice(rows, PART_HYPOTHESES, replace=False))
        tree = cKDTree(xs[rows])
        nb = rows[tree.query(xs[starts], k=min(kn, rows.size))[1]]
        R, t = kabsch(xs[nb], ys[nb])
        res = np.linalg.norm(np.einsum("hij,kj->hki", R, xs[rows]) + t[:, None, :] - ys[rows][None], axis=2)
        counts = (res <= tolerance).sum(axis=1)
        best = None
        for h in np.argsort(-counts, kind="stable")[:PART_CONNECTED]:  # the connected count of the best
            inl = np.zeros(K, bool)
            inl[rows[res[h] <= tolerance]] = True
            members = component(inl, starts[h])
            if best is None or members.sum() > best[1].sum():
                best = (h, members)
        members = best[1]
        if members.sum() < 3:  # no hypothesis holds its own seed: nothing rigid left
            return Candidate(None, int(members.sum()), members)
        for _ in range(2):  # refit on the inliers, count again
            Rf, tf = kabsch(xs[members], ys[members])
            inl = np.zeros(K, bool)
            r = np.linalg.norm(xs[rows] @ Rf.T + tf - ys[rows], axis=1)
            inl[rows[r <= tolerance]] = True
            start = np.flatnonzero(members)[0] if members.any() else starts[best[0]]
            grown = component(inl, start)
            if grown.sum() < members.sum():
                break
            members = grown
        Rf, tf = kabsch(xs[members], ys[members])
        return Candidate((Rf, tf), int(members.sum()), members)

    def accept(candidate):
        return Judgement(candidate.motion is not None and candidate.support >= min_size, "smaller than a part")

    def remove(candidate, judgement):
        members = candidate.detail
        left[members] = False
        R, t = candidate.motion
        r = np.linalg.norm(xs[members] @ R.T + t - ys[members], axis=1)
        return [Part(np.flatnonzero(members), R, t, float(np.sqrt(np.mean(r ** 2))))]

    outcome = peel_loop(search, accept, remove)
    return sorted(outcome.found, key=lambda p: -p.rows.size)


def joint(part_a: Part, part_b: Part, boundary) -> dict:
    """The joint of two parts that meet: axis and centre of their relative rotation.

    ``boundary`` (B, 3): source points where the parts meet.  The relative
    rotation ``R_a^T R_b`` (source frame) gives the axis and the angle; the
    centre is the point nearest the boundary's centroid ``m`` that both
    motions move alike, the least-squares (minimum-norm about ``m``)
    solution of ``(R_a − R_b) c = t_b − t_a``; ``gap`` is how far apart the
    two motions move it (0 for a true joint).
    """
    Ra, ta, Rb, tb = part_a.rotation, part_a.translation, part_b.rotation, part_b.translation
    rotor = Rotor.from_matrix(Ra.T @ Rb)
    axis, angle = rotor.as_axis_angle()
    m = np.asarray(boundary, dtype=float).mean(axis=0)
    A = Ra - Rb
    c = m + np.linalg.lstsq(A, tb - ta - A @ m, rcond=1e-6)[0]
    gap = float(np.linalg.norm(Ra @ c + ta - (Rb @ c + tb)))
    return {"axis": [float(v) for v in axis], "angle_deg": float(np.degrees(angle)),
            "centre": [float(v) for v in c], "moved_centre": [float(v) for v in Ra @ c + ta],
            "gap": gap}


def parts_info(source_points, target_points, *, spacing: float, floor: float = 0.0,
               seed: int = 0) -> tuple[list, list, np.ndarray]:
    """``info["parts"]``, ``info["joints"]`` and the part label of each match (-1: none).

    Parts from :func:`rigid_parts` at ``PART_TOLERANCE`` target spacings
    plus the noise ``floor``; each as a dict: ``rotor`` (scalar first),
    ``rotation``, ``translation``, ``angle_deg``, ``size``, ``rms``,
    ``joints`` (indices into the joints).  Above ``PART_MAX_POINTS`` matches
    the parts are found on a seeded subsample of that many, and each match
    takes the part of its nearest sampled match when that part's motion fits
    it within the tolerance.  Two parts meet when a match of
    one lies within three matched spacings of a match of the other (or, where the matches are
    sampled non-uniformly, is among its nearest within three of its local spacings:
    :func:`gatv.nonrigid.multiscale.neighbour_pairs`); their joint is :func:`joint` with
    ``parts`` the two part indices.
    """
    xs = np.asarray(source_points, dtype=np.float64)
    ys = np.asarray(target_points, dtype=np.float64)
    K = xs.shape[0]
    labels = np.full(K, -1, np.int64)
    if K < 8:
        return [], [], labels
    tolerance = PART_TOLERANCE * spacing + floor
    radius = 3.0 * median_spacing(xs)
    if K <= PART_MAX_POINTS:
        found = rigid_parts(xs, ys, tolerance=tolerance, seed=seed, radius=radius)
    else:  # the parts of a seeded subsample; every match then takes its nearest sampled match's
        # part when that part's motion fits it within the tolerance
        sub = np.sort(np.random.default_rng(seed).choice(K, PART_MAX_POINTS, replace=False))
        found = rigid_parts(xs[sub], ys[sub], tolerance=tolerance, seed=seed)
        lab = np.full(sub.size, -1, np.int64)
        for i, p in enumerate(found):
            lab[p.rows] = i
        near = lab[cKDTree(xs[sub]).query(xs, k=1)[1]]
        fits = np.zeros(K, bool)
        for i, p in enumerate(found):
            rows = np.flatnonzero(near == i)
            fits[rows] = np.linalg.norm(xs[rows] @ p.rotation.T + p.translation - ys[rows], axis=1) <= tolerance
        near[~fits] = -1
        found = [Part(np.flatnonzero(near == i), p.rotation, p.translation, p.rms) for i, p in enumerate(found)]
    parts = []
    for i, p in enumerate(found):
        labels[p.rows] = i
        rotor = Rotor.from_matrix(p.rotation)
        parts.append({"rotor": [float(v) for v in rotor.as_quaternion()],
                      "rotation": p.rotation.tolist(), "translation": [float(v) for v in p.translation],
                      "angle_deg": float(np.degrees(rotor.angle)), "size": int(p.rows.size),
                      "rms": p.rms, "joints": []})
    joints = []
    if len(found) >= 2:
        a, b, _ = _graph(xs, radius)
        la, lb = labels[a], labels[b]
        cross = (la >= 0) & (lb >= 0) & (la != lb)
        lo, hi = np.minimum(la[cross], lb[cross]), np.maximum(la[cross], lb[cross])
        for i, j in sorted(set(zip(lo.tolist(), hi.tolist()))):
            sel = (lo == i) & (hi == j)
            ends = np.unique(np.r_[a[cross][sel], b[cross][sel]])
            if ends.size < 3:
                continue
            record = dict(joint(found[i], found[j], xs[ends]), parts=[i, j], contacts=int(ends.size))
            parts[i]["joints"].append(len(joints))
            parts[j]["joints"].append(len(joints))
            joints.append(record)
    return parts, joints, labels
