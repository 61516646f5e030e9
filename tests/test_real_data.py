"""Rigid registration on real data: noise measured from the data, the pipeline choice, bounded work."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gatv import InputError, register, stages
from gatv.datasets import (
    DataNotFoundError,
    correspondence_stats,
    load_bunny_pair,
    paper_success,
    rotation_error_deg,
    table2_trial,
)
from gatv.models.rigid import NOISY_MAX_MATCHES, RIGID_TRIALS, WIDE
from gatv.registration import (
    choose_pipeline,
    surface_likeness,
)
from gatv.scans import plane_noise, register_scans
from gatv.stages import gate, noise_from_residuals


def _sphere(n, seed=0):
    u = np.random.default_rng(seed).normal(size=(n, 3))
    return u / np.linalg.norm(u, axis=1, keepdims=True)


# ---------------------------------------------------------------- noise
@settings(max_examples=30, deadline=None)
@given(sigma=st.floats(1e-3, 10.0), cut=st.floats(2.0, 6.0), seed=st.integers(0, 2**31 - 1))
def test_noise_from_truncated_residuals_is_unbiased(sigma, cut, seed):
    """Residual norms of pairs noisy in both sets, seen only within a gate: no bias in σ.

    Over 16 replicate sets the mean estimate is σ within 3 standard errors
    (plus 2%); a tight gate leaves few residuals and a nearly uniform ball,
    so one estimate alone may be off by more than 10% there.
    """
    rng = np.random.default_rng(seed)
    if cut < 0.5 ** (1 / 3) * 1.54 * np.sqrt(2.0):  # the gate hides more than half: unidentifiable
        return
    ests = []
    for _ in range(16):
        r = np.linalg.norm(rng.normal(0.0, np.sqrt(2.0) * sigma, (2000, 3)), axis=1)
        est = noise_from_residuals(r, cut * sigma)
        assert est is not None
        ests.append(est / sigma)
    ests = np.array(ests)
    assert abs(ests.mean() - 1.0) < 3.0 * ests.std(ddof=1) / 4.0 + 0.02
    if cut >= 3.5:  # the search's gate and wider: each estimate within 10%
        assert np.all(np.abs(ests - 1.0) < 0.1)


def test_noise_from_residuals_asks_for_a_wider_gate():
    """Residuals that fill the gate (the noise reaches past it) give None, not a wrong number."""
    r = np.linspace(0.6, 1.0, 1000)  # median 0.8 of the gate: more than a uniform ball's 0.794
    assert noise_from_residuals(r, 1.0) is None
    assert noise_from_residuals(np.zeros(10), 1.0) == 0.0


@settings(max_examples=10, deadline=None)  # each example: 24 replicate estimates of each kind
@given(sigma=st.floats(1e-3, 10.0), cut=st.floats(3.0, 5.0), n_true=st.integers(30, 60),
       chance_share=st.floats(0.05, 0.3), seed=st.integers(0, 2**31 - 1))
def test_noise_with_chance_pairs_in_the_gate(sigma, cut, n_true, chance_share, seed):
    """A motion's pairs hold chance pairs (residuals uniform over the gate's ball): given their
    expected number, the estimate is not biased by them, and the median's is.

    ``n_points`` source points, ``n_true`` of them the motion's; each of the
    others has a chance partner within the gate with probability ``p``
    (``chance_pairs = n_points p``).  Over 24 replicates the mixture's mean
    estimate is σ within 3 standard errors (plus 3%), below the median's.
    """
    rng = np.random.default_rng(seed)
    n_points, g = 4 * n_true, cut * sigma
    p = chance_share * n_true / (n_points - n_true)  # chance pairs: that share of the true ones
    plain, mixed = [], []
    for _ in range(24):
        r = np.linalg.norm(rng.normal(0.0, np.sqrt(2.0) * sigma, (n_true, 3)), axis=1)
        u = g * rng.random(rng.binomial(n_points - n_true, p)) ** (1.0 / 3.0)
        r = np.concatenate([r[r <= g], u])
        a = noise_from_residuals(r, g)
        b = noise_from_residuals(r, g, chance_pairs=n_points * p, n_points=n_points)
        if a is None:  # the median fills the gate: a wider gate is asked for, by both
            assert b is None
            continue
        plain.append(a / sigma)
        mixed.append(b / sigma)
    plain, mixed = np.array(plain), np.array(mixed)
    assert mixed.size >= 12
    assert abs(mixed.mean() - 1.0) < 3.0 * mixed.std(ddof=1) / np.sqrt(mixed.size) + 0.03
    assert mixed.mean() < plain.mean()


def test_noise_without_chance_pairs_is_the_median_estimate():
    """No chance pairs expected (or none given): the estimate is the truncated-median one, exactly."""
    r = np.linalg.norm(np.random.default_rng(1).normal(0.0, 0.2, (50, 3)), axis=1)
    base = noise_from_residuals(r, 0.7)
    assert noise_from_residuals(r, 0.7, chance_pairs=0.0, n_points=200) == base
    assert noise_from_residuals(r, 0.7, chance_pairs=5.0, n_points=None) == base


def _settle_from_a_noisy_triple(seed):
    """One motion of 32 points (target noise 0.2 a coordinate: σ = 0.2 / sqrt 2 for each set) among 160
    outliers, the fit a noisy triple's pose polished at the 0.12-spacing level, settled from there."""
    from scipy.spatial.transform import Rotation

    from gatv.motions import multi_motion_scene

    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=seed).as_matrix()
    scene = multi_motion_scene([R], [rng.uniform(-5, 5, 3)], [32], n_outliers=160, noise=0.2, seed=rng)
    P = stages.prepare(scene.source, scene.target)
    pairs = scene.true_pairs[0]
    levels = [f * P.spacing for f in (0.05, 0.12, 0.3)]
    tri = pairs[rng.choice(len(pairs), 3, replace=False)]
    M = P.model.fit(P.source[tri[:, 0]], P.target[tri[:, 1]])
    fit = stages.refine(P, stages.Fit(M, np.empty((0, 2), np.int64)), gate(levels[1]), 10)
    return P, fit, levels, 0.2 / np.sqrt(2.0)


