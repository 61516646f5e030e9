"""A motion model defined here, in a test file, runs through ``register`` and ``segment``.

Nothing outside this file knows it: it follows :class:`gatv.models.MotionModel`
(the protocol's members and ``search_policy()``, here the defaults) and joins
the registry with :func:`gatv.models.register_model`.  A pure translation in
3D: one point fixes it (``sample_size`` 1); its trial motions are the
differences ``y - x`` of a source point and every target point, scored by
how many moved source points land within the gate of a target point.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import pytest
from scipy.spatial import cKDTree

import gatv
from gatv.models.rigid.congruent import TrialMotions
from gatv.errors import InputError
from gatv.models import MotionModel, SearchPolicy, get_model, model_names, register_model
from gatv.models.base import homogeneous, matrix_residuals
from gatv.motion import RigidMotion
from gatv.motions import segment
from gatv.stats import chance_support


class TranslationIndex:
    """The target's k-d tree and its bounding box (the measure random translations scatter points over)."""

    def __init__(self, target: np.ndarray, radius: float):
        self.target = target
        self.tree = cKDTree(target)
        lo, hi = target.min(axis=0), target.max(axis=0)
        self.volume = float(np.prod(np.maximum(hi - lo, radius)))
        self.radius = float(radius)

    def set_radius(self, r: float) -> None:
        self.radius = float(r)

    def __copy__(self):
        new = object.__new__(TranslationIndex)
        new.__dict__.update(self.__dict__)
        return new


@dataclass(frozen=True)
class Translation:
    """``x' = x + t``: 3D points, one point a sample, 3 degrees of freedom."""

    name: str = "translation"
    dim: int = 3
    sample_size: int = 1
    n_params: int = 3

    def check_points(self, points, name: str) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 2 or not np.isfinite(p).all():
            raise InputError(f"Expected `{name}` to be (N, 3) finite points, N >= 2.")
        return p

    def fit(self, source, target, weights=None):
        w = np.ones(len(source)) if weights is None else np.asarray(weights, dtype=np.float64)
        return homogeneous(np.eye(3), np.average(target - source, axis=0, weights=w))

    def residuals(self, matrix, source, target):
        return matrix_residuals(matrix, source, target)

    def index(self, target, radius, *, memory_budget=None):
        return TranslationIndex(target, radius)

    def trial_motions(self, source, index, *, eps, max_triples, rng, keep, max_matches, accept=None, **options):
        picks = rng.choice(source.shape[0], min(int(max_triples), source.shape[0]), replace=False)
        shifts = np.concatenate([index.target[rng.permutation(index.target.shape[0])[:max_matches]] - source[i]
                                 for i in picks])
        counts = np.array([np.count_nonzero(np.isfinite(
            index.tree.query(source + t, distance_upper_bound=index.radius)[0])) for t in shifts], np.int64)
        order = np.argsort(-counts, kind="stable")[:keep]
        return TrialMotions(np.repeat(np.eye(3)[None], order.size, axis=0), shifts[order], counts[order],
                            int(accept or 0), int(picks.size), int(shifts.shape[0]))

    def tokens(self, source, target):
        return target - source

    def consistent(self, tokens, ref, tau):
        d = tokens.coords
        return np.flatnonzero(np.linalg.norm(d - d[ref], axis=1) <= tau)

    def chance(self, n_source, n_target, measure, gate, n_tests=1.0):
        return chance_support(n_source, n_target, measure, gate, n_tests=n_tests, dim=3,
                              sample_size=self.sample_size)

    def result(self, matrix, correspondences, *, score, rms, info):
        return RigidMotion(matrix[:3, :3], matrix[:3, 3], correspondences, score, rms, info)

    def search_policy(self) -> SearchPolicy:
        return SearchPolicy()


MODEL = register_model(Translation())


def _cloud(n, seed):
    return np.random.default_rng(seed).uniform(0.0, 10.0, (n, 3))


def test_the_model_follows_the_protocol_and_is_registered():
    assert isinstance(MODEL, MotionModel)
    assert get_model("translation") is MODEL
    assert "translation" in model_names()
    assert copy.copy(MODEL.index(_cloud(10, 0), 0.1)).radius == 0.1


def test_register_recovers_a_translation_among_outliers():
    x = _cloud(60, 1)
    t = np.array([1.5, -2.0, 0.75])
    y = np.vstack([x[:40] + t, _cloud(20, 2)])
    m = gatv.register(x, y, model="translation", seed=0)
    assert m and m.support >= 40
    np.testing.assert_allclose(m.translation, t, atol=1e-9)
    np.testing.assert_allclose(m.rotation, np.eye(3))
    assert {(i, i) for i in range(40)} <= set(map(tuple, m.correspondences.tolist()))
    assert m.info["verdict"]["passed"] and m.info["verdict"]["support"] == m.support


def test_segment_recovers_two_translations():
    x = _cloud(80, 3)
    ts = np.array([[3.0, 0.0, 0.0], [0.0, -4.0, 1.0]])
    y = np.vstack([x[:40] + ts[0], x[40:75] + ts[1], _cloud(10, 4)])
    seg = segment(x, y, model="translation", seed=0)
    assert len(seg) == 2
    for m, t in zip(seg.motions, ts):
        np.testing.assert_allclose(m.translation, t, atol=1e-9)
    assert [m.support for m in seg.motions] == [40, 35]


def test_a_built_in_name_is_refused_and_a_non_model_named():
    with pytest.raises(InputError, match="built-in"):
        register_model(Translation(name="rigid"))
    with pytest.raises(InputError, match="lacks"):
        register_model(object())
