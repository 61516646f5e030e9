"""Every motion on the sphere: the motions of a pair of views, peeled one at a time.

After the dominant motion (:func:`catadioptric.match`'s stages), the rays it
leaves unexplained may hold another motion: in the real catadioptric pairs
the corridor is static and a hand-held checkerboard moves. A plane moved
rigidly maps the rays by a homography of the sphere
(:mod:`catadioptric.plane`); :func:`peel` looks for one on the rays left,
keeps it when it beats the chance level of those rays and is not more of
an earlier motion, and repeats (the peeling of section 5 of Reyes, Medioni
& Bayro, IJCV 2007, on the sphere). Each motion is a :class:`SphereMotion`.
The rounds are the one peel loop of gatv, :func:`gatv.peel_loop.peel_loop`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from catadioptric.acceptance import cap_area
from catadioptric.constants import (
    CHANCE_ALPHA,
    GATE_SIGMAS,
    PEEL_OVERLAP,
    REACH_SPACINGS,
)
from catadioptric.plane import apply_homography, decompose_homography, plane_stage
from catadioptric.rotation import gated_pairs
from gatv.validation import frozen_array as _frozen
from gatv.fitting import kabsch
from gatv.motion import rotation_angle_deg
from gatv.peel_loop import Candidate, Judgement, Stop, peel_loop
from gatv.stats import chance_support

if TYPE_CHECKING:
    from numpy.typing import NDArray

__all__ = ["SphereMotion", "fits_motion", "peel", "plane_motion"]


@dataclass(frozen=True, eq=False)
class SphereMotion:
    """One motion between two catadioptric views and the corners it explains.

    Attributes
    ----------
    correspondences : (K, 2) ndarray of int
        One-to-one pairs ``(i, j)`` of input rows of ``pixels1`` and
        ``pixels2``, sorted by ``i``.
    strategy : str
        The stage that found it: ``"rigid"``, ``"local"``, ``"epipolar"``,
        ``"nonrigid"``, ``"voting"`` (the first motion) or ``"plane"`` (a
        plane moved rigidly, :mod:`catadioptric.plane`).
    rotation : (3, 3) ndarray of float or None
        Rotation of the motion ``y ∝ R X + t`` (view 1 to view 2). For a
        plane, the rotation of the decomposition of the homography
        (:func:`catadioptric.plane.decompose_homography`) with the smaller
        angle among those that put the matched points in front of both
        views (``info["plane_solutions"]`` lists them all).
    translation : (3,) ndarray of float or None
        Unit translation direction where there is parallax.
    homography : (3, 3) ndarray of float or None
        ``y ∝ H x`` for a plane's rays.
    info : dict
        The stage's diagnostics.
    """

    correspondences: NDArray[np.int64]
    strategy: str
    rotation: NDArray[np.float64] | None = None
    translation: NDArray[np.float64] | None = None
    homography: NDArray[np.float64] | None = None
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        c = np.asarray(self.correspondences, dtype=np.int64).reshape(-1, 2)
        c = c[np.argsort(c[:, 0], kind="stable")]
        object.__setattr__(self, "correspondences", _frozen(c, np.int64))
        for name in ("rotation", "translation", "homography"):
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
        """float or None: angle of :attr:`rotation` in degrees."""
        return None if self.rotation is None else rotation_angle_deg(self.rotation)

    def to_dict(self) -> dict:
        """JSON-serialisable summary (correspondences as lists of input rows)."""
        return {
            "strategy": self.strategy,
            "support": self.support,
            "correspondences": self.correspondences.tolist(),
            "rotation": None if self.rotation is None else self.rotation.tolist(),
            "rotation_deg": self.angle_deg,
            "translation": None if self.translation is None else self.translation.tolist(),
            "homography": None if self.homography is None else self.homography.tolist(),
        }


def plane_solutions(H, x, y):
    """Decompositions ``(R, t, n)`` of ``H`` that put the matched points in front of both views.

    A solution is kept when at least 90% of the pairs have ``n · x > 0``
    (the plane point ``X = x / (n · x)`` in front of view 1) and
    ``(R X + t) · y > 0``. Sorted by rotation angle.
    """
    out = []
    for R, t, n in decompose_homography(H):
        nx = x @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            X = x / nx[:, None]
        front = (nx > 0) & (np.sum((X @ R.T + t) * y, axis=1) > 0)
        if np.mean(front) >= 0.9:
            out.append((R, t, n))
    out.sort(key=lambda s: rotation_angle_deg(s[0]))
    return out


def plane_motion(r1, r2, s1, s2, rows1, rows2, gate, rng, info):
    """The plane stage on the rays ``rows1, rows2``; ``(H, pairs)`` in full ray rows, or None.

    Kept when its support reaches the chance level of those rays
    (:func:`gatv.stats.chance_support` over the area they cover, with the
    4 pairs that fix a homography, at the family-wise level over all the
    trial mappings), recorded in ``info["chance_support"]``.
    """
    sub1, sub2 = r1[rows1], r2[rows2]
    res = plane_stage(sub1, sub2, s1[rows1], s2[rows2], rng, info)
    if res is None:
        return None
    H, pairs = res
    # every trial mapping is a test (Bonferroni): the search picks the best of them
    chance = chance_support(rows1.size, rows2.size, cap_area(sub2), gate,
                            n_tests=max(1, info.get("plane_trials", 1)), alpha=CHANCE_ALPHA, dim=2,
                            sample_size=4)
    info["chance_support"] = int(chance)
    info["plane_support"] = int(pairs.shape[0])
    if pairs.shape[0] < chance:
        info["plane_reason"] = f"{pairs.shape[0]} pairs, below the chance level {chance}"
        return None
    return H, np.column_stack([rows1[pairs[:, 0]], rows2[pairs[:, 1]]])


def fits_motion(pairs, earlier, r1, r2, s1, s2, neighbours=6):
    """Which ``pairs`` an earlier motion's pairs ``earlier`` also predict.

    Each ray is moved by the rotation of its ``neighbours`` nearest pairs of
    ``earlier`` (locally rigid, as :func:`catadioptric.rotation.grow_local`
    predicts) and its pair fits when its partner lies within two noise
    gates of the prediction; rays farther than ``REACH_SPACINGS`` spacings
    of the earlier pairs are not predicted (they do not fit).
    """
    if earlier.shape[0] < 3 or pairs.shape[0] == 0:
        return np.zeros(pairs.shape[0], bool)
    xs, ys = r1[earlier[:, 0]], r2[earlier[:, 1]]
    k = min(neighbours, earlier.shape[0])
    tree = cKDTree(xs)
    x = r1[pairs[:, 0]]
    dist, nb = tree.query(x, k=k)
    nb = nb.reshape(x.shape[0], k)
    Rl = kabsch(xs[nb], ys[nb], translation=False)[0]
    pred = np.einsum("kij,kj->ki", Rl, x)
    spacing = float(np.median(tree.query(xs, k=2)[0][:, 1]))
    near = np.asarray(dist).reshape(x.shape[0], k)[:, 0] <= REACH_SPACINGS * spacing
    sig = np.sqrt(s1[pairs[:, 0]] ** 2 + s2[pairs[:, 1]] ** 2)
    return near & (np.linalg.norm(r2[pairs[:, 1]] - pred, axis=1) <= 2.0 * GATE_SIGMAS * sig)


def reclaim(motions, H, pairs, r1, r2, s1, s2, index1, index2, info):
    """The rays on the plane that earlier motions took: given back to the plane.

    A dominant motion grown locally (or a chance pair of a rigid one) may
    take corners of the moved plane where the two motions meet. An earlier
    pair whose view-1 ray lies on the plane (within 1.5 of its matches'
    median spacing of one of them) and which the plane's homography also
    explains (a view-2 ray within the noise gate of ``H x``) is dropped from
    the earlier motion; the plane is then matched again on the rays left
    free. Returns the updated ``motions`` and the plane's pairs.
    """
    xs = r1[pairs[:, 0]]
    tree = cKDTree(xs)
    spacing = float(np.median(tree.query(xs, k=2)[0][:, 1]))
    tree2 = cKDTree(r2)
    moved = apply_homography(H, r1)
    on_plane = tree.query(r1)[0] <= 1.5 * spacing
    explained = np.zeros(r1.shape[0], bool)
    hit = gated_pairs(moved, r2, tree2, s1, s2, 1.0)
    explained[hit[:, 0]] = True
    out, dropped = [], 0
    for motion, p in motions:
        bad = on_plane[p[:, 0]] & explained[p[:, 0]]
        if bad.any():
            dropped += int(bad.sum())
            keep = p[~bad]
            c = np.column_stack([index1[keep[:, 0]], index2[keep[:, 1]]])
            motion = SphereMotion(c, motion.strategy, motion.rotation, motion.translation, motion.homography,
                                  motion.info)
            p = keep
        out.append((motion, p))
    info["reclaimed_from_earlier"] = dropped
    if not dropped:
        return motions, pairs
    used1 = np.zeros(r1.shape[0], bool)
    used2 = np.zeros(r2.shape[0], bool)
    for _, p in out:
        used1[p[:, 0]] = True
        used2[p[:, 1]] = True
    free2 = np.flatnonzero(~used2)
    moved[used1] = np.inf
    sub = gated_pairs(moved, r2[free2], cKDTree(r2[free2]), s1, s2[free2], 1.0)
    return out, np.column_stack([sub[:, 0], free2[sub[:, 1]]])


def make_plane_motion(H, pairs, r1, r2, index1, index2, info) -> SphereMotion:
    """A :class:`SphereMotion` of a plane's homography and pairs (full ray rows)."""
    sols = plane_solutions(H, r1[pairs[:, 0]], r2[pairs[:, 1]])
    info["plane_solutions"] = [
        {"rotation_deg": rotation_angle_deg(R), "translation": (t / max(np.linalg.norm(t), 1e-300)).tolist(),
         "normal": n.tolist()} for R, t, n in sols]
    R = t = None
    if sols:
        R, t, _ = sols[0]
        nt = float(np.linalg.norm(t))
        t = t / nt if nt > 1e-9 else None
    out = np.column_stack([index1[pairs[:, 0]], index2[pairs[:, 1]]])
    return SphereMotion(out, "plane", R, t, H, info)


