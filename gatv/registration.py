"""Rigid registration without initialization (paper sections 2.1–3.4, Algorithm 1).

:func:`register` finds the rigid motion between two point sets with an
unknown motion of any size and many outliers in both sets, and a
one-to-one set of correspondences, with no initial guess.

How it works
------------
1. **Trial rotations** (replacing Algorithm 1's exhaustive grid, see
   :mod:`gatv.congruent`): source triples are matched to congruent target
   triples; each match gives a trial motion, scored by a cheap density
   test.  A trial built from true matches leaves a residual rotation near
   zero.
2. **Tensor voting judges the best trials.** The source is rotated by the
   trial rotation and the ``{dx, dy, dz}`` joint space (eq. 30) is populated
   with the candidate pairs inside the voting reach of the trial's
   translation.  A sparse ball pass (section 3.3) makes the true pairs
   stand out as the dense pure-translation cluster of section 3.4; where
   the residual rotation is not negligible they form a plane patch whose
   normal (the ball pass's ``e1``) is the rotation axis.
3. **Eq. 41** against the most salient tokens (``V × (A × Vs) = 0``,
   relaxed to the noise level; without a reliable axis, its
   length-preservation half ``V · Vs = 0``) drops false and multiple
   matches.  A least-squares fit (Kabsch/Horn) on the consistent pairs,
   a residual gate and a greedy one-to-one selection give the
   correspondences; a plane with less support than a random motion would
   collect is rejected.
4. Optional ICP polish on the found motion.

With ``max_angle`` (and optionally ``max_translation``) the trial search is
skipped: only the candidate pairs the bounds allow are voted on, with the
ball pass and stick passes of section 3.3 extracting the plane — the
paper's "optimised version" for small motions.

Noise: with ``noise=None`` a schedule of tolerances is tried, from
exact (relative 1e-6 of the point spacing) up to 5% of the spacing, in
round robin (a chunk of triples at each in turn); the first tolerance at
which a motion beats the chance level wins, and the tolerance then grows
while the support does.  Give ``noise`` (standard deviation of the point
noise, data units) for noisier data, or use :func:`gatv.register_scans`
for real scans.
"""

from __future__ import annotations

import copy
import time

import numpy as np
from scipy.spatial import cKDTree

from ._validation import as_points, check_positive
from .candidates import bounded_pairs, median_spacing, one_to_one
from .congruent import TargetIndex, chance_support, n_triples_needed, trial_motions
from .errors import InputError
from .ga import eq41_residual
from .motion import RigidMotion, fit_rigid

__all__ = ["register"]

#: Tolerances tried when ``noise`` is not given, relative to the spacing.
NOISE_SCHEDULE = (1e-6, 1e-3, 1e-2, 0.05)


def _check_not_degenerate(points: np.ndarray, name: str) -> None:
    c = points - points.mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False)
    if s[0] <= 1e-12 * max(1.0, float(np.abs(points).max())):
        raise InputError(f"All points of `{name}` are identical; a rigid motion needs 3 non-collinear points.")
    if s[1] <= 1e-9 * s[0]:
        raise InputError(f"All points of `{name}` are collinear; a rigid motion needs 3 non-collinear points.")


def _gate(tol: float) -> float:
    """Residual radius for a pair under the true motion, for noise std ``tol``.

    The residual ``x' - (R x + t)`` carries the noise of both points, a 3D
    Gaussian of per-axis std ``sqrt(2) tol``; its norm stays below
    ``3.5 tol`` for about 99% of pairs.
    """
    return 3.5 * tol


class _Problem:
    """Validated inputs and scale facts shared by the stages."""

    def __init__(self, source, target):
        self.X = as_points(source, "source", min_points=3)
        self.Y = as_points(target, "target", min_points=3)
        _check_not_degenerate(self.X, "source")
        _check_not_degenerate(self.Y, "target")
        self.tree = cKDTree(self.Y)
        self.spacing = 0.5 * (median_spacing(self.X) + median_spacing(self.Y))
        lo, hi = self.Y.min(axis=0), self.Y.max(axis=0)
        self.extent = float(np.abs(self.X - self.X.mean(axis=0)).max())
        self.volume = float(np.prod(np.maximum(hi - lo, self.spacing)))

    def chance(self, gate: float, n_tests: float = 1.0) -> int:
        return chance_support(self.X.shape[0], self.Y.shape[0], self.volume, gate, n_tests=n_tests)


