"""Every instance of a model in a scene (paper, section 4.1 and section 5).

Section 4.1 of the paper picks a model (a robotic arm) once in a stereo
reconstruction and finds it again in each later reconstruction by
registering the model against the scene, with no initial guess (Fig. 9).
A scene may hold several copies of the model (parts in a bin), and how many
is not known.  :func:`instances` finds them with the one peel loop of
section 5 ("we removed its tokens from the voting space and the process was
repeated until no more planes were found",
:func:`gatv.peel_loop.peel_loop`):

* **search**: :func:`gatv.register` of the model against the scene points
  no instance has taken yet, in the pipeline :func:`gatv.register` would
  choose for the whole scene (exact point sets, noisy sets, real scans;
  :func:`gatv.registration.checked_pipeline`), chosen once so that a scene
  thinned by the rounds does not switch pipelines half way.  On scans the
  model is registered against one connected part of the scene's surfaces
  at a time (:func:`scene_parts`, largest first): the scans verdict judges
  a motion against wrong motions polished on the data, and on a scene of
  several copies those polish onto the *other* copies, whose support is as
  high, so that no copy passes against the whole scene.  In the exact
  pipeline, once a copy is found, the rounds search one block of the
  scene at a time (:func:`scene_blocks`: overlapping boxes of a few copy
  extents, so that every copy lies whole in one) at the copies' measured
  noise: a search indexes every pair of its scene points, and a block's
  index is a small share of the whole scene's.  When every block is
  searched in vain, the whole scene is searched once more at the
  schedule's tolerances (a copy of another noise, or one a block missed);
* **accept**: the result's own verdict (:mod:`gatv.verdict`): a falsy
  result, or one whose ``info["verdict"]`` did not pass, ends the loop (on
  scans it sets its part aside and the next part is searched), so clutter
  and partial copies that do not beat chance give nothing.  On scans the
  motion's pairs must also sit at the scans' noise, as a scan
  segmentation keeps a part's motion (their point-to-plane residual
  deviation within :data:`gatv.motions.scans.NOISE_FACTOR` of the scans'
  noise): another object laid onto a part can beat the wrong motions;
* **remove**: the instance's scene points leave the scene, its
  correspondences and every remaining scene point within the final gate
  of the moved model, so that the points of a copy the one-to-one
  correspondences left out (noise, a denser sampling) do not seed a
  second, spurious instance.

The model's points serve every instance (the model is not consumed); a
scene point belongs to at most one instance.  Each instance is a motion
from the model to the scene whose correspondences index the model's rows
and the whole scene's rows.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from .._validation import as_rng, check_int, check_positive, check_progress, frozen_array
from ..candidates import median_spacing
from ..errors import InputError
from ..models import get_model
from ..peel_loop import Candidate, Judgement, Stop, peel_loop
from ..registration import TIME_LIMIT, checked_pipeline, register
from ..scans import MIN_OVERLAP, VOTE_POINTS
from ..stages import FINAL_GATE
from .scans import NOISE_FACTOR, regions, scan_surfaces

__all__ = ["BLOCK_SIDE", "LATER_SHARE", "MIN_MODEL_POINTS", "PART_LINK", "TIME_LIMIT_ROUNDS", "Blocks", "Instances",
           "final_gate", "instances", "model_diameter", "model_size", "expected_share", "pose_distance",
           "scene_blocks", "scene_parts", "smallest_copy", "smallest_part", "validate_model"]

#: Fewest model points: a rigid motion needs three, and a fourth is the
#: least support that says more than the sample that made the motion.
MIN_MODEL_POINTS = 4

#: Default wall-clock bound of a whole :func:`instances` call, in units of
#: one registration's bound (:data:`gatv.registration.TIME_LIMIT`): each
#: round is one registration, and no round starts past the bound.
TIME_LIMIT_ROUNDS = 10


@dataclass(frozen=True, eq=False)
class Instances:
    """The instances of a model found in a scene, and which scene points each took.

    Attributes
    ----------
    instances : tuple of RigidMotion
        In the order found (the search finds the best supported copy on
        what remains first).  Each maps the model onto one copy,
        ``scene ≈ model @ rotation.T + translation``; its
        ``correspondences`` are one-to-one ``(model row, scene row)``
        pairs, the scene rows those of the whole scene; its
        ``info["verdict"]`` the verdict it passed.
    labels : (M,) ndarray of int
        Per scene point: the index of the instance that took it, ``-1``
        for none.
    info : dict
        ``reason`` (why the search stopped), ``exhausted`` (stopped for want
        of an instance, not at a limit), ``pipeline`` and
        ``pipeline_reason``, ``rounds`` (one record per search), ``time_s``,
        ``n_model``, ``n_scene``, ``model_size``, ``smallest_copy``,
        ``dropped``.  Not compared.  A motion that passes its verdict with
        fewer points than :func:`smallest_copy` asks of a copy is no
        instance: its round records it (``set_aside``), or ``dropped`` when
        a better copy found later raised the bar, and its scene points stay
        unlabelled.
    """

    instances: tuple
    labels: np.ndarray
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "instances", tuple(self.instances))
        object.__setattr__(self, "labels", frozen_array(self.labels, np.int64))

    @property
    def motions(self) -> tuple:
        """The instances (the name every multi-motion result uses)."""
        return self.instances

    def __len__(self) -> int:
        return len(self.instances)

    def __bool__(self) -> bool:
        return len(self.instances) > 0

    def __iter__(self):
        return iter(self.instances)

    def __getitem__(self, k):
        return self.instances[k]

    def scene_rows(self, k: int) -> np.ndarray:
        """The scene rows instance ``k`` took (its correspondences and the points within its gate)."""
        return np.flatnonzero(self.labels == int(k))

    def to_dict(self) -> dict:
        """JSON-friendly dictionary (``motions`` as :class:`gatv.motions.Segmentation` has them)."""
        return {"n_instances": len(self.instances), "motions": [m.to_dict() for m in self.instances],
                "labels": self.labels.tolist()}

    def __repr__(self) -> str:
        inner = ", ".join(f"{m.angle_deg:.2f} deg/{m.support}" for m in self.instances)
        return f"Instances({len(self.instances)} found: [{inner}])"


def validate_model(model, name: str = "model") -> np.ndarray:
    """The model's points, checked as ``register`` checks a source, and at least :data:`MIN_MODEL_POINTS`."""
    X = get_model("rigid").check_points(model, name)
    if X.shape[0] < MIN_MODEL_POINTS:
        raise InputError(f"Expected `{name}` to have at least {MIN_MODEL_POINTS} points (a rigid motion "
                         f"needs 3 and its support one more), got {X.shape[0]}.")
    return X


