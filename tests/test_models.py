"""The motion-model seam: every model and result through the same interface."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import gatv
from gatv import stages
from gatv.errors import InputError
from gatv.ga import Rotor
from gatv.models import MODEL_NAMES, Motion, MotionModel, get_model


def _random_matrix(name: str, rng: np.random.Generator) -> np.ndarray:
    """A random motion of model ``name`` as a homogeneous matrix."""
    if name == "affine2d":
        A = rng.normal(size=(2, 2)) + 2.0 * np.eye(2)
        return np.block([[A, rng.normal(size=(2, 1))], [np.zeros((1, 2)), np.ones((1, 1))]])
    R = Rotor.from_axis_angle(rng.normal(size=3), rng.uniform(0.0, np.pi)).as_matrix()
    s = rng.uniform(0.1, 10.0) if name == "similarity" else 1.0
    T = np.eye(4)
    T[:3, :3] = s * R
    T[:3, 3] = rng.uniform(-5, 5, 3)
    return T


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_every_model_satisfies_the_protocol(name):
    model = get_model(name)
    assert isinstance(model, MotionModel)
    assert model.name == name
    assert get_model(model) is model
    assert model.sample_size <= model.n_params


@pytest.mark.parametrize("name", MODEL_NAMES)
@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_fit_is_exact_and_the_result_round_trips(name, seed):
    rng = np.random.default_rng(seed)
    model = get_model(name)
    T = _random_matrix(name, rng)
    x = rng.uniform(-5, 5, (12, model.dim))
    y = x @ T[:-1, :-1].T + T[:-1, -1]
    fitted = model.fit(x, y)
    assert np.allclose(fitted, T, atol=1e-8)
    assert np.allclose(model.residuals(fitted, x, y), 0.0, atol=1e-8)
    pairs = np.stack([np.arange(12), np.arange(12)], axis=1)
    m = model.result(fitted, pairs, score=12.0, rms=0.0, info={})
    assert isinstance(m, Motion) and m.model == name and bool(m) and m.support == 12
    assert np.allclose(m.matrix, T, atol=1e-8)
    assert np.allclose(m.transform(x), y, atol=1e-7)
    inv = m.inverse()
    assert np.allclose(inv.transform(y), x, atol=1e-7)
    assert np.array_equal(inv.correspondences, pairs[:, ::-1])
    assert np.allclose(type(m).from_matrix(m.matrix).matrix, m.matrix)
    d = json.loads(json.dumps(m.to_dict()))
    assert d["model"] == name and np.allclose(d["matrix"], m.matrix)


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_failure_is_falsy_with_its_reason(name):
    f = stages.failure(name, "nothing beat chance", {"n_source": 3})
    assert not f and f.support == 0
    assert f.info["reason"] == "nothing beat chance"
    assert f.to_dict()["reason"] == "nothing beat chance"
    assert np.array_equal(f.matrix, np.eye(get_model(name).dim + 1))


def test_unknown_model_lists_the_models():
    with pytest.raises(ValueError, match="'rigid', 'similarity', 'affine2d'"):
        gatv.register(np.zeros((5, 3)), np.zeros((5, 3)), model="projective")
    with pytest.raises(InputError, match="model"):
        get_model(3)


def test_wrong_dimension_names_the_argument_and_the_model():
    rng = np.random.default_rng(0)
    p2, p3 = rng.normal(size=(10, 2)), rng.normal(size=(10, 3))
    with pytest.raises(InputError, match=r"`source`.*'rigid'.*affine2d"):
        gatv.register(p2, p3)
    with pytest.raises(InputError, match=r"`target`.*'affine2d'.*'rigid' or 'similarity'"):
        from gatv.motions import segment

        segment(p2, p3, model="affine2d")


def test_results_are_frozen_values():
    m = gatv.RigidMotion(np.eye(3), np.zeros(3), [[0, 1]])
    with pytest.raises(AttributeError):
        m.rotation = np.eye(3)
    with pytest.raises(ValueError):
        m.rotation[0, 0] = 2.0
    with pytest.raises(InputError, match="`rotation`"):
        gatv.RigidMotion(np.eye(2), np.zeros(3))


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_register_with_a_generator_seed_is_reproducible(seed):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-5, 5, (30, 3))
    T = _random_matrix("rigid", rng)
    y = np.vstack([x @ T[:3, :3].T + T[:3, 3], rng.uniform(-5, 5, (20, 3))])
    a = gatv.register(x, y, seed=np.random.default_rng(7))
    b = gatv.register(x, y, seed=np.random.default_rng(7))
    assert np.array_equal(a.correspondences, b.correspondences)
    assert np.allclose(a.matrix, T, atol=1e-8)


@pytest.mark.parametrize("seed", [-1, 1.5, True, "0"])
def test_bad_seed_is_an_input_error(seed):
    with pytest.raises(InputError, match="`seed`"):
        gatv.register(np.random.default_rng(0).normal(size=(10, 3)),
                      np.random.default_rng(1).normal(size=(10, 3)), seed=seed)


def test_search_reports_progress_and_a_found_motion():
    rng = np.random.default_rng(2)
    x = rng.uniform(-5, 5, (40, 3))
    y = x @ Rotor.from_axis_angle([0, 0, 1], 1.0).as_matrix().T + 2.0
    P = stages.prepare(x, y, "rigid")
    seen = []
    found = stages.search(P, [1e-6 * P.spacing], budget=200, rng=rng,
                          progress=lambda f, msg="": seen.append(f))
    assert isinstance(found, stages.Found) and found.fit.support == 40
    assert seen and all(0.0 <= f <= 1.0 for f in seen)
    assert found.threshold <= found.fit.support


@settings(max_examples=40, deadline=None)
@given(mu=st.floats(1e-4, 60.0), n_matches=st.floats(1.0, 1e9))
def test_density_test_lets_through_at_most_the_judged_wrong_motions(mu, n_matches):
    """Over n_matches wrong motions of mean chance count mu, the expected number exceeding the
    density test's level is at most JUDGED_WRONG (family-wise ALPHA when that is stricter)."""
    from scipy.stats import poisson

    from gatv.stats import ALPHA, chance_count

    tests = stages.density_tests(n_matches)
    assert tests >= 1.0
    # 1000 source points, each landing on the one target ball (volume 1) with p = mu / 1000
    level = chance_count(1000.0, 1.0, 1000.0 / mu, 1.0 / np.cbrt(4.0 / 3.0 * np.pi), n_tests=tests)
    expected_wrong = n_matches * poisson.sf(level, mu)
    assert expected_wrong <= max(stages.JUDGED_WRONG, ALPHA * n_matches) * (1 + 1e-9)
    # and not much stricter than needed: one count less would let more through
    if tests > 1.0 and level > 0:
        assert n_matches * poisson.sf(level - 1, mu) > stages.JUDGED_WRONG * (1 - 1e-9)