# ---------------------------------------------------------------- stages
def _fit_and_gate(P: _Problem, pairs: np.ndarray, seed_pairs: np.ndarray, gate: float):
    """Fit on ``seed_pairs``, keep ``pairs`` within ``gate``, one-to-one, refit."""
    if seed_pairs.shape[0] < 3:
        return None
    R, t = fit_rigid(P.X[seed_pairs[:, 0]], P.Y[seed_pairs[:, 1]])
    for _ in range(3):
        res = np.linalg.norm(P.Y[pairs[:, 1]] - (P.X[pairs[:, 0]] @ R.T + t), axis=1)
        ok = np.flatnonzero(res <= gate)
        if ok.size < 3:
            return None
        keep = ok[one_to_one(pairs[ok], res[ok])]
        kept = pairs[keep]
        R_new, t_new = fit_rigid(P.X[kept[:, 0]], P.Y[kept[:, 1]])
        moved = np.abs(R_new - R).max() + np.abs(t_new - t).max()
        R, t = R_new, t_new
        if moved < 1e-12:
            break
    return R, t, kept


def _plane_normal(points: np.ndarray, tau: float) -> np.ndarray:
    """Unit normal of the least-squares plane through ``points``, trimmed once at ``tau``."""
    c = points - points.mean(axis=0)
    n = np.linalg.svd(c, full_matrices=False)[2][-1]
    near = np.abs(c @ n) <= tau
    if 3 <= near.sum() < len(points):
        c = points[near] - points[near].mean(axis=0)
        n = np.linalg.svd(c, full_matrices=False)[2][-1]
    return n


def _eq41_consistent(d: np.ndarray, s: np.ndarray, pairs: np.ndarray, ref: int,
                     tau: float) -> np.ndarray:
    """Indices of tokens consistent with the reference token by eq. 41.

    ``d``, ``s`` are the difference and sum vectors of the candidate
    ``pairs``.  First the length-preservation half of eq. 41,
    ``V · Vs = |Δx'|² - |Δx|² = 0``, which needs no axis; the rotation axis
    ``A`` is then the normal of the eq.-30 plane through the tokens kept,
    and the full constraint ``|V × (A × Vs)| / |Vs| <= tau`` (relaxed to the
    noise level, section 4.1) decides.  A token that reuses the
    reference's source or target point (the double match of Fig. 2 c/f)
    is dropped.
    """
    V = d - d[ref]
    Vs = s - s[ref]
    nvs = np.linalg.norm(Vs, axis=1)
    r = np.abs(np.einsum("ij,ij->i", V, Vs)) / np.where(nvs > 0, nvs, 1.0)
    same = (pairs[:, 0] == pairs[ref, 0]) ^ (pairs[:, 1] == pairs[ref, 1])
    cons = np.union1d(np.flatnonzero((r <= tau) & ~same), [ref])
    if cons.size < 4:
        return cons
    axis = _plane_normal(d[cons], tau)
    r = eq41_residual(d[cons], s[cons], d[ref], s[ref], axis, normalize="length")
    return np.union1d(cons[r <= tau], [ref])


def _best_reference(P, pairs, Xr, saliency, tol, n_refs=4):
    """Verify with eq. 41 against the most salient tokens; fit the best set.

    The paper tests the plane's most salient token against the rest
    (section 3.4); the next few are tried as well, which guards against a
    salient false token, and the reference with the largest eq.-41
    consistent set is fitted.
    """
    gate = _gate(tol)
    tau = 2.0 * gate
    xi = Xr[pairs[:, 0]]
    yj = P.Y[pairs[:, 1]]
    d, s = yj - xi, yj + xi
    best = None
    for ref in np.argsort(-saliency, kind="stable")[:n_refs]:
        if saliency[ref] <= 0:
            break
        cons = _eq41_consistent(d, s, pairs, ref, tau)
        if cons.size >= 3 and (best is None or cons.size > best.size):
            best = cons
    if best is None:
        return None
    # one-to-one by saliency before fitting
    sub = best[one_to_one(pairs[best], -saliency[best])]
    return _fit_and_gate(P, pairs, pairs[sub], gate)


