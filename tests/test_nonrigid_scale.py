"""Non-rigid registration at scale (gatv.nonrigid.multiscale) and several non-rigid motions (segment)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from hypothesis import given, settings
from hypothesis import strategies as st

from gatv.candidates import median_spacing
from gatv.datasets import correspondence_stats
from gatv.errors import InputError
from gatv.nonrigid import NonRigidSegmentation, register, segment
from gatv.nonrigid import deformations as deform
from gatv.nonrigid import multiscale as ms


def _pairs(m):
    return set(map(tuple, np.asarray(m.correspondences).tolist()))


# ------------------------------------------------------------------ kernels against numpy references
def test_grid_subsample_keeps_one_point_per_voxel_nearest_its_centre():
    p = np.random.default_rng(0).uniform(0, 10, (3000, 3)) * [1, 1, 0.01]
    idx = ms.grid_subsample(p, 200)
    assert 180 <= idx.size <= 220 and np.all(np.diff(idx) > 0)
    assert np.array_equal(idx, ms.grid_subsample(p, 200))  # deterministic
    # min_share: isolated points far from the structure take no voxel
    far = np.random.default_rng(1).uniform(-50, 60, (300, 3))
    both = np.vstack([p, far])
    idx = ms.grid_subsample(both, 200, min_share=0.25)
    assert np.mean(idx < p.shape[0]) > 0.95
    assert np.array_equal(ms.grid_subsample(p, 10_000), np.arange(p.shape[0]))


def test_local_affine_warp_reproduces_an_affine_field_and_matches_lstsq():
    rng = np.random.default_rng(2)
    x = rng.uniform(-5, 5, (400, 3))
    A = np.eye(3) + 0.1 * rng.normal(size=(3, 3))
    b = np.array([1.0, -2.0, 0.5])
    w = ms.LocalAffineWarp(x, x @ A.T + b - x)
    q = rng.uniform(-4, 4, (50, 3))
    np.testing.assert_allclose(w(q), q @ A.T + b, atol=1e-6)
    # a non-affine field: the constant of the least-squares fit on the k nearest (numpy reference)
    d = np.sin(x)
    w = ms.LocalAffineWarp(x, d, k=10)
    for qq in q[:5]:
        nb = np.argsort(np.linalg.norm(x - qq, axis=1))[:10]
        M = np.column_stack([np.ones(10), x[nb] - qq])
        coef, *_ = np.linalg.lstsq(M, d[nb], rcond=None)
        np.testing.assert_allclose(w(qq[None])[0], qq + coef[0], atol=1e-4)


def test_loo_affine_residuals_zero_for_affine_and_flag_a_swapped_match():
    x = deform.sample_plane(300, 10.0, seed=1)
    y = deform.twist(x, 20.0)
    r = ms.loo_affine_residuals(x, y - x)
    assert np.median(r) < 0.01
    d = y - x
    d[[10, 11]] = y[[11, 10]] - x[[10, 11]]  # two matches swapped
    r = ms.loo_affine_residuals(x, d)
    assert r[10] > 10 * np.median(r) and r[11] > 10 * np.median(r)


def test_local_eq41_passes_a_rigid_motion_and_rejects_wrong_matches():
    rng = np.random.default_rng(3)
    x = rng.uniform(-5, 5, (200, 3))
    y = deform.rigid(x, 40.0, axis=(1, 1, 0), translation=(1.0, 2.0, 3.0))
    pairs = np.column_stack([np.arange(200), np.arange(200)])
    passed, R, t = ms.local_eq41_pairs(x, y, pairs, strain=0.0, gate=1e-6)
    assert passed.all()
    np.testing.assert_allclose(x[:5] @ R[0].T + t[0], y[:5], atol=1e-8)
    wrong = pairs.copy()
    wrong[:20, 1] = rng.permutation(200)[:20]
    passed, _, _ = ms.local_eq41_pairs(x, y, wrong, strain=0.0, gate=1e-3)
    assert np.mean(passed[:20]) < 0.2
    # matches whose local patch (12 nearest) holds no wrong match keep passing
    from scipy.spatial import cKDTree

    _, nb = cKDTree(x).query(x, k=ms.MLS_NEIGHBOURS)
    clean = ~np.any(nb < 20, axis=1)
    assert clean.sum() > 20 and passed[clean].all()


# ------------------------------------------------------------------ memory: no N x M term
@settings(max_examples=40, deadline=None)
@given(n1=st.integers(5000, 10**7), n2=st.integers(5000, 10**7), c=st.integers(50, 5000))
def test_memory_estimate_grows_linearly_not_as_n_times_m(n1, n2, c):
    base = ms.memory_estimate(n1, n2, c)
    double = ms.memory_estimate(2 * n1, 2 * n2, c)
    # beyond the coarse subsample: linear in N + M (plus fixed terms), never 4x
    assert base < double <= 2 * base
    # bounded per point: no N x M allocation hides in the estimate
    from gatv.candidates import BYTES_PER_CANDIDATE_PAIR

    assert base <= 1000.0 * (n1 + n2) + BYTES_PER_CANDIDATE_PAIR * c * c + 1e8


def test_size_over_the_memory_budget_fails_at_once_naming_budget_and_subsampling():
    x = deform.sample_plane(3000, 10.0, seed=0)
    with pytest.raises(InputError, match="memory budget") as info:
        register(x, deform.twist(x, 30.0), multiscale=True, memory_budget=1e6)
    assert "coarse_points" in str(info.value) and "subsample" in str(info.value)


@pytest.mark.parametrize("kwargs, match", [
    ({"multiscale": "yes"}, "multiscale"),
    ({"coarse_points": 10}, "coarse_points"),
    ({"window_points": 0}, "window_points"),
    ({"model": "affine"}, "model"),
])
def test_bad_multiscale_options_name_the_argument(kwargs, match):
    x = deform.sample_plane(50, 10.0, seed=0)
    with pytest.raises(InputError, match=match):
        register(x, x + 1.0, **kwargs)


# ------------------------------------------------------------------ multi-resolution solve
@pytest.fixture(scope="module")
def twisted_multi():
    x = deform.sample_plane(200, 10.0, seed=3)
    trial = deform.nonrigid_trial(x, deform.twist(x, 60.0), 0.0, seed=4)
    m = register(trial.source, trial.target, multiscale=True, coarse_points=80, window_points=80)
    return trial, m


def test_multiscale_recovers_the_twist_with_the_local_mode(twisted_multi):
    trial, m = twisted_multi
    assert m and m.info["multiscale"]
    precision, recall = correspondence_stats(m.correspondences, trial.true_pairs)
    assert precision >= 0.98 and recall >= 0.9
    c = m.correspondences
    assert len(np.unique(c[:, 0])) == len(c) == len(np.unique(c[:, 1]))
    assert trial.warp_error(m.warp) < 0.05
    assert m.info["hypothesis"] == "voting"  # the paper's local mode gave the seeds


def test_multiscale_same_seed_same_result(twisted_multi):
    trial, m = twisted_multi
    again = register(trial.source, trial.target, multiscale=True, coarse_points=80, window_points=80)
    assert np.array_equal(again.correspondences, m.correspondences)


def test_multiscale_equals_the_direct_solve_where_both_run(twisted_multi):
    trial, m = twisted_multi
    direct = register(trial.source, trial.target, multiscale=False)
    common = _pairs(m) & _pairs(direct)
    assert len(common) >= 0.97 * max(m.support, direct.support)


def test_multiscale_places_the_window_by_the_identity_and_skips_the_coarse_solve(twisted_multi):
    _trial, m = twisted_multi
    assert m.info["placement"] == "identity"
    assert "time_coarse_s" not in m.info  # the identity-placed window beat chance: no coarse solve
    assert m.info["windows"][-1]["support"] > 0


def test_multiscale_falls_back_to_the_coarse_placement_when_the_identity_window_cannot_hold_the_partners():
    x = deform.sample_plane(200, 10.0, seed=3)
    y = deform.twist(x, 30.0) + [25.0, 0.0, 0.0]  # a shift of ~35 spacings: no identity window holds it
    trial = deform.nonrigid_trial(x, y, 0.0, seed=4)
    # without the rigid starts (prealign=False) the coarse solve places the windows
    m = register(trial.source, trial.target, multiscale=True, coarse_points=80, window_points=80,
                 prealign=False)
    assert m.info["placement"] == "coarse"
    assert [w["placement"] for w in m.info["windows"]][:2] == ["identity", "identity"]
    precision, recall = correspondence_stats(m.correspondences, trial.true_pairs)
    assert precision >= 0.98 and recall >= 0.9
    # by default the bounded rigid pre-alignment places them (a shift is a rigid motion), before the
    # identity's second window, as it explains more of the coarse sets than the identity does
    m = register(trial.source, trial.target, multiscale=True, coarse_points=80, window_points=80)
    assert m.info["placement"] == "rigid" and "time_coarse_s" not in m.info
    assert [w["placement"] for w in m.info["windows"]] == ["identity", "rigid"]
    explained = m.info["auto_prealign"]["explained"]
    assert explained[1] > explained[0]
    precision, recall = correspondence_stats(m.correspondences, trial.true_pairs)
    assert precision >= 0.98 and recall >= 0.9


@settings(max_examples=6, deadline=None)
@given(stretch=st.floats(1.0, 4.0), seed=st.integers(0, 10_000))
def test_grow_reaches_the_whole_of_an_anisotropic_strip_from_a_few_seeds(stretch, seed):
    # a strip sampled `stretch` times closer across than along, bent: the next row along it is
    # farther than 1.5 median spacings, and the growth still reaches every point, all correct
    x = deform.sample_plane(400, 10.0, seed=seed) * [1.0, 1.0 / stretch, 1.0]
    y = deform.bend(x, 60.0, axis=(0, 1, 0))
    perm = np.random.default_rng(seed).permutation(x.shape[0])
    Y = y[perm]
    truth = np.argsort(perm)  # row i of x is row truth[i] of Y
    centre = np.argsort(np.linalg.norm(x, axis=1))[:12]
    seeds = np.column_stack([centre, truth[centre]])
    from scipy.spatial import cKDTree

    gate = 0.5 * median_spacing(Y)
    pairs = ms.grow(x, Y, cKDTree(Y), seeds, gate)
    assert pairs.shape[0] == x.shape[0]
    assert np.array_equal(pairs[:, 1], truth[pairs[:, 0]])


@settings(max_examples=6, deadline=None)
@given(offset=st.floats(0.1, 0.3), row=st.integers(0, 399))
def test_grow_leaves_an_ambiguous_point_waiting(offset, row):
    """A point whose prediction lies halfway between two unused targets (its true partner moved by
    ``offset`` spacings one way, a decoy the other way) is not matched by the growth; every other
    point is matched to its true partner, and the decoy to nothing."""
    from scipy.spatial import cKDTree

    g = np.arange(20.0)
    x = np.column_stack([np.repeat(g, 20), np.tile(g, 20), np.zeros(400)])  # spacing 1
    Y = x.copy()
    Y[row, 0] += offset
    Y = np.vstack([Y, x[row] - [offset, 0.0, 0.0]])  # the decoy, row 400
    centre = np.argsort(np.linalg.norm(x - x[row] - [6.0, 6.0, 0.0], axis=1))[:9]
    centre = centre[centre != row]
    seeds = np.column_stack([centre, centre])
    pairs = ms.grow(x, Y, cKDTree(Y), seeds, 0.45)
    assert row not in pairs[:, 0] and 400 not in pairs[:, 1]
    assert pairs.shape[0] == 399 and np.array_equal(pairs[:, 0], pairs[:, 1])
    assert 0.0 < ms.GROW_AMBIGUITY < 1.0


def test_direct_solve_skips_the_annealed_hypothesis_only_when_it_cannot_win(monkeypatch):
    from gatv.nonrigid import registration as reg

    x = deform.sample_plane(150, 10.0, seed=5)
    trial = deform.nonrigid_trial(x, deform.twist(x, 45.0), 0.0, seed=6)
    m = register(trial.source, trial.target)
    assert m.info.get("anneal_skipped") == "cannot win" and "anneal" not in m.info["hypotheses"]
    best = max(v["support"] for v in m.info["hypotheses"].values())
    assert reg.ANNEAL_PREFERENCE * best > min(len(trial.source), len(trial.target))
    # forcing the annealed hypothesis changes nothing
    monkeypatch.setattr(reg, "ANNEAL_PREFERENCE", 0.0)
    forced = register(trial.source, trial.target)
    assert "anneal" in forced.info["hypotheses"] and "anneal_skipped" not in forced.info
    assert np.array_equal(forced.correspondences, m.correspondences)


@pytest.mark.slow
def test_multiscale_equals_the_direct_solve_on_a_few_thousand_points():
    x = deform.sample_plane(1200, 10.0, seed=3)
    trial = deform.nonrigid_trial(x, deform.twist(x, 60.0), 0.0, seed=4)
    direct = register(trial.source, trial.target, multiscale=False)
    multi = register(trial.source, trial.target, multiscale=True, coarse_points=300, window_points=200)
    assert len(_pairs(multi) & _pairs(direct)) >= 0.99 * max(multi.support, direct.support)
    assert correspondence_stats(multi.correspondences, trial.true_pairs)[0] >= 0.99


@pytest.mark.slow
def test_multiscale_differently_sampled_sets_report_only_within_the_sampling_gate():
    rng = np.random.default_rng(0)
    x = deform.sample_plane(5000, 10.0, seed=1)
    y = deform.twist(x, 90.0)
    a = np.sort(rng.choice(5000, 4000, replace=False))
    b = np.sort(rng.choice(5000, 4000, replace=False))
    m = register(x[a], y[b])
    assert m.info["multiscale"]
    d = np.linalg.norm(y[b][m.correspondences[:, 1]] - y[a][m.correspondences[:, 0]], axis=1)
    assert np.mean(d <= m.info["spacing"]) >= 0.95
    assert m.support >= 0.7 * 4000 * 0.8


def test_large_result_warp_is_local_and_linear_in_memory():
    from gatv.nonrigid.motion import TPS_MAX_CONTROL

    k = TPS_MAX_CONTROL + 10
    x = np.random.default_rng(0).uniform(-1, 1, (k, 3))
    y = x @ np.diag([1.1, 0.9, 1.0]) + 0.2
    from gatv.nonrigid import NonRigidMotion

    m = NonRigidMotion(np.column_stack([np.arange(k), np.arange(k)]), x, y,
                       np.tile(np.eye(3), (k, 1, 1)), np.zeros((k, 3)))
    np.testing.assert_allclose(m.warp(x[:100]), y[:100], atol=1e-6)


@pytest.mark.slow  # 8,000 points a set; the fast suite's multiscale solves are the twisted_multi tests
def test_windows_hold_the_structure_among_volume_outliers():
    """A curved sheet (its centroid off the surface), differently sampled (80%/80%), among as many
    outliers again in the bounding box: the windows are the structure's rows, centred on its denser
    half, so the first identity-placed window beats chance (a ball around the centroid held mostly
    outliers, and that window failed)."""
    rng = np.random.default_rng(21)
    full = deform.bend(deform.sample_plane(5000, 10.0, seed=rng), 120.0)
    moved = deform.elastic(full, 0.3, seed=rng)
    a, b = (np.sort(rng.choice(5000, 4000, replace=False)) for _ in range(2))
    src = np.vstack([full[a], rng.uniform(full[a].min(0), full[a].max(0), (4000, 3))])
    tgt = np.vstack([moved[b], rng.uniform(moved[b].min(0), moved[b].max(0), (4000, 3))])
    m = register(src, tgt, multiscale=True)
    assert m.info["placement"] == "identity" and len(m.info["windows"]) == 1
    c = m.correspondences
    inlier = c[:, 0] < 4000
    assert inlier.mean() >= 0.99
    d = np.linalg.norm(tgt[c[inlier, 1]] - moved[a[c[inlier, 0]]], axis=1)
    assert np.mean(d <= median_spacing(moved[b])) >= 0.95 and inlier.sum() >= 0.5 * 4000


# ------------------------------------------------------------------ several non-rigid motions
@pytest.fixture(scope="module")
def two_motions():
    plate = deform.sample_plane(90, 10.0, seed=5)
    bar = deform.sample_plane(90, 10.0, seed=6) * [1.0, 0.3, 1.0] + [13.0, 0.0, 0.0]
    x = np.vstack([plate, bar])
    y = np.vstack([deform.twist(plate, 60.0),
                   deform.rigid(deform.bend(bar, 60.0), 20.0, translation=(1.0, 2.0, 1.0))])
    trial = deform.nonrigid_trial(x, y, 0.2, seed=7)
    return trial, segment(trial.source, trial.target)


def test_two_motion_scene_gives_two_labelled_motions(two_motions):
    trial, seg = two_motions
    assert isinstance(seg, NonRigidSegmentation) and len(seg) == 2
    # every motion lies on one body: its matched true pairs come from one of the two halves
    inlier_body = np.full(trial.source.shape[0], -1)
    order = np.argsort(trial.true_pairs[:, 0])
    truth_rows = trial.true_pairs[order]
    # recover which body each inlier source row came from through its true position
    inlier_body[truth_rows[:, 0]] = (trial.target[truth_rows[:, 1], 0] > 7.0).astype(int)
    found = set()
    for m in seg.motions:
        bodies = inlier_body[m.correspondences[:, 0]]
        bodies = bodies[bodies >= 0]
        assert np.mean(bodies == np.bincount(bodies).argmax()) > 0.98
        found.add(int(np.bincount(bodies).argmax()))
        precision, _ = correspondence_stats(m.correspondences, trial.true_pairs)
        assert precision >= 0.95
    assert found == {0, 1}
    # labels: matched rows carry their motion's label; no row in two motions
    for k, m in enumerate(seg.motions):
        assert np.all(seg.source_labels[m.correspondences[:, 0]] == k)
        assert np.all(seg.target_labels[m.correspondences[:, 1]] == k)
    all_src = np.concatenate([m.correspondences[:, 0] for m in seg.motions])
    assert len(np.unique(all_src)) == len(all_src)
    assert json.loads(json.dumps(seg.to_dict()))["n_motions"] == 2


@pytest.mark.slow
def test_segment_same_seed_same_result(two_motions):
    trial, seg = two_motions
    again = segment(trial.source, trial.target)
    assert np.array_equal(again.source_labels, seg.source_labels)
    assert [m.support for m in again] == [m.support for m in seg]


@pytest.fixture(scope="module")
def two_motions_half_outliers():
    """The benchmark's scene: a twisted plate and a bent, turned bar of 400 points each, and as
    many outliers again in each set's bounding box (50%)."""
    rng = np.random.default_rng(11)
    plate = deform.sample_plane(400, 10.0, seed=rng)
    bar = deform.sample_plane(400, 10.0, seed=rng) * [1.0, 0.3, 1.0] + [13.0, 0.0, 0.0]
    x = np.vstack([plate, bar])
    y = np.vstack([deform.twist(plate, 60.0),
                   deform.rigid(deform.bend(bar, 60.0), 20.0, translation=(1.0, 2.0, 1.0))])
    src = np.vstack([x, rng.uniform(x.min(0), x.max(0), (800, 3))])
    tgt = np.vstack([y, rng.uniform(y.min(0), y.max(0), (800, 3))])
    ps, pt = rng.permutation(1600), rng.permutation(1600)
    inv_s, inv_t = np.argsort(ps), np.argsort(pt)
    truth = np.column_stack([inv_s[:800], inv_t[:800]])  # rows < 400 of x: the plate
    body = np.full(1600, -1)
    body[inv_s[:800]] = np.r_[np.zeros(400, int), np.ones(400, int)]
    return src[ps], tgt[pt], truth, body, segment(src[ps], tgt[pt])


