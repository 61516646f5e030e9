"""The scans pipeline's numba kernels (:mod:`gatv._icp_kernels`) against their numpy references."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from gatv._fit_kernels import kabsch3
from gatv._icp_kernels import (
    _cholesky_solve,
    _kdtree_build,
    _kdtree_build_serial,
    _median,
    _plane_step,
    _stops,
    bounding_box,
    KDTree,
    kdtree_build,
    kdtree_nearest2,
    kdtree_query,
    neighbourhood_axes,
    neighbourhood_noise,
    neighbourhood_normals,
    nearest_heights,
    nearest_kept,
    occupied_cells,
    pairing_state,
    plane_icp,
    plane_icp_many,
    plane_icp_parallel,
    rotvec_matrix,
    screen_icp,
)
from gatv.ga import Rotor
from gatv.models.rigid.congruent import TargetGrid
from gatv.scans import aligning_rotation, point_icp, refine_point_to_plane


def _surface(rng, n, noise=0.0):
    """A bumpy sheet of ``n`` points with its unit normals."""
    u, v = rng.uniform(-1.0, 1.0, (2, n))
    z = 0.3 * np.sin(2.0 * u) * np.cos(3.0 * v)
    normals = np.stack([-0.6 * np.cos(2.0 * u) * np.cos(3.0 * v), 0.9 * np.sin(2.0 * u) * np.sin(3.0 * v),
                        np.ones(n)], axis=1)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    pts = np.stack([u, v, z], axis=1) + rng.normal(0.0, noise, (n, 3))
    return pts, normals


def _pair(rng, n_target, n_source, noise, angle, shift):
    """A target sheet with its normals, a source sheet sampled apart, and a motion of about ``angle``
    degrees about a random axis and a translation of ``shift`` per axis: ``(Y, N, X, R, t)``."""
    Y, N = _surface(rng, n_target, noise)
    X = _surface(rng, n_source, noise)[0]
    R = Rotation.from_rotvec(rng.normal(size=3) * np.deg2rad(angle) / np.sqrt(3)).as_matrix()
    return Y, N, X, R, rng.normal(0.0, shift, 3)


def reference_plane_icp(source, target, target_normals, rotation, translation, gate, iterations=30, tol=1e-9,
                        stall=0.0):
    """The numpy point-to-plane ICP that :func:`gatv._icp_kernels.plane_icp` replaces (scipy's k-d tree)."""
    tree = cKDTree(target)
    R = np.array(rotation, dtype=np.float64)
    t = np.array(translation, dtype=np.float64)
    huber = 0.3 * gate
    last = np.inf
    for _ in range(iterations):
        moved = source @ R.T + t
        dist, j = tree.query(moved, k=1, distance_upper_bound=gate)
        ok = np.isfinite(dist)
        if ok.sum() < 6:
            break
        p, q, n = moved[ok], target[j[ok]], target_normals[j[ok]]
        c = p.mean(axis=0)
        r = np.einsum("ij,ij->i", p - q, n)
        w = np.where(np.abs(r) <= huber, 1.0, huber / np.maximum(np.abs(r), 1e-300))
        A = np.hstack([np.cross(p - c, n), n]) * np.sqrt(w)[:, None]
        b = -r * np.sqrt(w)
        x, *_ = np.linalg.lstsq(np.einsum("ij,ik->jk", A, A), np.einsum("ij,i->j", A, b), rcond=None)
        omega, delta = x[:3], x[3:]
        Rinc = Rotor.from_rotvec(omega).as_matrix()
        R = Rinc @ R
        t = Rinc @ (t - c) + c + delta
        step = (np.linalg.norm(omega) * np.abs(p - c).max() + np.linalg.norm(delta)) / gate
        # Converged, or stalled: a small step that did not halve the one before.
        if step < tol or 0.5 * last < step < stall:
            break
        last = step
    return R, t


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 400), radius=st.floats(0.01, 3.0),
       duplicates=st.booleans(), leaf=st.integers(1, 20))
