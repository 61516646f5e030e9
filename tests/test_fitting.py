"""The merged least-squares fits: numpy Kabsch/Umeyama, their numba twins, stacks."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from gatv._fit_kernels import _cross, kabsch3, triangle_pose, umeyama3
from gatv.errors import InputError
from gatv.fitting import fit_rigid, kabsch, umeyama
from gatv.models.rigid import check_spread
from gatv.ga import Rotor


def _motion(seed):
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    R = Rotor.from_axis_angle(axis, rng.uniform(0, np.pi)).as_matrix()
    return rng, R, rng.uniform(-5, 5, 3)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(3, 40))
def test_kabsch_recovers_exact_motions(seed, k):
    rng, R, t = _motion(seed)
    x = rng.normal(size=(k, 3)) * 3
    Rf, tf = kabsch(x, x @ R.T + t)
    assert np.allclose(Rf, R, atol=1e-9)
    assert np.allclose(tf, t, atol=1e-9)
    assert np.isclose(np.linalg.det(Rf), 1.0)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(0.1, 10.0))
def test_umeyama_recovers_exact_similarities(seed, scale):
    rng, R, t = _motion(seed)
    x = rng.normal(size=(12, 3))
    s, Rf, tf = umeyama(x, scale * x @ R.T + t)
    assert s == pytest.approx(scale, rel=1e-9)
    assert np.allclose(Rf, R, atol=1e-8)
    assert np.allclose(tf, t, atol=1e-8)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(3, 12))
def test_numba_kabsch3_matches_numpy(seed, k):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(k, 3))
    y = rng.normal(size=(k, 3))  # not a rigid copy: a genuine least-squares problem
    R0, t0 = kabsch(x, y)
    R1, t1 = kabsch3(np.ascontiguousarray(x), np.ascontiguousarray(y))
    assert np.allclose(R0, R1, atol=1e-10)
    assert np.allclose(t0, t1, atol=1e-10)


def _spread_by_svd(points) -> str:
    """``check_spread``'s verdict from the centred points' singular values alone (its own slow path)."""
    s = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    if s[0] <= 1e-12 * max(1.0, float(np.abs(points).max())):
        return "identical"
    return "collinear" if s[1] <= 1e-9 * s[0] else "spread"


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(3, 300), d=st.sampled_from([2, 3]),
       off_line=st.sampled_from([0.0, 1e-12, 1e-9, 1e-7, 1e-5, 1e-3, 1.0]), offset=st.floats(-1e4, 1e4))
def test_check_spread_decides_as_the_singular_values(seed, n, d, off_line, offset):
    """The scatter's fast path passes only sets the singular values call spread; near a line (or a point)
    the singular values decide, as before."""
    rng = np.random.default_rng(seed)
    p = offset + np.outer(rng.normal(size=n), rng.normal(size=d)) + off_line * rng.normal(size=(n, d))
    if rng.random() < 0.2:
        p[:] = p[0]
    want = _spread_by_svd(p)
    try:
        check_spread(p, "source", "fix")
        got = "spread"
    except InputError as e:
        got = "identical" if "identical" in str(e) else "collinear"
    assert got == want


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), noise=st.floats(0.0, 0.1))
def test_triangle_pose_equals_kabsch_on_congruent_triangles(seed, noise):
    """The closed form is the least-squares pose of two (noisy) congruent triangles."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(3, 3))
    a, b, c = x
    h = np.linalg.norm(np.cross(b - a, c - a)) / max(np.linalg.norm(b - a), np.linalg.norm(c - a),
                                                        np.linalg.norm(c - b))
    assume(h >= 0.3)  # nearly collinear: noise of 0.1 could flip its orientation
    R = Rotor.from_axis_angle(rng.normal(size=3), rng.uniform(0, np.pi)).as_matrix()
    y = x @ R.T + rng.normal(size=3) + noise * rng.normal(size=(3, 3))
    R0, t0 = kabsch3(np.ascontiguousarray(x), np.ascontiguousarray(y))
    R1, t1 = triangle_pose(np.ascontiguousarray(x), np.ascontiguousarray(y))
    assert np.allclose(R1, R0, atol=1e-9)
    assert np.allclose(t1, t0, atol=1e-9)
    assert np.allclose(R1 @ R1.T, np.eye(3), atol=1e-12) and np.linalg.det(R1) == pytest.approx(1.0)


