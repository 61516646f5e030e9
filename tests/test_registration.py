"""Rigid registration without initialization: gatv.register."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gatv import RigidMotion, Rotor, register
from gatv.registration import rival_draws
from gatv.stages import gate, prepare
from gatv.datasets import (
    correspondence_stats,
    demo_mesh,
    rotation_error_deg,
    synthetic_trial,
    table1_trial,
    table2_trial,
)


def _scene(angle_deg, axis=(1.0, 2.0, -0.5), t=(3.0, -7.0, 2.0), n=40, n_out=40, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-5, 5, (n, 3))
    R = Rotor.from_axis_angle(axis, np.radians(angle_deg))
    y = (R >> x) + np.asarray(t)
    src = np.vstack([x, rng.uniform(-5, 5, (n_out, 3))])
    tgt = np.vstack([y, rng.uniform(y.min(0), y.max(0), (n_out, 3))])
    ps, pt = rng.permutation(len(src)), rng.permutation(len(tgt))
    true = np.stack([np.argsort(ps)[:n], np.argsort(pt)[:n]], axis=1)
    return src[ps], tgt[pt], R.as_matrix(), np.asarray(t), true


def _pairs_set(m):
    return set(map(tuple, m.correspondences.tolist()))


@pytest.mark.parametrize("angle", [0.0, 3.0, 90.0, 170.0, 179.5])
def test_recovers_known_motion_exactly(angle):
    src, tgt, R, t, true = _scene(angle)
    m = register(src, tgt)
    assert isinstance(m, RigidMotion) and m
    np.testing.assert_allclose(m.rotation, R, atol=1e-6)
    np.testing.assert_allclose(m.translation, t, atol=1e-6)
    assert _pairs_set(m) == set(map(tuple, true.tolist()))
    np.testing.assert_allclose(m.transform(src[true[:, 0]]), tgt[true[:, 1]], atol=1e-6)


def test_output_is_one_to_one():
    src, tgt, *_ = _scene(120.0, n_out=120)
    c = register(src, tgt).correspondences
    assert len(np.unique(c[:, 0])) == len(c) == len(np.unique(c[:, 1]))


def test_swapping_source_and_target_gives_inverse():
    src, tgt, R, t, _ = _scene(135.0, seed=3)
    fwd = register(src, tgt)
    back = register(tgt, src)
    inv = fwd.inverse()
    np.testing.assert_allclose(back.rotation, inv.rotation, atol=1e-6)
    np.testing.assert_allclose(back.translation, inv.translation, atol=1e-6)
    assert _pairs_set(back) == _pairs_set(inv)


@settings(max_examples=5, deadline=None)
@given(shift=st.tuples(*[st.floats(-1e3, 1e3, allow_nan=False)] * 3))
def test_shifting_both_sets_changes_only_translation(shift):
    src, tgt, R, t, _ = _scene(60.0, seed=4)
    base = register(src, tgt)
    v = np.asarray(shift)
    moved = register(src + v, tgt + v)
    np.testing.assert_allclose(moved.rotation, base.rotation, atol=1e-6)
    # x' = R x + t  =>  (x' + v) = R (x + v) + (t + v - R v)
    np.testing.assert_allclose(moved.translation, base.translation + v - base.rotation @ v, atol=1e-5)
    assert _pairs_set(moved) == _pairs_set(base)


def test_same_seed_same_result():
    src, tgt, *_ = _scene(75.0, n_out=150, seed=5)
    a, b = register(src, tgt, seed=7), register(src, tgt, seed=7)
    np.testing.assert_array_equal(a.rotation, b.rotation)
    np.testing.assert_array_equal(a.correspondences, b.correspondences)


def test_accepts_pyvista_meshes():
    pv = pytest.importorskip("pyvista")
    src, tgt, R, t, _ = _scene(45.0, seed=6)
    m = register(pv.PolyData(src), pv.PolyData(tgt))
    np.testing.assert_allclose(m.rotation, R, atol=1e-6)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_table2_trials_at_75_percent_outliers(seed):
    tr = table2_trial(0.75, seed=seed)
    m = register(tr.source, tr.target, seed=seed)
    precision, recall = correspondence_stats(m.correspondences, tr.true_pairs)
    assert precision == 1.0 and recall == 1.0
    assert rotation_error_deg(m.rotation, tr.rotation) < 1e-6


@pytest.mark.parametrize("seed", [0, 1])
def test_small_motion_mode_table1(seed):
    tr = table1_trial(0.83, seed=seed)
    m = register(tr.source, tr.target, max_angle=5.0, max_translation=1.5 * np.sqrt(3))
    precision, recall = correspondence_stats(m.correspondences, tr.true_pairs)
    assert precision == 1.0 and recall == 1.0
    assert m.info["mode"] == "bounded"


def test_noisy_data_recovered_within_noise():
    rng = np.random.default_rng(11)
    src, tgt, R, t, true = _scene(100.0, n=60, n_out=30, seed=11)
    tgt = tgt + rng.normal(scale=0.01, size=tgt.shape)
    m = register(src, tgt)
    assert rotation_error_deg(m.rotation, R) < 0.5
    precision, recall = correspondence_stats(m.correspondences, true)
    assert precision >= 0.95 and recall >= 0.9


def test_only_outliers_gives_falsy_result():
    rng = np.random.default_rng(2)
    m = register(rng.uniform(0, 10, (30, 3)), rng.uniform(0, 10, (30, 3)), max_triples=2000)
    assert not m
    assert "reason" in m.info


@pytest.mark.parametrize(
    ("source", "target", "match"),
    [
        (np.zeros((2, 3)), np.zeros((5, 3)), "at least 3"),
        (np.ones((5, 2)), np.ones((5, 3)), r"shape \(N, 3\)"),
        (np.full((5, 3), np.nan), np.ones((5, 3)), "NaN"),
        (np.ones((5, 3)), np.ones((5, 3)), "identical"),
        (np.outer(np.arange(6.0), [1, 2, 3]), np.random.default_rng(0).normal(size=(6, 3)), "collinear"),
    ],
)
def test_bad_input(source, target, match):
    with pytest.raises(ValueError, match=match):
        register(source, target)


def test_bad_options():
    src, tgt, *_ = _scene(10.0)
    with pytest.raises(ValueError, match="noise"):
        register(src, tgt, noise=-1.0)
    with pytest.raises(ValueError, match="max_angle"):
        register(src, tgt, max_angle=400.0)
    with pytest.raises(ValueError, match="max_translation"):
        register(src, tgt, max_translation=1.0)
    with pytest.raises(ValueError, match="budget"):
        register(src, tgt, memory_budget=10.0)


@pytest.mark.parametrize("seed", [1, 2])
def test_a_mesh_among_outliers_gives_its_motion_not_a_partial_self_match(seed):
    """The demo's scene (a real mesh, 50% outliers, exact): a wrong motion that lines up a patch of the
    surface with another passes the lenient density screen and the judge, and must still lose to the
    family-wise level behind them."""
    mesh = demo_mesh("ant")
    trial = synthetic_trial(0.5, inliers=mesh, max_translation=float(np.ptp(mesh, axis=0).max()), seed=seed)
    m = register(trial.source, trial.target)
    assert rotation_error_deg(m.rotation, trial.rotation) < 1e-6
    assert correspondence_stats(m.correspondences, trial.true_pairs) == (1.0, 1.0)


def _polished_at_the_final_level(seed, rotation_error=None):
    """A Table-2 trial (f = 0.9, 1% noise), the noisy schedule up to the level where register's
    searches find its motion, and the true motion (or one ``rotation_error`` off it) polished at that
    level's gate from three true pairs."""
    from gatv import stages

    trial = table2_trial(0.9, noise=0.01, seed=seed)
    P = stages.prepare(trial.source, trial.target)
    levels = stages.tolerance_levels(P, None, stages.NOISY_SCHEDULE)[:5]
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = trial.rotation, trial.translation
    if rotation_error is not None:
        matrix[:3, :3] = rotation_error @ trial.rotation
    fit = stages.refine(P, stages.Fit(matrix, trial.true_pairs[:3]), stages.gate(levels[-1]))
    return P, fit, levels