def test_kdtree_finds_the_nearest_point_within_the_bound_as_scipy(seed, n, radius, duplicates, leaf):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3))
    if duplicates:  # repeated points and a flat coordinate: splits on ties
        pts = np.vstack([pts, pts[: n // 2]])
        pts[:, 2] = np.round(pts[:, 2], 1)
    queries = rng.normal(scale=1.5, size=(300, 3))
    tree = KDTree(pts, leafsize=leaf)
    d_ref, j_ref = cKDTree(pts).query(queries, k=1, distance_upper_bound=radius)
    d, j = tree.query(queries, k=1, distance_upper_bound=radius)
    assert np.array_equal(np.isfinite(d), np.isfinite(d_ref))
    hit = np.isfinite(d_ref)
    # The same distance (ties may pick another of several equally near points).
    np.testing.assert_allclose(d[hit], d_ref[hit], rtol=0, atol=1e-12)
    assert np.all(j[~hit] == pts.shape[0])
    assert np.allclose(np.linalg.norm(queries[hit] - pts[j[hit]], axis=1), d_ref[hit], atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 400), radius=st.floats(0.01, 3.0), leaf=st.integers(1, 20))
def test_nearest_heights_are_heights_over_the_nearest_points_plane(seed, n, radius, leaf):
    """Each queried row's height over its nearest tree point's plane, as cKDTree and numpy give it; inf with
    no tree point within the radius."""
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3))
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    points = rng.normal(scale=1.5, size=(500, 3))
    rows = np.sort(rng.choice(500, 300, replace=False))
    tree = KDTree(pts, leafsize=leaf)
    h = nearest_heights(points, rows, normals, tree.points, *tree.nodes, radius)
    d, j = cKDTree(pts).query(points[rows], k=1, distance_upper_bound=radius)
    hit = np.isfinite(d)
    assert np.array_equal(np.isfinite(h), hit)
    # The nearest point may be another of several as near (a tie): its plane is then checked by distance.
    k = tree.nearest(points[rows], radius)
    assert np.allclose(np.linalg.norm(points[rows][hit] - pts[k[hit]], axis=1), d[hit], atol=1e-12)
    ref = np.abs(np.einsum("ij,ij->i", points[rows][hit] - pts[k[hit]], normals[k[hit]]))
    np.testing.assert_allclose(h[hit], ref, rtol=0, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 6000), frontier=st.integers(1, 64),
       duplicates=st.floats(0.0, 0.9), leaf=st.integers(1, 32))
def test_kdtree_grown_in_parallel_is_the_serial_tree(seed, n, frontier, duplicates, leaf):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3))
    pts[: int(duplicates * n)] = pts[0]
    serial = _kdtree_build_serial(pts, leaf)
    order, lo, hi, axis, split, left, right = _kdtree_build(pts, leaf, frontier)
    np.testing.assert_array_equal(order, serial[0])

    def shape(nodes, k=0):  # the tree from node k, whatever the numbering: (lo, hi, axis, split, children)
        o, lo, hi, axis, split, left, right = nodes
        if axis[k] < 0:
            return (lo[k], hi[k])
        return (lo[k], hi[k], axis[k], split[k], shape(nodes, left[k]), shape(nodes, right[k]))

    assert shape((order, lo, hi, axis, split, left, right)) == shape(serial)
    # Numbers no node points to are empty leaves.
    reached = np.zeros(lo.size, bool)
    reached[0] = True
    reached[left[axis >= 0]] = reached[right[axis >= 0]] = True
    assert np.all(axis[~reached] == -1) and np.all(hi[~reached] == lo[~reached])


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 500), scale=st.floats(1e-3, 1e6))
def test_bounding_box_is_numpys_least_and_greatest_coordinates(seed, n, scale):
    pts = np.random.default_rng(seed).normal(0.0, scale, (n, 3))
    np.testing.assert_array_equal(bounding_box(pts), np.stack([pts.min(axis=0), pts.max(axis=0)]))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 40), opposite=st.integers(0, 40))
