"""Numba kernels of the congruent-triple search against numpy references."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gatv.models.rigid import congruent_kernels as k
from gatv.models.rigid.congruent import (
    TargetIndex,
    rarest_side_first,
    sample_triples,
    sequential_boundary,
    trial_motions,
    triangle_heights,
)
from gatv.fitting import kabsch
from gatv.ga import Rotor


def _cloud(seed, n):
    return np.random.default_rng(seed).uniform(-5, 5, (n, 3))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(2, 30))
def test_pair_table_is_every_pair_sorted_by_length(seed, n):
    p = _cloud(seed, n)
    lengths, pi, pj = k.pair_table(p)
    assert lengths.shape == (n * (n - 1) // 2,)
    assert np.all(np.diff(lengths) >= 0)
    assert np.all(pi < pj)
    assert np.allclose(lengths, np.linalg.norm(p[pi] - p[pj], axis=1))
    assert {(int(a), int(b)) for a, b in zip(pi, pj)} == set(itertools.combinations(range(n), 2))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(2, 30))
def test_sorted_neighbours_match_numpy(seed, n):
    p = _cloud(seed, n)
    dist, idx = k.sorted_neighbours(p)
    full = np.linalg.norm(p[:, None] - p[None], axis=2)
    np.fill_diagonal(full, np.inf)
    ref = np.sort(full, axis=1)[:, : n - 1]
    assert np.allclose(dist, ref)
    assert np.allclose(full[np.arange(n)[:, None], idx], dist)
    for i in range(n):
        assert i not in idx[i]


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 60), r=st.floats(0.05, 3.0))
def test_grid_nearest_and_count_match_brute_force(seed, n, r):
    target = _cloud(seed, n)
    index = TargetIndex(target, r) if n >= 2 else None
    if index is None:
        return
    queries = _cloud(seed + 1, 40)
    got = index.nearest(queries)
    d = np.linalg.norm(queries[:, None] - target[None], axis=2)
    want = np.where(d.min(axis=1) <= r, d.argmin(axis=1), -1)
    # ties aside, the same nearest point within the radius
    assert np.array_equal(got >= 0, want >= 0)
    hit = got >= 0
    assert np.allclose(d[hit, got[hit]], d[hit].min(axis=1))
    R = Rotor.from_axis_angle([1, 0, 0], 0.3).as_matrix()
    t = np.array([0.2, -0.1, 0.4])
    moved = queries @ R.T + t
    dm = np.linalg.norm(moved[:, None] - target[None], axis=2)
    count = k.count_inliers(R, t, queries, target, index.start, index.order, index.origin, index.cell,
                            index.dims, index.radius, 0, k._NO_VISIT, 0.0, 0.0)  # no omitted array: cached
    assert count == int(np.sum(dm.min(axis=1) <= r))


def _reference_best(source, target, tri, eps, radius):
    """Brute force over every ordered target triple: best inlier count of congruent ones."""
    a, b, c = tri
    sides = (np.linalg.norm(source[a] - source[b]), np.linalg.norm(source[a] - source[c]),
             np.linalg.norm(source[b] - source[c]))
    best = -1
    n = target.shape[0]
    for kk, ll, mm in itertools.permutations(range(n), 3):
        s2 = (np.linalg.norm(target[kk] - target[ll]), np.linalg.norm(target[kk] - target[mm]),
              np.linalg.norm(target[ll] - target[mm]))
        if all(abs(u - v) <= eps for u, v in zip(sides, s2)):
            R, t = kabsch(source[[a, b, c]], target[[kk, ll, mm]])
            moved = source @ R.T + t
            d = np.linalg.norm(moved[:, None] - target[None], axis=2).min(axis=1)
            best = max(best, int(np.sum(d <= radius)))
    return best


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_triple_hypotheses_find_the_best_congruent_triple(seed):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-5, 5, (9, 3))
    R = Rotor.from_axis_angle(rng.normal(size=3), rng.uniform(0, np.pi)).as_matrix()
    y = np.vstack([x[:6] @ R.T + [1.0, 2.0, 3.0], rng.uniform(-5, 5, (4, 3))])
    radius, eps = 1e-6, 2e-6
    index = TargetIndex(y, radius)
    tri = sample_triples(9, 6, rng)
    offsets = rng.integers(0, 1 << 30, tri.shape[0])  # any start: the full scan wraps around
    scores, _, _, _, _, _, _ = k.triple_hypotheses(
        x, y, tri, offsets, index.plen, index.pi, index.pj, index.ndist, index.nidx, eps, index.start, index.order,
        index.origin, index.cell, index.dims, radius, 1000, np.zeros((0, 3)), np.zeros((0, 3)), 0.15,
        # every argument given, as gatv.models.rigid.congruent.trial_motions gives them: omitted array defaults make
        # a specialisation numba cannot cache (13 s of compilation in every run)
        0, k._NO_VISIT, 0.0, 0.0, k._NO_OCC, k._ORIGIN, 1.0, k._DIMS, k._HALF_BOX)
    for q in range(tri.shape[0]):
        assert scores[q] == _reference_best(x, y, tri[q], eps, radius)


def test_trial_motions_recover_the_motion_and_rank_it_first():
    rng = np.random.default_rng(4)
    x = rng.uniform(-5, 5, (30, 3))
    R = Rotor.from_axis_angle([0, 1, 1], 2.0).as_matrix()
    y = np.vstack([x @ R.T + [3.0, 0.0, -1.0], rng.uniform(-5, 5, (30, 3))])
    index = TargetIndex(y, 1e-6)
    trials = trial_motions(x, index, eps=2e-6, max_triples=200, rng=rng, keep=4)
    assert len(trials) >= 1 and trials.support[0] == 30
    assert np.allclose(trials.matrices[0][:3, :3], R, atol=1e-8)
    assert np.allclose(trials.matrices[0][:3, 3], [3.0, 0.0, -1.0], atol=1e-8)


def test_triangle_height_of_a_3_4_5_triangle():
    pts = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 4.0, 0.0], [1.0, 1.0, 0.0]])
    h = triangle_heights(pts, np.array([[0, 1, 2], [0, 1, 1], [0, 3, 1]]))
    assert np.allclose(h, [12.0 / 5.0, 0.0, 1.0 * 3.0 / 3.0])


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(2, 80), per_bucket=st.sampled_from([1, 3, 16, 1000]),
       ties=st.booleans())
def test_length_lookup_gives_numpys_lower_bound(seed, n, per_bucket, ties):
    """Every lower bound through the bucket table equals ``np.searchsorted`` (side ``left``), at
    lengths on, between and beyond the table's entries and its buckets' bounds."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(-5, 5, (n, 3))
    if ties:
        p = np.round(p)  # repeated lengths, lengths on bucket bounds
    plen = k.pair_table(p)[0]
    bounds, step = k.length_lookup(plen, per_bucket)
    assert bounds[0] == 0 and np.all(np.diff(bounds) >= 0)
    queries = np.concatenate([plen, np.nextafter(plen, np.inf), np.nextafter(plen, -np.inf),
                              step * np.arange(bounds.shape[0] + 2), rng.uniform(-1.0, plen[-1] + 1.0, 50),
                              [-1.0, 0.0]])
    got = np.array([k._lower_bound_lookup(plen, float(q), bounds, step) for q in queries])
    assert np.array_equal(got, np.searchsorted(plen, queries))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(3, 60), eps=st.sampled_from([1e-9, 0.01, 0.3, 3.0]))