def test_final_level_keeps_noisy_true_motions():
    """``stages.beats_chance_at_some_level``: a true motion polished at a gate many noise deviations
    wide beats chance within a finer level's gate (its pairs stay tight, chance falls as the gate
    cubed).  Not every draw: the levels are 2.5 apart and the noise can fall between them (2 of
    seeds 0-4999 miss, 11 with the box's density; see docs/design-notes.md), so fixed seeds, all of
    which must pass."""
    from gatv import stages

    for seed in range(24):
        P, fit, levels = _polished_at_the_final_level(seed)
        assert stages.beats_chance_at_some_level(P, fit, levels, 5e7), seed


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 10**6), angle=st.floats(20.0, 180.0),
       axis=st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda a: np.linalg.norm(a) > 0.1))
def test_final_level_rejects_a_wrong_motion(seed, angle, axis):
    """A wrong motion of the same pose size, polished the same way as a true one, beats chance at none
    of the levels: its pairs scatter over the wide gate and thin out as the gate cubed."""
    from gatv import stages

    wrong = Rotor.from_axis_angle(axis, np.radians(angle)).as_matrix()
    P, polished, levels = _polished_at_the_final_level(seed, wrong)
    assert not stages.beats_chance_at_some_level(P, polished, levels, 5e7)


