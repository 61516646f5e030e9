from __future__ import annotations

import numpy as np
import pytest

from gatv.baselines import closest_pairs, fitzgibbon_icp, icp, median_spacing
from gatv.datasets import (
    correspondence_stats,
    paper_success,
    rotation_error_deg,
    synthetic_trial,
    table1_trial,
    translation_error,
)
from gatv.motion import RigidMotion


def _three_degrees(f, seed):
    return synthetic_trial(f, angle_range_deg=(3.0, 3.0), max_translation=1.5, seed=seed)


@pytest.mark.parametrize("method", [fitzgibbon_icp, icp])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recovers_three_degrees_without_outliers(method, seed):
    trial = _three_degrees(0.0, seed)
    motion = method(trial.source, trial.target)
    assert isinstance(motion, RigidMotion) and motion
    assert rotation_error_deg(motion.rotation, trial.rotation) < 0.1
    assert translation_error(motion.translation, trial.translation) < 0.01
    precision, recall = correspondence_stats(motion.correspondences, trial.true_pairs)
    assert precision == recall == 1.0
    assert motion.rms < 1e-6


@pytest.mark.parametrize("loss", ["huber", "cauchy", "linear"])
def test_ficp_losses_exact_data(loss):
    trial = _three_degrees(0.0, 5)
    motion = fitzgibbon_icp(trial.source, trial.target, loss=loss)
    assert rotation_error_deg(motion.rotation, trial.rotation) < 1e-6
    assert motion.info["method"] == "F-ICP" and motion.info["loss"] == loss


def test_ficp_success_rate_with_outliers():
    wins, errors = 0, []
    for seed in range(10):
        trial = table1_trial(0.5, seed=seed)
        motion = fitzgibbon_icp(trial.source, trial.target)
        wins += paper_success(motion.correspondences, trial.true_pairs)
        errors.append(rotation_error_deg(motion.rotation, trial.rotation))
    assert wins >= 8
    assert np.median(errors) < 1.0


def test_init_is_used():
    # a 40 degree motion is out of reach from the identity but not from near the truth
    trial = synthetic_trial(0.0, angle_range_deg=(40.0, 40.0), max_translation=1.0, seed=3)
    near = (trial.rotation, trial.translation + 0.05)
    for method in (fitzgibbon_icp, icp):
        motion = method(trial.source, trial.target, init=near)
        assert rotation_error_deg(motion.rotation, trial.rotation) < 1e-6
    start = RigidMotion(trial.rotation, trial.translation)
    assert fitzgibbon_icp(trial.source, trial.target, init=start).support == 50


def test_correspondences_are_one_to_one():
    rng = np.random.default_rng(0)
    target = rng.uniform(-1, 1, size=(20, 3))
    source = np.vstack([target, target + 1e-3, target[:5] - 2e-3])
    pairs, d = closest_pairs(source, target, 0.01)
    assert len(np.unique(pairs[:, 1])) == len(pairs) == 20
    np.testing.assert_array_equal(pairs[:, 0], np.arange(20))  # the exact copies win
    assert np.all(d == 0)
    motion = icp(source, target)
    assert len(np.unique(motion.correspondences[:, 1])) == motion.support


def test_no_correspondence_is_falsy_with_reason():
    trial = _three_degrees(0.0, 0)
    motion = icp(trial.source, trial.target, match_threshold=1e-30, max_iterations=1)
    assert not motion
    assert "no source point" in motion.info["reason"]


def test_median_spacing_units():
    pts = np.arange(10.0)[:, None] * np.array([[1.0, 0.0, 0.0]])
    assert median_spacing(pts) == pytest.approx(1.0)
    assert median_spacing(pts * 1000) == pytest.approx(1000.0)
    assert median_spacing(np.zeros((4, 3))) == 1.0


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"loss": "l2"}, "loss"),
        ({"scale": -1.0}, "scale"),
        ({"match_threshold": 0}, "match_threshold"),
        ({"init": "identity"}, "init"),
        ({"init": (np.eye(2), np.zeros(3))}, "init"),
    ],
)
def test_ficp_bad_options(kwargs, match):
    trial = _three_degrees(0.0, 0)
    with pytest.raises(ValueError, match=match):
        fitzgibbon_icp(trial.source, trial.target, **kwargs)


def test_bad_points():
    with pytest.raises(ValueError, match="source"):
        fitzgibbon_icp(np.zeros((5, 2)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="target"):
        icp(np.zeros((5, 3)), [[np.nan, 0, 0]] * 5)


def _load_benchmark(name):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    if not path.exists():
        pytest.skip(f"{path} not present")
    spec = importlib.util.spec_from_file_location(f"_bench_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_table1_benchmark_smoke(tmp_path, capsys):
    table1 = _load_benchmark("table1")
    rc = table1.main(["--trials", "2", "--fractions", "0.5", "--methods", "F-ICP,ICP", "--out", str(tmp_path)])
    assert rc == 0
    out = capsys.readouterr().out
    assert "| 0.50 | F-ICP  |" in out and "paper F-ICP %" in out
    lines = (tmp_path / "table1.csv").read_text().splitlines()
    assert lines[0].startswith("f,method,trials,success_pct") and len(lines) == 3
    assert len((tmp_path / "table1_trials.csv").read_text().splitlines()) == 5


def test_ficp_few_points():
    x = np.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3]])
    motion = fitzgibbon_icp(x, x + 0.01)
    assert motion.info["solver"] == "trf"
    assert np.allclose(motion.translation, 0.01, atol=1e-6)