def _vote_judge(P: _Problem, R0: np.ndarray, t0: np.ndarray, tol: float, sigma, max_candidates: int):
    """Tensor voting on the joint space of the trial-rotated source (section 3.4)."""
    from .voting import vote

    n1, n2 = P.X.shape[0], P.Y.shape[0]
    gate = _gate(tol)
    # Spacing of false tokens near t0 in the joint space: each source point
    # contributes the target's density there.
    false_spacing = (n1 * n2 / P.volume) ** (-1.0 / 3.0)
    sig = float(sigma) if sigma is not None else max(gate, 0.5 * min(false_spacing, P.spacing))
    Xr = P.X @ R0.T
    # Tokens within the voting reach (2σ) of the trial translation; at most
    # `max_candidates` per source point (the nearest), which bounds the
    # work on dense real scans where every point has many near targets.
    dist, j = P.tree.query(Xr + t0, k=max_candidates, distance_upper_bound=2.0 * sig)
    dist, j = dist.reshape(len(Xr), -1), j.reshape(len(Xr), -1)
    ii, kk = np.nonzero(np.isfinite(dist))
    pairs = np.stack([ii, j[ii, kk]], axis=1)
    if pairs.shape[0] < 3:
        return None
    tokens = P.Y[pairs[:, 1]] - Xr[pairs[:, 0]]
    ball = vote(tokens, sig)
    # The pure-translation cluster: large absolute saliency after the ball pass.
    saliency = ball.eigenvalues.sum(axis=1)
    best = _best_reference(P, pairs, Xr, saliency, tol)
    if best is None:
        return None
    return best + (int(pairs.shape[0]), sig)


def _refine(P: _Problem, R, t, gate, iterations=10):
    """ICP polish: nearest target within ``gate``, one-to-one, refit.

    Stops when the correspondences repeat or the motion moves by less than
    1e-9 of the point spacing.
    """
    kept = None
    for _ in range(iterations):
        moved = P.X @ R.T + t
        dist, j = P.tree.query(moved, k=1, distance_upper_bound=gate)
        ok = np.flatnonzero(np.isfinite(dist))
        if ok.size < 3:
            break
        pairs = np.stack([ok, j[ok]], axis=1)
        keep = one_to_one(pairs, dist[ok])
        new = pairs[keep]
        R_new, t_new = fit_rigid(P.X[new[:, 0]], P.Y[new[:, 1]])
        same = kept is not None and new.shape == kept.shape and np.array_equal(new, kept)
        step = np.abs(R_new - R).max() * P.extent + np.abs(t_new - t).max()
        R, t, kept = R_new, t_new, new
        if same or step < 1e-9 * P.spacing:
            break
    return R, t, kept


def _grow_tolerance(P: _Problem, R, t, kept, levels, level):
    """Move up the tolerance schedule while the support grows beyond chance.

    A motion accepted at a tolerance below the data's noise explains only
    the luckiest pairs; re-gating it at the next tolerance brings in the
    rest.  Stop when the gain is no larger than what the wider gate would
    collect from random points (Poisson, level 1e-3).
    """
    from scipy.stats import poisson

    while level + 1 < len(levels):
        gate = _gate(levels[level + 1])
        R2, t2, kept2 = _refine(P, R, t, gate)
        if kept2 is None:
            break
        p = min(1.0, P.Y.shape[0] * 4.0 / 3.0 * np.pi * gate**3 / P.volume)
        lam = P.X.shape[0] * p
        if kept2.shape[0] - kept.shape[0] <= max(2.0, poisson.isf(1e-3, lam)):
            break
        R, t, kept, level = R2, t2, kept2, level + 1
    return R, t, kept, level


def _result(X, Y, R, t, pairs, info, score=None) -> RigidMotion:
    """The :class:`RigidMotion` for correspondences ``pairs`` between ``X`` and ``Y``."""
    order = np.argsort(pairs[:, 0], kind="stable")
    pairs = pairs[order]
    res = Y[pairs[:, 1]] - (X[pairs[:, 0]] @ R.T + t)
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1)))) if pairs.size else float("nan")
    return RigidMotion(rotation=R, translation=t, correspondences=pairs,
                       score=float(pairs.shape[0] if score is None else score), rms=rms, info=info)


def _failure(reason: str, info: dict) -> RigidMotion:
    info = dict(info, reason=reason)
    return RigidMotion(np.eye(3), np.zeros(3), np.empty((0, 2), np.int64), 0.0, float("nan"), info)


def _bounded(P, max_angle, max_translation, levels, sigma, refine, memory_budget, info):
    """Small-motion mode: vote on the bounded candidate pairs, no search."""
    from .voting import default_sigma, extract_surfaces

    pairs = bounded_pairs(P.X, P.Y, max_angle, max_translation, memory_budget=memory_budget)
    info["n_tokens"] = int(pairs.shape[0])
    if pairs.shape[0] < 3:
        return None
    tokens = P.Y[pairs[:, 1]] - P.X[pairs[:, 0]]
    if sigma is None:
        # ~40 tokens within the voting radius of a typical token, estimated
        # from 500 of them (the full estimate costs more than the voting).
        sigma = default_sigma(tokens, sample=500)
    # The paper's optimised version: one ball pass and one stick pass.
    surf = extract_surfaces(tokens, sigma, n_stick_passes=1)
    idx = np.asarray(surf.indices)
    if idx.size < 3:
        return None
    saliency = np.zeros(pairs.shape[0])
    saliency[idx] = surf.surfaceness
    for tol in levels:
        gate = _gate(tol)
        best = _best_reference(P, pairs, P.X, saliency, tol)
        if best is None:
            continue
        R, t, kept = best
        if kept.shape[0] >= P.chance(gate):
            if refine:
                R, t, kept = _refine(P, R, t, gate)
            if len(levels) > 1:
                R, t, kept, grown = _grow_tolerance(P, R, t, kept, levels, levels.index(tol))
                tol = levels[grown]
            info.update(tolerance=tol, sigma=float(surf.sigma))
            return _result(P.X, P.Y, R, t, kept, info, score=float(np.mean(surf.surfaceness)))
    return None


