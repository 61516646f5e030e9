"""The rigid motion model: ``x' = R x R̃ + t`` (paper, sections 2–4).

Trial motions come from congruent point triples (side lengths survive any
rigid motion, :mod:`gatv.models.rigid.congruent`); tokens are the differences
``d = x' - R0 x`` in the ``{dx, dy, dz}`` joint space of eq. 30, where the
true pairs form the dense pure-translation cluster of section 3.4 (a plane
normal to the rotation axis when a residual rotation is left); eq. 41,
``V × (A × Vs) = 0``, checks pairs of tokens.
"""

from __future__ import annotations

import numpy as np

from ..._fit_kernels import neighbourhood_scatter
from ..._validation import as_points, coordinates, shape_hint
from .congruent import TargetIndex, trial_motions
from .congruent_kernels import polish_icp
from ...errors import InputError
from ...fitting import kabsch
from ...ga import eq41_length_residual, eq41_residual
from ...motion import RigidMotion
from ...stats import chance_alpha, chance_support
from ..base import MAX_WORK, NOISY_SCHEDULE, Motion, SearchPolicy, homogeneous, matrix_residuals

__all__ = ["MAX_ENUMERATED", "MODEL", "NOISY_MAX_MATCHES", "RIGID_TRIALS", "WIDE", "Rigid", "check_spread",
           "plane_normal"]

#: Matches scored per source triple in the rigid search (the chance level
#: counts them as tests).  Exact data rarely has more than a few; under noise
#: a triple matches hundreds of target triples and a cap of 64 would mostly
#: drop the true one.
NOISY_MAX_MATCHES = 512
#: Congruent matches listed per source triple, of which the
#: ``NOISY_MAX_MATCHES`` tightest are scored.
MAX_ENUMERATED = 32768
#: Candidate triples drawn for each one matched (:func:`gatv.models.rigid.congruent.trial_motions`'s
#: ``wide``): the one with the fewest expected matches is kept.  Fewer chance
#: matches make both the listing cheaper and the true match rank among the
#: scored tightest more often; the candidates cost a few searches each.
WIDE = 128
#: Options of the rigid model's trial motions in a search (see
#: :func:`gatv.models.rigid.congruent.trial_motions`); the callers add ``min_share``.
RIGID_TRIALS = {"wide": WIDE, "max_enumerated": MAX_ENUMERATED, "sequential": True}

#: The rigid model's search: the tolerances continued to real sensors'
#: noise, which is measured on each motion found; many matches a triple,
#: ranked by wide draws; the symmetry rival and turned copies; the
#: small-motion mode, the scans pipeline and the graph grouping of section 5.
POLICY = SearchPolicy(schedule=NOISY_SCHEDULE, max_matches=NOISY_MAX_MATCHES, trial_options=RIGID_TRIALS,
                      settle_noise=True, max_work=MAX_WORK, rival_check=True, turned_copies=True,
                      small_motion=True, scans=True, graph_grouping=True, merge_motions=True)


def check_spread(points: np.ndarray, name: str, need: str, need_off_line: str | None = None) -> None:
    """Raise when all ``points`` are identical or collinear (no motion is fixed then).

    ``need`` completes the message ("All points of `source` are identical;
    <need>."); ``need_off_line`` the collinear one (default ``need``).
    """
    scale = max(1.0, float(np.abs(points).max()))
    # The centred points' squared singular values are their scatter's eigenvalues, summed in one kernel
    # (one neighbourhood of every point; 2D points on a zero third axis): far above both thresholds
    # (rounding moves them by about n·eps of the largest) the points are spread, and the SVD of the whole
    # centred copy decides only near them.
    p = np.ascontiguousarray(points, dtype=np.float64)
    if p.shape[1] < 3:
        p = np.pad(p, ((0, 0), (0, 3 - p.shape[1])))
    xx, xy, xz, yy, yz, zz = neighbourhood_scatter(p, np.arange(p.shape[0])[None, :], p.shape[0])[1][0]
    lam = np.linalg.eigvalsh(np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]]))
    if lam[-1] > (1e-6 * scale) ** 2 and lam[-2] > 1e-6 * lam[-1]:
        return
    c = points - points.mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False)
    if s[0] <= 1e-12 * scale:
        raise InputError(f"All points of `{name}` are identical; {need}.")
    if s[1] <= 1e-9 * s[0]:
        raise InputError(f"All points of `{name}` are collinear; {need_off_line or need}.")


