"""Acceptance of matches: posterior probabilities, the chance level, rivals.

Three tests decide what the matcher reports, all "precision first":

* **Posterior** (:func:`posterior`, probabilistic data association): a
  match is kept when its probability of being its ray's true partner,
  against a chance ray of view 2 and against the other candidates of
  either ray, reaches ``MIN_POSTERIOR``. :func:`rigid_posterior` applies
  it to the pairs of a pure rotation; the epipolar stage applies it in its
  last growth round.
* **Chance level**: the support a wrong rotation reaches by chance on the
  sphere, :func:`gatv.stats.chance_support` over the area :func:`cap_area`
  that view 2's rays cover; a stage's answer must beat it.
* **Rivals** (:func:`rival`, repeated structure): a regular pattern, such
  as a checkerboard, also matches itself shifted by one period, and the
  shifted matching is as rigid (and as epipolar: a planar board is
  degenerate for the essential matrix) as the true one. The analogue of
  Lowe's ratio test at the level of hypotheses: when a rival with other
  partners explains ``RIVAL_RATIO`` of the winner's pairs, nothing tells
  which is right and the matcher reports nothing.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from catadioptric.constants import (
    GATE_SIGMAS,
    MIN_POSTERIOR,
    RIVAL_ANCHORS,
    RIVAL_SEEDS,
    TRIANGLE_NEIGHBOURS,
)
from catadioptric.rotation import gated_pairs, grow_local

__all__ = [
    "cap_area",
    "likelihood",
    "posterior",
    "rigid_posterior",
    "rival",
    "rival_likelihood",
]


# --------------------------------------------------------------- posterior
def likelihood(e, s_across, s_along):
    """Density per steradian of a true pair's residual: ``exp(-e^2/2) / (2 pi s_across s_along)``.

    ``e``: the residual's Mahalanobis norm; ``s_across``, ``s_along``: its
    standard deviations across and along the arc, on the unit sphere.
    """
    return np.exp(-0.5 * np.asarray(e, dtype=np.float64) ** 2) / (2.0 * np.pi * s_across * s_along)


def rival_likelihood(pairs, own, cand, like, n1, n2):
    """Summed likelihood of each match's rivals: the other candidates of either of its rays.

    ``cand`` (C, 2) are the candidate pairs inside the gate and ``like``
    their likelihoods (:func:`likelihood`); ``own`` is each match's own
    likelihood as counted among them (0 for a match that is not a
    candidate); ``n1, n2`` the numbers of rays of the views.
    """
    per1 = np.bincount(cand[:, 0], like, minlength=n1)
    per2 = np.bincount(cand[:, 1], like, minlength=n2)
    return np.maximum(per1[pairs[:, 0]] + per2[pairs[:, 1]] - 2.0 * own, 0.0)


def posterior(pairs, like, tree2, n1, rivals=0.0, k=16):
    """Posterior probability that each match is its ray's true partner.

    Probabilistic data association (Bar-Shalom), one view-1 ray at a time:
    a true partner's residual has the density ``like`` (:func:`likelihood`);
    every other ray of view 2 lands there like clutter, with the local
    density ``lam`` of view 2's rays (all of them, the match's own left
    out: under "no partner" any ray may be the chance one; from the ``k``
    nearest in ``tree2``, their :class:`~scipy.spatial.cKDTree`); the prior
    that a ray of view 1 has a partner is the share ``p`` of the ``n1``
    predicted rays matched. The match's ``rivals``
    (:func:`rival_likelihood`: the other candidates of either ray, any of
    which may be the true pair instead) share the evidence::

        P = like / (lam (1 - p) / p + like + rivals)

    Why this form: it is calibrated (or conservative) on the benchmark's
    scenes, where leaving out the rivals, or counting only the unmatched
    rays as clutter, made the odds too high; see docs/design-notes.md
    (catadioptric).
    """
    if pairs.shape[0] == 0:
        return np.empty(0)
    r2 = tree2.data
    kk = min(k + 1, r2.shape[0])
    if kk < 2:
        return np.ones(pairs.shape[0])
    dk = tree2.query(r2[pairs[:, 1]], k=kk)[0][:, -1]
    lam = (kk - 1) / (np.pi * np.maximum(dk, 1e-12) ** 2)
    p = min(max(pairs.shape[0] / max(n1, 1), 1e-3), 1.0 - 1e-3)
    return like / (lam * (1.0 - p) / p + like + rivals)


def rigid_posterior(r1, tree2, s1, s2, R, pairs):
    """The pairs of a rotation whose posterior (:func:`posterior`) reaches ``MIN_POSTERIOR``.

    The residual ``y - R x`` of a true pair is isotropic Gaussian with the
    pair's noise per axis; the rivals are the other pairs inside the noise
    gate of either ray; the prior counts the rays of view 1 that the
    rotation brings into the cap of view 2's rays (``tree2``: their
    :class:`~scipy.spatial.cKDTree`).
    """
    r2 = tree2.data
    moved = r1 @ R.T
    gmax = GATE_SIGMAS * math.sqrt(float(s1.max()) ** 2 + float(s2.max()) ** 2)
    near = cKDTree(moved).sparse_distance_matrix(tree2, gmax, output_type="ndarray")
    ci, cj = near["i"].astype(np.int64), near["j"].astype(np.int64)
    sig_c = np.sqrt(s1[ci] ** 2 + s2[cj] ** 2)
    inside = near["v"] <= GATE_SIGMAS * sig_c
    cand = np.column_stack([ci[inside], cj[inside]])
    like_c = likelihood(near["v"][inside] / sig_c[inside], sig_c[inside], sig_c[inside])
    sig = np.sqrt(s1[pairs[:, 0]] ** 2 + s2[pairs[:, 1]] ** 2)
    e = np.linalg.norm(r2[pairs[:, 1]] - moved[pairs[:, 0]], axis=1) / sig
    like = likelihood(e, sig, sig)
    rivals = rival_likelihood(pairs, np.where(e <= GATE_SIGMAS, like, 0.0), cand, like_c, r1.shape[0], r2.shape[0])
    cap = _cap(r2)
    n1 = r1.shape[0] if cap is None else int(np.count_nonzero(moved @ cap[0] >= cap[1]))
    return pairs[posterior(pairs, like, tree2, max(n1, pairs.shape[0]), rivals) >= MIN_POSTERIOR]


# --------------------------------------------------------------- chance level
def _cap(rays):
    """``(axis, cos)`` of the smallest cap around the mean direction holding 99% of the rays.

    None when the mean direction vanishes (rays all around the sphere).
    """
    m = rays.mean(axis=0)
    nm = np.linalg.norm(m)
    if nm < 1e-9:
        return None
    return m / nm, float(np.quantile(rays @ (m / nm), 0.01))


def cap_area(rays) -> float:
    """Area of the smallest cap around the mean direction holding 99% of the rays.

    The region the rays of a view cover (a catadioptric image sees a cap of
    the sphere, not all of it): the area over which chance rays spread.
    ``4 pi`` when the rays lie all around the sphere. The chance level of
    :func:`catadioptric.match` is :func:`gatv.stats.chance_support` over it.
    """
    cap = _cap(rays)
    if cap is None:
        return 4.0 * math.pi
    return max(2.0 * math.pi * (1.0 - cap[1]), 1e-6)


# --------------------------------------------------------------- rivals
def rival(r1, r2, tree2, s1, s2, pairs):
    """Best rival of the matches ``pairs``: a locally rigid matching with other partners.

    The analogue of Lowe's ratio test at the level of hypotheses. A regular
    pattern also matches itself shifted by one period; the shift moves
    every partner ``y_j`` by about the same vector (on a small patch) as
    the one from a matched target ray to one of its neighbours. For a few
    anchors among the matches (``RIVAL_ANCHORS``, spread over the matched
    rays) and each of the anchor's ``TRIANGLE_NEIGHBOURS`` target
    neighbours, the ``RIVAL_SEEDS`` matches nearest the anchor are moved by
    that vector onto the nearest target rays (within two noise gates) and
    grown by :func:`catadioptric.rotation.grow_local`. A rival's support is
    the number of its pairs that are not matches (different partners; a
    rival that snaps back onto the matches counts nothing). On scattered
    corners a shifted seed is a set of chance pairs and grows to about the
    chance level; on a grid it grows over the whole overlap (``(a - 1) / a``
    of an ``a``-square-wide board). Returns ``(support, rival pairs not
    among the matches)``.
    """
    m = pairs.shape[0]
    empty = (0, np.empty((0, 2), np.int64))
    if m < 4 or r2.shape[0] < 2:
        return empty
    xs = r1[pairs[:, 0]]
    # anchors: the match nearest the centroid, then farthest-point spread
    c = xs.mean(axis=0)
    anchors = [int(np.argmin(np.linalg.norm(xs - c, axis=1)))]
    dmin = np.linalg.norm(xs - xs[anchors[0]], axis=1)
    while len(anchors) < min(RIVAL_ANCHORS, m):
        # half-way out: far enough to see another part, with neighbours around
        far = np.flatnonzero(dmin >= 0.5 * dmin.max())
        a = int(far[np.argmin(dmin[far])])
        anchors.append(a)
        dmin = np.minimum(dmin, np.linalg.norm(xs - xs[a], axis=1))
    tree1 = cKDTree(xs)
    known = set(map(tuple, pairs.tolist()))
    k = min(TRIANGLE_NEIGHBOURS + 1, r2.shape[0])
    best = empty
    for a in anchors:
        j0 = pairs[a, 1]
        _, nbj = tree2.query(r2[j0], k=k)
        _, near = tree1.query(xs[a], k=min(RIVAL_SEEDS, m))
        near = np.atleast_1d(near)
        for jn in np.atleast_1d(nbj)[1:]:
            d = r2[jn] - r2[j0]
            moved = np.full((r1.shape[0], 3), np.inf)
            moved[pairs[near, 0]] = r2[pairs[near, 1]] + d
            seeds = gated_pairs(moved, r2, tree2, s1, s2, 2.0)
            if seeds.shape[0] < 3:
                continue
            grown = grow_local(r1, r2, tree2, s1, s2, seeds)
            other = np.array([p for p in grown.tolist() if tuple(p) not in known], np.int64).reshape(-1, 2)
            if other.shape[0] > best[0]:
                best = (int(other.shape[0]), other)
    return best
