"""Eq. 41 of the paper, pinned: ``V × (A × Vs) = 0`` for true pairs, and not for wrong ones.

Reyes, Medioni & Bayro (IJCV 2007), section 2.  For two candidate pairs
``x_i ↔ x'_i`` and ``x_j ↔ x'_j``, ``d = x' − x`` and ``s = x' + x``;
``V = d_i − d_j`` and ``Vs = s_i − s_j`` (so ``V = Δx' − Δx`` and
``Vs = Δx' + Δx`` with ``Δx = x_i − x_j``).  Eqs. 35–37 say that for two
pairs of one rigid motion of angle θ about the unit axis ``A``,
``k V = A × Vs`` with ``k = cot(θ/2)``; eqs. 38–40 eliminate ``k`` and
eq. 41 writes them as ``V × (A × Vs) = 0``.  Expanded (the BAC–CAB rule),
``A (V·Vs) − Vs (V·A)``: the pair distance kept (``V·Vs = |Δx'|² − |Δx|²``)
and both tokens on one plane normal to ``A`` (``V·A = 0``).

The tests below check the implementation against those derivations
(independent of :mod:`gatv.ga`'s own algebra), on exact rigid pairs of any
motion (hypothesis), on the paper's wrong pairs (Fig. 2 b/e: another angle;
Fig. 2 c/f: a double match), for the invariances the geometry has, for the
scale of the relaxed residuals (section 4.1), and through
:func:`gatv.models.rigid.eq41_consistent` and the cheapest-first
:func:`gatv.candidates.one_to_one` that the plane's tokens go through.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from gatv import stages
from gatv.candidates import one_to_one, one_to_one_rows
from gatv.errors import InputError
from gatv.ga import Rotor, eq41, eq41_length_residual, eq41_residual
from gatv.models.rigid import eq41_consistent

FAST = settings(max_examples=60, deadline=None)

# --------------------------------------------------------------- strategies
unit = st.floats(-1.0, 1.0, allow_nan=False)
axes = st.tuples(unit, unit, unit).filter(lambda v: np.linalg.norm(v) > 0.2).map(
    lambda v: np.asarray(v) / np.linalg.norm(v))
angles = st.floats(np.radians(5.0), np.pi, allow_nan=False)
coords = st.floats(-20.0, 20.0, allow_nan=False)
#: Components on a grid of 1/8: exact in binary, no subnormal products.
grid = st.integers(-160, 160).map(lambda k: k / 8.0)
translations = st.tuples(coords, coords, coords).map(np.asarray)
seeds = st.integers(0, 2**32 - 1)


def _rotation(axis, angle):
    """Right-handed rotation matrix by ``angle`` about the unit ``axis`` (Rodrigues, not gatv)."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


def _tokens(x, y):
    """``(d, s)`` of paired rows."""
    return y - x, y + x


def _all_pairs(n):
    i, j = np.triu_indices(n, 1)
    return i, j


# --------------------------------------------------- the derivation (eqs. 35-41)
@FAST
@given(axis=axes, angle=angles, t=translations, seed=seeds)
def test_true_pairs_satisfy_eqs_35_to_37_k_V_equals_A_cross_Vs(axis, angle, t, seed):
    """Eqs. 35–37: ``cot(θ/2) V = A × Vs`` for every two pairs of one rigid motion, whatever ``t``."""
    x = np.random.default_rng(seed).uniform(-10, 10, (12, 3))
    y = x @ _rotation(axis, angle).T + t
    d, s = _tokens(x, y)
    i, j = _all_pairs(len(x))
    V, Vs = d[i] - d[j], s[i] - s[j]
    scale = np.linalg.norm(Vs, axis=1, keepdims=True) + 1.0
    np.testing.assert_allclose(np.cross(axis, Vs) / scale, V / np.tan(angle / 2.0) / scale, atol=1e-9)


