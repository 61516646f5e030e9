"""gatv.motions.segment on noisy point sets and real scans (issue 16).

Fast tests: the pipeline choice, a static plane (identity only, reported
degenerate), the chance level's properties, labels against
correspondences, seeds, bad input, the labelled PLY.  Slow tests: a noisy
three-motion scene without ``noise=``, the shared-axis split under noise,
two real objects in a real-scan scene, leftovers of a partial-overlap pair.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gatv import Rotor
from gatv.datasets import (
    DataNotFoundError,
    load_bunny_pair,
    load_uwa_pair,
    rotation_error_deg,
)
from gatv.errors import InputError
from gatv.motions import multi_motion_scene, scan_scene, segment
from gatv.motions.scans import (
    chance_support,
    coherent_pairs,
    displaced_level,
    local_noise,
    regions,
    thickness,
)

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def _bunny(target, source):
    try:
        return load_bunny_pair(target, source, data_dir=DATA)
    except DataNotFoundError:
        pytest.skip("real data (../shared/data) not available")


def _uwa(name):
    try:
        target, source, R, t = load_uwa_pair(name, data_dir=DATA)
    except DataNotFoundError:
        pytest.skip("real data (../shared/data) not available")
    return target / 1000.0, source / 1000.0, R, t / 1000.0  # millimetres -> metres, as the bunny


def _plane(rng, n, noise=0.001):
    xy = rng.uniform(-0.5, 0.5, (n, 2))
    return np.column_stack([xy, rng.normal(0.0, noise, n)])


def _labels_match(seg):
    for k, m in enumerate(seg.motions):
        c = m.correspondences
        assert np.all(seg.source_labels[c[:, 0]] == k)
        assert np.all(seg.target_labels[c[:, 1]] == k)
        assert len(np.unique(c[:, 0])) == len(c) and len(np.unique(c[:, 1])) == len(c)  # one-to-one


# ------------------------------------------------------------------ scans, fast
@pytest.fixture(scope="module")
def static_plane():
    rng = np.random.default_rng(0)
    return _plane(rng, 2500), _plane(rng, 2500)


def test_static_plane_gives_the_identity_only(static_plane):
    source, target = static_plane
    seg = segment(source, target)
    assert seg.info["pipeline"] == "scans"
    assert len(seg) == 1
    m = seg[0]
    assert m.angle_deg == 0.0 and np.all(m.translation == 0.0)
    assert m.info["kind"] == "identity" and seg.info["static"]
    # a plane: a slide along it would fit as well, which the result says
    assert [d["motion"] for d in seg.info["degenerate"]] == ["identity"]
    # a sliver the identity left is no plane of the scene unless it beats its chance level
    assert all(r["support"] > r["chance"] for r in seg.info["rounds"] if r.get("verdict") == "degenerate")
    assert np.mean(seg.source_labels == 0) > 0.9
    assert seg.info["reason"]
    _labels_match(seg)


def test_slid_plane_is_not_peeled_into_motions(static_plane):
    source, target = static_plane
    seg = segment(source, target + [0.1, 0.05, 0.0])
    assert len(seg) <= 1  # the identity (a plane slides on itself), nothing more
    assert all(m.info["kind"] == "identity" for m in seg)


def test_same_seed_same_result(static_plane):
    source, target = static_plane
    a = segment(source, target, seed=3)
    b = segment(source, target, seed=3)
    assert np.array_equal(a.source_labels, b.source_labels)
    assert np.array_equal(a.target_labels, b.target_labels)
    assert [m.correspondences.tolist() for m in a] == [m.correspondences.tolist() for m in b]


def test_scans_pipeline_names_bad_scan_options(static_plane):
    source, target = static_plane
    with pytest.raises(InputError, match="bogus"):
        segment(source, target, scan_options={"bogus": 1})
    with pytest.raises(InputError, match="n_points"):
        segment(source, target, scan_options={"n_points": 2})
    with pytest.raises(InputError, match="min_overlap"):
        segment(source, target, scan_options={"min_overlap": 1.5})


def test_scans_pipeline_rejects_exact_only_options(static_plane):
    source, target = static_plane
    with pytest.raises(InputError, match="`noise`.*scans pipeline"):
        segment(source, target, noise=0.01)
    with pytest.raises(InputError, match="pipeline"):
        segment(source, target, pipeline="dense")
    with pytest.raises(InputError, match="scan_options"):
        segment(source[:100], target[:100], pipeline="exact", scan_options={"n_points": 300})
    with pytest.raises(InputError, match="grouping"):
        segment(source[:100], target[:100], grouping="clusters")
    with pytest.raises(ValueError, match="source"):
        segment(np.full((10, 3), np.nan), target)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 1000), g1=st.floats(0.005, 0.05), g2=st.floats(0.005, 0.05))
def test_chance_level_grows_with_the_gate(seed, g1, g2):
    rng = np.random.default_rng(seed)
    x, y = _plane(rng, 400), rng.uniform(-0.5, 0.5, (400, 3))
    lo, hi = sorted((g1, g2))
    for tangent in (True, False):
        a = chance_support(x, y, lo, seed=seed, tangent=tangent, polish=0)
        b = chance_support(x, y, hi, seed=seed, tangent=tangent, polish=0)
        assert 0 <= a <= b <= x.shape[0]


def test_chance_level_of_a_plane_sliding_on_itself_is_its_size():
    rng = np.random.default_rng(1)
    x, y = _plane(rng, 1500, 0.0005), _plane(rng, 1500, 0.0005)
    gate = 0.05
    slide = chance_support(x, y, gate, seed=0, tangent=True)
    assert slide > 0.8 * x.shape[0]
    assert chance_support(x, y, gate, seed=0, tangent=False, polish=0) < 0.6 * slide


def _static_plane_in_clutter(rng, n_plane, n_clutter):
    """A plane sampled independently in two scans (0 points: none), each with its own uniform clutter."""
    box = rng.uniform(-0.5, 0.5, (n_clutter, 3)), rng.uniform(-0.5, 0.5, (n_clutter, 3))
    return np.vstack([_plane(rng, n_plane), box[0]]), np.vstack([_plane(rng, n_plane), box[1]])


def _identity_support(source, target, gate):
    from scipy.spatial import cKDTree

    d, _ = cKDTree(target).query(source, distance_upper_bound=gate)
    return int(np.count_nonzero(np.isfinite(d)))


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_displaced_level_tells_a_static_plane_from_overlapping_clutter(seed):
    # Clutter alone: the identity collects what the two scans' overlap gives any motion near it
    # (the most at no displacement, which the level extrapolates); a static plane is far above that.
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    radius = 0.015
    for n_plane, static in ((0, False), (1500, True)):
        x, y = _static_plane_in_clutter(rng, n_plane, 3000)
        test = displaced_level(x, cKDTree(y), np.eye(3), np.zeros(3), radius, 8 * radius)
        assert test.support <= _identity_support(x, y, radius)  # the coherent ones among the pairs
        assert (test.support > test.level) == static, (n_plane, test)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000), radius=st.floats(0.05, 0.4), k=st.integers(1, 12))
def test_coherent_pairs_match_a_brute_force_reference(seed, radius, k):
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-1.0, 1.0, (60, 3)), rng.uniform(-1.0, 1.0, (80, 3))
    R, t = _rotation(rng.normal(size=3), rng.uniform(0.0, 180.0)), rng.normal(0.0, 0.1, 3)
    from scipy.spatial import cKDTree

    got = coherent_pairs(x, cKDTree(y), R, t, radius, neighbours=k)
    moved = x @ R.T + t
    paired = np.linalg.norm(moved[:, None, :] - y[None, :, :], axis=2).min(axis=1) <= radius
    d = np.linalg.norm(x[:, None, :] - x[None, :, :], axis=2)
    np.fill_diagonal(d, np.inf)
    near = np.argsort(d, axis=1, kind="stable")[:, :k]
    assert np.array_equal(got, paired & (paired[near].mean(axis=1) > 0.5))


def test_displaced_level_is_invariant_to_the_unit():
    from scipy.spatial import cKDTree

    x, y = _static_plane_in_clutter(np.random.default_rng(4), 800, 2000)
    R, t = _rotation([0.0, 0.0, 1.0], 3.0), np.array([0.01, 0.0, 0.0])
    tests = [displaced_level(s * x, cKDTree(s * y), R, s * t, s * 0.015, s * 0.12) for s in (0.25, 1.0, 8.0)]
    assert tests[0] == tests[1] == tests[2] and tests[0].level > 0


def test_thickness_local_noise_and_regions():
    rng = np.random.default_rng(2)
    p = _plane(rng, 3000, 0.002)
    assert thickness(p) == pytest.approx(0.002, rel=0.1)
    assert local_noise(p, np.arange(300)) == pytest.approx(0.002, rel=0.3)
    two = np.vstack([p, p + [5.0, 0.0, 0.0]])
    parts = regions(two, 0.1, min_points=10)
    assert [len(r) for r in parts] == [3000, 3000]
    assert set(parts[0].tolist()) in (set(range(3000)), set(range(3000, 6000)))


def _rotation(axis, deg):
    return Rotor.from_axis_angle(np.asarray(axis, float) / np.linalg.norm(axis), np.radians(deg)).as_matrix()


def _blob(rng, n, view):
    """``n`` directions of a bumpy closed surface (0.4 across), those a scanner looking along ``-view`` sees."""
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = v[v @ view > -0.1]
    th, ph = np.arctan2(v[:, 1], v[:, 0]), np.arccos(v[:, 2])
    r = 0.2 * (1 + 0.3 * np.sin(3 * th) * np.sin(ph) + 0.2 * np.cos(3 * ph)
               + 0.15 * np.cos(5 * th) * np.sin(ph) ** 2 + 0.1 * v[:, 0])
    return v * r[:, None]


def object_on_a_floor(seed, noise=0.001):
    """A bumpy object on a static floor (larger than the object's share), tilted and moved in the source.

    Each scan sees a little more than half of the object, from views 27° apart.
    Returns source, target, the floor's source rows and the object's motion.
    """
    rng = np.random.default_rng(seed)
    Q = _rotation([1.0, 0.3, 0.0], 70.0)
    dense = _blob(np.random.default_rng(12345), 200000, np.zeros(3))
    up = np.array([0.0, 0.0, -dense[:, 2].min()])  # resting on the floor z = 0
    v = np.array([0.1, -0.05, -(dense @ Q.T)[:, 2].min()])  # tilted, resting on it too
    obj_t = _blob(rng, 4000, np.array([0.0, 1.0, 0.0])) + up
    obj_s = _blob(rng, 4000, np.array([0.5, 1.0, 0.0])) @ Q.T + v
    src = np.vstack([obj_s, _plane(rng, 3000, 0.0) * [0.8, 0.8, 0.0]])
    tgt = np.vstack([obj_t, _plane(rng, 3000, 0.0) * [0.8, 0.8, 0.0]])
    src += rng.normal(0.0, noise, src.shape)
    tgt += rng.normal(0.0, noise, tgt.shape)
    return src, tgt, np.arange(len(obj_s), len(src)), (Q.T, up - Q.T @ v)


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow), pytest.param(2, marks=pytest.mark.slow)])
def test_an_object_on_a_static_floor_is_found(seed):
    # The identity explains the floor; the floor is then no evidence for any later motion: neither
    # searched with the object resting on it, nor in the chance level of the points still unexplained
    # (a floor slides on itself, so random motions counting it beat the object's own support).
    source, target, floor, (R, t) = object_on_a_floor(seed)
    seg = segment(source, target)
    assert [m.info["kind"] for m in seg] == ["identity", "search"]
    assert rotation_error_deg(seg[1].rotation, R) < 1.0 and np.linalg.norm(seg[1].translation - t) < 0.005
    assert np.mean(seg.source_labels[floor] == 0) > 0.9
    for r in seg.info["rounds"][1:]:
        if "chance" in r:  # counted among the points the identity does not explain
            assert r["unexplained"][0] < len(source) - 0.9 * len(floor)
    _labels_match(seg)


def test_a_part_whose_first_search_fails_is_searched_again_with_wider_normal_invariants(monkeypatch):
    """The first search of every part fails (as where the normals at the matching voxel are too far off
    their partners' for the triples' invariants): the part is searched once more at WIDER_NORMALS times
    the tolerance, and the object's motion is found there."""
    import gatv.motions.scans as S

    source, target, floor, (R, t) = object_on_a_floor(0)
    real, tolerances = S.register_part, []

    def narrow_fails(*args, **options):
        tolerances.append(options["feature_tol"])
        if options["feature_tol"] == S.FEATURE_TOL:
            return None, {"reason": "no motion at the first tolerance"}
        return real(*args, **options)

    monkeypatch.setattr(S, "register_part", narrow_fails)
    seg = segment(source, target)
    assert [m.info["kind"] for m in seg] == ["identity", "search"]
    assert seg[1].info["feature_tol"] == S.FEATURE_TOL * S.WIDER_NORMALS
    assert rotation_error_deg(seg[1].rotation, R) < 1.0 and np.linalg.norm(seg[1].translation - t) < 0.005
    assert tolerances[:2] == [S.FEATURE_TOL, S.FEATURE_TOL * S.WIDER_NORMALS]
    first = next(r for r in seg.info["rounds"] if r["kind"] == "search")
    assert first["verdict"] == "none" and first["feature_tol"] == S.FEATURE_TOL
    _labels_match(seg)


def object_in_clutter(seed, share=0.4, noise=0.001):
    """A bumpy object, tilted and moved in the source, in uniform clutter (``share`` of each scan) drawn
    independently in the two scans over the object's box; nothing in the scene is static.

    Returns source, target and the object's motion.
    """
    rng = np.random.default_rng(seed)
    Q = _rotation([1.0, 0.3, 0.2], 50.0)
    obj_t = _blob(rng, 4000, np.array([0.0, 1.0, 0.0]))
    obj_s = _blob(rng, 4000, np.array([0.3, 1.0, 0.0])) @ Q.T + [0.02, -0.01, 0.0]
    n_clutter = int(share / (1.0 - share) * len(obj_t))
    lo, hi = obj_t.min(axis=0) - 0.05, obj_t.max(axis=0) + 0.05
    src = np.vstack([obj_s, rng.uniform(lo, hi, (n_clutter, 3))])
    tgt = np.vstack([obj_t, rng.uniform(lo, hi, (n_clutter, 3))])
    t = -Q.T @ np.array([0.02, -0.01, 0.0])
    return src + rng.normal(0.0, noise, src.shape), tgt + rng.normal(0.0, noise, tgt.shape), (Q.T, t)


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow)])
def test_overlapping_clutter_is_not_a_static_part(seed):
    # The identity keeps the two scans' clutter boxes where they overlap most: it collects more pairs
    # than random motions, which move one box off the other, but no more than itself displaced.
    source, target, (R, t) = object_in_clutter(seed)
    seg = segment(source, target)
    identity = seg.info["rounds"][0]
    assert identity["kind"] == "identity" and identity["verdict"] == "chance"
    assert [m.info["kind"] for m in seg] == ["search"]
    assert rotation_error_deg(seg[0].rotation, R) < 1.0 and np.linalg.norm(seg[0].translation - t) < 0.005
    _labels_match(seg)


