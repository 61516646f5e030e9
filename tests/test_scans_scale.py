"""Scans of any size (issue 38): the work a call reports grows at most linearly in the points."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gatv import Rotor, register_scans
from hypothesis import given, settings
from hypothesis import strategies as st

from gatv.candidates import median_spacing
from gatv.datasets import rotation_error_deg
from gatv.scans import (FIT_POINTS, NOISE_SAMPLE, VOTE_POINTS, match_points, project_to_surface, scan_noise,
                        spatial_order, surface_rows, surface_tokens, SURFACE_REACH)


def _bumpy(rng, n, noise):
    """``n`` random points of a generic closed bumpy surface (about 4.5 units²), with Gaussian noise."""
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    x, y, z = u.T
    r = (1.0 + 0.2 * np.sin(2.1 * x + 1.3 * y + 0.7 * z + 0.4)
         + 0.15 * np.cos(1.7 * x - 2.3 * y + 1.1 * z + 1.0) + 0.1 * np.sin(3 * z + 0.2))
    return u * r[:, None] * np.array([1.0, 0.8, 0.6]) + rng.normal(0.0, noise, (n, 3))


def _pair(n, seed=0, noise=0.01):
    """Two samplings of the surface at ``n`` points each, the target moved (noise a few spacings at 10⁵)."""
    rng = np.random.default_rng(seed)
    R = Rotor.from_axis_angle([0.3, -1.0, 0.4], np.radians(140.0))
    return _bumpy(rng, n, noise), (R >> _bumpy(rng, n, noise)) + np.array([2.0, -1.0, 0.5])


def _bounds(n, cap=VOTE_POINTS):
    """Linear bounds on each count of one scan of ``n`` points (``work`` of :func:`gatv.register_surfaces`).

    The noise: its k-d trees (the whole scan once, then halving subsamples) and the fits of
    NOISE_SAMPLE neighbourhoods of at most 2 FIT_POINTS + 1 points, one a doubling of the neighbourhood;
    the projection: its fits' tree and FIT_POINTS + 1 neighbours of each row the vote samples; the
    votes (two when projected) and the matching: at most ``cap`` each (the rows sampled); the output's
    pairs: the whole scan.
    """
    sampled = min(n, cap)
    return {"input": n, "noise": 2 * n + NOISE_SAMPLE * (2 * FIT_POINTS + 1) * int(np.ceil(np.log2(n))),
            "projection": n + sampled * (FIT_POINTS + 1), "vote": 2 * sampled, "match": sampled, "output": n}


def test_the_work_of_a_large_scan_stays_within_linear_bounds():
    """Stage 1 of a scan past the vote's sample, against bounds linear in its points (projecting every
    row instead: 9.3 million points handled against the projection's bound of 7.9 million)."""
    n = VOTE_POINTS + 90000
    tokens = surface_tokens(_bumpy(np.random.default_rng(4), n, 0.01), seed=1, all_points=False)
    assert tokens.projection is not None
    bound = _bounds(n)
    assert 0 < tokens.noise.work <= bound["noise"]
    assert 0 < tokens.projection.work <= bound["projection"]
    assert tokens.voted == bound["vote"]


@pytest.mark.slow  # two calls at 64k and 256k points a scan (about 8 s)
def test_the_work_of_a_call_grows_at_most_linearly_in_the_points():
    """What ``register_scans`` reports for scans of 64k and 256k points: within the linear bounds of
    :func:`_bounds` at both sizes, and growing no faster than the points from one to the other (up to
    the noise estimate's own spread: its square sets the projection's neighbourhoods, and the
    projection's fits reach FIT_POINTS only past 10^5 points)."""
    small, factor = VOTE_POINTS + 4000, 4
    cap = match_points(600)  # register_scans' default matching grid
    works = []
    for n in (small, small * factor):
        m = register_scans(*_pair(n), seed=0)
        works.append(m.info["work"])
        bound = _bounds(n, cap)
        for key, value in m.info["work"].items():
            assert 0 < value <= 2 * bound[key], (n, key, value, 2 * bound[key])  # both scans
    a, b = works
    assert b["input"] == factor * a["input"] == 2 * factor * small
    # The noise's doubling may take a step more at one size than at the other (where its neighbourhoods
    # settle is the noise estimate's own spread): up to one step a scan, its tree and its fits.
    step = 2 * (factor * small + NOISE_SAMPLE * (2 * FIT_POINTS + 1))
    for key in a:
        assert b[key] <= 1.25 * factor * a[key] + (step if key == "noise" else 0), (key, a[key], b[key])
    # Past the sample the vote and the matching stop growing.
    assert b["vote"] <= 4 * cap and b["match"] <= 2 * cap


