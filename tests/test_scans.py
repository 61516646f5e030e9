"""Real-scan registration: gatv.register_scans and its pieces."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from gatv import Rotor, register, register_scans
from gatv.datasets import rotation_error_deg
from gatv.scans import local_scatter, surface_points, voxel_downsample

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def _resampled_sphere_pair(seed=0, n_source=3000, n_target=3000):
    """Two different random samplings of one bumpy closed surface, moved apart."""
    rng = np.random.default_rng(seed)

    def sample(n):
        u = rng.normal(size=(n, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        x, y, z = u.T  # a generic, asymmetric star-shaped surface
        r = (1.0 + 0.2 * np.sin(2.1 * x + 1.3 * y + 0.7 * z + 0.4)
             + 0.15 * np.cos(1.7 * x - 2.3 * y + 1.1 * z + 1.0) + 0.1 * np.sin(3 * z + 0.2))
        return u * r[:, None] * np.array([1.0, 0.8, 0.6])

    src = sample(n_source)
    tgt = sample(n_target)
    R = Rotor.from_axis_angle([0.3, -1.0, 0.4], np.radians(140.0))
    t = np.array([2.0, -1.0, 0.5])
    return src, (R >> tgt) + t, R.as_matrix(), t


def test_voxel_downsample_keeps_one_point_per_cell():
    pts = np.random.default_rng(0).uniform(0, 1, (5000, 3))
    down = voxel_downsample(pts, 0.25)
    assert down.shape == (64, 3)
    cells = np.floor((down - pts.min(axis=0)) / 0.25).astype(int)
    assert len(np.unique(cells, axis=0)) == 64


def test_surface_points_drop_clutter():
    rng = np.random.default_rng(1)
    plane = np.c_[rng.uniform(-1, 1, (3000, 2)), np.zeros(3000)]
    clutter = rng.uniform(-1, 1, (3000, 3))
    idx, normals = surface_points(np.vstack([plane, clutter]))
    on_plane = idx < 3000
    assert on_plane.mean() > 0.9
    assert on_plane.sum() > 0.8 * 3000
    assert np.median(np.abs(normals[on_plane, 2])) > 0.99


def test_differently_sampled_surfaces_register():
    src, tgt, R, t = _resampled_sphere_pair()
    m = register_scans(src, tgt, seed=0, n_points=300, max_triples=60)
    assert rotation_error_deg(m.rotation, R) < 0.5
    assert not m.info["ambiguous"]  # an asymmetric surface: no rival (an ellipsoid has one, test_real_data.py)
    assert np.linalg.norm(m.translation - t) < 0.01
    c = m.correspondences
    assert len(np.unique(c[:, 0])) == len(c) == len(np.unique(c[:, 1]))


@pytest.mark.parametrize(("n_source", "n_target"),
                         [pytest.param(20000, 300, marks=pytest.mark.slow), (300, 20000)])
def test_a_dense_and_a_sparse_sampling_register(n_source, n_target):
    """A dense scan against a coarse sampling of the same surface (a mesh's few hundred vertices):
    the matching voxel follows the coarser sampling, so both sets' voxel centroids are local means of
    the surface.  Fewer target points than ``n_points`` used to give a voxel far below the coarse
    spacing, and no congruent triple."""
    from gatv.candidates import median_spacing
    from gatv.scans import SAMPLING_VOXELS, matching_voxel

    src, tgt, R, t = _resampled_sphere_pair(1, n_source, n_target)
    coarse = median_spacing(src if n_source < n_target else tgt)
    assert matching_voxel(src, tgt, 600) >= SAMPLING_VOXELS * coarse
    m = register_scans(src, tgt, seed=0)
    assert m, m.info.get("reason")
    assert rotation_error_deg(m.rotation, R) < 2.0
    assert np.linalg.norm(m.translation - t) < 0.2 * coarse
    c = m.correspondences
    assert len(np.unique(c[:, 0])) == len(c) == len(np.unique(c[:, 1]))


def test_bad_input():
    with pytest.raises(ValueError, match="source"):
        register_scans(np.zeros((2, 3)), np.zeros((10, 3)))
    pts = np.random.default_rng(0).normal(size=(50, 3))
    with pytest.raises(ValueError, match="n_points"):
        register_scans(pts, pts, n_points=2)


@pytest.mark.slow  # 40k real points; fast suite: test_real_data's range scan against a coarse bunny mesh
@pytest.mark.skipif(not (DATA / "stanford_bunny_scans").is_dir(), reason="shared bunny scans absent")
def test_bunny_scans_bun000_from_bun045():
    from scipy.spatial.transform import Rotation

    from gatv.datasets import load_bunny_pair

    target, source, R, t = load_bunny_pair("bun000", "bun045", data_dir=DATA)
    rng = np.random.default_rng(3)
    Q = Rotation.random(random_state=rng).as_matrix()
    q = rng.uniform(-0.2, 0.2, 3)
    moved = source @ Q.T + q  # re-posed by a rotation of any size
    R_true, t_true = R @ Q.T, t - R @ Q.T @ q
    m = register_scans(moved, target)
    # measured 0.089 deg and 0.17-0.37 mm for the re-posings of seeds 0-3 (the benchmark's bar: 1 deg, 2 mm)
    assert rotation_error_deg(m.rotation, R_true) < 0.25
    assert np.linalg.norm(m.translation - t_true) < 1e-3


# ------------------------------------------------- noise wider than the sampling
def _noisy_unit_sphere(rng, n, sigma):
    """Points of the unit sphere moved along its normal by Gaussian noise: (points, directions)."""
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u * (1.0 + rng.normal(0.0, sigma, n))[:, None], u


#: Noise, in point spacings, where the 8-point neighbourhoods meet the radius rule only through their
#: own underestimate (10-15% low at 0.6-0.75 spacings; 16 points and 4-6% from 0.8 on).
UNDERESTIMATED = (0.55, 0.8)


@settings(max_examples=6, deadline=None)
@given(spacings=st.floats(0.3, 4.0), seed=st.integers(0, 2**16))
def test_scan_noise_is_measured_at_the_noise_own_scale(spacings, seed):
    """Noise from a third of a point spacing to four spacings: each estimate within 15%.  A fixed
    neighbourhood of a few spacings measures its own cut of the noisy shell instead.  (The band of
    :data:`UNDERESTIMATED` is the known defect pinned below.)"""
    from gatv.candidates import median_spacing
    from gatv.scans import NOISE_RADIUS, scan_noise

    assume(not UNDERESTIMATED[0] <= spacings < UNDERESTIMATED[1])
    rng = np.random.default_rng(seed)
    clean, _ = _noisy_unit_sphere(rng, 20000, 0.0)
    sigma = spacings * median_spacing(clean)
    pts, _ = _noisy_unit_sphere(rng, 20000, sigma)
    est = scan_noise(pts, seed=seed)
    assert abs(est.sigma / sigma - 1.0) < 0.15
    assert est.radius >= NOISE_RADIUS * est.sigma
    assert est.neighbours < 0.05 * pts.shape[0]


@pytest.mark.xfail(strict=True, reason=(
    "scan_noise underestimates noise of 0.6-0.75 point spacings by 10-15%: the 8-point neighbourhoods "
    "reach NOISE_RADIUS times the estimate only because the estimate is low (16 points and 4-6% from 0.8 "
    "spacings on); found by hypothesis at spacings 0.75, seed 32 (15.2% low)"))
def test_scan_noise_at_three_quarters_of_a_spacing():
    from gatv.candidates import median_spacing
    from gatv.scans import scan_noise

    rng = np.random.default_rng(32)
    clean, _ = _noisy_unit_sphere(rng, 20000, 0.0)
    sigma = 0.75 * median_spacing(clean)
    pts, _ = _noisy_unit_sphere(rng, 20000, sigma)
    assert abs(scan_noise(pts, seed=32).sigma / sigma - 1.0) < 0.1


def test_scan_noise_of_a_large_scan_starts_on_a_subsample():
    """Past NOISE_SAMPLE * 2 FIT_POINTS points the doubling starts on a subsample of at most that many, each
    step on the doubling's own subsample: the result is the doubling's from 8 points, bit for bit, both
    where the noise (eight spacings) settles above that first step, there with less work than the doubling
    less its k-d tree of every point, and where it (a third of a spacing) settles at the first step and the
    steps below run on every point."""
    from gatv.candidates import median_spacing
    from gatv.scans import FIT_POINTS, NOISE_SAMPLE, _noise_step, scan_noise

    n = NOISE_SAMPLE * 2 * FIT_POINTS + 44000
    rng = np.random.default_rng(5)
    clean, _ = _noisy_unit_sphere(rng, n, 0.0)
    spacing = median_spacing(clean)
    for spacings in (8.0, 0.3):
        sigma = spacings * spacing
        pts, _ = _noisy_unit_sphere(rng, n, sigma)
        est = scan_noise(pts, seed=1)
        draws = np.random.default_rng(1)
        at = pts[draws.choice(n, NOISE_SAMPLE, replace=False)]
        trees, k, work = {}, 8, 0
        while True:  # the doubling from 8
            ladder, settled = _noise_step(pts, at, draws, k, trees)
            work += ladder.work
            if settled:
                break
            k *= 2
        assert (est.sigma, est.neighbours, est.radius) == (ladder.sigma, ladder.neighbours, ladder.radius)
        if spacings > 1:
            assert abs(est.sigma / sigma - 1.0) < 0.07
            assert est.neighbours > 2 * FIT_POINTS
            assert est.work < work - n
        else:
            assert est.neighbours <= 2 * FIT_POINTS


def test_scan_noise_of_a_volume_reaches_the_whole_set():
    """Scattered points deviate from every plane by a share of the neighbourhood's size: no scale settles."""
    from gatv.scans import scan_noise

    pts = np.random.default_rng(3).uniform(-1, 1, (3000, 3))
    assert scan_noise(pts).neighbours == 2999


def test_projection_onto_the_surface_removes_most_of_the_noise():
    from gatv.candidates import median_spacing
    from gatv.scans import project_to_surface, scan_noise

    rng = np.random.default_rng(4)
    clean, _ = _noisy_unit_sphere(rng, 20000, 0.0)
    sigma = 3.0 * median_spacing(clean)
    pts, u = _noisy_unit_sphere(rng, 20000, sigma)
    proj = project_to_surface(pts, scan_noise(pts))
    assert proj is not None and proj.neighbours >= 20
    radial = np.linalg.norm(proj.points, axis=1) - 1.0
    assert np.std(radial) < 0.4 * sigma  # from sigma: each fit averages tens of points
    # The plane fits cut the sphere's cap: they shrink it by about r² / 4 (r = 3 sigma), alike in two scans.
    assert abs(np.mean(radial)) < 0.2 * sigma
    assert np.median(np.abs(np.einsum("ij,ij->i", proj.normals, u))) > 0.99
    # Noise within the sampling: nothing to project.
    fine, _ = _noisy_unit_sphere(rng, 20000, 0.01 * median_spacing(clean))
    assert project_to_surface(fine, scan_noise(fine)) is None


def test_noisy_surfaces_take_the_scans_pipeline_and_are_registered():
    """4% noise on 4000 points a set: not flat at twelve neighbours (the exact pipeline took them and
    ran out of time); projected onto their surfaces, registered, and the noise reported."""
    from gatv import register
    from gatv.registration import choose_pipeline

    src, tgt, R, t = _resampled_sphere_pair(0, 4000, 4000)
    rms = np.sqrt(((src - src.mean(axis=0)) ** 2).sum(axis=1).mean())
    sigma = 0.04 * rms
    rng = np.random.default_rng(10)
    src = src + rng.normal(0.0, sigma, src.shape)
    tgt = tgt + rng.normal(0.0, sigma, tgt.shape)
    kind, why = choose_pipeline(src, tgt)
    assert kind == "scans" and "noisy surfaces" in why
    m = register(src, tgt, seed=0, max_triples=100)  # fewer triples than the default: faster
    assert m.info["pipeline"] == "scans"
    assert rotation_error_deg(m.rotation, R) < 2.0
    c = src.mean(axis=0)
    assert np.linalg.norm(m.rotation @ c + m.translation - (R @ c + t)) < 0.01 * rms
    assert 0.8 * sigma < m.info["noise"] < 1.2 * sigma
    assert min(m.info["projected"]) > 0


def test_projection_names_a_bad_noise_argument():
    from gatv import InputError
    from gatv.scans import project_to_surface

    pts = np.random.default_rng(0).normal(size=(100, 3))
    with pytest.raises(InputError, match="`noise`.*scan_noise"):
        project_to_surface(pts, 0.01)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(4, 20), noise=st.floats(0.0, 0.05))