def test_aligning_rotations_of_rows_are_each_rows_own(seed, n, opposite):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, 3))
    a /= np.linalg.norm(a, axis=1)[:, None]
    b = rng.normal(size=(n, 3))
    b /= np.linalg.norm(b, axis=1)[:, None]
    b[:opposite] = -a[:opposite]  # the half-turn's branch
    Rs = aligning_rotation(a, b)
    for R, u, v in zip(Rs, a, b):
        np.testing.assert_allclose(R, aligning_rotation(u, v), atol=1e-15)
        np.testing.assert_allclose(R @ u, v, atol=1e-12)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)


def test_kdtree_nodes_partition_the_points():
    pts = np.random.default_rng(3).normal(size=(1000, 3))
    order, lo, hi, axis, split, left, right = kdtree_build(pts, 16)
    assert sorted(order) == list(range(1000))
    leaves = axis < 0
    assert np.all(hi[leaves] - lo[leaves] <= 16)
    # The leaves tile the order once; every inner node's children split it at the split value.
    assert (hi[leaves] - lo[leaves]).sum() == 1000
    for k in np.flatnonzero(~leaves):
        a = axis[k]
        assert np.all(pts[order[lo[left[k]]:hi[left[k]]], a] <= split[k])
        assert np.all(pts[order[lo[right[k]]:hi[right[k]]], a] >= split[k])


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 300), k=st.one_of(st.integers(2, 20), st.integers(30, 90),
                                                                           st.integers(120, 200)),
       radius=st.sampled_from([0.3, 1.0, np.inf]), duplicates=st.booleans(), leaf=st.integers(1, 20))
def test_kdtree_k_nearest_are_scipys(seed, n, k, radius, duplicates, leaf):
    # k from KNN_HEAP (128) on: the nearest found so far kept in a heap, not a sorted list.
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3))
    if duplicates:
        pts = np.vstack([pts, pts[: n // 2]])
        pts[:, 2] = np.round(pts[:, 2], 1)
    queries = np.vstack([pts[:50], rng.normal(scale=1.5, size=(100, 3))])
    d, j = KDTree(pts, leafsize=leaf).query(queries, k=k, distance_upper_bound=radius)
    d_ref, j_ref = cKDTree(pts).query(queries, k=k, distance_upper_bound=radius)
    assert d.shape == j.shape == (queries.shape[0], k)
    # The same distances, nearest first, and as many found; ties may pick other equally near points.
    assert np.array_equal(np.isfinite(d), np.isfinite(d_ref))
    hit = np.isfinite(d_ref)
    np.testing.assert_allclose(d[hit], d_ref[hit], rtol=0, atol=1e-12)
    assert np.all(j[~hit] == pts.shape[0])
    rows = np.nonzero(hit)[0]
    assert np.allclose(np.linalg.norm(queries[rows] - pts[j[hit]], axis=1), d_ref[hit], atol=1e-12)
    # Distinct points in each row.
    assert all(len(set(r[f])) == int(f.sum()) for r, f in zip(j, hit))


def test_kdtree_rejects_a_k_that_is_not_a_positive_integer():
    tree = KDTree(np.random.default_rng(4).normal(size=(20, 3)))
    for k in (0, 1.5, True):
        with pytest.raises(ValueError, match="`k`"):
            tree.query(np.zeros((1, 3)), k=k)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), m=st.integers(3, 16), flat=st.floats(1e-4, 1.0))
def test_neighbourhood_normals_are_the_local_planes(seed, m, flat):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(500, 3)) * np.array([1.0, 0.5, flat])
    neighbours = cKDTree(pts).query(pts, k=m)[1]
    got = neighbourhood_normals(pts, neighbours, m)
    # numpy reference: the least-variance axis of each neighbourhood's scatter (as local_scatter)
    local = pts[neighbours] - pts[neighbours].mean(axis=1, keepdims=True)
    values, axes = np.linalg.eigh(np.matmul(local.transpose(0, 2, 1), local))
    want = axes[:, :, 0]
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-12)
    # Up to sign; where the two least variances nearly tie, the axis is not defined: compare the variance.
    var = np.einsum("nki,ni->nk", local, got)
    np.testing.assert_allclose((var ** 2).sum(axis=1), values[:, 0], rtol=1e-8, atol=1e-12 * values[:, 2].max())
    # An eigenvector is good to about eps * |scatter| / gap: 1e-9 of the largest variance keeps it within 1e-6
    # (three points nearly on a line leave the two least variances both near 0).
    clear = values[:, 1] - values[:, 0] > 0.01 * values[:, 0] + 1e-9 * values[:, 2]
    assert clear.mean() > 0.5
    np.testing.assert_allclose(np.abs((got * want).sum(axis=1))[clear], 1.0, atol=1e-6)


