"""The paper's data flow as named stages (Algorithm 1, sections 2–5).

trial motions → tokens → tensor votes → constraint → one-to-one selection
→ fit and refine → result.

Each stage is a function over small frozen values; whatever depends on the
kind of motion is asked of the :class:`~gatv.models.MotionModel` the
:class:`Problem` carries, so the same stages serve rigid motions, similarities
and 2D affine maps.  :func:`gatv.register` (both its pipelines) and
:func:`gatv.motions.segment` are short sequences of these stages.

Motions travel between stages as homogeneous matrices ``T``
(``target ≈ source @ T[:d, :d].T + T[:d, d]``).
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, replace
from math import comb, erf

import numpy as np
from numba.core import event as numba_event
from scipy.optimize import brentq
from scipy.spatial import cKDTree
from scipy.stats import chi

from .candidates import median_spacing, one_to_one, one_to_one_rows
from .models import Motion, MotionModel, apply_matrix, get_model, split_matrix
from .models.base import MAX_MATCHES, NOISE_SCHEDULE, NOISY_SCHEDULE, homogeneous
from .stats import ALPHA, ball_measure, chance_count, likelihood_level, pair_scores, peak_ratios, samples_needed
from .verdict import Verdict, chance_verdict
from .voting import vote

__all__ = [
    "DENSITY_NEIGHBOURS",
    "JUDGED_WRONG",
    "NOISE_SCHEDULE",
    "NOISY_SCHEDULE",
    "Fit",
    "Found",
    "Judged",
    "LevelCount",
    "Problem",
    "Tokens",
    "Votes",
    "beats_chance_at_some_level",
    "candidate_tokens",
    "chunk_work",
    "closest_count",
    "constraint",
    "density_tests",
    "failure",
    "fit_and_gate",
    "found_verdict",
    "gate",
    "grow_tolerance",
    "joint_spaces",
    "judge",
    "judged_alike",
    "landing_level",
    "level_alphas",
    "level_counts",
    "likelihood_counts",
    "likelihood_passes",
    "likelihood_pose",
    "listed_share",
    "make_result",
    "motion_result",
    "nearest_pairs",
    "noise_from_residuals",
    "passing_level",
    "polish_trials",
    "polished_motions",
    "prepare",
    "refine",
    "regate",
    "search",
    "sample_points",
    "sample_space",
    "search_failure",
    "search_verdict",
    "select_one_to_one",
    "settle_noise",
    "tolerance_levels",
    "vote_tokens",
    "weighted_pose",
]

#: Target points counted around a moved source point to measure the
#: target's local density there (:meth:`Problem.landing_radii`): the
#: estimate's relative error is about ``1 / sqrt(k)``.
DENSITY_NEIGHBOURS = 16

#: Tolerances tried when the noise is not given, relative to the spacing
#: (:data:`gatv.models.base.NOISE_SCHEDULE`); :data:`NOISY_SCHEDULE`
#: continues it to the noise of real sensors (the rigid model's policy).


def tolerance_levels(problem: Problem, noise: float | None, schedule=NOISE_SCHEDULE) -> list[float]:
    """The tolerances a search tries: ``[noise]`` when given, else ``schedule`` × spacing."""
    if noise is not None:
        return [noise]
    return [r * problem.spacing for r in schedule]


def sample_space(model: MotionModel, n: int) -> int:
    """Distinct trial samples among ``n`` points: the model's ``sample_space(n)`` or C(n, sample_size)."""
    f = getattr(model, "sample_space", None)
    return int(f(n)) if f is not None else comb(n, model.sample_size)


def sample_points(model: MotionModel) -> int:
    """Points a trial sample of ``model`` draws: its ``trial_sample_size``, else ``sample_size``."""
    return int(getattr(model, "trial_sample_size", model.sample_size))


def gate(tolerance: float) -> float:
    """Residual radius of a true pair for point noise of standard deviation ``tolerance``.

    The residual ``x' - T(x)`` carries the noise of both points, a Gaussian
    of per-axis standard deviation ``sqrt(2) tolerance``; in 3D its norm
    stays below ``3.5 tolerance`` (2.47 of those standard deviations) for
    about 89% of the pairs, in 2D for about 95%.
    """
    return 3.5 * tolerance


# ------------------------------------------------------------------ problem
@dataclass(frozen=True, eq=False)
class Problem:
    """Validated inputs and the scale facts every stage shares.

    Attributes
    ----------
    source, target : (N, d), (M, d) ndarray
    model : MotionModel
    tree : scipy.spatial.cKDTree
        Of the target points.
    spacing : float
        Mean of the two sets' median nearest-neighbour distances (the
        target's alone for a model that changes scale: residuals are in
        target units).
    extent : float
        Largest coordinate offset of a source point from the source centroid.
    volume : float
        Measure of the target's bounding box (each side at least ``spacing``):
        the region random motions scatter points over (:meth:`chance`).
        A given motion's chance level uses the target's density where it
        puts the source instead (:meth:`chance_under`).
    """

    source: np.ndarray
    target: np.ndarray
    model: MotionModel
    tree: cKDTree
    spacing: float
    extent: float
    volume: float

    @property
    def dim(self) -> int:
        return int(self.source.shape[1])

    def chance(self, gate: float, n_tests: float = 1.0) -> int:
        """Support a random motion reaches within ``gate`` (see :mod:`gatv.stats`)."""
        return self.model.chance(self.source.shape[0], self.target.shape[0], self.volume, gate,
                                 n_tests)

    def residuals(self, matrix: np.ndarray, pairs: np.ndarray) -> np.ndarray:
        """``|target[j] - T(source[i])|`` of candidate pairs ``(i, j)``."""
        return self.model.residuals(matrix, self.source[pairs[:, 0]], self.target[pairs[:, 1]])

    def landing_radii(self, matrix: np.ndarray, *, without: np.ndarray | None = None) -> np.ndarray:
        """Radius of the ball around each moved source point ``T(x)`` that holds
        :data:`DENSITY_NEIGHBOURS` target points: the target's local density
        where ``matrix`` puts the source (:meth:`landing_measure`).

        ``without``: target rows left out (a motion's own partners, for the
        density of the other points), at least one target point staying; the
        ball then holds ``min(DENSITY_NEIGHBOURS, points left)`` of them.
        """
        tree = self.tree
        if without is not None:
            others = np.ones(self.target.shape[0], bool)
            others[without] = False
            tree = cKDTree(self.target[others])
        return self.density_radii(apply_matrix(matrix, self.source), tree)

    def density_radii(self, points: np.ndarray, tree: cKDTree | None = None) -> np.ndarray:
        """Radius of the ball around each of ``points`` that holds :data:`DENSITY_NEIGHBOURS` target points
        (of ``tree``, default the whole target's; fewer where it has fewer)."""
        tree = self.tree if tree is None else tree
        k = min(DENSITY_NEIGHBOURS, tree.n)
        d, _ = tree.query(points, k=k)
        return np.maximum(d.reshape(len(points), -1)[:, -1], 1e-300)

    def landing_pairs(self, radii: np.ndarray, gate: float, n_target: int | None = None) -> float:
        """Pairs within ``gate`` a motion with :meth:`landing_radii` ``radii`` collects by chance,
        in expectation: ``min(1, k (gate / r_k)^d)`` a moved source point, summed (``k`` the
        neighbours the radii counted among ``n_target`` points, default the whole target)."""
        k = min(DENSITY_NEIGHBOURS, self.target.shape[0] if n_target is None else int(n_target))
        return float(np.minimum(1.0, k * (gate / radii) ** self.dim).sum())

    def landing_measure(self, radii: np.ndarray, gate: float, n_target: int | None = None) -> float:
        """The measure that gives :meth:`chance` the chance pairs of a motion whose
        moved source points have :meth:`landing_radii` ``radii``.

        :meth:`chance` spreads the target uniformly over its bounding box.
        Where the target is denser than that mean (the inlier cube of Table 2
        holds the inliers and its share of the outliers; a scene's objects),
        a motion that lays the source onto the dense part collects more
        chance pairs than the box predicts, and a wrong one found there by a
        search that maximises its support beats the box's level.  A moved
        point lands within ``gate`` of a target point with probability
        ``min(1, k (gate / r_k)^d)`` by the ``k``-nearest-neighbour density
        (``k`` target points in the ball of radius ``r_k``); the box measure
        with the same expected count over the source is returned.  ``n_target``:
        as in :meth:`landing_pairs` (radii counted among fewer points).
        """
        expected = self.landing_pairs(radii, gate, n_target)
        uniform = self.source.shape[0] * self.target.shape[0] * ball_measure(gate, self.dim)
        return uniform / max(expected, 1e-300)

    def chance_under(self, matrix: np.ndarray, gate: float, n_tests: float = 1.0, radii=None) -> int:
        """:meth:`chance` at the target's density where ``matrix`` puts the source.

        ``radii``: :meth:`landing_radii` of ``matrix``, when already known.
        """
        radii = self.landing_radii(matrix) if radii is None else radii
        return self.model.chance(self.source.shape[0], self.target.shape[0],
                                 self.landing_measure(radii, gate), gate, n_tests)