@settings(max_examples=5, deadline=None)
@given(seed=st.integers(0, 10**6))
def test_chance_pairs_follow_the_density_where_the_motion_lands(seed):
    """``Problem.landing_measure``: random motions that lay the source on the dense part of the target
    (1,000 points in a 10-cube among 1,000 spread over a box 27 times its volume) collect, within a
    gate, the chance pairs the local density predicts, ten times what the box's mean density does."""
    from gatv import stages

    rng = np.random.default_rng(seed)
    target = np.vstack([rng.uniform(0, 10, (1000, 3)), rng.uniform(-10, 20, (1000, 3))])
    source = rng.uniform(0, 10, (2000, 3))
    P = stages.prepare(source, target)
    g = 0.3 * P.spacing
    ball = 2000 * 2000 * 4.0 / 3.0 * np.pi * g**3
    observed, predicted = [], []
    for _ in range(30):
        M = np.eye(4)
        M[:3, :3] = Rotor.from_axis_angle(rng.normal(size=3), rng.uniform(0, np.pi)).as_matrix()
        M[:3, 3] = 5.0 - M[:3, :3] @ np.full(3, 5.0)  # about the dense cube's centre
        moved = source @ M[:3, :3].T + M[:3, 3]
        observed.append(np.count_nonzero(P.tree.query(moved, distance_upper_bound=g)[0] <= g))
        predicted.append(ball / P.landing_measure(P.landing_radii(M), g))
    assert abs(np.mean(predicted) / np.mean(observed) - 1.0) < 0.15
    assert ball / P.volume < 0.2 * np.mean(observed)


@pytest.mark.slow
def test_a_dense_noisy_cube_gives_its_motion_or_none():
    """2,000 points (a 10-cube of 1,000 inliers, 3% noise, among 1,000 outliers): a wrong motion that
    lays the dense cube onto itself collects chance pairs at the cube's density, above the box's mean,
    and once beat the box's level by one pair (120° off).  At the density where it lands it does not."""
    trial = table2_trial(0.5, n_inliers=1000, noise=0.03,
                         seed=np.random.SeedSequence([11, 0, sum(map(ord, "cube f.5 3% 2000pts"))]))
    m = register(trial.source, trial.target, seed=0, time_limit=40)
    if m:
        assert rotation_error_deg(m.rotation, trial.rotation) < 2.0
    else:
        assert "time limit" in m.info["reason"]


def test_only_trials_that_beat_chance_once_polished_reach_the_judge(monkeypatch):
    """Behind the density screen the search judges (tensor voting) only trials whose own polish beats the
    judge's level within some gate up to theirs; the noisy motion is still found (f = 0.5, 3% noise,
    100 inliers, where coarse gates let wrong trials through the screen)."""
    from gatv import stages

    trial = table2_trial(0.5, n_inliers=100, noise=0.03, seed=2)
    P = stages.prepare(trial.source, trial.target)
    judged = []
    real = stages.judge

    def judge(problem, matrix, tolerance, **kw):
        judged.append((matrix, tolerance))
        return real(problem, matrix, tolerance, **kw)

    monkeypatch.setattr(stages, "judge", judge)
    m = register(trial.source, trial.target, seed=2)
    assert m and rotation_error_deg(m.rotation, trial.rotation) < 2.0
    levels = stages.tolerance_levels(P, None, stages.NOISY_SCHEDULE)
    empty = np.empty((0, 2), np.int64)
    for matrix, tol in judged:
        upto = levels[: levels.index(tol) + 1]
        polished = stages.refine(P, stages.Fit(matrix, empty), stages.gate(tol))
        assert stages.beats_chance_at_some_level(P, polished, upto, stages.JUDGED_WRONG)