def band_of_a_cylinder(seed, noise=0.001):
    """A static floor and, moved in the source only, a quarter band of a cylinder whose target holds all of it."""
    rng = np.random.default_rng(seed)

    def cylinder(n, arc):
        a, z = rng.uniform(0.0, arc, n), rng.uniform(0.0, 0.3, n)
        return np.column_stack([0.1 * np.cos(a), 0.1 * np.sin(a), z])

    band = cylinder(750, np.pi / 2) @ _rotation([1.0, 0.3, 0.2], 60.0).T + [0.2, 0.1, 0.1]
    src = np.vstack([band, _plane(rng, 3000, 0.0)])
    tgt = np.vstack([cylinder(3000, 2 * np.pi) + [-0.2, 0.0, 0.0], _plane(rng, 3000, 0.0)])
    return src + rng.normal(0.0, noise, src.shape), tgt + rng.normal(0.0, noise, tgt.shape)


@pytest.mark.parametrize("seed", [1, *(pytest.param(s, marks=pytest.mark.slow) for s in (2, 3, 4, 5))])
def test_a_self_sliding_part_gives_no_motion(seed):
    # The band slides on the target cylinder (about and along its axis) with all its points: a
    # search over the band alone fits it whole, which random motions over all unexplained points
    # do not show.  The band's own chance level, or the rival motion the search reports, says so.
    source, target = band_of_a_cylinder(seed)
    seg = segment(source, target)
    assert [m.info["kind"] for m in seg] == ["identity"]
    searched = [r for r in seg.info["rounds"] if r["kind"] == "search" and "support" in r]
    assert searched and all(r["verdict"] in ("chance", "ambiguous") for r in searched)