def _noise_reference(pts, neighbours, radius, quadric):
    """numpy reference of :func:`neighbourhood_noise`: the residuals about each neighbourhood's plane, or
    about the least-squares quadric over its tangent plane, in ``eigh``'s axes (as ``scan_noise`` fitted)."""
    m = neighbours.shape[1]
    local = pts[neighbours] - pts[neighbours].mean(axis=1, keepdims=True)
    _, vec = np.linalg.eigh(np.matmul(local.transpose(0, 2, 1), local))
    height = np.einsum("nki,ni->nk", local, vec[:, :, 0])
    if quadric:
        scale = np.maximum(radius, 1e-300)[:, None]
        u = np.einsum("nki,ni->nk", local, vec[:, :, 2]) / scale
        v = np.einsum("nki,ni->nk", local, vec[:, :, 1]) / scale
        A = np.stack([u * u, u * v, v * v, u, v, np.ones_like(u)], axis=-1)
        AtA = np.einsum("nki,nkj->nij", A, A) + 1e-9 * np.eye(6)
        coef = np.linalg.solve(AtA, np.einsum("nki,nk->ni", A, height / scale)[..., None])[..., 0]
        height = height - scale * np.einsum("nki,ni->nk", A, coef)
    params = 6 if quadric else 3
    return 1.4826 * np.median(np.abs(height), axis=1) * np.sqrt(m / max(m - params, 1))


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), m=st.integers(8, 64), noise=st.floats(1e-4, 0.1), quadric=st.booleans())
def test_neighbourhood_noise_is_the_residuals_about_the_local_fit(seed, m, noise, quadric):
    rng = np.random.default_rng(seed)
    pts, _ = _surface(rng, 800, noise)
    queries = pts[rng.choice(800, 100, replace=False)]
    radius, neighbours = cKDTree(pts).query(queries, k=m)
    radius = radius[:, -1]
    centroids, values, axes = neighbourhood_axes(pts, neighbours, m)
    np.testing.assert_allclose(centroids, pts[neighbours].mean(axis=1), rtol=0, atol=1e-14)
    assert np.all(np.diff(values, axis=1) <= 0.0)  # descending
    got = neighbourhood_noise(pts, neighbours, m, centroids, axes, radius, quadric)
    want = _noise_reference(pts, neighbours, radius, quadric)
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 300), levels=st.integers(1, 1000))
def test_median_kernel_is_numpys(seed, n, levels):
    """The selection median of :func:`neighbourhood_noise` against ``np.median``, ties included."""
    a = np.random.default_rng(seed).integers(0, levels, n) * 0.37
    assert _median(a.copy()) == np.median(a)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 8), ridge=st.floats(1e-9, 1.0))
def test_cholesky_kernel_solves_as_numpy(seed, n, ridge):
    rng = np.random.default_rng(seed)
    B = rng.normal(size=(3 * n, n))
    A = B.T @ B + ridge * np.eye(n)
    b = rng.normal(size=n)
    np.testing.assert_allclose(A @ _cholesky_solve(A, b), b, rtol=0, atol=1e-8 * np.linalg.cond(A))
    np.testing.assert_allclose(_cholesky_solve(A, b), np.linalg.solve(A, b), rtol=1e-6, atol=1e-9 * np.linalg.cond(A))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 3000), cell=st.floats(1e-3, 50.0),
       spread=st.floats(1e-2, 1e6))
