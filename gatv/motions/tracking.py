"""A model found in each frame of a sequence, identities kept by the closest pose (section 4.1, Fig. 9).

The paper follows a robotic arm through a sequence of stereo
reconstructions: the model is picked once and found in each later
reconstruction with no tracking between frames — "this is not a video".
:func:`track` does the same for every instance of the model: each frame
is searched on its own (:func:`gatv.motions.instances`, no motion model
and no prior from the previous frame), and only afterwards are the
instances of consecutive frames given identities, by the closest pose
(a Hungarian assignment on :func:`gatv.motions.instance_search.pose_distance`:
the rotation angle between two poses plus the distance of the moved
model's centroid over the model's size).  An identity not found in a
frame is absent there, and the result says so.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from .._validation import as_rng, check_int, check_positive, check_progress, frozen_array
from ..errors import InputError
from ..models import get_model
from ..registration import TIME_LIMIT, checked_pipeline
from .instance_search import (
    TIME_LIMIT_ROUNDS,
    Instances,
    model_size,
    peel_instances,
    pose_distance,
    validate_model,
)

__all__ = ["Track", "assign_identities", "track"]


@dataclass(frozen=True, eq=False)
class Track:
    """The instances of a model in each frame, with identities kept across frames.

    Attributes
    ----------
    frames : tuple of Instances
        What :func:`gatv.motions.instances` found in each frame, searched
        on its own.
    identities : tuple of tuple of int
        ``identities[f][k]``: the identity of instance ``k`` of frame ``f``.
    present : (F, I) ndarray of bool
        Whether identity ``i`` was found in frame ``f``.
    info : dict
        ``time_s``, ``pipeline`` and ``model_size``; ``missing``: per frame,
        the identities seen in an earlier frame and absent from it.
    """

    frames: tuple
    identities: tuple
    present: np.ndarray
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "frames", tuple(self.frames))
        object.__setattr__(self, "identities", tuple(tuple(int(i) for i in ids) for ids in self.identities))
        object.__setattr__(self, "present", frozen_array(np.asarray(self.present, bool).reshape(
            len(self.frames), -1), bool))

    @property
    def n_identities(self) -> int:
        """How many distinct instances the sequence showed."""
        return int(self.present.shape[1])

    def __len__(self) -> int:
        return len(self.frames)

    def __bool__(self) -> bool:
        return any(bool(f) for f in self.frames)

    def pose(self, identity: int, frame: int):
        """The motion of ``identity`` in ``frame`` (model to that frame), ``None`` when absent there."""
        ids = self.identities[frame]
        return self.frames[frame].instances[ids.index(identity)] if identity in ids else None

    def missing(self, frame: int) -> tuple:
        """Identities seen before ``frame`` and not found in it."""
        return tuple(self.info.get("missing", [()] * len(self.frames))[frame])

    def to_dict(self) -> dict:
        """JSON-friendly dictionary: per frame its instances and their identities."""
        return {"n_frames": len(self.frames), "n_identities": self.n_identities,
                "frames": [{"identities": list(ids), "missing": list(self.missing(f)), **fr.to_dict()}
                           for f, (fr, ids) in enumerate(zip(self.frames, self.identities))],
                "present": self.present.tolist()}

    def __repr__(self) -> str:
        return f"Track({len(self.frames)} frames, {self.n_identities} identities, " \
               f"found per frame {[len(f) for f in self.frames]})"


def assign_identities(frames: Sequence[Instances], centre: np.ndarray, size: float) -> tuple[list, np.ndarray]:
    """Identities of the instances of each frame, by the closest pose to each identity's last one.

    Frame by frame, a Hungarian assignment
    (:func:`scipy.optimize.linear_sum_assignment`) pairs the frame's
    instances with the identities seen so far, at the cost
    :func:`gatv.motions.instance_search.pose_distance` from each identity's last
    pose; an instance left over starts a new identity.  No motion model is
    assumed between frames (the paper's frames are not a video).  Returns
    ``(identities, present)`` as :class:`Track` has them.
    """
    last: list = []  # each identity's latest pose
    identities: list = []
    for frame in frames:
        poses = list(frame.instances)
        ids = [-1] * len(poses)
        if last and poses:
            cost = np.array([[pose_distance(p, q, centre, size) for q in last] for p in poses])
            rows, cols = linear_sum_assignment(cost)
            for r, c in zip(rows, cols):
                ids[r] = int(c)
        for k, p in enumerate(poses):
            if ids[k] < 0:
                ids[k] = len(last)
                last.append(p)
            else:
                last[ids[k]] = p
        identities.append(tuple(ids))
    present = np.zeros((len(identities), len(last)), bool)
    for f, ids in enumerate(identities):
        present[f, list(ids)] = True
    return identities, present


def track(
    model,
    frames,
    *,
    seed=0,
    progress=None,
    memory_budget: float | None = None,
    max_instances: int | None = None,
    pipeline: str = "auto",
    time_limit: float | None = TIME_LIMIT_ROUNDS * TIME_LIMIT,
) -> Track:
    """Every instance of ``model`` in each of ``frames``, with identities kept by the closest pose.

    Each frame is searched on its own, as :func:`gatv.motions.instances`
    does, with the same ``seed`` (the paper's section 4.1: the model found
    in each reconstruction, no tracking between frames); identities are
    then given by :func:`assign_identities`.

    Parameters
    ----------
    model : (N, 3) array_like or object with ``.points``
    frames : sequence of (M_f, 3) array_like or objects with ``.points``
        At least one frame.
    seed, memory_budget, max_instances, pipeline :
        As :func:`gatv.motions.instances`; the pipeline is chosen for each
        frame.
    progress : callable, optional
        ``progress(fraction, message)``: frames done.
    time_limit : float or None
        Seconds for each frame, as :func:`gatv.motions.instances`'s.

    Returns
    -------
    Track

    Raises
    ------
    InputError
        No frames (names ``frames``), bad points (names ``model`` or
        ``frames[f]``), bad options.
    """
    t_start = time.perf_counter()
    X = validate_model(model, "model")
    if isinstance(frames, np.ndarray) or not isinstance(frames, Sequence) or isinstance(frames, (str, bytes)):
        raise InputError(f"Expected `frames` to be a list of point sets, got {type(frames).__name__}.")
    if len(frames) == 0:
        raise InputError("Expected `frames` to hold at least one frame, got an empty list.")
    rigid = get_model("rigid")
    scenes = [rigid.check_points(f, f"frames[{k}]") for k, f in enumerate(frames)]
    max_instances = check_int(max_instances, "max_instances", 1, allow_none=True)
    time_limit = check_positive(time_limit, "time_limit", allow_none=True)
    report = check_progress(progress)
    seed = as_rng(seed) if isinstance(seed, np.random.Generator) else check_int(seed, "seed", 0)
    found = []
    for k, Y in enumerate(scenes):
        t0 = time.perf_counter()
        chosen, why, _ = checked_pipeline(X, Y, "rigid", pipeline, memory_budget)
        rng = seed if isinstance(seed, np.random.Generator) else as_rng(seed)
        deadline = None if time_limit is None else t0 + time_limit
        found.append(peel_instances(X, Y, chosen, why, rng, check_progress(None), memory_budget, max_instances,
                                    deadline, t0))
        report((k + 1) / len(scenes), f"frame {k}: {len(found[-1])} instances")
    size = model_size(X)
    identities, present = assign_identities(found, X.mean(axis=0), size)
    missing, seen = [], set()
    for ids in identities:
        missing.append(tuple(sorted(seen - set(ids))))
        seen |= set(ids)
    info = {"time_s": time.perf_counter() - t_start, "model_size": size, "missing": missing,
            "pipelines": [f.info["pipeline"] for f in found]}
    return Track(tuple(found), tuple(identities), present, info)