@pytest.mark.parametrize("chunk_s", [0.07, 0.15, 0.3, 0.45])
def test_time_limit_is_kept_by_the_chunks_it_starts(monkeypatch, chunk_s):
    """The search stops before a chunk that would end past ``time_limit``, not after: on a clock that only
    each chunk of trial motions advances, by ``chunk_s``, a search with no motion to find (two independent
    random sets) returns with the time limit's reason and its clock within the limit, having run every
    chunk that fitted."""
    import types

    from gatv import registration, stages
    from gatv.models import rigid as rigid_model

    rng = np.random.default_rng(5)
    src, tgt = rng.uniform(0, 10, (150, 3)), rng.uniform(0, 10, (150, 3))
    unlimited = register(src, tgt, noise=0.2)  # also compiles the kernels: no compile time on the fake clock
    assert not unlimited and "time limit" not in unlimited.info["reason"]
    clock = [0.0]
    fake = types.SimpleNamespace(perf_counter=lambda: clock[0])
    monkeypatch.setattr(stages, "time", fake)
    monkeypatch.setattr(registration, "time", fake)
    real = rigid_model.Rigid.trial_motions
    chunks = []

    def trial_motions(self, source, index, **options):
        chunks.append(clock[0])
        clock[0] += chunk_s
        return real(self, source, index, **options)

    monkeypatch.setattr(rigid_model.Rigid, "trial_motions", trial_motions)
    m = register(src, tgt, noise=0.2, time_limit=1.0)
    assert not m and "time limit" in m.info["reason"]
    assert clock[0] <= 1.0
    # chunk k starts at k chunk_s, and only when it would end by the limit: (k + 1) chunk_s < 1
    assert len(chunks) == int(np.ceil(1.0 / chunk_s)) - 1


def test_time_limit_leaves_out_numba_compilation(monkeypatch):
    """A first call compiles the kernels, a minute on a loaded machine: that time must not use up
    ``time_limit``.  A compilation longer than the limit (a numba compile event around a sleep, at the
    first trial chunk) still gives the exact motion, with a limit twice what the call takes here."""
    import time as _time

    from numba.core import event as numba_event

    from gatv.models import rigid as rigid_model

    src, tgt, R, t, _ = _scene(120.0)
    start = _time.perf_counter()
    assert register(src, tgt)  # compiled, and timed on this machine at its present load
    limit = 2.0 * (_time.perf_counter() - start) + 0.5
    real = rigid_model.Rigid.trial_motions
    calls = []

    def trial_motions(self, source, index, **options):
        if not calls:
            with numba_event.trigger_event("numba:compile"):
                _time.sleep(limit + 1.0)
        calls.append(1)
        return real(self, source, index, **options)

    monkeypatch.setattr(rigid_model.Rigid, "trial_motions", trial_motions)
    m = register(src, tgt, time_limit=limit)
    assert m, m.info.get("reason")
    assert np.allclose(m.rotation, R, atol=1e-8)


