"""Every motion on the sphere: the plane stage, repeated patterns, peeling, and strategy="voting"."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from catadioptric import SphereMotion, match, sphere_noise, synthetic_views
from catadioptric.constants import PATTERN_ALPHA
from catadioptric.plane import (
    apply_homography,
    decompose_homography,
    fit_homography,
    homography_from_rays,
    plane_stage,
    sign_test,
)
from gatv.datasets import correspondence_stats, rotation_error_deg
from gatv.errors import InputError

CAMERA = synthetic_views(10, xi=1.0, seed=0).camera1


def _board(rows=6, cols=8, spacing=0.1, notch=True):
    """Inner corners of a checkerboard in its own frame (z = 0), centred.

    With ``notch`` a 2 x 3 block of one corner is missing (a marker), so
    that the pattern is not symmetric under a half-turn: a turned match
    leaves 6 corners unexplained, as a shift by one period does.
    """
    gx, gy = np.meshgrid(np.arange(cols), np.arange(rows), indexing="xy")
    keep = ~((gx < 3) & (gy < 2)) if notch else np.ones(gx.shape, bool)
    gx, gy = gx[keep], gy[keep]
    return np.column_stack([(gx.ravel() - (cols - 1) / 2) * spacing, (gy.ravel() - (rows - 1) / 2) * spacing,
                            np.zeros(gx.size)])


def _pose(direction, distance, tilt_deg, seed):
    """Board-to-camera pose: the board's centre ``distance`` along ``direction``, facing the camera, tilted."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    z = -d
    a = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(a, z)
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z])
    tilt = Rotation.from_rotvec(np.radians(tilt_deg) * np.random.default_rng(seed).normal(size=3)
                                / np.sqrt(3)).as_matrix()
    return R @ tilt, d * distance


def two_motion_scene(seed=0, n_static=150, n_outliers=30, board_turn_deg=25.0):
    """A static scene seen twice by a still camera, plus a board (8 x 6 corners) moved rigidly.

    Returns ``(pixels1, pixels2, static truth, board truth)``: the truth as
    rows of the (shuffled) pixel arrays.
    """
    rng = np.random.default_rng(seed)
    dirs = rng.normal(size=(4 * n_static, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dirs = dirs[dirs[:, 2] > -0.2][:n_static]
    static = dirs * rng.uniform(3.0, 6.0, (len(dirs), 1))
    Rb, tb = _pose([0.8, 0.3, 0.5], 1.0, 20.0, seed)
    board = _board()
    X1 = board @ Rb.T + tb
    turn = Rotation.from_rotvec(np.radians(board_turn_deg) * np.array([0.3, 0.9, 0.3])
                                / np.linalg.norm([0.3, 0.9, 0.3])).as_matrix()
    X2 = (X1 - tb) @ turn.T + tb + np.array([0.05, -0.08, 0.04])
    noise = lambda n: rng.normal(0.0, 0.5, (n, 2))
    s1 = CAMERA.project(static) + noise(len(static))
    s2 = CAMERA.project(static) + noise(len(static))
    b1 = CAMERA.project(X1) + noise(len(X1))
    b2 = CAMERA.project(X2) + noise(len(X2))
    out = lambda: CAMERA.project(rng.normal(size=(n_outliers, 3)) * [1, 1, 0.3] + [0, 0, 1.0])
    p1 = np.vstack([s1, b1, out()])
    p2 = np.vstack([s2, b2, out()])
    perm = rng.permutation(len(p2))
    inv = np.argsort(perm)
    ns, nb = len(static), len(board)
    static_truth = np.column_stack([np.arange(ns), inv[:ns]])
    board_truth = np.column_stack([ns + np.arange(nb), inv[ns:ns + nb]])
    return p1, p2[perm], static_truth, board_truth


# ------------------------------------------------------------ the mapping
def test_homography_of_a_moved_plane_maps_its_rays_exactly():
    Rb, tb = _pose([0.2, 0.5, 0.8], 1.5, 30.0, 1)
    X1 = _board() @ Rb.T + tb
    R = Rotation.from_rotvec([0.2, -0.3, 0.1]).as_matrix()
    t = np.array([0.1, 0.05, -0.2])
    X2 = X1 @ R.T + t
    x, y = X1 / np.linalg.norm(X1, axis=1, keepdims=True), X2 / np.linalg.norm(X2, axis=1, keepdims=True)
    H = fit_homography(x, y)
    assert np.max(np.linalg.norm(apply_homography(H, x) - y, axis=1)) < 1e-10
    # the minimal solver on 4 pairs gives the same mapping
    H4 = homography_from_rays(x[None, [0, 5, 36, 41]], y[None, [0, 5, 36, 41]])[0]
    assert np.max(np.linalg.norm(apply_homography(H4, x) - y, axis=1)) < 1e-9
    # one of the decompositions is the true motion (t over the plane's distance, its normal)
    n = Rb[:, 2]
    d = float(n @ tb)
    errs = [rotation_error_deg(Rs, R) + np.linalg.norm(ts - t / d) + np.linalg.norm(ns - n)
            for Rs, ts, ns in decompose_homography(H)]
    assert min(errs) < 1e-6


def test_sign_test_is_the_binomial_tail():
    assert sign_test(0, 0) == 1.0
    assert sign_test(6, 0) == pytest.approx(0.5**6)
    assert sign_test(3, 3) == pytest.approx(sum(__import__("math").comb(6, k) for k in range(3, 7)) / 64)
    assert sign_test(0, 5) == 1.0


# ------------------------------------------------------------ repeated pattern
@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow), pytest.param(2, marks=pytest.mark.slow)])
def test_whole_pattern_beats_the_shifted_rival(seed):
    """The board alone, wholly visible in both views: the true mapping explains all its
    corners, a shift by one period (or a half-turn) leaves at least 5 unexplained, and
    the sign test rejects it."""
    p1, p2, _, truth = two_motion_scene(seed, n_static=0, n_outliers=0)
    r1, r2 = CAMERA.lift(p1), CAMERA.lift(p2)
    info = {}
    _, pairs = plane_stage(r1, r2, sphere_noise(CAMERA, p1), sphere_noise(CAMERA, p2),
                           np.random.default_rng(0), info)
    precision, recall = correspondence_stats(pairs, truth)
    assert precision == 1.0 and recall == 1.0
    assert info["plane_rival_support"] <= len(truth) - 5
    assert info["plane_rival_p"] < PATTERN_ALPHA and "plane_tie" not in info