@pytest.mark.slow
def test_two_non_rigid_motions_among_half_outliers(two_motions_half_outliers):
    """Both motions found (the bent bar in round 2, by a start that turns it), each precise and
    complete, on one body each, no third (spurious) motion; same seed, same result."""
    src, tgt, truth, body, seg = two_motions_half_outliers
    assert len(seg) == 2
    true_set = {tuple(p) for p in truth.tolist()}
    found = set()
    for m in seg.motions:
        bodies = body[m.correspondences[:, 0]]
        k = int(np.bincount(bodies[bodies >= 0]).argmax())
        found.add(k)
        ok = np.array([tuple(p) in true_set for p in m.correspondences.tolist()])
        precision, recall = ok.mean(), ok.sum() / 400
        assert precision >= 0.95 and recall >= 0.8, (k, precision, recall)
    assert found == {0, 1}
    # round 2 registers the bar (bent 60°, turned 20°) by a start that turns it: the local windows,
    # or the dominant rigid motion now that the plate's unmatched rows left the pool with it
    assert [r["hypothesis"] for r in seg.info["rounds"]][1] in ("local", "rigid")
    all_tgt = np.concatenate([m.correspondences[:, 1] for m in seg.motions])
    assert len(np.unique(all_tgt)) == len(all_tgt)
    again = segment(src, tgt)
    assert np.array_equal(again.source_labels, seg.source_labels)
    assert np.array_equal(again.target_labels, seg.target_labels)


