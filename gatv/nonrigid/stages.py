"""The stages of the non-rigid mode (section 5.1) and the values they pass on.

:func:`gatv.nonrigid.register` runs, in order:

1. :func:`candidate_pairs` → :class:`Candidates`, and :func:`joint_tokens`:
   the ``{dx, dy, dz}`` token of each pair (eq. 30's joint space);
2. :func:`tensor_votes` → :class:`Votes`: surfaces or curves among the
   tokens (section 3.3);
3. :func:`local_eq41` → :class:`LocalCheck`: eq. 41 between each token and
   its closest active neighbour (Fig. 14);
4. :func:`select_seeds` → :class:`Seeds`: the one-to-one verified tokens;
5. the hypotheses, one-to-one matches by name: :func:`voting_hypothesis`,
   :func:`coarse_hypothesis`, :func:`anneal_hypothesis` and, when asked or
   when nothing else counts, :func:`rigid_hypothesis`;
6. :func:`choose_hypothesis` → :class:`Verdict`: verification of each
   hypothesis against chance (:func:`verify_matches`);
7. :func:`refine_winner` and :func:`fit_local_motions` → :class:`LocalFit`:
   the reported matches, the warp's smoothing, the local rigid motions.

The fixed data of one call live in :class:`Problem`, the validated
options in :class:`Settings`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..candidates import all_pairs, median_spacing, one_to_one
from ..fitting import kabsch
from ..ga import eq41_length_residual
from ..registration import register as rigid_register
from ..voting import default_sigma, extract_surfaces, vote
from .affine_patch import affine_patch
from .hypotheses import (
    affine_residuals,
    anneal,
    coarse_to_fine,
    grow_rings,
    match_nearest,
    polish,
    window_centres,
)
from .motion import ThinPlateWarp

__all__ = [
    "ANNEAL_PREFERENCE",
    "AUTO_RIGID_TRIPLES",
    "CHANCE_SHARE",
    "LOCAL_GATE",
    "LOCAL_WINDOWS",
    "LOCAL_WINDOW_POINTS",
    "MIN_SHARE",
    "SMOOTHING_GRID",
    "VERIFY_GATE",
    "Candidates",
    "LocalCheck",
    "LocalFit",
    "LocalStart",
    "Problem",
    "RigidStart",
    "Score",
    "Seeds",
    "Settings",
    "Verdict",
    "Votes",
    "anneal_hypothesis",
    "candidate_pairs",
    "choose_hypothesis",
    "choose_smoothing",
    "coarse_hypothesis",
    "extract_curves",
    "fit_local_motions",
    "joint_tokens",
    "local_eq41",
    "local_hypothesis",
    "local_motions",
    "refine_winner",
    "rigid_hypothesis",
    "select_seeds",
    "target_scale",
    "tensor_votes",
    "verify_matches",
    "voting_hypothesis",
    "wants_rigid_start",
]

#: Relative smoothing values tried by the cross-validation (times extent²).
SMOOTHING_GRID = (0.0, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1)
#: Verification gate of a match, times the target scale (:func:`target_scale`).
VERIFY_GATE = 0.2
#: A hypothesis is kept when its chance passes are at most this share of its support.
CHANCE_SHARE = 0.25
#: ... and when its support is at least this share of the smaller set.
MIN_SHARE = 0.1
#: Source triples of the bounded rigid search of ``prealign="auto"``.
AUTO_RIGID_TRIPLES = 300
#: The annealed hypothesis replaces another verified one only with this many
#: times its support (its smooth field blurs creases).
ANNEAL_PREFERENCE = 2.0
#: Source points of a window of the *local* hypothesis (:func:`local_hypothesis`): a patch of
#: about 3.5 spacings' radius on a surface (π 3.5² ≈ 40), small enough that a bend or a twist
#: leaves it rigid within the rigid search's tolerances, large enough for a triple search.
LOCAL_WINDOW_POINTS = 40
#: Windows of the local hypothesis tried, densest first, before it gives up.
LOCAL_WINDOWS = 16
#: Match gate of a window's rigid search on exact data, times the window's spacing: a wrong
#: target lands that close to a predicted position with probability about 0.1² per target as
#: dense as the window, so chance matches stay under one in a window; a bend or twist leaves the
#: window's core rigid that closely (the rest is grown, following the warp).
LOCAL_GATE = 0.1


# ------------------------------------------------------------ values
@dataclass(frozen=True)
class Settings:
    """Validated options of :func:`gatv.nonrigid.register` (see its parameters)."""

    seed: int
    max_displacement: float | None
    max_candidates: int | None
    max_pairs: int
    noise: float | None
    sigma: float | None
    n_stick_passes: int
    structure: str
    strain: float
    gate: float | None
    smoothing: float | None
    neighbours: int
    grow: bool
    prealign: bool | str
    memory_budget: float | None
    model: str = "rigid"
    local: bool = True  # try the local hypothesis when nothing counts (not with prealign=False)
    parts: bool = True  # seed further parts where the growth did not reach (not inside a window)
    #: inside a placed window: how far a source row's partner may lie from the row (the window's
    #: margin); the local hypothesis then searches each patch against the targets that close only
    local_reach: float | None = None

    @property
    def noise_floor(self) -> float:
        """``3.5 σ`` of the point noise (0 without ``noise``): widens every gate."""
        return 3.5 * self.noise if self.noise is not None else 0.0


def target_scale(Y, tree_y) -> float:
    """Spacing of the target's structure: the 30th percentile of nearest-neighbour distances
    (the median is inflated by sparse outliers)."""
    d = tree_y.query(Y, k=2)[0][:, 1]
    return float(np.percentile(d, 30))


@dataclass(frozen=True, eq=False)
class Problem:
    """The fixed data of one registration.

    Attributes
    ----------
    source, target : (N, 3), (M, 3) ndarray
    tree : cKDTree
        Of ``target``.
    spacing : float
        Median nearest-neighbour distance of ``target``
        (:func:`gatv.candidates.median_spacing`).
    scale : float
        Spacing of the target's structure (:func:`target_scale`), the unit of
        the hypotheses' and the verification's gates.
    extent2 : float
        Squared diagonal of the source's bounding box, the unit of the
        thin-plate smoothing.
    noise_floor : float
        ``3.5 σ`` of the point noise, added to every gate.
    gate : float
        Match radius of the voted seeds' growth before :func:`select_seeds`
        tightens it: ``max(0.3 spacing, noise_floor)`` unless given.
    auto_gate : bool
        Neither ``gate`` nor ``noise`` was given (exact data): the seeds
        may tighten the gate.
    """

    source: np.ndarray
    target: np.ndarray
    tree: cKDTree
    spacing: float
    scale: float
    extent2: float
    noise_floor: float
    gate: float
    auto_gate: bool

    @classmethod
    def build(cls, X, Y, settings: Settings) -> Problem:
        tree = cKDTree(Y)
        spacing = median_spacing(Y)
        gate = settings.gate if settings.gate is not None else max(0.3 * spacing, settings.noise_floor)
        return cls(X, Y, tree, spacing, target_scale(Y, tree),
                   float(np.sum(np.ptp(X, axis=0) ** 2)) or 1.0, settings.noise_floor, gate,
                   settings.gate is None and settings.noise is None)

    @property
    def n_smaller(self) -> int:
        """Points in the smaller set: at most this many true pairs."""
        return min(self.source.shape[0], self.target.shape[0])

    @property
    def verify_gate(self) -> float:
        """Gate of the verification: ``VERIFY_GATE`` target scales plus the noise floor."""
        return VERIFY_GATE * self.scale + self.noise_floor

    @property
    def verify_radius(self) -> float:
        """Radius of the target density around a match: two target scales plus the noise floor."""
        return 2.0 * self.scale + self.noise_floor

    def displacements(self, pairs) -> np.ndarray:
        """``target[j] − source[i]`` of each pair ``(i, j)``: its eq.-30 token."""
        return self.target[pairs[:, 1]] - self.source[pairs[:, 0]]


@dataclass(frozen=True, eq=False)
class Candidates:
    """Candidate pairs ``(source row, target row)`` and the scheme that chose them."""

    pairs: np.ndarray
    scheme: str  # "all" (section 3.4) or "bounded" (nearest targets / max_displacement)


@dataclass(frozen=True, eq=False)
class Votes:
    """Tokens kept by tensor voting, with their normals and saliency (section 3.3).

    ``structure`` is ``"surface"`` (λ1 − λ2 decided) or ``"curve"`` (λ2 − λ3
    decided); ``pairs`` and ``tokens`` are the kept candidates, in candidate
    order; ``normals`` the surface normal (the local rotation axis) or, for
    curves, the ball pass's ``e1``.
    """

    structure: str
    sigma: float
    pairs: np.ndarray
    tokens: np.ndarray
    normals: np.ndarray
    saliency: np.ndarray


@dataclass(frozen=True, eq=False)
class LocalCheck:
    """The local eq.-41 check of each voted token (Fig. 14).

    ``partner[m]`` is the closest active neighbour token checked against
    (−1: none); ``ratio[m]`` the relaxed residual over its tolerance (inf
    without a partner).
    """

    partner: np.ndarray
    ratio: np.ndarray

    @property
    def verified(self) -> np.ndarray:
        return self.ratio <= 1.0


@dataclass(frozen=True, eq=False)
class Seeds:
    """One-to-one verified tokens on the local affine trend, and the growth gate.

    ``gate`` is the problem's, or, on exact data, tightened to the seeds'
    own departure from local affinity.
    """

    pairs: np.ndarray
    gate: float
    n_verified: int


@dataclass(frozen=True, eq=False)
class Score:
    """Verification of one hypothesis: ``support`` matches pass, ``chance`` of them expected at random."""

    support: int
    chance: float
    passed: np.ndarray


@dataclass(frozen=True, eq=False)
class Verdict:
    """Scores of every hypothesis and the one chosen (``None``: none beats chance)."""

    best: str | None
    scores: dict

    def summary(self) -> dict:
        """``info["hypotheses"]``: support and chance of each hypothesis."""
        return {k: {"support": v.support, "chance": round(float(v.chance), 2)}
                for k, v in self.scores.items()}


@dataclass(frozen=True, eq=False)
class LocalFit:
    """The reported matches with their warp smoothing and local rigid motions."""

    pairs: np.ndarray
    source_points: np.ndarray
    target_points: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    smoothing: float


# ------------------------------------------------------------ 1. candidates, tokens
def candidate_pairs(problem: Problem, settings: Settings) -> Candidates:
    """All pairs for small sets (section 3.4), else the nearest targets of each source point.

    With ``max_displacement`` only targets that close; with ``max_candidates``
    (or beyond ``max_pairs`` pairs) at most that many (``max_pairs // N``)
    nearest ones per source point.
    """
    X, Y = problem.source, problem.target
    n1, n2 = X.shape[0], Y.shape[0]
    if settings.max_displacement is None and settings.max_candidates is None \
            and n1 * n2 <= settings.max_pairs:
        return Candidates(all_pairs(n1, n2, memory_budget=settings.memory_budget), "all")
    k = min(n2, settings.max_candidates if settings.max_candidates is not None
            else max(1, settings.max_pairs // n1))
    bound = np.inf if settings.max_displacement is None else settings.max_displacement
    dist, j = problem.tree.query(X, k=k, distance_upper_bound=bound)
    dist, j = dist.reshape(n1, -1), j.reshape(n1, -1)
    ii, kk = np.nonzero(np.isfinite(dist))
    return Candidates(np.stack([ii, j[ii, kk]], axis=1).astype(np.int64), "bounded")


def joint_tokens(problem: Problem, candidates: Candidates) -> np.ndarray:
    """The ``{dx, dy, dz}`` token ``target[j] − source[i]`` of each candidate (eq. 30's joint space)."""
    return problem.displacements(candidates.pairs)


# ------------------------------------------------------------ 2. tensor votes
def extract_curves(tokens, sigma: float, n_passes: int, growth: float = 1.5, threshold: float = 0.1):
    """Curve analogue of section 3.3's extraction: ball passes thresholded on curveness λ2 − λ3.

    Each pass keeps the tokens with ``λ1`` and ``λ2 − λ3`` at least
    ``threshold`` times those of the most curve-salient token, then votes
    again among them with ``sigma`` grown by ``growth``.

    Returns
    -------
    indices : (M,) ndarray of int
        Kept tokens (not sorted).
    normals : (M, 3) ndarray
        Their ball pass's ``e1``.
    saliency : (M,) ndarray
        Their ``λ2 − λ3``.
    sigma : float
        The last pass's scale.
    """
    idx = np.arange(tokens.shape[0])
    s = sigma
    votes = vote(tokens, s)
    for p in range(n_passes):
        vals = votes.eigenvalues
        c = vals[:, 1] - vals[:, 2]
        if c.size == 0 or c.max() <= 0:
            return idx[:0], np.empty((0, 3)), np.empty(0), s
        star = int(np.argmax(c))
        keep = (vals[:, 0] >= threshold * vals[star, 0]) & (c >= threshold * c[star])
        idx = idx[keep]
        if p + 1 == n_passes or idx.size < 2:
            return idx, votes.normals[keep], c[keep], s
        s *= growth
        votes = vote(tokens[idx], s)
    return idx, votes.normals, votes.eigenvalues[:, 1] - votes.eigenvalues[:, 2], s


def tensor_votes(problem: Problem, candidates: Candidates, tokens, settings: Settings) -> Votes:
    """Surfaces (or curves) among the tokens by tensor voting (section 3.3); no plane is fitted.

    A sparse ball pass, then stick passes with growing σ
    (:func:`gatv.voting.extract_surfaces`): a locally rigid motion puts the
    true tokens on a curved surface, which is kept as it is.  With
    ``structure="auto"`` the structure is a curve when the most salient
    tokens of the ball pass are curve-like (median λ2 − λ3 above median
    λ1 − λ2): a motion whose displacement varies along one direction only
    (a plane rolled around a cylinder) puts them on a 3D curve, extracted
    by :func:`extract_curves`.  σ defaults to
    :func:`gatv.voting.default_sigma` with the call's seed.
    """
    sigma = settings.sigma if settings.sigma is not None else default_sigma(tokens, seed=settings.seed)
    structure = settings.structure
    surf = extract_surfaces(tokens, sigma, n_stick_passes=settings.n_stick_passes)
    if structure == "auto":
        ball = surf.ball
        top = np.argsort(-ball.eigenvalues[:, 0], kind="stable")[:max(3, problem.n_smaller)]
        curve = float(np.median(ball.curveness[top])) > float(np.median(ball.surfaceness[top]))
        structure = "curve" if curve else "surface"
    if structure == "surface":
        idx, normals, saliency = (np.asarray(surf.indices), np.asarray(surf.normals),
                                  np.asarray(surf.surfaceness))
    else:
        idx, normals, saliency, _ = extract_curves(tokens, sigma, settings.n_stick_passes)
        order = np.argsort(idx, kind="stable")
        idx, normals, saliency = idx[order], normals[order], saliency[order]
    return Votes(structure, float(sigma), candidates.pairs[idx], tokens[idx], normals, saliency)


# ------------------------------------------------------------ 3. local eq. 41
def local_eq41(problem: Problem, votes: Votes, settings: Settings, k: int = 12) -> LocalCheck:
    """Check each voted token against its closest active neighbour in the joint space (Fig. 14).

    The neighbour is the nearest of the ``k`` nearest tokens that uses
    neither of the token's points.  The residual is eq. 41's
    ``|V × (A × Vs)| / |Vs|`` with ``A`` the token's surface normal (the
    local rotation axis, as :func:`gatv.ga.eq41_residual`); for curves, whose
    normal is not the axis, its length half ``|V · Vs| / |Vs|``
    (:func:`gatv.ga.eq41_length_residual`).  The tolerance is relaxed to
    ``strain · |Δx| + gate``: a locally rigid motion keeps lengths only up
    to the local strain (a twist of ``α`` rad per unit shears a
    neighbourhood at distance ``r`` from its axis by ``α r``), and the gate
    covers noise.
    """
    X, Y, pairs, tokens = problem.source, problem.target, votes.pairs, votes.tokens
    m = pairs.shape[0]
    partner = np.full(m, -1, np.int64)
    ratio = np.full(m, np.inf)
    if m < 2:
        return LocalCheck(partner, ratio)
    _, nb = cKDTree(tokens).query(tokens, k=min(k + 1, m))
    nb = nb.reshape(m, -1)
    i, j = pairs[:, 0], pairs[:, 1]
    active = (i[nb] != i[:, None]) & (j[nb] != j[:, None])
    first = np.argmax(active, axis=1)
    has = active[np.arange(m), first]
    partner[has] = nb[np.arange(m), first][has]
    a = np.flatnonzero(has)
    b = partner[a]
    xi, xj = X[i[a]], X[i[b]]
    yi, yj = Y[j[a]], Y[j[b]]
    # |Vs| = 0 (a half-turn of the two points, or duplicates) makes V · Vs and
    # A × Vs zero: the residual is 0 whatever the division by |Vs| does there
    if votes.structure == "surface":
        # eq41_residual(..., normalize="length") without re-normalising the voted
        # normals (unit to an ulp): dividing by their norm would move the last bits
        V = (yi - xi) - (yj - xj)
        Vs = (yi + xi) - (yj + xj)
        nvs = np.linalg.norm(Vs, axis=1)
        r = np.linalg.norm(np.cross(V, np.cross(votes.normals[a], Vs)), axis=1) / np.where(nvs > 0, nvs, 1.0)
    else:
        r = eq41_length_residual(yi - xi, yi + xi, yj - xj, yj + xj)
    tol = settings.strain * np.linalg.norm(xi - xj, axis=1) + problem.gate
    ratio[a] = r / tol
    return LocalCheck(partner, ratio)


# ------------------------------------------------------------ 4. seeds
def select_seeds(problem: Problem, votes: Votes, check: LocalCheck) -> Seeds:
    """One-to-one selection of the verified tokens by saliency, pruned by the local affine trend.

    A seed whose displacement is off the affine trend of its neighbouring
    seeds by more than 3 median residuals (plus the noise floor) is dropped,
    twice.  On exact data (``problem.auto_gate``) the growth gate is
    tightened to 8 median residuals of the kept seeds: match no wider than
    the seeds' own departure from local affinity.
    """
    ver = np.flatnonzero(check.verified)
    keep = ver[one_to_one(votes.pairs[ver], -votes.saliency[ver])] if ver.size else ver
    seeds = votes.pairs[keep]
    X, Y = problem.source, problem.target
    floor = 1e-9 * problem.spacing + problem.noise_floor
    for _ in range(2):
        res = affine_residuals(X[seeds[:, 0]], Y[seeds[:, 1]] - X[seeds[:, 0]])
        if res.size:
            seeds = seeds[res <= 3.0 * float(np.median(res)) + floor]
    gate = problem.gate
    if problem.auto_gate and seeds.shape[0] >= 5:
        res = affine_residuals(X[seeds[:, 0]], Y[seeds[:, 1]] - X[seeds[:, 0]])
        gate = min(gate, max(8.0 * float(np.median(res)), 1e-6 * problem.spacing))
    return Seeds(seeds[np.argsort(seeds[:, 0], kind="stable")], gate, int(ver.size))


# ------------------------------------------------------------ 5. hypotheses
def voting_hypothesis(problem: Problem, seeds: Seeds, settings: Settings) -> np.ndarray | None:
    """The *voting* hypothesis: the seeds grown ring by ring and polished (or the seeds alone).

    A false seed survives the growth (the warp passes through it): matches
    off the local affine trend of the grown set are dropped and the rest
    re-matched.  ``None`` with fewer than 4 seeds.
    """
    if seeds.pairs.shape[0] < 4:
        return None
    if not settings.grow:
        return seeds.pairs
    X, Y, tree, gate = problem.source, problem.target, problem.tree, seeds.gate
    matched = grow_rings(X, Y, tree, seeds.pairs, gate, settings.neighbours)
    matched = polish(X, Y, tree, matched, gate)
    res = affine_residuals(X[matched[:, 0]], Y[matched[:, 1]] - X[matched[:, 0]])
    if res.size:
        floor = 1e-9 * problem.spacing + problem.noise_floor
        kept = matched[res <= max(gate, 3.0 * float(np.median(res)) + floor)]
        if kept.shape[0] >= 4 and kept.shape[0] < matched.shape[0]:
            matched = polish(X, Y, tree, kept, gate)
    return matched if matched.shape[0] >= 4 else seeds.pairs


def coarse_hypothesis(problem: Problem) -> np.ndarray:
    """The *coarse* hypothesis: coarse-to-fine matching from the identity.

    For a dominant near-identity motion plus a local deformation of about
    the point spacing (the face expressions), whose joint space is one
    dense blob where the voted tokens are mostly wrong, and for piecewise
    rigid motions (a hinge: two separate surfaces in the joint space).
    """
    return coarse_to_fine(problem.source, problem.target, problem.tree, lambda p: p, problem.scale,
                          problem.extent2, problem.noise_floor)


def anneal_hypothesis(problem: Problem, seed: int) -> np.ndarray:
    """The *anneal* hypothesis: nearest targets, within half a target scale, of the annealed warp.

    For displacements of several spacings among many outliers, where the
    hard matching of the coarse levels locks on to wrong targets.
    """
    span = max(median_spacing(problem.source), problem.spacing)
    warp = anneal(problem.source, problem.target, span, seed)
    return match_nearest(warp(problem.source), problem.tree,
                         0.5 * problem.scale + problem.noise_floor).pairs


def wants_rigid_start(settings: Settings, best: str | None) -> bool:
    """Try the *rigid* hypothesis: always with ``prealign=True``; with ``"auto"`` when growing
    and no hypothesis counts or the annealed one wins (it recovers only part of a large
    rigid motion)."""
    return settings.prealign is True or (settings.prealign == "auto" and best in (None, "anneal")
                                         and settings.grow)


@dataclass(frozen=True, eq=False)
class RigidStart:
    """The dominant rigid motion found by :func:`gatv.register` and the matches grown from it."""

    angle_deg: float
    support: int
    pairs: np.ndarray


def rigid_hypothesis(problem: Problem, settings: Settings) -> RigidStart | None:
    """The *rigid* hypothesis: coarse-to-fine matching from the dominant rigid motion.

    For a non-rigid motion on top of a large rigid one, where the true
    surface in the joint space is as sparse as the false tokens.  With
    ``prealign="auto"`` the rigid search is bounded to
    ``AUTO_RIGID_TRIPLES`` source triples.  ``None`` when the rigid mode
    finds nothing.
    """
    bound = None if settings.prealign is True else AUTO_RIGID_TRIPLES
    rigid = rigid_register(problem.source, problem.target, model=settings.model, seed=settings.seed,
                           noise=settings.noise, max_triples=bound, check_rivals=False)
    if not rigid:
        return None
    pairs = coarse_to_fine(problem.source, problem.target, problem.tree, rigid.transform,
                           problem.scale, problem.extent2, problem.noise_floor)
    return RigidStart(rigid.angle_deg, rigid.support, pairs)


@dataclass(frozen=True, eq=False)
class LocalStart:
    """The *local* hypothesis: windows tried, and the grown matches of the best one.

    ``windows`` holds one record per window (its centre row, the rigid
    search's angle and support or the affine patch search's support, chance
    and trials, the grown matches' support and chance).
    """

    pairs: np.ndarray
    windows: tuple


def local_hypothesis(problem: Problem, settings: Settings) -> LocalStart:
    """The *local* hypothesis: rigid registration of local source windows, grown (section 5.1, locally).

    A locally rigid motion with no dominant rigid part (a bar bent through
    60° and turned) puts no large share of the points on one rigid motion,
    so the global rigid start finds a wrong one; but a small window of the
    source moves rigidly.  Windows of ``LOCAL_WINDOW_POINTS`` source points
    (:func:`gatv.nonrigid.hypotheses.window_centres`: densest first, not
    overlapping) are registered against the whole target by
    :func:`gatv.register` (the congruent-triple search, bounded to
    ``AUTO_RIGID_TRIPLES`` triples, its match gate ``LOCAL_GATE`` window
    spacings, or ``3.5 noise`` when larger), their matches grown ring by ring by
    local affine maps (:func:`gatv.nonrigid.hypotheses.grow_rings`, which
    follows the bend) and polished, and the result verified against chance
    (:func:`verify_matches`).  In a placed window (``settings.local_reach``) a patch that no
    rigid motion fits is searched as an affine patch
    (:func:`gatv.nonrigid.affine_patch.affine_patch`: a 4-point affine-invariant base, kept only
    above the support of the other affine fits of the same patch): a warp with a large local
    strain (the bcpd bunny shrinks a 40-row patch by up to 45% along one direction) leaves no
    rigid patch within the rigid search's gate, and an affine one within a tenth of a spacing.
    The first window whose grown matches count
    (as in :func:`choose_hypothesis`) ends the search; otherwise the best
    supported of ``LOCAL_WINDOWS`` windows is returned.  Wrong windows grow
    little: their matches have no consistent continuation.
    """
    X, Y, tree, gate = problem.source, problem.target, problem.tree, problem.verify_gate
    least = max(4, MIN_SHARE * problem.n_smaller)
    k = min(LOCAL_WINDOW_POINTS, X.shape[0])
    _, near = cKDTree(X).query(X, k=k)
    near = near.reshape(X.shape[0], -1)
    best, best_support = np.empty((0, 2), np.int64), -1
    records = []
    for c in window_centres(X, k, LOCAL_WINDOWS):
        patch = near[c]
        record = {"centre": int(c), "support": 0}
        records.append(record)
        tolerance = max(settings.noise or 0.0, LOCAL_GATE * median_spacing(X[patch]) / 3.5)
        near_y = np.arange(Y.shape[0])
        if settings.local_reach is not None:  # a placed window: the patch's partners lie that close
            r = float(np.max(np.linalg.norm(X[patch] - X[c], axis=1)))
            near_y = np.asarray(tree.query_ball_point(X[c], r + settings.local_reach), np.int64)
            record["targets"] = int(near_y.size)
            if near_y.size < 3:
                continue
        try:
            rigid = rigid_register(X[patch], Y[near_y], model=settings.model, seed=settings.seed,
                                   noise=tolerance, max_triples=AUTO_RIGID_TRIPLES, check_rivals=False)
        except ValueError:  # a degenerate window (collinear points)
            rigid = None
        if rigid:
            seeds = np.column_stack([patch[rigid.correspondences[:, 0]], near_y[rigid.correspondences[:, 1]]])
            record.update(angle_deg=round(float(rigid.angle_deg), 2), rigid_support=int(rigid.support))
        elif settings.local_reach is not None:
            # placed rows under a local strain that no rigid patch fits: the affine patch search
            found = affine_patch(X[patch], Y[near_y], gate, settings.strain)
            record.update(affine_support=found.support, affine_chance=round(found.chance, 2),
                          affine_trials=found.trials)
            if found.pairs.shape[0] == 0:
                continue
            seeds = np.column_stack([patch[found.pairs[:, 0]], near_y[found.pairs[:, 1]]])
        else:
            continue
        if seeds.shape[0] < 3:
            continue
        grown = polish(X, Y, tree, grow_rings(X, Y, tree, seeds, gate, settings.neighbours), gate)
        score = verify_matches(problem, grown)
        record.update(support=score.support, chance=round(float(score.chance), 2))
        if score.support > best_support:
            best, best_support = grown, score.support
        if score.support >= least and score.chance <= CHANCE_SHARE * score.support:
            break
    return LocalStart(best, tuple(records))


# ------------------------------------------------------------ 6. verification
def verify_matches(problem: Problem, pairs) -> Score:
    """Local-affine check of each match and the number expected to pass by chance.

    A match passes when its displacement is within the verification gate
    of the affine trend of its neighbouring matches (leave-one-out).  A
    wrong match passes by chance when some target falls within the gate of
    the predicted position: for a surface, with ``n`` targets within the
    verification radius of it, about ``n (gate / radius)²``.  With ``n_w``
    wrong matches among ``K``, ``K − passed ≈ n_w (1 − c̄)``; the chance
    passes are ``n_w c̄``.  Fewer than 5 matches: nothing passes.
    """
    if pairs.shape[0] < 5:
        return Score(0, np.inf, np.zeros(pairs.shape[0], bool))
    gate, radius = problem.verify_gate, problem.verify_radius
    xs, ys = problem.source[pairs[:, 0]], problem.target[pairs[:, 1]]
    ok = affine_residuals(xs, ys - xs) <= gate
    # target density around each match (its own target left out)
    n_near = np.array([len(r) - 1 for r in problem.tree.query_ball_point(ys, radius)], dtype=float)
    c = float(np.clip(np.mean(n_near) * (gate / radius) ** 2, 0.0, 0.99))
    n_wrong = (pairs.shape[0] - ok.sum()) / (1.0 - c)
    return Score(int(ok.sum()), n_wrong * c, ok)


def choose_hypothesis(problem: Problem, hypotheses: dict) -> Verdict:
    """Verify every hypothesis and keep the best supported one that beats chance.

    A hypothesis counts when its chance passes are at most ``CHANCE_SHARE``
    of its support and the support is at least ``MIN_SHARE`` of the smaller
    set (and 4).  The annealed one beats another counted one only with
    ``ANNEAL_PREFERENCE`` times its support: its field is smooth and blurs
    a crease.
    """
    scores = {name: verify_matches(problem, pairs) for name, pairs in hypotheses.items()}
    least = max(4, MIN_SHARE * problem.n_smaller)
    good = [k for k, v in scores.items() if v.support >= least and v.chance <= CHANCE_SHARE * v.support]
    others = [k for k in good if k != "anneal"]
    if others and "anneal" in good:
        top = max(others, key=lambda k: scores[k].support)
        if scores["anneal"].support < ANNEAL_PREFERENCE * scores[top].support:
            good = others
    return Verdict(max(good, key=lambda k: scores[k].support) if good else None, scores)


# ------------------------------------------------------------ 7. fit
def refine_winner(problem: Problem, hypotheses: dict, verdict: Verdict, settings: Settings) -> np.ndarray:
    """The chosen hypothesis's verified matches, grown and re-verified (the voted one is grown already).

    Growth and polish use the verification gate; only the grown matches
    that pass the verification again are kept (when at least 4 do): fewer,
    correct matches rather than many wrong ones.
    """
    best = verdict.best
    matched = hypotheses[best][verdict.scores[best].passed]
    if settings.grow and best != "voting":
        X, Y, tree, gate = problem.source, problem.target, problem.tree, problem.verify_gate
        matched = grow_rings(X, Y, tree, matched, gate, settings.neighbours)
        matched = polish(X, Y, tree, matched, gate)
        ok = verify_matches(problem, matched).passed
        if ok.sum() >= 4:
            matched = matched[ok]
    return matched


def choose_smoothing(points, displacements, seed: int, max_points: int = 600) -> float:
    """Thin-plate smoothing of the warp by 5-fold cross-validation over ``SMOOTHING_GRID``.

    At most ``max_points`` matches (a seeded subsample) enter; fewer than 20
    give 0 (exact interpolation).
    """
    n = points.shape[0]
    if n < 20:
        return 0.0
    rng = np.random.default_rng(seed)
    sub = rng.choice(n, size=min(n, max_points), replace=False)
    Xs, D = points[sub], displacements[sub]
    extent2 = float(np.sum(np.ptp(Xs, axis=0) ** 2)) or 1.0
    folds = np.arange(Xs.shape[0]) % 5
    rng.shuffle(folds)
    best, best_err = 0.0, np.inf
    for rel in SMOOTHING_GRID:
        lam = rel * extent2
        err = 0.0
        for f in range(5):
            test = folds == f
            w = ThinPlateWarp(Xs[~test], D[~test], lam)
            err += float(np.sum((w(Xs[test]) - Xs[test] - D[test]) ** 2))
        if err < best_err * (1 - 1e-9):
            best, best_err = lam, err
    return best


def local_motions(xs, ys, neighbours: int, only=None):
    """Rigid motion (Kabsch/Horn) of each match fitted on its ``neighbours`` nearest matches.

    The local rigidity of section 5.1.  With ``only`` (indices), fit those
    rows only; the others are left as the identity.

    Returns
    -------
    rotations : (K, 3, 3) ndarray
    translations : (K, 3) ndarray
    """
    k = xs.shape[0]
    R, t = np.tile(np.eye(3), (k, 1, 1)), np.zeros((k, 3))
    if k == 0:
        return R, t
    rows = np.arange(k) if only is None else np.asarray(only, dtype=np.int64)
    m = min(neighbours, k)
    _, nb = cKDTree(xs).query(xs[rows], k=m)
    nb = nb.reshape(rows.size, m)
    R[rows], t[rows] = kabsch(xs[nb], ys[nb])
    return R, t


def fit_local_motions(problem: Problem, matched, settings: Settings) -> LocalFit:
    """The warp's smoothing (given, or cross-validated) and each match's local rigid motion."""
    xs, ys = problem.source[matched[:, 0]], problem.target[matched[:, 1]]
    lam = (settings.smoothing if settings.smoothing is not None
           else choose_smoothing(xs, ys - xs, settings.seed))
    R, t = local_motions(xs, ys, settings.neighbours)
    return LocalFit(matched, xs, ys, R, t, lam)