def prepare(source, target, model="rigid", *, validated: bool = False) -> Problem:
    """Validate the two point sets for ``model`` and measure their scale.

    ``validated``: ``source`` and ``target`` are already the arrays
    ``model.check_points`` returned (a caller that checked them to choose
    its pipeline); they are not checked again.

    Raises
    ------
    InputError
        Wrong shapes (naming the argument and the model's dimension), too few,
        identical or collinear points, NaN or inf.
    """
    model = get_model(model)
    if validated:
        X, Y = source, target
    else:
        X = model.check_points(source, "source")
        Y = model.check_points(target, "target")
    if getattr(model, "changes_scale", False):
        spacing = median_spacing(Y)  # residuals, gates and tolerances are in target units
    else:
        spacing = 0.5 * (median_spacing(X) + median_spacing(Y))
    lo, hi = Y.min(axis=0), Y.max(axis=0)
    extent = float(np.abs(X - X.mean(axis=0)).max())
    volume = float(np.prod(np.maximum(hi - lo, spacing)))
    return Problem(X, Y, model, cKDTree(Y), spacing, extent, volume)


# ------------------------------------------------------------------- tokens
@dataclass(frozen=True, eq=False)
class Tokens:
    """Candidate pairs and their joint-space coordinates (section 3.4).

    Attributes
    ----------
    pairs : (T, 2) ndarray of int
        ``(source index, target index)``.
    source_points : (T, d) ndarray
        ``source[i]`` moved by the trial motion's linear part (the trial
        rotation for rigid motions): the residual motion of true pairs is
        then near a pure translation.
    target_points : (T, d) ndarray
        ``target[j]``.
    coords : (T, 3) ndarray
        The joint-space point voted on (``{dx, dy, dz}`` of eq. 30 for rigid
        motions).
    """

    pairs: np.ndarray
    source_points: np.ndarray
    target_points: np.ndarray
    coords: np.ndarray

    def __len__(self) -> int:
        return int(self.pairs.shape[0])


def candidate_tokens(problem: Problem, matrix: np.ndarray, reach: float,
                     max_candidates: int) -> Tokens:
    """Pairs within ``reach`` of the trial motion ``matrix``, at most ``max_candidates`` a point.

    The nearest targets of each moved source point are kept, which bounds
    the work on dense real scans where every point has many near targets.
    """
    A, t = split_matrix(matrix)
    moved = problem.source @ A.T
    dist, j = problem.tree.query(moved + t, k=max_candidates, distance_upper_bound=reach)
    dist, j = dist.reshape(len(moved), -1), j.reshape(len(moved), -1)
    ii, kk = np.nonzero(np.isfinite(dist))
    pairs = np.stack([ii, j[ii, kk]], axis=1)
    xs, ys = moved[pairs[:, 0]], problem.target[pairs[:, 1]]
    return Tokens(pairs, xs, ys, problem.model.tokens(xs, ys))


# -------------------------------------------------------------------- votes
@dataclass(frozen=True, eq=False)
class Votes:
    """What the sparse ball pass (section 3.3) says of each token.

    Attributes
    ----------
    saliency : (T,) ndarray
        ``λ1 + λ2 + λ3``: large in the dense pure-translation cluster of
        section 3.4 and on the plane of a residual rotation.
    normals : (T, 3) ndarray
        ``e1``: the plane normal (the residual rotation axis) where the
        tokens form a plane.
    sigma : float
        Voting scale.
    """

    saliency: np.ndarray
    normals: np.ndarray
    sigma: float


def joint_spaces(model: MotionModel, tokens: Tokens) -> tuple[np.ndarray, ...]:
    """The joint spaces voted on: the model's ``joint_spaces`` when it has several, else ``coords``.

    Kang et al.'s 2D affine motions live in two 3D joint spaces, ``(x, y, x')``
    and ``(x, y, y')`` (paper, eqs. 1–4); rigid motions and similarities in one.
    """
    spaces = getattr(model, "joint_spaces", None)
    if spaces is None:
        return (tokens.coords,)
    return tuple(spaces(tokens.source_points, tokens.target_points))


def vote_tokens(tokens: Tokens, sigma: float, model: MotionModel | None = None) -> Votes:
    """One sparse ball pass in each joint space of ``model`` (just ``coords`` without one).

    With several spaces a token is salient when it is salient in all of
    them: its saliency is the geometric mean over the spaces; the normals
    are those of the first space.
    """
    spaces = (tokens.coords,) if model is None else joint_spaces(model, tokens)
    balls = [vote(c, sigma) for c in spaces]
    if len(balls) == 1:
        saliency = balls[0].eigenvalues.sum(axis=1)
    else:
        logs = [np.log(np.maximum(b.eigenvalues.sum(axis=1), 1e-300)) for b in balls]
        saliency = np.exp(np.mean(logs, axis=0))
    return Votes(saliency, np.asarray(balls[0].normals), float(sigma))


# --------------------------------------------------------------- constraint
def constraint(tokens: Tokens, votes: Votes, tau: float, model: MotionModel,
               n_refs: int = 4) -> np.ndarray | None:
    """Tokens consistent with the best of the most salient tokens (eq. 41).

    The paper tests the plane's most salient token against the rest
    (section 3.4); the next few are tried as well, which guards against a
    salient false token, and the reference with the largest consistent set
    wins.  ``None`` when no reference has three consistent tokens.
    """
    best = None
    for ref in np.argsort(-votes.saliency, kind="stable")[:n_refs]:
        if votes.saliency[ref] <= 0:
            break
        cons = model.consistent(tokens, int(ref), tau)
        if cons.size >= 3 and (best is None or cons.size > best.size):
            best = cons
    return best


def select_one_to_one(pairs: np.ndarray, cost: np.ndarray) -> np.ndarray:
    """Rows of ``pairs`` kept by the greedy one-to-one selection, cheapest first."""
    return one_to_one(pairs, cost)


# ---------------------------------------------------------------------- fit
@dataclass(frozen=True, eq=False)
class Fit:
    """A motion and the one-to-one correspondences it was fitted on."""

    matrix: np.ndarray
    correspondences: np.ndarray

    @property
    def support(self) -> int:
        return int(self.correspondences.shape[0])


def fit_and_gate(problem: Problem, pairs: np.ndarray, seed_pairs: np.ndarray,
                 gate: float) -> Fit | None:
    """Fit on ``seed_pairs``, keep ``pairs`` within ``gate``, one-to-one, refit (3 rounds)."""
    model = problem.model
    X, Y = problem.source, problem.target
    if seed_pairs.shape[0] < model.sample_size:
        return None
    T = model.fit(X[seed_pairs[:, 0]], Y[seed_pairs[:, 1]])
    for _ in range(3):
        res = problem.residuals(T, pairs)
        ok = np.flatnonzero(res <= gate)
        if ok.size < model.sample_size:
            return None
        keep = ok[one_to_one(pairs[ok], res[ok])]
        kept = pairs[keep]
        T_new = model.fit(X[kept[:, 0]], Y[kept[:, 1]])
        (A, t), (A_new, t_new) = split_matrix(T), split_matrix(T_new)
        moved = np.abs(A_new - A).max() + np.abs(t_new - t).max()
        T = T_new
        if moved < 1e-12:
            break
    return Fit(T, kept)


def refine(problem: Problem, fit: Fit, gate: float, iterations: int = 10) -> Fit:
    """ICP polish: nearest target within ``gate``, one-to-one, refit.

    Stops when the correspondences repeat or the motion moves by less than
    1e-9 of the point spacing.  Returns ``fit`` unchanged when fewer than
    ``sample_size`` points have a target within the gate, one-to-one.
    """
    model = problem.model
    X, Y = problem.source, problem.target
    T, kept = fit.matrix, None
    for _ in range(iterations):
        A, t = split_matrix(T)
        dist, j = problem.tree.query(X @ A.T + t, k=1, distance_upper_bound=gate)
        ok = np.flatnonzero(np.isfinite(dist))
        if ok.size < model.sample_size:
            break
        pairs = np.stack([ok, j[ok]], axis=1)
        new = pairs[one_to_one(pairs, dist[ok])]
        if new.shape[0] < model.sample_size:  # points sharing targets: too few pairs to fit
            break
        T_new = model.fit(X[new[:, 0]], Y[new[:, 1]])
        same = kept is not None and new.shape == kept.shape and np.array_equal(new, kept)
        A_new, t_new = split_matrix(T_new)
        step = np.abs(A_new - A).max() * problem.extent + np.abs(t_new - t).max()
        T, kept = T_new, new
        if same or step < 1e-9 * problem.spacing:
            break
    if kept is None:
        return fit
    return Fit(T, kept)