def test_a_large_scan_is_projected_only_where_the_vote_samples_and_alike():
    """The rows the pipeline keeps, and their points, are those of projecting the whole scan."""
    rng = np.random.default_rng(3)
    points = _bumpy(rng, VOTE_POINTS + 20000, 0.01)
    whole = surface_tokens(points, seed=5)
    sampled = surface_tokens(points, seed=5, all_points=False)
    assert whole.projection is not None and sampled.projection is not None
    np.testing.assert_array_equal(sampled.rows, whole.rows)
    np.testing.assert_array_equal(sampled.points[sampled.rows], whole.points[whole.rows])
    np.testing.assert_array_equal(sampled.normals, whole.normals)
    assert sampled.projection.work < whole.projection.work
    assert sampled.voted == whole.voted == 2 * VOTE_POINTS


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(500, 3000), st.floats(0.2, 0.6))
def test_surface_rows_are_the_sample_kept_and_the_unsampled_rows_on_its_surface(seed, max_points, clutter):
    """``surface_rows`` of a plane in uniform clutter, voted on a sample: every row the vote kept, and of
    the rows it did not sample exactly those within the reach of a kept one and the band about its
    tangent plane (a brute-force reference); nearly all the plane, little of the clutter."""
    rng = np.random.default_rng(seed)
    n = 4000
    plane = np.column_stack([rng.uniform(-1, 1, (n, 2)), np.zeros(n)])
    noise = rng.uniform(-1, 1, (int(n * clutter / (1 - clutter)), 3))
    points = np.vstack([plane, noise])
    tokens = surface_tokens(points, seed=seed, all_points=False, max_points=max_points)
    assert tokens.sampled is not None and tokens.sampled.size == max_points
    assert np.isin(tokens.rows, tokens.sampled).all()
    rows = surface_rows(tokens)
    assert np.isin(tokens.rows, rows).all() and np.all(np.diff(rows) > 0)
    kept = points[tokens.rows]
    s = median_spacing(kept)
    rest = np.setdiff1d(np.arange(points.shape[0]), tokens.sampled)
    d = np.linalg.norm(points[rest][:, None, :] - kept[None, :, :], axis=2)
    j = d.argmin(axis=1)
    h = np.abs(np.einsum("ij,ij->i", points[rest] - kept[j], tokens.normals[j]))
    on = (d[np.arange(rest.size), j] < SURFACE_REACH * s) & (h <= s + 3.0 * tokens.noise.sigma)
    np.testing.assert_array_equal(np.setdiff1d(rows, tokens.rows), rest[on])
    assert np.isin(np.arange(n), rows).mean() > 0.9  # the vote drops some of a sparse sample's border
    # The clutter kept: about the share of its height range the band spans.
    assert np.isin(np.arange(n, points.shape[0]), rows).mean() < s + 3.0 * tokens.noise.sigma + 0.05
    assert np.all(surface_rows(tokens, clutter=False) == np.arange(points.shape[0]))


def test_a_scan_past_its_matching_sample_pairs_every_point_on_its_surface():
    """Scans of 12,000 points matched on samples of 2,500 (``n_points=100``): the motion is found, and the
    one-to-one pairs count points of the whole scans (more than the samples hold), true pairs under the
    motion."""
    n, n_points = 12000, 100
    cap = match_points(n_points)
    assert cap < n
    rng = np.random.default_rng(7)
    R = Rotor.from_axis_angle([0.3, -1.0, 0.4], np.radians(140.0))
    t = np.array([2.0, -1.0, 0.5])
    source = _bumpy(rng, n, 0.0)
    target = (R >> _bumpy(rng, n, 0.0)) + t
    m = register_scans(source, target, n_points=n_points, seed=0)
    assert m, m.info.get("reason")
    assert rotation_error_deg(m.rotation, R.as_matrix()) < 1.0
    assert m.info["work"]["match"] <= 2 * cap < m.info["work"]["output"] <= 2 * n
    c = m.correspondences
    assert np.unique(c[:, 0]).size == c.shape[0] == np.unique(c[:, 1]).size
    assert c.shape[0] > max(m.info["surface_points"])  # more pairs than either sample's surface holds points
    # Pairs within the final gate under the true motion too (up to the motion's own error).
    err = np.linalg.norm(source[c[:, 0]] @ R.as_matrix().T + t - target[c[:, 1]], axis=1)
    assert np.median(err) < m.info["final_gate"]