def test_side_widths_against_numpy(seed, n, eps):
    """The kernel's window of target pairs a side, against searchsorted on the sorted lengths."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-5, 5, (n, 3)), rng.uniform(-5, 5, (n, 3))
    index = TargetIndex(y, 0.1)
    tri = sample_triples(n, 40, rng)
    ref = np.empty((40, 3), np.int64)
    for q, (u, v) in enumerate(((0, 1), (0, 2), (1, 2))):
        d = np.linalg.norm(x[tri[:, u]] - x[tri[:, v]], axis=1)
        ref[:, q] = np.maximum(np.searchsorted(index.plen, d + eps) - np.searchsorted(index.plen, d - eps), 0)
    got = k.side_widths(x, tri, index.plen, index.plen_bounds, index.plen_step, eps)
    assert np.array_equal(got, ref)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_triangle_heights_against_numpy(seed):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(15, 3))
    tri = np.concatenate([sample_triples(15, 30, rng), [[0, 1, 1], [2, 2, 2]]])
    a, b, c = (pts[tri[:, q]] for q in range(3))
    longest = np.max(np.stack([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - a, axis=1),
                               np.linalg.norm(c - b, axis=1)]), axis=0)
    ref = np.linalg.norm(np.cross(b - a, c - a), axis=1) / np.maximum(longest, np.finfo(np.float64).tiny)
    assert np.allclose(triangle_heights(pts, tri), ref, rtol=1e-12, atol=0.0)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10**6), scale=st.floats(0.01, 100.0))
def test_triangle_heights_are_rigid_invariant_and_scale_linearly(seed, scale):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(12, 3))
    tri = sample_triples(12, 20, rng)
    R = Rotor.from_axis_angle(rng.normal(size=3), rng.uniform(0, np.pi)).as_matrix()
    moved = scale * pts @ R.T + rng.normal(size=3)
    h = triangle_heights(pts, tri)
    assert np.allclose(triangle_heights(moved, tri), scale * h, rtol=1e-9, atol=1e-12 * scale)
    # The smallest height is at most every side (it is one triangle's height over its longest side).
    sides = np.linalg.norm(pts[tri[:, [0, 0, 1]]] - pts[tri[:, [1, 2, 2]]], axis=2)
    assert np.all(h <= sides.min(axis=1) + 1e-12)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 40), r=st.floats(0.05, 2.0))
def test_occupancy_never_turns_a_hit_into_a_miss(seed, n, r):
    """A query within ``r`` of a target lies in an occupied cell; counts with the grid are exact."""
    rng = np.random.default_rng(seed)
    target = _cloud(seed, max(n, 2))
    index = TargetIndex(target, r)
    near = target[rng.integers(0, target.shape[0], 60)] + rng.normal(size=(60, 3)) * r / 2
    queries = np.vstack([near, _cloud(seed + 1, 60)])
    d = np.linalg.norm(queries[:, None] - target[None], axis=2).min(axis=1)
    occupied = np.array([k.maybe_occupied(q, index.occupancy, index.occ_origin, index.occ_cell, index.occ_dims)
                         for q in queries])
    assert np.all(occupied[d <= r])
    R, t = np.eye(3), np.zeros(3)
    got, visited = k.count_inliers_visited(R, t, queries, target, index.start, index.order, index.origin,
                                           index.cell, index.dims, index.radius, 0, np.zeros(0, np.int64),
                                           0.0, 0.0, index.occupancy, index.occ_origin, index.occ_cell,
                                           index.occ_dims, np.zeros(0, np.int64))
    assert got == int(np.sum(d <= r)) and visited == queries.shape[0]


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), p_accept=st.floats(0.05, 0.5), ratio=st.floats(2.0, 50.0))
def test_sequential_count_stops_exactly_at_the_boundary(seed, p_accept, ratio):
    """The count so far is the brute-force count of the visited prefix, stopped where it first crosses."""
    rng = np.random.default_rng(seed)
    source = _cloud(seed, 200)
    target = np.vstack([source[: int(200 * p_accept)], _cloud(seed + 1, 50)])
    index = TargetIndex(target, 1e-6)
    slope, offset = sequential_boundary(p_accept / ratio, p_accept)
    visit = rng.permutation(200).astype(np.int64)
    base = visit[:3].copy()  # base points count, but not in the test
    n, v = k.count_inliers_visited(np.eye(3), np.zeros(3), source, target, index.start, index.order, index.origin,
                                   index.cell, index.dims, index.radius, 0, visit, slope, offset, index.occupancy,
                                   index.occ_origin, index.occ_cell, index.occ_dims, base)
    hits = (np.arange(200) < int(200 * p_accept))[visit]
    assert n == int(hits[:v].sum())
    in_base = np.isin(visit, base)
    stat = np.concatenate([[0], np.cumsum(hits & ~in_base)])
    steps = np.concatenate([[0], np.cumsum(~in_base)])
    crossed = stat < slope * steps + offset
    first = int(np.argmax(crossed)) if crossed[:200].any() else 200
    assert v == min(first, 200)


@settings(max_examples=10, deadline=None)
@given(p_accept=st.floats(0.02, 0.4), ratio=st.floats(3.0, 30.0), miss=st.sampled_from([0.01, 0.05, 0.2]))
def test_sequential_boundary_is_walds_test(p_accept, ratio, miss):
    """On the boundary the log-likelihood ratio is log(miss); a motion at p_accept is dropped at most
    that often, a wrong one almost always within a few times the expected -log(miss) / KL points."""
    p0 = p_accept / ratio
    slope, offset = sequential_boundary(p0, p_accept, miss)
    v = 100.0
    h = slope * v + offset
    llr = h * np.log(p_accept / p0) + (v - h) * np.log((1 - p_accept) / (1 - p0))
    assert llr == pytest.approx(np.log(miss), abs=1e-9)
    kl = p0 * np.log(p0 / p_accept) + (1 - p0) * np.log((1 - p0) / (1 - p_accept))
    horizon = int(4 * -np.log(miss) / kl) + 50
    line = slope * np.arange(1, horizon + 1) + offset
    rng = np.random.default_rng(0)
    stat = np.cumsum(rng.random((2000, horizon)) < p_accept, axis=1)
    dropped = np.any(stat < line, axis=1).mean()
    assert dropped <= miss + 4 * np.sqrt(miss / 2000)
    wrong = np.cumsum(rng.random((1000, horizon)) < p0, axis=1)
    assert np.any(wrong < line, axis=1).mean() > 0.9
    assert sequential_boundary(p_accept, p_accept) == (0.0, 0.0)


def _congruent_by_discrepancy(source, target, tri, eps):
    """Brute force: every ordered target triple congruent to ``tri`` within ``eps``, tightest first."""
    a, b, c = tri
    sides = (np.linalg.norm(source[a] - source[b]), np.linalg.norm(source[a] - source[c]),
             np.linalg.norm(source[b] - source[c]))
    found = []
    for kk, ll, mm in itertools.permutations(range(target.shape[0]), 3):
        s2 = (np.linalg.norm(target[kk] - target[ll]), np.linalg.norm(target[kk] - target[mm]),
              np.linalg.norm(target[ll] - target[mm]))
        e = np.subtract(s2, sides)
        if np.all(np.abs(e) <= eps):
            found.append((float(e @ e), (kk, ll, mm)))
    return [m for _, m in sorted(found)]


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), eps=st.sampled_from([0.3, 0.6, 1.0]), keep=st.sampled_from([2, 8, 20]),
       first_box=st.sampled_from([0.0, 0.1, 0.25, 0.5]))
def test_scored_matches_are_the_tightest_of_all(seed, eps, keep, first_box):
    """With more matches listed than scored, the scored ones are the tightest of all, whichever pass
    (whichever box first)."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-3, 3, (10, 3))
    y = rng.uniform(-3, 3, (14, 3))
    index = TargetIndex(y, 0.1)
    a, b, c = sample_triples(10, 1, rng)[0]
    ks, ls, ms, listed, _ = k.scored_matches(x, y, a, b, c, int(rng.integers(0, 1 << 30)), index.plen,
                                             index.pi, index.pj, index.ndist, index.nidx, eps, 10**5, keep,
                                             np.zeros((0, 3)), np.zeros((0, 3)), 0.15, False, first_box)
    want = _congruent_by_discrepancy(x, y, (a, b, c), eps)[:keep]
    assert sorted(zip(ks.tolist(), ls.tolist(), ms.tolist())) == sorted(want)
    assert listed >= len(want)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), eps=st.sampled_from([0.05, 0.3, 1.0]), n2=st.sampled_from([6, 14, 25]))