def model_size(points: np.ndarray) -> float:
    """The diagonal of the model's bounding box: the scale of its translation errors."""
    pts = np.asarray(points, dtype=np.float64)
    return float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))


def pose_distance(a, b, centre: np.ndarray, size: float) -> float:
    """How far apart two poses of one model are: rotation angle (radians) plus centre distance over ``size``.

    ``a`` and ``b`` are motions (with ``rotation`` and ``translation``) or
    4×4 matrices; ``centre`` is the model's centroid, so that the distance
    does not depend on where the model's origin lies.
    """
    Ra, ta = _pose(a)
    Rb, tb = _pose(b)
    cos = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    angle = float(np.arccos(np.clip(cos, -1.0, 1.0)))
    apart = float(np.linalg.norm((Ra @ centre + ta) - (Rb @ centre + tb)))
    return angle + apart / max(float(size), 1e-300)


def _pose(m) -> tuple[np.ndarray, np.ndarray]:
    if hasattr(m, "rotation"):
        return np.asarray(m.rotation, dtype=np.float64), np.asarray(m.translation, dtype=np.float64)
    T = np.asarray(m, dtype=np.float64)
    return T[:3, :3], T[:3, 3]


def final_gate(result) -> float:
    """The gate of the found motion's final pairs: the scans pipeline's ``final_gate``, else
    :data:`gatv.stages.FINAL_GATE` times the exact pipeline's measured noise (``tolerance``)."""
    info = result.info
    if info.get("final_gate") is not None:
        return float(info["final_gate"])
    tol = info.get("tolerance", info.get("noise"))
    return FINAL_GATE * float(tol) if tol is not None and np.isscalar(tol) else 0.0


#: A copy is at least this share as well supported as the best copy found
#: (:func:`smallest_copy`; the later rounds search for such a copy,
#: :func:`expected_share`).
LATER_SHARE = 0.5


