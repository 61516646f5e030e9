"""Non-rigid registration (section 5.1): gatv.nonrigid."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gatv import register as rigid_register
from gatv.datasets import correspondence_stats
from gatv.nonrigid import NonRigidMotion, register
from gatv.nonrigid import deformations as deform


def _pairs(m):
    return set(map(tuple, np.asarray(m.correspondences).tolist()))


@pytest.fixture(scope="module")
def twisted():
    x = deform.sample_plane(150, 10.0, seed=3)
    trial = deform.nonrigid_trial(x, deform.twist(x, 60.0), 0.25, seed=4)
    return trial, register(trial.source, trial.target)


# ------------------------------------------------------------------ registration
def test_twisted_plane_correspondences(twisted):
    trial, m = twisted
    assert isinstance(m, NonRigidMotion) and m
    precision, recall = correspondence_stats(m.correspondences, trial.true_pairs)
    assert precision >= 0.95
    assert recall >= 0.8
    c = m.correspondences
    assert len(np.unique(c[:, 0])) == len(c) == len(np.unique(c[:, 1]))
    assert trial.warp_error(m.warp) < 0.1


def test_diagnostics_carry_the_local_eq41_checks(twisted):
    _, m = twisted
    d = m.diagnostics
    assert d.structure in ("surface", "curve")
    k = d.pairs.shape[0]
    assert d.tokens.shape == (k, 3) and d.normals.shape == (k, 3) and d.saliency.shape == (k,)
    assert d.verification.shape == (k, 2) and d.verified.shape == (k,)
    partners = d.verification[d.verified, 1]
    assert np.all(partners >= 0) and np.all(partners != np.flatnonzero(d.verified))
    assert m.rotations.shape == (m.support, 3, 3) and m.rotors.shape == (m.support, 4)
    np.testing.assert_allclose(np.einsum("kij,kil->kjl", m.rotations, m.rotations),
                               np.broadcast_to(np.eye(3), m.rotations.shape), atol=1e-9)


def test_rigid_motion_agrees_with_rigid_register():
    rng = np.random.default_rng(0)
    x = rng.uniform(-5, 5, (60, 3))
    y = deform.rigid(x, 20.0, axis=(1, 2, -1), translation=(1.0, -0.5, 0.3))
    trial = deform.nonrigid_trial(x, y, 0.2, seed=1)
    rigid = rigid_register(trial.source, trial.target)
    m = register(trial.source, trial.target)
    assert _pairs(m) == _pairs(rigid)
    i = m.correspondences[:, 0]
    np.testing.assert_allclose(m.warp(trial.source[i]), rigid.transform(trial.source[i]), atol=1e-6)
    np.testing.assert_allclose(m.rotations, np.broadcast_to(rigid.rotation, m.rotations.shape), atol=1e-6)
    # between matches the warp of a rigid motion stays rigid
    inside = rng.uniform(-3, 3, (20, 3))
    np.testing.assert_allclose(m.warp(inside), rigid.transform(inside), atol=1e-6)


def test_warp_exact_at_matches_and_smooth_between():
    x = deform.sample_plane(100, 10.0, seed=5)
    y = deform.bend(x, 60.0)
    m = register(x, y[::-1], smoothing=0.0)
    assert m.smoothing == 0.0 and m.support >= 90
    c = m.correspondences
    np.testing.assert_allclose(m.warp(x[c[:, 0]]), y[::-1][c[:, 1]], atol=1e-8)
    assert m.transform is not None and np.array_equal(m.transform(x[:5]), m.warp(x[:5]))
    # a fine line across the plane: the warp follows the true bend, without jumps
    t = np.linspace(-4.5, 4.5, 200)
    line = np.column_stack([t, 0.3 * t, np.zeros_like(t)])
    w = m.warp(line)
    assert np.abs(w - deform.bend(line, 60.0, center=np.zeros(3), length=np.ptp(x[:, 0]))).max() < 0.1
    steps = np.linalg.norm(np.diff(w, axis=0), axis=1)
    assert steps.max() < 1.5 * np.linalg.norm(line[1] - line[0])


def test_bend_gives_a_curve_in_the_joint_space():
    """The paper's remark: some non-rigid motions make 3D curves, not surfaces."""
    x = deform.sample_plane(120, 10.0, seed=6)
    trial = deform.nonrigid_trial(x, deform.bend(x, 90.0), 0.2, seed=7)
    m = register(trial.source, trial.target)
    assert m.diagnostics.structure == "curve"
    precision, recall = correspondence_stats(m.correspondences, trial.true_pairs)
    assert precision >= 0.95 and recall >= 0.8