# ---------------------------------------------------------- exact/noisy, fast
def test_exact_scene_keeps_the_graph_grouping():
    from gatv.motions import fig12_scene

    scene = fig12_scene(seed=0, n_outliers=20)
    seg = segment(scene.source, scene.target)
    assert seg.info["pipeline"] == "exact" and seg.info["grouping"] == "graph"
    assert sorted(m.support for m in seg) == [40, 40, 40]
    assert seg.info["reason"]
    _labels_match(seg)


# ------------------------------------------------------------------ slow
def _noisy_scene(seed, k, share, outliers=0.5):
    rng = np.random.default_rng(seed)
    rots, ts = [], []
    for _ in range(k):
        a = rng.normal(size=3)
        rots.append(Rotor.from_axis_angle(a / np.linalg.norm(a), np.radians(rng.uniform(20, 170))).as_matrix())
        ts.append(rng.uniform(-5, 5, 3))
    sizes = [40] * k
    n_out = round(sum(sizes) * outliers / (1 - outliers))
    # noise as a share of each object's RMS radius (points uniform in a 10-cube: 5)
    return multi_motion_scene(rots, ts, sizes, n_outliers=n_out, noise=share * 5.0, seed=rng)


def _check_against_truth(scene, seg, rot_deg, trans):
    assert len(seg) == scene.n_motions
    for m in seg:
        errs = [(rotation_error_deg(m.rotation, R), np.linalg.norm(m.translation - t))
                for R, t in zip(scene.rotations, scene.translations)]
        best = min(errs, key=lambda e: e[0])
        assert best[0] < rot_deg and best[1] < trans
    _labels_match(seg)