def test_local_scatter_is_the_pca_of_the_k_nearest_neighbours(seed, k, noise):
    """Against a brute-force reference (all distances, covariance, eigvalsh); on a noisy plane the
    least-variance axis is the plane's normal and its eigenvalue the residual sum of squares about the fit."""
    rng = np.random.default_rng(seed)
    normal = rng.normal(size=3)
    normal /= np.linalg.norm(normal)
    u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    ref = rng.uniform(-1, 1, (60, 1)) * u + rng.uniform(-1, 1, (60, 1)) * v + rng.normal(0, noise, (60, 1)) * normal
    queries = ref[rng.choice(60, 9, replace=False)] + rng.normal(0, 0.01, (9, 3))
    fit = local_scatter(ref, queries, k)
    d = np.linalg.norm(queries[:, None, :] - ref[None, :, :], axis=2)
    nb = np.argsort(d, axis=1)[:, :k]
    for i in range(len(queries)):
        local = ref[nb[i]] - ref[nb[i]].mean(axis=0)
        np.testing.assert_allclose(fit.centroids[i], ref[nb[i]].mean(axis=0), atol=1e-12)
        np.testing.assert_allclose(fit.eigenvalues[i], np.linalg.eigvalsh(local.T @ local), atol=1e-10)
        assert fit.radius[i] == pytest.approx(np.sort(d[i])[k - 1])
        # the axes diagonalise the scatter: A^T C A = diag(eigenvalues)
        C = local.T @ local
        np.testing.assert_allclose(fit.axes[i].T @ C @ fit.axes[i], np.diag(fit.eigenvalues[i]), atol=1e-10)
        # the normal's eigenvalue is the sum of squared heights about the least-squares plane
        assert fit.eigenvalues[i, 0] == pytest.approx(np.sum((local @ fit.normals[i]) ** 2), abs=1e-12)
        if noise < 0.01:
            # The fitted plane tilts by about the noise over the neighbourhood's spread in the plane (its
            # middle eigenvalue): four points nearly in a line tilt far (seed 85, k = 4: 19 degrees);
            # worst 1.8x this bound over 1,200 neighbourhoods of k = 4-8.
            tilt = np.sqrt(max(0.0, 1.0 - (fit.normals[i] @ normal) ** 2))
            assert tilt <= 4.0 * noise * np.sqrt(k / fit.eigenvalues[i, 1]) + 1e-6