def test_window_centres_densest_first_and_not_overlapping():
    """The local windows' centres: the densest point first, each centre outside the windows
    chosen before it, deterministic."""
    from scipy.spatial import cKDTree

    from gatv.nonrigid.hypotheses import window_centres

    rng = np.random.default_rng(3)
    strip = deform.sample_plane(300, 10.0, seed=1) * [1.0, 0.3, 1.0]
    P = np.vstack([strip, rng.uniform([-5, -5, 0], [5, 5, 0], (300, 3))])
    k = 20
    c = window_centres(P, k, 8)
    dist, _ = cKDTree(P).query(P, k=k)
    assert c[0] == int(np.argmin(dist[:, -1]))
    for a in range(1, c.size):
        for b in range(a):
            assert np.linalg.norm(P[c[a]] - P[c[b]]) > dist[c[b], -1]
    assert np.all(c[:4] < 300)  # the dense strip (10 points per unit area) before the scattered (3)
    assert np.array_equal(c, window_centres(P, k, 8))


def test_segment_of_noise_is_falsy_with_a_reason():
    rng = np.random.default_rng(9)
    seg = segment(rng.uniform(0, 1, (40, 3)), rng.uniform(0, 1, (40, 3)), prealign=False)
    assert not seg and seg.info["reason"]
    assert seg.source_labels.shape == (40,) and np.all(seg.source_labels == -1)