@pytest.mark.slow
def test_noisy_three_motions_without_noise_given():
    scene = _noisy_scene(0, 3, 0.01, outliers=0.33)
    seg = segment(scene.source, scene.target)
    assert seg.info["grouping"] == "peel"
    _check_against_truth(scene, seg, 2.0, 0.3)
    for m in seg:  # the noise is measured, not given: target noise 0.05 per axis
        assert 0.02 < m.info["noise"] < 0.1


@pytest.mark.slow
def test_shared_axis_split_under_noise():
    rng = np.random.default_rng(5)
    axis = np.array([1.0, 2.0, -1.0]) / np.sqrt(6.0)
    rots = [Rotor.from_axis_angle(axis, np.radians(a)).as_matrix() for a in (40.0, 110.0)]
    t = rng.uniform(-3, 3, 3)
    scene = multi_motion_scene(rots, [t, t], [50, 50], n_outliers=30, noise=0.05, seed=rng)
    seg = segment(scene.source, scene.target)
    _check_against_truth(scene, seg, 2.0, 0.3)


@pytest.mark.slow
def test_two_real_objects_in_a_scan_scene():
    # Two different objects: a scene holding one scan twice (bun000 as the target of two bunny
    # pairs) is ambiguous by construction, either source object fitting either copy.
    a, b = _bunny("bun000", "bun045"), _uwa("chef")
    scene = scan_scene([a, b], n_points=40000, seed=1)
    seg = segment(scene.source, scene.target)
    assert seg.info["pipeline"] == "scans"
    assert len(seg) == 3  # two objects and the static patch
    assert seg[0].info["kind"] == "identity"
    for m in seg:
        errs = [(rotation_error_deg(m.rotation, R), 1000 * np.linalg.norm(m.translation - t))
                for R, t in zip(scene.rotations, scene.translations)]
        k = int(np.argmin([e[0] + e[1] for e in errs]))
        assert errs[k][0] < 1.0 and errs[k][1] < 3.0
        mine = seg.source_labels == seg.motions.index(m)
        truth = scene.source_labels
        # hardly a point of another motion (an object point its own motion leaves unmatched may lie
        # within the gate of the static patch where the object crosses its old place)
        assert np.mean(np.isin(truth[mine], [k, -1])) > 0.9
        assert np.mean(mine[truth == k]) > 0.8  # most of its own points
    _labels_match(seg)