@FAST
@given(axis=axes, angle=angles, t=translations, seed=seeds)
def test_true_pairs_give_exactly_zero(axis, angle, t, seed):
    """Eq. 41 and its relaxed residuals vanish on exact rigid pairs, for any rotation and translation."""
    x = np.random.default_rng(seed).uniform(-10, 10, (12, 3))
    y = x @ _rotation(axis, angle).T + t
    d, s = _tokens(x, y)
    i, j = _all_pairs(len(x))
    size = np.linalg.norm(d[i] - d[j], axis=1) * np.linalg.norm(s[i] - s[j], axis=1) + 1.0
    assert np.all(np.linalg.norm(eq41(d[i], s[i], d[j], s[j], axis), axis=1) <= 1e-9 * size)
    # the axis is normalised inside: any positive multiple, or the opposite direction, is the same axis
    assert np.all(np.linalg.norm(eq41(d[i], s[i], d[j], s[j], -7.5 * axis), axis=1) <= 1e-9 * size)
    extent = 1.0 + np.abs(y).max()
    for normalize in ("length", "angle", "none"):
        r = eq41_residual(d[i], s[i], d[j], s[j], axis, normalize=normalize)
        assert r.shape == (len(i),) and np.all(r >= 0.0)
        assert np.all(r <= 1e-9 * (size if normalize == "none" else extent))
    assert np.all(np.abs(eq41_length_residual(d[i], s[i], d[j], s[j])) <= 1e-9 * extent)


@FAST
@given(V=st.tuples(grid, grid, grid), Vs=st.tuples(grid, grid, grid), A=axes)
def test_eq41_is_the_paper_eqs_38_to_40(V, Vs, A):
    """Component by component, eq. 41 is eqs. 38–40 as printed (x: −(40), y: (39), z: −(38)), and
    ``A (V·Vs) − Vs (V·A)``; the residuals are its norm scaled as documented."""
    vx, vy, vz = V
    sx, sy, sz = Vs
    ax, ay, az = A
    e38 = vy * (ay * sz - az * sy) - vx * (az * sx - ax * sz)
    e39 = vz * (ay * sz - az * sy) - vx * (ax * sy - ay * sx)
    e40 = vz * (az * sx - ax * sz) - vy * (ax * sy - ay * sx)
    zero = np.zeros(3)
    # as pairs (d_i, s_i) = (V, Vs) and (d_j, s_j) = 0
    got = eq41(np.asarray(V), np.asarray(Vs), zero, zero, A)
    scale = 1.0 + np.linalg.norm(V) * np.linalg.norm(Vs)
    np.testing.assert_allclose(got / scale, np.array([-e40, e39, -e38]) / scale, atol=1e-12)
    V, Vs = np.asarray(V), np.asarray(Vs)
    np.testing.assert_allclose(got / scale, (A * (V @ Vs) - Vs * (V @ A)) / scale, atol=1e-12)
    norm = np.linalg.norm(got)
    nv, nvs = np.linalg.norm(V), np.linalg.norm(Vs)
    r = {k: float(eq41_residual(V, Vs, zero, zero, A, normalize=k)) for k in ("none", "length", "angle")}
    assert r["none"] == pytest.approx(norm, rel=1e-12, abs=1e-300)
    assert r["length"] == pytest.approx(norm / nvs if nvs > 0 else 0.0, rel=1e-12, abs=1e-300)
    assert r["angle"] == pytest.approx(norm / (nv * nvs) if nv * nvs > 0 else 0.0, rel=1e-12, abs=1e-300)
    assert 0.0 <= r["angle"] <= 1.0 + 1e-12
    L = float(eq41_length_residual(V, Vs, zero, zero))
    assert L == pytest.approx(abs(V @ Vs) / nvs if nvs > 0 else 0.0, rel=1e-12, abs=1e-300)


# ----------------------------------------------------------- wrong pairs (Fig. 2)
def test_fig2_b_another_angle_breaks_the_symmetry():
    """Fig. 2(b/e): x_i turned 30°, x_j turned 60° about z, no translation.

    By hand: Δx = (1, −2, 0), |Δx|² = 5; x'_i = (√3/2, 1/2, 0), x'_j = (−√3, 1, 0),
    Δx' = (3√3/2, −1/2, 0), |Δx'|² = 7; so V·Vs = 2, Vs = Δx' + Δx = (1 + 3√3/2, −5/2, 0),
    and with V·A = 0 every length-scaled residual is 2 / |Vs| (0.456).
    """
    x = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    y = np.array([_rotation([0, 0, 1], np.radians(30.0)) @ x[0], _rotation([0, 0, 1], np.radians(60.0)) @ x[1]])
    d, s = _tokens(x, y)
    expected = 2.0 / np.hypot(1.0 + 1.5 * np.sqrt(3.0), -2.5)
    assert float(eq41_length_residual(d[0], s[0], d[1], s[1])) == pytest.approx(expected, rel=1e-12)
    assert float(eq41_residual(d[0], s[0], d[1], s[1], [0, 0, 1])) == pytest.approx(expected, rel=1e-12)
    assert float(eq41_residual(d[0], s[0], d[1], s[1], [0, 0, 1], normalize="none")) == pytest.approx(2.0)
    # swapping the two pairs changes nothing (V and Vs both change sign)
    assert float(eq41_length_residual(d[1], s[1], d[0], s[0])) == pytest.approx(expected, rel=1e-12)


