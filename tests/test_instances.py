"""Every instance of a model in a scene, and a model tracked through frames (gatv.motions.instances, track).

The paper's section 4.1 (Fig. 9) finds a model in each frame with no
tracking between frames; these tests check that each copy of a model in a
scene is found once, with its pose, that a scene without the model gives
nothing (every instance passes the verdict), that model points serve every
instance while scene points serve one, and that identities follow the
closest pose through a short sequence.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from gatv.errors import InputError
from gatv.io import read_points
from gatv.motions import Instances, Track, instances, track
from gatv.motions.instance_search import MIN_MODEL_POINTS, model_size, pose_distance
from gatv.motions.tracking import assign_identities

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def _model(seed: int = 0, n: int = 60) -> np.ndarray:
    """A random, asymmetric cloud of ``n`` points in a box of size ~2."""
    return np.random.default_rng(seed).uniform(-1.0, 1.0, (n, 3)) * [1.0, 0.7, 0.5]


def _poses(k: int, seed: int, spread: float = 6.0) -> list:
    """``k`` random poses whose copies of the model lie apart (centres on a line, spaced ``spread``)."""
    rng = np.random.default_rng(seed)
    rot = Rotation.random(k, random_state=seed).as_matrix().reshape(k, 3, 3)
    return [(rot[i], np.array([spread * i, 0.0, 0.0]) + rng.uniform(-0.5, 0.5, 3)) for i in range(k)]


def _scene(model, poses, n_outliers: int, seed: int):
    """The copies of ``model`` at ``poses`` and uniform outliers, shuffled; also where each copy went."""
    rng = np.random.default_rng(seed)
    copies = [model @ R.T + t for R, t in poses]
    pts = np.vstack(copies)
    lo, hi = pts.min(axis=0) - 1.0, pts.max(axis=0) + 1.0
    scene = np.vstack([pts, rng.uniform(lo, hi, (n_outliers, 3))])
    owner = np.concatenate([np.full(len(model), k) for k in range(len(poses))] + [np.full(n_outliers, -1)])
    order = rng.permutation(len(scene))
    return scene[order], owner[order]


def _errors(motion, pose):
    R, t = pose
    cos = (np.trace(R.T @ motion.rotation) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), float(np.linalg.norm(motion.translation - t))


def _match(found, poses, model):
    """For each found instance the index of the true pose it is closest to."""
    centre, size = model.mean(axis=0), model_size(model)
    return [int(np.argmin([pose_distance(m, np.block([[R, t[:, None]], [0, 0, 0, 1]]), centre, size)
                           for R, t in poses])) for m in found]


@pytest.fixture(scope="module")
def three_copies():
    model = _model(0)
    poses = _poses(3, seed=1)
    scene, owner = _scene(model, poses, n_outliers=120, seed=2)
    return model, poses, scene, owner, instances(model, scene, seed=0)


def test_three_exact_copies_and_outliers_give_three_instances(three_copies):
    model, poses, scene, owner, found = three_copies
    assert isinstance(found, Instances) and len(found) == 3
    assert sorted(_match(found, poses, model)) == [0, 1, 2]
    for m, k in zip(found, _match(found, poses, model)):
        angle, shift = _errors(m, poses[k])
        assert angle < 1e-4 and shift < 1e-5 * model_size(model)
        assert m.support == len(model)
        assert m.info["verdict"]["passed"]
    assert found.info["exhausted"] and found.info["reason"]


def test_model_points_serve_every_instance_scene_points_one(three_copies):
    model, poses, scene, owner, found = three_copies
    rows = np.concatenate([m.correspondences[:, 1] for m in found])
    assert np.unique(rows).size == rows.size  # one scene point, one instance
    for k, m in enumerate(found):
        assert np.unique(m.correspondences[:, 0]).size == m.support  # one-to-one inside an instance
        assert np.all(found.labels[m.correspondences[:, 1]] == k)
        # every model point serves this instance (the model is not consumed by the earlier ones)
        assert set(m.correspondences[:, 0]) == set(range(len(model)))
        # its scene points are those of one copy
        assert np.unique(owner[found.scene_rows(k)]).size == 1
    assert np.all(found.labels[owner < 0] == -1)


def test_labels_and_record_are_frozen_and_json_ready(three_copies):
    found = three_copies[-1]
    with pytest.raises(ValueError):
        found.labels[0] = 5
    d = found.to_dict()
    assert d["n_instances"] == 3 and len(d["motions"]) == 3 and len(d["labels"]) == len(three_copies[2])
    assert "3 found" in repr(found)


def test_a_scene_without_the_model_gives_none():
    model = _model(0)
    rng = np.random.default_rng(5)
    clutter = rng.uniform(-3, 3, (150, 3))
    found = instances(model, clutter, seed=0, time_limit=30)
    assert not found and len(found) == 0
    assert np.all(found.labels == -1)
    assert found.info["reason"]
    other = _model(7, 60)  # another random shape of the same size
    assert not instances(model, other, seed=0, time_limit=30)
    sphere = rng.normal(size=(80, 3))  # another shape
    assert not instances(model, sphere / np.linalg.norm(sphere, axis=1)[:, None], seed=0, time_limit=30)


@pytest.mark.slow
def test_another_shape_among_outliers_gives_none():
    model = _model(0)
    rng = np.random.default_rng(5)
    found = instances(model, np.vstack([_model(7, 60), rng.uniform(-2, 2, (60, 3))]), seed=0)
    assert not found and found.info["exhausted"]


def test_same_seed_same_result():
    model = _model(3, 40)
    scene, _ = _scene(model, _poses(2, seed=4), n_outliers=40, seed=5)
    a = instances(model, scene, seed=3)
    b = instances(model, scene, seed=3)
    assert len(a) == len(b) == 2
    assert np.array_equal(a.labels, b.labels)
    for m, n in zip(a, b):
        assert np.array_equal(m.matrix, n.matrix)
        assert np.array_equal(m.correspondences, n.correspondences)


def test_max_instances_stops_with_a_reason():
    model = _model(3, 40)
    scene, _ = _scene(model, _poses(2, seed=4), n_outliers=40, seed=5)
    found = instances(model, scene, max_instances=1)
    assert len(found) == 1 and found.info["reason"] == "max_instances reached"
    assert not found.info["exhausted"]


def test_identities_kept_across_three_frames():
    model = _model(0, 50)
    rng = np.random.default_rng(11)
    start = _poses(3, seed=12)
    frames, truth = [], []
    for f in range(3):
        # each instance turns a little and drifts; the frames are searched independently
        poses = [(Rotation.from_rotvec(rng.normal(0, 0.15, 3)).as_matrix() @ R, t + rng.normal(0, 0.3, 3))
                 for R, t in (truth[-1] if truth else start)]
        truth.append(poses)
        frames.append(_scene(model, poses, n_outliers=40, seed=20 + f)[0])
    out = track(model, frames, seed=0)
    assert isinstance(out, Track) and len(out) == 3 and out.n_identities == 3
    assert out.present.all()
    for ident in range(3):
        which = {_match([out.pose(ident, f)], truth[f], model)[0] for f in range(3)}
        assert len(which) == 1  # the same true copy in every frame: never swapped
    assert out.to_dict()["n_identities"] == 3


def test_a_missing_instance_is_recorded():
    model = _model(0, 50)
    poses = _poses(2, seed=12)
    full = _scene(model, poses, n_outliers=30, seed=1)[0]
    one = _scene(model, poses[1:], n_outliers=30, seed=2)[0]
    out = track(model, [full, one, full], seed=0)
    assert [len(f) for f in out.frames] == [2, 1, 2]
    assert out.n_identities == 2
    assert len(out.missing(1)) == 1 and out.missing(2) == ()
    gone = out.missing(1)[0]
    assert not out.present[1, gone] and out.pose(gone, 1) is None
    assert out.present[2, gone]  # found again in the last frame, under its own identity


def test_assign_identities_follows_the_closest_pose():
    model = _model(0, 20)

    class Frame:
        def __init__(self, mats):
            self.instances = tuple(_Pose(m) for m in mats)

    a = np.eye(4)
    b = np.eye(4)
    b[:3, 3] = [10.0, 0, 0]
    moved_a, moved_b = a.copy(), b.copy()
    moved_a[:3, 3] += [0.5, 0, 0]
    moved_b[:3, 3] += [-0.5, 0, 0]
    ids, present = assign_identities([Frame([a, b]), Frame([moved_b, moved_a])], model.mean(axis=0),
                                     model_size(model))
    assert ids == [(0, 1), (1, 0)] and present.all()


class _Pose:
    def __init__(self, matrix):
        self.rotation, self.translation = matrix[:3, :3], matrix[:3, 3]


@pytest.mark.parametrize("bad, name", [
    (np.zeros((MIN_MODEL_POINTS - 1, 3)) + np.arange(3)[:, None] * [1, 2, 0.5], "model"),
    (np.eye(3), "model"),
    (np.full((10, 3), np.nan), "model"),
])
def test_bad_model_names_the_argument(bad, name):
    with pytest.raises(InputError, match=f"`{name}`"):
        instances(bad, _model(1))


def test_model_of_three_points_is_refused():
    tri = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    with pytest.raises(InputError, match="`model`.*at least 4"):
        instances(tri, _model(1))
    with pytest.raises(InputError, match="`model`"):
        track(tri, [_model(1)])


def test_bad_scene_and_frames_name_the_argument():
    with pytest.raises(InputError, match="`scene`"):
        instances(_model(0), np.full((10, 3), np.inf))
    with pytest.raises(InputError, match="`scene`"):
        instances(_model(0), np.zeros((10, 2)))
    with pytest.raises(InputError, match="`frames`"):
        track(_model(0), [])
    with pytest.raises(InputError, match=r"`frames\[1\]`"):
        track(_model(0), [_model(1), np.zeros((5, 4))])
    with pytest.raises(InputError, match="`frames`"):
        track(_model(0), _model(1))
    with pytest.raises(InputError, match="`max_instances`"):
        instances(_model(0), _model(1), max_instances=0)
    with pytest.raises(InputError, match="`pipeline`"):
        instances(_model(0), _model(1), pipeline="fast")


@pytest.mark.slow
@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(k=st.integers(1, 4), seed=st.integers(0, 2**16), outliers=st.sampled_from([0, 50, 150]))
def test_every_copy_found_at_random_poses(k, seed, outliers):
    model = _model(seed % 97, 50)
    poses = _poses(k, seed=seed)
    scene, _ = _scene(model, poses, n_outliers=outliers, seed=seed + 1)
    found = instances(model, scene, seed=seed)
    assert len(found) == k
    assert sorted(_match(found, poses, model)) == list(range(k))
    for m, j in zip(found, _match(found, poses, model)):
        angle, shift = _errors(m, poses[j])
        assert angle < 1e-3 and shift < 1e-4 * model_size(model)


@pytest.mark.slow
def test_copies_of_a_real_mesh_cut_by_planes():
    """Partial copies of the Stanford bunny (30% cut away by a random plane) among clutter."""
    path = DATA / "stanford_bunny_reconstruction" / "bun_zipper_res4.ply"
    if not path.is_file():
        pytest.skip("real data (../shared/data) not available")
    model = read_points(path)
    rng = np.random.default_rng(0)
    size = model_size(model)
    poses = _poses(3, seed=3, spread=2.0 * size)
    parts = []
    for R, t in poses:
        normal = rng.normal(size=3)
        d = model @ (normal / np.linalg.norm(normal))
        parts.append((model @ R.T + t)[d > np.quantile(d, 0.3)])
    pts = np.vstack(parts)
    scene = np.vstack([pts, rng.uniform(pts.min(0), pts.max(0), (len(pts) // 2, 3))])
    found = instances(model, scene, seed=0)
    assert len(found) == 3
    for m, j in zip(found, _match(found, poses, model)):
        angle, shift = _errors(m, poses[j])
        assert angle < 0.1 and shift < 1e-3 * size


# ------------------------------------------------------------------ command line
@pytest.fixture(scope="module")
def point_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("instances")
    model = _model(0, 50)
    np.savetxt(folder / "model.xyz", model)
    frames = []
    for f in range(2):
        path = folder / f"frame{f}.xyz"
        np.savetxt(path, _scene(model, _poses(2, seed=f), 30, f)[0])
        frames.append(path)
    return folder, folder / "model.xyz", frames


def test_cli_instances_writes_every_output(point_files, capsys):
    from gatv import cli

    folder, model, frames = point_files
    out, labelled = folder / "found.json", folder / "labels.ply"
    assert cli.main(["instances", str(model), str(frames[0]), "--out", str(out), "--labelled", str(labelled),
                     "-q"]) == 0
    record = json.loads(out.read_text())
    assert record["success"] and record["n_instances"] == 2 and len(record["motions"]) == 2
    labels = read_points(labelled, scalars=True)[1]["motion"]
    assert sorted(set(labels.tolist())) == [-1, 0, 1]


def test_cli_track_writes_identities(point_files):
    from gatv import cli

    folder, model, frames = point_files
    out = folder / "track.json"
    assert cli.main(["track", str(model), *map(str, frames), "--out", str(out), "-q"]) == 0
    record = json.loads(out.read_text())
    assert record["n_frames"] == 2 and record["n_identities"] == 2
    assert [sorted(f["identities"]) for f in record["frames"]] == [[0, 1], [0, 1]]


def test_cli_bad_input_exits_2_with_nothing_written(point_files, capsys):
    from gatv import cli

    folder, model, frames = point_files
    tiny = folder / "tiny.xyz"
    np.savetxt(tiny, _model(0, 3))
    out = folder / "never.json"
    assert cli.main(["instances", str(tiny), str(frames[0]), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "`model`" in err[0]
    assert cli.main(["instances", str(model), str(frames[0]), "--labelled", str(folder / "l.txt")]) == 2
    assert cli.main(["instances", str(model), str(frames[0]), "--max-instances", "0"]) == 2
    assert cli.main(["track", str(model), str(folder / "missing.xyz"), "--out", str(out)]) == 2
    assert not out.exists() and not (folder / "l.txt").exists()


def test_batch_runs_instances(point_files):
    from gatv.batch import run

    folder, model, frames = point_files
    rows = [{"source": str(model), "target": str(f), "name": f"scene{k}"} for k, f in enumerate(frames)]
    result = run(rows, folder / "batch", command="instances", scheduler="serial")
    assert result and result.counts()["found"] == 2
    record = json.loads((folder / "batch" / "scene0.json").read_text())
    assert record["n_instances"] == 2


# ------------------------------------------------------------------ noisy sequences, real scans, parts
def test_scene_parts_split_apart_copies_and_drop_clutter():
    from gatv.motions.instance_search import scene_parts, smallest_part

    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0), [0.0]), -1).reshape(-1, 3)
    scene = np.vstack([grid, grid + [50.0, 0, 0], rng.uniform(-10, 80, (30, 3))])
    mask = np.ones(len(scene), bool)
    mask[800:] = False  # the clutter is off the voted surfaces
    rows = np.arange(len(scene))
    parts = scene_parts(scene, rows, mask, 3.0, 10)
    assert [sorted(p.tolist()) for p in parts] == [list(range(400)), list(range(400, 800))]
    assert scene_parts(scene, rows[rows >= 400], mask, 3.0, 10)[0].tolist() == list(range(400, 800))
    assert scene_parts(scene, rows, mask, 3.0, 401) == []  # each sheet is smaller than a copy must be
    # a copy must hold MIN_OVERLAP of the model's points at the scene's sampling (twice as fine: 4x)
    assert smallest_part(grid, grid) == int(np.ceil(0.2 * 400))
    assert smallest_part(grid, grid / 2.0) == int(np.ceil(0.2 * 400 * 4))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**16), reach=st.floats(0.1, 0.8), stretch=st.tuples(*[st.floats(0.2, 3.0)] * 3))
def test_scene_blocks_hold_every_set_of_a_reach_whole(seed, reach, stretch):
    """Whatever the scene's shape, any set spanning at most ``reach`` along each axis lies whole in a block."""
    from gatv.motions.instance_search import BLOCK_SIDE, scene_blocks

    rng = np.random.default_rng(seed)
    scene = rng.uniform(0.0, 1.0, (400, 3)) * np.asarray(stretch)
    blocks = scene_blocks(scene, reach)
    extent = scene.max(0) - scene.min(0)
    if blocks is None:
        assert np.all(extent <= BLOCK_SIDE * reach)
        return
    rows = np.arange(len(scene))
    member = np.zeros((len(blocks), len(scene)), bool)
    for b in range(len(blocks)):
        member[b, blocks.rows(b, rows)] = True
    assert member.any(axis=0).all()  # every point in some block
    for _ in range(20):
        corner = scene.min(0) + rng.uniform(-0.2, 1.0, 3) * extent
        box = np.all((scene >= corner) & (scene <= corner + reach * rng.uniform(0.3, 1.0, 3)), axis=1)
        assert member[:, box].all(axis=1).any()
    blocks.set_aside(0, rows[:5], len(scene))  # set aside for one block only
    assert not np.isin(rows[:5], blocks.rows(0, rows)).any()
    assert all(np.array_equal(blocks.rows(b, rows), np.flatnonzero(member[b])) for b in range(1, len(blocks)))