def _refits_while_settling(monkeypatch, seed):
    """``(gate of each refit, gate of the estimate before it)`` while :func:`stages.settle_noise` runs."""
    P, fit, levels, _ = _settle_from_a_noisy_triple(seed)
    real_refine, real_nfr = stages.refine, stages.noise_from_residuals
    calls, last = [], [None]

    def nfr(res, g, dim=3, **kw):
        last[0] = g
        return real_nfr(res, g, dim, **kw)

    def refine(problem, f, g, *args):
        calls.append((g, last[0]))
        return real_refine(problem, f, g, *args)

    with monkeypatch.context() as m:
        m.setattr(stages, "noise_from_residuals", nfr)
        m.setattr(stages, "refine", refine)
        stages.settle_noise(P, fit, levels, 1)
    return calls


def test_settle_noise_refits_the_pose_only_on_a_wider_gate(monkeypatch):
    """A narrower gate keeps the pose (a refit on the pairs it keeps would fit their noise, and the estimates
    would shrink round after round); a wider one refits it."""
    for seed in range(8):
        calls = _refits_while_settling(monkeypatch, seed)
        # every refit after an estimate is at a gate wider than the one the estimate was made at
        assert all(g > g_est for g, g_est in calls if g_est is not None), (seed, calls)


def test_settle_noise_does_not_collapse_onto_a_motions_tightest_pairs():
    """From a noisy triple's polished pose, a motion of at least 20 pairs settles at no less than half its
    noise on each of 30 scenes (one settled at 0.27 of it when every narrower gate refitted the pose)."""
    for seed in range(30):
        P, fit, levels, sigma = _settle_from_a_noisy_triple(seed)
        if fit.support < 20:  # not a motion the peel would keep
            continue
        _, est = stages.settle_noise(P, fit, levels, 1)
        assert est > 0.5 * sigma, (seed, est / sigma)