def grow_tolerance(problem: Problem, fit: Fit, levels, level: int) -> tuple[Fit, int]:
    """Move up the tolerance schedule while the support grows beyond chance.

    A motion accepted at a tolerance below the data's noise explains only
    the luckiest pairs; re-gating it at the next tolerance brings in the
    rest.  Stop when the gain is no larger than what the wider gate would
    collect from random points (Poisson, level 1e-3).
    """
    n1, n2 = problem.source.shape[0], problem.target.shape[0]
    while level + 1 < len(levels):
        g = gate(levels[level + 1])
        wider = refine(problem, fit, g)
        if wider is fit:
            break
        measure = problem.landing_measure(problem.landing_radii(wider.matrix), g)
        gain = chance_count(n1, n2, measure, g, dim=problem.dim, alpha=1e-3)
        if wider.support - fit.support <= max(2.0, gain):
            break
        fit, level = wider, level + 1
    return fit, level


#: Gate of the final correspondences once the noise ``σ`` is measured, in
#: units of ``σ``: the residual norm of a true pair (per-axis deviation
#: ``sqrt(2) σ``) stays below it for about 98% of pairs in 3D.
FINAL_GATE = 4.5


def noise_from_residuals(residuals: np.ndarray, gate: float, dim: int = 3, *,
                         chance_pairs: float = 0.0, n_points: int | None = None) -> float | None:
    """Point noise ``σ`` of each set, from the residuals of a motion's pairs cut at ``gate``.

    A true pair's residual ``x' - T(x)`` is an isotropic Gaussian of per-axis
    standard deviation ``s = sqrt(2) σ`` (both points noisy), so its norm
    follows a chi distribution with ``dim`` degrees of freedom scaled by
    ``s``; only residuals within ``gate`` are seen.  ``s`` solves
    ``F(m / s) / F(gate / s) = 1/2`` for the median ``m`` of the seen
    residuals (``F`` the chi CDF), which is unbiased by the cut.  ``None``
    when the median is so close to the gate (above ``0.5 ** (1/dim)`` of it)
    that the noise reaches beyond the gate: a wider gate is needed.

    ``chance_pairs``: the pairs a random motion would find within ``gate``
    had every one of the ``n_points`` source points a random partner (the
    target's density times the gate's measure, summed over the source).
    Where the target is dense such pairs are among the motion's own, with
    residuals spread uniformly over the gate's ball, and the median above
    counts them as noise (too high a noise, and a gate at that noise takes
    in more of them).  Given them, the residuals are a mixture of the
    truncated chi (``m`` true pairs, ``m F(gate / s)`` of them seen) and the
    uniform ball (``chance_pairs · (1 − m / n_points)``, the source points
    without a partner), and ``s`` and ``m`` are fitted to it by EM whose
    M-step takes the weighted median (:func:`_mixture_scale`), started from
    the median's ``s``.
    """
    r = np.asarray(residuals, dtype=np.float64)
    r = r[r <= gate]
    if r.size < 3:
        return None
    m = float(np.median(r))
    if m <= 0.0:
        return 0.0
    if m >= gate * 0.5 ** (1.0 / dim) * (1.0 - 1e-9):
        return None
    dist = chi(dim)
    s = _median_scale(m, gate, dist)
    if chance_pairs > 0.0 and n_points:
        s = _mixture_scale(r, gate, dist, s, float(chance_pairs), int(n_points))
    return float(s / np.sqrt(2.0))


def _median_scale(m: float, gate: float, dist) -> float:
    """The scale ``s`` whose chi distribution ``dist``, cut at ``gate``, has median ``m``."""
    def excess(s):
        return dist.cdf(m / s) / dist.cdf(gate / s) - 0.5

    return float(brentq(excess, m * 1e-3, m * 1e3, xtol=1e-6 * m))


def _mixture_scale(r: np.ndarray, gate: float, dist, s: float, chance_pairs: float, n_points: int,
                   rounds: int = 50) -> float:
    """EM for :func:`noise_from_residuals`' mixture of true pairs and chance pairs (residual norms ``r``).

    E-step: each residual's probability of being a true pair's.  M-step:
    the scale whose cut chi distribution has the weighted median of the
    residuals as its median (the unmixed estimate when no pair is a chance
    one), and the true pairs' number.
    """
    dim = int(dist.args[0])
    order = np.argsort(r)
    r = r[order]
    uniform = dim * r ** (dim - 1) / gate**dim  # norm density of a point uniform in the ball
    m_true = float(r.size)
    for _ in range(rounds):
        seen = float(dist.cdf(gate / s))
        true_pdf = dist.pdf(r / s) / (s * seen)
        a = m_true * seen
        b = chance_pairs * max(0.0, 1.0 - m_true / n_points)
        w = a * true_pdf / (a * true_pdf + b * uniform + 1e-300)
        cum = np.cumsum(w)
        median = float(r[min(int(np.searchsorted(cum, 0.5 * cum[-1])), r.size - 1)])
        if not 0.0 < median < gate * 0.5 ** (1.0 / dim):
            break
        s_new = _median_scale(median, gate, dist)
        m_new = min(float(w.sum()) / float(dist.cdf(gate / s_new)), float(n_points))
        done = abs(s_new - s) <= 1e-6 * s and abs(m_new - m_true) <= 1e-3
        s, m_true = s_new, m_new
        if done:
            break
    return s


def _other_radii(problem: Problem, matrix: np.ndarray, partners: np.ndarray) -> tuple[np.ndarray | None, int]:
    """:meth:`Problem.landing_radii` of ``matrix`` among the target points other than ``partners`` (rows,
    repeats allowed), and how many such points there are (radii ``None`` when there are none)."""
    n_others = problem.target.shape[0] - np.unique(partners).size
    if n_others == 0:
        return None, 0
    return problem.landing_radii(matrix, without=partners), n_others


def _chance_pairs(problem: Problem, fit: Fit, gate_radius: float) -> float:
    """Pairs within ``gate_radius`` that ``fit``'s motion would find had every source point a random
    partner: the density of the target points other than its partners, where it lands."""
    radii, n_others = _other_radii(problem, fit.matrix, fit.correspondences[:, 1])
    return 0.0 if n_others == 0 else problem.landing_pairs(radii, gate_radius, n_others)


def settle_noise(problem: Problem, fit: Fit, levels, level: int, *, floor: float = 0.0,
                 rounds: int = 8, remeasure: bool = False) -> tuple[Fit, float]:
    """Measure the point noise on a found motion and re-gate it there.

    A motion accepted at ``levels[level]`` may have been found below the
    data's noise, on its luckiest pairs, whose residuals say little about
    the noise; the tolerance first grows up the schedule while the support
    grows beyond chance (:func:`grow_tolerance`).  Then
    :func:`noise_from_residuals` on the correspondences (given the chance
    pairs the gate holds at the density of the target's other points where
    the motion lands) and the gate of the estimate alternate until the
    estimate moves by less than 5%: a wider gate refits the pose
    (:func:`refine`), a narrower one keeps it (:func:`regate`), since a
    refit on the pairs the narrower gate keeps fits their noise, and the
    estimates would shrink round after round.  When the residuals
    fill the gate (the noise reaches beyond it) the gate grows by 1.5 while
    the support grows beyond what the wider gate would collect from random
    points.  Returns the re-gated fit and the noise estimate (at least
    ``floor``).  The pose is then :func:`weighted_pose`'s at the estimate,
    or with ``remeasure`` :func:`likelihood_pose`'s (at the noise measured
    again on that pose); the estimate returned is the one settled here.
    """
    n1, n2 = problem.source.shape[0], problem.target.shape[0]
    fit, level = grow_tolerance(problem, fit, levels, level)
    sigma = float(levels[level])
    for _ in range(rounds):
        g = gate(sigma)
        res = problem.residuals(fit.matrix, fit.correspondences)
        est = noise_from_residuals(res, g, problem.dim, chance_pairs=_chance_pairs(problem, fit, g),
                                   n_points=n1)
        if est is None:
            wider = refine(problem, fit, gate(1.5 * sigma))
            gain = chance_count(n1, n2, problem.volume, gate(1.5 * sigma), dim=problem.dim, alpha=1e-3)
            if wider is fit or wider.support - fit.support <= max(2.0, gain):
                break
            fit, sigma = wider, 1.5 * sigma
            continue
        est = max(est, floor)
        if abs(est - sigma) <= 0.05 * sigma:
            sigma = est
            break
        # A narrower gate keeps the pose: a refit on the pairs it keeps would fit
        # their noise, and the next estimate would shrink with it.
        moved = refine(problem, fit, gate(est)) if est > sigma else regate(problem, fit, gate(est))
        if moved is fit or moved.support < problem.model.sample_size:
            break
        fit, sigma = moved, est
    sigma = max(sigma, floor)
    fit = likelihood_pose(problem, fit, sigma)[0] if remeasure else weighted_pose(problem, fit, sigma)
    # Final correspondences within the wider gate that holds ~98% of true
    # pairs (3D), when it brings in more than random points would; the pose
    # stays the one weighted by the noise.
    g = FINAL_GATE * sigma
    wider = regate(problem, fit, g)
    gain = chance_count(n1, n2, problem.volume, g, dim=problem.dim, alpha=1e-3)
    if wider.support - fit.support > max(1.0, gain):
        fit = wider
    return fit, sigma