def test_local_scatter_names_k_when_it_exceeds_the_reference():
    from gatv.errors import InputError

    with pytest.raises(InputError, match="`k`"):
        local_scatter(np.zeros((5, 3)), np.zeros((1, 3)), 6)


def test_voxel_cells_match_the_row_unique_they_replace():
    """The flat cell keys give the cells, their order and their centroids of ``np.unique(axis=0)``."""
    from gatv.scans import _unique_cells, _voxel_for

    rng = np.random.default_rng(3)
    pts = rng.normal(size=(4000, 3)) * [1.0, 0.2, 3.0] - 5.0
    key = np.floor((pts - pts.min(axis=0)) / 0.3).astype(np.int64)
    ref, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    out = np.zeros((counts.size, 3))
    np.add.at(out, inv.ravel(), pts)
    np.testing.assert_array_equal(voxel_downsample(pts, 0.3), out / counts[:, None])
    for voxel in (0.05, 0.7):
        cells = np.floor(pts / voxel).astype(np.int64)
        assert len(_unique_cells(cells)) == len(np.unique(cells, axis=0))
    assert _voxel_for(pts, 200) > 0
    huge = np.array([[0, 0, 0], [2**40, 2**40, 2**40], [0, 0, 0]], dtype=np.int64)
    assert len(_unique_cells(huge)) == 2  # ranges whose product overflows: the rows themselves