@pytest.mark.parametrize("kwargs, match", [
    ({"max_motions": 0}, "max_motions"),
    ({"min_share": 1.5}, "min_share"),
    ({"progress": 3}, "progress"),
])
def test_segment_bad_options_name_the_argument(kwargs, match):
    x = deform.sample_plane(50, 10.0, seed=0)
    with pytest.raises(InputError, match=match):
        segment(x, x + 1.0, **kwargs)


def test_motion_parts_splits_disconnected_and_discontinuous_matches():
    from gatv.nonrigid.segment import motion_parts

    # segment's motion_parts is multiscale's (one function, re-exported)
    assert motion_parts is ms.motion_parts
    a = deform.sample_plane(100, 10.0, seed=0)
    xs = np.vstack([a, a + [20.0, 0, 0]])  # two bodies far apart, the same translation
    ys = xs + 0.1
    labels = motion_parts(xs, ys, 0.35, 0.05)
    # each body one part, label 0 the first (equal sizes: the stable rank keeps the order)
    assert labels.tolist() == [0] * 100 + [1] * 100
    # one body moving as one: a single part however it is placed
    assert motion_parts(xs[:100], ys[:100], 0.35, 0.05).tolist() == [0] * 100
    # one body, but its right strip (30 of the 100 points) jumps by 3 units: two parts, the larger 0
    jumped = ys[:100].copy()
    right = a[:, 0] > 2.0
    assert right.sum() == 30
    jumped[right] += [0, 0, 3.0]
    parts = motion_parts(xs[:100], jumped, 0.35, 0.05)
    assert np.all(parts[~right] == 0) and np.all(parts[right] == 1)
    # a jump within the strain allowance (|Δd| <= strain |Δx| + gate between neighbours) splits nothing
    small = ys[:100].copy()
    small[a[:, 0] > 0] += [0, 0, 0.04]
    assert np.all(motion_parts(xs[:100], small, 0.35, 0.05) == 0)


