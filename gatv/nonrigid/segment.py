"""Several non-rigid motions between two point sets (the paper's conclusion's next step).

:func:`segment` peels non-rigid motions one after another, as
:func:`gatv.motions.segment` peels rigid ones: :func:`gatv.nonrigid.register`
on the points no motion explains yet; its matches split into the parts that
are connected in the source *and* move continuously — two matches are
neighbours when their source points are within three matched spacings (three
local spacings where the sampling is non-uniform) and their displacements
agree up to the local strain (the tolerance of the local eq. 41,
``strain · |Δx| + gate``, at each match's local gate) — so two bodies that
move independently become two motions even when one smooth warp was fitted
through both.  The round's largest part is a motion, and so is each part
with enough support that meets it (a limb past a joint); a part apart from
it (a second body the growth reached across outliers) goes back to the pool
and is searched from its own seeds.  A motion's matched points and the
unmatched points lying among them leave the pool, and the search repeats
until nothing beats chance or too little structure is left apart from the
motions found.  The number of motions is not given.  The rounds are the one
peel loop, :func:`gatv.peel_loop.peel_loop`, with the registration as its
search step.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from .._validation import as_points, check_fraction, check_int, check_progress, seed_int
from .._validation import frozen_array as _frozen
from ..candidates import median_spacing
from ..peel_loop import Candidate, Judgement, Stop, peel_loop
from ..verdict import chance_verdict
from .motion import NonRigidMotion
from .multiscale import GROW_NEIGHBOURS, dense_rows, local_gates, motion_parts, nonuniform_spacings
from .parts import MIN_CONTACTS, UNCOVERED_REACH
from .registration import VERDICT_METHOD, register

__all__ = ["NonRigidSegmentation", "motion_parts", "segment"]


@dataclass(frozen=True, eq=False)
class NonRigidSegmentation:
    """Non-rigid motions found between two point sets, and who belongs to which.

    Attributes
    ----------
    motions : tuple of NonRigidMotion
        Largest support first; correspondences in rows of the inputs; no
        source or target row is in two motions.
    source_labels, target_labels : (N,), (M,) ndarray of int
        Index into ``motions`` of each row's motion, ``-1`` when none
        explains it.  Unmatched rows lying among a motion's matched points
        (within one spacing) carry its label.
    info : dict
        Per round: the registration's hypothesis and support, the parts
        found; the reason the peeling stopped; ``source_parts`` and
        ``target_parts``, per row the near-rigid part of its match within its
        motion (an index into that motion's ``info["parts"]``; -1: none).  Not
        compared.
    """

    motions: tuple
    source_labels: np.ndarray
    target_labels: np.ndarray
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "motions", tuple(self.motions))
        object.__setattr__(self, "source_labels", _frozen(self.source_labels, np.int64))
        object.__setattr__(self, "target_labels", _frozen(self.target_labels, np.int64))

    def __len__(self) -> int:
        return len(self.motions)

    def __bool__(self) -> bool:
        return len(self.motions) > 0

    def __iter__(self):
        return iter(self.motions)

    def __getitem__(self, k) -> NonRigidMotion:
        return self.motions[k]

    def to_dict(self) -> dict:
        """JSON-friendly dictionary."""
        return {
            "model": "nonrigid",
            "n_motions": len(self.motions),
            "motions": [m.to_dict() for m in self.motions],
            "source_labels": self.source_labels.tolist(),
            "target_labels": self.target_labels.tolist(),
        }

    def __repr__(self) -> str:
        return f"NonRigidSegmentation({len(self.motions)} motions: {[m.support for m in self.motions]})"


def segment(
    source,
    target,
    *,
    max_motions: int = 8,
    min_share: float = 0.05,
    strain: float = 0.35,
    seed=0,
    progress=None,
    **options,
) -> NonRigidSegmentation:
    """Find several non-rigid motions, their number unknown, with per-point labels.

    Parameters
    ----------
    source, target : (N, 3), (M, 3) array_like or object with ``.points``
    max_motions : int, default: 8
        Stop after this many motions.
    min_share : float, default: 0.05
        A part counts as a motion when it holds at least this share of the
        smaller set (and 10 matches).
    strain : float, default: 0.35
        Local strain of the continuity test (:func:`motion_parts`) and of
        :func:`gatv.nonrigid.register`.
    seed : int or numpy.random.Generator, default: 0
    progress : callable, optional
        ``progress(fraction, message)`` at each round.
    **options
        Passed to :func:`gatv.nonrigid.register` (``noise``,
        ``memory_budget``, ``multiscale``...).

    Returns
    -------
    NonRigidSegmentation
        Falsy when no motion beats chance (``info["reason"]``).

    Raises
    ------
    gatv.errors.InputError
        As :func:`gatv.nonrigid.register`, and for bad ``max_motions`` or
        ``min_share``.

    Examples
    --------
    >>> import numpy as np
    >>> from gatv.nonrigid import segment, deformations as D
    >>> a = D.sample_plane(100, 10.0, seed=0)
    >>> b = a + [14.0, 0, 0]
    >>> seg = segment(np.vstack([a, b]), np.vstack([D.twist(a, 45.0), D.bend(b, 60.0) + [0, 0, 3]]))
    >>> first, second = seg.source_labels[:100], seg.source_labels[100:]
    >>> len(seg), bool(np.mean(first == first[0]) > 0.95 and np.mean(second == 1 - first[0]) > 0.95)
    (2, True)
    """
    X = as_points(source, "source", min_points=4)
    Y = as_points(target, "target", min_points=4)
    max_motions = check_int(max_motions, "max_motions", 1)
    min_share = check_fraction(min_share, "min_share")
    strain = check_fraction(strain, "strain", high=np.inf, open_low=False)
    report = check_progress(progress)
    base_seed = seed_int(seed)
    least = max(10, int(np.ceil(min_share * min(X.shape[0], Y.shape[0]))))
    src_lab = np.full(X.shape[0], -1, np.int64)
    tgt_lab = np.full(Y.shape[0], -1, np.int64)
    motions: list[NonRigidMotion] = []
    rounds: list[dict] = []

    # the structure's rows (multiscale.dense_rows of each whole set: not the outliers scattered
    # through the volume); a round needs ``least`` of them unexplained on either side
    structure_s = np.zeros(X.shape[0], bool)
    structure_t = np.zeros(Y.shape[0], bool)
    structure_s[dense_rows(X)] = True
    structure_t[dense_rows(Y)] = True
    reach_s = UNCOVERED_REACH * median_spacing(X[structure_s])
    reach_t = UNCOVERED_REACH * median_spacing(Y[structure_t])

    def search():
        """:func:`register` on the rows no motion explains yet; or why there is nothing to register."""
        rs, rt = np.flatnonzero(src_lab < 0), np.flatnonzero(tgt_lab < 0)
        if min(rs.size, rt.size) < least:
            return Stop("fewer unexplained points than a motion needs", exhausted=True)
        left = (_apart(X, rs[structure_s[rs]], src_lab >= 0, reach_s),
                _apart(Y, rt[structure_t[rt]], tgt_lab >= 0, reach_t))
        if min(left) < least:
            return Stop("fewer unexplained rows on the structure, apart from the motions found, than a "
                        "motion needs", exhausted=True)
        report(len(motions) / max_motions, f"round {len(rounds) + 1}: {rs.size} x {rt.size} points")
        t0 = time.perf_counter()
        try:
            m = register(X[rs], Y[rt], seed=base_seed + len(rounds), strain=strain, **options)
        except ValueError as exc:  # e.g. the remaining points are collinear
            if "collinear" in str(exc) or "identical" in str(exc):
                return Stop(f"the remaining points have no structure ({exc})", exhausted=True)
            raise
        record = {"support": m.support, "hypothesis": m.info.get("hypothesis"),
                  "hypotheses": m.info.get("hypotheses"), "prealign": m.info.get("prealign"),
                  "windows": m.info.get("windows"), "coarse": m.info.get("coarse_hypothesis"),
                  "local_windows": m.info.get("local_windows"), "time_s": time.perf_counter() - t0,
                  "verdict": _round_verdict(m, m.support, least), "structure_rows": left}
        rounds.append(record)
        return Candidate(m, m.support, _Registered(rs, rt, record))

    def accept(candidate: Candidate) -> Judgement:
        """Kept when the registration reaches ``least`` and splits into at least one part that does."""
        m, d = candidate.motion, candidate.detail
        if m.support < least:
            return Judgement(False, m.info.get("reason", "no motion beats chance among the remaining points"))
        pairs = np.column_stack([d.rs[m.correspondences[:, 0]], d.rt[m.correspondences[:, 1]]])
        parts = motion_parts(X[pairs[:, 0]], Y[pairs[:, 1]], strain, _match_gates(Y, d.rt, m))
        sizes = np.bincount(parts)
        d.record["parts"] = sizes.tolist()
        if sizes[0] < least:
            return Judgement(False, "the registration's matches split into parts too small to count")
        return Judgement(True, "kept", detail=_Parts(pairs, _beside(X, pairs, parts), sizes, parts))

    def remove(candidate: Candidate, judgement: Judgement) -> list[NonRigidMotion]:
        """Each part with enough support that meets the round's largest part a motion (up to
        ``max_motions``); its rows leave the pool.  A part apart from the largest goes back to the
        pool: the registration vouches for what its seeds grew continuously, and a second body
        reached across a gap (by outliers between two shapes, 30% outliers: a face's growth crossed
        to the body and matched 1,017 of its rows at precision 0.40) is searched again from its own
        seeds in a later round.  A part that meets it (a limb past a joint, split off where the
        displacement turns faster than the strain allows) is its own motion, as before."""
        m, d = candidate.motion, judgement.detail
        added = []
        for p in np.flatnonzero((d.sizes >= least) & d.beside):
            if len(motions) >= max_motions:
                break
            sel = d.pairs[d.parts == p]
            motions.append(_sub_motion(m, d.parts == p, sel))
            motions[-1].info["verdict"] = _round_verdict(m, int(d.sizes[p]), least)
            label = len(motions) - 1
            src_lab[sel[:, 0]] = label
            tgt_lab[sel[:, 1]] = label
            # unmatched rows lying among its matches (a row whose partner the other set lacks)
            _absorb(X, src_lab, sel[:, 0], label)
            _absorb(Y, tgt_lab, sel[:, 1], label)
            added.append(motions[-1])
        return added

    reason = peel_loop(search, accept, remove, max_motions=max_motions,
                       full=f"reached max_motions={max_motions}").reason

    # unmatched rows among a motion's matched points carry its label
    for k, mo in enumerate(motions):
        _absorb(X, src_lab, mo.correspondences[:, 0], k)
        _absorb(Y, tgt_lab, mo.correspondences[:, 1], k)
    order = np.argsort([-mo.support for mo in motions], kind="stable")
    remap = np.full(len(motions) + 1, -1, np.int64)
    remap[order] = np.arange(len(motions))
    info = {"rounds": rounds, "min_support": least}
    # per row: the near-rigid part (index into its motion's info["parts"]) of its match, -1 when none
    src_part = np.full(X.shape[0], -1, np.int64)
    tgt_part = np.full(Y.shape[0], -1, np.int64)
    for mo in motions:
        labels = mo.info.get("part_labels")
        if labels is not None and len(labels) == mo.support:
            src_part[mo.correspondences[:, 0]] = labels
            tgt_part[mo.correspondences[:, 1]] = labels
    info.update(source_parts=src_part, target_parts=tgt_part)
    if motions:  # the weakest motion's verdict; with none, the last round's
        info["verdict"] = min((mo.info["verdict"] for mo in motions), key=lambda v: v["margin"])
    else:
        info["verdict"] = rounds[-1]["verdict"] if rounds else chance_verdict(
            0, least, 1.0, method=VERDICT_METHOD).to_dict()
    if not motions:
        info["reason"] = reason
    else:
        info["stopped"] = reason
    report(1.0, f"done: {len(motions)} motions")
    return NonRigidSegmentation([motions[i] for i in order], remap[src_lab], remap[tgt_lab], info)


@dataclass(frozen=True, eq=False)
class _Registered:
    """A round's registration on the unexplained rows (a :class:`gatv.peel_loop.Candidate`'s detail)."""

    rs: np.ndarray  # the source rows registered
    rt: np.ndarray  # the target rows
    record: dict  # the round's entry of info["rounds"]


@dataclass(frozen=True, eq=False)
class _Parts:
    """The matches of an accepted registration split into continuously moving parts."""

    pairs: np.ndarray  # the matches, in input rows
    beside: np.ndarray  # each part: it is the largest or meets it (:func:`_beside`)
    sizes: np.ndarray  # matches per part
    parts: np.ndarray  # each match's part


def _round_verdict(m: NonRigidMotion, support: int, least: float) -> dict:
    """A round's (or one part's) verdict: ``support`` against the level of the round's
    registration (its ``info["verdict"]``), and at least ``least`` (the smallest motion counted)."""
    v = m.info.get("verdict") or {}
    return chance_verdict(support, max(float(v.get("chance", 0.0)), float(least)), v.get("n_tested", 1.0),
                          method=VERDICT_METHOD).to_dict()


def _sub_motion(m: NonRigidMotion, rows, pairs) -> NonRigidMotion:
    """The part ``rows`` of ``m``'s matches as a motion, with input-row correspondences."""
    smoothing = m.smoothing if int(rows.sum()) == m.support else 0.0
    info = dict(m.info)
    labels = info.get("part_labels")
    if labels is not None and len(labels) == m.support:  # the near-rigid part of each of its matches
        info["part_labels"] = np.asarray(labels)[rows]
    return NonRigidMotion(pairs, m.source_points[rows], m.target_points[rows], m.rotations[rows],
                          m.translations[rows], smoothing, None, info)