def test_likelihood_pose_measures_the_noise_again_on_its_own_pose():
    """A pose refitted to the pairs of a gate at 0.7 of the noise measures the noise low (its own fit shrinks
    their residuals: median 0.84 over these 24 scenes at f = 0.5, 4%); measured again on the weighted pose's
    pairs within the final gate, it is about the truth (median 1.00), and the pose at it is no farther from
    the true rotation.  Never below the estimate it started from."""
    ratios, angles = [], []
    for k in range(24):
        tr = table2_trial(0.5, noise=0.04, seed=np.random.SeedSequence([7, k]))
        inliers = tr.source[tr.true_pairs[:, 0]]
        sigma = 0.04 * np.sqrt(np.mean(np.sum((inliers - inliers.mean(axis=0)) ** 2, axis=1)))
        P = stages.prepare(tr.source, tr.target)
        truth = np.eye(4)
        truth[:3, :3], truth[:3, 3] = tr.rotation, tr.translation
        g = gate(0.7 * sigma)
        fit = stages.refine(P, stages.regate(P, stages.Fit(truth, np.empty((0, 2), np.int64)), g), g)
        est = noise_from_residuals(P.residuals(fit.matrix, fit.correspondences), g)
        pose, again = stages.likelihood_pose(P, fit, est)
        assert again >= est
        np.testing.assert_array_equal(pose.correspondences, fit.correspondences)
        ratios.append((est / sigma, again / sigma))
        angles.append([rotation_error_deg(f.matrix[:3, :3], tr.rotation)
                       for f in (stages.weighted_pose(P, fit, est), pose)])
    ratios, angles = np.array(ratios), np.array(angles)
    assert np.median(ratios[:, 0]) < 0.9 and 0.93 < np.median(ratios[:, 1]) < 1.07, np.median(ratios, axis=0)
    assert np.mean(angles[:, 1]) <= np.mean(angles[:, 0]), angles.mean(axis=0)


@pytest.mark.parametrize("noise", [0.01, 0.03])
def test_noisy_sets_recovered_without_noise_given(noise):
    """The Table-2 protocol with Gaussian noise on every inlier: motion, pairs and the noise itself.

    Rotation error bound 50 × noise degrees (0.5° and 1.5°; the benchmark's success bar is 2°):
    over seeds 0-7, measured 0.10-0.35° at 1% and 0.49-1.40° at 3% (this seed, 3: 0.14° and
    0.52°); the noise estimate was 0.80-1.05 of the truth (this seed: 0.88, 0.875).
    """
    trial = table2_trial(0.5, noise=noise, seed=3)
    m = register(trial.source, trial.target)
    assert m and m.info["pipeline"] == "exact"
    assert rotation_error_deg(m.rotation, trial.rotation) < 50.0 * noise
    assert paper_success(m.correspondences, trial.true_pairs)
    precision, _ = correspondence_stats(m.correspondences, trial.true_pairs)
    assert precision >= 0.9
    sigma = noise * 5.0
    assert 0.7 * sigma < m.info["noise"] < 1.2 * sigma


def test_exact_sets_keep_an_exact_noise_estimate():
    trial = table2_trial(0.75, seed=1)
    m = register(trial.source, trial.target)
    precision, recall = correspondence_stats(m.correspondences, trial.true_pairs)
    assert precision == 1.0 and recall == 1.0
    assert m.info["noise"] < 1e-5 * m.info["spacing"]


# ----------------------------------------------------------- bounded work
@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(noise=st.sampled_from([0.0, 0.02, 0.08, 0.2]), seed=st.integers(0, 1000))
def test_trial_motions_stay_under_their_bound_as_noise_grows(noise, seed):
    """However noisy (and hopeless) the data, the scored trial motions stay under the work bound."""
    trial = table2_trial(0.9, noise=noise, seed=seed)
    n = trial.source.shape[0]
    max_work = 2e5
    m = register(trial.source, trial.target, seed=seed, max_work=max_work)
    levels = [r for r in m.info["trials"] if "triples" in r]
    scored = sum(r["congruent"] for r in levels)
    triples = sum(r["triples"] for r in levels)
    assert scored <= NOISY_MAX_MATCHES * triples
    # The bound is checked between chunks of samples: at most one chunk (<= 4096 samples) per level past it.
    per_match = stages.SCORE_COST + stages.VISIT_COST * n
    one_chunk = 4096 * (stages.SAMPLE_COST + stages.CANDIDATE_COST * WIDE + per_match * NOISY_MAX_MATCHES)
    assert scored * per_match + triples * stages.SAMPLE_COST <= max_work + len(levels) * one_chunk
    # Each level's work record counts at least its samples, their wide draws and its scored matches,
    # and all of it stays bounded.
    work = [r["work"] for r in levels]
    assert all(r["candidates"] <= WIDE * r["triples"] for r in levels)
    assert all(w >= stages.SAMPLE_COST * r["triples"] + stages.CANDIDATE_COST * r["candidates"]
               + stages.SCORE_COST * r["congruent"] for w, r in zip(work, levels))
    assert sum(work) <= max_work + len(levels) * one_chunk
    if not m:
        assert "reason" in m.info