def test_hinge_gives_both_rigid_parts():
    """Piecewise rigid: the two parts are separate surfaces in the joint space;
    the coarse-to-fine hypothesis matches both, not just the larger one."""
    x = deform.sample_plane(200, 10.0, seed=9)
    trial = deform.nonrigid_trial(x, deform.piecewise_rigid(x, 30.0), 0.25, seed=10)
    m = register(trial.source, trial.target)
    precision, recall = correspondence_stats(m.correspondences, trial.true_pairs)
    assert precision >= 0.95 and recall >= 0.8
    # matches on each side of the hinge (x < 0 stays, x > 0 turns)
    side = trial.source[m.correspondences[:, 0], 0] > 0
    moving_true = np.sum(x[:, 0] > 0)
    assert side.sum() >= 0.7 * moving_true and (~side).sum() >= 0.7 * (len(x) - moving_true)
    # the local rigid motions of the moving part turn by the hinge angle
    angles = m.local_angles_deg
    far = np.abs(trial.source[m.correspondences[:, 0], 0]) > 2.0
    np.testing.assert_allclose(np.median(angles[far & side]), 30.0, atol=1.0)
    np.testing.assert_allclose(np.median(angles[far & ~side]), 0.0, atol=1.0)


def test_bent_bar_among_half_outliers_is_found_by_local_windows():
    """A bar bent through 60 degrees and turned has no dominant rigid motion: a local window
    registered rigidly and grown ring by ring follows the bend over the whole bar (section 5.1's
    local mode).  The rigid start's coarse-to-fine growth may follow it too, from some first
    motions of the search and not others; the local windows must reach the whole bar either way."""
    bar = deform.sample_plane(200, 10.0, seed=0) * [1.0, 0.3, 1.0]
    y = deform.rigid(deform.bend(bar, 60.0), 20.0, translation=(1.0, 2.0, 1.0))
    trial = deform.nonrigid_trial(bar, y, 0.5, seed=10)
    m = register(trial.source, trial.target)
    scores = m.info["hypotheses"]
    assert scores["local"]["support"] >= 0.98 * len(bar)
    assert m.info["hypothesis"] in ("local", "rigid")
    assert scores[m.info["hypothesis"]]["support"] == max(h["support"] for h in scores.values())
    precision, recall = correspondence_stats(m.correspondences, trial.true_pairs)
    assert precision >= 0.98 and recall >= 0.95
    assert trial.warp_error(m.warp) < 0.05
    # windows registered before the one that counted did not count; the last one did
    windows = m.info["local_windows"]
    assert windows[-1]["support"] >= 0.1 * len(bar) and windows[-1]["chance"] <= 0.25 * windows[-1]["support"]


@pytest.mark.slow
def test_bent_bar_without_the_fallbacks_runs_neither_the_rigid_start_nor_the_windows():
    """The bent bar's second half (fast suite: the same check on the elastic warp, prealign=False)."""
    bar = deform.sample_plane(200, 10.0, seed=0) * [1.0, 0.3, 1.0]
    y = deform.rigid(deform.bend(bar, 60.0), 20.0, translation=(1.0, 2.0, 1.0))
    trial = deform.nonrigid_trial(bar, y, 0.5, seed=10)
    # without the fallbacks (prealign=False) neither the rigid start nor the windows run
    off = register(trial.source, trial.target, prealign=False)
    assert "local_windows" not in off.info and "rigid" not in off.info.get("hypotheses", {})