@FAST
@given(axis=axes, angle=angles, t=translations, seed=seeds)
def test_double_match_residual_is_the_distance_between_the_two_targets(axis, angle, t, seed):
    """Fig. 2(c/f): x_i matched to x'_i and to x'_j.  Δx = 0, so ``V = Vs = Δx'`` and the length
    residual is ``|Δx'|``, the distance between the two targets; the full one too."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-10, 10, (2, 3))
    assume(np.linalg.norm(x[0] - x[1]) > 0.1)
    y = x @ _rotation(axis, angle).T + t
    d_i, s_i = y[0] - x[0], y[0] + x[0]
    d_j, s_j = y[1] - x[0], y[1] + x[0]  # the same source point, the other target
    gap = np.linalg.norm(y[0] - y[1])
    assert float(eq41_length_residual(d_i, s_i, d_j, s_j)) == pytest.approx(gap, rel=1e-9)
    # V = Vs: A × Vs ⊥ V, so |V × (A × Vs)| = |V| |A × V| = gap² sin∠(A, V)
    r = float(eq41_residual(d_i, s_i, d_j, s_j, axis, normalize="length"))
    u = (y[0] - y[1]) / gap
    assert r == pytest.approx(gap * np.linalg.norm(np.cross(axis, u)), rel=1e-9, abs=1e-9 * gap)


@FAST
@given(dx=st.tuples(coords, coords, coords).map(np.asarray), lam=st.floats(0.05, 20.0),
       base=st.tuples(coords, coords, coords).map(np.asarray), shift=translations)
def test_length_residual_of_a_stretch_is_the_change_of_distance(dx, lam, base, shift):
    """``Δx' = λ Δx``: ``V = (λ−1) Δx``, ``Vs = (λ+1) Δx``, and ``|V·Vs| / |Vs| = |λ−1| |Δx|``,
    the change of the pair's distance, in the data's unit, for a stretch or a shrink alike
    (the normalisation by ``|Vs|`` of section 4.1; by ``|V|`` it would be ``(λ+1) |Δx|``)."""
    n = np.linalg.norm(dx)
    assume(n > 0.1 and abs(lam - 1.0) > 1e-3)
    x_i, x_j = base, base - dx
    y_i = shift
    y_j = shift - lam * dx
    d_i, s_i, d_j, s_j = y_i - x_i, y_i + x_i, y_j - x_j, y_j + x_j
    r = float(eq41_length_residual(d_i, s_i, d_j, s_j))
    assert r == pytest.approx(abs(lam - 1.0) * n, rel=1e-7, abs=1e-9 * (1 + lam) * n)


@FAST
@given(seed=seeds)
def test_length_residual_is_bounded_by_the_distance_change_and_by_V(seed):
    """Any two pairs: ``||Δx'| − |Δx|| <= |V·Vs| / |Vs| <= |V|`` (``|Vs| <= |Δx'| + |Δx|`` and
    Cauchy–Schwarz): the residual is at least how much the pair distance changed."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-10, 10, (2, 20, 3))
    d, s = _tokens(x, y)
    i, j = _all_pairs(20)
    r = eq41_length_residual(d[i], s[i], d[j], s[j])
    change = np.abs(np.linalg.norm(y[i] - y[j], axis=1) - np.linalg.norm(x[i] - x[j], axis=1))
    V = np.linalg.norm(d[i] - d[j], axis=1)
    assert np.all(r >= change - 1e-9) and np.all(r <= V + 1e-9)
    assert np.all(r > 0)