@pytest.mark.parametrize("angle", [40.0, 130.0])
def test_a_symmetric_set_gives_no_motion_and_says_why(angle):
    """A 5×5×5 grid maps onto itself by 90° turns: whichever motion the search finds, a distinct one
    explains every point as well.  The data do not tell them apart, so no motion is reported (a
    confident single motion would be a symmetry of the truth), and the result says why."""
    grid = np.stack(np.meshgrid(*[np.arange(5.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    R = Rotor.from_axis_angle((0.3, -0.5, 0.8), np.radians(angle)).as_matrix()
    m = register(grid, grid @ R.T + np.array([1.0, 2.0, -0.5]))
    assert not m and m.info["reason"].startswith("ambiguous") and m.info["ambiguous"]
    rival = m.info["rival"]
    assert rival["support"] == rival["best_support"] == 125
    assert rival["angle_deg"] > 45.0  # a symmetry of the grid, not a jitter of the found motion
    rivals = m.info["rivals"]  # (the points on the turn's axis stay, and are not the rival's)
    assert rivals["support"] == 125 and rivals["rival"] >= 0.9 * 125 and rivals["angle_deg"] > 45.0
    # asked not to check, the caller gets the motion (a symmetry of the truth) and the figures
    m = register(grid, grid @ R.T + np.array([1.0, 2.0, -0.5]), check_rivals=False)
    assert m.support == 125 and m.info["ambiguous"] and m.info["rivals"]["ambiguous"]


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 10**6), noise=st.sampled_from([0.0, 0.02]))
def test_a_generic_set_is_not_ambiguous(seed, noise):
    trial = table2_trial(0.5, noise=noise, seed=seed)
    m = register(trial.source, trial.target, seed=seed)
    assert m and m.info["ambiguous"] is False and "rival" not in m.info
    # its turned and shifted copies hold chance pairs only, as on evenly spread points
    rivals = m.info["rivals"]
    assert not rivals["ambiguous"] and rivals["rival"] < 0.5 * rivals["support"]


def _plane_and_blob(rng, n):
    """Half the points on a plane (thickness 0.05), half in a blob placed at random."""
    m = n // 2
    plane = np.column_stack([rng.uniform(-6, 6, (m, 2)), rng.normal(0, 0.05, m)])
    return np.vstack([plane, rng.normal(0, 1.5, (n - m, 3)) + rng.uniform(-4, 4, 3)])


def _lattice(rng, n):
    """Random sites of a 9 x 9 x 9 lattice of period 1.5, jittered by 0.05."""
    return rng.integers(-4, 5, (n, 3)).astype(float) * 1.5 + rng.normal(0, 0.05, (n, 3))


def _thin_cloud(rng, n):
    """A Gaussian cloud of random shape with principal deviations about 6, 2 and 0.4."""
    shape = rng.normal(0, 1, (3, 3)) * np.array([6.0, 2.0, 0.4])
    return rng.normal(0, 1, (n, 3)) @ shape.T


STRUCTURED = {"plane": _plane_and_blob, "lattice": _lattice, "thin": _thin_cloud}


@pytest.mark.parametrize("kind, seed", [("plane", 2004), ("lattice", 2002), ("thin", 2004),
                                        pytest.param("plane", 2002, marks=pytest.mark.slow),
                                        pytest.param("lattice", 2003, marks=pytest.mark.slow),
                                        pytest.param("lattice", 2004, marks=pytest.mark.slow)])
def test_unrelated_structured_sets_give_no_motion(kind, seed):
    """Two unrelated sets drawn alike: half on a plane, sites of a lattice, or thin dense clouds.

    Laid plane on plane, sites on sites or core on core they hold far more pairs than the Poisson
    levels expect of points spread over a box, and the search found such a lay (32-72 pairs before
    rival_draws).  Turned about its inliers' axes or shifted, and polished, the lay holds about as
    many, where evenly spread points give a few: no motion, and the reason says why.
    """
    rng = np.random.default_rng(seed)
    n1, n2 = rng.integers(120, 400, 2)
    a, b = STRUCTURED[kind](rng, n1), STRUCTURED[kind](rng, n2)
    m = register(a, b)
    assert not m, (m.support, m.info.get("rivals"))
    assert m.info["reason"].startswith("ambiguous") and m.info["ambiguous"] and not m.info["verdict"]["passed"]
    rivals = m.info["rivals"]
    assert rivals["ambiguous"] and rivals["rival"] > rivals["even"] + 3 * np.sqrt(max(rivals["even"], 1))


def test_rival_draws_tell_a_motion_from_a_lay_of_planes():
    """rival_draws directly: a true motion of evenly spread points is not ambiguous (its rivals hold what
    they hold on evenly spread points); two unrelated sets of a plane and a blob, laid plane on plane by
    the identity, are.  (Two samples of one plane alone are evenly spread over their thin box: there the
    Poisson levels hold, and the search's own level judges.)"""
    rng = np.random.default_rng(7)
    x = rng.uniform(-5, 5, (200, 3))
    R = Rotor.from_axis_angle((1.0, 2.0, -0.5), np.radians(50)).as_matrix()
    y = x @ R.T + [1.0, 0.0, 2.0] + rng.normal(0, 0.02, x.shape)
    P = prepare(x, y)
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, [1.0, 0.0, 2.0]
    pairs = np.column_stack([np.arange(200), np.arange(200)])
    g = gate(0.03)
    true = rival_draws(P, M, pairs, g, np.random.default_rng(0))
    assert not true.ambiguous and not true.structured and true.support >= 190 and true.rival < 20
    # two unrelated samples of a plane and a blob, laid plane on plane: any in-plane turn or shift of
    # the lay holds as many chance pairs, far more than on points spread evenly over the box
    P = prepare(_plane_and_blob(rng, 300), _plane_and_blob(rng, 300))
    s = P.source
    d, j = P.tree.query(s, distance_upper_bound=gate(0.1))
    near = np.flatnonzero(np.isfinite(d))
    lay = rival_draws(P, np.eye(4), np.column_stack([near, j[near]]), gate(0.1), np.random.default_rng(0))
    assert lay.structured and lay.ambiguous, lay


def test_a_motion_found_beside_is_not_a_rival():
    """Two true motions, the second the first turned 90 deg about its inliers' principal axis (one of
    rival_draws' turns): alone, the first's turn lands on the second and the data do not tell them
    apart; given the second as ``others``, the first stands (drop_ambiguous passes the other motions found)."""
    rng = np.random.default_rng(3)
    x1, x2 = rng.uniform(-5, 5, (100, 3)), rng.uniform(-5, 5, (100, 3))
    A = np.eye(4)
    A[:3, :3] = Rotor.from_axis_angle((1.0, 2.0, -0.5), np.radians(50)).as_matrix()
    A[:3, 3] = [1.0, 0.0, 2.0]
    c = x1.mean(axis=0)
    axis = np.linalg.eigh(np.cov(x1.T))[1][:, 0]
    Q = np.eye(4)
    Q[:3, :3] = Rotor.from_axis_angle(axis, np.radians(90)).as_matrix()
    Q[:3, 3] = c - Q[:3, :3] @ c
    B = A @ Q
    src = np.vstack([x1, x2])
    tgt = np.vstack([x1 @ A[:3, :3].T + A[:3, 3], x2 @ B[:3, :3].T + B[:3, 3]])
    P = prepare(src, tgt)
    pairs = np.column_stack([np.arange(100), np.arange(100)])
    alone = rival_draws(P, A, pairs, gate(0.01), np.random.default_rng(0))
    assert alone.ambiguous and alone.rival >= 95 and abs(alone.angle_deg - 90.0) < 1.0
    beside = rival_draws(P, A, pairs, gate(0.01), np.random.default_rng(0), others=[B])
    assert not beside.ambiguous and beside.rival < 10


# ----------------------------------------------------------- every model
@pytest.mark.parametrize("seed", [0, 1])
def test_a_single_affine2d_motion_among_outliers_is_registered(seed):
    """register takes every registered model: one 2D affine map, (N, 2) arrays, half outliers."""
    rng = np.random.default_rng(seed)
    A = np.array([[1.2, 0.3], [-0.2, 0.8]]) @ np.array([[np.cos(0.7), -np.sin(0.7)], [np.sin(0.7), np.cos(0.7)]])
    t = np.array([40.0, -25.0])
    x = rng.uniform(0, 200, (60, 2))
    src = np.vstack([x, rng.uniform(0, 200, (60, 2))])
    y = x @ A.T + t
    tgt = np.vstack([y, rng.uniform(y.min(0), y.max(0), (60, 2))])
    perm = rng.permutation(len(tgt))
    m = register(src, tgt[perm], model="affine2d", seed=seed)
    assert m and m.model == "affine2d"
    np.testing.assert_allclose(m.linear, A, atol=1e-8)
    np.testing.assert_allclose(m.translation, t, atol=1e-6)
    true = set(zip(range(60), np.argsort(perm)[:60].tolist()))
    assert true <= _pairs_set(m)
    assert m.info["verdict"]["passed"] and m.info["verdict"]["support"] == m.support


def test_the_small_motion_mode_is_refused_for_a_model_without_it():
    x = np.random.default_rng(0).uniform(0, 10, (20, 2))
    with pytest.raises(ValueError, match="small-motion"):
        register(x, x + 1.0, model="affine2d", max_angle=5.0)


# ------------------------------------------- a symmetric object's partial copy
def _nut_copy(seed):
    """150 vertices of PyVista's nut and a copy of the 70% of them on one side of a random plane, moved."""
    from gatv.datasets import random_rotation

    rng = np.random.default_rng(seed)
    mesh = demo_mesh("nut")
    model = mesh[np.sort(rng.choice(mesh.shape[0], 150, replace=False))]
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    h = (model - model.mean(0)) @ u
    R = random_rotation(rng, (0.0, 180.0))
    return model, model[h > np.quantile(h, 0.3)] @ R.T + rng.uniform(-50, 50, 3), R


@pytest.mark.parametrize("scene, seed", [
    (0, 0), (3, 1),
    pytest.param(8, 4, marks=pytest.mark.xfail(strict=True, reason=(
        "known defect: the search stops at the first motion that beats chance; on the nut, a "
        "symmetry maps 19 sampled points exactly onto others (180 deg off) and is returned, though "
        "the copy's own motion explains all 105"))),
    # A near-symmetry admitted at a coarse level (16 pairs, 180 deg off) from that level's first chunk,
    # before the exact level had had as much work: found since a level's motion waits for the finer ones.
    (9, 4),
])
def test_partial_copy_of_a_symmetric_object_is_found(scene, seed):
    model, copy, R = _nut_copy(scene)
    m = register(model, copy, seed=seed)
    assert m and rotation_error_deg(m.rotation, R) < 1.0
    assert m.support == copy.shape[0]


@settings(max_examples=5, deadline=None)
@given(seed=st.integers(0, 10**6))
def test_count_ceiling_keeps_the_true_pose_and_never_a_random_one(seed):
    """On a Table-2 trial at f = 0.5 and 1% noise the true pose beats the search's final level at some
    gate; a random pose (at least 20 degrees off) never does."""
    from gatv import stages
    from gatv.models.base import homogeneous
    from gatv.registration import count_ceiling

    trial = table2_trial(0.5, noise=0.01, seed=seed)
    P = stages.prepare(trial.source, trial.target)
    assert count_ceiling(P, homogeneous(trial.rotation, trial.translation))
    rng = np.random.default_rng(seed)
    R = Rotor.from_axis_angle(rng.normal(size=3), np.radians(rng.uniform(20, 180))).as_matrix() @ trial.rotation
    assert not count_ceiling(P, homogeneous(R, trial.translation + rng.normal(0, 2.0, 3)))


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 10**6), f=st.sampled_from([0.5, 0.75]), noise=st.sampled_from([0.01, 0.04]),
       tilt=st.floats(0.0, 4.0))
