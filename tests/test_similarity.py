"""The similarity model (rotation, uniform scale, translation): gatv.models.similarity."""

from __future__ import annotations

import dataclasses
import itertools
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gatv import register, stages
from gatv.models.rigid.congruent_kernels import similar_triple_hypotheses
from gatv._fit_kernels import umeyama3
from gatv.models.rigid.congruent import TargetIndex
from gatv.datasets import random_rotation, synthetic_trial
from gatv.errors import InputError
from gatv.fitting import umeyama
from gatv.models import MotionModel, get_model
from gatv.models.similarity import (
    MODEL,
    Similarity,
    SimilarityMotion,
    order_triples,
    similar_trial_motions,
)

BUNNY = Path("/work/shared/data/nonrigid_bcpd_bunny")


def _scene(scale, outlier_fraction=0.5, n_inliers=50, seed=0, centre=(1.0, -2.0, 0.5)):
    """Table 2's protocol (:func:`gatv.datasets.synthetic_trial`), the target scaled about ``centre``."""
    trial = synthetic_trial(outlier_fraction, n_inliers=n_inliers, seed=seed)
    c = np.asarray(centre)
    target = c + scale * (trial.target - c)
    translation = scale * trial.translation + (1.0 - scale) * c
    return trial.source, target, trial.rotation, translation, trial.true_pairs


def _pairs(m):
    return set(map(tuple, np.asarray(m.correspondences).tolist()))


# ------------------------------------------------------------ registration
@pytest.mark.parametrize("scale", [0.1, 0.5, 2.0, 10.0])
def test_exact_recovery_with_half_outliers(scale):
    x, y, R, t, true = _scene(scale)
    m = register(x, y, model="similarity")
    assert isinstance(m, SimilarityMotion) and m
    assert m.model == "similarity" and m.info["model"] == "similarity"
    assert m.scale == pytest.approx(scale, rel=1e-9)
    np.testing.assert_allclose(m.rotation, R, atol=1e-9)
    np.testing.assert_allclose(m.translation, t, atol=1e-8 * max(1.0, scale))
    assert _pairs(m) == set(map(tuple, true.tolist()))
    assert m.rms <= 1e-9 * scale
    np.testing.assert_allclose(m.transform(x[true[:, 0]]), y[true[:, 1]], atol=1e-8 * max(1.0, scale))


def test_swapping_source_and_target_gives_the_inverse():
    x, y, _, _, true = _scene(2.0, seed=3)
    fwd = register(x, y, model="similarity")
    back = register(y, x, model="similarity")
    assert fwd and back
    assert back.scale == pytest.approx(0.5, rel=1e-9)
    np.testing.assert_allclose(back.matrix, fwd.inverse().matrix, atol=1e-9)
    np.testing.assert_allclose(back.matrix @ fwd.matrix, np.eye(4), atol=1e-9)
    assert _pairs(back) == {(j, i) for i, j in _pairs(fwd)} == {(j, i) for i, j in true.tolist()}


def test_correspondences_are_one_to_one_and_sorted():
    x, y, *_ = _scene(0.5, outlier_fraction=0.6, seed=5)
    m = register(x, y, model="similarity")
    c = m.correspondences
    assert len(set(c[:, 0])) == len(c) == len(set(c[:, 1]))
    assert np.all(np.diff(c[:, 0]) > 0)
    assert m.support == c.shape[0]


def test_narrow_scale_range_through_the_model_object():
    x, y, *_ = _scene(2.0, seed=1)
    m = register(x, y, model=Similarity(scale_range=(1.5, 3.0)))
    assert m and m.scale == pytest.approx(2.0, rel=1e-9)
    miss = register(x, y, model=Similarity(scale_range=(3.0, 5.0)), max_triples=64)
    assert not miss and miss.support == 0 and "chance" in miss.info["reason"]
    assert "reason" in miss.to_dict()


def test_rigid_data_gives_scale_one():
    x, y, R, _, _ = _scene(1.0, seed=2)
    m = register(x, y, model="similarity")
    assert m.scale == pytest.approx(1.0, rel=1e-9)
    np.testing.assert_allclose(m.rotation, R, atol=1e-9)


