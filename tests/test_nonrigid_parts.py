"""Articulated motions: seeds in every part, local gates, near-rigid parts and their joints."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from gatv.candidates import median_spacing
from gatv.ga import Rotor
from gatv.nonrigid import multiscale as ms
from gatv.nonrigid import register
from gatv.nonrigid.deformations import two_link_arm
from gatv.nonrigid.parts import MIN_CONTACTS, Part, joint, parts_info, rigid_parts

BODY = Path(__file__).resolve().parents[2] / "shared" / "data" / "nonrigid_bcpd_human"


def _angle_between(R1, R2) -> float:
    return float(np.degrees(Rotor.from_matrix(np.asarray(R1).T @ np.asarray(R2)).angle))


# ------------------------------------------------------------ kernels against numpy references
def _local_gates_reference(y, gate, floor, k=8):
    d = np.linalg.norm(y[:, None] - y[None], axis=2)
    np.fill_diagonal(d, np.inf)
    d1 = d.min(axis=1)
    np.fill_diagonal(d, 0.0)
    local = np.array([np.median(d1[np.argsort(d[j], kind="stable")[:k]]) for j in range(len(y))])
    lo, hi = np.percentile(local, [10, 90])
    if hi <= ms.SAMPLING_CONTRAST * lo:
        return np.full(len(y), gate)
    return np.maximum(ms.LOCAL_GATE_MIN * gate, 0.5 * local + floor)


def test_local_gates_match_a_loop_over_rows():
    rng = np.random.default_rng(0)
    # a sparse part and a part 25 times denser: the local gate follows the local spacing
    y = np.vstack([rng.uniform(0, 10, (300, 3)) * [1, 1, 0], rng.uniform(10, 12, (300, 3)) * [1, 1, 0]])
    gate, floor = 0.1, 0.01
    got = ms.local_gates(y, cKDTree(y), gate, floor)
    np.testing.assert_allclose(got, _local_gates_reference(y, gate, floor), rtol=1e-12)
    assert np.median(got[:300]) > 2 * np.median(got[300:])
    # sampled about uniformly: one gate, as before local gates
    u = rng.uniform(0, 10, (600, 3)) * [1, 1, 0]
    got = ms.local_gates(u, cKDTree(u), gate, floor)
    np.testing.assert_array_equal(got, np.full(600, gate))
    np.testing.assert_allclose(got, _local_gates_reference(u, gate, floor))


def test_growth_never_takes_rows_another_part_holds():
    x = two_link_arm(400, seed=3).source
    y = x + [0.3, 0.0, 0.0]
    tree_y = cKDTree(y)
    h = median_spacing(y)
    used_s = np.zeros(len(x), bool)
    used_t = np.zeros(len(y), bool)
    used_s[:150] = True
    used_t[150:200] = True  # the partners of rows 150-199 are taken
    seeds = np.array([[i, i] for i in range(250, 256)])
    grown = ms.grow(x, y, tree_y, seeds, 0.4 * h, used_source=used_s, used_target=used_t)
    assert not np.any(used_s[grown[:, 0]]) and not np.any(used_t[grown[:, 1]])
    assert len(np.unique(grown[:, 0])) == len(grown) == len(np.unique(grown[:, 1]))
    free = ~used_s & ~np.isin(np.arange(len(x)), np.arange(150, 200))
    assert np.mean(grown[:, 0] == grown[:, 1]) == 1.0
    assert len(grown) >= 0.9 * free.sum()


# ------------------------------------------------------------ joints
@settings(max_examples=30, deadline=None)
@given(st.floats(5.0, 120.0), st.floats(-1, 1), st.floats(-1, 1), st.floats(0.1, 1),
       st.floats(-5, 5), st.floats(-5, 5), st.floats(-5, 5))
def test_joint_of_two_motions_sharing_an_axis_lies_on_it(angle, ax, ay, az, cx, cy, cz):
    axis = np.array([ax, ay, az]) / np.linalg.norm([ax, ay, az])
    centre = np.array([cx, cy, cz])
    Ra = Rotor.from_axis_angle([0.3, -0.2, 0.9], 0.4).as_matrix()
    ta = np.array([1.0, 2.0, -1.0])
    Rrel = Rotor.from_axis_angle(axis, np.radians(angle)).as_matrix()
    # part b: first turn about the axis through the centre, then part a's motion
    Rb, tb = Ra @ Rrel, Ra @ (centre - Rrel @ centre) + ta
    boundary = centre + np.random.default_rng(0).normal(scale=0.5, size=(20, 3))
    j = joint(Part(np.arange(3), Ra, ta, 0.0), Part(np.arange(3), Rb, tb, 0.0), boundary)
    assert j["gap"] < 1e-8
    assert abs(j["angle_deg"] - angle) < 1e-6
    assert abs(abs(np.dot(j["axis"], axis)) - 1.0) < 1e-9
    c = np.asarray(j["centre"])
    off = (c - centre) - np.dot(c - centre, axis) * axis  # distance from the axis line
    assert np.linalg.norm(off) < 1e-7


def test_parts_of_the_two_link_arm_from_its_true_pairs():
    arm = two_link_arm(600, angles=(30.0, 45.0), seed=0)
    parts, joints, labels = parts_info(arm.source, arm.target, spacing=median_spacing(arm.target))
    assert len(parts) == 2 and len(joints) == 1
    for k, p in enumerate(parts):
        link = np.bincount(arm.labels[labels == k]).argmax()
        assert _angle_between(p["rotation"], arm.rotations[link]) < 0.5
        assert np.mean(arm.labels[labels == k] == link) > 0.97
    j = joints[0]
    assert abs(abs(j["axis"][2]) - 1.0) < 1e-3 and abs(j["angle_deg"] - 45.0) < 0.5
    assert np.hypot(j["centre"][0] - arm.joints[1][0], j["centre"][1] - arm.joints[1][1]) < 0.1
    # one rigid motion: one part, no joint
    one = rigid_parts(arm.source, arm.source @ arm.rotations[0].T + arm.translations[0],
                      tolerance=0.01, seed=0)
    assert len(one) == 1 and one[0].rows.size == 600


# ------------------------------------------------------------ end to end
@pytest.fixture(scope="module")
def arm_result():
    arm = two_link_arm(400, angles=(30.0, 45.0), seed=1)
    perm = np.random.default_rng(7).permutation(400)
    return arm, perm, register(arm.source, arm.target[perm], seed=0)


def test_register_finds_both_links_of_the_arm_and_their_rotations(arm_result):
    arm, perm, m = arm_result
    inv = np.argsort(perm)
    c = m.correspondences
    ok = inv[c[:, 0]] == c[:, 1]
    assert ok.mean() >= 0.99
    for link in (0, 1):  # each link matched, not only the first window's
        rows = arm.labels[c[:, 0]] == link
        assert ok[rows].sum() >= 0.9 * np.sum(arm.labels == link)
    parts = m.info["parts"]
    assert len(parts) >= 2
    angles = sorted(_angle_between(np.eye(3), p["rotation"]) for p in parts[:2])
    assert abs(angles[0] - 30.0) < 1.0 and abs(angles[1] - 75.0) < 1.0
    assert len(m.info["joints"]) >= 1
    assert abs(m.info["joints"][0]["angle_deg"] - 45.0) < 1.0
    labels = m.info["part_labels"]
    assert labels.shape == (c.shape[0],)


@pytest.mark.slow
def test_register_same_seed_same_parts(arm_result):
    arm, perm, m = arm_result
    again = register(arm.source, arm.target[perm], seed=0)
    assert np.array_equal(again.correspondences, m.correspondences)
    assert again.info["parts"] == m.info["parts"] and again.info["joints"] == m.info["joints"]
    assert np.array_equal(again.info["part_labels"], m.info["part_labels"])


def test_parts_info_same_seed_same_result():
    arm = two_link_arm(500, seed=4)
    a = parts_info(arm.source, arm.target, spacing=median_spacing(arm.target), seed=3)
    b = parts_info(arm.source, arm.target, spacing=median_spacing(arm.target), seed=3)
    assert a[0] == b[0] and a[1] == b[1] and np.array_equal(a[2], b[2])


@pytest.mark.slow
@pytest.mark.skipif(not (BODY / "female-x.txt").is_file(), reason="shared data absent")
def test_articulated_body_sampled_80_80_recall():
    x = np.loadtxt(BODY / "female-x.txt")
    y = np.loadtxt(BODY / "female-y.txt")
    rng = np.random.default_rng(11)
    n, k = len(x), round(0.8 * len(x))
    xr = np.sort(rng.choice(n, k, replace=False))
    yr = np.sort(rng.choice(n, k, replace=False))
    ps, pt = rng.permutation(k), rng.permutation(k)
    m = register(x[xr][ps], y[yr][pt], seed=0)
    c = m.correspondences
    src, tgt = xr[ps][c[:, 0]], yr[pt][c[:, 1]]
    shared = np.intersect1d(xr, yr).size
    assert np.sum(src == tgt) / shared >= 0.9  # exact recall of the rows both sets share
    h = median_spacing(y[yr])
    assert np.mean(np.linalg.norm(y[tgt] - y[src], axis=1) <= h) >= 0.95
    # the arms turn by about 50° at the shoulders: parts that turn are reported, and a joint between
    # the torso (near 0°) and a turned part, where the two motions move the centre alike within a
    # spacing (the shoulder blends; the elbows' gaps are under a tenth of a spacing)
    parts = m.info["parts"]
    assert any(p["angle_deg"] > 30.0 for p in parts)
    assert any(j["gap"] < h and min(parts[i]["angle_deg"] for i in j["parts"]) < 5.0
               and max(parts[i]["angle_deg"] for i in j["parts"]) > 30.0 for j in m.info["joints"])


def test_part_windows_join_a_limb_at_its_joint_but_not_a_second_body():
    from gatv.nonrigid.parts import seed_parts

    arm = two_link_arm(500, angles=(20.0, 50.0), seed=5)
    far = arm.source + [0.0, 40.0, 0.0]  # a second body, 40 units away, with its own rigid motion
    far_moved = far @ Rotor.from_axis_angle([1, 0, 0], 0.7).as_matrix().T + [3.0, 1.0, 0.0]
    X = np.vstack([arm.source, far])
    Y = np.vstack([arm.target, far_moved])
    n = len(arm.source)
    first = np.flatnonzero(arm.labels == 0)
    pairs = np.column_stack([first, first])  # the first link, as the first growth leaves it
    rows = np.arange(len(X))
    h = median_spacing(Y)
    found = seed_parts(X, Y, cKDTree(X), cKDTree(Y), rows, rows, pairs, gate=0.2 * h, spacing=h,
                       spacing_x=median_spacing(X), least=0.1 * n, seed=0)
    got = found.pairs
    assert np.all(got[:, 0] == got[:, 1])  # every match right
    assert np.all(got[:, 0] < n)  # nothing on the second body
    assert np.sum(arm.labels[got[:, 0]] == 1) >= 0.9 * np.sum(arm.labels == 1)  # the second link joined
    assert found.growth.max() == 1
    kept = [w for w in found.windows if w.get("kept")]
    # joined where it meets the first link continuously (the first link's local motions carry across
    # the joint, 30° apart), or else at a hinge whose two motions share the joint
    assert len(kept) == 1
    assert kept[0]["contacts"] >= MIN_CONTACTS or (kept[0].get("hinge_gap") is not None
                                                   and kept[0]["hinge_gap"] < 0.2 * h)
    # the second body met nothing and was no hinge
    assert all(w["contacts"] < MIN_CONTACTS for w in found.windows if not w.get("kept") and "contacts" in w)


def test_neighbour_pairs_are_the_radius_pairs_on_a_uniform_sampling_and_reach_sparse_rows():
    from gatv.nonrigid.deformations import sample_plane

    p = sample_plane(300, 10.0, seed=2)
    r = 3.0 * median_spacing(p)
    a, b = ms.neighbour_pairs(p, r)
    ref = cKDTree(p).query_pairs(r, output_type="ndarray")
    assert np.array_equal(np.column_stack([a, b]), ref)
    # a strip sampled at 0.1 (630 rows) and at 0.5 (175 rows): every sparse row gets a neighbour
    g = np.mgrid[0:3:0.1, 0:2.05:0.1].reshape(2, -1).T
    s = np.mgrid[3:20:0.5, 0:2.05:0.5].reshape(2, -1).T
    q = np.column_stack([np.vstack([g, s]), np.zeros(len(g) + len(s))])
    a, b = ms.neighbour_pairs(q, 3.0 * median_spacing(q))
    linked = np.zeros(len(q), bool)
    linked[a] = linked[b] = True
    assert linked.all()
    assert np.all(np.linalg.norm(q[a] - q[b], axis=1) <= 1.5 + 1e-9)  # three sparse spacings at most


def test_segment_labels_each_row_with_the_part_of_its_match():
    from gatv.nonrigid import deformations as D
    from gatv.nonrigid import segment

    a = D.sample_plane(100, 10.0, seed=0)
    b = a + [14.0, 0, 0]
    seg = segment(np.vstack([a, b]), np.vstack([D.twist(a, 45.0), D.bend(b, 60.0) + [0, 0, 3]]))
    assert len(seg) == 2
    sp, tp = seg.info["source_parts"], seg.info["target_parts"]
    matched = np.zeros(200, bool)
    for mo in seg.motions:
        labels = np.asarray(mo.info["part_labels"])
        assert labels.shape == (mo.support,)
        assert np.array_equal(sp[mo.correspondences[:, 0]], labels)
        assert np.array_equal(tp[mo.correspondences[:, 1]], labels)
        assert labels.max() < len(mo.info["parts"])
        matched[mo.correspondences[:, 0]] = True
    assert np.all(sp[~matched] == -1)


def test_contacts_reach_across_a_sparse_boundary_and_not_across_a_jump():
    from gatv.nonrigid.parts import contacts

    # dense rows (0.1) for x < 3, sparse (0.5) beyond; the sparse rows are the new part
    g = np.mgrid[0:3:0.1, 0:2.05:0.1].reshape(2, -1).T
    s = np.mgrid[3:20:0.5, 0:2.05:0.5].reshape(2, -1).T
    X = np.column_stack([np.vstack([g, s]), np.zeros(len(g) + len(s))])
    old = np.column_stack([np.arange(len(g))] * 2)
    new = np.column_stack([np.arange(len(g), len(X))] * 2)
    moved = X @ Rotor.from_axis_angle([0, 0, 1], 0.1).as_matrix().T + [0.3, 0.1, 0.0]
    # the three sparse columns within three sparse spacings of the dense edge meet it (5 rows each,
    # less the corners beyond 1.5): more than three median spacings (0.3) reach
    n = contacts(X, moved, old, new, 0.35, 0.05)
    assert n >= 10
    # the sparse part moved 2 units off: no contact
    jumped = moved.copy()
    jumped[len(g):] += [0.0, 0.0, 2.0]
    assert contacts(X, jumped, old, new, 0.35, 0.05) == 0


@given(angle=st.floats(30.0, 180.0), ax=st.floats(-1, 1), ay=st.floats(-1, 1), az=st.floats(0.1, 1))
@settings(max_examples=20, deadline=None)
def test_contacts_of_a_shape_turned_as_a_whole_do_not_depend_on_the_turn(angle, ax, ay, az):
    """Two halves of one plane turned as a whole by any angle meet along their whole boundary, as
    they do unturned (lengths are compared: displacements of neighbours differ by 2 sin(θ/2) |Δx|,
    over the 0.35 strain beyond about 20°); the same halves pulled apart by two units do not."""
    from gatv.nonrigid.deformations import sample_plane
    from gatv.nonrigid.parts import contacts

    X = sample_plane(400, 10.0, seed=4)
    left = np.flatnonzero(X[:, 0] < 0.0)
    right = np.flatnonzero(X[:, 0] >= 0.0)
    old, new = np.column_stack([left, left]), np.column_stack([right, right])
    h = median_spacing(X)
    turned = X @ Rotor.from_axis_angle([ax, ay, az], np.radians(angle)).as_matrix().T + [5.0, -2.0, 1.0]
    still = contacts(X, X, old, new, 0.35, 0.2 * h)
    assert still >= 10
    assert contacts(X, turned, old, new, 0.35, 0.2 * h) == still
    # pulled apart by two units, or slid along the plane by two units (lengths alone would pass
    # the slide towards the old half, as long as twice the reach)
    for shift in ([0.0, 0.0, 2.0], [-2.0, 0.0, 0.0]):
        moved = X.copy()
        moved[right] += shift
        moved = moved @ Rotor.from_axis_angle([ax, ay, az], np.radians(angle)).as_matrix().T
        assert contacts(X, moved, old, new, 0.35, 0.2 * h) == 0