def test_symmetric_pattern_reports_the_tie():
    """Without the notch the half-turned match explains every corner too: said so in info."""
    from catadioptric import plane

    Rb, tb = _pose([0.8, 0.3, 0.5], 1.0, 20.0, 0)
    X1 = _board(notch=False) @ Rb.T + tb
    turn = Rotation.from_rotvec(np.radians(20.0) * np.array([0.0, 1.0, 0.0])).as_matrix()
    X2 = (X1 - tb) @ turn.T + tb
    x, y = X1 / np.linalg.norm(X1, axis=1, keepdims=True), X2 / np.linalg.norm(X2, axis=1, keepdims=True)
    s = np.full(len(x), 0.003)
    info = {}
    _, pairs = plane_stage(x, y, s, s, np.random.default_rng(0), info)
    assert len(pairs) == 48 and info["plane_rival_support"] == 48
    assert "plane_tie" in info and "half-turn" in info["plane_tie"]
    assert plane.sign_test(0, 0) == 1.0


def test_plane_stage_without_any_plane_finds_nothing_above_chance():
    v = synthetic_views(120, rotation_deg=0.0, translation=(0, 0, 0), outlier_fraction=0.0, seed=3)
    rng = np.random.default_rng(3)
    other = CAMERA.project(rng.normal(size=(120, 3)) * [1, 1, 0.3] + [0, 0, 1.0])
    m = match(v.pixels1, other, CAMERA)
    assert not m or all(mo.support < 20 for mo in m.motions)


# ------------------------------------------------------------ every motion
@pytest.fixture(scope="module")
def two_motions():
    """Scene 0 and its match at the default seed (0), shared by the tests below."""
    p1, p2, static, board = two_motion_scene(0)
    return p1, p2, static, board, match(p1, p2, CAMERA)


