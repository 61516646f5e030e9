"""The likelihood-ratio test of a motion's pairs (`gatv.stats.likelihood_level`, `gatv.stages.likelihood_counts`).

Its null (the count's: chance target points a Poisson process at the local
density) checked against a numpy simulation; its power and its false keeps on
Table-2 trials; its work bounded.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from gatv import Rotor, stages, stats
from gatv.datasets import table2_trial
from gatv.models.base import homogeneous
from gatv.registration import count_ceiling, register_budget


def _simulated_sums(ratios, odds, replicates, rng, reach=stages.SCORE_REACH):
    """Numpy reference: the compound Poisson sum of `stats.pair_scores` over every chance target point
    within `reach` noise deviations of each source point (σ = 1)."""
    ratios = np.asarray(ratios, float)
    density = odds / (ratios * (4.0 * np.pi) ** 1.5)  # peak_ratios inverted at σ = 1
    lam = density * 4.0 / 3.0 * np.pi * reach**3
    total = np.zeros(replicates)
    for a, rho, mean in zip(ratios, density, lam):
        n = rng.poisson(mean, replicates)
        r = reach * rng.uniform(size=n.sum()) ** (1.0 / 3.0)
        g = stats.pair_scores(r, 1.0, rho, odds)
        total += np.bincount(np.repeat(np.arange(replicates), n), weights=g, minlength=replicates)
    return total


def test_cumulants_match_the_simulated_sum():
    """K(1) is the odds a point (the ratio's mean is 1); K'(0) and K''(0) are the simulated sum's mean
    and variance."""
    rng = np.random.default_rng(0)
    ratios, odds = np.array([0.5, 4.0, 30.0]), 0.05
    k0, k1, k2 = stats.score_cumulants(1.0, ratios, np.ones(3), odds)
    assert abs(k0 - 3 * odds) < 1e-9
    _, mean, var = stats.score_cumulants(0.0, ratios, np.ones(3), odds)
    sums = _simulated_sums(ratios, odds, 400_000, rng)
    assert abs(sums.mean() - mean) < 4 * sums.std() / np.sqrt(sums.size)
    assert abs(sums.var() / var - 1.0) < 0.03


@settings(max_examples=4, deadline=None)
@given(seed=st.integers(0, 10**6), log_ratio=st.floats(-1.0, 4.0), n_points=st.integers(20, 200))
def test_level_is_reached_about_as_often_as_it_says(seed, log_ratio, n_points):
    """At a level of 1e-3 (`alpha=1`, 1,000 tests) the simulated sums reach it at most 1.5e-3 of the
    time (Bahadur–Rao is an approximation, Chernoff's prefactor a bound) and not far less (3 nats
    below it at least 1e-3 of the time): the level is the tail, not a loose bound."""
    rng = np.random.default_rng(seed)
    odds = 0.0417
    ratios = np.exp(log_ratio + rng.normal(0.0, 0.3, n_points))
    level = stats.likelihood_level(ratios, odds, 1e3, alpha=1.0)
    sums = _simulated_sums(ratios, odds, 100_000, rng)
    assert np.mean(sums >= level) <= 1.5e-3
    assert np.mean(sums >= level - 3.0) >= 1e-3


@settings(max_examples=6, deadline=None)
@given(log_ratio=st.floats(-3.0, 12.0), spread=st.floats(0.0, 1.0), log_tests=st.floats(0.0, 16.0))
def test_level_grows_with_the_tests_and_stays_finite(log_ratio, spread, log_tests):
    """Bounded work: the level converges (finite, positive) for peak ratios from 0.05 to 1.6e5 and up
    to 1e16 tests, and more tests never lower it."""
    ratios = np.exp(log_ratio + spread * np.linspace(-1.0, 1.0, 300))
    low = stats.likelihood_level(ratios, 0.0417, 10.0**log_tests)
    high = stats.likelihood_level(ratios, 0.0417, 10.0 ** (log_tests + 2.0))
    assert 0.0 < low <= high < np.inf


def _trial(f, noise, k):
    return table2_trial(f, noise=noise, seed=np.random.SeedSequence([0, round(1000 * f), round(10000 * noise), k]))


def test_likelihood_keeps_true_poses_the_count_refuses():
    """Table 2, f = 0.95, 1% noise (`benchmarks/table2.py`'s trials 0, 3, 4): the count test refuses
    the true pose at every level (`count_ceiling`), the likelihood-ratio test keeps it."""
    for k in (0, 3, 4):
        trial = _trial(0.95, 0.01, k)
        P = stages.prepare(trial.source, trial.target)
        truth = homogeneous(trial.rotation, trial.translation)
        assert not count_ceiling(P, truth), k
        assert count_ceiling(P, truth, likelihood=True), k


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 10**6), f=st.sampled_from([0.5, 0.9, 0.95]), angle=st.floats(20.0, 180.0))
def test_likelihood_never_keeps_a_random_pose(seed, f, angle):
    """A pose 20–180° off the truth, with a shifted translation, cross-fitted at each level's gate as the
    search does: the likelihood-ratio test passes at none, at the family-wise level of the search's
    final test; the true pose of the same trial passes (f = 0.5 and 0.9: at 0.95 the truth fails
    in 3 of 20 trials, `benchmarks/table2.py`'s count ceiling column)."""
    trial = table2_trial(f, noise=0.01, seed=seed)
    P = stages.prepare(trial.source, trial.target)
    share, budget = register_budget(P)
    levels = stages.tolerance_levels(P, None, stages.NOISY_SCHEDULE)
    n_final = float(budget) * P.model.search_policy().max_matches
    rng = np.random.default_rng(seed)
    R = Rotor.from_axis_angle(rng.normal(size=3), np.radians(angle)).as_matrix() @ trial.rotation
    wrong = homogeneous(R, trial.translation + rng.normal(0, 2.0, 3))
    for k, tol in enumerate(levels):
        counts = stages.likelihood_counts(P, wrong, stages.gate(tol), levels[:k + 1], n_final, share)
        assert stages.likelihood_passes(counts) is None
        assert len(counts) <= k + 1
    if f < 0.95:
        assert count_ceiling(P, homogeneous(trial.rotation, trial.translation), likelihood=True)


def test_likelihood_counts_rejects_a_bad_share():
    import pytest

    trial = _trial(0.5, 0.01, 0)
    P = stages.prepare(trial.source, trial.target)
    with pytest.raises(ValueError, match="inlier_share"):
        stages.likelihood_counts(P, np.eye(4), 1.0, [0.1], 1.0, 1.0)