def test_occupied_cells_counts_np_uniques_cells(seed, n, cell, spread):
    rng = np.random.default_rng(seed)
    pts = rng.normal(0.0, spread, (n, 3))
    pts[n // 2:] = pts[: n - n // 2]  # repeated points share their cell
    want = len(np.unique(np.floor(pts / cell).astype(np.int64), axis=0))
    assert occupied_cells(np.ascontiguousarray(pts), cell) == want


@settings(max_examples=20, deadline=None)
@given(w=st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3))
def test_rotvec_matrix_is_the_rotors(w):
    w = np.array(w)
    np.testing.assert_allclose(rotvec_matrix(w), Rotor.from_rotvec(w).as_matrix(), atol=1e-14)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), angle=st.floats(0.0, 40.0))
def test_screen_icp_is_point_icp_for_every_draw(seed, angle):
    rng = np.random.default_rng(seed)
    Y, _ = _surface(rng, 600)
    X = _surface(rng, 300)[0]
    rotations = Rotation.from_rotvec(rng.normal(size=(12, 3)) * np.deg2rad(angle) / np.sqrt(3)).as_matrix()
    translations = rng.normal(0.0, 0.1, (12, 3))
    gate = 0.15
    grid = TargetGrid.of(Y, gate)
    Rk, tk, sk = screen_icp(X, grid.target, grid.start, grid.order, grid.origin, grid.cell, grid.dims,
                            rotations, translations, gate, 10)
    tree = cKDTree(Y)
    for k in range(12):
        R, t, s = point_icp(X, Y, tree, rotations[k], translations[k], gate, fit=kabsch3)
        assert s == sk[k]
        np.testing.assert_allclose(Rk[k], R, atol=1e-9)
        np.testing.assert_allclose(tk[k], t, atol=1e-9)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), angle=st.floats(0.0, 10.0), noise=st.floats(0.0, 0.01))
def test_plane_icp_is_the_numpy_point_to_plane_icp(seed, angle, noise):
    Y, N, X, R0, t0 = _pair(np.random.default_rng(seed), 1500, 500, noise, angle, 0.02)
    for gate, iterations, tol, stall in [(0.2, 30, 1e-9, 0.0), (0.05, 10, 1e-3, 0.0), (0.1, 30, 1e-9, 1e-3),
                                         (0.1, 30, 1e-9, 0.05)]:
        R_ref, t_ref = reference_plane_icp(X, Y, N, R0, t0, gate, iterations, tol, stall)
        R, t = refine_point_to_plane(X, Y, N, R0, t0, gate, iterations=iterations, tol=tol, stall=stall)
        np.testing.assert_allclose(R, R_ref, atol=1e-9)
        np.testing.assert_allclose(t, t_ref, atol=1e-9)


def test_plane_icp_recovers_a_small_motion_of_a_surface():
    rng = np.random.default_rng(7)
    Y, N = _surface(rng, 4000)
    R_true = Rotation.from_rotvec([0.03, -0.02, 0.04]).as_matrix()
    t_true = np.array([0.02, -0.01, 0.015])
    X = (_surface(rng, 1000)[0] - t_true) @ R_true  # Y ≈ R_true X + t_true, sampled apart
    tree = KDTree(Y)
    R, t = plane_icp(X, tree.points, N, *tree.nodes, np.eye(3), np.zeros(3), 0.2, 50, 1e-9, 0.0)
    assert np.degrees(np.arccos(np.clip((np.trace(R @ R_true.T) - 1) / 2, -1, 1))) < 0.2
    assert np.linalg.norm(t - t_true) < 5e-3


def test_kdtree_rejects_points_not_in_3d():
    with pytest.raises(ValueError, match="points"):
        KDTree(np.zeros((4, 2)))


def test_plane_icp_many_is_plane_icp_through_the_gates_for_each_start():
    rng = np.random.default_rng(11)
    Y, N = _surface(rng, 2000)
    X = _surface(rng, 400)[0]
    tree = KDTree(Y)
    rotations = Rotation.from_rotvec(rng.normal(size=(5, 3)) * 0.1).as_matrix()
    translations = rng.normal(0.0, 0.05, (5, 3))
    gates = np.array([0.3, 0.15, 0.08])
    tols = np.array([1e-3, 1e-9, 1e-9])
    stalls = np.array([0.0, 1e-3, 0.0])
    Rs, ts = plane_icp_many(X, tree.points, N, *tree.nodes, rotations, translations, gates, 7, tols, stalls)
    for k in range(5):
        R, t = rotations[k], translations[k]
        for g, tol, stall in zip(gates, tols, stalls):
            R, t = plane_icp(X, tree.points, N, *tree.nodes, R, t, g, 7, tol, stall)
        np.testing.assert_array_equal(Rs[k], R)
        np.testing.assert_array_equal(ts[k], t)