@pytest.mark.parametrize("angle", [60.0, 180.0])
def test_motion_parts_keep_a_shape_turned_as_a_whole_in_one_part(angle):
    # a twisted plane turned as a whole: every displacement between neighbours changes by
    # 2 sin(θ/2) |Δx| (over the strain), their lengths only by the twist's strain
    a = deform.sample_plane(200, 10.0, seed=1)
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    b = deform.rigid(deform.twist(a, 30.0), angle, axis=axis, translation=(5.0, -2.0, 1.0))
    assert np.all(ms.motion_parts(a, b, 0.35, 0.05) == 0)
    # the same turned shape with a third of it lifted by 3 units still splits there
    lifted = b.copy()
    right = a[:, 0] > 1.5
    lifted[right] += 3.0 * axis
    parts = ms.motion_parts(a, lifted, 0.35, 0.05)
    assert np.unique(parts[right]).size == 1 and np.unique(parts[~right]).size == 1
    assert parts[right][0] != parts[~right][0]


def _two_densities():
    """A strip sampled at 0.1 for x < 3 (630 rows) and at 0.5 beyond (175 rows, 22%): the median
    spacing is the dense one's, five times under the sparse one's (as a body's limbs)."""
    g = np.mgrid[0:3:0.1, 0:2.05:0.1].reshape(2, -1).T
    h = np.mgrid[3:20:0.5, 0:2.05:0.5].reshape(2, -1).T
    xy = np.vstack([g, h])
    return np.column_stack([xy, np.zeros(len(xy))]), len(g)