def likelihood_pose(problem: Problem, fit: Fit, sigma: float, rounds: int = 8) -> tuple[Fit, float]:
    """:func:`weighted_pose` at the noise measured on its own pose: ``(fit, σ)``.

    The estimate ``sigma`` was measured on a pose refitted to the pairs of
    a narrower gate, whose residuals that refit shrinks, so it is low where
    the noise is large against the spacing; the likelihood's pose at too
    small a noise weighs the nearest targets too much.  Here the noise is
    measured again (:func:`noise_from_residuals`, with the chance pairs) on
    the weighted pose's pairs within the final gate (:data:`FINAL_GATE` σ),
    to which that pose was not refitted; while that estimate is more than 5%
    larger, the weighted pose is taken again from ``fit`` at it.  A smaller
    estimate leaves ``sigma`` (a narrower gate's pairs would fit their own
    noise, as in :func:`settle_noise`).  The correspondences stay ``fit``'s.
    """
    pose = weighted_pose(problem, fit, sigma)
    for _ in range(rounds):
        g = FINAL_GATE * sigma
        wide = regate(problem, pose, g)
        if wide.support < 2 * problem.model.sample_size:
            break
        est = noise_from_residuals(problem.residuals(wide.matrix, wide.correspondences), g, problem.dim,
                                   chance_pairs=_chance_pairs(problem, wide, g), n_points=problem.source.shape[0])
        if est is None or est <= 1.05 * sigma:
            break
        sigma = est
        pose = weighted_pose(problem, fit, sigma)
    return pose, sigma


def nearest_pairs(moved: np.ndarray, tree: cKDTree, gate_radius: float,
                  keep: np.ndarray | None = None, *, by_row: bool = False) -> np.ndarray:
    """One-to-one ``(row of moved, point of tree)`` pairs: each moved point's nearest within ``gate_radius``,
    cheapest first; ``keep``: a boolean mask of the tree's points, the nearest among those it marks (a
    :class:`~gatv._icp_kernels.KDTree` alone).  ``by_row``: the same pairs in the moved rows' order, without
    the sort by distance (:func:`~gatv.candidates.one_to_one_rows`; for a caller that orders them itself)."""
    options = {} if keep is None else {"keep": keep}
    dist, j = tree.query(moved, k=1, distance_upper_bound=gate_radius, **options)
    ok = np.flatnonzero(np.isfinite(dist))
    pairs = np.stack([ok, j[ok]], axis=1)
    if by_row:
        return pairs[one_to_one_rows(j[ok], dist[ok])]
    return pairs[one_to_one(pairs, dist[ok])]


def regate(problem: Problem, fit: Fit, gate_radius: float) -> Fit:
    """The one-to-one nearest pairs within ``gate_radius`` of ``fit``'s motion, which stays as it is."""
    A, t = split_matrix(fit.matrix)
    return Fit(fit.matrix, nearest_pairs(problem.source @ A.T + t, problem.tree, gate_radius))


def weighted_pose(problem: Problem, fit: Fit, sigma: float, rounds: int = 8) -> Fit:
    """Refit the motion by soft correspondences at the noise ``σ`` (an EM step per round).

    Under noise comparable to the point spacing, a point's nearest target is
    often a neighbour of its true partner, and a fit on the one-to-one
    nearest pairs is biased by them.  Here each moved source point spreads
    its weight over every target within the gate, in proportion to
    ``exp(-r² / (4 σ²))`` (the Gaussian likelihood of the residual ``r``,
    per-axis variance ``2 σ²``), against an outlier term equal to what the
    target's mean density would give (``n_target / volume · (4 π σ²)^{3/2}``);
    the motion is the weighted least-squares fit over all those pairs, as in
    the rigid EM of Coherent Point Drift restricted to the gate, its scale
    annealed from ``2 σ`` down to ``σ``.  The gate is :data:`FINAL_GATE`
    times the scale, which holds ~98% of true pairs: a tighter one (the
    search's 89% :func:`gate`) drops a true pair with a large residual,
    which pulls the next fit away from it and drops more (the estimate
    drifts).  The correspondences stay those of ``fit``.
    """
    if sigma <= 0 or fit.support < 2 * problem.model.sample_size:
        return fit
    model, X, Y = problem.model, problem.source, problem.target
    d = problem.dim
    T = fit.matrix
    # Annealed from twice the noise: a start a few degrees off converges.
    for scale in np.geomspace(2.0, 1.0, rounds):
        s2 = (scale * sigma) ** 2
        outlier = Y.shape[0] / problem.volume * (4.0 * np.pi * s2) ** (d / 2.0)
        A, t = split_matrix(T)
        dist, j = problem.tree.query(X @ A.T + t, k=8, distance_upper_bound=FINAL_GATE * scale * sigma)
        ii, kk = np.nonzero(np.isfinite(dist))
        if ii.size < model.sample_size:
            return fit
        kern = np.exp(-(dist[ii, kk] ** 2) / (4.0 * s2))
        total = np.bincount(ii, weights=kern, minlength=X.shape[0])
        w = kern / (total[ii] + outlier)
        if w.sum() < model.sample_size:
            return fit
        T = model.fit(X[ii], Y[j[ii, kk]], w)
    return Fit(T, fit.correspondences)


# -------------------------------------------------------------------- judge
@dataclass(frozen=True, eq=False)
class Judged:
    """What tensor voting made of one trial motion."""

    fit: Fit
    n_tokens: int
    sigma: float


def judge(problem: Problem, matrix: np.ndarray, tolerance: float, *, sigma: float | None = None,
          max_candidates: int = 8, n_refs: int = 4) -> Judged | None:
    """Tensor voting judges a trial motion (section 3.4).

    tokens within the voting reach (2σ) of the trial motion → one ball pass
    in each of the model's joint spaces → eq. 41 (the model's constraint)
    against the most salient tokens → one-to-one by saliency → fit
    and residual gate.  σ defaults to half the spacing of false tokens near
    the trial translation (each source point contributes the target's
    density there), at least the gate.
    """
    n1, n2 = problem.source.shape[0], problem.target.shape[0]
    g = gate(tolerance)
    false_spacing = (n1 * n2 / problem.volume) ** (-1.0 / problem.dim)
    sig = float(sigma) if sigma is not None else max(g, 0.5 * min(false_spacing, problem.spacing))
    tokens = candidate_tokens(problem, matrix, 2.0 * sig, max_candidates)
    if len(tokens) < problem.model.sample_size:
        return None
    votes = vote_tokens(tokens, sig, problem.model)
    best = constraint(tokens, votes, 2.0 * g, problem.model, n_refs=n_refs)
    if best is None:
        return None
    sub = best[select_one_to_one(tokens.pairs[best], -votes.saliency[best])]
    fit = fit_and_gate(problem, tokens.pairs, tokens.pairs[sub], g)
    if fit is None:
        return None
    return Judged(fit, len(tokens), sig)


def judged_alike(judged: Judged, problem: Problem, matrix: np.ndarray, tolerance: float) -> bool:
    """Whether the trial motion ``matrix`` is the hypothesis ``judged`` already resolved, at the judge's scale.

    :func:`judge` votes on every pair within 2σ of a trial's moved source
    points (:func:`candidate_tokens`) and keeps the pairs within the gate
    ``g`` of its fit.  A trial that moves every source point within
    ``2σ − g`` of where ``judged``'s fit puts it has each of those kept pairs
    within its own candidates' reach, around the same dense cluster of tokens: judging
    it votes on the same evidence again (the best trials of a congruent
    search are mostly one motion found from several triples).  σ is
    ``judged.sigma``, the scale :func:`judge` derives from ``problem`` and
    ``tolerance`` alone.
    """
    reach = 2.0 * judged.sigma - gate(tolerance)
    if reach <= 0.0:
        return False
    A, t = split_matrix(matrix)
    B, s = split_matrix(judged.fit.matrix)
    gap = problem.source @ (A - B).T + (t - s)
    return float(np.max(np.einsum("ij,ij->i", gap, gap))) <= reach * reach


# ------------------------------------------------------------------- search
@dataclass(frozen=True)
class LevelCount:
    """A fit's pairs within one level's gate against chance there (:func:`passing_level`)."""

    gate: float
    support: int
    level: float
    n_tested: float


@dataclass(frozen=True, eq=False)
class Found:
    """The first trial motion of a :func:`search` whose judged support beat chance.

    Attributes
    ----------
    fit : Fit
        After refinement and the tolerance growth.
    tolerance : float
        The tolerance it was accepted at (after growth).
    judged : Judged
        What tensor voting made of the trial.
    trial_support : int
        The trial's density-test support.
    threshold : int
        The support it had to reach (the verdict's chance level).
    n_tested : float
        The tests that level is family-wise over (the judge's calls, or
        every match the budget scores behind the density test's screen).
    gate : float
        The gate the level was computed at (the accepting level's).
    passed_at : LevelCount, optional
        Behind the density test's screen, the level whose gate held enough
        of the polished pairs to beat chance (:func:`passing_level`; it
        may be finer than the accepting level, whose ``threshold`` the
        motion then need not reach).
    """

    fit: Fit
    tolerance: float
    judged: Judged
    trial_support: int
    threshold: int
    n_tested: float = 1.0
    gate: float = float("nan")
    passed_at: LevelCount | None = None