@settings(max_examples=4, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 1000))
def test_a_narrower_listing_lists_fewer_matches_a_sample(seed):
    """A sample at 1 deviation lists fewer matches than at 2.5 (whose half box, at 1.25, already holds more)."""
    trial = table2_trial(0.9, noise=0.02, seed=seed)
    P = stages.prepare(trial.source, trial.target)
    levels = [0.1 * P.spacing]
    listed = {}
    for listing in (1.0, 2.5):
        tried: list = []
        stages.search(P, levels, budget=64, rng=np.random.default_rng(seed), max_matches=NOISY_MAX_MATCHES,
                      trial_options=RIGID_TRIALS, tried=tried, max_work=2e5, listing=listing)
        rec = tried[0]
        listed[listing] = rec["listed"] / max(rec["triples"], 1)
        assert rec["congruent"] <= min(rec["listed"], NOISY_MAX_MATCHES * rec["triples"])
        assert rec["work"] >= (stages.SAMPLE_COST * rec["triples"] + stages.SCORE_COST * rec["congruent"]
                               + stages.LIST_COST * rec["listed"] + stages.CANDIDATE_COST * rec["candidates"])
        # After its first chunk this busy level draws its samples wide, and the candidates are counted.
        assert 0 < rec["candidates"] <= WIDE * rec["triples"]
    assert listed[1.0] < listed[2.5]


def test_time_limit_stops_the_search_with_a_reason():
    trial = table2_trial(0.9, noise=0.02, seed=3)
    m = register(trial.source, trial.target, seed=0, time_limit=1e-3)
    assert not m
    assert "time_limit" in m.info["reason"]
    assert {"stopped": "time limit"}.items() <= m.info["trials"][-1].items()
    assert m.info["time_s"] < 30.0


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), "60"])
def test_time_limit_is_checked(bad):
    trial = table2_trial(0.5, seed=0)
    with pytest.raises(ValueError, match="time_limit"):
        register(trial.source, trial.target, time_limit=bad)


# -------------------------------------------------------------- pipelines
def test_pipeline_choice_follows_the_data():
    trial = table2_trial(0.75, seed=0)
    assert choose_pipeline(trial.source, trial.target)[0] == "exact"
    surface = _sphere(3000) * [1.0, 0.7, 0.5]
    kind, why = choose_pipeline(surface, surface + 0.1)
    assert kind == "scans" and "surfaces" in why
    assert surface_likeness(surface) < 0.01 < surface_likeness(trial.source)
    big = np.random.default_rng(0).uniform(size=(6000, 3))
    assert choose_pipeline(big, big)[0] == "scans"


def test_forced_exact_pipeline_names_the_scans_pipeline():
    x = np.random.default_rng(0).uniform(size=(3000, 3))
    with pytest.raises(InputError, match="pipeline='scans'"):
        register(x, x, pipeline="exact", memory_budget=1e6)
    with pytest.raises(InputError, match="pipeline"):
        register(x, x, pipeline="fast")
    surface = _sphere(3000) * [1.0, 0.7, 0.5]
    with pytest.raises(InputError, match="`noise`.*pipeline='exact'"):
        register(surface, surface, noise=0.01)
    with pytest.raises(InputError, match="scan_options"):
        register(x[:50], x[:50], pipeline="exact", scan_options={"n_points": 100})


def test_register_scans_is_the_scans_pipeline():
    rng = np.random.default_rng(2)
    surface = _sphere(4000, seed=2) * [1.0, 0.7, 0.5]
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    moved = surface[rng.permutation(4000)[:3000]] @ R.T + [0.2, 0.0, -0.1]
    a = register_scans(surface, moved, seed=0, n_points=300, max_triples=60)
    b = register(surface, moved, seed=0, pipeline="scans", max_triples=60, scan_options={"n_points": 300})
    np.testing.assert_array_equal(a.matrix, b.matrix)
    assert a.info["pipeline"] == "scans" and "ambiguous" in a.info
    # the ellipsoid matches itself after a half-turn: said so (a bumpy surface is not ambiguous:
    # test_scans.py::test_differently_sampled_surfaces_register)
    assert a.info["ambiguous"] and a.info["rival"]["angle_deg"] > 90.0


