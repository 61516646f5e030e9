"""Geometric algebra: rotors, joint spaces (eqs. 27–30) and eq. 41."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from gatv.ga import (
    Rotor,
    eq41,
    eq41_residual,
    joint_space_coordinates,
    joint_space_planes,
    rotor_product,
    turn_about,
)

unit = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
quats = st.tuples(unit, unit, unit, unit).filter(lambda q: np.linalg.norm(q) > 0.1)
seeds = st.integers(0, 2**32 - 1)


def _random_motion(rng):
    rot = Rotor.from_scipy(Rotation.random(random_state=rng))
    return rot, rng.uniform(-10, 10, 3)


@settings(max_examples=60, deadline=None)
@given(q=quats, seed=seeds)
def test_sandwich_matches_kingdon(q, seed):
    kingdon = pytest.importorskip("kingdon")
    alg = kingdon.Algebra(3, 0, 0)
    R = Rotor(q)
    q0, qx, qy, qz = R.q
    # kingdon names the e31 blade e13 = -e31.
    kR = alg.multivector(e=q0, e23=qx, e13=-qy, e12=qz)
    x = np.random.default_rng(seed).normal(size=(5, 3))
    ours = R >> x
    for row, got in zip(x, ours):
        y = kR >> alg.vector(list(row))
        np.testing.assert_allclose([y.e1, y.e2, y.e3], got, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(q=quats, seed=seeds)
def test_sandwich_matches_scipy_and_matrix(q, seed):
    R = Rotor(q)
    x = np.random.default_rng(seed).uniform(-10, 10, size=(7, 3))
    np.testing.assert_allclose(R >> x, R.as_scipy().apply(x), atol=1e-12)
    np.testing.assert_allclose(R >> x, x @ R.as_matrix().T, atol=1e-12)
    # R and -R are one rotation: compare up to sign.
    for back in (Rotor.from_matrix(R.as_matrix()), Rotor.from_scipy(R.as_scipy())):
        sign = np.sign(back.q @ R.q)
        np.testing.assert_allclose(sign * back.q, R.q, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(q1=quats, q2=quats, seed=seeds)
def test_composition_and_reverse(q1, q2, seed):
    R1, R2 = Rotor(q1), Rotor(q2)
    x = np.random.default_rng(seed).normal(size=(4, 3))
    np.testing.assert_allclose((R1 * R2) >> x, R1 >> (R2 >> x), atol=1e-12)
    np.testing.assert_allclose((~R1) >> (R1 >> x), x, atol=1e-12)
    rev = R1.q * np.array([1, -1, -1, -1])  # raw reverse, before sign canonicalisation
    np.testing.assert_allclose(rotor_product(R1.q, rev), [1, 0, 0, 0], atol=1e-12)
    expected = (Rotation.from_quat(R1.as_quaternion(scalar_first=False))
                * Rotation.from_quat(R2.as_quaternion(scalar_first=False)))
    np.testing.assert_allclose((R1 * R2).as_matrix(), expected.as_matrix(), atol=1e-12)


def test_axis_angle_convention():
    R = Rotor.from_axis_angle([0, 0, 2], np.pi / 2)
    # exp(-θ I a / 2): the e12 coefficient is -sin(θ/2).
    np.testing.assert_allclose(R.q, [np.cos(np.pi / 4), 0, 0, -np.sin(np.pi / 4)], atol=1e-15)
    np.testing.assert_allclose(R >> np.array([1.0, 0, 0]), [0, 1, 0], atol=1e-15)
    axis, angle = Rotor.from_axis_angle([1, 2, 3], 2.5).as_axis_angle()
    np.testing.assert_allclose(axis, np.array([1, 2, 3]) / np.sqrt(14), atol=1e-12)
    assert angle == pytest.approx(2.5)
    assert Rotor.identity().angle == 0.0
    np.testing.assert_allclose(Rotor.from_rotvec([0.3, -0.2, 0.1]).as_scipy().as_rotvec(),
                               [0.3, -0.2, 0.1], atol=1e-12)


def test_rotor_is_immutable_and_canonical():
    R = Rotor([-1.0, 0.0, 0.0, 0.0])
    assert R.q[0] == 1.0
    with pytest.raises(ValueError):
        R.q[0] = 2.0


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(q=[0, 0, 0, 0]), "non-zero"),
        (dict(q=[1, 0, 0]), "4 components"),
        (dict(q=[np.nan, 0, 0, 1]), "NaN"),
    ],
)
def test_rotor_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Rotor(**kwargs)


def test_rotor_bad_constructors():
    with pytest.raises(ValueError, match="axis"):
        Rotor.from_axis_angle([0, 0, 0], 1.0)
    with pytest.raises(ValueError, match="reflection"):
        Rotor.from_matrix(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="shape"):
        Rotor.identity() >> np.zeros((3, 2))


@settings(max_examples=40, deadline=None)
@given(seed=seeds)
def test_joint_space_planes_hold_for_true_pairs(seed):
    rng = np.random.default_rng(seed)
    R, t = _random_motion(rng)
    x = rng.uniform(-5, 5, size=(30, 3))
    xp = (R >> x) + t
    coords = joint_space_coordinates(x, xp)
    planes = joint_space_planes(R, t)
    for k in range(4):
        res = coords[k] @ planes[k, :3] + planes[k, 3]
        np.testing.assert_allclose(res, 0.0, atol=1e-10)
    # The eq.-30 normal is the rotation axis.
    n = planes[3, :3] / np.linalg.norm(planes[3, :3])
    assert abs(abs(n @ R.axis) - 1.0) < 1e-10


def test_joint_space_planes_fail_for_random_pairs():
    rng = np.random.default_rng(1)
    R, t = _random_motion(rng)
    x = rng.uniform(-5, 5, size=(200, 3))
    xp = rng.permutation((R >> x) + t)  # wrong pairing
    coords = joint_space_coordinates(x, xp)
    planes = joint_space_planes(R, t)
    for k in range(4):
        res = np.abs(coords[k] @ planes[k, :3] + planes[k, 3])
        assert np.median(res) > 0.1


def test_joint_space_coordinates_layout():
    x = np.array([[1.0, 2.0, 3.0]])
    xp = np.array([[10.0, 20.0, 30.0]])
    c = joint_space_coordinates(x, xp)
    np.testing.assert_array_equal(c[0, 0], [9, 33, 22])
    np.testing.assert_array_equal(c[1, 0], [18, 33, 11])
    np.testing.assert_array_equal(c[2, 0], [27, 22, 11])
    np.testing.assert_array_equal(c[3, 0], [9, 18, 27])
    with pytest.raises(ValueError, match="same number"):
        joint_space_coordinates(np.zeros((2, 3)), np.zeros((3, 3)))


@settings(max_examples=40, deadline=None)
@given(seed=seeds)
def test_eq41_zero_for_one_motion(seed):
    rng = np.random.default_rng(seed)
    R, t = _random_motion(rng)
    x = rng.uniform(-5, 5, size=(20, 3))
    xp = (R >> x) + t
    d, s = xp - x, xp + x
    out = eq41(d[:10], s[:10], d[10:], s[10:], R.axis)
    np.testing.assert_allclose(out, 0.0, atol=1e-9)


def _fig2_pairs(angle_j):
    """Fig. 2: screw axis e3, same translation; pair j may turn by another angle."""
    t = np.array([1.0, -2.0, 0.5])
    xi, xj = np.array([3.0, 1.0, 0.2]), np.array([-1.0, 2.0, -0.4])
    Ri = Rotor.from_axis_angle([0, 0, 1], 0.7)
    Rj = Rotor.from_axis_angle([0, 0, 1], angle_j)
    xpi, xpj = (Ri >> xi) + t, (Rj >> xj) + t
    return xi, xpi, xj, xpj


def test_eq41_fig2_same_motion_vs_different_angles():
    axis = [0, 0, 1]
    xi, xpi, xj, xpj = _fig2_pairs(0.7)  # Fig. 2 a/d
    same = eq41_residual(xpi - xi, xpi + xi, xpj - xj, xpj + xj, axis, normalize="angle")
    assert same < 1e-12
    xi, xpi, xj, xpj = _fig2_pairs(1.2)  # Fig. 2 b/e: other angle, same t
    other = eq41_residual(xpi - xi, xpi + xi, xpj - xj, xpj + xj, axis, normalize="angle")
    assert other > 0.1


def test_eq41_rejects_double_match():
    # Fig. 2 c/f: x_i matched to both x'_i and x'_j.
    rng = np.random.default_rng(3)
    R, t = _random_motion(rng)
    x = rng.uniform(-5, 5, size=(2, 3))
    xp = (R >> x) + t
    d_ok, s_ok = xp[0] - x[0], xp[0] + x[0]
    d_bad, s_bad = xp[1] - x[0], xp[1] + x[0]
    r = eq41_residual(d_ok, s_ok, d_bad, s_bad, R.axis, normalize="angle")
    assert r > 0.05
    r_len = eq41_residual(d_ok, s_ok, d_bad, s_bad, R.axis, normalize="length")
    assert r_len > 0.1


def test_eq41_residual_normalisation_is_scale_free():
    rng = np.random.default_rng(5)
    R, t = _random_motion(rng)
    x = rng.uniform(-5, 5, size=(20, 3))
    xp = rng.permutation((R >> x) + t)
    d, s = xp - x, xp + x
    a = eq41_residual(d[:10], s[:10], d[10:], s[10:], R.axis, normalize="angle")
    b = eq41_residual(7 * d[:10], 7 * s[:10], 7 * d[10:], 7 * s[10:], R.axis, normalize="angle")
    np.testing.assert_allclose(a, b, rtol=1e-12)
    c = eq41_residual(7 * d[:10], 7 * s[:10], 7 * d[10:], 7 * s[10:], R.axis, normalize="length")
    np.testing.assert_allclose(
        c, 7 * eq41_residual(d[:10], s[:10], d[10:], s[10:], R.axis), rtol=1e-12)
    with pytest.raises(ValueError, match="normalize"):
        eq41_residual(d, s, d, s, R.axis, normalize="bogus")


@settings(max_examples=50, deadline=None)
@given(seed=seeds, angle=st.floats(-2.0 * np.pi, 2.0 * np.pi))
def test_a_turn_about_a_line_fixes_the_line_and_keeps_distances_to_it(seed, angle):
    """``turn_about``: the points of the line stay put; every other point keeps its distance to the line
    and its height along it, and is turned by ``angle`` about it (scipy's rotation vector, a reference)."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    through = rng.uniform(-10.0, 10.0, 3)
    R, t = turn_about(axis, angle, through)
    line = through + np.outer(rng.uniform(-5.0, 5.0, 4), axis)
    np.testing.assert_allclose(line @ R.T + t, line, atol=1e-9)
    x = rng.uniform(-10.0, 10.0, (20, 3))
    expected = (x - through) @ Rotation.from_rotvec(angle * axis).as_matrix().T + through
    np.testing.assert_allclose(x @ R.T + t, expected, atol=1e-9)