#: Wrong trial motions :func:`search`'s density test may pass on to tensor
#: voting over a whole search, in expectation (see :func:`density_tests`).
JUDGED_WRONG = 50.0


def passing_level(problem: Problem, fit: Fit, levels, n_tests: float) -> LevelCount | None:
    """The first level (finest first, as given) whose gate holds enough of ``fit``'s pairs to beat chance.

    A motion found at a coarse tolerance is polished at its gate, which
    also collects the chance pairs of that wide gate; a true motion's pairs
    stay tight (the noise, not the gate), so within a finer level's gate it
    keeps most of them while chance falls as the gate cubed.  Each level's
    count is tested family-wise over ``n_tests`` matches and, Bonferroni,
    over the ``len(levels)`` gates looked at, at the target's density
    where ``fit`` puts the source (:meth:`Problem.chance_under`): a wrong
    motion that lays the source onto a dense part of the target collects
    chance pairs at that part's density.  The pairs are ``fit``'s own
    (one-to-one), so a finer gate only drops pairs.  ``None`` when no level
    passes.
    """
    return _passed(level_counts(problem, fit, levels, n_tests))


def level_counts(problem: Problem, fit: Fit, levels, n_tests: float) -> list[LevelCount]:
    """:func:`passing_level`'s count at each level, finest first, up to the first that passes.

    All of them when none passes: a refused motion's closest count
    (:func:`closest_count`) is then the one a search's verdict reports.
    """
    n_all = n_tests * float(len(levels))
    n_source, n_target = problem.source.shape[0], problem.target.shape[0]
    counts = []
    for g, count, measure in _gate_counts(problem, fit, levels):
        level = problem.model.chance(n_source, n_target, measure, g, n_all)
        counts.append(LevelCount(float(g), count, float(level), float(n_all)))
        if count >= level:
            break
    return counts


def level_alphas(problem: Problem, fit: Fit, levels, n_tests: float) -> list[float]:
    """The family-wise level at which each of :func:`level_counts`' counts would pass, every level's.

    The model's ``chance_alpha`` hook at the same gate, count, landing
    density and tests as :func:`level_counts`, so that count passes at
    level ``i`` exactly when ``level_alphas(...)[i] <=`` :data:`ALPHA`.
    """
    n_all = n_tests * float(len(levels))
    n_source, n_target = problem.source.shape[0], problem.target.shape[0]
    return [problem.model.chance_alpha(count, n_source, n_target, measure, g, n_all)
            for g, count, measure in _gate_counts(problem, fit, levels)]


def _gate_counts(problem: Problem, fit: Fit, levels):
    """``(gate, count, measure)`` at each level, finest first: ``fit``'s pairs within the level's gate,
    and the measure the target's density gives there where ``fit`` puts the source
    (:meth:`Problem.landing_measure`)."""
    res = problem.residuals(fit.matrix, fit.correspondences)
    radii = problem.landing_radii(fit.matrix)
    for tol in levels:
        g = gate(tol)
        yield g, int(np.count_nonzero(res <= g)), problem.landing_measure(radii, g)


#: Reach of :func:`likelihood_counts`' pairs, in noise deviations ``σ``: a pair's
#: score there is below ``e^{-18}`` of its peak (:func:`gatv.stats.pair_scores`).
SCORE_REACH = 6.0 * np.sqrt(2.0)

#: Folds of :func:`likelihood_counts`' cross-fit: each fold's points are scored
#: under the pose refined on the other folds' points alone.
SCORE_FOLDS = 5


def likelihood_counts(problem: Problem, matrix: np.ndarray, gate_radius: float, levels, n_tests: float,
                      inlier_share: float) -> list[LevelCount]:
    """The likelihood-ratio test of the trial motion ``matrix``, at each level's noise, finest first,
    up to the first that passes.

    :func:`level_counts` counts a motion's pairs within one gate, so a pair
    at a tenth of the noise counts as much as one at the gate, and the
    chance pairs the gate holds grow as its cube.  Here each source point
    is paired with its nearest target point (one to one, within
    :data:`SCORE_REACH` ``σ``) and the pair scores its log likelihood
    ratio of a true pair (Gaussian residual at the level's tolerance
    ``σ``, prior odds ``inlier_share / (1 − inlier_share)``) against a
    chance neighbour at the target's local density where the point lands
    (:meth:`Problem.landing_radii`; :func:`gatv.stats.pair_scores`).

    **Cross-fit.**  A pose refined on the points it is scored on pulls
    their chance pairs tight, and tight pairs score most: on Table 2
    (f = 0.95, 1%, the 0.05-spacing level) 1 in 1,000 random poses polished
    by :func:`refine` summed 33 nats, where the fixed-pose null's 1-in-1,000
    level is 23.  So the source is split into :data:`SCORE_FOLDS` folds (by
    index), and each fold's points are scored under ``matrix`` refined
    within ``gate_radius`` on the other folds' points alone: given that
    pose, a wrong motion's scored pairs are the fixed-pose null's.  The
    sample's own points (the :func:`sample_points` source points nearest a
    target under ``matrix``, which it lays on their partners) are not
    scored.

    The sum, in nats rounded down, must reach the level a wrong motion
    reaches with probability ``ALPHA / (n_tests · len(levels))`` under the
    count's null (the target's points a Poisson process at that density,
    :func:`gatv.stats.likelihood_level`), rounded up: family-wise over the
    ``n_tests`` matches and, Bonferroni, the levels looked at, as the
    count.  Levels whose gate holds less than one chance pair over the
    source are left out (``support`` and ``level`` 0): there the count
    within the gate is already the whole likelihood (no chance pairs, and
    the Gaussian's mass within the gate).  Empty for fewer than ``2 ·
    SCORE_FOLDS`` source points.

    Returns :class:`LevelCount` records whose ``support`` and ``level`` are
    nats (integers) and whose ``gate`` is the level's :func:`gate`.

    :func:`search` does not use it (the trials it refuses are refused by
    its screen or fall short here too, design notes);
    :func:`gatv.registration.count_ceiling` asks what it would keep.
    """
    if not 0.0 < inlier_share < 1.0:
        raise ValueError(f"`inlier_share` must lie in (0, 1), got {inlier_share!r}.")
    X = problem.source
    n, d = X.shape[0], problem.dim
    if n < 2 * SCORE_FOLDS:
        return []
    odds = float(inlier_share) / (1.0 - float(inlier_share))
    matrix = np.asarray(matrix, dtype=np.float64)
    at_trial, _ = problem.tree.query(apply_matrix(matrix, X), k=1)
    scored = np.ones(n, bool)
    scored[np.argsort(at_trial, kind="stable")[:sample_points(problem.model)]] = False
    fold = np.arange(n) % SCORE_FOLDS
    moved = np.empty_like(X)
    for f in range(SCORE_FOLDS):
        rest = replace(problem, source=X[fold != f])
        pose = refine(rest, Fit(matrix, np.empty((0, 2), np.int64)), gate_radius).matrix
        moved[fold == f] = apply_matrix(pose, X[fold == f])
    moved = moved[scored]
    radii = problem.density_radii(moved)
    k = min(DENSITY_NEIGHBOURS, problem.target.shape[0])
    density = k / (ball_measure(1.0, d) * radii**d)  # k-nearest-neighbour density where each lands
    n_all = float(n_tests) * float(len(levels))
    counts = []
    for tol in levels:
        g = gate(tol)
        if tol <= 0.0 or problem.landing_pairs(radii, g) < 1.0:
            counts.append(LevelCount(float(g), 0, 0.0, n_all))
            continue
        pairs = nearest_pairs(moved, problem.tree, SCORE_REACH * tol)
        r = np.linalg.norm(problem.target[pairs[:, 1]] - moved[pairs[:, 0]], axis=1)
        score = float(pair_scores(r, tol, density[pairs[:, 0]], odds, d).sum())
        level = likelihood_level(peak_ratios(tol, density, odds, d), odds, n_all, dim=d)
        counts.append(LevelCount(float(g), int(np.floor(score)), float(np.ceil(level)), n_all))
        if counts[-1].support >= counts[-1].level:
            break
    return counts


def likelihood_passes(counts: list[LevelCount]) -> LevelCount | None:
    """The level of :func:`likelihood_counts`' ``counts`` that passed, or ``None``."""
    last = counts[-1] if counts else None
    return last if last is not None and last.level > 0 and last.support >= last.level else None


def closest_count(counts) -> LevelCount | None:
    """The count of ``counts`` (:class:`LevelCount`) nearest its level, by ``support / level``."""
    return max(counts, key=lambda c: _ratio(c.support, c.level), default=None)