# ------------------------------------------------------------------- model
def test_model_registry_and_sizes():
    model = get_model("similarity")
    assert model is MODEL and isinstance(model, MotionModel)
    assert (model.name, model.dim, model.sample_size, model.n_params) == ("similarity", 3, 3, 7)
    assert repr(model) == "Similarity()"
    assert repr(Similarity(scale_range=(0.5, 2))) == "Similarity(scale_range=(0.5, 2.0))"


def test_fit_and_residuals():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(20, 3))
    R = random_rotation(rng, (0.0, 360.0))
    y = 3.0 * x @ R.T + [1.0, 2.0, 3.0]
    T = MODEL.fit(x, y)
    np.testing.assert_allclose(T[:3, :3], 3.0 * R, atol=1e-12)
    np.testing.assert_allclose(MODEL.residuals(T, x, y), 0.0, atol=1e-12)
    np.testing.assert_allclose(MODEL.residuals(T, x, y + [0.0, 0.0, 0.5]), 0.5, atol=1e-12)


def test_consistent_removes_a_residual_scale():
    # True pairs after a trial whose scale is 0.2% off, plus random tokens:
    # eq. 41 alone (length half) drops the long true pairs at a tight tau.
    rng = np.random.default_rng(4)
    x = rng.uniform(-5, 5, (60, 3))
    y = x + [2.0, -1.0, 0.5]
    xs = 1.002 * x
    false_x = rng.uniform(-5, 5, (30, 3))
    false_y = rng.uniform(-5, 5, (30, 3))
    src = np.vstack([xs, false_x])
    tgt = np.vstack([y, false_y])
    pairs = np.stack([np.arange(90), np.arange(90)], axis=1)
    tokens = stages.Tokens(pairs, src, tgt, MODEL.tokens(src, tgt))
    from gatv.models.rigid import eq41_consistent

    rigid = eq41_consistent(tgt - src, tgt + src, pairs, 0, 1e-3)
    cons = MODEL.consistent(tokens, 0, 1e-3)
    assert rigid.size < 60
    assert set(range(60)) <= set(cons.tolist()) and len(set(cons.tolist()) - set(range(60))) <= 1


def test_chance_needs_a_point_beyond_the_sample():
    from gatv.stats import chance_support

    assert MODEL.chance(500, 500, 1000.0, 1e-6) == chance_support(500, 500, 1000.0, 1e-6) == 4
    assert MODEL.chance(500, 500, 1000.0, 0.5, 1e4) == chance_support(500, 500, 1000.0, 0.5, 1e4)


# ------------------------------------------------------------------ motion
@settings(max_examples=40, deadline=None)
@given(st.floats(0.1, 10.0), st.integers(0, 2**31 - 1))
def test_motion_identities(scale, seed):
    rng = np.random.default_rng(seed)
    R = random_rotation(rng, (0.0, 360.0))
    t = rng.uniform(-10, 10, 3)
    pairs = np.array([[0, 3], [1, 4], [2, 5]])
    m = SimilarityMotion(scale, R, t, pairs, score=3.0, rms=0.0, info={"a": 1})
    T = m.matrix
    np.testing.assert_allclose(T[:3, :3], scale * R, atol=1e-12 * scale)
    np.testing.assert_allclose(T[3], [0, 0, 0, 1])
    again = SimilarityMotion.from_matrix(T, pairs)
    assert again.scale == pytest.approx(scale, rel=1e-12)
    np.testing.assert_allclose(again.rotation, R, atol=1e-10)
    p = rng.normal(size=(7, 3)) * 5
    np.testing.assert_allclose(m.transform(p), scale * p @ R.T + t, atol=1e-9 * scale)
    inv = m.inverse()
    assert isinstance(inv, SimilarityMotion) and inv.scale == pytest.approx(1.0 / scale, rel=1e-12)
    np.testing.assert_allclose(inv.matrix, np.linalg.inv(T), atol=1e-9 * max(1.0, 1.0 / scale))
    np.testing.assert_allclose(inv.transform(m.transform(p)), p, atol=1e-9 * max(1.0, scale))
    np.testing.assert_array_equal(inv.correspondences, pairs[:, ::-1])
    np.testing.assert_allclose(inv.inverse().matrix, T, atol=1e-9 * max(1.0, scale))
    d = json.loads(json.dumps(m.to_dict()))
    assert {"model", "matrix", "correspondences", "support", "score", "rms", "rotation",
            "translation", "scale", "angle_deg"} <= set(d)
    assert d["model"] == "similarity" and d["support"] == 3 and d["scale"] == pytest.approx(scale)
    np.testing.assert_allclose(d["matrix"], T)
    np.testing.assert_allclose(d["rotation"], R)
    assert d["angle_deg"] == pytest.approx(m.angle_deg)
    assert 0.0 <= m.angle_deg <= 180.0 and len(m.rotor) == 4 and bool(m)


