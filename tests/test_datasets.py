from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gatv.datasets import (
    DataNotFoundError,
    correspondence_stats,
    demo_mesh,
    load_bunny_pair,
    outlier_count,
    paper_success,
    rotation_error_deg,
    synthetic_trial,
    table1_trial,
    table2_trial,
    translation_error,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
FRACTIONS = [0.0, 0.5, 0.66, 0.75, 0.83, 0.9, 0.95]


@pytest.mark.parametrize("make", [table1_trial, table2_trial])
@pytest.mark.parametrize("f", FRACTIONS)
def test_true_pairs_satisfy_motion(make, f):
    trial = make(f, seed=7)
    n_out = int(round(50 * f / (1 - f)))
    assert trial.source.shape == trial.target.shape == (50 + n_out, 3)
    assert trial.n_outliers == n_out == outlier_count(f, 50)
    assert trial.true_pairs.shape == (50, 2)
    s = trial.source[trial.true_pairs[:, 0]]
    t = trial.target[trial.true_pairs[:, 1]]
    np.testing.assert_allclose(s @ trial.rotation.T + trial.translation, t, rtol=0, atol=1e-12)
    np.testing.assert_allclose(trial.rotation @ trial.rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(trial.rotation) == pytest.approx(1.0)
    # pairs are distinct rows on both sides
    assert len(np.unique(trial.true_pairs[:, 0])) == len(np.unique(trial.true_pairs[:, 1])) == 50


def test_outlier_counts_paper_values():
    assert [outlier_count(f, 50) for f in (0.75, 0.83, 0.85, 0.88, 0.9, 0.93, 0.95)] == [
        150, 244, 283, 367, 450, 664, 950,
    ]


def test_outliers_inside_each_bounding_box():
    trial = table2_trial(0.9, seed=3)
    inl_s = np.zeros(len(trial.source), bool)
    inl_s[trial.true_pairs[:, 0]] = True
    inl_t = np.zeros(len(trial.target), bool)
    inl_t[trial.true_pairs[:, 1]] = True
    for pts, inl in ((trial.source, inl_s), (trial.target, inl_t)):
        lo, hi = pts[inl].min(0), pts[inl].max(0)
        assert np.all(pts[~inl] >= lo) and np.all(pts[~inl] <= hi)
    assert np.all(np.abs(trial.source[inl_s]) <= 5)


def test_motion_ranges():
    angles, trans = [], []
    for seed in range(40):
        t1 = table1_trial(0.5, seed=seed)
        angles.append(t1.angle_deg)
        trans.append(np.abs(t1.translation).max())
    assert max(angles) <= 5 + 1e-9 and max(trans) <= 1.5
    big = [table2_trial(0.5, seed=s).angle_deg for s in range(40)]
    assert max(big) > 120  # full range of angles
    assert max(np.abs(table2_trial(0.5, seed=s).translation).max() for s in range(40)) <= 10


def test_determinism_and_seed_sensitivity():
    a, b, c = table2_trial(0.8, seed=11), table2_trial(0.8, seed=11), table2_trial(0.8, seed=12)
    np.testing.assert_array_equal(a.source, b.source)
    np.testing.assert_array_equal(a.target, b.target)
    np.testing.assert_array_equal(a.true_pairs, b.true_pairs)
    assert not np.array_equal(a.source, c.source)
    rng_trial = table1_trial(0.5, seed=np.random.default_rng(5))
    np.testing.assert_array_equal(rng_trial.source, table1_trial(0.5, seed=5).source)


def test_trial_is_frozen():
    trial = table1_trial(0.5, seed=0)
    with pytest.raises(ValueError):
        trial.source[0, 0] = 1.0
    with pytest.raises(AttributeError):
        trial.outlier_fraction = 0.1


@pytest.mark.parametrize("bad", [-0.1, 1.0, 1.5, "x"])
def test_bad_fraction(bad):
    with pytest.raises(ValueError, match="outlier_fraction"):
        table2_trial(bad, seed=0)


@pytest.mark.parametrize("bad", [-0.01, np.nan, np.inf, "0.01", True, None])
def test_bad_noise_is_named(bad):
    with pytest.raises(ValueError, match="`noise` to be a finite number >= 0 .a share of the inlier RMS radius"):
        table2_trial(0.5, noise=bad, seed=0)


def test_seed_required_and_bad_inliers():
    with pytest.raises(ValueError, match="seed"):
        table2_trial(0.5)
    with pytest.raises(ValueError, match="n_inliers"):
        table2_trial(0.5, n_inliers=2, seed=0)


def test_correspondence_stats_hand_cases():
    true = [[0, 1], [1, 2], [2, 3], [3, 4]]
    assert correspondence_stats(true, true) == (1.0, 1.0)
    assert correspondence_stats([[0, 1], [1, 2], [5, 5]], true) == pytest.approx((2 / 3, 0.5))
    assert correspondence_stats([[0, 1], [0, 1]], true) == (1.0, 0.25)  # duplicates count once
    assert correspondence_stats(np.empty((0, 2), int), true) == (0.0, 0.0)
    assert correspondence_stats([[9, 9]], []) == (0.0, 1.0)
    with pytest.raises(ValueError, match="found_pairs"):
        correspondence_stats([[1, 2, 3]], true)


def test_paper_success():
    true = [[0, 1], [1, 2], [2, 3], [3, 4]]
    assert paper_success([[0, 1], [1, 2]], true)
    assert not paper_success([[0, 1], [1, 3], [4, 4]], true)
    assert not paper_success(np.empty((0, 2), int), true)
    with pytest.raises(ValueError, match="one-to-one"):
        paper_success([[0, 1], [0, 2]], true)


def test_errors():
    trial = table2_trial(0.5, seed=1)
    assert rotation_error_deg(trial.rotation, trial.rotation) == pytest.approx(0, abs=1e-6)
    assert rotation_error_deg(trial.rotation, np.eye(3)) == pytest.approx(trial.angle_deg)
    assert translation_error([1, 2, 3], [1, 2, 5]) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="R_est"):
        rotation_error_deg(np.eye(2), np.eye(3))


def test_demo_mesh_offline():
    pts = demo_mesh("ant")
    assert pts.shape == (486, 3) and np.isfinite(pts).all()
    with pytest.raises(ValueError, match="name"):
        demo_mesh("bunny")


def test_bunny_missing_data_dir(tmp_path):
    with pytest.raises(DataNotFoundError):
        load_bunny_pair("bun000", "bun045", data_dir=tmp_path / "nope")
    with pytest.raises(FileNotFoundError):
        load_bunny_pair("bun000", "bun045", data_dir=tmp_path)


@pytest.mark.skipif(not (DATA / "stanford_bunny_scans").is_dir(), reason="real data not present")
@pytest.mark.parametrize(("target", "source"), [("bun000", "bun045"), ("bun315", "bun000")])
def test_bunny_ground_truth_aligns_overlap(target, source):
    from scipy.spatial import cKDTree

    tgt, src, R, t = load_bunny_pair(target, source, data_dir=DATA)
    assert tgt.shape[1] == src.shape[1] == 3 and len(tgt) > 30000
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)
    sub = src[:: max(1, len(src) // 5000)]
    d, _ = cKDTree(tgt).query(sub @ R.T + t)
    overlap = d < 0.005
    assert overlap.mean() > 0.5
    assert np.median(d[overlap]) < 0.001  # metres: ~1 mm
    with pytest.raises(FileNotFoundError, match="bun999"):
        load_bunny_pair("bun999", source, data_dir=DATA)


def test_synthetic_trial_with_given_inliers():
    mesh = demo_mesh("nut")
    trial = synthetic_trial(0.5, inliers=mesh, max_translation=2.0, seed=0)
    assert trial.n_inliers == len(mesh) and trial.n_outliers == len(mesh)
    def rows(a):
        return a[np.lexsort(a.T[::-1])]

    np.testing.assert_array_equal(rows(trial.source[trial.true_pairs[:, 0]]), rows(mesh))
    s = trial.source[trial.true_pairs[:, 0]] @ trial.rotation.T + trial.translation
    np.testing.assert_allclose(s, trial.target[trial.true_pairs[:, 1]], atol=1e-12)