@pytest.mark.slow
def test_a_noisy_real_scan_scene():
    # Noise of 4% of the bunny's RMS radius (2.3 mm, twice the scene's spacing) on every point of both
    # scenes: the motions were found before the projection too, but 0.8-3.2 degrees and 3.7-9.4 mm off.
    a, b = _bunny("bun000", "bun045"), _uwa("chef")
    scene = scan_scene([a, b], n_points=40000, seed=1)
    rng = np.random.default_rng(9)
    obj = scene.source[scene.source_labels == 0]
    sigma = 0.04 * np.sqrt(((obj - obj.mean(axis=0)) ** 2).sum(axis=1).mean())
    seg = segment(scene.source + rng.normal(0.0, sigma, scene.source.shape),
                  scene.target + rng.normal(0.0, sigma, scene.target.shape))
    assert min(seg.info["projected"]) > 0
    assert 0.8 * sigma < seg.info["noise"] < 1.2 * sigma
    assert len(seg) == 3 and seg[0].info["kind"] == "identity"
    for R, t in zip(scene.rotations, scene.translations):
        errs = [(rotation_error_deg(m.rotation, R), 1000 * np.linalg.norm(m.translation - t)) for m in seg]
        k = int(np.argmin([e[0] + e[1] for e in errs]))
        assert errs[k][0] < 1.0 and errs[k][1] < 3.0
    _labels_match(seg)