def _passed(counts: list[LevelCount]) -> LevelCount | None:
    """The last of :func:`level_counts`' ``counts`` when it reaches its level (the first that passes)."""
    return counts[-1] if counts and counts[-1].support >= counts[-1].level else None


def _ratio(support: float, level: float) -> float:
    """``support / level``, the closeness to passing that the verdicts of failed searches compare."""
    return support / max(float(level), 1e-300)


def beats_chance_at_some_level(problem: Problem, fit: Fit, levels, n_tests: float) -> bool:
    """Whether ``fit``'s pairs within some level's gate beat chance there (:func:`passing_level`)."""
    return passing_level(problem, fit, levels, n_tests) is not None


def search_failure(tried: list, time_limit: float | None = None) -> str:
    """Why :func:`search` returned ``None``, from its ``tried`` records.

    The time limit (``deadline``, given as ``time_limit`` seconds), the
    work bound (``max_work``), or the samples spent without a motion
    beating the chance level.
    """
    stopped = {rec["stopped"] for rec in tried if "stopped" in rec}
    if "time limit" in stopped:
        return (f"the time limit (`time_limit`, {time_limit:g} s) ran out before a trial motion beat "
                "the chance level")
    if stopped:
        return "the work bound (`max_work`) ran out before a trial motion beat the chance level"
    return "no trial motion beat the chance level"


def _duration(listener: numba_event.TimingListener) -> float:
    """Seconds a numba event listener has measured so far (0 before the first event)."""
    return float(listener.duration) if listener.done else 0.0


def density_tests(n_matches: float, judged_wrong: float | None = JUDGED_WRONG) -> float:
    """The ``n_tests`` of the density test's chance level when ``n_matches`` matches are scored.

    The density test only screens trial motions for the judge (tensor
    voting, with its own chance level): it may let :data:`JUDGED_WRONG`
    wrong motions through in expectation over the ``n_matches`` scored, a
    level of ``JUDGED_WRONG / n_matches`` a match, instead of the
    family-wise :data:`gatv.stats.ALPHA` over all of them.  At f = 0.9
    and 1% noise that is 43 instead of 62 points at the coarse tolerance
    where a true motion brings ~65.  Returns the count to give as
    ``n_tests`` (at least 1) to the chance level, family-wise at ``ALPHA``;
    ``judged_wrong=None`` keeps the level family-wise over all the matches
    (``n_matches``).

    Raises
    ------
    ValueError
        ``judged_wrong`` not positive (give ``None`` for the family-wise level).
    """
    if judged_wrong is None:
        return float(n_matches)
    if not judged_wrong > 0:
        raise ValueError(f"`judged_wrong` must be positive, got {judged_wrong!r}; "
                         "None keeps the level family-wise over all the matches.")
    return max(1.0, ALPHA * float(n_matches) / float(judged_wrong))


def listed_share(listing: float, sample_points: int = 3) -> float:
    """Share of all-inlier samples whose true match a congruent listing at ``listing`` keeps.

    A side's length error is Gaussian (four noisy points projected on it);
    the listing keeps a match when each side is within ``listing`` standard
    deviations, ``2Φ(listing) − 1`` for one side, about that to the power of
    the ``sample_points`` sides (taken as independent).  The matches listed
    per sample grow as ``listing³`` (target triangles within the tolerance
    of all three sides) while the all-inlier samples listed grow as this
    share, so the work per motion found goes as ``(listing / (2Φ(listing) −
    1))³``: 16.2 at 2.5 standard deviations, 3.1 at one, 2.0 at the limit
    of none, where the samples drawn grow without bound.
    """
    return float(erf(float(listing) / np.sqrt(2.0)) ** sample_points)


#: Default side-length tolerance of :func:`search`'s congruent listing, in
#: standard deviations of a side's length error at the level's tolerance.
LISTING = 2.5

#: Work units per round of :func:`search` at each tolerance (see there).
SEARCH_SHARE = 20000.0
#: Best model matches scored per trial sample: :data:`gatv.models.base.MAX_MATCHES`
#: (a model's policy may score more, :class:`gatv.models.SearchPolicy`).
# Work units of :func:`search`, about a microsecond of CPU each: the costs
# below were fitted (non-negative least squares) to the CPU time each
# tolerance level took in whole searches, so that the round robin's equal
# work is about equal CPU at fine and coarse levels alike (see the design
# notes).
#: Work units per sample drawn: its draw, reordering and share of the batch.
SAMPLE_COST = 2.5
#: Work units per candidate triple of a wide draw (its side windows and
#: height, :func:`gatv.models.rigid.congruent.trial_motions`' ``wide``).
CANDIDATE_COST = 0.5
#: Work units per congruent match listed but not necessarily scored.
LIST_COST = 0.2
#: Work units per probe of the listing (a binary search in a sorted length
#: list or a candidate third point): at fine tolerances a sample lists a
#: few matches but still probes hundreds of target pairs.
PROBE_COST = 0.1
#: Work units per match scored (its pose).
SCORE_COST = 2.0
#: Work units per source point a match's count visits.
VISIT_COST = 0.02
#: Samples of the first chunk at each tolerance, before its cost is measured.
FIRST_CHUNK = 2
#: Samples at least in the costliest level's chunk: the model scores a
#: chunk's samples in parallel, and a coarse level whose samples cost
#: milliseconds each would otherwise run two or three to a chunk, leaving
#: threads idle while the slowest finishes.  Every level's share of a round
#: grows alike, so the levels still get equal work.  A constant, not the
#: thread count, so that a seed gives the same result on every machine.
MIN_CHUNK = 8
#: Matches listed per sample from which :func:`search` passes its
#: ``trial_options`` (ways of coping with many matches) to the model.
OPTIONS_FROM = 8


def _listed_and_visited(trials, n_source: int) -> tuple[int, int]:
    """Matches a chunk listed (at least those it scored) and source points its counts visited
    (all ``n_source`` a scored match when the model does not count them)."""
    visited = getattr(trials, "n_visited", -1)
    if visited < 0:
        visited = n_source * trials.n_congruent
    return max(getattr(trials, "n_listed", 0), trials.n_congruent), visited


def chunk_work(trials, n_source: int, triple_cost: float = 0.0) -> float:
    """Work units of one chunk of a search: the model's trial motions ``trials`` on ``n_source`` points.

    Counted from what the chunk did, never from the clock, so that a seed
    gives the same search everywhere: samples drawn (plus the model's own
    ``triple_cost`` a sample) and the candidates of a wide draw, matches
    listed and the listing's probes, matches scored and the source points
    their counts visited (all ``n_source`` a match unless the model counts
    fewer, see its sequential test).
    """
    listed, visited = _listed_and_visited(trials, n_source)
    return ((SAMPLE_COST + triple_cost) * trials.n_triples
            + CANDIDATE_COST * getattr(trials, "n_candidates", 0)
            + LIST_COST * listed + PROBE_COST * getattr(trials, "n_probes", 0)
            + SCORE_COST * trials.n_congruent + VISIT_COST * visited)


#: ICP rounds a polished trial may take (:func:`refine`'s ``iterations``),
#: each charged as a scored match visiting every source point.
POLISH_ROUNDS = 10


def polish_trials(problem: Problem, trials, gate_radius: float, index=None):
    """``trials`` each polished by ICP within ``gate_radius`` (:func:`refine`), ranked by their polished support.

    The local optimisation of LO-RANSAC: under noise the pose of three noisy
    points is off by about the noise over the triangle's height, and far
    from the triangle a true trial's points fall outside a gate of the
    noise's size; its support there is a fraction of its motion's, and a
    small motion stays under the density test's level.  Its polish brings
    them in (a wrong trial's gains little: its pairs are chance pairs,
    which a refit only moves among).  The trials keep the
    model's type; their matrices and support are replaced.

    ``index``: the model's index of ``problem.target`` at ``gate_radius``
    (the search's); a model with the optional hook ``polish_motions`` then
    polishes every trial in one call (the rigid model: one numba kernel,
    trials in parallel, :func:`refine`'s steps).
    """
    if not len(trials):
        return trials
    linear, shift, support = polished_motions(problem, trials.rotations, trials.translations, gate_radius, index)
    order = np.argsort(-support, kind="stable")
    return replace(trials, rotations=np.ascontiguousarray(linear[order]),
                   translations=np.ascontiguousarray(shift[order]), support=support[order])