def test_model_diameter_is_the_largest_distance():
    from scipy.spatial.distance import pdist

    from gatv.motions.instance_search import model_diameter

    pts = _model(4, 300)
    assert model_diameter(pts) == pytest.approx(pdist(pts).max(), rel=1e-12)
    assert model_diameter(pts[:10]) == pytest.approx(pdist(pts[:10]).max(), rel=1e-12)


def test_many_copies_are_searched_block_by_block_with_their_whole_correspondences():
    """Twelve exact copies on a grid among outliers: after the first copy the rounds search blocks of the scene,
    and every copy is found once, with all its points, even where a block's side cuts it."""
    model = _model(2, 50)
    rng = np.random.default_rng(8)
    rots = Rotation.random(12, random_state=9).as_matrix()
    grid = np.stack(np.meshgrid(np.arange(3), np.arange(2), np.arange(2), indexing="ij"), -1).reshape(-1, 3)
    poses = [(R, 4.0 * g + rng.uniform(-0.4, 0.4, 3)) for R, g in zip(rots, grid)]
    scene, owner = _scene(model, poses, n_outliers=300, seed=10)
    found = instances(model, scene, seed=0)
    assert len(found) == 12 and sorted(_match(found, poses, model)) == list(range(12))
    assert any("block" in r for r in found.info["rounds"])  # the blocks were searched
    assert any(r.get("whole_copy") is True for r in found.info["rounds"])  # a block's side cut a copy
    for k, m in enumerate(found):
        assert m.support == len(model)  # the whole copy's correspondences
        assert np.unique(owner[found.scene_rows(k)]).size == 1
    rows = np.concatenate([m.correspondences[:, 1] for m in found])
    assert np.unique(rows).size == rows.size