def register(
    source,
    target,
    *,
    seed: int = 0,
    max_angle: float | None = None,
    max_translation: float | None = None,
    noise: float | None = None,
    refine: bool = True,
    min_inlier_share: float = 0.04,
    confidence: float = 0.999,
    max_triples: int | None = None,
    sigma: float | None = None,
    n_judged: int = 4,
    max_candidates: int = 8,
    memory_budget: float | None = None,
    progress=None,
) -> RigidMotion:
    """Register ``source`` onto ``target`` with no initial guess.

    Parameters
    ----------
    source, target : (N, 3) array_like or object with ``.points``
        The two point sets; any share of either may be outliers.
    seed : int, default: 0
        Seed of the random source-triple sampling; same seed, same result.
    max_angle : float, optional
        Bound on the rotation angle in **degrees**. Enables the small-motion
        mode (no trial search; only candidate pairs the bounds allow).
    max_translation : float, optional
        Bound on ``|t|`` (data units) in the small-motion mode.
    noise : float, optional
        Standard deviation of the point noise (data units). Default: a
        schedule from exact to a fifth of the point spacing.
    refine : bool, default: True
        Polish the motion with one-to-one ICP iterations inside the
        noise gate.
    min_inlier_share : float, default: 0.04
        Smallest share of source points expected to have a true match;
        sets how many source triples are drawn (with ``confidence``).
    confidence : float, default: 0.999
        Probability of drawing one all-inlier triple when the inlier share
        is ``min_inlier_share``.
    max_triples : int, optional
        Hard cap on the source triples drawn per tolerance level.
    sigma : float, optional
        Tensor-voting scale (data units). Default from the data: half the
        spacing of false tokens near the trial translation, and at least
        twice the noise gate.
    n_judged : int, default: 4
        Best trial motions handed to tensor voting.
    max_candidates : int, default: 8
        Cap on the candidate pairs per source point in the joint space
        voted on (the nearest targets to the trial position); bounds the
        work on dense real scans.
    memory_budget : float, optional
        Bytes; inputs needing more fail at once (see
        :func:`gatv._validation.check_memory`).
    progress : callable, optional
        ``progress(fraction, message)`` called as work proceeds.

    Returns
    -------
    RigidMotion
        ``target ≈ source @ rotation.T + translation`` with one-to-one
        ``correspondences``. Falsy, with ``info["reason"]``, when no motion
        beats the chance level.

    Raises
    ------
    ValueError
        Fewer than 3 points, NaN/inf, wrong shapes, identical or collinear
        points, bad options, or a token count over the memory budget.

    Examples
    --------
    >>> import numpy as np
    >>> from gatv import Rotor, register
    >>> rng = np.random.default_rng(0)
    >>> x = rng.uniform(-5, 5, (40, 3))
    >>> R = Rotor.from_axis_angle([1, 1, 0], np.radians(150))
    >>> y = (R >> x) + [3.0, -2.0, 1.0]
    >>> m = register(x, rng.permutation(y))
    >>> m.support, round(m.angle_deg, 6)
    (40, 150.0)
    """
    t_start = time.perf_counter()
    P = _Problem(source, target)
    noise = check_positive(noise, "noise", allow_none=True)
    if not (0.0 < float(min_inlier_share) <= 1.0):
        raise InputError(f"Expected `min_inlier_share` in (0, 1], got {min_inlier_share!r}.")
    if not (0.0 < float(confidence) < 1.0):
        raise InputError(f"Expected `confidence` in (0, 1), got {confidence!r}.")
    if sigma is not None:
        sigma = check_positive(sigma, "sigma")
    if int(max_candidates) < 1:
        raise InputError(f"Expected `max_candidates` >= 1, got {max_candidates!r}.")
    max_candidates = int(max_candidates)
    levels = [noise] if noise is not None else [r * P.spacing for r in NOISE_SCHEDULE]
    report = progress if progress is not None else (lambda f, m: None)
    info: dict = {"n_source": int(P.X.shape[0]), "n_target": int(P.Y.shape[0]), "spacing": P.spacing}

    if max_angle is not None:
        ang = check_positive(max_angle, "max_angle")
        if ang > 180.0:
            raise InputError(f"Expected `max_angle` in degrees, at most 180, got {ang!r}.")
        mt = check_positive(max_translation, "max_translation", allow_none=True)
        info["mode"] = "bounded"
        out = _bounded(P, np.radians(ang), mt, levels, sigma, refine, memory_budget, info)
        info["time_s"] = time.perf_counter() - t_start
        return out if out is not None else _failure("no plane with support above chance", info)
    if max_translation is not None:
        raise InputError("`max_translation` needs `max_angle` (the small-motion mode).")

    info["mode"] = "congruent-triples"
    rng = np.random.default_rng(seed)
    n = P.X.shape[0]
    need = n_triples_needed(max(float(min_inlier_share), 3.0 / n), confidence)
    n_possible = n * (n - 1) * (n - 2) // 6
    budget = int(min(need, 3 * n_possible if n_possible < 10**6 else need))
    if max_triples is not None:
        budget = min(budget, int(max_triples))
    # One index of the target's pair lengths; one scoring grid per tolerance.
    base = TargetIndex(P.Y, _gate(levels[0]), memory_budget=memory_budget)
    indexes = []
    for tol in levels:
        idx = copy.copy(base)
        idx.set_radius(_gate(tol))
        indexes.append(idx)
    max_matches = 64
    accept = [chance_support(n, P.Y.shape[0], idx.volume, idx.radius, n_tests=budget * max_matches)
              for idx in indexes]
    tried = [{"tolerance": tol, "triples": 0, "congruent": 0, "best_support": 0, "threshold": a}
             for tol, a in zip(levels, accept)]
    # Round robin over the tolerances with an equal share of work each: a
    # motion that shows at a coarse tolerance is not kept waiting for the
    # whole budget of the finer, fruitless ones, and a coarse tolerance
    # (many congruent but wrong triangles, each scored on every point) does
    # not slow down an exact one.  Work is counted deterministically, in
    # microsecond-like units: 1 per triple drawn plus (2 + 0.03 n) per
    # congruent triangle scored, so the same seed gives the same result.
    share = 20000.0
    done = [0] * len(levels)
    per_triple = [share / 64.0] * len(levels)  # first chunk: 64 triples, then measured
    while min(done) < budget:
        for level, tol in enumerate(levels):
            if done[level] >= budget:
                continue
            m = int(min(budget - done[level], max(16, min(4096, share / per_triple[level]))))
            done[level] += m
            report(sum(done) / (budget * len(levels)),
                   f"tolerance {tol:.3g}: {tried[level]['triples']} triples")
            gate = _gate(tol)
            eps = 2.0 * gate  # side-length tolerance: two points' noise per side
            trials = trial_motions(P.X, indexes[level], eps=eps, max_triples=m, rng=rng,
                                   keep=n_judged, max_matches=max_matches, accept=accept[level])
            rec = tried[level]
            rec["triples"] += trials.n_triples
            rec["congruent"] += trials.n_congruent
            per_triple[level] = 1.0 + (2.0 + 0.03 * n) * rec["congruent"] / max(rec["triples"], 1)
            if len(trials):
                rec["best_support"] = max(rec["best_support"], int(trials.support[0]))
            if not len(trials) or trials.support[0] < accept[level]:
                continue
            threshold = P.chance(gate)
            for k in range(len(trials)):
                if trials.support[k] < accept[level]:
                    break
                judged = _vote_judge(P, trials.rotations[k], trials.translations[k], tol, sigma,
                                     max_candidates)
                if judged is None:
                    continue
                R, t, kept, n_tokens, sig = judged
                if kept.shape[0] < threshold:
                    continue
                if refine:
                    R, t, kept = _refine(P, R, t, gate)
                if noise is None:
                    R, t, kept, grown = _grow_tolerance(P, R, t, kept, levels, level)
                    tol = levels[grown]
                info.update(tolerance=tol, sigma=sig, n_tokens=n_tokens, trials=tried,
                            trial_support=int(trials.support[k]), chance_support=threshold,
                            time_s=time.perf_counter() - t_start)
                report(1.0, f"found {kept.shape[0]} correspondences")
                return _result(P.X, P.Y, R, t, kept, info)
    info.update(trials=tried, time_s=time.perf_counter() - t_start)
    return _failure("no trial motion beat the chance level", info)