@dataclass(frozen=True, eq=False)
class _Plane:
    """A plane the search found (a :class:`gatv.peel_loop.Candidate`'s detail)."""

    pairs: NDArray[np.int64]  # its pairs in ray rows
    info: dict  # the plane stage's diagnostics, the motion's info


def peel(motions, r1, r2, s1, s2, index1, index2, noise, rng, *, max_motions, progress, info):
    """Further motions on the rays the ``motions`` so far leave unexplained.

    ``motions`` is a list of ``(SphereMotion, pairs in ray rows)``; it is
    extended in place, one plane at a time, until ``max_motions``, until
    no plane beats the chance level, or until a plane is mostly more of an
    earlier motion (``PEEL_OVERLAP``). ``info["peel_reason"]`` says why
    the peeling stopped.
    """
    gate = GATE_SIGMAS * math.sqrt(2.0) * noise

    def search():
        """The plane stage on the rays no motion explains yet (:func:`plane_motion`); or why none beats chance."""
        used1 = np.zeros(r1.shape[0], bool)
        used2 = np.zeros(r2.shape[0], bool)
        for _, p in motions:
            used1[p[:, 0]] = True
            used2[p[:, 1]] = True
        rows1, rows2 = np.flatnonzero(~used1), np.flatnonzero(~used2)
        progress(0.92, f"looking for motion {len(motions) + 1} on {rows1.size} / {rows2.size} rays")
        pinfo: dict = {}
        found = plane_motion(r1, r2, s1, s2, rows1, rows2, gate, rng, pinfo)
        info.setdefault("peel", []).append({k: v for k, v in pinfo.items() if k != "plane_tie"})
        if found is None:
            return Stop(pinfo.get("plane_reason", "no further motion"), exhausted=True)
        H, pairs = found
        return Candidate(H, int(pairs.shape[0]), _Plane(pairs, pinfo))

    def accept(candidate: Candidate) -> Judgement:
        """Rejected when the plane's pairs are mostly more of an earlier motion (``PEEL_OVERLAP``)."""
        pairs, pinfo = candidate.detail.pairs, candidate.detail.info
        if motions:
            old = np.vstack([p for _, p in motions])
            share = float(np.mean(fits_motion(pairs, old, r1, r2, s1, s2)))
            pinfo["earlier_share"] = share
            if share > PEEL_OVERLAP:
                return Judgement(False, f"the next plane's {pairs.shape[0]} pairs are {share:.0%} an "
                                        f"earlier motion's")
        return Judgement(True, "kept")

    def remove(candidate: Candidate, judgement: Judgement) -> tuple:
        """The plane's rays out of the pool, with those earlier motions took from it (:func:`reclaim`)."""
        H, pairs, pinfo = candidate.motion, candidate.detail.pairs, candidate.detail.info
        if motions:
            updated, pairs = reclaim(motions, H, pairs, r1, r2, s1, s2, index1, index2, pinfo)
            motions[:] = updated
        motions.append((make_plane_motion(H, pairs, r1, r2, index1, index2, pinfo), pairs))
        return (motions[-1],)

    # the motions given (the dominant one) count toward max_motions; reclaim may change them, so
    # ``motions``, not the loop's outcome, holds the result
    outcome = peel_loop(search, accept, remove, max_motions=max_motions - len(motions),
                        full=f"max_motions = {max_motions} reached")
    info["peel_reason"] = outcome.reason
    return motions