@pytest.mark.parametrize("bad, match", [
    (dict(target=np.zeros((0, 3))), "target"),
    (dict(target_normals=np.zeros((5, 3))), "target_normals"),
    (dict(rotation=np.eye(4)), "rotation"),
    (dict(translation=[0.0, np.nan, 0.0]), "translation"),
    (dict(gate=0.0), "gate"),
    (dict(iterations=-1), "iterations"),
    (dict(source=np.full((4, 3), np.nan)), "source"),
])
def test_refine_point_to_plane_names_a_bad_argument(bad, match):
    from gatv.errors import InputError

    rng = np.random.default_rng(0)
    Y, N = _surface(rng, 50)
    args = dict(source=Y[:20], target=Y, target_normals=N, rotation=np.eye(3), translation=np.zeros(3), gate=0.1)
    args.update(bad)
    gate, iterations = args.pop("gate"), args.pop("iterations", 30)
    with pytest.raises(InputError, match=match):
        refine_point_to_plane(*args.values(), gate, iterations=iterations)


def reference_surface_support(X, Y, normals, tree, R, t, gates, reach, frame):
    """The numpy :func:`gatv.scans.surface_support` that :func:`gatv._icp_kernels.local_heights` replaces."""
    from gatv.scans import NORMAL_AGREEMENT

    moved = X @ R.T + t
    d, j = tree.query(moved, k=1, distance_upper_bound=max(reach, gates[0]))
    near = np.isfinite(d)
    j = np.where(near, j, 0)
    n = normals[j]
    agree = near & (np.abs(np.einsum("ij,ij->i", frame.normals @ R.T, n)) >= NORMAL_AGREEMENT)
    off = np.where(near[:, None], moved - Y[j], 0.0)
    rows = np.flatnonzero(agree)
    nb = frame.neighbours[rows]
    heights = np.einsum("ikj,ij->ik", off[nb], n[rows])
    h = np.abs(heights.sum(axis=1)) / np.maximum(near[nb].sum(axis=1), 1)
    return np.array([np.count_nonzero(d[rows] <= gates[0])] + [np.count_nonzero(h <= g) for g in gates[1:]])


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), angle=st.floats(0.0, 30.0), noise=st.floats(0.0, 0.02))
def test_surface_support_counts_as_its_numpy_reference(seed, angle, noise):
    from gatv.scans import SourceFrame, surface_support

    Y, N, X, R, t = _pair(np.random.default_rng(seed), 2000, 800, noise, angle, 0.05)
    frame = SourceFrame.of(X)
    gates = [0.1 / 2.0**k for k in range(5)]
    for tree in (cKDTree(Y), KDTree(Y)):
        got = surface_support(X, Y, N, tree, R, t, gates, 0.12, frame)
        want = reference_surface_support(X, Y, N, cKDTree(Y), R, t, gates, 0.12, frame)
        assert np.array_equal(got, want)


def reference_chance_support(source, target, gate, *, n_draws, polish, seed, sample, screen_points, final):
    """:func:`gatv.motions.scans.chance_support` (tangent draws) with every ICP by the numpy
    :func:`point_icp` (the code the screen kernel replaced there), Kabsch by ``kabsch3``."""
    from gatv.scans import tangent_motions

    X, Y = np.asarray(source, np.float64), np.asarray(target, np.float64)
    rng = np.random.default_rng(seed)
    tree = cKDTree(Y)
    sub = X if X.shape[0] <= sample else X[rng.choice(X.shape[0], sample, replace=False)]
    starts = tangent_motions(X, Y, n_draws, rng, target_tree=tree)
    if len(starts) > final and sub.shape[0] > screen_points:
        screen = sub[rng.choice(sub.shape[0], screen_points, replace=False)]
        ranks = [point_icp(screen, Y, tree, R, t, gate, polish, fit=kabsch3)[2] for R, t in starts]
        starts = [starts[k] for k in np.argsort(ranks, kind="stable")[::-1][:final]]
    best = max(point_icp(sub, Y, tree, R, t, gate, polish, fit=kabsch3)[2] for R, t in starts)
    return int(np.ceil(best * X.shape[0] / sub.shape[0]))