def test_a_fragment_too_small_for_a_copy_is_set_aside_once():
    """Two copies and a 30% fragment of the model apart: the fragment passes its verdict but is no copy; found on
    the whole scene after the blocks, it is set aside there once and for all (not searched again and again)."""
    model = _model(2, 50)
    rots = Rotation.random(3, random_state=5).as_matrix()
    cut = model[model[:, 0] > np.quantile(model[:, 0], 0.7)]
    pts = np.vstack([model @ rots[0].T, model @ rots[1].T + [12.0, 0, 0], cut @ rots[2].T + [24.0, 0, 0]])
    rng = np.random.default_rng(3)
    scene = np.vstack([pts, rng.uniform(pts.min(0) - 1, pts.max(0) + 1, (100, 3))])
    found = instances(model, scene, seed=0, time_limit=60)
    assert len(found) == 2 and found.info["exhausted"]
    small = [r for r in found.info["rounds"] if r.get("kept") is False]
    assert len(small) == 1 and "block" not in small[0]
    assert np.all(found.labels[100:115] == -1)  # the fragment's points belong to no instance


def _noisy_frames(model, k, n_frames, noise, seed, clutter=0.3):
    """Frames of ``k`` whole copies moving independently, Gaussian ``noise`` on every point, uniform clutter."""
    rng = np.random.default_rng(seed)
    size = model_size(model)
    poses = [(R, t * size / 6.0) for R, t in _poses(k, seed=seed, spread=6.0 * 1.5)]
    frames, truth = [], []
    for f in range(n_frames):
        if f:
            poses = [(Rotation.from_rotvec(rng.normal(0, 0.15, 3)).as_matrix() @ R, t + rng.normal(0, 0.05 * size, 3))
                     for R, t in poses]
        pts = np.vstack([model @ R.T + t for R, t in poses])
        pts = pts + rng.normal(0.0, noise, pts.shape)
        n_clutter = int(round(clutter / (1 - clutter) * len(pts)))
        frames.append(rng.permutation(np.vstack([pts, rng.uniform(pts.min(0), pts.max(0), (n_clutter, 3))])))
        truth.append(poses)
    return frames, truth