def expected_share(found, n_model: int) -> float | None:
    """The share of model points the later rounds expect a copy to match (``min_inlier_share``).

    :func:`gatv.register` draws model triples until one of a copy matching
    4% of the model would have been drawn (``min_inlier_share``): on the
    clutter left once every copy is found, that many draws at every
    tolerance of its schedule run to the time limit.  The copies of one
    scene are copies of one model seen by one sensor, so once copies are
    found the later rounds expect one at least :data:`LATER_SHARE` as well
    supported as the best found (as a share of the model's points; the
    support :func:`smallest_copy` asks of a copy):
    a 30%-cut copy among clutter is found at the same cost, and the last,
    fruitless round on the clutter takes about a second instead of a
    minute.  (Searching at the measured noise alone, as the point-set peel
    does, does not do: at the finest tolerances of the schedule the density
    screen passes a copy's trial motion that the tensor-voting judge then
    rejects.)  ``None`` before the first instance (register's default).
    """
    if not found:
        return None
    return min(1.0, max(smallest_copy(found) / max(int(n_model), 1), 0.04))


def smallest_copy(found) -> int:
    """The least support of a copy: :data:`LATER_SHARE` of the best copy found, and more than a sample.

    The verdict passes a motion that beats the wrong motions, and on exact
    data a handful of points does (a sample's three points, at a tolerance
    of 1e-6 of the spacing, against a chance level of three).  Among copies
    of one model such a motion is not a copy: a round whose motion falls
    short sets its scene points aside (out of the later searches,
    unlabelled) and the search goes on, and at the end the motions kept
    before a better copy raised the bar are dropped.  At least
    :data:`MIN_MODEL_POINTS` (one point more than the sample that made the
    motion) before any copy is found.
    """
    best = max((int(m.support) for m in found), default=0)
    return max(MIN_MODEL_POINTS, int(np.ceil(LATER_SHARE * best)))


#: Surface points closer than this many of their spacings are joined into one part (:func:`scene_parts`;
#: :data:`gatv.motions.scans.SAMPLING_GATE`, the gate that joins the parts of a scan segmentation).
PART_LINK = 3.0


class _Parts:
    """The scene's points on salient surfaces, once, for :func:`scene_parts` in every round."""

    def __init__(self, Y: np.ndarray, seed: int, memory_budget):
        self.mask = scan_surfaces(Y, seed=seed, memory_budget=memory_budget).mask
        on = Y[self.mask]  # the spacing of the points the parts are made of (a sample of a large scene's)
        self.link = PART_LINK * median_spacing(on if on.shape[0] >= MIN_MODEL_POINTS else Y)
        #: The share of the scene's rows the vote looked at (a large scene is voted on a sample,
        #: :data:`gatv.scans.VOTE_POINTS`): a part holds that share of a copy's points.
        self.voted = min(1.0, VOTE_POINTS / max(Y.shape[0], 1))


def smallest_part(X: np.ndarray, Y: np.ndarray) -> int:
    """The fewest scene points a part must hold to be searched for a copy of the model.

    A copy is found when at least :data:`gatv.scans.MIN_OVERLAP` of the
    model has a partner on it (the share the scans search draws its
    triples for), and a part's points cover the copy's surface at the
    scene's sampling: that share of the model's points, scaled by the two
    samplings' densities on a surface (the square of their spacings' ratio).
    """
    ratio = median_spacing(X) / max(median_spacing(Y), 1e-300)
    return max(MIN_MODEL_POINTS, int(np.ceil(MIN_OVERLAP * X.shape[0] * ratio**2)))


def scene_parts(Y: np.ndarray, rows: np.ndarray, mask: np.ndarray, link: float, least: int) -> list[np.ndarray]:
    """The connected parts of ``rows`` on the surfaces (``mask``) of ``least`` points or more, largest first.

    Scene points closer than ``link`` are joined (:func:`gatv.motions.scans.regions`):
    the copies of a model lying apart fall into parts of their own, uniform
    clutter (off the surfaces the tensor voting keeps) into none.
    """
    on = rows[mask[rows]]
    if on.size < least:
        return []
    return [on[r] for r in regions(Y[on], link, min_points=least)]