def test_count_alpha_is_the_level_at_which_count_ceiling_keeps_a_pose(seed, f, noise, tilt):
    """``count_alpha`` is the family-wise level at which ``count_ceiling`` keeps a pose: the truth and
    the truth turned by up to 4 degrees (about the inliers' centre) on Table-2 trials, some kept and some
    not at ``ALPHA``; a pose far off needs a level far above it."""
    from gatv import stages
    from gatv.models.base import homogeneous
    from gatv.registration import count_alpha, count_ceiling
    from gatv.stats import ALPHA

    trial = table2_trial(f, noise=noise, seed=seed)
    P = stages.prepare(trial.source, trial.target)
    rng = np.random.default_rng(seed)
    turn = Rotor.from_axis_angle(rng.normal(size=3), np.radians(tilt)).as_matrix()
    centre = trial.target[trial.true_pairs[:, 1]].mean(axis=0)
    matrix = homogeneous(turn, centre - turn @ centre) @ homogeneous(trial.rotation, trial.translation)
    a = count_alpha(P, matrix)
    assert a > 0.0
    assert count_ceiling(P, matrix) == (a <= ALPHA)
    far = Rotor.from_axis_angle(rng.normal(size=3), np.radians(rng.uniform(30, 180))).as_matrix()
    assert count_alpha(P, homogeneous(far @ trial.rotation, trial.translation + rng.normal(0, 2.0, 3))) > 1e3 * ALPHA


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 10**6), tilt=st.floats(0.0, 8.0))
def test_level_alphas_pass_exactly_where_level_counts_do(seed, tilt):
    """Gate by gate, a level's count reaches its level exactly when its ``level_alphas`` entry is within
    ``ALPHA`` (f = 0.5, 4%, the truth turned by up to 8 degrees over 1e5 tests: it fails the finer gates
    and passes a coarser one)."""
    from gatv import stages
    from gatv.models.base import homogeneous
    from gatv.stats import ALPHA

    trial = table2_trial(0.5, noise=0.04, seed=seed)
    P = stages.prepare(trial.source, trial.target)
    rng = np.random.default_rng(seed)
    turn = Rotor.from_axis_angle(rng.normal(size=3), np.radians(tilt)).as_matrix()
    levels = stages.tolerance_levels(P, None, P.model.search_policy().schedule)
    fit = stages.refine(P, stages.Fit(homogeneous(turn @ trial.rotation, trial.translation),
                                      np.empty((0, 2), np.int64)), stages.gate(levels[-1]))
    counts = stages.level_counts(P, fit, levels, 1e5)
    alphas = stages.level_alphas(P, fit, levels, 1e5)
    assert len(alphas) == len(levels) >= len(counts)
    assert [c.support >= c.level for c in counts] == [a <= ALPHA for a in alphas[:len(counts)]]