@pytest.mark.slow
def test_a_part_searched_in_vain_is_searched_again_after_a_motion_is_kept():
    # bun315 <- bun045 with the chef, seed 0: the bunny's part is searched first, while the chef's
    # target surfaces are still in the pool, and its best motion lays it 161° off (ambiguous).  Once
    # the chef's motion is kept its target points leave the pool, and the bunny searched again is found.
    pairs = [_bunny("bun315", "bun045"), _uwa("chef")]
    scene = scan_scene(pairs, n_points=40000, clutter=0.2, static_patch=0.1, seed=np.random.default_rng(0))
    seg = segment(scene.source, scene.target)
    assert len(seg) == 3 and seg[0].info["kind"] == "identity"
    for k, (R, t) in enumerate(zip(scene.rotations, scene.translations)):
        errs = [(rotation_error_deg(m.rotation, R), 1000 * np.linalg.norm(m.translation - t)) for m in seg]
        assert min(e[0] for e in errs) < 1.0 and min(e[1] for e in errs) < 3.0, k
    verdicts = [r["verdict"] for r in seg.info["rounds"] if r["kind"] == "search"]
    assert verdicts.count("kept") == 2 and verdicts.index("kept") > 0  # one search failed before
    _labels_match(seg)


@pytest.mark.slow
def test_leftovers_of_a_partial_overlap_pair_give_no_extra_motion():
    target, source, R, t = _bunny("bun000", "bun315")  # 91% of the source overlaps
    scene = scan_scene([(target, source, R, t)], n_points=20000, clutter=0.0, static_patch=0.0, seed=4)
    seg = segment(scene.source, scene.target)
    assert len(seg) == 1
    assert rotation_error_deg(seg[0].rotation, scene.rotations[0]) < 1.0
    assert any(r["verdict"] in ("chance", "noise") for r in seg.info["rounds"]) or "no unexplained" in seg.info[
        "reason"]