def test_triangle_pose_of_collinear_points_falls_back_to_kabsch():
    x = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])
    y = x + [0.5, 1.0, -2.0]
    R, t = triangle_pose(x, y)
    assert np.allclose(x @ R.T + t, y, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(3, 12))
def test_numba_umeyama3_matches_numpy(seed, k):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(k, 3))
    y = 2.0 * rng.normal(size=(k, 3))
    s0, R0, t0 = umeyama(x, y)
    s1, R1, t1 = umeyama3(np.ascontiguousarray(x), np.ascontiguousarray(y))
    assert s0 == pytest.approx(s1, rel=1e-10)
    assert np.allclose(R0, R1, atol=1e-10)
    assert np.allclose(t0, t1, atol=1e-10)


def test_stacks_equal_one_problem_at_a_time():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(7, 5, 3))
    B = rng.normal(size=(7, 5, 3))
    w = rng.uniform(0.1, 1.0, size=(7, 5))
    R, t = kabsch(A, B, w)
    s, Rs, ts = umeyama(A, B)
    Ro, to = kabsch(A, B, translation=False)
    for k in range(7):
        Rk, tk = kabsch(A[k], B[k], w[k])
        assert np.allclose(R[k], Rk, atol=1e-12) and np.allclose(t[k], tk, atol=1e-12)
        sk, Rsk, tsk = umeyama(A[k], B[k])
        assert np.isclose(s[k], sk) and np.allclose(Rs[k], Rsk) and np.allclose(ts[k], tsk)
        Rok, tok = kabsch(A[k], B[k], translation=False)
        assert np.allclose(Ro[k], Rok) and np.allclose(tok, 0.0) and np.allclose(to[k], 0.0)


def test_rotation_about_the_origin_on_rays():
    rng, R, _ = _motion(5)
    rays = rng.normal(size=(20, 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    Rf, t = kabsch(rays, rays @ R.T, translation=False)
    assert np.allclose(Rf, R) and np.all(t == 0)


def test_weights_select_the_pairs_that_count():
    rng, R, t = _motion(7)
    x = rng.normal(size=(10, 3))
    y = x @ R.T + t
    y[:3] += 50.0  # three gross outliers, weight 0
    w = np.r_[np.zeros(3), np.ones(7)]
    Rf, tf = fit_rigid(x, y, w)
    assert np.allclose(Rf, R) and np.allclose(tf, t)


def test_reflections_are_turned_into_rotations():
    x = np.eye(3)
    y = -np.eye(3)  # a point reflection: the best proper rotation has det +1
    R, _ = kabsch(x, y)
    assert np.isclose(np.linalg.det(R), 1.0)


@pytest.mark.parametrize(
    ("args", "match"),
    [
        ((np.zeros((3, 3)), np.zeros((4, 3))), "paired"),
        ((np.zeros((3, 3)), np.zeros((3, 3)), -np.ones(3)), "weights"),
        ((np.zeros((3, 3)), np.zeros((3, 3)), np.zeros(3)), "weights"),
        ((np.zeros(3), np.zeros(3)), "paired"),
    ],
)
def test_bad_input(args, match):
    with pytest.raises(InputError, match=match):
        kabsch(*args)


@given(st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=6, max_size=6))
@settings(max_examples=50, deadline=None)
def test_cross_kernel_equals_numpys_cross_bit_for_bit(values):
    """``_cross`` (triangle_pose's frame) is numpy's cross product, to the last bit."""
    a, b = np.array(values[:3]), np.array(values[3:])
    out = np.empty(3)
    _cross(a, b, out)
    np.testing.assert_array_equal(out, np.cross(a, b))
