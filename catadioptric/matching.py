"""Corner correspondences between two catadioptric images, on the unit sphere.

The catadioptric example of Reyes, Medioni & Bayro (IJCV 2007, end of
section 5.1, Fig. 15): the corners of both images are lifted to the unit
sphere of the unified camera model, and the corresponding corners are found
as a structure in the joint space of candidate pairs. This module holds the
entry point :func:`match`, its result :class:`SphereMatch` and the
orchestration of the stages, which live in their own modules:

* :mod:`catadioptric.rotation`: the dominant rotation and locally rigid growth;
* :mod:`catadioptric.epipolar`: the motion (R, t) and matching along epipolar arcs;
* :mod:`catadioptric.acceptance`: posteriors, the chance level, rivals;
* :mod:`catadioptric.plane` and :mod:`catadioptric.peeling`: a plane moved
  rigidly (a homography of the sphere) and every further motion;
* :mod:`catadioptric.voting`: the paper's tensor-voting surface
  (``strategy="voting"``);
* :mod:`catadioptric.constants`: the tuning constants, each explained.

How it works
------------
1. **Lift.** Both pixel sets are lifted to unit rays; pixels the camera
   cannot lift (outside the mirror's disc, NaN rows) are dropped, and the
   index maps back to the input rows are kept. Each ray gets its own noise
   level, ``noise_px`` times the lifting's Jacobian at that pixel
   (:func:`sphere_noise`: the sphere noise of a 1-pixel error is largest
   at the image centre, ``(1 + xi) / f``, and falls towards the rim).
2. **Dominant rotation.** A pure camera rotation moves the rays rigidly
   about the centre of the sphere, ``y = R x``: the densest cluster of the
   trial rotations of matched local triangles, polished by rotation-only
   ICP inside the per-pair noise gate (:mod:`catadioptric.rotation`).
3. **Rigid or locally rigid.** The rotation's support is compared with the
   chance level of the sphere (a wrong rotation brings a ray within the
   gate of a target ray with probability ``n2 π gate² / area``,
   :func:`gatv.stats.chance_support`); when it explains nearly all rays
   (``rigid_share``) it is the answer; its pairs are kept when their
   posterior against a chance ray reaches ``MIN_POSTERIOR``
   (:func:`catadioptric.acceptance.rigid_posterior`). With a camera
   translation the rays move non-rigidly (parallax ``t⊥ / depth``), only
   locally rigidly: each ray is moved by the rotation of its nearest
   matched neighbours, grown from the rotation's pairs or from the
   vertices of a wider cluster of triangle rotations ("local").
4. **Epipolar geometry.** True pairs satisfy ``y · (t × R x) = 0``: a
   motion (R, t) from LO-RANSAC on matched triangles, and the rays matched
   along their epipolar arcs at the inverse depth of their matched
   neighbours, each match kept when its posterior reaches
   ``MIN_POSTERIOR`` (:mod:`catadioptric.epipolar`). Without parallax (a
   pure rotation, ``t`` undefined) the stage stands aside. The epipolar
   result is kept when it explains clearly more pairs than the rotation
   (``nonrigid_gain``) and beats the chance level. ``strategy="nonrigid"``
   instead extracts the curved surface of the tokens ``y_j − R x_i`` with
   tensor voting and local eq. 41 (:func:`gatv.nonrigid.register`).
5. **Ambiguity (repeated structure).** A regular pattern, such as a
   checkerboard, also matches itself shifted by one period, as rigidly
   and as epipolarly as the true matching. The winning matches are
   shifted by the vector from a matched target ray to one of its
   neighbours and grown locally rigidly
   (:func:`catadioptric.acceptance.rival`); when the rival's pairs with
   other partners reach ``RIVAL_RATIO`` of the winner's support, and the
   chance level, the result is empty with ``info["reason"]`` "ambiguous
   (repeated structure) ...": nothing tells which of the two is right,
   and precision comes first. The threshold and its margins: see
   :data:`catadioptric.constants.RIVAL_RATIO` and docs/design-notes.md
   (catadioptric). With ``strategy="auto"`` the plane stage then compares
   whole-pattern supports (step 6): a pattern on a plane seen whole in
   both views is resolved, ``info["resolved"]`` says so.
6. **Every motion.** The rays the motions so far leave unexplained are
   searched for a plane moved rigidly (:mod:`catadioptric.plane`: local
   quadruples matched by affine signature, grown homographies, rivals of a
   repeated pattern compared by whole-pattern support), kept when it beats
   the chance level of those rays and is not more of an earlier motion,
   again until ``max_motions`` (:func:`catadioptric.peeling.peel`, the
   peeling of section 5 on the sphere). :attr:`SphereMatch.motions` lists
   them, the dominant first; ``correspondences`` is their union.

Motion convention: a scene point seen along ray ``x`` in view 1 is seen
along ``y ≈ R x`` in view 2 (pure rotation), ``y ∝ R X + t`` in general
(``X = d x`` the point in view 1's frame, the convention of
:func:`catadioptric.synthetic_views`).
"""