@settings(max_examples=5, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), gate=st.floats(0.03, 0.2))
def test_chance_support_is_its_numpy_reference(seed, gate):
    from gatv.motions import scans as motion_scans

    rng = np.random.default_rng(seed)
    Y, _ = _surface(rng, 1500, 0.005)
    X = np.vstack([_surface(rng, 900, 0.005)[0] @ Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix().T,
                   rng.uniform(-1.0, 1.0, (300, 3))])
    opts = dict(n_draws=24, polish=10, seed=seed % 1000)
    # A sample over the screen's points: every draw screened, the best N_CHANCE_FINAL polished on it.
    sample = motion_scans.CHANCE_SCREEN + 150
    assert X.shape[0] > sample and opts["n_draws"] > motion_scans.N_CHANCE_FINAL
    got = motion_scans.chance_support(X, Y, gate, sample=sample, **opts)
    want = reference_chance_support(X, Y, gate, sample=sample, screen_points=motion_scans.CHANCE_SCREEN,
                                    final=motion_scans.N_CHANCE_FINAL, **opts)
    assert got == want > 0


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), angle=st.floats(0.0, 20.0), n=st.integers(3, 1200),
       gate=st.sampled_from([0.02, 0.1, 0.3]))
def test_plane_icp_parallel_is_plane_icp_to_the_last_bit(seed, angle, n, gate):
    Y, N, X, R0, t0 = _pair(np.random.default_rng(seed), 1500, n, 0.003, angle, 0.02)
    tree = KDTree(Y)
    for iterations, tol, stall in [(30, 1e-9, 0.0), (5, 1e-3, 0.0), (30, 1e-9, 1e-3)]:
        R1, t1 = plane_icp(X, Y, N, *tree.nodes, R0, t0, gate, iterations, tol, stall)
        R2, t2 = plane_icp_parallel(X, Y, N, *tree.nodes, R0, t0, gate, iterations, tol, stall)
        assert np.array_equal(R1, R2) and np.array_equal(t1, t2)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 400), radius=st.floats(0.01, 3.0),
       duplicates=st.booleans(), leaf=st.integers(1, 20))