def _mesh_model(name: str, n: int = 150) -> np.ndarray:
    path = {"bunny": DATA / "stanford_bunny_reconstruction" / "bun_zipper_res4.ply",
            "ant": DATA / "pyvista_example_meshes" / "ant.ply"}[name]
    if not path.is_file():
        pytest.skip("real data (../shared/data) not available")
    pts = np.unique(read_points(path), axis=0)
    return pts[np.sort(np.random.default_rng(0).choice(len(pts), n, replace=False))]


def test_a_noisy_sequence_keeps_every_copy_and_its_identity():
    """The ant mesh, two copies, three frames, noise 2% of its RMS radius (0.2 of its spacing), 30% clutter."""
    model = _mesh_model("ant")
    rms = float(np.sqrt(np.mean(np.sum((model - model.mean(0)) ** 2, axis=1))))
    frames, truth = _noisy_frames(model, 2, 3, 0.02 * rms, seed=4)
    out = track(model, frames, seed=0)
    assert out.n_identities == 2 and out.present.all()
    size = model_size(model)
    for ident in range(2):
        which = set()
        for f in range(3):
            m = out.pose(ident, f)
            j = _match([m], truth[f], model)[0]
            which.add(j)
            R, t = truth[f][j]
            angle = np.degrees(np.arccos(np.clip((np.trace(R.T @ m.rotation) - 1) / 2, -1, 1)))
            assert angle < 2.0 and np.linalg.norm(m.rotation @ model.mean(0) + m.translation
                                                  - R @ model.mean(0) - t) < 0.02 * size
        assert len(which) == 1  # never swapped