def test_scans_whose_sample_gives_no_motion_are_tried_whole(monkeypatch):
    """Where the sample's try gives no motion, the call tries the whole scans (up to VOTE_POINTS rows) and
    answers as the pipeline on the whole scans alone does; ``info["sampled"]`` says why."""
    import gatv.scans as S

    n, n_points = 12000, 100
    cap = match_points(n_points)
    rng = np.random.default_rng(7)
    R = Rotor.from_axis_angle([0.3, -1.0, 0.4], np.radians(140.0))
    source = _bumpy(rng, n, 0.0)
    target = (R >> _bumpy(rng, n, 0.0)) + np.array([2.0, -1.0, 0.5])
    real, rows = S.match_surfaces, []

    def sample_fails(Xs, Ys, *args, **options):
        rows.append(Xs.shape[0])
        out = real(Xs, Ys, *args, **options)
        if len(rows) > 1:
            return out
        return S.SurfaceMatch(None, None, out.gate, np.empty((0, 2), np.int64), 0,
                              dict(out.info, reason="no motion on the sample"))

    monkeypatch.setattr(S, "match_surfaces", sample_fails)
    m = register_scans(source, target, n_points=n_points, seed=0)
    assert len(rows) == 2 and rows[0] <= cap < rows[1]
    assert m and m.info["sampled"] == {"rows": cap, "reason": "no motion on the sample"}
    monkeypatch.setattr(S, "match_surfaces", real)
    monkeypatch.setattr(S, "MATCH_POINTS_PER_CELL", 10**6)  # the whole scans at once
    whole = register_scans(source, target, n_points=n_points, seed=0)
    assert "sampled" not in whole.info
    np.testing.assert_array_equal(m.rotation, whole.rotation)
    np.testing.assert_array_equal(m.correspondences, whole.correspondences)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 300), st.floats(0.01, 2.0))
def test_spatial_order_visits_every_row_once_cell_by_cell(seed, n, cell):
    """A permutation; the ordered rows' cells are lexicographically non-decreasing (a cell's rows consecutive)."""
    points = np.random.default_rng(seed).normal(size=(n, 3))
    order = spatial_order(points, cell)
    np.testing.assert_array_equal(np.sort(order), np.arange(n))
    if n > 1:
        index = np.floor((points[order] - points.min(axis=0)) / cell).astype(np.int64)
        step = np.diff(index, axis=0)
        first = np.argmax(step != 0, axis=1)  # the first axis on which consecutive cells differ
        lead = step[np.arange(n - 1), first]
        assert np.all(lead >= 0)


def test_the_projection_of_rows_in_any_order_is_each_rows_own():
    """Rows projected in a shuffled order (the fits run in spatial order) equal the whole scan's rows, bit for bit."""
    rng = np.random.default_rng(11)
    points = _bumpy(rng, 30000, 0.01)
    noise = scan_noise(points, seed=2)
    whole = project_to_surface(points, noise, seed=2)
    rows = rng.permutation(points.shape[0])[:12000]
    some = project_to_surface(points, noise, seed=2, rows=rows)
    assert whole is not None and some is not None
    np.testing.assert_array_equal(some.points, whole.points[rows])
    np.testing.assert_array_equal(some.normals, whole.normals[rows])
    assert not np.array_equal(some.points, points[rows])  # the rows did move onto the surface