def test_motion_parts_follow_a_non_uniform_sampling():
    xs, n_dense = _two_densities()
    R = np.array([[np.cos(0.2), -np.sin(0.2), 0.0], [np.sin(0.2), np.cos(0.2), 0.0], [0.0, 0.0, 1.0]])
    ys = xs @ R.T + [1.0, 2.0, 0.5]
    # one rigid motion: one part, the sparse rows (spacing 5x the median) included
    assert np.all(ms.motion_parts(xs, ys, 0.35, 0.05) == 0)
    # the sparse end jumps by 3 units: two parts, exactly the two densities
    jumped = ys.copy()
    jumped[n_dense:] += [0.0, 0.0, 3.0]
    parts = ms.motion_parts(xs, jumped, 0.35, 0.05)
    assert np.all(parts[:n_dense] == 0) and np.all(parts[n_dense:] == 1)
    # one gate per match equal to the float gate: the same labels
    assert np.array_equal(ms.motion_parts(xs, jumped, 0.35, np.full(len(xs), 0.05)), parts)


@given(st.floats(0.01, 0.2), st.integers(0, 3))
@settings(max_examples=10, deadline=None)
def test_motion_parts_per_match_gates_widen_never_split(gate, seed):
    a = deform.sample_plane(150, 10.0, seed=seed)
    b = deform.twist(a, 40.0)
    base = ms.motion_parts(a, b, 0.35, gate)
    wider = ms.motion_parts(a, b, 0.35, np.full(len(a), gate) * np.linspace(1.0, 2.0, len(a)))
    # a wider gate only joins: every part with the wider gates is a union of the float gate's parts
    for p in np.unique(base):
        assert np.unique(wider[base == p]).size == 1


