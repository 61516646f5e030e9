"""Real scans down to 40% overlap with 30% clutter (issue 38), on the shared bunny scans and UWA views."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from gatv import register
from gatv.datasets import rotation_error_deg

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def cropped_case(target_name, source_name, overlap, clutter, seed):
    """``benchmarks/scans.py``'s ``make_case(f"{target}<-{source}", clutter, overlap, seed)``, drawn the same way.

    The target is cut by a plane of random direction so that the share ``overlap`` of the source's
    points lies within 5 mm of it after the true motion; the source is re-posed by a random rotation
    and translation; each view gets uniform clutter in its bounding box, the share ``clutter`` of its
    points.  Returns ``(source, target, R, t, centroid, share)``: ``share`` is the overlap reached.
    """
    from gatv.datasets import load_bunny_pair

    return _crop_and_pose(*load_bunny_pair(target_name, source_name, data_dir=DATA), overlap, clutter, seed, 0.005)


def _crop_and_pose(target, source, R, t, overlap, clutter, seed, near_within):
    """:func:`cropped_case` on a loaded pair; a source point overlaps within ``near_within`` (5 mm)."""
    rng = np.random.default_rng(seed)
    on_target = source @ R.T + t
    near = cKDTree(target).query(on_target, k=1)[0] < near_within
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    h = on_target @ u
    order = np.argsort(h)
    cum = np.cumsum(near[order]) / len(source)
    target = target[target @ u <= h[order[int(np.searchsorted(cum, overlap))]]]
    share = float(np.mean(cKDTree(target).query(on_target, k=1)[0] < near_within))
    extent = float(np.linalg.norm(target.max(0) - target.min(0)))
    Q = Rotation.random(random_state=rng).as_matrix()
    q = rng.uniform(-0.2, 0.2, 3) * extent
    moved = source @ Q.T + q
    views = []
    for pts in (moved, target):
        k = int(round(len(pts) * clutter / (1 - clutter)))
        views.append(np.vstack([pts, rng.uniform(pts.min(0), pts.max(0), (k, 3))]))
    return views[0], views[1], R @ Q.T, t - R @ Q.T @ q, moved.mean(axis=0), share


@pytest.mark.slow  # two 45k/23k-point calls (10-20 s each), one through the partial-overlap search
@pytest.mark.skipif(not (DATA / "stanford_bunny_scans").is_dir(), reason="shared bunny scans absent")
@pytest.mark.parametrize("target, source, seed", [("bun090", "bun045", 7), ("bun000", "bun090", 1)])
def test_a_pair_cropped_to_40_percent_overlap_with_30_percent_clutter(target, source, seed):
    """Within the benchmark's 1 degree and 2 mm.  bun090<-bun045 at seed 7: the right motion's trials
    ranked 8th-25th by their voxel support and the first two searches ended with "no motion" (before
    the partial-overlap search: no triple with sides of a quarter of the source's extent spanned the
    overlap)."""
    src, tgt, R, t, c, share = cropped_case(target, source, 0.4, 0.3, seed)
    assert 0.38 <= share <= 0.46
    m = register(src, tgt, seed=seed)
    assert m, m.info.get("reason")
    assert rotation_error_deg(m.rotation, R) < 1.0
    assert 1000 * np.linalg.norm(m.rotation @ c + m.translation - R @ c - t) < 2.0


@pytest.mark.skipif(not (DATA / "uwa_views_bcpd").is_dir(), reason="shared UWA views absent")
def test_the_chef_at_42_percent_overlap_is_right_or_no_motion():
    """``benchmarks/scans.py --overlap 0.4 --clutter 0.3``'s chef row (seed 5): never a wrong motion
    returned as found.  Its adaptive search stopped at 166 triples on a motion 177 degrees off, flagged
    ambiguous (a rival 21 degrees away held 0.96 of its points) and passing the draws' level at 1.15;
    counted against its rival it fails, and the whole budget finds the truth (about 5 CPU-s)."""
    from gatv.datasets import load_uwa_pair

    src, tgt, R, t, c, share = _crop_and_pose(*load_uwa_pair("chef", data_dir=DATA), 0.4, 0.3, 5, 5.0)
    assert 0.38 <= share <= 0.46
    m = register(src, tgt, seed=5)
    if m:  # the benchmark's UWA tolerance: 0.3 degrees, 1 mm at the source's centroid
        assert rotation_error_deg(m.rotation, R) <= 0.3
        assert np.linalg.norm(m.rotation @ c + m.translation - (R @ c + t)) <= 1.0
    else:
        assert m.info["reason"]