def _apart(P, rows, explained, reach: float) -> int:
    """How many of ``rows`` lie farther than ``reach`` from every ``explained`` row: the structure a
    further motion could hold (rows among a found motion's matches whose partner the other set
    lacks, or that its gate missed, are its own; two real shapes at 30% outliers left 1,007 such
    rows beside the found motions, and a last round that found nothing took 105–310 s)."""
    if rows.size == 0 or not explained.any():
        return int(rows.size)
    d = cKDTree(P[explained]).query(P[rows], k=1, distance_upper_bound=reach)[0]
    return int(np.sum(~np.isfinite(d)))


def _beside(X, pairs, parts) -> np.ndarray:
    """For each part of ``parts``: whether it is part 0 (the largest) or meets it: at least
    ``MIN_CONTACTS`` of its matches have a match of part 0 among their ``GROW_NEIGHBOURS`` nearest
    matches (source side), within three median matched spacings, or three of their local spacings
    where the matches are sampled non-uniformly (a body's shoulder, sampled three times more
    sparsely than its face and hands)."""
    xs = X[pairs[:, 0]]
    n = int(parts.max()) + 1
    out = np.zeros(n, bool)
    out[0] = True
    if n == 1:
        return out
    tree = cKDTree(xs)
    reach = np.full(xs.shape[0], 3.0 * median_spacing(xs))
    local = nonuniform_spacings(xs, tree)
    if local is not None:
        reach = np.maximum(reach, 3.0 * local)
    k = min(GROW_NEIGHBOURS + 1, xs.shape[0])
    dist, nb = tree.query(xs, k=k)
    meets = np.any((parts[nb[:, 1:]] == 0) & (dist[:, 1:] <= reach[:, None]), axis=1)
    near = np.bincount(parts[meets & (parts != 0)], minlength=n)
    out[1:] = near[1:] >= MIN_CONTACTS
    return out