def test_large_rigid_motion_on_top_of_a_twist_needs_the_rigid_hypothesis():
    """Voting alone fails (the twisted surface is as sparse as the false tokens);
    the coarse stage started from gatv.register's dominant motion recovers it,
    by default ("auto") because no other hypothesis beats chance."""
    x = deform.sample_plane(200, 10.0, seed=3)
    y = deform.rigid(deform.twist(x, 60.0), 70.0, axis=(1, 1, 0), translation=(3, -2, 1))
    trial = deform.nonrigid_trial(x, y, 0.25, seed=4)
    m = register(trial.source, trial.target)
    # the bounded rigid search (300 triples) finds a motion beating chance, sometimes only a small
    # rigid patch (6-24 pairs over seeds 0-3), which coarse-to-fine grows to the dominant motion; the
    # local windows (registered rigidly and grown) may match a few more of the twisted ends and win
    hyp = m.info["hypotheses"]
    assert m.info["prealign"]["support"] >= 3
    assert hyp["rigid"]["support"] >= 0.8 * len(x)
    assert hyp["voting"]["support"] < 0.1 * len(x)
    assert m.info["hypothesis"] in ("rigid", "local")
    precision, recall = correspondence_stats(m.correspondences, trial.true_pairs)
    assert precision >= 0.95 and recall >= 0.9
    assert trial.warp_error(m.warp) < 0.05
    forced = register(trial.source, trial.target, prealign=True)
    assert correspondence_stats(forced.correspondences, trial.true_pairs)[0] >= 0.95


@pytest.mark.slow
def test_large_rigid_motion_on_top_of_a_twist_without_the_rigid_start_is_annealed():
    """The case above with prealign=False (fast suite: the annealed hypothesis on the elastic warp)."""
    x = deform.sample_plane(200, 10.0, seed=3)
    y = deform.rigid(deform.twist(x, 60.0), 70.0, axis=(1, 1, 0), translation=(3, -2, 1))
    trial = deform.nonrigid_trial(x, y, 0.25, seed=4)
    # without the rigid start the annealed soft matching finds part of it, precisely
    off = register(trial.source, trial.target, prealign=False)
    assert off.info["hypothesis"] == "anneal"
    precision, recall = correspondence_stats(off.correspondences, trial.true_pairs)
    assert precision >= 0.95 and recall >= 0.5


def test_near_identity_deformation_with_sparse_outliers():
    """Face-like: a displacement of about the point spacing (no rigid part)
    on a curved surface; the tokens are one dense blob in the joint space and
    the coarse-to-fine hypothesis wins; every reported pair is verified."""
    rng = np.random.default_rng(11)
    u, v = rng.uniform(-1, 1, (2, 300))
    x = np.column_stack([u, v, 0.4 * (u**2 + v**2)]) * 50.0
    from scipy.spatial import cKDTree

    sp = float(np.median(cKDTree(x).query(x, k=2)[0][:, 1]))
    y = x + 1.0 * sp * np.column_stack([np.sin(u * 2), np.cos(v * 3), np.sin(u * v * 4)])
    trial = deform.nonrigid_trial(x, y, 0.5, seed=12)
    m = register(trial.source, trial.target)
    assert m.info["hypothesis"] == "coarse"
    precision, recall = correspondence_stats(m.correspondences, trial.true_pairs)
    assert precision >= 0.95 and recall >= 0.7


def test_support_below_chance_reports_nothing():
    """Unrelated clouds: no hypothesis beats chance, so no matches are reported."""
    rng = np.random.default_rng(5)
    m = register(rng.uniform(size=(80, 3)), rng.uniform(size=(80, 3)), prealign=False)
    assert not m and "chance" in m.info["reason"]
    assert set(m.info["hypotheses"]) <= {"voting", "coarse", "anneal"}


def test_large_elastic_warp_with_outliers_is_found_by_the_annealed_hypothesis():
    """An elastic warp of about 4 spacings with 50% outliers in the plane's box (the
    source outliers lie among the inliers): neither the voted tokens nor the
    coarse-to-fine matching from no motion beat chance; the annealed soft
    matching does, and its verified matches are precise."""
    x = deform.sample_plane(300, 10.0, seed=0)
    trial = deform.nonrigid_trial(x, deform.elastic(x, 1.5, seed=100), 0.5, seed=200)
    m = register(trial.source, trial.target, prealign=False)
    assert m.info["hypothesis"] == "anneal"
    assert m.info["hypotheses"]["coarse"]["support"] < 0.1 * len(trial.source)
    # without the fallbacks (prealign=False) neither the rigid start nor the windows run
    assert "local_windows" not in m.info and "rigid" not in m.info["hypotheses"]
    precision, recall = correspondence_stats(m.correspondences, trial.true_pairs)
    assert precision >= 0.95 and recall >= 0.6
    assert trial.warp_error(m.warp) < 0.1