def polished_motions(problem: Problem, linear: np.ndarray, shift: np.ndarray, gate_radius: float, index=None):
    """``(linear, shift, support)``: each motion ``(linear[k], shift[k])`` polished by ICP within
    ``gate_radius`` (:func:`refine`'s steps, :data:`POLISH_ROUNDS` rounds) and its polished support.

    ``index``: the model's index of ``problem.target`` at ``gate_radius``; a model with the optional
    hook ``polish_motions`` then polishes every motion in one call (the rigid model: one numba kernel,
    motions in parallel), else each goes through :func:`refine`.
    """
    fast = getattr(problem.model, "polish_motions", None)
    if fast is not None and index is not None and float(index.radius) == float(gate_radius):
        linear, shift, support = fast(problem.source, index, linear, shift, POLISH_ROUNDS,
                                      extent=problem.extent, spacing=problem.spacing)
        return linear, shift, np.asarray(support, np.int64)
    none = np.empty((0, 2), np.int64)
    fits = [refine(problem, Fit(homogeneous(A, b), none), gate_radius, POLISH_ROUNDS) for A, b in zip(linear, shift)]
    support = np.array([f.support for f in fits], np.int64)
    linear, shift = (np.stack(a) for a in zip(*(split_matrix(f.matrix) for f in fits)))
    return linear, shift, support


def landing_level(problem: Problem, matrix: np.ndarray, gate_radius: float, n_tests: float) -> int:
    """The density test's level at the density of the target's other points where ``matrix`` puts the source.

    The support a motion's moved source points collect by chance (each within
    ``gate_radius`` of some target point) at the local density of the target
    points other than those it already lands on (its own partners, which a
    true motion brings with it): :meth:`Problem.landing_pairs` of their
    :data:`DENSITY_NEIGHBOURS`-nearest radii, family-wise over ``n_tests``.
    Where the points are spread evenly through their box it is about the box's
    level; where the motion lays the source onto a dense part of the target
    (two Gaussian blobs' cores) it is that part's.
    """
    dist, j = problem.tree.query(apply_matrix(matrix, problem.source), k=1, distance_upper_bound=gate_radius)
    radii, n_others = _other_radii(problem, matrix, j[np.isfinite(dist)])
    if n_others == 0:
        return problem.chance(gate_radius, n_tests)
    return problem.model.chance(problem.source.shape[0], problem.target.shape[0],
                                problem.landing_measure(radii, gate_radius, n_others), gate_radius, n_tests)


def search(problem: Problem, levels, *, budget: int, rng: np.random.Generator, keep: int = 4,
           sigma: float | None = None, max_candidates: int = 8, polish: bool = True, grow: bool = True,
           threshold_tests: float = 1.0, min_support: int | None = None, memory_budget=None,
           progress=None, tried: list | None = None, max_matches: int = MAX_MATCHES,
           max_work: float | None = None, trial_options: dict | None = None,
           deadline: float | None = None, confidence: float = 0.999,
           judged_wrong: float | None = JUDGED_WRONG, listing: float = LISTING,
           polish_trial_motions: bool = False, index=None) -> Found | None:
    """Trial motions → judge → refine → grow, until a motion beats chance (Algorithm 1).

    Round robin over the tolerance ``levels`` with an equal share of work
    each: a motion that shows at a coarse tolerance is not kept waiting for
    the whole ``budget`` of samples of the finer, fruitless ones, and a
    coarse tolerance (many matching but wrong samples, each scored on every
    point) does not slow down an exact one.  Work is counted
    deterministically, in microsecond-like units (:func:`chunk_work`: the
    samples drawn and their candidates, the matches listed and the
    listing's probes, the matches scored and the points their counts
    visited), so the same seed gives the same result.  The ``keep`` best
    trials of a chunk that reach the density test's chance level
    (:func:`density_tests` with ``judged_wrong``; ``None``: family-wise
    over every match, and also at the density of the target's other points
    where the trial lands, :func:`landing_level`) are judged by tensor
    voting (:func:`judge`), behind
    the screen only those whose own polish beats the judge's level within
    some gate up to theirs (:func:`beats_chance_at_some_level`); the
    first whose support reaches the chance level of the gate (family-wise
    over ``threshold_tests`` × ``judged_wrong`` judged trials; or
    ``min_support``) is refined (``polish``, :func:`refine`), kept when
    (behind the screen) its refined pairs within its level's gate or a
    finer one's also beat
    chance family-wise over every match the budget scores
    (:func:`beats_chance_at_some_level`), and its tolerance grown while its
    support grows beyond chance (``grow``, :func:`grow_tolerance`).

    ``tried`` (a list) receives one record per tolerance: samples drawn and
    their wide draws' candidates, matches scored and listed, points
    visited, work units spent, best trial support, the density test's
    threshold.
    ``max_matches`` caps the matches scored per sample (under noise a sample
    matches many target samples; the model scans them from a random start,
    so a capped scan is an unbiased share of them); ``max_work`` caps the
    work units of the whole search, which bounds its time whatever the
    noise; ``trial_options`` go to the model's ``trial_motions``;
    ``deadline`` (a :func:`time.perf_counter` reading) stops the search
    between chunks, before a chunk as slow as the slowest so far would end
    past it: a wall-clock bound for callers that promise one (unlike the
    work bound, it depends on the machine's speed); the time numba spends
    compiling kernels on a first call moves it on.

    A sample's congruent matches are listed within ``listing`` standard
    deviations of a side's length error at the level's tolerance ``τ``
    (``eps = 2 listing τ``, four noisy points on a side): when ``τ`` is
    the noise, a wider listing keeps more true matches (each side with
    probability ``erf(listing / sqrt 2)``) but lists chance matches as
    ``eps³``, and the work a motion found costs goes as ``(listing /
    erf(listing / sqrt 2))³``.

    A level draws at most the samples that find, with ``confidence``, the
    smallest motion its density test accepts (the RANSAC bound of
    :func:`gatv.stats.samples_needed` at ``accept / n`` times that
    probability, one factor a side), never more than
    ``budget``: at a coarse tolerance random motions already reach a large
    share of the points, and only a motion larger still can be found
    there, which a few samples hit.
    ``polish_trial_motions``: each chunk's ``keep`` best trials are polished
    (:func:`polish_trials`) before the density test, which then sees their
    polished support: the local optimisation of LO-RANSAC, for noise so
    large that a noisy sample's pose leaves most of its motion's points
    outside the gate.

    ``index``: the model's index of ``problem.target`` when the caller has
    built it already (any radius: each level's copy gets its own).

    Returns ``None`` when the budget, the work or the time runs out.
    """
    model = problem.model
    report = progress if progress is not None else (lambda fraction, message="": None)
    n, n2 = problem.source.shape[0], problem.target.shape[0]
    # One index of the target's samples; one scoring grid per tolerance.
    # A first call compiles the kernels (a minute on a loaded machine): that
    # time is not the search's, and the deadline moves by it.
    compiling = numba_event.TimingListener()
    with numba_event.install_listener("numba:compile", compiling):
        base = model.index(problem.target, gate(levels[0]), memory_budget=memory_budget) if index is None else index
        indexes = []
        for tol in levels:
            idx = copy.copy(base)
            idx.set_radius(gate(tol))
            indexes.append(idx)
        accept = [model.chance(n, n2, idx.volume, idx.radius, density_tests(budget * max_matches, judged_wrong))
                  for idx in indexes]  # each level's density test (the screen)
        k_pts = int(getattr(model, "trial_sample_size", model.sample_size))
        # Each side of a true sample stays within the listing's tolerance
        # (listed_share of one side): one factor a point of the sample.
        side_kept = listed_share(listing, 1)
        caps = [min(budget, samples_needed(min(1.0, a / n) * side_kept, confidence, k_pts)) for a in accept]
        screen_tests = density_tests(budget * max_matches, judged_wrong)
        records = [{"tolerance": tol, "triples": 0, "candidates": 0, "congruent": 0, "listed": 0, "visited": 0,
                    "work": 0.0, "best_support": 0, "threshold": a, "n_tests": screen_tests}
                   for tol, a in zip(levels, accept)]
        if tried is not None:
            tried.extend(records)
        triple_cost = getattr(model, "triple_cost", None)
        done = [0] * len(levels)
        per_triple = [SEARCH_SHARE / FIRST_CHUNK] * len(levels)  # first chunk: a few samples, then measured
        options = dict(trial_options or {})
        work = 0.0
        # The deadline is kept by not starting a chunk that the slowest one so far would carry past it.
        last_check, slowest = None, 0.0
        # Tests the judge's level counts (its calls, up to ``judged_wrong`` wrong
        # ones), and the final level's (every match the budget scores).
        n_judge_tests = threshold_tests * (judged_wrong or 1.0)
        n_final = threshold_tests * float(budget) * max_matches
        # The first round's chunks (FIRST_CHUNK samples a level) only measure each level's cost, so
        # its work is not equal across levels: a motion a level finds there waits until every finer
        # level has had as much work (a finer level's motion wins).  Later rounds share work equally.
        pending: tuple[int, Found] | None = None
        first_round = True

        def behind(upto):
            if not first_round and pending is None:
                return []
            return [lv for lv in range(upto) if done[lv] < caps[lv] and records[lv]["work"] < records[upto]["work"]]

        while any(d < c for d, c in zip(done, caps)):
            if pending is not None and not behind(pending[0]):
                return pending[1]
            measured = [p for p, rec in zip(per_triple, records) if rec["triples"] > 0]
            share = max(SEARCH_SHARE, MIN_CHUNK * max(measured, default=0.0))
            for level, tol in enumerate(levels):
                if done[level] >= caps[level]:
                    continue
                if pending is not None and level not in behind(pending[0]):
                    continue
                if max_work is not None and work >= max_work:
                    if pending is not None:
                        return pending[1]
                    if tried is not None:
                        tried.append({"stopped": "work bound", "work": work, "max_work": float(max_work)})
                    return None
                if deadline is not None:
                    now = time.perf_counter() - _duration(compiling)
                    if last_check is not None:
                        slowest = max(slowest, now - last_check)
                    last_check = now
                    if now + slowest >= deadline:
                        if pending is not None:
                            return pending[1]
                        if tried is not None:
                            tried.append({"stopped": "time limit", "work": work})
                        return None
                m = int(min(caps[level] - done[level], max(2, min(4096, share / per_triple[level]))))
                done[level] += m
                rec = records[level]
                report(sum(done) / sum(caps), f"tolerance {tol:.3g}: {rec['triples']} triples")
                g = gate(tol)
                # Side-length tolerance: a side's length error is the noise of four
                # points projected on it (standard deviation 2 tol); ``listing`` of those.
                eps = 2.0 * listing * tol
                # The model's options for many matches a sample (``trial_options``)
                # only where the samples so far had many: they cost more than they
                # save on exact data.
                busy = rec["triples"] > 0 and rec["listed"] >= OPTIONS_FROM * rec["triples"]
                trials = model.trial_motions(problem.source, indexes[level], eps=eps, max_triples=m, rng=rng,
                                             keep=keep, max_matches=max_matches, accept=accept[level],
                                             **(options if busy else {}))
                rec["triples"] += trials.n_triples
                rec["candidates"] += getattr(trials, "n_candidates", 0)
                rec["congruent"] += trials.n_congruent
                listed, visited = _listed_and_visited(trials, n)
                rec["listed"] += listed
                rec["visited"] += visited
                chunk = chunk_work(trials, n, triple_cost(n2) if triple_cost is not None else 0.0)
                if polish_trial_motions and len(trials):
                    trials = polish_trials(problem, trials, g, indexes[level])
                    chunk += len(trials) * POLISH_ROUNDS * (SCORE_COST + VISIT_COST * n)
                rec["work"] += chunk
                work += chunk
                per_triple[level] = rec["work"] / max(rec["triples"], 1)
                if len(trials):
                    rec["best_support"] = max(rec["best_support"], int(trials.support[0]))
                if not len(trials) or trials.support[0] < accept[level]:
                    continue
                # Family-wise over the judge's calls too: up to judged_wrong wrong ones.
                threshold = min_support if min_support is not None else problem.chance(g, n_judge_tests)
                # But the judge's count of a trial is not independent of the screen's
                # (same points, and the judge refits): a wrong trial that passed a
                # lenient screen is already near its level.  So behind a screen the
                # polished support must also beat chance family-wise over every
                # match scored, the level the density test has without the screen.
                final = threshold
                if judged_wrong is not None and min_support is None:
                    final = max(threshold, problem.chance(g, n_final))
                for k, matrix in enumerate(trials.matrices):
                    if trials.support[k] < accept[level]:
                        break
                    if judged_wrong is None:
                        # Without a lenient screen the density test is the family-wise one: at the
                        # density of the other target points where the trial puts the source too (a
                        # search that maximises support finds the dense parts of points not spread
                        # evenly through their box, where the box's level is far too low).
                        local = landing_level(problem, matrix, g, screen_tests)
                        if trials.support[k] < local:
                            _refused(rec, LevelCount(g, int(trials.support[k]), float(local), float(screen_tests)))
                            continue
                    # Behind the screen, before the judge: the trial polished by
                    # itself must beat the judge's own level within some gate up to
                    # this one.  Coarse gates let many wrong trials through the
                    # screen; polished, their pairs scatter over the gate and fail
                    # every finer one, at the cost of a few nearest-neighbour
                    # queries instead of a tensor-voting pass.
                    if final > threshold:
                        counts = level_counts(
                            problem, refine(problem, Fit(matrix, np.empty((0, 2), np.int64)), g),
                            levels[:level + 1], n_judge_tests)
                        if _passed(counts) is None:
                            _refused(rec, closest_count(counts))
                            continue
                    judged = judge(problem, matrix, tol, sigma=sigma, max_candidates=max_candidates)
                    if judged is None or judged.fit.support < threshold:
                        _refused(rec, LevelCount(g, 0 if judged is None else int(judged.fit.support),
                                                 float(threshold), float(n_judge_tests)))
                        continue
                    fit = judged.fit
                    if polish:
                        fit = refine(problem, fit, g)
                    if final > threshold:
                        # At its own gate or a finer level's (a true motion's pairs stay tight).
                        counts = level_counts(problem, fit, levels[:level + 1], n_final)
                        passed = _passed(counts)
                        if passed is None:
                            _refused(rec, closest_count(counts))
                            continue
                    elif fit.support < final:
                        _refused(rec, LevelCount(g, int(fit.support), float(final), float(n_judge_tests)))
                        continue
                    if grow:
                        fit, grown = grow_tolerance(problem, fit, levels, level)
                        tol = levels[grown]
                    n_tested = n_final if final > threshold else n_judge_tests
                    found = Found(fit, tol, judged, int(trials.support[k]), int(final), float(n_tested), g,
                                  passed if final > threshold else None)
                    if not behind(level):
                        return found
                    pending = (level, found)
                    break
            first_round = False
        return None if pending is None else pending[1]