def test_two_motions_static_scene_and_moved_board(two_motions):
    p1, p2, static, board, m = two_motions
    assert len(m.motions) >= 2 and isinstance(m.motions[0], SphereMotion)
    first, second = m.motions[0], m.motions[1]
    assert first.strategy == "rigid" and first.angle_deg < 0.5
    p, r = correspondence_stats(first.correspondences, static)
    assert p >= 0.95 and r >= 0.8
    assert second.strategy == "plane" and second.homography is not None
    # the board's motion, whatever the number of plane solutions: the one reported is the truth
    # (measured 2.4 deg, its translation direction 3.4 deg and its plane's normal 2.8 deg off)
    turn = Rotation.from_rotvec(np.radians(25.0) * np.array([0.3, 0.9, 0.3]) / np.linalg.norm([0.3, 0.9, 0.3]))
    Rb, tb = _pose([0.8, 0.3, 0.5], 1.0, 20.0, 0)
    t_true = tb - turn.as_matrix() @ tb + np.array([0.05, -0.08, 0.04])
    assert rotation_error_deg(second.rotation, turn.as_matrix()) < 3.0
    cos_t = second.translation @ t_true / (np.linalg.norm(second.translation) * np.linalg.norm(t_true))
    assert np.degrees(np.arccos(min(1.0, cos_t))) < 6.0
    normals = [np.asarray(sol["normal"]) for sol in second.info["plane_solutions"]]
    assert min(np.degrees(np.arccos(min(1.0, abs(n @ Rb[:, 2]) / np.linalg.norm(n)))) for n in normals) < 5.0
    p, r = correspondence_stats(second.correspondences, board)
    assert p >= 0.95 and r >= 0.8
    # the top level holds every motion's matches, one-to-one
    allc = np.vstack([mo.correspondences for mo in m.motions])
    assert m.support == len(allc)
    assert len(np.unique(m.correspondences[:, 0])) == len(np.unique(m.correspondences[:, 1])) == m.support
    record = m.to_dict()
    assert len(record["motions"]) == len(m.motions) and record["motions"][1]["strategy"] == "plane"


def test_same_seed_same_motions(two_motions):
    p1, p2, _, _, a = two_motions
    b = match(p1, p2, CAMERA, seed=0)
    assert len(a.motions) == len(b.motions)
    for x, y in zip(a.motions, b.motions, strict=True):
        assert np.array_equal(x.correspondences, y.correspondences) and x.strategy == y.strategy


@pytest.mark.slow
def test_max_motions_one_reports_the_dominant_motion_only():
    p1, p2, static, _ = two_motion_scene(2)
    m = match(p1, p2, CAMERA, max_motions=1)
    assert len(m.motions) == 1 and m.motions[0].strategy == "rigid"
    assert correspondence_stats(m.correspondences, static)[0] >= 0.95


def test_a_single_motion_scene_gains_no_false_motion():
    v = synthetic_views(200, rotation_deg=30.0, translation=(0, 0, 0), outlier_fraction=0.5, seed=11)
    m = match(v.pixels1, v.pixels2, v.camera1)
    p, _ = correspondence_stats(m.correspondences, v.pairs)
    assert p >= 0.95
    assert len(m.motions) == 1, m.info.get("peel")


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2"])
def test_bad_max_motions_is_named(bad):
    v = synthetic_views(30, seed=1)
    with pytest.raises(InputError, match="max_motions"):
        match(v.pixels1, v.pixels2, v.camera1, max_motions=bad)


def test_unknown_strategy_lists_voting():
    v = synthetic_views(30, seed=1)
    with pytest.raises(InputError, match="'voting'"):
        match(v.pixels1, v.pixels2, v.camera1, strategy="hough")