@pytest.mark.parametrize("value", ["yes", 1.5, None])
def test_bad_prealign_names_the_argument(value):
    x = deform.sample_plane(20, seed=0)
    with pytest.raises(ValueError, match="`prealign`"):
        register(x, x + 0.1, prealign=value)


def test_same_seed_same_result(twisted):
    trial, m = twisted
    again = register(trial.source, trial.target, seed=0)
    assert np.array_equal(again.correspondences, m.correspondences)
    assert again.smoothing == m.smoothing
    np.testing.assert_array_equal(again.warp(trial.source), m.warp(trial.source))


def test_progress_reports_each_stage_and_to_dict_names_the_model(twisted):
    trial, m = twisted
    calls = []
    again = register(trial.source, trial.target, progress=lambda f, msg: calls.append((f, msg)))
    assert np.array_equal(again.correspondences, m.correspondences)
    fractions = [f for f, _ in calls]
    assert fractions == sorted(fractions) and fractions[0] == 0.0 and fractions[-1] == 1.0
    assert len(calls) >= 6 and all(isinstance(msg, str) and msg for _, msg in calls)
    record = m.to_dict()
    assert record["model"] == "nonrigid" and record["support"] == m.support


def test_generator_seed_is_reproducible(twisted):
    trial, _ = twisted
    a = register(trial.source, trial.target, seed=np.random.default_rng(7))
    b = register(trial.source, trial.target, seed=np.random.default_rng(7))
    assert np.array_equal(a.correspondences, b.correspondences)
    assert correspondence_stats(a.correspondences, trial.true_pairs)[0] >= 0.95


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize(
    ("source", "kwargs", "match"),
    [
        (np.zeros((10, 2)), {}, r"`source` to have shape \(N, 3\)"),
        (np.full((10, 3), np.nan), {}, "`source` contains"),
        (np.ones((3, 3)), {}, "at least 4"),
        (np.zeros((10, 3)), {}, "identical"),
        (np.outer(np.arange(10.0), [1.0, 2.0, 3.0]), {}, "collinear"),
        (None, {"strain": -1.0}, "`strain`"),
        (None, {"structure": "plane"}, "`structure`"),
        (None, {"max_candidates": 0}, "`max_candidates`"),
        (None, {"max_displacement": 0.0}, "`max_displacement`"),
        (None, {"noise": float("inf")}, "`noise`"),
        (None, {"seed": -1}, "`seed`"),
        (None, {"prealign": "always"}, "`prealign`"),
        (None, {"memory_budget": 1.0}, "memory budget"),
        (None, {"progress": "yes"}, "`progress`"),
        (None, {"seed": 1.5}, "`seed`"),
    ],
)
def test_bad_input_raises_clear_value_errors(source, kwargs, match):
    good = deform.sample_plane(20, seed=0)
    with pytest.raises(ValueError, match=match):
        register(good if source is None else source, good + 0.1, **kwargs)


def test_no_structure_is_a_falsy_result_not_an_error():
    rng = np.random.default_rng(2)
    m = register(rng.uniform(size=(30, 3)), rng.uniform(size=(30, 3)), max_displacement=1e-6)
    assert not m and "reason" in m.info
    assert m.warp(np.ones((2, 3))).shape == (2, 3)


# ------------------------------------------------------------------ generators
def test_generators_are_deterministic():
    x = deform.sample_plane(64, seed=1)
    np.testing.assert_array_equal(x, deform.sample_plane(64, seed=1))
    assert not np.array_equal(x, deform.sample_plane(64, seed=2))
    np.testing.assert_array_equal(deform.elastic(x, 1.0, seed=3), deform.elastic(x, 1.0, seed=3))
    a = deform.nonrigid_trial(x, deform.twist(x, 30.0), 0.5, seed=4)
    b = deform.nonrigid_trial(x, deform.twist(x, 30.0), 0.5, seed=4)
    np.testing.assert_array_equal(a.source, b.source)
    np.testing.assert_array_equal(a.target, b.target)
    np.testing.assert_array_equal(a.true_pairs, b.true_pairs)
    assert a.source.shape == (128, 3)
    from scipy.spatial import cKDTree

    _, rows = cKDTree(x).query(a.source[a.true_pairs[:, 0]])
    np.testing.assert_array_equal(a.target[a.true_pairs[:, 1]], deform.twist(x, 30.0)[rows])


