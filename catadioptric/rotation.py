"""Rotation search on the unit sphere: the dominant camera rotation and rigid growth.

A pure camera rotation moves the rays rigidly about the centre of the
sphere, ``y = R x``. Local oriented triangles (each ray with two of its
nearest neighbours, counter-clockwise) are matched between the views by
their side lengths; each match gives a trial rotation (three rays suffice,
the sphere's centre is the fourth, fixed point), and the densest cluster of
trial rotations, found by counting neighbours in quaternion space, is the
dominant rotation (:func:`dominant_rotation`). It is polished by
rotation-only ICP inside the per-pair noise gate (:func:`rotation_icp`).
With a camera translation the rays move only locally rigidly:
:func:`grow_local` moves each ray by the rotation of its nearest matched
neighbours.

Why not the congruent-triple search of :func:`gatv.register`: on a sphere
every wrong rotation maps the points onto the same surface, so its
volumetric chance level accepts wrong trials, and a triangle has more
congruent partners than that search keeps.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from catadioptric.constants import (
    GATE_SIGMAS,
    QUATERNION_SAMPLE,
    REACH_SPACINGS,
    TRIANGLE_NEIGHBOURS,
)
from gatv.validation import check_memory
from gatv.candidates import one_to_one
from gatv.fitting import kabsch

__all__ = ["dominant_rotation", "gated_pairs", "grow_local", "rotation_icp", "voted_seeds"]

#: Bytes per trial rotation while the trials are fitted (the stacked 3x3
#: covariances, their SVD factors and the products), for the memory check.
_BYTES_PER_TRIAL = 1024


def _quaternions(R):
    """Unit quaternions ``(w, x, y, z)`` with ``w >= 0`` of rotation stacks."""
    tr = np.trace(R, axis1=1, axis2=2)
    w = 0.5 * np.sqrt(np.maximum(0.0, 1.0 + tr))
    x = 0.5 * np.sqrt(np.maximum(0.0, 1.0 + R[:, 0, 0] - R[:, 1, 1] - R[:, 2, 2]))
    y = 0.5 * np.sqrt(np.maximum(0.0, 1.0 - R[:, 0, 0] + R[:, 1, 1] - R[:, 2, 2]))
    z = 0.5 * np.sqrt(np.maximum(0.0, 1.0 - R[:, 0, 0] - R[:, 1, 1] + R[:, 2, 2]))
    x = np.copysign(x, R[:, 2, 1] - R[:, 1, 2])
    y = np.copysign(y, R[:, 0, 2] - R[:, 2, 0])
    z = np.copysign(z, R[:, 1, 0] - R[:, 0, 1])
    q = np.column_stack([w, x, y, z])
    return q / np.linalg.norm(q, axis=1)[:, None]


def _triangles(rays, k: int):
    """Oriented local triangles ``(a, b, c)`` and their side lengths.

    ``b, c`` are two of the ``k`` nearest neighbours of ``a`` with
    ``det(a, b, c) > 0`` (counter-clockwise seen from outside the sphere;
    a rotation keeps the orientation, a mirror would not).
    """
    n = rays.shape[0]
    k = min(k, n - 1)
    if k < 2:
        return np.empty((0, 3), np.int64), np.empty((0, 3))
    _, nb = cKDTree(rays).query(rays, k=k + 1)
    nb = nb[:, 1:]
    p, q = np.triu_indices(k, 1)
    a = np.repeat(np.arange(n), p.size)
    b = nb[:, p].ravel()
    c = nb[:, q].ravel()
    det = np.einsum("ij,ij->i", rays[a], np.cross(rays[b], rays[c]))
    swap = det < 0
    b, c = np.where(swap, c, b), np.where(swap, b, c)
    tri = np.column_stack([a, b, c])
    sides = np.column_stack([
        np.linalg.norm(rays[a] - rays[b], axis=1),
        np.linalg.norm(rays[a] - rays[c], axis=1),
        np.linalg.norm(rays[b] - rays[c], axis=1),
    ])
    return tri, sides


def _trial_rotations(r1, r2, rel_tol, max_matches=8, memory_budget=None):
    """Rotations of source triangles onto target triangles of the same shape.

    Returns the rotations (K, 3, 3) and the triangles' vertex pairs
    (K, 3, 2) ``(source ray, target ray)``. Raises
    :class:`~gatv.errors.InputError` when the trials would not fit in
    ``memory_budget`` bytes.
    """
    t1, s1 = _triangles(r1, TRIANGLE_NEIGHBOURS)
    t2, s2 = _triangles(r2, TRIANGLE_NEIGHBOURS)
    empty = np.empty((0, 3, 3)), np.empty((0, 3, 2), np.int64)
    if t1.shape[0] == 0 or t2.shape[0] == 0:
        return empty
    l1, l2 = np.log(np.maximum(s1, 1e-12)), np.log(np.maximum(s2, 1e-12))
    k = min(max_matches, t2.shape[0])
    check_memory(16.0 * len(l1) * k, f"{len(l1) * k:,} triangle matches", memory_budget)
    dist, j = cKDTree(l2).query(l1, k=k, distance_upper_bound=rel_tol)
    dist, j = dist.reshape(len(l1), -1), j.reshape(len(l1), -1)
    ii, kk = np.nonzero(np.isfinite(dist))
    if ii.size == 0:
        return empty
    check_memory(float(_BYTES_PER_TRIAL) * ii.size, f"{ii.size:,} trial rotations", memory_budget)
    a, b = t1[ii], t2[j[ii, kk]]
    return kabsch(r1[a], r2[b], translation=False)[0], np.stack([a, b], axis=2)


def dominant_rotation(r1, r2, rel_tol, radius_deg, max_matches=8, memory_budget=None):
    """Densest cluster of trial rotations of matched local triangles.

    Parameters
    ----------
    r1, r2 : (N1, 3), (N2, 3) ndarray
        Unit rays of the two views.
    rel_tol : float
        Tolerance on the triangles' log side lengths.
    radius_deg : float
        Radius of the cluster, degrees of rotation angle.
    max_matches : int, default: 8
        Target triangles retrieved per source triangle (nearest in shape).
    memory_budget : float, optional
        Bytes the trial tables may take (:func:`gatv.validation.check_memory`).

    Returns
    -------
    tuple
        ``(rotation, cluster size, number of trials, vertex pairs of the
        cluster's trials)``; the rotation is None when no triangles matched.
    """
    Rs, verts = _trial_rotations(r1, r2, rel_tol, max_matches, memory_budget)
    if Rs.shape[0] == 0:
        return None, 0, 0, np.empty((0, 2), np.int64)
    q = _quaternions(Rs)
    both = np.vstack([q, -q])
    tree = cKDTree(both)
    rad = 2.0 * math.sin(math.radians(radius_deg) / 4.0)  # chord for a rotation angle
    if q.shape[0] <= QUATERNION_SAMPLE:
        sample = q
    else:
        sample = q[np.random.default_rng(0).choice(q.shape[0], QUATERNION_SAMPLE, replace=False)]
    counts = tree.query_ball_point(sample, rad, return_length=True)
    best = int(np.argmax(counts))
    near = np.asarray(tree.query_ball_point(sample[best], rad), dtype=np.int64)
    qs = both[near]
    qs = qs * np.sign(qs @ sample[best])[:, None]
    m = qs.mean(axis=0)
    m /= np.linalg.norm(m)
    w, x, y, z = m
    R = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    members = np.unique(near % q.shape[0])
    return R, int(counts[best]), int(Rs.shape[0]), verts[members]


def voted_seeds(vertex_pairs, min_votes=2):
    """Pairs named by at least ``min_votes`` trials of a cluster, one-to-one by votes.

    A pair that several trial rotations of the cluster agree on is a safer
    seed for growth than one named by a single (possibly chance) triangle.
    """
    vertex_pairs = vertex_pairs.reshape(-1, 2)
    if vertex_pairs.shape[0] == 0:
        return vertex_pairs
    pairs, votes = np.unique(vertex_pairs, axis=0, return_counts=True)
    ok = votes >= min_votes
    pairs, votes = pairs[ok], votes[ok]
    if pairs.shape[0] == 0:
        return pairs
    return pairs[one_to_one(pairs, -votes.astype(np.float64))]


def grow_local(r1, r2, tree2, s1, s2, seeds, neighbours=6, scale=2.0, rounds=15, final_scale=1.0):
    """Locally rigid growth: each ray moves by the rotation of its nearest matches.

    The rotation (about the sphere's centre) fitted on the ``neighbours``
    matched rays nearest to a source ray predicts where it lands; target
    rays within ``scale`` noise gates of the prediction are matched
    one-to-one, closest first, and the matches are recomputed from the
    previous round's until they repeat (the local constraint of section
    5.1: rigid only between neighbours); the last round uses
    ``final_scale``. A ray farther than ``REACH_SPACINGS`` match spacings
    from every match is not predicted.

    ``tree2`` is the :class:`~scipy.spatial.cKDTree` of ``r2``; ``s1, s2``
    the rays' sphere noise. Returns the pairs (K, 2) of rows of ``r1, r2``.
    """
    pairs = seeds
    for r in range(rounds + 1):
        if pairs.shape[0] < 3:
            return pairs
        last = r == rounds
        xs, ys = r1[pairs[:, 0]], r2[pairs[:, 1]]
        k = min(neighbours, pairs.shape[0])
        _, nb = cKDTree(xs).query(r1, k=k)
        nb = nb.reshape(r1.shape[0], k)
        Rl = kabsch(xs[nb], ys[nb], translation=False)[0]
        pred = np.einsum("kij,kj->ki", Rl, r1)
        # a ray far from every match is not predicted
        reach = np.linalg.norm(r1 - xs[nb[:, 0]], axis=1)
        spacing = float(np.median(cKDTree(xs).query(xs, k=2)[0][:, 1])) if xs.shape[0] > 1 else 1.0
        pred[reach > REACH_SPACINGS * spacing] = np.inf
        new = gated_pairs(pred, r2, tree2, s1, s2, final_scale if last else scale)
        if last:
            return new
        if new.shape == pairs.shape and np.array_equal(new, pairs):
            rounds = r + 1
        pairs = new
    return pairs


def gated_pairs(moved, r2, tree2, s1, s2, scale=1.0, k=4):
    """One-to-one pairs within ``scale`` per-pair noise gates, closest first.

    ``moved`` (N1, 3): the predicted positions of view 1's rays (rows that
    are not finite are not predicted); each is paired with the nearest of
    its ``k`` nearest rays of ``r2`` (tree ``tree2``) whose distance is
    within ``scale * GATE_SIGMAS * sqrt(s1[i]^2 + s2[j]^2)``.
    """
    gmax = scale * GATE_SIGMAS * math.sqrt(float(s1.max()) ** 2 + float(s2.max()) ** 2)
    rows = np.flatnonzero(np.all(np.isfinite(moved), axis=1))
    d, j = tree2.query(moved[rows], k=min(k, r2.shape[0]), distance_upper_bound=gmax)
    d, j = d.reshape(len(rows), -1), j.reshape(len(rows), -1)
    ii, kk = np.nonzero(np.isfinite(d))
    jj, dd = j[ii, kk], d[ii, kk]
    ii = rows[ii]
    ok = dd <= scale * GATE_SIGMAS * np.sqrt(s1[ii] ** 2 + s2[jj] ** 2)
    pairs = np.column_stack([ii[ok], jj[ok]]).astype(np.int64)
    if pairs.shape[0] == 0:
        return pairs
    return pairs[one_to_one(pairs, dd[ok])]


def rotation_icp(r1, r2, tree2, s1, s2, R, iterations=30):
    """Rotation-only ICP from the trial rotation ``R``; returns ``(R, pairs)``.

    The gate narrows from 4 to 2 to 1 noise gates: the trial rotation (a
    cluster mean) is a few degrees off, so the first pairs need a wide
    gate, and the last ones the plain noise gate.
    """
    kept = np.empty((0, 2), np.int64)
    for scale in (4.0, 2.0, 1.0):
        for _ in range(iterations):
            new = gated_pairs(r1 @ R.T, r2, tree2, s1, s2, scale)
            if new.shape[0] < 3:
                break
            R = kabsch(r1[new[:, 0]], r2[new[:, 1]], translation=False)[0]
            if new.shape == kept.shape and np.array_equal(new, kept):
                break
            kept = new
    kept = gated_pairs(r1 @ R.T, r2, tree2, s1, s2)
    return R, kept