def test_both_listings_give_every_congruent_match(seed, eps, n2):
    """Listed by pair or by point, the matches are the brute-force set; each costs probes."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-3, 3, (10, 3))
    y = rng.uniform(-3, 3, (n2, 3))
    index = TargetIndex(y, 0.1)
    a, b, c = sample_triples(10, 1, rng)[0]
    want = sorted(_congruent_by_discrepancy(x, y, (a, b, c), eps))
    none = np.zeros((0, 3))
    for by_point in (0, 1, -1):
        ks, ls, ms, disc, probes = k._congruent_matches(
            x, y, a, b, c, int(rng.integers(0, 1 << 30)), index.plen, index.pi, index.pj, index.ndist,
            index.nidx, eps, 10**5, none, none, 0.15, False, by_point)
        assert sorted(zip(ks.tolist(), ls.tolist(), ms.tolist())) == want
        sides = np.array([[np.linalg.norm(y[p] - y[q]) for p, q in ((kk, ll), (kk, mm), (ll, mm))]
                          for kk, ll, mm in zip(ks, ls, ms)]).reshape(-1, 3)
        ref = np.array([np.linalg.norm(x[a] - x[b]), np.linalg.norm(x[a] - x[c]), np.linalg.norm(x[b] - x[c])])
        assert np.allclose(disc, ((sides - ref) ** 2).sum(axis=1))
        assert probes >= 2


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), eps=st.sampled_from([0.05, 0.3, 1.0]))
def test_rarest_side_first_keeps_the_triangles(seed, eps):
    """Same vertex sets and side lengths, the sides ordered by their target pairs (fewest first, the
    third-point side (0, 2) next); the matches follow."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-3, 3, (12, 3))
    y = rng.uniform(-3, 3, (15, 3))
    index = TargetIndex(y, 0.1)
    tri = sample_triples(12, 20, rng)
    out = rarest_side_first(x, tri, index, eps)
    assert np.array_equal(np.sort(out, axis=1), np.sort(tri, axis=1))

    def width(t, u, v):
        d = np.linalg.norm(x[t[:, u]] - x[t[:, v]], axis=1)
        return np.searchsorted(index.plen, d + eps) - np.searchsorted(index.plen, d - eps)

    first, second = width(out, 0, 1), width(out, 0, 2)
    assert np.all(first <= second) and np.all(second <= width(out, 1, 2))
    # The reordered triple's matches are the original's, relabelled.
    q = int(np.argmax(first))
    perm = [list(tri[q]).index(v) for v in out[q]]
    before = {tuple(m[p] for p in perm) for m in _congruent_by_discrepancy(x, y, tuple(tri[q]), eps)}
    assert set(_congruent_by_discrepancy(x, y, tuple(out[q]), eps)) == before


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), eps=st.sampled_from([0.2, 0.5]))
def test_predicted_matches_follow_the_count(seed, eps):
    """``predicted_matches`` (independent sides, 8 w1 w2 w3 / n^3) against the listed count on uniform
    points: the totals over many triples agree within a factor of 2."""
    from gatv.models.rigid.congruent import predicted_matches

    rng = np.random.default_rng(seed)
    x = rng.uniform(-3, 3, (40, 3))
    y = rng.uniform(-3, 3, (60, 3))
    index = TargetIndex(y, 0.1)
    tri = sample_triples(40, 60, rng)
    none = np.zeros((0, 3))
    counted = sum(k._congruent_matches(x, y, a, b, c, 0, index.plen, index.pi, index.pj, index.ndist,
                                       index.nidx, eps, 10**6, none, none, 0.15, False, -1)[0].shape[0]
                  for a, b, c in tri)  # by_point given, as scored_matches gives it: one specialisation
    predicted = predicted_matches(x, tri, index, eps).sum()
    assert 0.5 < counted / predicted < 2.0


@given(predicted=st.lists(st.floats(0.0, 1e9), min_size=1, max_size=20), max_matches=st.sampled_from([64, 512]))
def test_first_boxes_hold_the_scored_matches(predicted, max_matches):
    """The first box: none below HALF_BOX_FROM x the scored matches, else at most half the listing's,
    sized to hold FIRST_BOX_MATCHES x them where smaller, and never larger for a triple with more."""
    from gatv.models.rigid.congruent import FIRST_BOX_MATCHES, HALF_BOX_FROM, first_boxes

    p = np.asarray(predicted)
    box = first_boxes(p, max_matches)
    small = p < HALF_BOX_FROM * max_matches
    assert np.all(box[small] == 0.0)
    assert np.all((box[~small] > 0.0) & (box[~small] <= 0.5))
    sized = ~small & (box < 0.5)
    assert np.allclose(p[sized] * box[sized] ** 3, FIRST_BOX_MATCHES * max_matches)
    order = np.argsort(p[~small])
    assert np.all(np.diff(box[~small][order]) <= 1e-12)
