"""The paper's method on the sphere: a curved surface of candidate pairs, found by tensor voting.

End of section 5.1 of Reyes, Medioni & Bayro (IJCV 2007), Fig. 15: the
corners of both images are lifted to the unit sphere, and there "the
corresponding corners form a curved 3D surface which is easily detected
using Tensor Voting", the true pairs being checked with eq. 41 only
locally (the non-rigid mode, Fig. 14). :func:`voting_stage` runs it as
``catadioptric.match(..., strategy="voting")``:

1. **Candidates.** After the dominant rotation (when one beats the chance
   level; else the identity), every ray of view 1 is paired with the rays
   of view 2 within ``max_parallax``.
2. **Tokens.** The rays are charted on the plane by the azimuthal
   equidistant projection about the mean ray of view 2 (``(u, v)``, in
   radians, undistorted near the centre, defined up to the antipode). A
   pair's displacement is smooth over the sphere for the true pairs
   (parallax varies with depth, smoothly over each surface of the scene),
   so the tokens ``(u, v, Δu)`` and ``(u, v, Δv)`` of the true pairs lie on
   two curved surfaces, and the wrong pairs scatter (Kang's two joint
   spaces, as :mod:`gatv.models.affine2d` uses them).
3. **Votes.** :func:`gatv.voting.extract_surfaces` in each joint space, at
   σ twice the rays' median spacing (the surface is sampled that densely); a
   candidate is kept when it survives in both, with the smaller of its two
   relative surface saliencies.
4. **Local eq. 41.** Each kept token is checked against its closest kept
   tokens that use neither of its rays (Fig. 14 shows the closest one;
   here the ``EQ41_NEIGHBOURS`` closest, and most must pass): the length half of eq. 41,
   ``|V · Vs| / |Vs|`` on the sphere points (a locally rigid motion about
   the sphere's centre keeps the distance between neighbouring rays), up to
   ``strain · |Δx|`` plus the pair noise gate.
5. **Selection.** One-to-one by the share of passed checks, then
   saliency; the whole must beat the chance level of the sphere.

No growth, no epipolar model: the stage is the paper's, measured beside
the default (``"auto"``) in ``benchmarks/catadioptric.py``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from catadioptric.constants import GATE_SIGMAS
from gatv.candidates import one_to_one
from gatv.ga import eq41_length_residual

__all__ = ["chart", "voting_stage"]

#: Relative length change allowed between neighbouring true pairs by the
#: local eq. 41 (the default of :func:`gatv.nonrigid.register`): parallax
#: stretches the rays' neighbourhoods where depth changes.
STRAIN = 0.35
#: Closest kept tokens each token is checked against with the local eq. 41;
#: a token is verified when most of them pass (Fig. 14 checks the closest
#: one; a majority of several is what a lone chance token cannot reach).
EQ41_NEIGHBOURS = 6
#: Candidates per ray of view 1 at most (the nearest within ``max_parallax``):
#: the true surface is sampled only as densely as the corners, so every
#: further candidate per ray thickens the clutter around it.
MAX_CANDIDATES = 8


def chart(rays, centre):
    """Azimuthal equidistant coordinates ``(u, v)`` (radians) of unit ``rays`` about ``centre``."""
    c = centre / np.linalg.norm(centre)
    a = np.array([1.0, 0.0, 0.0]) if abs(c[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(c, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(c, e1)
    cos = np.clip(rays @ c, -1.0, 1.0)
    theta = np.arccos(cos)
    px, py = rays @ e1, rays @ e2
    rho = np.hypot(px, py)
    scale = np.where(rho > 1e-12, theta / np.maximum(rho, 1e-12), 1.0)
    return np.column_stack([px * scale, py * scale])


def voting_stage(r1, r2, tree2, s1, s2, R, noise, max_parallax, chance, info, memory_budget=None):
    """Correspondences of the paper's method (module docstring); ``(K, 2)`` rows of ``r1, r2``.

    ``R`` is the dominant rotation or None; ``chance`` the chance level the
    result must reach (else it is empty, ``info["voting_reason"]``).
    """
    from gatv.voting import extract_surfaces

    empty = np.empty((0, 2), np.int64)
    x = r1 if R is None else r1 @ R.T
    k = min(MAX_CANDIDATES, r2.shape[0])
    dist, j = tree2.query(x, k=k, distance_upper_bound=max_parallax)
    dist, j = dist.reshape(x.shape[0], k), j.reshape(x.shape[0], k)
    ii, kk = np.nonzero(np.isfinite(dist))
    cand = np.column_stack([ii, j[ii, kk]]).astype(np.int64)
    info["voting_candidates"] = int(cand.shape[0])
    if cand.shape[0] < 8:
        info["voting_reason"] = "fewer than 8 candidate pairs"
        return empty
    centre = r2.mean(axis=0)
    if np.linalg.norm(centre) < 1e-9:
        centre = np.array([0.0, 0.0, 1.0])
    cx, cy = chart(x, centre), chart(r2, centre)
    uv = cx[cand[:, 0]]
    duv = cy[cand[:, 1]] - uv
    # the scale of the surface: twice the corners' spacing on the sphere
    sigma = 2.0 * float(np.median(cKDTree(x).query(x, k=2)[0][:, 1]))
    info["voting_sigma"] = sigma
    kept = np.zeros(cand.shape[0], bool)
    sal = np.full(cand.shape[0], np.inf)
    # the displacement axis stretched so that the candidates fill a cube (the
    # chart's extent over the candidates' spread): the clutter thins out while
    # the true surface, as thin as the noise, stays a surface
    spread = max(float(np.ptp(duv)), 1e-12)
    stretch = float(np.max(np.ptp(uv, axis=0))) / spread
    info["voting_stretch"] = stretch
    for axis in (0, 1):
        tokens = np.column_stack([uv, stretch * duv[:, axis]])
        surf = extract_surfaces(tokens, sigma, memory_budget=memory_budget)
        keep = np.zeros(cand.shape[0], bool)
        keep[surf.indices] = True
        s = np.zeros(cand.shape[0])
        if surf.indices.size:
            s[surf.indices] = surf.surfaceness / max(float(surf.surfaceness.max()), 1e-300)
        kept = keep if axis == 0 else kept & keep
        sal = np.minimum(sal, s)
    idx = np.flatnonzero(kept)
    info["voting_tokens_kept"] = int(idx.size)
    if idx.size < 4:
        info["voting_reason"] = "tensor voting kept fewer than 4 tokens"
        return empty
    # local eq. 41 against the closest kept tokens that use neither ray (Fig. 14)
    pairs = cand[idx]
    joint = np.column_stack([uv[idx], stretch * duv[idx]])
    m = idx.size
    _, nb = cKDTree(joint).query(joint, k=min(4 * EQ41_NEIGHBOURS + 1, m))
    nb = nb.reshape(m, -1)[:, 1:]
    active = (pairs[nb, 0] != pairs[:, None, 0]) & (pairs[nb, 1] != pairs[:, None, 1])
    # the first EQ41_NEIGHBOURS active neighbours of each token
    rank = np.cumsum(active, axis=1)
    use = active & (rank <= EQ41_NEIGHBOURS)
    a, q = np.nonzero(use)
    b = nb[a, q]
    xi, xj = x[pairs[a, 0]], x[pairs[b, 0]]
    yi, yj = r2[pairs[a, 1]], r2[pairs[b, 1]]
    res = eq41_length_residual(yi - xi, yi + xi, yj - xj, yj + xj)
    sig = np.sqrt(s1[pairs[a, 0]] ** 2 + s2[pairs[a, 1]] ** 2 + s1[pairs[b, 0]] ** 2 + s2[pairs[b, 1]] ** 2)
    tol = STRAIN * np.linalg.norm(xi - xj, axis=1) + GATE_SIGMAS * sig
    passes = np.bincount(a, weights=(res <= tol).astype(float), minlength=m)
    checked = np.bincount(a, minlength=m)
    # a token is verified when most of its closest neighbours agree with it
    ok = (checked > 0) & (passes > 0.5 * checked)
    info["voting_eq41_passed"] = int(ok.sum())
    ver = np.flatnonzero(ok)
    if ver.size < 4:
        info["voting_reason"] = "fewer than 4 tokens pass the local eq. 41"
        return empty
    sel = pairs[ver[one_to_one(pairs[ver], -(passes[ver] / np.maximum(checked[ver], 1)) - 1e-3 * sal[idx[ver]])]]
    info["voting_support"] = int(sel.shape[0])
    if sel.shape[0] < chance:
        info["voting_reason"] = f"{sel.shape[0]} pairs, below the chance level {chance}"
        return empty
    return sel[np.argsort(sel[:, 0], kind="stable")]