@pytest.mark.slow
def test_noise_beyond_the_spacing_gives_no_wrong_instance():
    """Noise of 2% of the ant's bounding-box diagonal (0.9 of its spacing): a point's partner is lost
    among its neighbours, and the count verdict cannot tell the copy from chance; what is found is right."""
    model = _mesh_model("ant")
    frames, truth = _noisy_frames(model, 1, 1, 0.02 * model_size(model), seed=5)
    found = instances(model, frames[0], seed=0, time_limit=20)
    size = model_size(model)
    for m in found:
        R, t = truth[0][0]
        angle = np.degrees(np.arccos(np.clip((np.trace(R.T @ m.rotation) - 1) / 2, -1, 1)))
        assert angle < 5.0 and np.linalg.norm(m.translation - t) < 0.05 * size


@pytest.mark.slow
def test_copies_of_a_real_bunny_scan_against_another_view():
    """Two copies of bun045 among 30% clutter, bun000 as the model: both within 1 deg and 3 mm, nothing else."""
    from gatv.datasets import DataNotFoundError, load_bunny_pair

    try:
        model, view, R, t = load_bunny_pair("bun000", "bun045", DATA)
    except DataNotFoundError:
        pytest.skip("real data (../shared/data) not available")
    rng = np.random.default_rng(1)
    size = model_size(model)
    truth, copies = [], []
    for k, Q in enumerate(Rotation.random(2, random_state=1).as_matrix()):
        q = np.array([1.5 * size * k, 0.0, 0.0]) - Q @ view.mean(0)
        copies.append(view @ Q.T + q)
        truth.append((Q @ R.T, q - Q @ R.T @ t))
    pts = np.vstack(copies)
    scene = rng.permutation(np.vstack([pts, rng.uniform(pts.min(0), pts.max(0), (int(len(pts) * 3 / 7), 3))]))
    found = instances(model, scene, seed=0)
    assert found.info["pipeline"] == "scans" and len(found) == 2
    centre = model.mean(0)
    assert sorted(_match(found, truth, model)) == [0, 1]
    for m, j in zip(found, _match(found, truth, model)):
        Rt, tt = truth[j]
        angle = np.degrees(np.arccos(np.clip((np.trace(Rt.T @ m.rotation) - 1) / 2, -1, 1)))
        assert angle < 1.0 and np.linalg.norm(m.rotation @ centre + m.translation - Rt @ centre - tt) < 3e-3
    rows = np.concatenate([m.correspondences[:, 1] for m in found])
    assert np.unique(rows).size == rows.size


