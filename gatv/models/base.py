"""The motion-model seam and the result base shared by every motion.

A motion model tells the pipeline of :mod:`gatv.stages` everything that
depends on the kind of motion (paper, sections 2–5):

* its size: point dimension ``dim``, minimal sample ``sample_size``,
  degrees of freedom ``n_params``;
* the least-squares ``fit`` of weighted correspondences and the
  ``residuals`` of pairs under a motion;
* ``trial_motions``: hypotheses from *invariant* samples (side lengths for
  rigid motions, side-length ratios for similarities, area ratios for 2D
  affine maps), scored by a density test;
* ``tokens``: the joint-space coordinates tensor voting works on
  (``{dx, dy, dz}`` of eq. 30 for rigid motions; ``(x, y, x')`` and
  ``(x, y, y')`` for Kang's 2D affine motions);
* ``consistent``: the pairwise constraint between tokens (eq. 41 for rigid
  motions, its analogue for the others);
* ``chance``: the support a random motion collects;
* ``result``: the frozen result object.

Optional hooks, read with ``getattr`` where a model needs them:
``joint_spaces(source, target)`` (several 3D joint spaces to vote in, as
Kang's two for 2D affine motions; :func:`gatv.stages.vote_tokens`),
``trial_sample_size`` (points per trial sample when it exceeds
``sample_size``, for the RANSAC bound) and ``sample_space(n)`` (distinct
samples among ``n`` points); :func:`gatv.motions.peel` reads the last two;
``changes_scale`` (true when the motion scales: :func:`gatv.stages.prepare`
then measures the spacing in the target alone) and ``triple_cost(m)``
(work units of one trial sample against ``m`` targets, for the round robin
of :func:`gatv.register`); ``polish_motions(source, index, rotations,
translations, iterations, extent=, spacing=)`` (the ICP polish of many trial
motions at once on the model's index: :func:`gatv.stages.polish_trials`).

How the pipelines search for a model's motions (tolerance schedule, match
cap, trial options, noise settling, rival check, which paths apply) is the
model's :class:`SearchPolicy`, from ``search_policy()``.

Every motion is carried between stages as its ``(dim + 1) × (dim + 1)``
homogeneous matrix ``T``: ``target ≈ source @ T[:d, :d].T + T[:d, d]``.
See ``docs/extending.md`` for a worked example (the 2D affine model).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, ClassVar, Mapping, Protocol, runtime_checkable

import numpy as np

from .._validation import as_points, frozen_array
from ..errors import InputError
from ..ga import Rotor, rotation_angle_deg

if TYPE_CHECKING:  # pragma: no cover
    from .rigid.congruent import TrialMotions
    from ..stages import Tokens

__all__ = ["MAX_MATCHES", "MAX_WORK", "NOISE_SCHEDULE", "NOISY_SCHEDULE", "MotionModel", "Motion",
           "Rotational", "SearchPolicy", "freeze_fields", "homogeneous", "split_matrix", "apply_matrix",
           "matrix_residuals"]

#: Tolerances tried when the noise is not given, relative to the point spacing.
NOISE_SCHEDULE = (1e-6, 1e-3, 1e-2, 0.05)

#: :data:`NOISE_SCHEDULE` continued to the noise of real sensors: a few
#: percent of an object's size is a sizeable share of its point spacing.
#: Beyond about a third of the spacing a point's true partner is no longer
#: distinguishable from its neighbours.  Steps of about 2.5: a level at or
#: above the data's noise finds the motion, and
#: :func:`gatv.stages.settle_noise` then measures the noise itself.
NOISY_SCHEDULE = NOISE_SCHEDULE + (0.12, 0.3)

#: Best model matches scored per trial sample (:func:`gatv.stages.search`'s default).
MAX_MATCHES = 64

#: Default work bound of a search, in the search's work units (about a
#: microsecond of CPU each, :func:`gatv.stages.chunk_work`): a call fails
#: with a reason instead of running on, after about 100 s of CPU, under a
#: minute on two cores.  Deterministic: the same seed stops at the same point.
MAX_WORK = 1e8


@dataclass(frozen=True)
class SearchPolicy:
    """How the pipelines search for a model's motions (:meth:`MotionModel.search_policy`).

    Every choice the searches of :func:`gatv.register`,
    :func:`gatv.motions.segment` and :func:`gatv.motions.peel` make by the
    kind of motion is read here; no module outside :mod:`gatv.models`
    branches on a model's name.  The defaults are those of a model with no
    tuning of its own (the similarity and 2D affine models).

    Attributes
    ----------
    schedule : tuple of float
        Tolerances a search tries when the noise is not given, relative to
        the point spacing (:data:`NOISE_SCHEDULE`; the rigid model goes on
        to real sensors' noise, :data:`NOISY_SCHEDULE`).
    max_matches : int
        Matches scored per trial sample (:data:`MAX_MATCHES`; the chance
        level counts them as tests).
    trial_options : mapping
        Options of the model's ``trial_motions`` for samples that list many
        matches (:func:`gatv.stages.search`'s ``trial_options``); the
        callers add ``min_share`` (the smallest motion wanted, a share of
        the source).  Empty: none.
    settle_noise : bool
        Noise not given: measure it on a found motion and re-gate its pairs
        there (:func:`gatv.stages.settle_noise`), and peel several motions
        with the noise-aware search (:func:`gatv.motions.peel`'s
        ``noisy``).  False: grow the tolerance while the support grows
        beyond chance (:func:`gatv.stages.grow_tolerance`).
    max_work : float or None
        Work bound of each round of a noise-aware peel (None: none).
    rival_check : bool
        Look for a distinct motion explaining the found pairs nearly as
        well (a symmetric set, :func:`gatv.registration.symmetry_rival`).
    turned_copies : bool
        Hold each motion found on point sets against its turned and
        shifted copies (:func:`gatv.registration.rival_draws`; 2D or 3D):
        ``register`` reports no motion and ``segment`` drops one that a
        copy explains alike (two unrelated sets with shared structure).
    small_motion : bool
        ``register``'s small-motion mode (``max_angle``) applies.
    scans : bool
        The scans pipeline (:mod:`gatv.scans`) registers this model's
        motions; ``pipeline="auto"`` then chooses from the data.
    graph_grouping : bool
        :func:`gatv.motions.segment` groups the tokens of several motions
        by the eq.-41 graph in the eq.-30 joint space (section 5); False:
        it peels one motion at a time.
    merge_motions : bool
        A noise-aware peel joins two motions that are one
        (:func:`gatv.motions.peeling.merge_same_motions`).
    moment_prealign : bool
        :func:`gatv.nonrigid.register`'s pre-alignment falls back to
        principal axes and similarity ICP when the search finds no motion.
    """

    schedule: tuple[float, ...] = NOISE_SCHEDULE
    max_matches: int = MAX_MATCHES
    trial_options: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    settle_noise: bool = False
    max_work: float | None = None
    rival_check: bool = False
    turned_copies: bool = False
    small_motion: bool = False
    scans: bool = False
    graph_grouping: bool = False
    merge_motions: bool = False
    moment_prealign: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "schedule", tuple(float(r) for r in self.schedule))
        object.__setattr__(self, "trial_options", MappingProxyType(dict(self.trial_options)))

    def __hash__(self) -> int:
        return hash((self.schedule, self.max_matches, tuple(sorted(self.trial_options.items())),
                     self.settle_noise, self.max_work, self.rival_check, self.turned_copies, self.small_motion,
                     self.scans, self.graph_grouping, self.merge_motions, self.moment_prealign))

    def trials(self, min_share: float) -> dict | None:
        """:attr:`trial_options` with ``min_share`` added, or None when the model has none."""
        if not self.trial_options:
            return None
        return dict(self.trial_options, min_share=min_share)


#: The policy of a model with no tuning of its own.
DEFAULT_POLICY = SearchPolicy()


def homogeneous(linear, translation) -> np.ndarray:
    """The ``(d + 1) × (d + 1)`` matrix of ``x -> linear @ x + translation``."""
    A = np.asarray(linear, dtype=np.float64)
    d = A.shape[0]
    T = np.eye(d + 1)
    T[:d, :d] = A
    T[:d, d] = np.asarray(translation, dtype=np.float64).reshape(d)
    return T


def split_matrix(matrix) -> tuple[np.ndarray, np.ndarray]:
    """``(linear, translation)`` of a homogeneous matrix (views, not copies)."""
    d = matrix.shape[-1] - 1
    return matrix[..., :d, :d], matrix[..., :d, d]


def apply_matrix(matrix, points: np.ndarray) -> np.ndarray:
    """``points @ A.T + t`` for the homogeneous matrix ``[[A, t], [0, 1]]``."""
    A, t = split_matrix(matrix)
    return points @ A.T + t


def matrix_residuals(matrix, source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(K,) distances ``|target - T(source)|`` of paired rows under a homogeneous matrix."""
    return np.linalg.norm(target - apply_matrix(matrix, source), axis=1)


def freeze_fields(obj, **shapes: tuple[int, ...]) -> None:
    """Validate and freeze array fields of a frozen dataclass in ``__post_init__``.

    ``shapes`` maps a field name to its shape; a 1-D shape accepts any array
    with that many entries.  ``correspondences`` is always frozen as (K, 2)
    integers.

    Raises
    ------
    InputError
        A field of the wrong shape, naming it.
    """
    for name, shape in shapes.items():
        a = np.asarray(getattr(obj, name), dtype=np.float64)
        if len(shape) == 1:
            a = a.reshape(-1)
        if a.shape != shape:
            raise InputError(f"Expected `{name}` to have shape {shape}, got {a.shape}.")
        object.__setattr__(obj, name, frozen_array(a))
    pairs = np.asarray(obj.correspondences, dtype=np.int64).reshape(-1, 2)
    object.__setattr__(obj, "correspondences", frozen_array(pairs, np.int64))


@runtime_checkable
class MotionModel(Protocol):
    """What the pipeline needs to know about a kind of motion.

    Implementations: :class:`gatv.models.Rigid`,
    :class:`gatv.models.Similarity`, :class:`gatv.models.Affine2D`.
    """

    #: Name used by ``model=`` arguments ("rigid", "similarity", "affine2d").
    name: str
    #: Dimension of the points (3 for rigid and similarity, 2 for affine2d).
    dim: int
    #: Smallest number of correspondences that fixes a motion.
    sample_size: int
    #: Degrees of freedom of the motion.
    n_params: int

    def check_points(self, points, name: str) -> np.ndarray:
        """Validated (N, dim) float64 points; the error names ``name`` and the fix."""

    def fit(self, source: np.ndarray, target: np.ndarray, weights=None) -> np.ndarray:
        """Least-squares motion of paired (K, dim) rows, as a homogeneous matrix."""

    def residuals(self, matrix: np.ndarray, source: np.ndarray, target: np.ndarray) -> np.ndarray:
        """(K,) distances ``|target - T(source)|`` of paired rows."""

    def index(self, target: np.ndarray, radius: float, *, memory_budget=None) -> Any:
        """What :meth:`trial_motions` looks target samples up in.

        It has ``radius`` and ``volume`` (the measure random motions scatter
        points over), ``set_radius(r)`` and survives ``copy.copy``.
        """

    def trial_motions(self, source: np.ndarray, index: Any, *, eps: float, max_triples: int,
                      rng: np.random.Generator, keep: int, max_matches: int,
                      accept: int | None, **options: Any) -> TrialMotions:
        """Hypotheses from invariant samples, ranked by their density-test support."""

    def tokens(self, source: np.ndarray, target: np.ndarray) -> np.ndarray:
        """(T, 3) joint-space coordinates of paired rows (source already trial-moved)."""

    def consistent(self, tokens: Tokens, ref: int, tau: float) -> np.ndarray:
        """Indices of the tokens consistent with token ``ref`` (eq. 41 or its analogue)."""

    def chance(self, n_source: int, n_target: int, measure: float, gate: float,
               n_tests: float = 1.0) -> int:
        """Support a random motion collects within ``gate`` (family-wise over ``n_tests``)."""

    def result(self, matrix: np.ndarray, correspondences: np.ndarray, *, score: float,
               rms: float, info: dict) -> Motion:
        """The frozen result of this model."""

    def search_policy(self) -> SearchPolicy:
        """How the pipelines search for this model's motions (``SearchPolicy()``: the defaults)."""


class Motion:
    """Base of the motion results: a frozen value with its correspondences.

    Subclasses are frozen dataclasses (``eq=False``) with fields
    ``correspondences``, ``score``, ``rms`` and ``info``, and define
    :attr:`matrix` and :meth:`from_matrix`.

    Attributes
    ----------
    matrix : (d + 1, d + 1) ndarray
        Homogeneous transform, ``target ≈ T @ [source, 1]``.
    correspondences : (K, 2) ndarray of int
        One-to-one ``(source index, target index)`` pairs.
    support : int
        Number of correspondences.
    info : dict
        Diagnostics; ``info["reason"]`` on failure (the result is falsy).
    """

    #: Model name of the result ("rigid", "similarity", "affine2d").
    model: ClassVar[str] = ""

    correspondences: np.ndarray
    score: float
    rms: float
    info: dict

    # -------------------------------------------------------- to define
    @property
    def matrix(self) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    @classmethod
    def from_matrix(cls, matrix, correspondences=None, *, score: float = 0.0,
                    rms: float = float("nan"), info: dict | None = None) -> Motion:  # pragma: no cover
        raise NotImplementedError

    # ----------------------------------------------------------- shared
    @property
    def dim(self) -> int:
        """Dimension of the points moved."""
        return int(self.matrix.shape[0] - 1)

    @property
    def support(self) -> int:
        return int(self.correspondences.shape[0])

    def __bool__(self) -> bool:
        return self.support > 0

    def as_matrix(self) -> np.ndarray:
        """The homogeneous matrix, ``p_target = T @ [p_source, 1]`` (a copy)."""
        return np.array(self.matrix)

    def transform(self, points) -> np.ndarray:
        """Move source points: ``points @ A.T + t``."""
        p = as_points(points, "points", min_points=0, dim=self.dim)
        return apply_matrix(self.matrix, p)

    def inverse(self) -> Motion:
        """The motion from target to source, with swapped correspondences."""
        return type(self).from_matrix(np.linalg.inv(self.matrix), self.correspondences[:, ::-1],
                                      score=self.score, rms=self.rms, info=dict(self.info))

    def to_dict(self) -> dict:
        """JSON-friendly dictionary (``matrix`` row-major, as Open3D writes it)."""
        out = {
            "model": self.model,
            "matrix": self.matrix.tolist(),
            "correspondences": self.correspondences.tolist(),
            "support": self.support,
            "score": float(self.score),
            "rms": float(self.rms),
        }
        if not self and "reason" in self.info:
            out["reason"] = str(self.info["reason"])
        return out



class Rotational:
    """What every motion with ``rotation`` (3×3) and ``translation`` fields offers."""

    rotation: np.ndarray
    translation: np.ndarray

    @property
    def rotor(self) -> np.ndarray:
        """``(q0, qx, qy, qz)`` of the rotor ``R = q0 + qx e23 + qy e31 + qz e12``."""
        return Rotor.from_matrix(self.rotation).q.copy()

    @property
    def angle_deg(self) -> float:
        """Rotation angle in degrees."""
        return rotation_angle_deg(self.rotation)

    def rotation_dict(self) -> dict:
        """The JSON entries of a motion with a rotation: rotation, translation, rotor, angle."""
        return {
            "rotation": self.rotation.tolist(),
            "translation": self.translation.tolist(),
            "rotor": self.rotor.tolist(),
            "angle_deg": self.angle_deg,
        }