def test_motion_is_frozen_and_failure_is_falsy():
    m = SimilarityMotion(2.0, np.eye(3), [1.0, 2.0, 3.0])
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.scale = 3.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        m.rotation[0, 0] = 2.0
    bad = stages.failure("similarity", "nothing", {})
    assert isinstance(bad, SimilarityMotion) and not bad and bad.info["reason"] == "nothing"
    assert bad.to_dict()["reason"] == "nothing" and bad.scale == 1.0
    assert "scale=2" in repr(m)


# ----------------------------------------------------------------- kernels
@settings(max_examples=40, deadline=None)
@given(st.integers(3, 12), st.floats(0.1, 10.0), st.integers(0, 2**31 - 1))
def test_umeyama3_matches_numpy(k, scale, seed):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(k, 3)) * 3
    R = random_rotation(rng, (0.0, 360.0))
    y = scale * x @ R.T + rng.uniform(-5, 5, 3) + rng.normal(scale=0.01, size=(k, 3))
    s0, R0, t0 = umeyama(x, y)
    s1, R1, t1 = umeyama3(np.ascontiguousarray(x), np.ascontiguousarray(y))
    assert s1 == pytest.approx(s0, rel=1e-9)
    np.testing.assert_allclose(R1, R0, atol=1e-9)
    np.testing.assert_allclose(t1, t0, atol=1e-8 * max(1.0, scale))
    assert np.linalg.det(R1) == pytest.approx(1.0)


def _reference(source, target, tri, eps, s_min, s_max, radius):
    """Brute force over ordered target triples: (best distinct-target support, n similar) per triple."""
    out = []
    M = target.shape[0]
    dist = np.linalg.norm(target[:, None] - target[None], axis=2)
    for a, b, c in tri:
        dab = np.linalg.norm(source[a] - source[b])
        dac = np.linalg.norm(source[a] - source[c])
        dbc = np.linalg.norm(source[b] - source[c])
        rho1, rho2 = dac / dab, dbc / dab
        best, n = -1, 0
        for k, l, m in itertools.permutations(range(M), 3):
            dkl = dist[k, l]
            if not (s_min * dab - eps <= dkl <= s_max * dab + eps):
                continue
            if abs(dist[k, m] - rho1 * dkl) > eps * (1 + rho1):
                continue
            if abs(dist[l, m] - dkl / dab * dbc) > eps * (1 + rho2):
                continue
            s, R, t = umeyama(source[[a, b, c]], target[[k, l, m]])
            if not s_min <= s <= s_max:
                continue
            n += 1
            best = max(best, _distinct_support(s * R, t, source, target, radius))
        out.append((best, n))
    return out


def _distinct_support(A, t, source, target, radius):
    moved = source @ A.T + t
    taken, count = set(), 0
    for p in moved:
        d = np.linalg.norm(target - p, axis=1)
        j = int(np.argmin(d))
        if d[j] <= radius and j not in taken:
            taken.add(j)
            count += 1
    return count