def _match_gates(Y, rows, m: NonRigidMotion) -> np.ndarray | float:
    """The sampling gate of each of ``m``'s matches (targets ``Y[rows]``): the registration's
    gate, or half the local spacing where the target is sampled non-uniformly
    (:func:`gatv.nonrigid.multiscale.local_gates`, as the registration gated them)."""
    Yr = Y[rows]
    spacing = m.info.get("spacing")
    gate = float(m.info.get("gate", 0.5 * median_spacing(Yr)))
    floor = max(0.0, gate - 0.5 * float(spacing)) if spacing else 0.0
    gates = local_gates(Yr, cKDTree(Yr), gate, floor, rows=dense_rows(Yr))
    return gates[m.correspondences[:, 1]]


def _absorb(P, labels, matched, k: int) -> None:
    """Give label ``k`` to unlabelled rows lying among ``k``'s matched rows: within one spacing of the
    nearest, its own (the distance to its nearest other matched row) where that is wider than the
    median (a body's limbs)."""
    free = np.flatnonzero(labels < 0)
    if free.size == 0 or matched.size < 2:
        return
    pts = P[matched]
    tree = cKDTree(pts)
    own = tree.query(pts, k=2)[0][:, 1]
    h = median_spacing(pts)
    d, j = tree.query(P[free], k=1, distance_upper_bound=max(h, float(own.max())))
    ok = np.isfinite(d)
    ok[ok] = d[ok] <= np.maximum(h, own[j[ok]])
    labels[free[ok]] = k