# ------------------------------------------------------------------ verdict
def found_verdict(found: Found, support: int | None = None) -> Verdict:
    """The verdict on a :func:`search`'s motion: the test that admitted it.

    ``support`` (default the found fit's) against the level it had to reach
    (:attr:`Found.threshold`, family-wise over :attr:`Found.n_tested`); or,
    for a motion admitted at a level finer than its own
    (:attr:`Found.passed_at`), which need not reach that threshold, its
    pairs within that level's gate against chance there.
    """
    if found.passed_at is not None:
        at = found.passed_at
        return chance_verdict(at.support, float(np.ceil(at.level)), at.n_tested, method="poisson")
    return chance_verdict(found.fit.support if support is None else support, found.threshold, found.n_tested,
                          method="poisson")


def search_verdict(tried: list) -> Verdict:
    """The verdict on a :func:`search` that found nothing, from its ``tried`` records.

    Each tolerance's closest test to passing: where a trial beat the
    density screen, the test that refused it (the check before the judge,
    the judge's level or the final level; its ``"refused"`` record), else
    the best trial support against the screen's level.  The verdict is the
    closest of those, by ratio, so a search that returns nothing never
    reads "passed".
    """
    figures = []
    for r in tried:
        if "refused" in r:
            c = r["refused"]
            figures.append((c["support"], c["level"], c["n_tests"]))
        elif "best_support" in r:
            figures.append((r["best_support"], float(r["threshold"]), r.get("n_tests", 1.0)))
    if not figures:
        return chance_verdict(0, 0.0, 1.0, method="poisson")
    support, level, n_tests = max(figures, key=lambda f: _ratio(f[0], f[1]))
    return chance_verdict(support, level, n_tests, method="poisson")


def _refused(rec: dict, count: LevelCount) -> None:
    """Keep in ``rec["refused"]`` the refused trial's test nearest its level (:func:`search_verdict`)."""
    old = rec.get("refused")
    if old is None or _ratio(count.support, count.level) > _ratio(old["support"], old["level"]):
        rec["refused"] = {"support": int(count.support), "level": float(count.level),
                          "n_tests": float(count.n_tested)}


# ------------------------------------------------------------------- result
def make_result(problem: Problem, fit: Fit, info: dict, score: float | None = None) -> Motion:
    """The model's result for ``fit``: correspondences sorted by source index, their rms."""
    return motion_result(problem.model, problem.source, problem.target, fit, info, score)


def motion_result(model, source: np.ndarray, target: np.ndarray, fit: Fit, info: dict,
                  score: float | None = None) -> Motion:
    """:func:`make_result` for correspondences into ``source`` and ``target`` (no :class:`Problem`).

    ``score`` defaults to the support.
    """
    model = get_model(model)
    pairs = fit.correspondences
    pairs = pairs[np.argsort(pairs[:, 0], kind="stable")]
    res = model.residuals(fit.matrix, source[pairs[:, 0]], target[pairs[:, 1]])
    rms = float(np.sqrt(np.mean(res**2))) if pairs.size else float("nan")
    return model.result(fit.matrix, pairs, score=float(pairs.shape[0] if score is None else score),
                        rms=rms, info=info)


def failure(model, reason: str, info: dict) -> Motion:
    """A falsy result of ``model`` whose ``info["reason"]`` says why."""
    model = get_model(model)
    d = model.dim
    return model.result(np.eye(d + 1), np.empty((0, 2), np.int64), score=0.0, rms=float("nan"),
                        info=dict(info, reason=reason))
