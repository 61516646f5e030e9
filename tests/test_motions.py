"""Tests of gatv.motions: several overlapping rigid motions (paper section 5)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gatv.datasets import rotation_error_deg
from gatv.ga import Rotor
from gatv.motions import (
    Segmentation,
    fig12_scene,
    joint_space_residuals,
    multi_motion_scene,
    segment,
)


def _matched(scene, seg):
    """True motion index of each found motion (by shared correspondences)."""
    out = []
    for m in seg.motions:
        found = set(map(tuple, m.correspondences.tolist()))
        overlap = [len(found & set(map(tuple, p.tolist()))) for p in scene.true_pairs]
        out.append(int(np.argmax(overlap)))
    return out


@pytest.fixture(scope="module")
def fig12():
    scene = fig12_scene(seed=0, n_outliers=20)
    return scene, segment(scene.source, scene.target, seed=0)


def test_fig12_recovers_three_motions_exactly(fig12):
    scene, seg = fig12
    assert isinstance(seg, Segmentation)
    assert len(seg) == 3
    match = _matched(scene, seg)
    assert sorted(match) == [0, 1, 2]
    for m, k in zip(seg.motions, match):
        assert rotation_error_deg(m.rotation, scene.rotations[k]) < 1e-6
        assert np.linalg.norm(m.translation - scene.translations[k]) < 1e-6
        np.testing.assert_array_equal(m.correspondences, scene.true_pairs[k])
    supports = [m.support for m in seg.motions]
    assert supports == sorted(supports, reverse=True)


def test_labels_consistent_with_correspondences(fig12):
    scene, seg = fig12
    src = np.full(len(scene.source), -1)
    tgt = np.full(len(scene.target), -1)
    for k, m in enumerate(seg.motions):
        c = m.correspondences
        assert len(np.unique(c[:, 0])) == len(c) and len(np.unique(c[:, 1])) == len(c)
        assert (src[c[:, 0]] == -1).all() and (tgt[c[:, 1]] == -1).all()  # one motion per point
        src[c[:, 0]] = k
        tgt[c[:, 1]] = k
    np.testing.assert_array_equal(seg.source_labels, src)
    np.testing.assert_array_equal(seg.target_labels, tgt)
    # every correspondence is a token of its own plane
    assert seg.tokens.shape == (len(seg.token_labels), 2)
    lookup = {tuple(p): int(lab) for p, lab in zip(seg.tokens.tolist(), seg.token_labels)}
    for k, m in enumerate(seg.motions):
        assert all(lookup[tuple(p)] == k for p in m.correspondences.tolist())
    # the outliers stay unexplained
    np.testing.assert_array_equal(seg.source_labels == -1, scene.source_labels == -1)


def test_result_is_frozen(fig12):
    _, seg = fig12
    with pytest.raises(AttributeError):
        seg.motions = ()
    with pytest.raises(ValueError):
        seg.source_labels[0] = 5
    json.dumps(seg.to_dict())


def test_shared_axis_and_translation_split():
    """Same axis and translation: one eq.-30 plane, two motions (section 5)."""
    axis = [1.0, 2.0, -1.0]
    rots = [Rotor.from_axis_angle(axis, np.radians(a)).as_matrix() for a in (40.0, 75.0)]
    t = [1.0, -2.0, 3.0]
    scene = multi_motion_scene(rots, [t, t], [45, 35], n_outliers=30, seed=4)
    seg = segment(scene.source, scene.target)
    assert len(seg) == 2
    assert sorted(_matched(scene, seg)) == [0, 1]
    for m, k in zip(seg.motions, _matched(scene, seg)):
        np.testing.assert_array_equal(m.correspondences, scene.true_pairs[k])
    # the two motions shared one salient surface, split into two
    assert seg.info["n_surfaces"] == 1
    assert seg.info["shared_surfaces"][0]["motions"] == 2


def test_joint_space_residuals_split_a_shared_plane():
    """Eq. 30 cannot tell the two motions apart, eqs. 27-29 can (through q0)."""
    rng = np.random.default_rng(1)
    x = rng.uniform(-5, 5, (20, 3))
    R1 = Rotor.from_axis_angle([0, 0, 1], np.radians(30)).as_matrix()
    R2 = Rotor.from_axis_angle([0, 0, 1], np.radians(70)).as_matrix()
    t = np.array([1.0, 2.0, 3.0])
    y = x @ R2.T + t  # pairs of motion 2
    pairs = np.column_stack([np.arange(20), np.arange(20)])
    r1 = joint_space_residuals(x, y, pairs, R1, t)
    r2 = joint_space_residuals(x, y, pairs, R2, t)
    np.testing.assert_allclose(r1[:, 3], 0.0, atol=1e-12)  # same eq.-30 plane
    np.testing.assert_allclose(r2, 0.0, atol=1e-12)
    assert (np.abs(r1[:, :3]).max(axis=1) > 1e-3).all()
    # the four residuals together are the Euclidean residual
    y_noisy = y + rng.normal(0, 0.1, y.shape)
    r = joint_space_residuals(x, y_noisy, pairs, R2, t)
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), np.linalg.norm(y_noisy - (x @ R2.T + t), axis=1))


def test_one_motion_gives_one():
    R = Rotor.from_axis_angle([1, 0, 1], np.radians(120)).as_matrix()
    scene = multi_motion_scene([R], [[2.0, 0.0, -1.0]], [50], n_outliers=50, seed=2)
    seg = segment(scene.source, scene.target)
    assert len(seg) == 1
    np.testing.assert_array_equal(seg[0].correspondences, scene.true_pairs[0])


def test_only_outliers_gives_none():
    # one tolerance level (exact data): the default noise schedule would
    # search every level, which is slow when there is nothing to find
    rng = np.random.default_rng(5)
    seg = segment(rng.uniform(-5, 5, (80, 3)), rng.uniform(-5, 5, (80, 3)), noise=1e-6)
    assert not seg and len(seg) == 0
    assert (seg.source_labels == -1).all() and (seg.target_labels == -1).all()
    assert seg.tokens.shape == (0, 2)
    assert "reason" in seg.info


def test_max_motions_caps(fig12):
    scene, full = fig12
    seg = segment(scene.source, scene.target, max_motions=2)
    assert len(seg) == 2
    assert [m.support for m in seg] == [m.support for m in full][:2]
    assert set(np.unique(seg.source_labels)) <= {-1, 0, 1}


def test_same_seed_same_result():
    scene = fig12_scene(seed=3, n_per_motion=30, n_outliers=30)
    a = segment(scene.source, scene.target, seed=7)
    b = segment(scene.source, scene.target, seed=7)
    assert len(a) == len(b)
    for ma, mb in zip(a, b):
        np.testing.assert_array_equal(ma.correspondences, mb.correspondences)
        np.testing.assert_array_equal(ma.rotation, mb.rotation)
    np.testing.assert_array_equal(a.tokens, b.tokens)
    np.testing.assert_array_equal(a.token_labels, b.token_labels)


def test_greedy_grouping_agrees(fig12):
    scene, seg = fig12
    greedy = segment(scene.source, scene.target, grouping="greedy")
    assert [m.correspondences.tolist() for m in greedy] == [m.correspondences.tolist() for m in seg]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"max_motions": 0}, "max_motions"),
        ({"max_motions": -2}, "max_motions"),
        ({"max_motions": 1.5}, "max_motions"),
        ({"max_motions": True}, "max_motions"),
        ({"min_support": 2}, "min_support"),
        ({"grouping": "louvain"}, "grouping"),
        ({"noise": -1.0}, "noise"),
    ],
)
def test_bad_options(kwargs, match):
    x = np.random.default_rng(0).uniform(-1, 1, (10, 3))
    with pytest.raises(ValueError, match=match):
        segment(x, x, **kwargs)


@pytest.mark.parametrize(
    ("source", "match"),
    [
        (np.zeros((10, 2)), "shape"),
        (np.zeros((2, 3)), "at least 3"),
        (np.full((10, 3), np.nan), "NaN"),
        (np.ones((10, 3)), "identical"),
        (np.outer(np.arange(10.0), [1.0, 2.0, 3.0]), "collinear"),
        (None, "None"),
    ],
)
def test_bad_points(source, match):
    x = np.random.default_rng(0).uniform(-1, 1, (10, 3))
    with pytest.raises(ValueError, match=match):
        segment(source, x)
    with pytest.raises(ValueError, match=match):
        segment(x, source)