@pytest.mark.parametrize("scale", [1.0, 0.01, 250.0])
def test_on_surfaces_drops_matches_beside_a_coarsely_sampled_surface(scale):
    # a cylinder of radius 2 sampled at 0.5: its median plane height (0.07) is over a quarter of the
    # gate (0.25), as on a body's limbs; 20 points 1.2 off it, among its rows
    t = np.linspace(0, 2 * np.pi, 25, endpoint=False)
    T, Z = np.meshgrid(t, np.arange(0, 10, 0.5))
    cyl = np.column_stack([2 * np.cos(T.ravel()), 2 * np.sin(T.ravel()), Z.ravel()])
    pick = np.random.default_rng(0).choice(len(cyl), 20, replace=False)
    P = scale * np.vstack([cyl, cyl[pick] * [1.6, 1.6, 1.0] + [0, 0, 0.25]])
    pairs = np.column_stack([np.arange(len(P))] * 2)
    ok = ms.on_surfaces(P, P, pairs, 0.25 * scale)
    assert ok is not None and ok[:500].all() and not ok[500:].any()
    # one side off is enough: the target rows on the surface, the source rows beside it
    Q = P.copy()
    Q[500:] = scale * cyl[pick]
    assert not ms.on_surfaces(P, Q, pairs, 0.25 * scale)[500:].any()


# ------------------------------------------------------------------ command line
def test_cli_segment_writes_labels(tmp_path, capsys, parse_nonrigid):
    from gatv.cli.nonrigid import run

    a = deform.sample_plane(80, 10.0, seed=0)
    b = a + [14.0, 0, 0]
    np.save(tmp_path / "s.npy", np.vstack([a, b]))
    np.save(tmp_path / "t.npy", np.vstack([deform.twist(a, 45.0), deform.bend(b, 60.0) + [0, 0, 3]]))
    out = tmp_path / "r.json"
    args = parse_nonrigid(["nonrigid", str(tmp_path / "s.npy"), str(tmp_path / "t.npy"), "--segment",
                   "--out", str(out)])
    assert run(args) == 0
    record = json.loads(out.read_text())
    assert record["success"] and record["n_motions"] == 2
    assert len(record["source_labels"]) == 160
    assert "motions:         2" in capsys.readouterr().out


def test_segment_counts_only_structure_apart_from_the_motions_found():
    from gatv.nonrigid.segment import _apart

    a = deform.sample_plane(200, 10.0, seed=0)
    P = np.vstack([a, a + [30.0, 0.0, 0.0]])  # two patches far apart
    explained = np.zeros(400, bool)
    explained[:200:2] = True  # every other row of the first patch matched
    h = median_spacing(a)
    rows = np.flatnonzero(~explained)
    # the first patch's unmatched rows lie among its matches: only the second patch counts
    assert _apart(P, rows, explained, 3.0 * h) == 200
    assert _apart(P, rows, np.zeros(400, bool), 3.0 * h) == rows.size


