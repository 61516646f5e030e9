"""The affine patch hypothesis of the local windows (gatv.nonrigid.affine_patch)."""

from __future__ import annotations

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from gatv.candidates import median_spacing
from gatv.nonrigid.affine_patch import (
    AFFINE_BASE_POINTS,
    affine_patch,
    crossing_base,
    crossing_points,
    stretch_band,
)


def _surface(n: int, radius: float, seed: int):
    """``n`` points on a gently curved surface over a disc of ``radius``, nearest the origin first."""
    rng = np.random.default_rng(seed)
    r = radius * np.sqrt(rng.uniform(size=n))
    a = rng.uniform(0, 2 * np.pi, n)
    x, y = r * np.cos(a), r * np.sin(a)
    p = np.column_stack([x, y, 0.02 * (x ** 2 - 0.5 * y ** 2) + 0.1 * np.sin(0.3 * x)])
    return p[np.argsort(np.linalg.norm(p[:, :2], axis=1), kind="stable")]


def _strained(p, stretch, angle_seed: int, shift):
    """``p`` under a linear strain with principal stretches ``stretch`` (in the surface's plane),
    then a rotation and a shift."""
    S = np.diag([stretch[0], stretch[1], 1.0])
    R = Rotation.random(random_state=angle_seed).as_matrix()
    return p @ S.T @ R.T + np.asarray(shift)


# ------------------------------------------------------------------ numpy references
@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000))
@example(31)
def test_crossing_ratios_are_affine_invariants(seed):
    rng = np.random.default_rng(seed)
    a, b, c, d = rng.normal(size=(4, 3)) * [1, 1, 0]  # coplanar
    r1, r2, gap = crossing_points(a, b, c, d)
    # Rounding grows with the crossing's distance: nearly parallel lines cross thousands of segment
    # lengths away (seed 31: r1 = -3019, gap 2.1e-9).
    far = 1.0 + max(abs(r1), abs(r2))
    assert gap < 1e-9 * far
    np.testing.assert_allclose(a + r1 * (b - a), c + r2 * (d - c), atol=1e-9 * far)
    A = rng.normal(size=(3, 3)) + 2 * np.eye(3)
    t = rng.normal(size=3)
    s1, s2, g2 = crossing_points(*(v @ A.T + t for v in (a, b, c, d)))
    np.testing.assert_allclose([s1, s2], [r1, r2], rtol=1e-6, atol=1e-9 * far)
    assert g2 < 1e-8 * far


def test_crossing_base_diagonals_cross_inside_and_match_a_brute_force():
    P = _surface(AFFINE_BASE_POINTS, 3.0, 1)
    rows, r1, r2, gap = crossing_base(P)
    assert len(set(rows.tolist())) == 4 and 0.2 <= r1 <= 0.8 and 0.2 <= r2 <= 0.8
    a, b, c, d = P[rows]
    best = np.linalg.norm(np.cross(b - a, d - c)) / max(np.linalg.norm(b - a), np.linalg.norm(d - c))
    # brute force over the same pairings: no crossing base is wider
    from itertools import combinations, permutations
    for q in combinations(range(P.shape[0]), 4):
        for i, j, k, m in permutations(q):
            s1, s2, _ = crossing_points(P[i], P[j], P[k], P[m])
            if 0.2 <= s1 <= 0.8 and 0.2 <= s2 <= 0.8:
                u, v = P[j] - P[i], P[m] - P[k]
                w = np.linalg.norm(np.cross(u, v)) / max(np.linalg.norm(u), np.linalg.norm(v))
                assert w <= best * (1 + 1e-9)
    assert crossing_base(P, max_gap=gap) is not None
    narrow = crossing_base(P, max_gap=0.5 * gap) if gap > 0 else None
    assert narrow is None or narrow[3] <= 0.5 * gap
    assert crossing_base(np.zeros((3, 3))) is None
    assert crossing_base(np.outer(np.arange(8.0), [1, 0, 0])) is None  # collinear