def test_a_coarse_try_that_gives_no_motion_leads_to_the_call_without_it(monkeypatch):
    """``register_surfaces`` tries half the cells first, with the adaptive search alone; where that gives no
    motion, the answer is the call's without the coarse try (motion and pairs equal), ``info["coarse"]``
    saying why.  A clean pair ends at the coarse try: no ``info["coarse"]``, the motion within 1°.  (The
    bumpy ellipsoid is within the coarse grid's voxel of its own half-turn: the coarse try of this
    noise-free pair judges that rival as the full grid does, and ends there at seeds 0-5 of ``_pair``.)"""
    import gatv.scans as S

    n, n_points = 12000, 400
    source, target = _pair(n, seed=1, noise=0.0)
    R = Rotor.from_axis_angle([0.3, -1.0, 0.4], np.radians(140.0)).as_matrix()
    first = register_scans(source, target, n_points=n_points, seed=0)
    assert first and "coarse" not in first.info
    assert first.info["search"] == "adaptive"
    assert sum(first.info["n_downsampled"]) < 2 * 0.75 * n_points  # the coarse grid's cells
    assert rotation_error_deg(first.rotation, R) < 1.0

    real, calls = S.match_surfaces, []

    def coarse_fails(Xs, Ys, *args, **options):
        calls.append((options["n_points"], options["searches"]))
        out = real(Xs, Ys, *args, **options)
        if options["n_points"] == n_points:
            return out
        return S.SurfaceMatch(None, None, out.gate, np.empty((0, 2), np.int64), 0,
                              dict(out.info, reason="no motion on the coarse grid"))

    monkeypatch.setattr(S, "match_surfaces", coarse_fails)
    m = register_scans(source, target, n_points=n_points, seed=0)
    assert calls == [(n_points // 2, S.SEARCHES[:1]), (n_points, S.SEARCHES)]
    assert m and m.info["coarse"] == {"rows": match_points(n_points // 2, S.COARSE_POINTS_PER_CELL),
                                      "n_points": n_points // 2,
                                      "reason": "no motion on the coarse grid"}
    monkeypatch.setattr(S, "match_surfaces", real)
    without = register_scans(source, target, n_points=n_points, seed=0, coarse_first=False)
    assert "coarse" not in without.info
    np.testing.assert_array_equal(m.rotation, without.rotation)
    np.testing.assert_array_equal(m.correspondences, without.correspondences)


def test_the_coarse_try_leaves_rivals_to_the_finer_grid_only_for_noisy_scans(monkeypatch):
    """The coarse try judges its rivals itself on scans within their sampling's noise (not projected); on
    scans noisier than their sampling (projected) it leaves a rival that does not end on the best to the
    finer grid, whose twice as many rows polish the answer closer.  Either way the motion is found."""
    import gatv.scans as S

    real, deferred = S.match_surfaces, []

    def recorded(Xs, Ys, *args, **options):
        deferred.append((options["n_points"], options["defer_rivals"]))
        return real(Xs, Ys, *args, **options)

    monkeypatch.setattr(S, "match_surfaces", recorded)
    R = Rotor.from_axis_angle([0.3, -1.0, 0.4], np.radians(140.0)).as_matrix()
    n_points = 400
    for noise, projected in ((0.0, False), (0.03, True)):
        deferred.clear()
        m = register_scans(*_pair(12000, seed=1, noise=noise), n_points=n_points, seed=0)
        assert (min(m.info["projected"]) > 0) == projected
        assert deferred[0] == (n_points // 2, projected)  # the coarse try
        assert all(not d for _, d in deferred[1:])  # the finer grid judges its rivals
        assert m and rotation_error_deg(m.rotation, R) < 1.0


def test_a_coarse_motion_with_a_close_rival_is_left_to_the_finer_grid(monkeypatch):
    """A motion that passes the coarse try's verdict against a rival keeping ``RIVAL_SHARE`` of its support
    (``info["rival"]`` or ``info["symmetric_rival"]``) is not the answer: the finer grid tells the two apart,
    and the answer is the call's without the coarse try, ``info["coarse"]`` naming the rival."""
    import gatv.scans as S

    n, n_points = 12000, 400
    source, target = _pair(n, seed=1, noise=0.0)
    real, calls = S.match_surfaces, []
    for key in ("rival", "symmetric_rival"):
        def close_rival(Xs, Ys, *args, **options):
            calls.append(options["n_points"])
            out = real(Xs, Ys, *args, **options)
            if options["n_points"] == n_points or not out:
                return out
            return dataclasses.replace(out, info=dict(out.info, ambiguous=True, **{key: {
                "on_surface": 90, "best_on_surface": 100, "angle_deg": 150.0}}))

        calls.clear()
        monkeypatch.setattr(S, "match_surfaces", close_rival)
        m = register_scans(source, target, n_points=n_points, seed=0)
        assert calls == [n_points // 2, n_points]
        assert m and m.info["coarse"]["reason"].startswith("ambiguous: a rival 150 deg away keeps 90 of")
        monkeypatch.setattr(S, "match_surfaces", real)
        without = register_scans(source, target, n_points=n_points, seed=0, coarse_first=False)
        np.testing.assert_array_equal(m.rotation, without.rotation)
        np.testing.assert_array_equal(m.correspondences, without.correspondences)