def test_plane_noise_measures_noise_along_the_normal():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-1, 1, (5000, 2))
    a = np.c_[xy, rng.normal(0, 0.01, 5000)]
    b = np.c_[xy, rng.normal(0, 0.01, 5000)]
    normals = np.tile([0.0, 0.0, 1.0], (5000, 1))
    pairs = np.c_[np.arange(5000), np.arange(5000)]
    assert plane_noise(a, b, normals, pairs) == pytest.approx(0.01, rel=0.1)
    assert np.isnan(plane_noise(a, b, normals, np.empty((0, 2), int)))


def _bunny_pair():
    try:
        return load_bunny_pair("bun000", "bun045")
    except DataNotFoundError:
        pytest.skip("shared bunny scans not available")


def test_pipeline_choice_on_a_real_scan_pair():
    target, source, _, _ = _bunny_pair()
    kind, why = choose_pipeline(source, target)
    assert kind == "scans", why


def test_range_scan_registered_to_a_coarse_mesh_of_the_object():
    """bun045 (40k range points) against the bunny's reconstruction decimated to 453 vertices (same
    world frame as bun000), re-posed by a rotation of any size: sets sampled 17 times apart.  Found
    within the decimated mesh's own limit (point-to-plane ICP started at the truth settles 1.2-1.5°
    and 0.3-0.4 mm off it)."""
    from scipy.spatial.transform import Rotation

    from gatv.datasets import find_data_dir
    from gatv.io import read_points

    _, source, R, t = _bunny_pair()
    mesh = find_data_dir() / "stanford_bunny_reconstruction" / "bun_zipper_res4.ply"
    if not mesh.exists():
        pytest.skip("shared bunny reconstruction not available")
    target = read_points(mesh)
    rng = np.random.default_rng(5)
    Q = Rotation.random(random_state=rng).as_matrix()
    q = rng.uniform(-0.03, 0.03, 3)
    moved = source @ Q.T + q
    m = register(moved, target, seed=0)
    assert m and m.info["pipeline"] == "scans", m.info.get("reason")
    R_true, t_true = R @ Q.T, t - R @ Q.T @ q
    c = moved.mean(axis=0)
    assert rotation_error_deg(m.rotation, R_true) < 2.5
    assert np.linalg.norm(m.rotation @ c + m.translation - (R_true @ c + t_true)) < 2e-3


@pytest.mark.slow
def test_real_scan_pair_registered_by_the_default_call():
    target, source, R, t = _bunny_pair()
    m = register(source, target)
    assert m.info["pipeline"] == "scans"
    assert rotation_error_deg(m.rotation, R) < 1.0
    assert np.linalg.norm(m.translation - t) < 2e-3
    assert 0 < m.info["noise"] < 1e-3  # the scanner's noise is well below a millimetre
    assert gate(1.0) == 3.5


@pytest.mark.slow
@pytest.mark.parametrize("share", [0.02, 0.04])
def test_a_noisy_real_scan_pair_is_projected_and_registered(share):
    """Gaussian noise of 2 and 4% of the bunny's RMS radius (1.1 and 2.2 mm, two to four times the
    scanner's spacing) on both scans: without the projection the polish's nearest pairs cross the
    noisy shell and the pose came out 0.6-3.5 degrees off; the noise was reported at a fifth of the truth."""
    target, source, R, t = _bunny_pair()
    rng = np.random.default_rng(11)
    sigma = share * np.sqrt(((target - target.mean(axis=0)) ** 2).sum(axis=1).mean())
    noisy_source = source + rng.normal(0.0, sigma, source.shape)
    m = register(noisy_source, target + rng.normal(0.0, sigma, target.shape))
    assert m.info["pipeline"] == "scans" and min(m.info["projected"]) > 0
    assert rotation_error_deg(m.rotation, R) < 1.0
    c = source.mean(axis=0)
    assert np.linalg.norm(m.rotation @ c + m.translation - (R @ c + t)) < 2e-3
    assert 0.85 * sigma < m.info["noise"] < 1.15 * sigma