def test_count_alpha_names_a_model_without_its_hook():
    import dataclasses

    from gatv import stages
    from gatv.errors import InputError
    from gatv.registration import count_alpha

    class WithoutHook:
        """The rigid model without ``chance_alpha``."""

        def __init__(self, model):
            self._model = model

        def __getattr__(self, name):
            if name == "chance_alpha":
                raise AttributeError(name)
            return getattr(self._model, name)

    trial = table2_trial(0.5, noise=0.01, seed=0)
    P = stages.prepare(trial.source, trial.target)
    with pytest.raises(InputError, match="chance_alpha"):
        count_alpha(dataclasses.replace(P, model=WithoutHook(P.model)), np.eye(4))


@settings(max_examples=3, deadline=None)
@given(seed=st.integers(0, 10**6), low=st.floats(0.005, 0.05), factor=st.floats(1.5, 8.0))
def test_registers_trial_counts_stay_bounded_as_the_noise_grows(seed, low, factor):
    """``register`` on two random sets at a noise and at a larger one: in ``info["trials"]`` the samples
    drawn never exceed the RANSAC cap of the smallest motion the level's density test accepts, the
    larger noise's cap is no larger, the work stays within the bound plus one chunk, and the call
    says why it found nothing."""
    from gatv import stages
    from gatv.stats import samples_needed

    rng = np.random.default_rng(seed)
    source, target = rng.uniform(-5, 5, (150, 3)), rng.uniform(-5, 5, (150, 3))
    spacing = stages.prepare(source, target).spacing
    max_work = 1e6
    caps = []
    for noise in (low * spacing, low * factor * spacing):
        m = register(source, target, noise=noise, max_work=max_work, seed=seed)
        assert not m and m.info["reason"]
        assert not m.info["verdict"]["passed"]
        records = [r for r in m.info["trials"] if "tolerance" in r]
        assert [r["tolerance"] for r in records] == [noise]
        rec = records[0]
        cap = samples_needed(min(1.0, rec["threshold"] / 150) * stages.listed_share(stages.LISTING, 1), 0.999, 3)
        assert rec["triples"] <= cap
        assert rec["work"] <= max_work + 4096 * rec["work"] / max(rec["triples"], 1)
        assert any(r.get("stopped") == "work bound" for r in m.info["trials"]) or rec["triples"] == cap
        caps.append(cap)
    assert caps[1] <= caps[0]