@pytest.mark.parametrize("eps", [1e-6, 0.3])
def test_similar_triple_kernel_against_numpy_reference(eps):
    rng = np.random.default_rng(7)
    source = rng.uniform(-3, 3, (7, 3))
    R = random_rotation(rng, (0.0, 360.0))
    target = np.vstack([2.5 * source[:5] @ R.T + [1.0, 0.0, -2.0], rng.uniform(-6, 6, (5, 3))])
    target = target[rng.permutation(10)]
    tri = order_triples(source, np.array(list(itertools.combinations(range(7), 3))))
    radius = max(eps, 1e-6)
    index = TargetIndex(target, radius)
    scores, A, t, nm = similar_triple_hypotheses(
        source, target, tri, np.zeros(len(tri), np.int64), index.ndist, index.nidx, eps, 0.1, 10.0,
        index.start, index.order, index.origin, index.cell, index.dims, index.radius, 10**6)
    ref = _reference(source, target, tri, eps, 0.1, 10.0, radius)
    assert [int(v) for v in scores] == [r[0] for r in ref]
    assert [int(v) for v in nm] == [r[1] for r in ref]
    for q in np.flatnonzero(scores >= 0):
        assert _distinct_support(A[q], t[q], source, target, radius) == scores[q]
    # all-inlier triples find the true similarity and its 5 inliers
    inl = [q for q, (a, b, c) in enumerate(tri) if max(a, b, c) < 5]
    assert all(scores[q] == 5 for q in inl)
    q = inl[0]
    np.testing.assert_allclose(A[q], 2.5 * R, atol=1e-6)
    if eps > 0.1:
        assert nm.sum() > len(inl)  # the loose tolerance meets false similar triangles too


def test_order_triples_puts_the_longest_side_first():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(30, 3))
    tri = np.array(list(itertools.combinations(range(30), 3)))[::7]
    out = order_triples(p, tri)
    assert np.array_equal(np.sort(out, axis=1), np.sort(tri, axis=1))
    ab = np.linalg.norm(p[out[:, 0]] - p[out[:, 1]], axis=1)
    ac = np.linalg.norm(p[out[:, 0]] - p[out[:, 2]], axis=1)
    bc = np.linalg.norm(p[out[:, 1]] - p[out[:, 2]], axis=1)
    assert np.all(ab >= ac) and np.all(ab >= bc)


def test_trial_motions_hold_the_linear_part():
    x, y, R, t, _ = _scene(4.0, seed=2)
    index = TargetIndex(y, 1e-6)
    trials = similar_trial_motions(x, index, eps=2e-6, max_triples=256,
                                   rng=np.random.default_rng(0), keep=2)
    assert len(trials) >= 1 and trials.support[0] == 50
    np.testing.assert_allclose(trials.rotations[0], 4.0 * R, atol=1e-8)
    np.testing.assert_allclose(trials.matrices[0][:3, 3], t, atol=1e-7)
    assert trials.n_triples <= 256


# --------------------------------------------------------------- bad input
def test_planar_points_name_the_argument():
    x3 = np.random.default_rng(0).normal(size=(20, 3))
    with pytest.raises(InputError, match="`source`.*\\(N, 3\\).*similarity"):
        register(x3[:, :2], x3, model="similarity")
    with pytest.raises(InputError, match="`target`.*\\(N, 3\\).*affine2d"):
        register(x3, x3[:, :2], model="similarity")


@pytest.mark.parametrize("bad", [(0.0, 1.0), (2.0, 1.0), (1.0, np.inf), "ab", (1.0,), None])
def test_bad_scale_range(bad):
    with pytest.raises(InputError, match="scale_range"):
        Similarity(scale_range=bad)


def test_bad_motion_values():
    with pytest.raises(InputError, match="scale"):
        SimilarityMotion(-1.0, np.eye(3), np.zeros(3))
    with pytest.raises(InputError, match="rotation"):
        SimilarityMotion(1.0, np.eye(2), np.zeros(3))
    with pytest.raises(InputError, match="det"):
        SimilarityMotion.from_matrix(np.diag([-1.0, 1.0, 1.0, 1.0]))
    with pytest.raises(InputError, match="collinear"):
        register(np.outer(np.arange(5.0), [1.0, 2.0, 3.0]), np.eye(3), model="similarity")


def _lattice_sites(rng, n):
    """Random sites of one lattice (period 1.5), jittered by 0.05: unrelated sets with shared structure."""
    return rng.integers(-4, 5, (n, 3)).astype(float) * 1.5 + rng.normal(0, 0.05, (n, 3))