def model_diameter(points: np.ndarray) -> float:
    """The largest distance between two of the model's points (over its convex hull's vertices when it has one).

    A copy of the model, at any pose, spans at most this along any direction.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[0] > 64:
        try:
            from scipy.spatial import ConvexHull

            pts = pts[ConvexHull(pts).vertices]
        except Exception:  # flat or degenerate: all the points
            pass
    if pts.shape[0] < 2:
        return 0.0
    d = 0.0
    for k in range(0, pts.shape[0], 512):  # row blocks: memory linear in the points
        d = max(d, float(np.max(np.linalg.norm(pts[k:k + 512, None, :] - pts[None, :, :], axis=-1))))
    return d


#: Side of a block of :func:`scene_blocks`, in copy reaches (the model's diameter plus the final gate's
#: margin on each side): blocks overlap by one reach, so that a copy lies whole in one of them.
BLOCK_SIDE = 3.0


class Blocks:
    """Overlapping axis-aligned boxes covering a scene, such that any set of extent at most ``reach`` along
    each axis lies whole in at least one of them (:func:`scene_blocks`).

    Along each axis the boxes are ``side`` long and start at most ``side -
    reach`` apart, the first at the scene's least coordinate and the last
    ending at its largest (the outer boxes reach on to infinity, so that
    rounding leaves no point out).  Box ``b`` is the product of one
    interval per axis (``index[b]``); ``aside[b]`` holds the rows set aside
    for that box only, ``exhausted[b]`` whether it was searched in vain.
    """

    def __init__(self, Y: np.ndarray, reach: float, side: float):
        lo, hi = Y.min(axis=0), Y.max(axis=0)
        extent = hi - lo
        self.side, self.reach = float(side), float(reach)
        #: Per axis, (intervals, points) membership of each point in each interval.
        self.inside = []
        for a in range(Y.shape[1]):
            m = 1 if extent[a] <= side else int(np.ceil((extent[a] - side) / max(side - reach, 1e-300))) + 1
            start = lo[a] + np.linspace(0.0, max(extent[a] - side, 0.0), m)
            low, high = start.copy(), start + side
            low[0], high[-1] = -np.inf, np.inf
            self.inside.append((Y[:, a][None, :] >= low[:, None]) & (Y[:, a][None, :] <= high[:, None]))
        counts = [ins.shape[0] for ins in self.inside]
        self.index = np.stack([g.ravel() for g in np.meshgrid(*[np.arange(c) for c in counts], indexing="ij")],
                              axis=1)
        self.aside: dict = {}
        self.exhausted = np.zeros(len(self.index), bool)

    def __len__(self) -> int:
        return len(self.index)

    def rows(self, b: int, rows: np.ndarray) -> np.ndarray:
        """The ``rows`` in box ``b``, less those set aside for it."""
        keep = np.ones(rows.size, bool)
        for ins, i in zip(self.inside, self.index[b]):
            keep &= ins[i, rows]
        if b in self.aside:
            keep &= ~self.aside[b][rows]
        return rows[keep]

    def set_aside(self, b: int, rows: np.ndarray, n: int) -> None:
        """Set ``rows`` (of a scene of ``n`` points) aside for box ``b`` only."""
        self.aside.setdefault(b, np.zeros(n, bool))[rows] = True


def scene_blocks(Y: np.ndarray, reach: float) -> Blocks | None:
    """The scene's blocks for copies of extent ``reach``, or ``None`` when one block would cover the scene.

    Each round of the exact pipeline indexes its scene for congruent
    triples in time and memory quadratic in the scene's points (every pair
    of points); a copy of the model spans at most ``reach``, so a search
    for it needs only a box around it.  Boxes of :data:`BLOCK_SIDE` reaches
    a side, overlapping by one reach, cover the scene so that every copy
    lies whole in one box.
    """
    side = BLOCK_SIDE * reach
    extent = Y.max(axis=0) - Y.min(axis=0)
    if reach <= 0 or np.all(extent <= side):
        return None
    return Blocks(Y, reach, side)


def _best_trial(result) -> int:
    """The best trial support a failed exact search saw (its verdict's support; 0 when none)."""
    return int((result.info.get("verdict") or {}).get("support", 0) or 0)


def _stopped_at_limit(result) -> bool:
    """Whether a falsy registration stopped at its time or work bound rather than for want of a motion."""
    return any("stopped" in rec for rec in result.info.get("trials", ()) if isinstance(rec, dict))


def instances(
    model,
    scene,
    *,
    seed=0,
    progress=None,
    memory_budget: float | None = None,
    max_instances: int | None = None,
    pipeline: str = "auto",
    time_limit: float | None = TIME_LIMIT_ROUNDS * TIME_LIMIT,
) -> Instances:
    """Every instance of ``model`` in ``scene``, their number unknown (section 4.1, section 5).

    Parameters
    ----------
    model : (N, 3) array_like or object with ``.points``
        The model's points (at least :data:`MIN_MODEL_POINTS`).  Every
        instance may use all of them.
    scene : (M, 3) array_like or object with ``.points``
        The scene: copies of the model, whole or partial, among clutter.
        Each scene point goes to at most one instance.
    seed : int or numpy.random.Generator, default: 0
        Seed of the rounds' searches; same seed, same result (unless the
        time limit stopped a search).
    progress : callable, optional
        ``progress(fraction, message)``: the share of the scene taken so
        far, after each round.
    memory_budget : float, optional
        Bytes, as :func:`gatv.register`'s.
    max_instances : int, optional
        Stop after this many instances.  Default: no bound but the data's
        (each instance takes at least one scene point, so the loop runs at
        most as many rounds as the scene has points).
    pipeline : {"auto", "exact", "scans"}, default: "auto"
        As :func:`gatv.register`; chosen once, for the whole scene.  On
        scans each round registers the model on one connected part of the
        scene's surfaces (:func:`scene_parts`): copies that touch fall into
        one part, and there neither passes the verdict against the other.
    time_limit : float or None, default: ten times :data:`gatv.registration.TIME_LIMIT`
        Seconds for the whole call: no round starts past it, and each
        round's search gets what is left (at most a registration's own
        bound).  ``info["reason"]`` says when it stopped the search.  On
        scans the parts searched in vain since the last copy found (or the
        start) share one registration's bound
        (:data:`gatv.registration.TIME_LIMIT`, at most ``time_limit``): a
        part that holds no copy costs a whole scans search (three attempts,
        10-15 s on a 2-core machine), and a scene without the model would
        otherwise cost that for each of its parts; no part starts when the
        slowest part search so far would carry them past it.

    Returns
    -------
    Instances
        Falsy when no instance beats the wrong motions (a scene without
        the model).

    Raises
    ------
    InputError
        Bad points (the message names ``model`` or ``scene``), a model of
        fewer than :data:`MIN_MODEL_POINTS` points, bad options.

    Examples
    --------
    >>> import numpy as np
    >>> from gatv import Rotor
    >>> from gatv.motions import instances
    >>> rng = np.random.default_rng(0)
    >>> m = rng.uniform(-1, 1, (60, 3))
    >>> copies = [(Rotor.from_axis_angle(rng.normal(size=3), a) >> m) + 5 * k for k, a in enumerate((0.3, 2.0))]
    >>> found = instances(m, np.vstack(copies + [rng.uniform(-2, 8, (100, 3))]))
    >>> len(found), sorted(i.support for i in found)
    (2, [60, 60])
    """
    t_start = time.perf_counter()
    X = validate_model(model, "model")
    Y = get_model("rigid").check_points(scene, "scene")
    max_instances = check_int(max_instances, "max_instances", 1, allow_none=True)
    time_limit = check_positive(time_limit, "time_limit", allow_none=True)
    rng = as_rng(seed)
    report = check_progress(progress)
    chosen, why, _ = checked_pipeline(X, Y, "rigid", pipeline, memory_budget)
    deadline = None if time_limit is None else t_start + time_limit
    return peel_instances(X, Y, chosen, why, rng, report, memory_budget, max_instances, deadline, t_start)


def peel_instances(X, Y, chosen: str, why: str, rng, report, memory_budget, max_instances, deadline,
                   t_start: float) -> Instances:
    """The peel loop of :func:`instances` on validated points (also each frame of :func:`gatv.motions.track`).

    ``X`` and ``Y`` are checked (N, 3) and (M, 3) float arrays, ``chosen``
    and ``why`` the pipeline :func:`gatv.registration.checked_pipeline`
    chose, ``report`` a checked progress callable, ``deadline`` a
    :func:`time.perf_counter` instant or ``None``.
    """
    return InstancePeel(X, Y, chosen, rng, memory_budget, deadline, t_start).run(why, report, max_instances)


class InstancePeel:
    """The state of one :func:`instances` peel: the scene's labels, the copies found, the rounds' records.

    Its methods are the loop's stages (:func:`gatv.peel_loop.peel_loop`):
    :meth:`search`, :meth:`accept`, :meth:`reject` and :meth:`remove`.
    """

    def __init__(self, X, Y, chosen: str, rng, memory_budget, deadline, t_start: float):
        self.X, self.Y, self.chosen, self.rng = X, Y, chosen, rng
        self.memory_budget, self.deadline, self.t_start = memory_budget, deadline, t_start
        self.m = Y.shape[0]
        self.labels = np.full(self.m, -1, np.int64)
        #: The points of motions too small for a copy: out of the later searches.
        self.aside = np.zeros(self.m, bool)
        self.found: list = []
        self.rounds: list[dict] = []
        self.parts = _Parts(Y, int(rng.integers(0, 2**31 - 1)), memory_budget) if chosen == "scans" else None
        #: The exact pipeline's blocks once a copy is found (:func:`scene_blocks`).
        self.blocks: Blocks | None = None
        #: On scans: since when parts have been searched in vain (the start, or the last copy kept), how
        #: many, and the slowest part search so far (:meth:`search_parts`' bound).
        self.vain_since, self.vain_parts, self.slowest = t_start, 0, 0.0
        #: The block of the last candidate (-1: the whole scene).
        self.current = -1
        self.least_part = (max(MIN_MODEL_POINTS, int(np.ceil(smallest_part(X, Y) * self.parts.voted)))
                           if self.parts is not None else 0)
        self.report = None

    def remaining(self) -> np.ndarray:
        return np.flatnonzero((self.labels < 0) & ~self.aside)

    def past_deadline(self) -> bool:
        return self.deadline is not None and time.perf_counter() > self.deadline

    def register_on(self, rows, share, noise=None):
        """One registration of the model on the scene ``rows`` (its record appended to ``rounds``)."""
        round_seed = int(self.rng.integers(0, 2**63 - 1))
        left = None if self.deadline is None else max(self.deadline - time.perf_counter(), 1e-3)
        t0 = time.perf_counter()
        options = {} if share is None else {"min_inlier_share": share}
        if noise is not None:
            options["noise"] = noise
        # The other instances are each found motion's rivals by design: not checked here.
        result = register(self.X, self.Y[rows], pipeline=self.chosen, seed=round_seed,
                          memory_budget=self.memory_budget, check_rivals=False,
                          time_limit=TIME_LIMIT if left is None else min(TIME_LIMIT, left), **options)
        self.rounds.append({"round": len(self.rounds), "scene_points": int(rows.size), "min_inlier_share": share,
                            "noise": noise, "support": int(result.support), "time_s": time.perf_counter() - t0,
                            "verdict": result.info.get("verdict")})
        return result

    def search(self):
        rows = self.remaining()
        if rows.size < MIN_MODEL_POINTS:
            return Stop(f"{rows.size} scene points left, fewer than the {MIN_MODEL_POINTS} an instance needs",
                        exhausted=True)
        if self.parts is not None:
            return self.search_parts(rows)
        share = expected_share(self.found, self.X.shape[0]) if self.chosen == "exact" else None
        self.current = -1
        if self.blocks is not None and not self.blocks.exhausted.all():
            in_block = self.search_blocks(rows, share)
            if in_block is not None:
                return in_block
        # The whole scene at the schedule's tolerances: the first round, and once every block was searched in
        # vain at the copies' noise (a copy of another noise, or one the blocks' searches missed).
        try:
            result = self.register_on(rows, share)
        except InputError as exc:
            if self.found:  # what the earlier rounds left is no point set a motion can be registered on
                return Stop(f"the {rows.size} scene points left cannot be registered on: {exc}", exhausted=True)
            raise
        if not result:
            reason = result.info.get("reason", "no motion beats the wrong motions on what remains")
            self.rounds[-1]["reason"] = reason
            return Stop(reason, exhausted=not _stopped_at_limit(result))
        return Candidate(result, int(result.support), rows)

    def search_blocks(self, rows, share):
        """The exact pipeline's rounds once a copy is found: one block at a time, at the copies' noise.

        The block with the most points left first; a block searched in vain
        holds no whole copy at that noise and is not searched again (until a
        copy found on the whole scene resets them).  ``None`` once every
        block is searched in vain.
        """
        blocks = self.blocks
        least = smallest_copy(self.found)
        noise = self.block_noise()
        while True:
            live = np.flatnonzero(~blocks.exhausted)
            if live.size == 0:
                return None
            inside = [blocks.rows(b, rows) for b in live]
            pick = int(np.argmax([w.size for w in inside]))
            b, here = int(live[pick]), inside[pick]
            if here.size < max(least, MIN_MODEL_POINTS):
                blocks.exhausted[b] = True
                continue
            try:
                result = self.register_at_noise(here, share, noise, least)
            except InputError as exc:
                self.rounds.append({"round": len(self.rounds), "scene_points": int(here.size), "reason": str(exc)})
                result = None
            self.rounds[-1]["block"] = b
            if result and (result.info.get("verdict") or {}).get("passed", False):
                self.current = b
                return self.whole_copy(Candidate(result, int(result.support), here), rows, share, noise)
            if result is not None:
                self.rounds[-1]["reason"] = result.info.get("reason",
                                                            "no motion beats the wrong motions in the block")
            blocks.exhausted[b] = True
            if self.past_deadline():
                return Stop("the time limit ran out before the next search", exhausted=False)

    def register_at_noise(self, rows, share, noise, least):
        """:meth:`register_on` at the copies' ``noise``; at the schedule's tolerances when a trial as large as
        a copy (``least`` points) beat the density screen there and the judge refused it at this tolerance
        (at a millionth of the spacing it may, where the schedule's next level finds the copy)."""
        result = self.register_on(rows, share, noise=noise)
        if not result and noise is not None and _best_trial(result) >= least:
            self.rounds[-1]["reason"] = result.info.get("reason", "")
            result = self.register_on(rows, share)
        return result

    def whole_copy(self, candidate, rows, share, noise):
        """The candidate again on every point left around its copy, when its block cut the copy.

        A block holds a copy cut by its side as well as whole ones; the
        pose is the copy's, but its correspondences would miss the points
        beyond the side.  The model moved by the pose, grown by its gate,
        bounds the copy: registered on the points left in that box, the
        copy gives all its correspondences.
        """
        Y, rounds = self.Y, self.rounds
        moved = self.X @ np.asarray(candidate.motion.rotation).T + np.asarray(candidate.motion.translation)
        margin = final_gate(candidate.motion)
        lo, hi = moved.min(axis=0) - margin, moved.max(axis=0) + margin
        box = rows[np.all((Y[rows] >= lo) & (Y[rows] <= hi), axis=1)]
        if np.setdiff1d(box, candidate.detail, assume_unique=True).size == 0:
            return candidate  # the block holds every point around the copy
        before = len(rounds)
        try:
            again = self.register_at_noise(box, share, noise, candidate.support)
        except InputError:
            again = None
        if again and (again.info.get("verdict") or {}).get("passed", False) and again.support >= candidate.support:
            rounds[-1].update(block=self.current, whole_copy=True)
            return Candidate(again, int(again.support), box)
        # Kept as the block gave it: the block's round stays the candidate's record (the last one).
        tried = rounds[before:]
        del rounds[before:]
        rounds[-1]["whole_copy"] = {"tried": len(tried), "reason": tried[-1].get("reason", "") if tried else ""}
        return candidate

    def block_noise(self):
        """The tolerance of the blocks' searches: the largest the copies found measured (``None``: the schedule)."""
        tol = [float(m.info["tolerance"]) for m in self.found if np.isscalar(m.info.get("tolerance"))]
        return max(tol) if tol and max(tol) > 0 else None

    def search_parts(self, rows):
        """The scans rounds: the largest part first; a part where no copy passes is set aside.

        Setting a part aside leaves the other parts as they are (each is a
        connected component of the rows), so they are found once a round.
        """
        parts, rounds = self.parts, self.rounds
        for part in scene_parts(self.Y, rows, parts.mask, parts.link, self.least_part):
            now = time.perf_counter()
            if (self.deadline is not None
                    and now - self.vain_since + self.slowest > min(TIME_LIMIT, self.deadline - self.t_start)):
                return Stop(f"the parts searched in vain since the last copy ({self.vain_parts}) took "
                            f"{now - self.vain_since:.0f} s, and one more would take the scene past one "
                            f"registration's time limit ({TIME_LIMIT:g} s)", exhausted=False)
            try:
                result = self.register_on(part, None)
                self.slowest = max(self.slowest, rounds[-1]["time_s"])
            except InputError as exc:
                result = None
                rounds.append({"round": len(rounds), "scene_points": int(part.size), "reason": str(exc)})
            rounds[-1]["part"] = True
            if result:
                verdict = result.info.get("verdict") or {}
                if verdict.get("passed", False):
                    return Candidate(result, int(result.support), part)
            if result is not None:
                rounds[-1]["reason"] = result.info.get("reason", "the part's motion did not pass its verdict")
            rounds[-1]["set_aside"] = int(part.size)
            self.aside[part] = True
            self.vain_parts += 1
            if self.past_deadline():
                return Stop("the time limit ran out before the next search", exhausted=False)
        return Stop(f"no part of the scene's surfaces left holds the {self.least_part} points a copy needs",
                    exhausted=True)

    def accept(self, candidate: Candidate) -> Judgement:
        verdict = candidate.motion.info.get("verdict") or {}
        if not verdict.get("passed", False):
            return Judgement(False, f"the best instance on what remains ({candidate.support} points) does not "
                                    "pass its verdict", verdict)
        if self.parts is not None:
            # As a scan segmentation keeps a part's motion (section 8): a right motion's pairs sit at the
            # scans' own noise, a wrong one's (a surface laid across another) spread over the gate.
            info = candidate.motion.info
            res, noise = info.get("residual_noise"), info.get("noise")
            if res is not None and noise is not None and noise > 0 and not res <= NOISE_FACTOR * noise:
                return Judgement(False, f"its pairs' residual deviation {res:.3g} is {res / noise:.1f} times the "
                                        f"scans' noise {noise:.3g}, more than {NOISE_FACTOR}", verdict,
                                 detail="noise")
        least = smallest_copy(self.found)
        if candidate.support < least:
            return Judgement(False, f"a motion of {candidate.support} points, fewer than the {least} expected of "
                                    "a copy", verdict, detail="small")
        return Judgement(True, "kept", verdict)

    def reject(self, candidate: Candidate, judgement):
        if judgement.detail == "noise":  # on scans: the part is set aside, the next one searched
            self.aside[candidate.detail] = True
            self.vain_parts += 1
            self.rounds[-1].update(kept=False, set_aside=int(candidate.detail.size), reason=judgement.reason)
            return None
        if judgement.detail != "small":
            return Stop(judgement.reason, exhausted=True)
        rows = candidate.detail
        small = rows[np.asarray(candidate.motion.correspondences, dtype=np.int64)[:, 1]]
        if self.current >= 0:  # found in a block (a copy cut by its side?): its points stay in the other blocks
            self.blocks.set_aside(self.current, small, self.m)
        else:
            self.aside[small] = True
        self.rounds[-1].update(kept=False, set_aside=int(candidate.support), reason=judgement.reason)
        return None

    def remove(self, candidate: Candidate, judgement) -> tuple:
        result, rows = candidate.motion, candidate.detail
        found, Y = self.found, self.Y
        k = len(found)
        pairs = np.asarray(result.correspondences, dtype=np.int64).copy()
        pairs[:, 1] = rows[pairs[:, 1]]
        taken = [pairs[:, 1]]
        g = final_gate(result)
        if g > 0:
            moved = self.X @ np.asarray(result.rotation).T + np.asarray(result.translation)
            free = self.remaining()  # on scans beyond the part searched: the copy's points off the voted surfaces
            near = cKDTree(moved).query(Y[free], k=1, distance_upper_bound=g)[0]
            taken.append(free[np.isfinite(near)])
        taken = np.unique(np.concatenate(taken))
        self.labels[taken] = k
        info = dict(result.info, instance=k, gate=g, scene_points=int(taken.size))
        motion = dataclasses.replace(result, correspondences=pairs, info=info)
        found.append(motion)
        self.rounds[-1].update(kept=True, scene_points_taken=int(taken.size))
        self.vain_since, self.vain_parts = time.perf_counter(), 0
        if self.chosen == "exact" and not found[:-1]:
            # once the first copy says how far a copy reaches (the model's extent and its gate's margin)
            self.blocks = scene_blocks(Y, model_diameter(self.X) + 2.0 * g)
        elif self.blocks is not None and self.current < 0:
            self.blocks.exhausted[:] = False  # found on the whole scene: the blocks again, at the copies' noise now
        self.report(float(np.mean(self.labels >= 0)), f"instance {k}: {motion.support} correspondences")
        return (motion,)

    def run(self, why: str, report, max_instances) -> Instances:
        """The peel loop to its end; the copies smaller than the smallest copy dropped, the labels renumbered."""
        self.report = report
        labels, found = self.labels, self.found
        outcome = peel_loop(self.search, self.accept, self.remove, reject=self.reject, max_motions=max_instances,
                            deadline=self.deadline, max_rounds=self.m + 1, full="max_instances reached",
                            late="the time limit ran out before the next search")
        least = smallest_copy(found)
        kept = [m for m in found if m.support >= least]
        dropped = [{"support": int(m.support), "angle_deg": float(m.angle_deg)} for m in found if m.support < least]
        if dropped:  # found before a better copy raised the bar: renumber the rest
            relabel = np.full(len(found) + 1, -1, np.int64)
            for new, m in enumerate(kept):
                relabel[m.info["instance"]] = new
            labels[:] = relabel[labels]
            kept = [dataclasses.replace(m, info=dict(m.info, instance=k)) for k, m in enumerate(kept)]
        report(1.0, f"{len(kept)} instances")
        info = {"reason": outcome.reason, "exhausted": outcome.exhausted, "pipeline": self.chosen,
                "pipeline_reason": why, "rounds": self.rounds, "n_model": int(self.X.shape[0]),
                "n_scene": int(self.m), "model_size": model_size(self.X), "smallest_copy": least,
                "dropped": dropped, "time_s": time.perf_counter() - self.t_start}
        return Instances(tuple(kept), labels, info)