def test_growth_waits_between_two_samples_however_narrow_the_nearest_gate():
    # seeds on a line, matched in place; the next source row (5, 0, 0) is predicted in place, its
    # nearest target 0.2 away (inside its gate, 0.25) and a second 0.3 away (outside that gate)
    x = np.array([[float(i), 0.0, 0.0] for i in range(6)])
    y = np.vstack([x[:5], [[5.2, 0.0, 0.0], [5.0, 0.3, 0.0], [40.0, 0.0, 0.0]]])
    seeds = np.column_stack([np.arange(5), np.arange(5)])
    tree_y = cKDTree(y)
    gates = np.array([0.25] * 7 + [1.0])  # one wide gate elsewhere (a sparse region): non-uniform
    grown = ms.grow(x, y, tree_y, seeds, gates, spacing=1.0)
    assert 5 not in grown[:, 0]  # ambiguous: waits
    # with the second target beyond the widest gate it is no rival: matched to the nearest
    y2 = y.copy()
    y2[6] = [5.0, 1.5, 0.0]
    grown = ms.grow(x, y2, cKDTree(y2), seeds, gates, spacing=1.0)
    assert [5, 5] in grown.tolist()


BUNNY = Path(__file__).resolve().parents[2] / "shared" / "data" / "nonrigid_bcpd_bunny"


@pytest.mark.slow
@pytest.mark.skipif(not (BUNNY / "bunny-x.txt").is_file(), reason="shared data absent")
def test_bunny_turned_and_scaled_sampled_80_80_with_the_defaults():
    # the bcpd bunny x → y (rotated 93°, scaled 0.83, deformed), each set an independent 80% of the
    # rows: no rigid motion explains the change of scale, the principal axes' similarity places
    # the windows (nothing was found before)
    x, y = np.loadtxt(BUNNY / "bunny-x.txt"), np.loadtxt(BUNNY / "bunny-y.txt")
    rng = np.random.default_rng(5)
    n, k = len(x), round(0.8 * len(x))
    xr, yr = np.sort(rng.choice(n, k, replace=False)), np.sort(rng.choice(n, k, replace=False))
    ps, pt = rng.permutation(k), rng.permutation(k)
    m = register(x[xr][ps], y[yr][pt], seed=0)
    assert m.info["placement"] == "similarity"
    c = m.correspondences
    src, tgt = xr[ps][c[:, 0]], yr[pt][c[:, 1]]
    assert np.sum(src == tgt) / np.intersect1d(xr, yr).size >= 0.9  # exact recall of the shared rows
    assert np.mean(src == tgt) >= 0.95  # exact precision
    h = median_spacing(y[yr])
    assert np.mean(np.linalg.norm(y[tgt] - y[src], axis=1) <= h) >= 0.95


def test_local_patches_of_a_placed_window_search_only_the_targets_within_its_margin(window_settings):
    """Inside a placed window (``local_reach``: the window's margin) each local patch is searched
    against the targets within that reach of it only.  The target holds the source's partners,
    twisted (so no patch moves exactly rigidly), and, 60 units away, an exact copy of the source:
    against the whole target every patch's rigid search prefers the exact copy far away; within
    the reach each takes its twisted partners."""
    from gatv.nonrigid.stages import Problem, local_hypothesis

    x = deform.sample_plane(300, 10.0, seed=3)
    near = deform.twist(x, 40.0)
    y = np.vstack([near, x + [0.0, 0.0, 60.0]])
    reach = 3.0 * median_spacing(near)
    free = local_hypothesis(Problem.build(x, y, window_settings()), window_settings())
    placed = local_hypothesis(Problem.build(x, y, window_settings(local_reach=reach)),
                              window_settings(local_reach=reach))
    # the whole target: the exact copy wins
    assert free.pairs.shape[0] > 0 and np.mean(free.pairs[:, 1] >= len(x)) > 0.5
    # within the reach: only the twisted partners, and every one right
    assert placed.pairs.shape[0] >= 0.9 * len(x)
    assert np.all(placed.pairs[:, 1] == placed.pairs[:, 0])
    assert all(w["targets"] < len(y) / 2 for w in placed.windows)