def check_dimension(points, name: str, dim: int, model: str) -> None:
    """A clear error for points of the wrong dimension for ``model``."""
    shape = np.shape(coordinates(points))  # PyVista, Open3D, trimesh containers alike
    if len(shape) == 2 and shape[1] != dim:
        hint = shape_hint(shape, dim)
        if hint:  # (dim, N): the points are the columns
            raise InputError(f"Expected `{name}` to have shape (N, {dim}) for the {model!r} model, got {shape}{hint}.")
        other = "'affine2d'" if shape[1] == 2 else "'rigid' or 'similarity'"
        msg = (f"Expected `{name}` to have shape (N, {dim}) for the {model!r} model, got {shape}; "
               f"for ({shape[0]}, {shape[1]}) points use model={other}.")
        raise InputError(msg)


#: Planes through three of the points tried by :func:`plane_normal` when the
#: least-squares plane leaves some of them off it.
PLANE_TRIALS = 32


def _least_squares_plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The centroid and unit normal of the least-squares plane through ``points``."""
    c = points.mean(axis=0)
    return c, np.linalg.svd(points - c, full_matrices=False)[2][-1]


def plane_normal(points: np.ndarray, tau: float) -> np.ndarray:
    """Unit normal of the plane most of ``points`` lie on, within ``tau`` (the eq.-30 plane of true tokens).

    The least-squares plane, trimmed once at ``tau``, is the answer when
    every point lies on it.  Otherwise a point far off the plane may have
    tilted it (a chance pair that keeps its length, eq. 41's first half,
    but not the rotation), so planes through three of the points
    (:data:`PLANE_TRIALS`, drawn with a seed fixed by the input's size)
    compete with it, and the one with the most points within ``tau`` is
    refitted by least squares on those points, as the paper detects the
    plane by its tokens rather than fitting all of them.
    """
    c, n = _least_squares_plane(points)
    near = np.abs((points - c) @ n) <= tau
    if 3 <= near.sum() < len(points):
        c, n = _least_squares_plane(points[near])
        near = np.abs((points - c) @ n) <= tau
    if near.all() or len(points) < 4:
        return n
    rng = np.random.default_rng(len(points))
    triples = np.array([rng.choice(len(points), 3, replace=False) for _ in range(PLANE_TRIALS)])
    a, b, e = points[triples[:, 0]], points[triples[:, 1]], points[triples[:, 2]]
    normals = np.cross(b - a, e - a)
    length = np.linalg.norm(normals, axis=1)
    good = length > 0
    if not good.any():
        return n
    normals, a = normals[good] / length[good, None], a[good]
    on = np.abs(points @ normals.T - np.einsum("ij,ij->i", a, normals)) <= tau
    best = int(np.argmax(on.sum(axis=0)))
    if on[:, best].sum() <= near.sum() or on[:, best].sum() < 3:
        return n
    return _least_squares_plane(points[on[:, best]])[1]


def eq41_consistent(d: np.ndarray, s: np.ndarray, pairs: np.ndarray, ref: int,
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
    r = eq41_length_residual(d, s, d[ref], s[ref])
    same = (pairs[:, 0] == pairs[ref, 0]) ^ (pairs[:, 1] == pairs[ref, 1])
    cons = np.union1d(np.flatnonzero((r <= tau) & ~same), [ref])
    if cons.size < 4:
        return cons
    axis = plane_normal(d[cons], tau)
    r = eq41_residual(d[cons], s[cons], d[ref], s[ref], axis, normalize="length")
    return np.union1d(cons[r <= tau], [ref])


class Rigid:
    """Rotation and translation in 3D: 3-point samples, 6 degrees of freedom."""

    name = "rigid"
    dim = 3
    sample_size = 3
    n_params = 6

    def __repr__(self) -> str:
        return "Rigid()"

    # ------------------------------------------------------------ input
    def check_points(self, points, name: str) -> np.ndarray:
        """(N, 3) float64 points, at least 3, not all identical or collinear."""
        check_dimension(points, name, self.dim, self.name)
        p = as_points(points, name, min_points=self.sample_size)
        check_spread(p, name, "a rigid motion needs 3 non-collinear points")
        return p

    # -------------------------------------------------------------- fit
    def fit(self, source: np.ndarray, target: np.ndarray, weights=None) -> np.ndarray:
        """Kabsch/Horn least squares, as a 4×4 matrix."""
        R, t = kabsch(source, target, weights)
        return homogeneous(R, t)

    def residuals(self, matrix: np.ndarray, source: np.ndarray, target: np.ndarray) -> np.ndarray:
        return matrix_residuals(matrix, source, target)

    # ----------------------------------------------------------- trials
    def index(self, target: np.ndarray, radius: float, *, memory_budget=None):
        """The target's pair-length table and scoring grid (:class:`gatv.models.rigid.congruent.TargetIndex`)."""
        return TargetIndex(target, radius, memory_budget=memory_budget)

    def polish_motions(self, source: np.ndarray, index, rotations, translations, iterations: int, *,
                       extent: float, spacing: float):
        """Each motion polished by ICP within ``index.radius`` on the index's scoring grid.

        :func:`gatv.stages.refine`'s steps (nearest target, one-to-one cheapest
        first, Kabsch refit, until the pairs repeat or the motion stops moving)
        for every motion at once, in parallel (:func:`gatv.models.rigid.congruent_kernels.polish_icp`).
        Returns ``(rotations, translations, supports)``; a motion that never had
        ``sample_size`` targets within the gate is returned as it was, support 0.
        """
        R0 = np.ascontiguousarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
        t0 = np.ascontiguousarray(translations, dtype=np.float64).reshape(-1, 3)
        R, t, support = polish_icp(np.ascontiguousarray(source, dtype=np.float64), index.target, index.start,
                                   index.order, index.origin, float(index.cell), index.dims, R0, t0,
                                   float(index.radius), int(iterations), float(extent), float(spacing))
        return R, t, np.maximum(support, 0)

    def trial_motions(self, source: np.ndarray, index, **options):
        """Trial motions from congruent triples (:func:`gatv.models.rigid.congruent.trial_motions`)."""
        return trial_motions(source, index, **options)

    # ----------------------------------------------------------- tokens
    def tokens(self, source: np.ndarray, target: np.ndarray) -> np.ndarray:
        """``{dx, dy, dz}`` of eq. 30: ``d = x' - x`` (``x`` already trial-rotated)."""
        return target - source

    def consistent(self, tokens, ref: int, tau: float) -> np.ndarray:
        """Eq. 41 against token ``ref`` (:func:`eq41_consistent`)."""
        xs, ys = tokens.source_points, tokens.target_points
        return eq41_consistent(ys - xs, ys + xs, tokens.pairs, ref, tau)

    def chance(self, n_source: int, n_target: int, measure: float, gate: float,
               n_tests: float = 1.0) -> int:
        return chance_support(n_source, n_target, measure, gate, n_tests=n_tests, dim=3,
                              sample_size=self.sample_size)

    def chance_alpha(self, support: int, n_source: int, n_target: int, measure: float, gate: float,
                     n_tests: float = 1.0) -> float:
        """The smallest family-wise level at which ``support`` reaches :meth:`chance`."""
        return chance_alpha(support, n_source, n_target, measure, gate, n_tests, dim=3,
                            sample_size=self.sample_size)

    # ----------------------------------------------------------- result
    def result(self, matrix: np.ndarray, correspondences: np.ndarray, *, score: float,
               rms: float, info: dict) -> Motion:
        return RigidMotion(matrix[:3, :3], matrix[:3, 3], correspondences, score, rms, info)

    def search_policy(self) -> SearchPolicy:
        """:data:`POLICY`."""
        return POLICY


MODEL = Rigid()