@settings(max_examples=4, deadline=None)
@given(seed=st.integers(0, 10**6), noise=st.floats(0.002, 0.2))
def test_trials_drawn_stay_bounded_as_the_noise_grows(seed, noise):
    """On two random sets (nothing to find) each tolerance draws at most its RANSAC cap, which does not
    grow with the tolerance, and the whole search stops at its work bound (one chunk over at most)."""
    from gatv import stages
    from gatv.stats import samples_needed

    rng = np.random.default_rng(seed)
    P = stages.prepare(rng.uniform(-5, 5, (200, 3)), rng.uniform(-5, 5, (200, 3)))
    policy = P.model.search_policy()
    # the noise as a share of the spacing, and three tolerances up to it
    levels = sorted({noise * P.spacing * f for f in (0.25, 0.5, 1.0)})
    tried: list = []
    max_work = 1.5e6
    found = stages.search(P, levels, budget=10**6, rng=rng, max_matches=policy.max_matches,
                          trial_options=policy.trial_options, max_work=max_work, judged_wrong=None,
                          tried=tried)
    assert not found
    records = [r for r in tried if "tolerance" in r]
    caps = [min(10**6, samples_needed(min(1.0, r["threshold"] / 200) * stages.listed_share(stages.LISTING, 1),
                                      0.999, 3)) for r in records]
    assert all(r["triples"] <= c for r, c in zip(records, caps))
    assert all(a >= b for a, b in zip(caps, caps[1:]))  # a coarser tolerance never draws more
    work = sum(r["work"] for r in records)
    chunk = max(r["work"] / max(r["triples"], 1) for r in records) * 4096
    assert work <= max_work + chunk
    assert any(r.get("stopped") == "work bound" for r in tried) or all(
        r["triples"] == c for r, c in zip(records, caps))


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), share=st.floats(0.0, 1.0))
def test_a_trial_judged_alike_holds_every_pair_the_judged_fit_kept_within_its_reach(seed, share):
    """``judged_alike``: a trial that moves every source point within 2σ − g of a judged fit's position has
    that fit's kept pairs among its own candidates (within the judge's reach); a distinct motion is not
    alike, and a fit is alike to itself."""
    from gatv import stages
    from gatv.models.base import homogeneous

    src, tgt, R, t, _ = _scene(30.0, n=60, n_out=60, seed=seed % 1000)
    P = stages.prepare(src, tgt)
    tol = 0.01
    j = stages.judge(P, homogeneous(R, t), tol)
    assert j is not None and j.fit.support >= 50
    assert stages.judged_alike(j, P, j.fit.matrix, tol)
    reach = 2.0 * j.sigma - stages.gate(tol)
    # A trial off the fit by a small rotation about the source's centroid, scaled to ``share`` of the reach.
    c = P.source.mean(axis=0)
    A, b = j.fit.matrix[:3, :3], j.fit.matrix[:3, 3]
    spin = Rotor.from_axis_angle((0.3, -1.0, 0.4), 1.0).as_matrix()
    off = np.linalg.norm((P.source - c) @ (spin - np.eye(3)).T, axis=1).max()
    spin = Rotor.from_axis_angle((0.3, -1.0, 0.4), share * reach / off).as_matrix()  # small angle: ≈ share·reach
    trial = homogeneous(A @ spin, A @ (c - spin @ c) + b)
    moved = P.source @ trial[:3, :3].T + trial[:3, 3]
    gap = np.linalg.norm(moved - (P.source @ A.T + b), axis=1).max()
    assert stages.judged_alike(j, P, trial, tol) == (gap <= reach)
    if gap <= reach:
        near = stages.candidate_tokens(P, trial, 2.0 * j.sigma, P.target.shape[0])
        assert set(map(tuple, j.fit.correspondences.tolist())) <= set(map(tuple, near.pairs.tolist()))
    # Another motion (90° away) is not the same hypothesis.
    turn = Rotor.from_axis_angle((1.0, 0.0, 0.0), np.pi / 2).as_matrix()
    assert not stages.judged_alike(j, P, homogeneous(A @ turn, b), tol)