@pytest.mark.parametrize("judged_wrong", [0.0, -1.0, float("nan")])
def test_density_tests_needs_a_positive_judged_wrong(judged_wrong):
    with pytest.raises(ValueError, match="judged_wrong"):
        stages.density_tests(1e6, judged_wrong)
    assert stages.density_tests(1e6, None) == 1e6


# ----------------------------------------------------------- search policy
def test_each_model_returns_its_search_policy():
    from gatv.models import DEFAULT_POLICY, SearchPolicy
    from gatv.models.base import MAX_WORK, NOISE_SCHEDULE, NOISY_SCHEDULE
    from gatv.models.rigid import NOISY_MAX_MATCHES, RIGID_TRIALS

    rigid = get_model("rigid").search_policy()
    assert rigid.schedule == NOISY_SCHEDULE and rigid.max_matches == NOISY_MAX_MATCHES == 512
    assert dict(rigid.trial_options) == RIGID_TRIALS
    assert rigid.trials(0.1) == dict(RIGID_TRIALS, min_share=0.1)
    assert rigid.settle_noise and rigid.rival_check and rigid.small_motion and rigid.scans
    assert rigid.graph_grouping and rigid.merge_motions and rigid.max_work == MAX_WORK and rigid.turned_copies
    for name in ("similarity", "affine2d"):
        p = get_model(name).search_policy()
        assert isinstance(p, SearchPolicy)
        assert p.schedule == NOISE_SCHEDULE and p.max_matches == stages.MAX_MATCHES == 64
        assert p.trials(0.1) is None and not (p.settle_noise or p.rival_check or p.scans or p.graph_grouping)
        assert p.turned_copies  # every model's motions are held against their copies
    assert get_model("similarity").search_policy().moment_prealign
    assert get_model("affine2d").search_policy() == SearchPolicy(turned_copies=True)
    assert DEFAULT_POLICY == SearchPolicy() and not DEFAULT_POLICY.turned_copies
    assert stages.NOISE_SCHEDULE == NOISE_SCHEDULE and stages.NOISY_SCHEDULE == NOISY_SCHEDULE
    with pytest.raises(TypeError):
        rigid.trial_options["wide"] = 2  # frozen


@settings(max_examples=60, deadline=None)
@given(name=st.sampled_from(["rigid", "similarity", "affine2d"]), n_source=st.integers(10, 3000),
       n_target=st.integers(10, 3000), gate=st.floats(1e-3, 1.0), log_tests=st.floats(0.0, 12.0),
       below=st.booleans())
def test_a_models_chance_alpha_is_the_level_at_which_its_chance_is_reached(name, n_source, n_target, gate,
                                                                            log_tests, below):
    from gatv.models import get_model
    from gatv.stats import ALPHA

    model = get_model(name)
    n_tests = 10.0**log_tests
    level = model.chance(n_source, n_target, 1000.0, gate, n_tests)
    support = level - 1 if below else level
    a = model.chance_alpha(support, n_source, n_target, 1000.0, gate, n_tests)
    assert (a <= ALPHA) == (not below)


def test_no_module_outside_the_models_branches_on_a_model_name():
    import re
    from pathlib import Path

    root = Path(gatv.__file__).parent
    pattern = re.compile(r"\.name\s*(==|!=|in\b|not in\b)|model\s*==\s*\"|\bname\s*!=\s*\"rigid\"")
    skip = {"models", "cli"}  # the CLI's choices belong to the CLI
    hits = [f"{p.relative_to(root)}:{n}" for p in root.rglob("*.py") if p.relative_to(root).parts[0] not in skip
            and p.name != "batch.py" for n, line in enumerate(p.read_text().splitlines(), 1)
            if pattern.search(line)]
    assert not hits, hits