@pytest.mark.slow  # at the default options; fast suite: the same ellipsoid and a bumpy surface at n_points=300
def test_symmetric_object_reports_the_ambiguity():
    """An ellipsoid matches itself after half-turns: info says ambiguous; a bumpy blob does not."""
    rng = np.random.default_rng(2)
    u = _sphere(4000, seed=2)
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    pick = rng.permutation(4000)[:3000]
    ellipsoid = u * [1.0, 0.7, 0.5]
    m = register(ellipsoid, ellipsoid[pick] @ R.T + [0.2, 0.0, -0.1], seed=0)
    assert m.info["pipeline"] == "scans" and m.info["ambiguous"]
    assert m.info["rival"]["angle_deg"] > 90.0
    radius = 1 + 0.3 * np.sin(3 * u[:, 0] + 1) * np.cos(2 * u[:, 1]) + 0.2 * u[:, 2] ** 3
    blob = u * radius[:, None]
    m = register(blob, blob[pick] @ R.T + [0.2, 0.0, -0.1], seed=0)
    assert not m.info["ambiguous"]
    assert rotation_error_deg(m.rotation, R) < 0.5


@pytest.mark.slow
def test_partial_overlap_with_clutter_on_real_scans():
    """Target cropped so that 40% of the source lies on it, 30% clutter in both: the right motion."""
    from scipy.spatial import cKDTree

    try:
        target, source, R, t = load_bunny_pair("bun000", "bun315")
    except DataNotFoundError:
        pytest.skip("shared bunny scans not available")
    rng = np.random.default_rng(1)
    on_target = source @ R.T + t
    near = cKDTree(target).query(on_target)[0] < 5e-3
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    h = on_target @ u
    order = np.argsort(h)
    cut = h[order[np.searchsorted(np.cumsum(near[order]) / len(source), 0.4)]]
    target = target[target @ u <= cut]
    assert np.mean(cKDTree(target).query(on_target)[0] < 5e-3) < 0.5
    clutter = [rng.uniform(p.min(0), p.max(0), (int(0.43 * len(p)), 3)) for p in (source, target)]
    m = register(np.vstack([source, clutter[0]]), np.vstack([target, clutter[1]]), seed=1)
    assert m.info["pipeline"] == "scans"
    assert rotation_error_deg(m.rotation, R) < 1.0
    assert np.linalg.norm((source.mean(0) @ m.rotation.T + m.translation) - (source.mean(0) @ R.T + t)) < 2e-3


@pytest.mark.parametrize("given", [None, "ACTIVE"])
def test_openmp_threads_wait_passively_unless_the_user_says(given):
    """gatv sets OMP_WAIT_POLICY=PASSIVE before numba starts its threads; a user's own value wins."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if given is not None:
        env["OMP_WAIT_POLICY"] = given
    out = subprocess.run([sys.executable, "-c", "import os, gatv; print(os.environ['OMP_WAIT_POLICY'])"],
                         env=env, capture_output=True, text=True, check=True).stdout.strip()
    assert out == (given or "PASSIVE")


def _thinned(points, rng, fall):
    """``points`` thinned to a density falling off ``fall`` times across them along a random direction (as a
    range scan's density falls with the distance)."""
    d = rng.normal(size=3)
    u = points @ (d / np.linalg.norm(d))
    u = (u - u.min()) / np.ptp(u)
    return points[rng.uniform(size=len(points)) < fall ** -u]


@pytest.mark.parametrize("pair", [("bun315", "bun045"), pytest.param(("bun045", "bun090"), marks=pytest.mark.slow),
                                  pytest.param(("bun000", "bun315"), marks=pytest.mark.slow)])
def test_range_scans_whose_density_falls_off_twentyfold_register(pair):
    """A bunny pair (target, source), each scan thinned to a density falling off 20 times across it:
    found within 1° and 2 mm.  The paper's threshold alone (relative to the densest token) kept mostly
    each scan's dense end: these three pairs at thinning seeds 0-7 were found in 8 of 24 cases, now in
    23 (`/work/bench/s37/falltest.py`; design notes, section 6, 'Uneven density')."""
    try:
        target, source, R, t = load_bunny_pair(*pair)
    except DataNotFoundError:
        pytest.skip("shared bunny scans not available")
    rng = np.random.default_rng(0)
    source, target = _thinned(source, rng, 20.0), _thinned(target, rng, 20.0)
    m = register(source, target, seed=0)
    assert m and m.info["pipeline"] == "scans", m.info.get("reason")
    c = source.mean(axis=0)
    assert rotation_error_deg(m.rotation, R) < 1.0
    assert np.linalg.norm(m.rotation @ c + m.translation - (R @ c + t)) < 2e-3