def test_stretch_band_contains_the_strain_both_ways():
    lo, hi = stretch_band(0.35)
    assert lo < 1 - 0.35 and hi > 1 + 0.35 and np.isclose(lo * hi, (1 - 0.35 ** 2) ** 2)


# ------------------------------------------------------------------ the search
@settings(max_examples=4, deadline=None)
@given(st.integers(0, 1000), st.floats(0.55, 0.8), st.floats(1.0, 1.25))
def test_a_patch_under_a_known_affine_strain_is_found_exactly(seed, squeeze, stretch):
    """A 40-row patch whose partners are strained by up to 45% (no rigid fit within a tenth of a
    spacing) among the strained surface around it: every returned pair is the true one."""
    src = _surface(300, 7.0, seed)
    h = median_spacing(src)
    tgt = _strained(src, (stretch, squeeze), seed, [3.0, -1.0, 2.0])
    perm = np.random.default_rng(seed + 1).permutation(tgt.shape[0])
    inv = np.argsort(perm)
    found = affine_patch(src[:40], tgt[perm], 0.2 * h * squeeze, 0.35)
    assert found.pairs.shape[0] == 40  # an affine map of 3D: exact on the curved patch too
    assert np.array_equal(inv[found.pairs[:, 0]], found.pairs[:, 1])  # each row's own partner
    assert found.support >= 2.0 * found.chance and found.trials > 0


@settings(max_examples=4, deadline=None)
@given(st.integers(0, 1000))
def test_an_unrelated_patch_gives_nothing(seed):
    """Targets sampled independently on another surface: no pairs."""
    src = _surface(300, 7.0, seed)
    h = median_spacing(src)
    other = _strained(_surface(300, 7.0, seed + 7) * [1, 1, -1.5], (1.1, 0.7), seed, [0, 0, 0])
    found = affine_patch(src[:40], other, 0.2 * h, 0.35)
    assert found.pairs.shape[0] == 0


def test_affine_patch_is_deterministic_and_bounded():
    src = _surface(300, 7.0, 3)
    tgt = _strained(src, (1.1, 0.6), 3, [1.0, 0.0, 0.0])
    h = median_spacing(src)
    a = affine_patch(src[:40], tgt, 0.12 * h, 0.35)
    b = affine_patch(src[:40], tgt, 0.12 * h, 0.35, tree_t=cKDTree(tgt))
    assert np.array_equal(a.pairs, b.pairs) and a.trials == b.trials
    assert a.pairs.shape[0] <= 40 and len(set(a.pairs[:, 1].tolist())) == a.pairs.shape[0]
    assert affine_patch(src[:5], tgt, h, 0.35).pairs.shape[0] == 0  # too few rows


# ------------------------------------------------------------------ in the local hypothesis
def test_a_placed_window_under_a_strain_no_rigid_patch_fits_is_grown_from_an_affine_patch(window_settings):
    """The target compressed by 40% along one axis of the surface (no 40-row patch fits rigidly
    within the rigid search's gate): inside a placed window the affine patch seeds the growth and
    every grown pair is right; the direct path (no reach) does not search affine patches."""
    from gatv.nonrigid.stages import Problem, local_hypothesis

    x = _surface(300, 7.0, 5)
    y = np.column_stack([x[:, 0], 0.6 * x[:, 1], x[:, 2]]) + [0.3, -0.2, 0.1]  # placed: no turn
    perm = np.random.default_rng(5).permutation(len(y))
    inv = np.argsort(perm)
    y = y[perm]
    reach = 3.0 * median_spacing(y)
    placed = local_hypothesis(Problem.build(x, y, window_settings(local_reach=reach)),
                              window_settings(local_reach=reach))
    assert placed.pairs.shape[0] >= 0.9 * len(x)
    assert np.array_equal(inv[placed.pairs[:, 0]], placed.pairs[:, 1])
    assert any(w.get("affine_support", 0) > 0 for w in placed.windows)
    free = local_hypothesis(Problem.build(x, y, window_settings()), window_settings())
    assert not any("affine_support" in w for w in free.windows)