def test_verdict_screen_counts_as_point_icp_then_a_query():
    """point_icp's support is a fresh query at the motion it returns, and the verdict's screen (the numba
    Kabsch as its fit) counts as the fit_rigid one does."""
    from scipy.spatial import cKDTree

    from gatv._fit_kernels import kabsch3
    from gatv.scans import point_icp, tangent_motions

    src, tgt, _, _ = _resampled_sphere_pair(n_source=800, n_target=1500)
    tree = cKDTree(tgt)
    for R, t in tangent_motions(src, tgt, 8, np.random.default_rng(0), target_tree=tree):
        R2, t2, support = point_icp(src, tgt, tree, R, t, 0.3)
        d, _ = tree.query(src @ R2.T + t2, k=1, distance_upper_bound=0.3)
        assert support == np.count_nonzero(np.isfinite(d))
        assert point_icp(src, tgt, tree, R, t, 0.3, fit=kabsch3)[2] == support


def test_point_to_plane_step_on_a_plane_leaves_the_free_motions_alone():
    """On a plane the slide and the spin are free: the minimum-norm step leaves them at zero."""
    from gatv.scans import refine_point_to_plane

    rng = np.random.default_rng(4)
    tgt = np.c_[rng.uniform(-1, 1, (2000, 2)), np.zeros(2000)]
    src = np.c_[rng.uniform(-0.8, 0.8, (500, 2)), np.full(500, 0.01)]
    normals = np.tile([0.0, 0.0, 1.0], (2000, 1))
    R, t = refine_point_to_plane(src, tgt, normals, np.eye(3), np.zeros(3), 0.1)
    np.testing.assert_allclose(R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(t, [0.0, 0.0, -0.01], atol=1e-12)


@given(seed=st.integers(0, 2**16), confidence=st.sampled_from([0.9, 0.999]), min_share=st.floats(0.05, 0.6))
@settings(max_examples=4, deadline=None)
def test_the_adaptive_search_stops_at_the_ransac_bound_of_its_best_trial(seed, confidence, min_share):
    """Adaptive RANSAC termination: the triples drawn reach the bound the best trial's inlier share
    needs within one batch, and stay within the budget; a whole-budget search draws every triple."""
    from gatv.models.rigid.congruent import TargetIndex, n_triples_needed, trial_motions

    src, tgt, _, _ = _resampled_sphere_pair(seed % 7, 400, 400)
    index = TargetIndex(tgt, 0.15)
    budget, batch = 200, 16
    seen = []  # (triples drawn, best support) after each batch

    def progress(fraction, message):
        drawn, best = message.split(" triples, best support ")
        seen.append((int(drawn), int(best)))

    adaptive = trial_motions(src, index, eps=0.15, max_triples=budget, rng=np.random.default_rng(seed), keep=4,
                             accept=0, batch=batch, adaptive_confidence=confidence, min_share=min_share,
                             progress=progress)

    def bound(best):
        return n_triples_needed(max(best / src.shape[0], min_share, 1e-6), confidence)

    assert adaptive.n_triples == seen[-1][0] <= budget
    assert all(drawn < bound(best) for drawn, best in seen[:-1])  # no batch ended past its bound ...
    assert adaptive.n_triples == budget or adaptive.n_triples >= bound(seen[-1][1])  # ... but the last
    whole = trial_motions(src, index, eps=0.15, max_triples=budget, rng=np.random.default_rng(seed), keep=4,
                          accept=0, batch=batch)
    assert whole.n_triples == budget


def test_a_motion_that_fails_its_verdict_after_the_adaptive_stop_gets_the_whole_budget():
    """A true pair is found by the adaptive search alone.  Against a stretched copy of the surface
    (similar enough that the adaptive search stops at a wrong motion) the verdict rejects that motion,
    the whole budget is drawn, and then the partial-overlap search, before the answer "no motion"."""
    rng = np.random.default_rng(3)
    src, tgt, R, _ = _resampled_sphere_pair(2, 3000, 3000)
    other = _resampled_sphere_pair(5, 3000, 3000)[0] * [1.0, 1.6, 0.5]  # the surface stretched
    m = register_scans(src, tgt, seed=0, n_points=300)
    assert m and m.info["search"] == "adaptive"
    assert rotation_error_deg(m.rotation, R) < 0.5
    null = register_scans(other @ np.linalg.qr(rng.normal(size=(3, 3)))[0], tgt, seed=0, n_points=300)
    assert not null
    assert null.info["search"] == "partial overlap"
    assert null.info["adaptive"]["triples"] < null.info["whole_budget"]["triples"] == null.info["triples"]
    for search in ("adaptive", "whole_budget"):
        assert "wrong motions" in null.info[search]["reason"]
    assert "wrong motions" in null.info["reason"]


def _verdict_case(seed=0, n=1500):
    """Two samplings of one asymmetric surface in place (the identity is the motion), the target's normals,
    its tree and a cheap polish of wrong draws (point-to-point ICP at a fixed gate)."""
    from scipy.spatial import cKDTree

    from gatv.scans import point_icp

    src, tgt, _, _ = _resampled_sphere_pair(seed, n, n)
    tgt = _resampled_sphere_pair(seed + 100, n, n)[0]
    normals = local_scatter(tgt, tgt, 12).normals
    tree = cKDTree(tgt)

    def polish(R, t):
        R, t, _ = point_icp(src, tgt, tree, R, t, 0.3, iterations=5)
        return R, t, 0.1, None

    return src, tgt, normals, tree, polish


def _judge(case, R, t, **options):
    from gatv.scans import surface_verdict

    src, tgt, normals, tree, polish = case
    options.setdefault("rng", np.random.default_rng(7))
    return surface_verdict(src, tgt, normals, R, t, polish=polish, voxel=0.3, gate=0.1, n_tested=1000,
                           tree=tree, n_draws=48, **options)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_sequential_verdict_stops_only_on_a_pass(seed):
    """``surface_verdict(sure=)`` polishes the best-screened draws first and stops at the first of them
    over which the margin reaches ``sure_after`` that many (``sure`` from VERDICT_MIN_WRONG on, more
    before, less from VERDICT_LATE_WRONG on): the right motion passes after those few, its wrong supports
    the full verdict's first ones; a wrong motion's verdict is the full one, figure for figure."""
    from gatv.scans import VERDICT_SURE, gate_verdicts, sure_after

    case = _verdict_case(seed)
    full, full_figures = _judge(case, np.eye(3), np.zeros(3))
    fast, fast_figures = _judge(case, np.eye(3), np.zeros(3), sure=VERDICT_SURE)
    assert full and fast and fast.margin >= VERDICT_SURE
    assert full_figures["polished"] == 16 and 1 <= fast_figures["polished"] < 16
    assert fast_figures["wrong_support"] == full_figures["wrong_support"][:len(fast_figures["wrong_support"])]
    assert fast.margin >= full.margin  # fewer draws, lower levels
    # It stops at the first count of wrong draws whose margin reaches that count's threshold.
    margins = [max(v.margin for v in gate_verdicts(full_figures["support"], full_figures["wrong_support"][:k], 1000,
                                                    case[0].shape[0]))
               for k in range(1, full_figures["wrong_motions"] + 1)]
    stop = next(k for k, m in enumerate(margins, 1) if m >= sure_after(k, VERDICT_SURE))
    assert fast_figures["wrong_motions"] == stop and fast.margin == pytest.approx(margins[stop - 1])
    R_wrong = Rotor.from_axis_angle([1.0, 0.2, -0.5], np.radians(70.0)).as_matrix()
    wrong, wrong_figures = _judge(case, R_wrong, np.zeros(3))
    wrong_fast, wrong_fast_figures = _judge(case, R_wrong, np.zeros(3), sure=VERDICT_SURE)
    assert not wrong and not wrong_fast
    assert wrong_fast.to_dict() == wrong.to_dict() and wrong_fast_figures == wrong_figures


@settings(max_examples=50, deadline=None)
@given(sure=st.floats(0.5, 20.0), n=st.integers(0, 40))
def test_the_sequential_verdicts_margin_falls_with_the_draws(sure, n):
    """``sure_after``: the margin the sequential verdict stops at never rises with the wrong draws counted,
    is ``sure`` itself between VERDICT_MIN_WRONG and VERDICT_LATE_WRONG draws, never below it before them
    and never above it after."""
    from gatv.scans import VERDICT_LATE_WRONG, VERDICT_MIN_WRONG, sure_after

    assert sure_after(n + 1, sure) <= sure_after(n, sure)
    if n < VERDICT_MIN_WRONG:
        assert sure_after(n, sure) >= sure
    elif n < VERDICT_LATE_WRONG:
        assert sure_after(n, sure) == sure
    else:
        assert sure_after(n, sure) <= sure


def test_the_motion_is_judged_as_polished_like_its_draws():
    """``surface_verdict(start=)``: the search's trial is polished again as the wrong draws are, and the motion
    counts at each gate with the smaller of its two supports.  Started from itself, the right motion keeps its
    support and passes (its level only raised for the search's selection among n_tested motions); a start that
    the draws' polish leaves 70 degrees off is judged by what it holds there, and fails."""
    case = _verdict_case(3)
    plain, plain_figures = _judge(case, np.eye(3), np.zeros(3))
    right, figures = _judge(case, np.eye(3), np.zeros(3), start=(np.eye(3), np.zeros(3)))
    assert plain and right
    assert figures["support_polished"] == plain_figures["support"]
    assert figures["support"] == np.minimum(figures["support_polished"], figures["support_alike"]).tolist()
    assert figures["support_alike"][0] >= 0.95 * figures["support_polished"][0]
    assert figures["wrong_support"] == plain_figures["wrong_support"]
    assert all(a >= b for a, b in zip(figures["chance"], plain_figures["chance"]))
    R_wrong = Rotor.from_axis_angle([1.0, 0.2, -0.5], np.radians(70.0)).as_matrix()
    off, off_figures = _judge(case, np.eye(3), np.zeros(3), start=(R_wrong, np.zeros(3)))
    assert off_figures["support_polished"] == plain_figures["support"]
    assert off_figures["support"] == np.minimum(off_figures["support_polished"],
                                                off_figures["support_alike"]).tolist()
    assert off_figures["support_alike"][0] < 0.5 * off_figures["support_polished"][0]
    assert not off


def test_wrong_draws_are_polished_once_for_every_verdict():
    """One WrongDraws for several verdicts (match_surfaces' searches): each verdict equals the one that
    draws its own from the same stream, and a draw polished for one is not polished again for the next."""
    from gatv.scans import SourceFrame, WrongDraws

    case = _verdict_case(2)
    src, tgt, normals, tree, polish = case
    calls = []

    def counted(R, t):
        calls.append(1)
        return polish(R, t)

    draws = WrongDraws(src, tgt, normals, tree, SourceFrame.of(src), polish=counted, voxel=0.3,
                       rng=np.random.default_rng(7), n_draws=48)
    R_wrong = Rotor.from_axis_angle([0.2, 1.0, 0.3], np.radians(50.0)).as_matrix()
    for R in (R_wrong, np.eye(3)):
        shared = _judge(case, R, np.zeros(3), draws=draws)
        own = _judge(case, R, np.zeros(3))
        assert shared[0].to_dict() == own[0].to_dict() and shared[1] == own[1]
    assert len(calls) == draws.n_polished == max(_judge(case, R, np.zeros(3))[1]["polished"]
                                                  for R in (R_wrong, np.eye(3)))


def test_draws_polished_many_at_a_time_give_the_same_verdict():
    """``WrongDraws(polish_many=)`` (match_surfaces' parallel polish) polishes several draws at a time and
    the motion's start with the first draws, as many as fill numba's threads beside it (at least one): the
    same verdicts, figure for figure, as one by one."""
    from numba import get_num_threads

    from gatv.scans import VERDICT_SURE, SourceFrame, WrongDraws

    case = _verdict_case(4)
    src, tgt, normals, tree, polish = case
    batches = []

    def many(motions):
        batches.append(len(motions))
        return [polish(R, t)[:2] for R, t in motions]

    R_wrong = Rotor.from_axis_angle([0.2, 1.0, 0.3], np.radians(50.0)).as_matrix()
    for R, start in ((np.eye(3), (np.eye(3), np.zeros(3))), (R_wrong, (R_wrong, np.zeros(3)))):
        draws = WrongDraws(src, tgt, normals, tree, SourceFrame.of(src), polish=polish, voxel=0.3,
                           rng=np.random.default_rng(7), n_draws=48, polish_many=many)
        batches.clear()
        together = _judge(case, R, np.zeros(3), draws=draws, sure=VERDICT_SURE, start=start)
        alone = _judge(case, R, np.zeros(3), sure=VERDICT_SURE, start=start)
        assert together[0].to_dict() == alone[0].to_dict() and together[1] == alone[1]
        assert batches[0] == max(1, get_num_threads() - 1) + 1  # the start and the first draws, in one call
        assert draws.n_polished >= together[1]["polished"]


def test_a_rival_counts_first_and_the_verdict_tells_the_right_motion():
    """A rival (match_surfaces' distinct motion nearly as well supported) counts as a wrong motion before
    the draws: the right motion still passes against a wrong rival (its points sit at the noise at every
    gate), a wrong motion against the right one as its rival fails, and fails against that rival alone
    (``gate_verdicts``, the reason's "ambiguous" test); ``gate_verdicts`` gives the verdict's own levels."""
    from gatv.scans import gate_verdicts

    case = _verdict_case(3)
    src = case[0]
    R_wrong = Rotor.from_axis_angle([0.4, -1.0, 0.2], np.radians(25.0)).as_matrix()
    right, figures = _judge(case, np.eye(3), np.zeros(3), searched=[(R_wrong, np.zeros(3))])
    assert right and figures["searched"] == 1
    levels = gate_verdicts(figures["support"], figures["wrong_support"], 1000, src.shape[0])
    assert [v.chance for v in levels] == figures["chance"]
    wrong, wrong_figures = _judge(case, R_wrong, np.zeros(3), searched=[(np.eye(3), np.zeros(3))])
    assert not wrong and wrong_figures["searched"] == 1
    alone = gate_verdicts(wrong_figures["support"], wrong_figures["wrong_support"][:1], 1000, src.shape[0])
    assert not any(alone)


def test_two_motions_the_data_hold_alike_give_no_motion_and_say_so():
    """An ellipsoid matches itself after a half-turn: the motion and its rival hold the same points at
    every gate, so the answer is no motion, its reason naming the two (not one of them, confidently)."""
    rng = np.random.default_rng(2)
    u = rng.normal(size=(4000, 3))
    surface = u / np.linalg.norm(u, axis=1, keepdims=True) * [1.0, 0.7, 0.5]
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    moved = surface[rng.permutation(4000)[:3000]] @ R.T + [0.2, 0.0, -0.1]
    m = register_scans(surface, moved, seed=0, n_points=300, max_triples=60)
    assert not m and m.info["reason"].startswith("ambiguous: two motions")
    rival = m.info["rival"]
    assert rival["angle_deg"] > 90.0
    assert np.allclose(rival["supports"], m.info["verdict_gates"]["support"], rtol=0.02)


def test_wrong_draws_screened_on_given_source_points():
    """``WrongDraws(screen_source=)``: the screen moves those points (match_surfaces passes its voxel grid's
    centroids); the source itself is the default screen of a source of at most VERDICT_SCREEN points, so
    passing it changes nothing, and a draw's rank never exceeds the screen's points."""
    from gatv.scans import VERDICT_SCREEN, SourceFrame, WrongDraws

    src, tgt, normals, tree, polish = _verdict_case(4, n=800)
    assert src.shape[0] <= VERDICT_SCREEN
    frame = SourceFrame.of(src)

    def draws(**options):
        return WrongDraws(src, tgt, normals, tree, frame, polish=polish, voxel=0.3, rng=np.random.default_rng(5),
                          n_draws=48, **options)

    default, given = draws(), draws(screen_source=src)
    np.testing.assert_array_equal(default.ranks, given.ranks)
    assert all(np.array_equal(Ra, Rb) and np.array_equal(ta, tb)
               for (Ra, ta), (Rb, tb) in zip(default.starts, given.starts))
    cells = voxel_downsample(src, 0.3)
    coarse = draws(screen_source=cells)
    assert coarse.n_screen == cells.shape[0] < src.shape[0]
    assert np.all(np.diff(coarse.ranks) <= 0) and coarse.ranks[0] <= cells.shape[0]
    assert coarse.ranks[0] > 0


def test_a_rival_left_to_a_finer_grid_gives_no_motion_there_and_says_so():
    """``match_surfaces(defer_rivals=True)`` (the coarse try): on an ellipsoid, which matches itself after a
    half-turn, a rival that does not end on the best trial motion gives no motion on that grid, before any
    verdict; without it the two are judged ("ambiguous: two motions")."""
    from gatv.scans import SourceFrame, match_surfaces

    rng = np.random.default_rng(2)
    u = rng.normal(size=(4000, 3))
    surface = u / np.linalg.norm(u, axis=1, keepdims=True) * [1.0, 0.7, 0.5]
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    moved = surface[rng.permutation(4000)[:3000]] @ R.T + [0.2, 0.0, -0.1]
    normals = SourceFrame.of(moved).normals
    options = dict(n_points=300, seed=0, max_triples=60, verdict=True)
    deferred = match_surfaces(surface, moved, normals, defer_rivals=True, **options)
    assert not deferred and "not judged on this grid" in deferred.info["reason"]
    assert "verdict" not in deferred.info
    judged = match_surfaces(surface, moved, normals, **options)
    assert not judged and judged.info["reason"].startswith("ambiguous: two motions")


def test_match_surfaces_runs_the_searches_it_is_given_and_refuses_others():
    """``searches``: a subset of SEARCHES, run in that order; an unknown name is refused, naming it."""
    from gatv.errors import InputError
    from gatv.scans import SEARCHES, SourceFrame, match_surfaces

    rng = np.random.default_rng(1)
    src, tgt, _, _ = _resampled_sphere_pair(2, 3000, 3000)
    other = _resampled_sphere_pair(5, 3000, 3000)[0] * [1.0, 1.6, 0.5]
    normals = SourceFrame.of(tgt).normals
    options = dict(n_points=300, seed=0, verdict=True)
    null = match_surfaces(other @ np.linalg.qr(rng.normal(size=(3, 3)))[0], tgt, normals, searches=SEARCHES[:1],
                          **options)
    assert not null and null.info["search"] == "adaptive" and "whole_budget" not in null.info
    with pytest.raises(InputError, match="searches"):
        match_surfaces(src, tgt, normals, searches=("everything",), **options)


def test_a_sparse_surface_beside_a_dense_one_keeps_its_points():
    """Two surfaces of one scan, one sampled densely towards a point (a cone's apex), one evenly: the
    vote keeps most of each, whatever the other's density (``PLANAR_CHANCE``)."""
    rng = np.random.default_rng(0)
    th, z = rng.uniform(0.0, 2.0 * np.pi, 8000), rng.uniform(0.0, 6.0, 8000)
    cone = np.column_stack([z / 3.0 * np.cos(th), z / 3.0 * np.sin(th), z])
    u = rng.normal(size=(8000, 3))
    blob = 2.0 * u / np.linalg.norm(u, axis=1, keepdims=True) + [8.0, 0.0, 0.0]  # a sphere, evenly sampled
    scene = np.vstack([cone, blob]) + rng.normal(0.0, 0.01, (16000, 3))
    alone, _ = surface_points(scene[8000:], max_points=16000)
    assert alone.size > 0.9 * 8000  # alone, the sphere keeps nearly every point
    rows, _ = surface_points(scene, max_points=16000)
    assert np.count_nonzero(rows >= 8000) > 0.5 * 8000  # the paper's threshold alone kept 0 of 8,000


def _cone_and_blob(rng, n):
    """A cone sampled evenly in height (dense towards its apex) and an asymmetric bumpy blob beside it."""
    th, z = rng.uniform(0.0, 2.0 * np.pi, n), rng.uniform(0.0, 6.0, n)
    cone = np.column_stack([z / 3.0 * np.cos(th), z / 3.0 * np.sin(th), z])
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = 1 + 0.2 * np.sin(2.1 * u[:, 0] + 1.3 * u[:, 1] + 0.4) + 0.15 * np.cos(1.7 * u[:, 0] - 2.3 * u[:, 1] + u[:, 2])
    blob = 2.0 * u * r[:, None] * [1.2, 0.9, 0.6] + [8.0, 0.0, 0.0]
    return cone + rng.normal(0.0, 0.01, cone.shape), blob + rng.normal(0.0, 0.01, blob.shape)


def test_an_object_is_registered_onto_a_scene_where_a_denser_one_stands_beside_it():
    """The blob alone as the source; the moved blob beside a cone as the target: its motion is found.
    (With the paper's threshold alone the target kept about 5% of the blob: no congruent triples.)"""
    rng = np.random.default_rng(0)
    _, blob = _cone_and_blob(rng, 8000)
    cone, moved = _cone_and_blob(rng, 8000)
    R = Rotation.from_rotvec([0.3, -1.1, 0.6]).as_matrix()
    c, t = blob.mean(axis=0), np.array([0.5, -1.0, 2.0])
    target = np.vstack([cone, (moved - c) @ R.T + c + t])
    m = register(blob, target, seed=0, pipeline="scans")
    assert m, m.info.get("reason")
    assert rotation_error_deg(m.rotation, R) < 1.0
    assert np.linalg.norm(m.translation - (c + t - R @ c)) < 0.05