def test_zero_Vs_gives_zero():
    """Pairs with ``Vs = 0`` give 0 (the documented convention): no division by zero, no NaN."""
    d = np.array([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]])
    s = np.array([[0.5, 0.5, 0.5], [0.5, 0.5, 0.5]])
    assert eq41_length_residual(d[0], s[0], d[1], s[1]) == 0.0
    for normalize in ("length", "angle", "none"):
        assert eq41_residual(d[0], s[0], d[1], s[1], [0, 0, 1], normalize=normalize) == 0.0


# ---------------------------------------------------------------- invariances
@FAST
@given(axis=axes, angle=angles, t=translations, seed=seeds, s=st.floats(0.01, 100.0))
def test_residuals_follow_a_common_rigid_motion_and_a_scaling(axis, angle, t, seed, s):
    """Any pairs (right or wrong): moving both sets by one rigid motion ``Q, q`` rotates
    ``V``, ``Vs`` and ``A`` by ``Q`` (``q`` cancels in ``Vs``), so the residuals are unchanged;
    scaling every coordinate by ``c`` scales "none" by ``c²``, "length" by ``c`` and not "angle"."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-10, 10, (2, 15, 3))
    A = rng.normal(size=3)
    i, j = _all_pairs(15)
    Q = _rotation(axis, angle)

    def residuals(xx, yy, a):
        d, sm = _tokens(xx, yy)
        out = {k: eq41_residual(d[i], sm[i], d[j], sm[j], a, normalize=k) for k in ("none", "length", "angle")}
        out["length half"] = eq41_length_residual(d[i], sm[i], d[j], sm[j])
        return out

    before = residuals(x, y, A)
    moved = residuals(x @ Q.T + t, y @ Q.T + t, Q @ A)
    scaled = residuals(s * x, s * y, A)
    for k, r in before.items():
        np.testing.assert_allclose(moved[k], r, rtol=1e-9, atol=1e-9 * (1 + r.max()))
        power = {"none": 2.0, "length": 1.0, "angle": 0.0, "length half": 1.0}[k]
        np.testing.assert_allclose(scaled[k], s**power * r, rtol=1e-9, atol=1e-12 * s**power * (1 + r.max()))


@FAST
@given(seed=seeds, A=axes)
def test_order_of_the_pairs_and_of_the_sets(seed, A):
    """Swapping the two pairs (``V, Vs → −V, −Vs``) leaves eq. 41 as it is; swapping source and
    target (``V → −V``, ``Vs`` kept: the inverse motion, same axis) negates it; norms unchanged."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-10, 10, (2, 15, 3))
    i, j = _all_pairs(15)
    d, s = _tokens(x, y)
    e = eq41(d[i], s[i], d[j], s[j], A)
    np.testing.assert_allclose(eq41(d[j], s[j], d[i], s[i], A), e, atol=1e-9)
    # only the axis' direction counts (it is normalised): 0.01 A or 40 A give the same vector
    for c in (0.01, 40.0):
        np.testing.assert_allclose(eq41(d[i], s[i], d[j], s[j], c * A), e, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(eq41_residual(d[i], s[i], d[j], s[j], c * A),
                                   eq41_residual(d[i], s[i], d[j], s[j], A), rtol=1e-12, atol=1e-12)
    di, si = _tokens(y, x)
    np.testing.assert_allclose(eq41(di[i], si[i], di[j], si[j], A), -e, atol=1e-9)
    for k in ("none", "length", "angle"):
        np.testing.assert_allclose(eq41_residual(di[i], si[i], di[j], si[j], A, normalize=k),
                                   eq41_residual(d[i], s[i], d[j], s[j], A, normalize=k), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(eq41_length_residual(d[j], s[j], d[i], s[i]),
                               eq41_length_residual(d[i], s[i], d[j], s[j]), rtol=1e-12)


# --------------------------------------------------------- eq41_consistent both ways
def _impostor(x_k, y_ref, x_ref, R, axis, offset):
    """A target for ``x_k`` at its true distance from the reference's target, ``offset`` off the plane.

    The true ``Δx' = R Δx`` turned by ``φ`` about ``w = A × Δx' / |A × Δx'|`` (normal to both) keeps
    ``|Δx'| = |Δx|`` (so ``V·Vs = 0``: the length half of eq. 41 passes) and moves it along the axis:
    ``V·A = a (cos φ − 1) − |Δx'_⊥| sin φ`` with ``a = Δx'·A``; ``φ`` is solved for ``V·A = offset``.
    Returns the target and its exact ``V·A``.
    """
    dx = x_k - x_ref
    u = R @ dx
    a = float(u @ axis)
    perp = float(np.linalg.norm(np.cross(axis, u)))
    w = np.cross(axis, u) / perp
    # a (cos φ − 1) − perp sin φ = offset, with |φ| small: Newton from the linear guess
    phi = -offset / perp
    for _ in range(20):
        f = a * (np.cos(phi) - 1.0) - perp * np.sin(phi) - offset
        phi -= f / (-a * np.sin(phi) - perp * np.cos(phi))
    turned = u * np.cos(phi) + np.cross(w, u) * np.sin(phi)
    return y_ref + turned, a * (np.cos(phi) - 1.0) - perp * np.sin(phi)


def _scene(axis, angle, t, seed, n_true=30, n_wrong=30, impostors=(), far=False):
    """An exact rigid set and its candidate pairs: true ones, random wrong ones, double matches of
    the reference, and impostors (one per ``impostors`` offset) that keep their distance to the
    reference's pair but lie that far off its plane (``far``: turned by 30-150°, far off).

    Returns ``(d, s, pairs, is_true, ref, offsets)``.
    """
    rng = np.random.default_rng(seed)
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    R = _rotation(axis, angle)
    x = rng.uniform(-10, 10, (n_true, 3))
    y = x @ R.T + t
    ref = int(rng.integers(n_true))
    src, tgt = [x], [y]
    pairs = [np.column_stack([np.arange(n_true), np.arange(n_true)])]
    # wrong pairs: a source point with another point's target
    a = rng.integers(n_true, size=n_wrong)
    b = (a + rng.integers(1, n_true, size=n_wrong)) % n_true
    src.append(x[a])
    tgt.append(y[b])
    pairs.append(np.column_stack([a, b]))
    # the reference's source with other targets, other sources with its target (Fig. 2 c/f)
    others = np.setdiff1d(np.arange(n_true), [ref])[:4]
    src += [np.repeat(x[[ref]], 4, axis=0), x[others]]
    tgt += [y[others], np.repeat(y[[ref]], 4, axis=0)]
    pairs += [np.column_stack([np.full(4, ref), others]), np.column_stack([others, np.full(4, ref)])]
    k = np.setdiff1d(np.arange(n_true), [ref])[:len(impostors)]
    offsets = []
    for m, (kk, h) in enumerate(zip(k, impostors)):
        if far:
            turn = _rotation(np.cross(axis, rng.normal(size=3)), np.radians(rng.uniform(30.0, 150.0)))
            y_imp = (y[kk] - y[ref]) @ turn.T + y[ref]
            h = float(((y_imp - x[kk]) - (y[ref] - x[ref])) @ axis)
        else:
            y_imp, h = _impostor(x[kk], y[ref], x[ref], R, axis, h)
        src.append(x[[kk]])
        tgt.append(y_imp[None])
        pairs.append(np.array([[kk, n_true + m]]))  # a new target point
        offsets.append(h)
    x, y, pairs = np.vstack(src), np.vstack(tgt), np.vstack(pairs)
    is_true = np.zeros(len(pairs), bool)
    is_true[:n_true] = True
    d, s = _tokens(x, y)
    return d, s, pairs, is_true, ref, np.array(offsets)


@settings(max_examples=40, deadline=None)
@given(axis=axes, angle=angles, t=translations, seed=seeds)
def test_eq41_consistent_keeps_every_true_token_and_only_those(axis, angle, t, seed):
    """On an exact rigid set, against a true reference: all 30 true tokens kept, and no wrong
    pair, no double match of the reference (sharing its source or its target point)."""
    d, s, pairs, is_true, ref, _ = _scene(axis, angle, t, seed)
    tau = 1e-7 * (1.0 + np.abs(d).max())
    kept = eq41_consistent(d, s, pairs, ref, tau)
    assert kept.tolist() == np.flatnonzero(is_true).tolist()


@pytest.mark.parametrize("seed", range(6))
def test_eq41_consistent_rejects_tokens_that_keep_the_distance_off_the_plane(seed):
    """Two impostors at their true distance from the reference's pair (the length half passes) but
    4 and 6 τ off the plane normal to the axis: only the full eq. 41 (``|V·A| > τ``, with the axis
    fitted on the tokens) rejects them; the true tokens stay."""
    tau = 0.02  # the points span 20 units: a noise-level tolerance
    rng = np.random.default_rng([43, seed])
    axis = rng.normal(size=3)
    d, s, pairs, is_true, ref, offsets = _scene(axis, rng.uniform(0.3, 3.0), rng.uniform(-5, 5, 3), seed,
                                                 n_wrong=0, impostors=(4 * tau, -6 * tau))
    np.testing.assert_allclose(offsets, [4 * tau, -6 * tau], rtol=1e-6)
    imp = np.flatnonzero(~is_true)[-2:]
    assert np.all(eq41_length_residual(d[imp], s[imp], d[ref], s[ref]) <= 1e-9 * tau)
    kept = eq41_consistent(d, s, pairs, ref, tau)
    assert kept.tolist() == np.flatnonzero(is_true).tolist()


def test_eq41_consistent_survives_one_far_impostor():
    """A token at its true distance from the reference but far off the eq.-30 plane (a chance pair that
    passes the length half) tilted the least-squares axis until every true token failed eq. 41; the
    plane the tokens detect keeps them all and drops it."""
    for seed in range(5):
        rng = np.random.default_rng([44, seed])
        d, s, pairs, is_true, ref, _ = _scene(rng.normal(size=3), rng.uniform(0.3, 3.0),
                                              rng.uniform(-5, 5, 3), seed, impostors=(None,), far=True)
        tau = 1e-7 * (1.0 + np.abs(d).max())
        assert eq41_length_residual(d[-1], s[-1], d[ref], s[ref]) <= tau  # it passes the length half
        kept = eq41_consistent(d, s, pairs, ref, tau)
        assert kept.tolist() == np.flatnonzero(is_true).tolist(), seed


def test_eq41_consistent_drops_a_double_match_that_eq41_cannot_see():
    """A duplicate of the reference's target point (another row, same place): the token that pairs
    the reference's source with it is the reference's own token, ``V = Vs = 0``, and passes every
    residual; only the shared source point tells it is a second match of that point (Fig. 2 c/f)."""
    d, s, pairs, is_true, ref, _ = _scene([0.0, 0.0, 1.0], 0.7, np.array([1.0, -2.0, 3.0]), 0)
    dup = np.array([[pairs[ref, 0], 999]])
    d2, s2 = np.vstack([d, d[ref]]), np.vstack([s, s[ref]])
    pairs2 = np.vstack([pairs, dup])
    tau = 1e-7 * (1.0 + np.abs(d).max())
    kept = eq41_consistent(d2, s2, pairs2, ref, tau)
    assert len(pairs2) - 1 not in kept
    assert kept.tolist() == np.flatnonzero(is_true).tolist()


def test_eq41_consistent_with_a_wrong_reference_keeps_little():
    """Against a wrong token, the true tokens are not consistent: the plane is rejected in effect."""
    d, s, pairs, is_true, _, _ = _scene([0.3, 0.2, 0.9], 1.1, np.array([4.0, 0.0, -1.0]), 5)
    wrong = int(np.flatnonzero(~is_true)[0])
    tau = 1e-7 * (1.0 + np.abs(d).max())
    kept = eq41_consistent(d, s, pairs, wrong, tau)
    assert wrong in kept and np.count_nonzero(is_true[kept]) <= 2


# ------------------------------------------------------- one_to_one, cheapest first
def _greedy_reference(pairs, cost):
    """The rule as documented: by cost, ties to the earlier row, each point used once."""
    used_s, used_t, out = set(), set(), []
    for r in sorted(range(len(pairs)), key=lambda r: (cost[r], r)):
        i, j = map(int, pairs[r])
        if i in used_s or j in used_t:
            continue
        used_s.add(i)
        used_t.add(j)
        out.append(r)
    return out


@settings(max_examples=80, deadline=None)
@given(rows=st.lists(st.tuples(st.integers(0, 6), st.integers(0, 6), st.sampled_from([0.0, 0.5, 1.0, 2.0, 3.5])),
                     min_size=1, max_size=60))
def test_one_to_one_is_cheapest_first_ties_to_the_earlier_row(rows):
    pairs = np.array([(i, j) for i, j, _ in rows], np.int64)
    cost = np.array([c for _, _, c in rows])
    keep = one_to_one(pairs, cost)
    assert keep.tolist() == _greedy_reference(pairs, cost)
    assert stages.select_one_to_one(pairs, cost).tolist() == keep.tolist()
    chosen = pairs[keep]
    assert len(set(chosen[:, 0])) == len(keep) == len(set(chosen[:, 1]))
    assert np.all(np.diff(cost[keep]) >= 0)  # in the order taken: cheapest first
    # every row left out lost to a kept row no dearer that shares one of its points
    for r in np.setdiff1d(np.arange(len(pairs)), keep):
        rivals = keep[(pairs[keep, 0] == pairs[r, 0]) | (pairs[keep, 1] == pairs[r, 1])]
        assert rivals.size and np.any((cost[rivals] < cost[r]) | ((cost[rivals] == cost[r]) & (rivals < r)))


@settings(max_examples=80, deadline=None)
@given(rows=st.lists(st.tuples(st.integers(0, 6), st.sampled_from([0.0, 0.5, 1.0, 2.0, 3.5])), min_size=1,
                     max_size=60))
def test_one_to_one_rows_keeps_the_greedy_rows_in_row_order(rows):
    """One pair a source row (each moved point's nearest target): the rows the cheapest-first greedy keeps,
    ascending, in linear time."""
    targets = np.array([j for j, _ in rows], np.int64)
    cost = np.array([c for _, c in rows])
    pairs = np.stack([np.arange(len(rows)), targets], axis=1)
    kept = one_to_one_rows(targets, cost)
    assert kept.tolist() == sorted(_greedy_reference(pairs, cost))
    assert np.all(np.diff(kept) > 0)


def test_nearest_pairs_by_row_are_the_same_pairs_in_row_order():
    """``by_row``: the pairs of the cheapest-first rule, sorted by the moved row (ties of distance included:
    a lattice queried from its own points shifted half a step)."""
    from scipy.spatial import cKDTree

    from gatv._icp_kernels import KDTree

    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(*[np.arange(12.0)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    moved = np.concatenate([grid[rng.permutation(len(grid))[:900]] + [0.5, 0.0, 0.0],
                            rng.uniform(-1.0, 12.0, (900, 3))])
    for tree in (KDTree(grid), cKDTree(grid)):
        for radius in (0.6, 1.5):
            ranked = stages.nearest_pairs(moved, tree, radius)
            by_row = stages.nearest_pairs(moved, tree, radius, by_row=True)
            assert by_row.tolist() == ranked[np.argsort(ranked[:, 0])].tolist()
            assert len(ranked) > 100 and len(set(by_row[:, 1])) == len(by_row)


def test_one_to_one_rows_names_a_bad_argument():
    with pytest.raises(InputError, match="`targets` and `cost`"):
        one_to_one_rows(np.array([0, 1]), np.array([1.0]))
    with pytest.raises(InputError, match="`targets` of indices >= 0, got -1"):
        one_to_one_rows(np.array([0, -1]), np.array([1.0, 2.0]))


def test_one_to_one_ties_go_to_the_earlier_row_in_a_long_list():
    """Hundreds of equal costs (an unstable sort reorders them): the earliest row of each point wins."""
    rng = np.random.default_rng(1)
    pairs = rng.integers(0, 40, (600, 2))
    cost = np.ones(600)
    cost[rng.permutation(600)[:200]] = 0.5
    keep = one_to_one(pairs, cost)
    assert keep.tolist() == _greedy_reference(pairs, cost)


def test_one_to_one_keeps_the_cheap_pair_not_the_first():
    # a -> t0 costs 2, b -> t0 costs 1, a -> t1 costs 3: b-t0 first, then a-t1
    pairs = np.array([[0, 0], [1, 0], [0, 1]])
    assert one_to_one(pairs, np.array([2.0, 1.0, 3.0])).tolist() == [1, 2]
    assert one_to_one(np.empty((0, 2), np.int64), np.empty(0)).tolist() == []