@pytest.mark.slow
def test_another_real_object_gives_no_instance():
    """Two copies of the parasaurolophus view among 30% clutter, the chef's view as the model: nothing.

    The scene of ``benchmarks/instances.py --real null`` (scene 1 of 2 copies), where the part of one copy
    once beat the wrong motions (margin 1.30) with pairs 7.9 times the scans' noise.  Either check sets
    such a part aside: the noise check, or the verdict, where a rival nearly as well supported counts as
    a wrong motion (1297c1e: "ambiguous: two motions ... explain the data alike").
    """
    from gatv.datasets import DataNotFoundError, load_uwa_pair

    try:
        model, view = load_uwa_pair("chef", DATA)[0], load_uwa_pair("parasaurolophus", DATA)[1]
    except DataNotFoundError:
        pytest.skip("real data (../shared/data) not available")
    rng = np.random.default_rng([0, 41, 2, 1, 4])
    size = model_size(model)
    centres, side = [], 1.6 * size * 2 ** (1 / 3)
    while len(centres) < 2:
        c = rng.uniform(0.0, side, 3)
        if all(np.linalg.norm(c - d) >= 1.2 * size for d in centres):
            centres.append(c)
        else:
            side *= 1.01
    rots = Rotation.random(2, random_state=rng).as_matrix()
    pts = np.vstack([view @ Q.T + c - Q @ view.mean(0) for Q, c in zip(rots, centres)])
    scene = np.vstack([pts, rng.uniform(pts.min(0), pts.max(0), (int(round(3 / 7 * len(pts))), 3))])
    found = instances(model, scene[rng.permutation(len(scene))], seed=1)
    assert not found and np.all(found.labels == -1)
    parts = [r for r in found.info["rounds"] if r.get("part")]
    assert parts and all(r.get("set_aside") and r.get("kept") is not True for r in parts)
    assert any("scans' noise" in r.get("reason", "") or "ambiguous" in r.get("reason", "") for r in parts)