from __future__ import annotations

import math
import numbers
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from catadioptric.acceptance import cap_area, rigid_posterior, rival
from catadioptric.camera import UnifiedCamera
from catadioptric.constants import (
    CHANCE_ALPHA,
    GATE_SIGMAS,
    RIVAL_RATIO,
    WIDE_CLUSTER_FACTOR,
)
from catadioptric.epipolar import epipolar_stage, essential_from_motion
from catadioptric.peeling import SphereMotion, peel
from catadioptric.rotation import (
    dominant_rotation,
    grow_local,
    rotation_icp,
    voted_seeds,
)
from catadioptric.voting import voting_stage
from gatv.validation import as_rng, check_progress, file_hint, seed_int
from gatv.validation import frozen_array as _frozen
from gatv.errors import InputError
from gatv.motion import rotation_angle_deg
from gatv.stats import chance_support
from gatv.verdict import chance_verdict

if TYPE_CHECKING:
    from numpy.typing import ArrayLike, NDArray

__all__ = ["STRATEGIES", "SphereMatch", "SphereMotion", "match", "sphere_noise"]

#: The values of ``match``'s ``strategy``.
STRATEGIES = ("auto", "rigid", "local", "epipolar", "nonrigid", "voting")




@dataclass(frozen=True, eq=False)
class SphereMatch:
    """Corner correspondences between two catadioptric views.

    All arrays are read-only. The result is falsy when nothing was matched
    (``info["reason"]`` says why).

    Attributes
    ----------
    correspondences : (K, 2) ndarray of int
        One-to-one pairs ``(i, j)`` of rows of ``pixels1`` and ``pixels2``
        (the input rows), sorted by ``i``.
    rays1, rays2 : (M1, 3), (M2, 3) ndarray of float
        Unit rays of the pixels that could be lifted.
    index1, index2 : (M1,), (M2,) ndarray of int
        Input row of each ray: ``rays1[k]`` is ``pixels1[index1[k]]``.
    rotation : (3, 3) ndarray of float or None
        Camera rotation ``R`` (view 1 rays to view 2 rays). For the
        ``"epipolar"`` strategy the rotation of the recovered motion
        ``y ∝ d R x + t``; otherwise the dominant pure rotation ``y ≈ R x``
        when its support beats the chance level of the sphere, else None
        (None too when the match is ambiguous, ``info["reason"]``).
    rotation_support : int
        Pairs within the noise gate of the pure rotation ``y ≈ R x``
        (one-to-one; 0 when no rotation beat the chance level).
    strategy : {"rigid", "local", "epipolar", "nonrigid", "voting", "plane", "none"}
        Which stage gave ``correspondences``.
    noise : float
        Median sphere noise of the rays (unit-sphere units, per axis).
    info : dict
        Diagnostics: chance level, supports of the stages, timings.
    translation : (3,) ndarray of float or None
        Unit direction of the translation ``t`` in ``X2 = R X1 + t`` (the
        epipole of view 1's centre in view 2) for the ``"epipolar"``
        strategy; None otherwise (also for a pure rotation, where ``t``
        is not defined).
    motions : tuple of SphereMotion
        Every motion found, the dominant one first, each with its own
        correspondences, rotation and translation direction (a plane moved
        rigidly also has its homography); :attr:`correspondences` is their
        union. ``rotation``, ``translation`` and ``strategy`` above are the
        first motion's.
    """

    correspondences: NDArray[np.int64]
    rays1: NDArray[np.float64]
    rays2: NDArray[np.float64]
    index1: NDArray[np.int64]
    index2: NDArray[np.int64]
    rotation: NDArray[np.float64] | None
    rotation_support: int
    strategy: str
    noise: float
    info: dict = field(default_factory=dict)
    translation: NDArray[np.float64] | None = None
    motions: tuple = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "motions", tuple(self.motions))
        object.__setattr__(self, "correspondences",
                           _frozen(np.asarray(self.correspondences).reshape(-1, 2), np.int64))
        for name in ("rays1", "rays2"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))
        for name in ("index1", "index2"):
            object.__setattr__(self, name, _frozen(getattr(self, name), np.int64))
        for name in ("rotation", "translation"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, _frozen(getattr(self, name)))

    @property
    def support(self) -> int:
        """int: number of correspondences."""
        return int(self.correspondences.shape[0])

    def __bool__(self) -> bool:
        return self.support > 0

    @property
    def angle_deg(self) -> float | None:
        """float or None: angle of :attr:`rotation` in degrees (None without a rotation).

        The name the result classes of gatv share
        (:func:`gatv.motion.rotation_angle_deg`).
        """
        if self.rotation is None:
            return None
        return rotation_angle_deg(self.rotation)

    @property
    def rotation_deg(self) -> float | None:
        """float or None: :attr:`angle_deg`, under the name of the command line's output."""
        return self.angle_deg

    @property
    def essential(self) -> NDArray[np.float64] | None:
        """(3, 3) ndarray or None: essential matrix ``E = [t]x R``, ``y^T E x = 0`` for true pairs."""
        if self.translation is None or self.rotation is None:
            return None
        return essential_from_motion(self.rotation, self.translation)

    def to_dict(self) -> dict:
        """JSON-serialisable summary (correspondences as lists of input rows)."""
        return {
            "strategy": self.strategy,
            "support": self.support,
            "correspondences": self.correspondences.tolist(),
            "rotation": None if self.rotation is None else self.rotation.tolist(),
            "rotation_deg": self.rotation_deg,
            "rotation_support": int(self.rotation_support),
            "translation": None if self.translation is None else self.translation.tolist(),
            "essential": None if self.translation is None else self.essential.tolist(),
            "noise": self.noise,
            "n_rays1": int(self.rays1.shape[0]),
            "n_rays2": int(self.rays2.shape[0]),
            "motions": [m.to_dict() for m in self.motions],
        }