def test_twist_preserves_local_distances():
    x = deform.sample_plane(400, 10.0, seed=0)
    angle = 30.0
    y = deform.twist(x, angle, center=np.zeros(3), length=10.0)
    # each cross-section turns rigidly: distances to the axis are kept
    np.testing.assert_allclose(np.hypot(y[:, 1], y[:, 2]), np.hypot(x[:, 1], x[:, 2]), atol=1e-12)
    # neighbour distances change at most by the strain sqrt(1 + (alpha r)^2) - 1
    from scipy.spatial import cKDTree

    d, nb = cKDTree(x).query(x, k=7)
    d_new = np.linalg.norm(y[nb[:, 1:]] - y[:, None, :], axis=2)
    change = np.abs(d_new / d[:, 1:] - 1.0)
    alpha = np.radians(angle) / 10.0
    bound = np.sqrt(1.0 + (alpha * 5.0) ** 2) - 1.0
    assert change.max() <= bound + 1e-9
    assert np.median(change) < 0.01


def test_bend_is_an_isometry_and_piecewise_rigid_moves_two_rigid_parts():
    x = deform.sample_plane(200, 10.0, seed=2)
    y = deform.bend(x, 120.0)
    from scipy.spatial import cKDTree

    d, nb = cKDTree(x).query(x, k=2)
    assert np.abs(np.linalg.norm(y[nb[:, 1]] - y, axis=1) / d[:, 1] - 1).max() < 0.01
    z = deform.piecewise_rigid(x, 25.0, translation=(0.0, 0.0, 1.0))
    left = x[:, 0] < 0
    np.testing.assert_array_equal(z[left], x[left])
    right = ~left
    dx = np.linalg.norm(x[right][:, None] - x[right][None], axis=2)
    dz = np.linalg.norm(z[right][:, None] - z[right][None], axis=2)
    np.testing.assert_allclose(dz, dx, atol=1e-9)


def test_generators_reject_bad_input():
    with pytest.raises(ValueError, match="`angle`"):
        deform.twist(np.ones((4, 3)), "ninety")
    with pytest.raises(ValueError, match="`axis`"):
        deform.twist(np.ones((4, 3)), 10.0, axis=(0, 0, 0))
    with pytest.raises(ValueError, match="`amplitude`"):
        deform.elastic(np.ones((4, 3)), -1.0)
    with pytest.raises(ValueError, match="same shape"):
        deform.nonrigid_trial(np.ones((4, 3)), np.ones((5, 3)))


# ------------------------------------------------------------------ command line
def test_cli_run_writes_json(tmp_path, capsys, parse_nonrigid):
    from gatv.cli.nonrigid import run

    x = deform.sample_plane(60, 10.0, seed=8)
    np.save(tmp_path / "s.npy", x)
    np.save(tmp_path / "t.npy", deform.twist(x, 45.0)[::-1])
    out = tmp_path / "r.json"
    args = parse_nonrigid(["nonrigid", str(tmp_path / "s.npy"), str(tmp_path / "t.npy"), "--out", str(out)])
    assert run(args) == 0
    record = json.loads(out.read_text())
    assert record["success"] and record["support"] >= 55
    assert len(record["correspondences"]) == record["support"]
    assert "correspondences:" in capsys.readouterr().out
    assert record["options"]["prealign"] == "auto" and record["info"]["hypothesis"] in ("voting", "coarse")
    args = parse_nonrigid(["nonrigid", str(tmp_path / "s.npy"), str(tmp_path / "t.npy"), "--prealign", "never", "-q"])
    assert run(args) == 0


def test_cli_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, parse_nonrigid):
    from gatv.cli.nonrigid import run

    np.save(tmp_path / "s.npy", np.zeros((10, 2)))
    np.save(tmp_path / "t.npy", deform.sample_plane(10, seed=0))
    out = tmp_path / "r.json"
    args = parse_nonrigid(["nonrigid", str(tmp_path / "s.npy"), str(tmp_path / "t.npy"), "--out", str(out)])
    assert run(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("gatv: error:")
    assert not out.exists()
    args = parse_nonrigid(["nonrigid", str(tmp_path / "missing.npy"), str(tmp_path / "t.npy")])
    assert run(args) == 2