def test_kdtree_nearest2_is_kdtree_nearest_and_the_next_distance(seed, n, radius, duplicates, leaf):
    """The same index as ``kdtree_nearest`` (ties too), its squared distance and the next nearest point's
    (the radius's square where fewer than two are closer), against a brute-force sort."""
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3))
    if duplicates:
        pts = np.vstack([pts, pts[: n // 2]])
        pts[:, 2] = np.round(pts[:, 2], 1)
    queries = rng.normal(scale=1.5, size=(200, 3))
    tree = KDTree(pts, leafsize=leaf)
    want = kdtree_query(queries, pts, *tree.nodes, radius, np.zeros(0, bool))
    stack, offsets, bounds = np.empty(128, np.int64), np.empty((128, 3)), np.empty(128)
    for q, j_ref in zip(queries, want):
        j, d1, d2 = kdtree_nearest2(q, pts, *tree.nodes, radius, stack, offsets, bounds)
        assert j == j_ref
        near = np.sort(((pts - q) ** 2).sum(axis=1))
        near = near[near < radius * radius]
        first, second = (list(near[:2]) + [radius * radius] * 2)[:2]
        np.testing.assert_allclose([d1, d2], [first, second], rtol=1e-14, atol=0)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 300), gate=st.floats(0.02, 0.5),
       step=st.floats(1e-6, 0.3), duplicates=st.booleans(), offset=st.sampled_from([0.0, 1e4]))
def test_nearest_kept_answers_as_a_fresh_search_every_step(seed, n, gate, step, duplicates, offset):
    """Points walked by small and large random motions: at every step ``nearest_kept`` names the target
    ``kdtree_nearest`` finds from scratch within the gate (-1 where none), to the index, whether it
    searched again or not; and it searches less often than every step once the steps are small."""
    rng = np.random.default_rng(seed)
    Y = rng.uniform(-1.0, 1.0, (n, 3)) + offset
    if duplicates:
        Y = np.vstack([Y, Y[: n // 2]])
    tree = KDTree(Y)
    q = rng.uniform(-1.2, 1.2, (150, 3)) + offset
    anchor, near, gap, margin = pairing_state(q.shape[0], tree.nodes[-1], gate)
    stack, offsets, bounds = np.empty(128, np.int64), np.empty((128, 3)), np.empty(128)
    searched = 0
    for k in range(25):
        jump = step if k % 8 else 10.0 * step  # now and then a larger move
        R = Rotation.from_rotvec(rng.normal(size=3) * jump * 0.2).as_matrix()
        q = (q - offset) @ R.T + offset + rng.normal(0.0, jump, 3)
        want = kdtree_query(q, Y, *tree.nodes, gate, np.zeros(0, bool))
        before = anchor.copy()
        got = [nearest_kept(q[i], Y, *tree.nodes, gate, margin, anchor, near, gap, i, stack, offsets, bounds)
               for i in range(q.shape[0])]
        np.testing.assert_array_equal(got, want)
        searched += int(np.count_nonzero(np.any(anchor != before, axis=1) | np.isnan(before[:, 0])))
    if step < 1e-3 and not duplicates:
        assert searched < 0.5 * 25 * q.shape[0]


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), angle=st.floats(0.0, 20.0), n=st.integers(3, 800),
       gate=st.sampled_from([0.02, 0.1, 0.3]))
def test_plane_icp_pairs_as_a_fresh_search_every_iteration_to_the_last_bit(seed, angle, n, gate):
    """``plane_icp`` (its searches kept between iterations) equals the loop that searches every point
    afresh each iteration (``kdtree_query``) with the same step, to the last bit."""
    Y, N, X, R0, t0 = _pair(np.random.default_rng(seed), 1500, n, 0.003, angle, 0.02)
    tree = KDTree(Y)
    for iterations, tol, stall in [(30, 1e-9, 0.0), (30, 1e-9, 1e-3)]:
        R, t, last = R0.copy(), t0.copy(), np.inf
        for _ in range(iterations):
            moved = np.stack([R[a, 0] * X[:, 0] + R[a, 1] * X[:, 1] + R[a, 2] * X[:, 2] + t[a] for a in range(3)],
                             axis=1)
            idx = kdtree_query(moved, Y, *tree.nodes, gate, np.zeros(0, bool))
            R, t, step = _plane_step(Y, N, moved, idx, R, t, gate)
            if _stops(step, last, tol, stall):
                break
            last = step
        R1, t1 = plane_icp(X, Y, N, *tree.nodes, R0, t0, gate, iterations, tol, stall)
        assert np.array_equal(R1, R) and np.array_equal(t1, t)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 400), radius=st.floats(0.01, 3.0),
       share=st.floats(0.0, 1.0), leaf=st.integers(1, 20))
def test_kdtree_nearest_among_marked_points_is_the_tree_of_those_points(seed, n, radius, share, leaf):
    """``KDTree.nearest(..., keep=mask)`` on the tree of every point finds what a tree of the marked points
    alone finds (their indices mapped back), and -1 where none of them is within the radius."""
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3))
    keep = rng.uniform(size=n) < share
    queries = rng.normal(scale=1.5, size=(200, 3))
    got = KDTree(pts, leafsize=leaf).nearest(queries, radius, keep)
    rows = np.flatnonzero(keep)
    if rows.size == 0:
        assert np.all(got == -1)
        return
    j = KDTree(pts[rows], leafsize=leaf).nearest(queries, radius)
    np.testing.assert_array_equal(got, np.where(j >= 0, rows[np.maximum(j, 0)], -1))
    with pytest.raises(ValueError, match="keep"):
        KDTree(pts).nearest(queries, radius, keep[:-1] if n > 1 else np.ones(2, bool))