@pytest.mark.slow
def test_parts_searched_in_vain_stop_within_one_registrations_time(monkeypatch):
    """Five copies of the parasaurolophus view, the chef's view as the model: each part searched in vain costs
    a whole scans search (11-15 s on 2 loaded cores); the parts searched in vain share one registration's
    time limit (here made 10 s), so the call ends with nothing found, before the last part, and a reason that
    says the scene was not exhausted."""
    import time

    from gatv.datasets import DataNotFoundError, load_uwa_pair
    from gatv.motions import instance_search

    try:
        model, view = load_uwa_pair("chef", DATA)[0], load_uwa_pair("parasaurolophus", DATA)[1]
    except DataNotFoundError:
        pytest.skip("real data (../shared/data) not available")
    rots = Rotation.random(5, random_state=2).as_matrix()
    size = model_size(model)
    scene = np.vstack([view @ Q.T + [1.5 * size * k, 0.0, 0.0] for k, Q in enumerate(rots)])
    monkeypatch.setattr(instance_search, "TIME_LIMIT", 10.0)  # one registration's bound, shortened
    t0 = time.perf_counter()
    found = instances(model, scene, seed=0)  # the call's own limit (600 s) is not what stops it
    took = time.perf_counter() - t0
    assert not found and np.all(found.labels == -1)
    searched = [r for r in found.info["rounds"] if r.get("part")]
    assert not found.info["exhausted"] and "in vain" in found.info["reason"]
    assert 1 <= len(searched) < 5  # not every part: the bound stopped the search
    assert took < 10.0 + max(r["time_s"] for r in searched)
