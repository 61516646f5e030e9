"""Open3D and trimesh objects go in wherever arrays do (duck-typed; neither library is imported
unless given one), and gatv's PCD and matrices round-trip through Open3D."""

from __future__ import annotations

import functools
import subprocess
import sys

import numpy as np
import pytest

import gatv
from gatv._validation import as_points
from gatv.datasets import table2_trial
from gatv.io import read_points, write_points


@functools.cache
def _importable(name: str) -> bool:
    """Import ``name`` in a child process first: a broken binary wheel can crash, not raise."""
    done = subprocess.run([sys.executable, "-c", f"import {name}"], capture_output=True, timeout=300, check=False)
    return done.returncode == 0


def _need(name: str):
    pytest.importorskip(name)  # skips cleanly when not installed
    if not _importable(name):
        pytest.skip(f"{name} is installed but cannot be imported here")
    return sys.modules[name]


@pytest.fixture(scope="module")
def trial():
    return table2_trial(0.5, n_inliers=20, seed=8)


def _same_motion(a, b):
    np.testing.assert_array_equal(a.matrix, b.matrix)
    np.testing.assert_array_equal(a.correspondences, b.correspondences)


def test_duck_typed_inputs_import_nothing():
    code = (
        "import sys, numpy as np\n"
        "from gatv._validation import as_points\n"
        "class Mesh:\n    vertices = np.eye(3)\n"
        "class Tensor:\n    def __init__(self, a): self.a = a\n    def numpy(self): return self.a\n"
        "class Map:\n    positions = Tensor(2 * np.eye(3))\n"
        "class TCloud:\n    point = Map()\n"
        "assert (as_points(Mesh(), 'm') == np.eye(3)).all()\n"
        "assert (as_points(TCloud(), 't') == 2 * np.eye(3)).all()\n"
        "assert 'open3d' not in sys.modules and 'trimesh' not in sys.modules\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr


def test_open3d_point_clouds_register_like_arrays(trial):
    o3d = _need("open3d")
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(trial.source)))
    tgt = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.array(trial.target)))
    motion = gatv.register(src, tgt, seed=1)
    _same_motion(motion, gatv.register(trial.source, trial.target, seed=1))
    assert {tuple(p) for p in trial.true_pairs} <= {tuple(p) for p in motion.correspondences}
    # the 4x4 matrix moves an Open3D cloud onto the target as motion.transform does
    moved = np.asarray(src.transform(motion.matrix).points)
    np.testing.assert_allclose(moved, motion.transform(trial.source), atol=1e-12)
    mesh = o3d.geometry.TriangleMesh.create_box()
    np.testing.assert_array_equal(as_points(mesh, "mesh"), np.asarray(mesh.vertices))
    with pytest.raises(ValueError, match="at least 1 point"):
        as_points(o3d.geometry.PointCloud(), "source")


def test_trimesh_objects_register_like_arrays(trial):
    trimesh = _need("trimesh")
    src = trimesh.PointCloud(trial.source)
    tgt = trimesh.Trimesh(vertices=trial.target, faces=np.zeros((0, 3), int), process=False)
    _same_motion(gatv.register(src, tgt, seed=2), gatv.register(trial.source, trial.target, seed=2))
    box = trimesh.creation.box()
    np.testing.assert_array_equal(as_points(box, "box"), np.asarray(box.vertices))


@pytest.mark.parametrize("ascii_", [False, True])
def test_pcd_through_open3d(tmp_path, trial, ascii_):
    o3d = _need("open3d")
    pts = np.array(trial.source)
    ours = tmp_path / "ours.pcd"
    write_points(ours, pts, ascii=ascii_)
    back = np.asarray(o3d.io.read_point_cloud(str(ours)).points)
    np.testing.assert_array_equal(back.astype(np.float32), pts.astype(np.float32))
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    for kind, options in (("ascii", {"write_ascii": True}), ("binary", {}), ("compressed", {"compressed": True})):
        theirs = tmp_path / f"{kind}.pcd"
        o3d.io.write_point_cloud(str(theirs), cloud, **options)
        np.testing.assert_array_equal(read_points(theirs), np.asarray(o3d.io.read_point_cloud(str(theirs)).points))