@pytest.mark.slow
@pytest.mark.parametrize("trial", [2, 19])
def test_three_objects_a_static_patch_and_no_spurious_motion(trial):
    # benchmarks/motions.py's row "scans: bun000<-045 + chef + parasaurolophus" (row 29), seed 0.
    # Trial 19: the chef's part held the static patch, whose slide was kept instead of the chef.
    # Trial 2: once the patch no longer raised the chance level (bb25b04), a 248-point leftover strip
    # of the parasaurolophus that fitted the target whole beat it; the strip's own chance level does not.
    pairs = [_bunny("bun000", "bun045"), _uwa("chef"), _uwa("parasaurolophus")]
    scene = scan_scene(pairs, n_points=40000, clutter=0.2, static_patch=0.1,
                       seed=np.random.default_rng(np.random.SeedSequence([0, 29, trial])))
    seg = segment(scene.source, scene.target)
    assert len(seg) == 4 and seg[0].info["kind"] == "identity"
    matched = set()
    for m in seg:
        errs = [(rotation_error_deg(m.rotation, R), 1000 * np.linalg.norm(m.translation - t))
                for R, t in zip(scene.rotations, scene.translations)]
        k = int(np.argmin([e[0] + e[1] for e in errs]))
        assert errs[k][0] < 1.0 and errs[k][1] < 3.0
        matched.add(k)
    assert matched == {0, 1, 2, 3}
    patch = scene.source_labels == 3
    assert np.mean(seg.source_labels[patch] == 0) > 0.9
    _labels_match(seg)


@pytest.mark.slow
def test_a_leftover_of_clutter_does_not_beat_its_part_level():
    # benchmarks/motions.py's row "scans: bun000<-315 + parasaurolophus +4% noise" (row 28, seed 0,
    # trial 0).  Once both objects are kept, a leftover of 1,133 source points (816 of them clutter,
    # 317 bunny points bun000 does not see) was laid 100 degrees off with 785 pairs: over the best of 64
    # random polished motions of the part (745), not over the best of 256 (793-815 by seed).
    pairs = [_bunny("bun000", "bun315"), _uwa("parasaurolophus")]
    rng = np.random.default_rng(np.random.SeedSequence([0, 28, 0]))
    scene = scan_scene(pairs, n_points=40000, clutter=0.2, static_patch=0.1, seed=rng)
    first = scene.source[scene.source_labels == 0]
    sigma = 0.04 * float(np.sqrt(((first - first.mean(axis=0)) ** 2).sum(axis=1).mean()))
    seg = segment(scene.source + rng.normal(0.0, sigma, scene.source.shape),
                  scene.target + rng.normal(0.0, sigma, scene.target.shape))
    assert len(seg) == 3 and seg[0].info["kind"] == "identity"
    for R, t in zip(scene.rotations, scene.translations):
        errs = [(rotation_error_deg(m.rotation, R), 1000 * np.linalg.norm(m.translation - t)) for m in seg]
        k = int(np.argmin([e[0] + e[1] for e in errs]))
        assert errs[k][0] < 1.0 and errs[k][1] < 3.0
    assert any(r["verdict"] == "chance" and r["chance"] < r["support"] <= r["part_chance"]
               for r in seg.info["rounds"] if "part_chance" in r)
    _labels_match(seg)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1002, 1004, 1008])