def test_two_samples_of_one_lattice_give_no_similarity():
    """Site on site, two unrelated samples of a lattice hold 18 pairs against a Poisson level that
    takes the target as spread through its box: found before the similarity held its motions against
    their turned and shifted copies (``turned_copies``); one of them, 0.6 deg off, holds 17."""
    rng = np.random.default_rng(2001)
    n = int(rng.integers(120, 400))
    x, y = _lattice_sites(rng, n), _lattice_sites(rng, n)
    m = register(x, y, model="similarity", seed=0)
    assert not m and m.info["reason"].startswith("ambiguous: a motion")
    assert m.info["rivals"]["ambiguous"] and not m.info["verdict"]["passed"]
    kept = register(x, y, model="similarity", seed=0, check_rivals=False)
    assert kept and kept.info["rivals"] == m.info["rivals"]  # measured either way


@settings(max_examples=8, deadline=None)
@given(st.floats(0.2, 5.0), st.integers(0, 2**31 - 1))
def test_a_true_similarity_on_structured_points_is_not_its_copies(scale, seed):
    """Half the points on a plane, half in a blob (where unrelated sets lay plane on plane), moved by
    a similarity: the motion is found, and none of its turned or shifted copies rivals it."""
    rng = np.random.default_rng(seed)
    n = 150
    x = np.vstack([np.column_stack([rng.uniform(-6, 6, (n // 2, 2)), rng.normal(0, 0.05, n // 2)]),
                   rng.normal(0, 1.5, (n - n // 2, 3)) + rng.uniform(-4, 4, 3)])
    R = random_rotation(rng, (0.0, 180.0))
    t = rng.uniform(-10, 10, 3)
    y = scale * x @ R.T + t
    y = np.vstack([y, rng.uniform(y.min(axis=0), y.max(axis=0), (n // 2, 3))])
    m = register(x, y, model="similarity", seed=seed)
    assert m and m.scale == pytest.approx(scale, rel=1e-9)
    np.testing.assert_allclose(m.rotation, R, atol=1e-9)
    rivals = m.info["rivals"]
    assert not rivals["ambiguous"] and rivals["rival"] < 0.5 * rivals["support"]


# ------------------------------------------------------------------- slow
@pytest.mark.slow
@settings(max_examples=12, deadline=None)
@given(st.sampled_from([0.1, 0.3, 1.7, 6.0, 10.0]), st.sampled_from([0.0, 0.5, 0.8]),
       st.integers(0, 10**6))
def test_exact_recovery_sweep(scale, outlier_fraction, seed):
    x, y, R, _, true = _scene(scale, outlier_fraction, seed=seed)
    m = register(x, y, model="similarity", seed=seed)
    assert m.scale == pytest.approx(scale, rel=1e-9)
    np.testing.assert_allclose(m.rotation, R, atol=1e-9)
    assert _pairs(m) == set(map(tuple, true.tolist()))


@pytest.mark.slow
def test_unrelated_point_sets_give_no_motion():
    # Before the +1 in Similarity.chance, a random similar triangle (support
    # 3, its own sample) passed the exact tolerance's chance level here.
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-5, 5, (500, 3)), rng.uniform(-5, 5, (500, 3))
    m = register(x, y, model="similarity", max_triples=1000)
    assert not m and m.info["reason"]


# Not slow (3 s): in the default suite, strict, so that the day it passes is seen.
@pytest.mark.skipif(not (BUNNY / "bunny-y.txt").exists(), reason="BCPD bunny data not present")
@pytest.mark.xfail(strict=True, reason=(
    "deformed bunny: the non-rigid residual (median 0.156, 4.5% of the diagonal) is far above the "
    "point spacing, so side-ratio matching at that tolerance meets millions of false similar "
    "triangles per source triple and the 64 scored ones miss the true one; the volume chance level "
    "is also meaningless on a surface"))
def test_deformed_bcpd_bunny():
    x = np.loadtxt(BUNNY / "bunny-x.txt")
    y = np.loadtxt(BUNNY / "bunny-y.txt")
    rows = np.random.default_rng(0).choice(len(x), 200, replace=False)
    m = register(x[rows], y[rows], model="similarity", noise=0.05, max_triples=500)
    assert m
    assert m.scale == pytest.approx(0.83, abs=0.05)
    assert m.angle_deg == pytest.approx(93.0, abs=5.0)