# --------------------------------------------------------------- validation
def _check_pixels(pixels, name: str) -> NDArray[np.float64]:
    """``pixels`` as an (N, 2) float64 array (NaN rows allowed: they are dropped, rows kept)."""
    if pixels is None:
        msg = f"Expected `{name}` to be an (N, 2) array of pixels, got None."
        raise InputError(msg)
    hint = file_hint(pixels, 2)
    if hint is not None:
        raise InputError(f"Expected `{name}` to be an (N, 2) array of pixels, got the path {str(pixels)!r}; {hint}.")
    try:
        arr = np.asarray(pixels, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        msg = f"Expected `{name}` to be an (N, 2) array of numbers: {exc}."
        raise InputError(msg) from exc
    if arr.ndim != 2 or arr.shape[1] != 2:
        msg = f"Expected `{name}` to have shape (N, 2), got {arr.shape}."
        raise InputError(msg)
    return np.ascontiguousarray(arr)


def _check_camera(camera, name: str) -> UnifiedCamera:
    if not isinstance(camera, UnifiedCamera):
        msg = f"Expected `{name}` to be a catadioptric.UnifiedCamera, got {type(camera).__name__}."
        raise InputError(msg)
    return camera


def _check_real(value, name: str, *, low: float = 0.0, allow_zero: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        msg = f"Expected `{name}` to be a finite number, got {value!r}."
        raise InputError(msg)
    value = float(value)
    if value < low or (value == low and not allow_zero):
        msg = f"Expected `{name}` {'>=' if allow_zero else '>'} {low}, got {value!r}."
        raise InputError(msg)
    return value


# --------------------------------------------------------------- lifting
def _lift(camera: UnifiedCamera, pixels: NDArray[np.float64]):
    finite = np.all(np.isfinite(pixels), axis=1)
    rays = np.full((pixels.shape[0], 3), np.nan)
    valid = np.zeros(pixels.shape[0], dtype=bool)
    if finite.any():
        r, ok = camera.lift(pixels[finite], return_mask=True)
        rays[finite] = r
        valid[finite] = ok
    index = np.flatnonzero(valid)
    return rays[index], index


def sphere_noise(camera: UnifiedCamera, pixels: ArrayLike, noise_px: float = 1.0) -> NDArray[np.float64]:
    """Per-axis sphere noise of rays lifted from pixels with ``noise_px`` noise.

    The lifting's Jacobian is taken by central differences (0.5 px); the
    result is ``noise_px`` times the root-mean-square of its two columns
    (the ray's displacement per pixel along ``u`` and ``v``).

    Parameters
    ----------
    camera : UnifiedCamera
    pixels : (N, 2) array_like of float
        Pixels that the camera can lift.
    noise_px : float, default: 1.0
        Pixel noise, standard deviation per coordinate.

    Returns
    -------
    (N,) ndarray of float
        At the image centre ``noise_px (1 + xi) / f`` for an undistorted
        camera.

    Examples
    --------
    >>> cam = UnifiedCamera(1.0, 300.0, 300.0, 640.0, 512.0)
    >>> round(float(sphere_noise(cam, [[640.0, 512.0]])[0] * 300.0), 3)
    2.0
    """
    pix = _check_pixels(pixels, "pixels")
    h = 0.5
    cols = []
    for du, dv in ((h, 0.0), (0.0, h)):
        plus, ok1 = camera.lift(pix + [du, dv], return_mask=True)
        minus, ok2 = camera.lift(pix - [du, dv], return_mask=True)
        d = np.linalg.norm(plus - minus, axis=1) / (2.0 * h)
        fallback = (1.0 + camera.xi) / min(camera.fx, camera.fy)
        cols.append(np.where(ok1 & ok2 & np.isfinite(d), d, fallback))
    return noise_px * np.sqrt(0.5 * (cols[0] ** 2 + cols[1] ** 2))


# --------------------------------------------------------------- entry point
def match(
    pixels1: ArrayLike,
    pixels2: ArrayLike,
    camera1: UnifiedCamera,
    camera2: UnifiedCamera | None = None,
    *,
    noise_px: float = 1.0,
    strategy: str = "auto",
    max_parallax: float = 0.5,
    nonrigid_gain: float = 1.15,
    rigid_share: float = 0.9,
    shape_tolerance: float = 0.15,
    cluster_deg: float = 4.0,
    max_motions: int = 3,
    seed: int | np.random.Generator = 0,
    progress=None,
    memory_budget: float | None = None,
) -> SphereMatch:
    """Match the corners of two catadioptric images on the unit sphere.

    Parameters
    ----------
    pixels1, pixels2 : (N1, 2), (N2, 2) array_like of float
        Corner pixels ``(u, v)`` of the two images, in any order, with any
        share of unmatched corners. Rows that are NaN or that the camera
        cannot lift are dropped (see :attr:`SphereMatch.index1`).
    camera1 : UnifiedCamera
        Camera of image 1.
    camera2 : UnifiedCamera, optional
        Camera of image 2; default: ``camera1``.
    noise_px : float, default: 1.0
        Assumed corner noise in pixels (standard deviation per
        coordinate); sets every gate through :func:`sphere_noise`. It is
        given in pixels, not in the data units of the ``noise`` of
        :func:`gatv.register`, because the corners are measured in pixels
        and the noise on the sphere differs from ray to ray (the lifting's
        Jacobian); :attr:`SphereMatch.noise` reports its median on the
        sphere.
    strategy : {"auto", "rigid", "local", "epipolar", "nonrigid", "voting"}, default: "auto"
        ``"voting"``: the paper's method (end of section 5.1): the
        candidate pairs after the dominant rotation form a curved surface
        in the joint space, found by tensor voting and checked with the
        local eq. 41 (:mod:`catadioptric.voting`); ``"rigid"``: pure camera rotation only; ``"local"``: locally rigid
        growth after the rotation; ``"epipolar"``: matching along the
        epipolar arcs of a recovered motion (R, t); ``"nonrigid"``: the
        local-constraint mode of :func:`gatv.nonrigid.register` after the
        rotation; ``"auto"``: the rotation when it explains nearly all
        rays, else the epipolar result when it has at least
        ``nonrigid_gain`` times the rotation's support, else the local
        one under the same rule, else the rotation.
    max_parallax : float, default: 0.5
        Largest displacement of a ray left after the camera rotation
        (chord on the unit sphere, ~radians): the camera translation over
        the nearest depth. Bounds the candidate pairs of the epipolar and
        non-rigid stages.
    nonrigid_gain : float, default: 1.15
        See ``strategy``.
    shape_tolerance : float, default: 0.15
        Tolerance on the log side lengths of matched local triangles (the
        relative change of a triangle's sides that parallax may cause).
    cluster_deg : float, default: 4.0
        Radius of the cluster of trial rotations, degrees.
    max_motions : int, default: 3
        Most motions reported. After the dominant motion, the rays it
        leaves unexplained are searched for a plane moved rigidly (a
        homography of the sphere, :mod:`catadioptric.plane`), again and
        again (:func:`catadioptric.peeling.peel`); 1 reports the dominant
        motion only.
    seed : int or numpy.random.Generator, default: 0
        Seed of the random stages (the epipolar RANSAC samples and the
        non-rigid stage): an integer ``>= 0`` (same seed, same result) or
        a ``Generator``, which draws one integer seed for them.
    progress : callable, optional
        ``progress(fraction, message)``, called as the stages start
        (lifting, rotation search, local growth, epipolar stage) and with
        1.0 at the end.
    memory_budget : float, optional
        Bytes that one of the large tables (trial rotations of matched
        triangles, the RANSAC table, the epipolar candidates) may take;
        default :data:`gatv.validation.DEFAULT_MEMORY_BUDGET` or the
        ``GATV_MEMORY_BUDGET`` environment variable.

    Returns
    -------
    SphereMatch
        Falsy, with ``info["reason"]``, when nothing was matched, also when
        a rival matching with other partners explains nearly as many rays
        (a repeated pattern, ``info["rival_support"]``; see the module
        docstring, step 5).

    Raises
    ------
    gatv.errors.InputError
        Pixels not an (N, 2) array of numbers, a camera that is not a
        :class:`UnifiedCamera`, a bad option, or a table over
        ``memory_budget`` (a :class:`ValueError`).

    References
    ----------
    Reyes, Medioni & Bayro, IJCV 75(3) 2007, section 5.1 and Fig. 15.

    Examples
    --------
    >>> from catadioptric import synthetic_views
    >>> v = synthetic_views(120, rotation_deg=40.0, translation=(0, 0, 0), seed=2)
    >>> m = match(v.pixels1, v.pixels2, v.camera1)
    >>> m.strategy, round(m.angle_deg), m.support == len(v.pairs)
    ('rigid', 40, True)
    """
    t_start = time.perf_counter()
    p1 = _check_pixels(pixels1, "pixels1")
    p2 = _check_pixels(pixels2, "pixels2")
    camera1 = _check_camera(camera1, "camera1")
    camera2 = camera1 if camera2 is None else _check_camera(camera2, "camera2")
    noise_px = _check_real(noise_px, "noise_px")
    max_parallax = _check_real(max_parallax, "max_parallax")
    nonrigid_gain = _check_real(nonrigid_gain, "nonrigid_gain")
    shape_tolerance = _check_real(shape_tolerance, "shape_tolerance")
    cluster_deg = _check_real(cluster_deg, "cluster_deg")
    rigid_share = _check_real(rigid_share, "rigid_share")
    if strategy not in STRATEGIES:
        msg = (f"Expected `strategy` to be 'auto', 'rigid', 'local', 'epipolar', 'nonrigid' or "
               f"'voting', got {strategy!r}.")
        raise InputError(msg)
    as_rng(seed)  # validates: an integer >= 0 or a Generator
    # one integer for the random stages (an int seed is used as it is)
    seed = seed_int(seed)
    progress = check_progress(progress)
    if memory_budget is not None:
        memory_budget = _check_real(memory_budget, "memory_budget")
    if isinstance(max_motions, bool) or not isinstance(max_motions, numbers.Integral) or max_motions < 1:
        msg = f"Expected `max_motions` to be an integer >= 1, got {max_motions!r}."
        raise InputError(msg)
    max_motions = int(max_motions)

    progress(0.0, "lifting the pixels to the sphere")
    r1, index1 = _lift(camera1, p1)
    r2, index2 = _lift(camera2, p2)
    info: dict = {"n_pixels1": int(p1.shape[0]), "n_pixels2": int(p2.shape[0]),
                  "n_rays1": int(r1.shape[0]), "n_rays2": int(r2.shape[0])}
    s1 = sphere_noise(camera1, p1[index1], noise_px) if index1.size else np.empty(0)
    s2 = sphere_noise(camera2, p2[index2], noise_px) if index2.size else np.empty(0)
    noise = float(np.median(np.concatenate([s1, s2]))) if s1.size + s2.size else float("nan")

    def result(pairs, rotation, rot_support, used, reason=None, motion=None):
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        if used == "rigid" and pairs.shape[0]:
            pairs = rigid_posterior(r1, tree2, s1, s2, rotation, pairs)
        if pairs.shape[0] and reason is None:
            progress(0.9, "testing for a rival matching (repeated structure)")
            t_r = time.perf_counter()
            rival_support, _ = rival(r1, r2, tree2, s1, s2, pairs)
            info.update(rival_support=rival_support, time_rival_s=time.perf_counter() - t_r)
            if rival_support >= max(chance, RIVAL_RATIO * pairs.shape[0]):
                info.update(ambiguous_strategy=used, ambiguous_support=int(pairs.shape[0]))
                used, reason = "none", (
                    f"ambiguous (repeated structure): the {used} match of {pairs.shape[0]} pairs has a "
                    f"rival with other partners for {rival_support} rays")
                # the motion is as ambiguous as the pairs; the plane stage
                # below compares whole-pattern supports instead
                pairs, rotation, rot_support, motion = np.empty((0, 2), np.int64), None, 0, None
        # The verdict (gatv.verdict): the first motion's pairs against the sphere's chance level.
        if "chance_support" in info:
            info["verdict"] = chance_verdict(pairs.shape[0], info["chance_support"],
                                             info.get("n_trial_rotations", 1), method="poisson").to_dict()
        motions = []
        if pairs.shape[0]:
            first = np.column_stack([index1[pairs[:, 0]], index2[pairs[:, 1]]])
            motions.append((SphereMotion(first, used, rotation, motion), pairs))
        # further motions after the first; with "auto" the plane stage may
        # also be the first (a repeated pattern the dominant stages call ambiguous)
        if (motions or strategy == "auto") and max_motions > len(motions) and min(r1.shape[0], r2.shape[0]) >= 5:
            t_p = time.perf_counter()
            peel(motions, r1, r2, s1, s2, index1, index2, noise, np.random.default_rng(seed),
                 max_motions=max_motions, progress=progress, info=info)
            info["time_peel_s"] = time.perf_counter() - t_p
        if motions and reason is not None:
            # the first motion is the plane stage's: say what the dominant stages found
            if reason.startswith("ambiguous"):
                info["resolved"] = reason + "; resolved by whole-pattern support (plane stage)"
            else:
                info["dominant_reason"] = reason
            reason = None
        if motions and used == "none":
            used = motions[0][0].strategy
            rotation, motion = motions[0][0].rotation, motions[0][0].translation
        found = tuple(m for m, _ in motions)
        allp = np.vstack([m.correspondences for m in found]) if found else np.empty((0, 2), np.int64)
        allp = allp[np.argsort(allp[:, 0], kind="stable")]
        if reason is not None:
            info["reason"] = reason
        elif not found:
            info["reason"] = "nothing matched"
        info["time_s"] = time.perf_counter() - t_start
        progress(1.0, "done")
        return SphereMatch(allp, r1, r2, index1, index2, rotation, rot_support, used, noise, info,
                           translation=motion, motions=found)

    if r1.shape[0] < 3 or r2.shape[0] < 3:
        return result([], None, 0, "none", "fewer than 3 liftable pixels in a view")

    # Stage 2: the dominant rotation.
    progress(0.1, "searching the dominant rotation")
    t0 = time.perf_counter()
    tree2 = cKDTree(r2)
    R0, cluster, n_trials, votes = dominant_rotation(r1, r2, shape_tolerance, cluster_deg,
                                                     memory_budget=memory_budget)
    gate = GATE_SIGMAS * math.sqrt(2.0) * noise
    chance = chance_support(r1.shape[0], r2.shape[0], cap_area(r2), gate, alpha=CHANCE_ALPHA, dim=2)
    info.update(n_trial_rotations=n_trials, cluster_size=cluster, chance_support=chance)
    rigid = np.empty((0, 2), np.int64)
    R = None
    if R0 is not None:
        R, rigid = rotation_icp(r1, r2, tree2, s1, s2, R0)
        if rigid.shape[0] < chance:
            R, rigid = None, np.empty((0, 2), np.int64)
    info.update(rigid_support=int(rigid.shape[0]), time_rotation_s=time.perf_counter() - t0)
    if strategy == "rigid":
        if R is None:
            return result([], None, 0, "none", "no rotation beat the chance level of the sphere")
        return result(rigid, R, rigid.shape[0], "rigid")

    # Stage 3: locally rigid matching (translation: parallax).
    rot_support = int(rigid.shape[0])
    if strategy == "voting":
        # the paper's method: tensor voting on the candidate pairs, local eq. 41
        progress(0.3, "tensor voting on the candidate pairs")
        t0 = time.perf_counter()
        voted = voting_stage(r1, r2, tree2, s1, s2, R, noise, max_parallax, chance, info, memory_budget)
        info["time_voting_s"] = time.perf_counter() - t0
        if voted.shape[0] == 0:
            return result([], R, rot_support, "none", info.get("voting_reason", "nothing matched"))
        return result(voted, R, rot_support, "voting")
    if strategy == "auto" and R is not None and rigid.shape[0] >= rigid_share * min(r1.shape[0], r2.shape[0]):
        return result(rigid, R, rot_support, "rigid")
    progress(0.3, "growing locally rigid matches")
    t0 = time.perf_counter()
    if strategy == "nonrigid":
        local = _nonrigid(r1, r2, R, noise, max_parallax, seed, info)
    else:
        if R is not None and rigid.shape[0] >= 3:
            seeds = rigid
        else:
            # parallax spreads the triangles' rotations: a wider cluster,
            # whose triangles' vertices are the seeds
            _, wide, _, votes = dominant_rotation(r1, r2, shape_tolerance, WIDE_CLUSTER_FACTOR * cluster_deg,
                                                  memory_budget=memory_budget)
            info["wide_cluster_size"] = wide
            seeds = voted_seeds(votes)
        info["n_seeds"] = int(seeds.shape[0])
        local = grow_local(r1, r2, tree2, s1, s2, seeds)
    info["time_local_s"] = time.perf_counter() - t0
    info["local_support"] = int(local.shape[0])
    if strategy in ("auto", "epipolar"):
        # Stage 4: epipolar geometry (camera translation).
        progress(0.4, "estimating the epipolar geometry")
        t0 = time.perf_counter()
        seeds_e = local if local.shape[0] >= rigid.shape[0] else rigid
        epi = epipolar_stage(r1, r2, tree2, s1, s2, seeds_e, noise, max_parallax, np.random.default_rng(seed),
                             info, memory_budget)
        info["time_epipolar_s"] = time.perf_counter() - t0
        if epi is not None:
            Re, te, pe = epi
            info["epipolar_support"] = int(pe.shape[0])
            if pe.shape[0] >= max(nonrigid_gain * rigid.shape[0], chance):
                return result(pe, Re, rot_support, "epipolar", motion=te)
            info.setdefault("epipolar_reason", "fewer pairs than the rotation or the chance level")
        if strategy == "epipolar":
            return result([], R, rot_support, "none", info.get("epipolar_reason", "nothing matched"))
    if strategy != "auto" or local.shape[0] >= max(nonrigid_gain * rigid.shape[0], chance):
        if local.shape[0] == 0:
            return result([], R, rot_support, "none", info.get("nonrigid_reason", "nothing matched"))
        return result(local, R, rot_support, "local" if strategy != "nonrigid" else "nonrigid")
    if R is None:
        return result([], None, 0, "none", "no rotation and no locally rigid match beat the chance level")
    return result(rigid, R, rot_support, "rigid")



def _nonrigid(r1, r2, R, noise, max_parallax, seed, info):
    from gatv.nonrigid import register as nonrigid_register

    x = r1 if R is None else r1 @ R.T
    if x.shape[0] < 4 or r2.shape[0] < 4:
        info["nonrigid_reason"] = "fewer than 4 rays"
        return np.empty((0, 2), np.int64)
    try:
        m = nonrigid_register(x, r2, seed=seed, noise=noise, max_displacement=max_parallax)
    except ValueError as exc:
        info["nonrigid_reason"] = str(exc)
        return np.empty((0, 2), np.int64)
    info["nonrigid"] = {k: m.info[k] for k in ("structure", "n_candidates", "n_seeds", "gate")
                        if k in m.info}
    if not m:
        info["nonrigid_reason"] = m.info.get("reason", "nothing found")
    return np.asarray(m.correspondences, dtype=np.int64).reshape(-1, 2)