def test_every_motion_of_a_cluttered_real_scene_is_found(seed):
    # 20,000 points a scene and 30% clutter: the chef's and the bunny's normals at the matching voxel
    # are 15-23 degrees off their partners' (7-10 on the benchmark's 40,000-point scenes).  With the
    # vote keeping only each scan's densest surfaces (the paper's threshold alone) these seeds found 4,
    # 2 and 3 of the 4 motions, the first two after a search at the wider normal invariants; with
    # PLANAR_CHANCE all four at the first tolerance (/work/bench/s37/wider.py, seeds 1000-1008).
    pairs = [_bunny("bun000", "bun315"), _uwa("chef"), _uwa("parasaurolophus")]
    scene = scan_scene(pairs, n_points=20000, clutter=0.3, static_patch=0.1, seed=np.random.default_rng(seed))
    seg = segment(scene.source, scene.target)
    assert len(seg) == 4 and seg[0].info["kind"] == "identity"
    for m in seg:  # every motion reported is a true one, each once
        errs = [(rotation_error_deg(m.rotation, R), 1000 * np.linalg.norm(m.translation - t))
                for R, t in zip(scene.rotations, scene.translations)]
        k = int(np.argmin([e[0] + e[1] for e in errs]))
        assert errs[k][0] < 1.0 and errs[k][1] < 3.0
    assert seg.info["ambiguous"] == []
    _labels_match(seg)


def test_a_part_ambiguous_at_both_tolerances_is_reported_ambiguous_once(monkeypatch):
    """The object's part has a rival at both normal tolerances (made so here): its second search's
    verdict replaces its first's, so ``info["ambiguous"]`` lists it once."""
    import gatv.motions.scans as S

    source, target, floor, (R, t) = object_on_a_floor(0)
    real = S.register_part

    def with_a_rival(*args, **options):
        found, info = real(*args, **options)
        return found, dict(info, ambiguous=True, rival={"angle_deg": 180.0})

    monkeypatch.setattr(S, "register_part", with_a_rival)
    seg = segment(source, target)
    assert [m.info["kind"] for m in seg] == ["identity"]
    searched = [r for r in seg.info["rounds"] if r["kind"] == "search"]
    tolerances = [r["feature_tol"] for r in searched if r["verdict"] == "ambiguous"]
    assert S.FEATURE_TOL in tolerances and S.FEATURE_TOL * S.WIDER_NORMALS in tolerances
    assert len(seg.info["ambiguous"]) == 1
    centroids = np.array([a["centroid"] for a in seg.info["ambiguous"]])
    assert np.linalg.norm(centroids[0] - source[:-len(floor)].mean(axis=0)) < 0.2  # the object's part


# ------------------------------------------------------------------ CLI
def test_cli_labelled_ply(tmp_path):
    from gatv import cli
    from gatv.motions import fig12_scene

    scene = fig12_scene(seed=0)
    src, tgt = tmp_path / "s.xyz", tmp_path / "t.xyz"
    np.savetxt(src, scene.source)
    np.savetxt(tgt, scene.target)
    out, lab = tmp_path / "r.json", tmp_path / "labelled.ply"
    assert cli.main(["segment", str(src), str(tgt), "--out", str(out), "--labelled", str(lab), "-q"]) == 0
    raw = lab.read_bytes()
    head, body = raw.split(b"end_header\n", 1)
    assert b"property int motion" in head
    assert b"property uchar red" in head  # each motion's colour, which PyVista shows (it drops `motion`)
    rows = np.frombuffer(body, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("motion", "<i4"),
                                      ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    assert np.allclose(np.column_stack([rows["x"], rows["y"], rows["z"]]), scene.source, atol=1e-5)
    import json

    record = json.loads(out.read_text())
    assert rows["motion"].tolist() == record["source_labels"]
    assert sorted(np.bincount(rows["motion"][rows["motion"] >= 0]).tolist()) == [40, 40, 40]
    assert cli.main(["segment", str(src), str(tgt), "--labelled", str(tmp_path / "x.txt"), "-q"]) == 2