# ------------------------------------------------------------ the paper's method
def test_voting_strategy_reports_what_its_stages_did():
    """strategy="voting" on an outlier-free pure rotation (seed 5): the paper's surface keeps few
    true pairs here (design notes, section 10), and the result says why it returns nothing, with
    numbers that hold: each stage keeps at most what the one before it had, and the match falls
    short of the chance level (one pair above the count wrong rotations exceed only rarely)."""
    v = synthetic_views(150, rotation_deg=30.0, translation=(0, 0, 0), outlier_fraction=0.0, seed=5)
    m = match(v.pixels1, v.pixels2, v.camera1, strategy="voting", max_motions=1)
    i = m.info
    assert i["voting_candidates"] >= i["voting_tokens_kept"] >= i["voting_eq41_passed"] >= i["voting_support"] > 0
    assert not m and m.strategy == "none" and not m.motions and m.support == 0
    assert 0 < i["voting_support"] < i["chance_support"]
    assert i["reason"] == f"{i['voting_support']} pairs, below the chance level {i['chance_support']}"


def test_voting_strategy_match_beats_chance_one_to_one():
    """Seed 1 of the same scene: a voting match is returned, one-to-one, above the chance level."""
    from catadioptric.constants import RIVAL_RATIO

    v = synthetic_views(150, rotation_deg=30.0, translation=(0, 0, 0), outlier_fraction=0.0, seed=1)
    m = match(v.pixels1, v.pixels2, v.camera1, strategy="voting", max_motions=1)
    assert m and m.strategy == "voting"
    c = m.correspondences
    assert len(np.unique(c[:, 0])) == len(np.unique(c[:, 1])) == len(c) == m.info["voting_support"]
    assert len(c) >= m.info["chance_support"]
    assert m.info["rival_support"] < max(m.info["chance_support"], RIVAL_RATIO * len(c))


@pytest.mark.xfail(strict=True, reason=(
    "strategy='voting' does not recover an outlier-free pure camera rotation of 150 corners: over "
    "seeds 0-7 it returns nothing (below chance, or 'ambiguous' against a rival that is the true "
    "matching, 119-125 rays) or 18-31 pairs at 52-61% precision (seeds 1, 2); the tensor voting "
    "keeps 68-159 of ~1,100 candidates (design notes: the surface's saliency AUC is 0.55-0.71)"))
def test_voting_strategy_recovers_a_pure_rotation():
    for seed in (1, 5):
        v = synthetic_views(150, rotation_deg=30.0, translation=(0, 0, 0), outlier_fraction=0.0, seed=seed)
        m = match(v.pixels1, v.pixels2, v.camera1, strategy="voting", max_motions=1)
        assert m and m.strategy == "voting", m.info.get("reason")
        precision, recall = correspondence_stats(m.correspondences, v.pairs)
        assert precision >= 0.9 and recall >= 0.5, (seed, precision, recall)


def test_voting_chart_is_equidistant():
    from catadioptric.voting import chart

    c = np.array([0.0, 0.0, 1.0])
    theta = np.radians([0.0, 30.0, 90.0, 120.0])
    rays = np.column_stack([np.sin(theta), np.zeros(4), np.cos(theta)])
    uv = chart(rays, c)
    assert np.allclose(np.hypot(uv[:, 0], uv[:, 1]), theta, atol=1e-12)
    near = cKDTree(uv).query(uv, k=2)[0][:, 1]
    assert np.all(near > 0)


def test_reclaim_gives_the_plane_its_corners_back():
    """An earlier motion that took board corners (wrong partners) gives them back to the plane."""
    from catadioptric.peeling import reclaim

    p1, p2, static, board = two_motion_scene(0)
    r1, r2 = CAMERA.lift(p1), CAMERA.lift(p2)
    s1, s2 = sphere_noise(CAMERA, p1), sphere_noise(CAMERA, p2)
    H = fit_homography(r1[board[:, 0]], r2[board[:, 1]])
    wrong = np.column_stack([board[:5, 0], np.roll(board[:5, 1], 1)])
    earlier = np.vstack([static, wrong])
    rows1, rows2 = np.arange(len(p1)), np.arange(len(p2))
    info = {}
    out, plane = reclaim([(SphereMotion(earlier, "local"), earlier)], H, board[5:], r1, r2, s1, s2,
                         rows1, rows2, info)
    assert info["reclaimed_from_earlier"] == 5
    assert set(map(tuple, out[0][1].tolist())) == set(map(tuple, static.tolist()))
    assert out[0][0].support == len(static)
    precision, recall = correspondence_stats(plane, board)
    assert recall == 1.0 and precision >= 0.95  # at most a chance pair of the free rays
