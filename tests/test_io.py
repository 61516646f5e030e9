from __future__ import annotations

import json
import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gatv.errors import InputError
from gatv.io import PointFileError, atomic_path, read_points, write_json, write_points


@pytest.fixture
def points():
    return np.random.default_rng(0).uniform(-5, 5, size=(30, 3))


@pytest.mark.parametrize("ext", [".xyz", ".txt", ".csv", ".pts", ".npy", ".vtk", ".vtp"])
def test_round_trip_exact(tmp_path, points, ext):
    path = tmp_path / f"cloud{ext}"
    write_points(path, points)
    back = read_points(path)
    assert back.dtype == np.float64 and back.flags.c_contiguous
    np.testing.assert_array_equal(back, points)


def test_round_trip_ply_float32(tmp_path, points):
    path = tmp_path / "cloud.ply"
    write_points(path, points)
    np.testing.assert_allclose(read_points(path), points, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("ext", [".stl", ".obj"])
def test_read_mesh_formats(tmp_path, ext):
    pv = pytest.importorskip("pyvista")
    mesh = pv.Cube().triangulate()
    path = tmp_path / f"cube{ext}"
    mesh.save(path)
    got = read_points(path)
    assert got.shape[1] == 3 and len(got) >= 8
    # every cube corner is present
    corners = np.unique(np.asarray(mesh.points), axis=0)
    d = np.min(np.linalg.norm(got[:, None] - corners[None], axis=2), axis=0)
    assert d.max() < 1e-6


def test_text_variants(tmp_path):
    path = tmp_path / "pts.csv"
    path.write_text("x,y,z,intensity\n1,2,3,9\n4,5,6,9\n# comment\n\n7, 8, 9, 9\n")
    np.testing.assert_array_equal(read_points(path), [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    path = tmp_path / "pts.xyz"
    path.write_text("1\t2 3\n4 5 6\n")
    np.testing.assert_array_equal(read_points(path), [[1, 2, 3], [4, 5, 6]])


def test_npy_extra_columns_and_single_point(tmp_path):
    path = tmp_path / "a.npy"
    np.save(path, np.arange(12.0).reshape(3, 4))
    np.testing.assert_array_equal(read_points(path), np.arange(12.0).reshape(3, 4)[:, :3])
    np.save(path, np.array([1.0, 2.0, 3.0]))
    assert read_points(path).shape == (1, 3)


@pytest.mark.parametrize(
    ("name", "content", "match"),
    [
        ("two.xyz", "1 2\n3 4\n", "at least 3 columns"),
        ("nan.xyz", "1 2 3\nnan 1 1\n", "NaN or infinite"),
        ("inf.csv", "1,2,3\n1,inf,1\n", "NaN or infinite"),
        ("empty.xyz", "# nothing\n", "no points"),
        ("ragged.txt", "1 2 3\n4 5\n", "line 2 has 2 columns"),
        ("words.txt", "1 2 3\na b c\n", "line 2 is not a row of numbers"),
        ("bad.ply", "this is not a ply file\n", "no points|cannot be read"),
        ("bad.vtk", "garbage", "no points|cannot be read"),
        ("bad.npy", "garbage", "cannot be read as .npy"),
        ("points.png", "x", "unknown point-file format"),
        ("noext", "1 2 3\n", "unknown point-file format"),
    ],
)
def test_bad_files_name_the_path(tmp_path, name, content, match):
    path = tmp_path / name
    path.write_text(content)
    with pytest.raises(PointFileError, match=match) as info:
        read_points(path)
    assert str(path) in str(info.value)
    assert isinstance(info.value, ValueError)


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(ValueError, match="no such file") as info:
        read_points(tmp_path / "missing.ply")
    assert str(tmp_path / "missing.ply") in str(info.value)
    with pytest.raises(ValueError, match="is a folder"):
        read_points(tmp_path)


def test_npy_wrong_shape(tmp_path):
    path = tmp_path / "flat.npy"
    np.save(path, np.zeros((2, 2, 3)))
    with pytest.raises(PointFileError, match="shape"):
        read_points(path)


def test_write_rejects_bad_input_without_writing(tmp_path, points):
    bad = points.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        write_points(tmp_path / "out.xyz", bad)
    with pytest.raises(PointFileError, match="cannot write points"):
        write_points(tmp_path / "out.stl", points)
    with pytest.raises(PointFileError, match="does not exist"):
        write_points(tmp_path / "nofolder" / "out.xyz", points)
    assert list(tmp_path.iterdir()) == []


def test_atomic_write_failure_leaves_nothing(tmp_path):
    dest = tmp_path / "out.json"
    with pytest.raises(RuntimeError), atomic_path(dest) as tmp:
        tmp.write_text("half")
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_atomic_write_failure_keeps_old_file(tmp_path, monkeypatch):
    dest = tmp_path / "out.json"
    write_json(dest, {"a": 1})

    def broken_dumps(*args, **kwargs):
        raise OSError("disk full")

    with pytest.raises(ValueError), atomic_path(dest) as tmp:
        tmp.write_text("partial")
        raise ValueError("disk full")
    monkeypatch.setattr(np, "savetxt", broken_dumps)
    with pytest.raises(OSError, match="disk full"):
        write_points(tmp_path / "out.xyz", np.zeros((2, 3)))
    assert json.loads(dest.read_text()) == {"a": 1}
    assert sorted(os.listdir(tmp_path)) == ["out.json"]


def test_write_json_numpy_and_nan(tmp_path):
    dest = tmp_path / "r.json"
    write_json(dest, {"m": np.eye(2), "x": np.float32(1.5), "n": np.int64(3), "nan": float("nan"), "p": tmp_path})
    data = json.loads(dest.read_text())
    assert data == {"m": [[1.0, 0.0], [0.0, 1.0]], "x": 1.5, "n": 3, "nan": None, "p": str(tmp_path)}
    assert "NaN" not in dest.read_text()


# ------------------------------------------------------------------------ PCD
from gatv.io import read_log, read_matrix, write_log, write_matrix


@pytest.mark.parametrize("ascii_", [False, True])
def test_pcd_round_trip(tmp_path, points, ascii_):
    path = tmp_path / "cloud.pcd"
    write_points(path, points, double=True)  # float64: exact, as ascii
    np.testing.assert_array_equal(read_points(path), points)
    write_points(path, points, ascii=ascii_)  # float32, as PCL and Open3D
    np.testing.assert_array_equal(read_points(path).astype(np.float32), points.astype(np.float32))
    head = path.read_bytes()[:400].decode("ascii", "replace")
    assert "FIELDS x y z" in head and "SIZE 4 4 4" in head and f"DATA {'ascii' if ascii_ else 'binary'}" in head


def _pcd_header(fields, sizes, types, n, data, counts=None):
    counts = counts or [1] * len(fields)
    return ("# .PCD v0.7\nVERSION 0.7\n"
            f"FIELDS {' '.join(fields)}\nSIZE {' '.join(map(str, sizes))}\nTYPE {' '.join(types)}\n"
            f"COUNT {' '.join(map(str, counts))}\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
            f"POINTS {n}\nDATA {data}\n").encode()


def test_pcd_binary_with_other_fields(tmp_path, points):
    """PCL's PointXYZRGBNormal-like records: x, y, z found among padding, colour and counts."""
    dtype = np.dtype([("rgb", "<u4"), ("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("_", "u1", (4,)),
                      ("normal", "<f8", (3,)), ("label", "<i2")])
    rec = np.zeros(len(points), dtype)
    rec["x"], rec["y"], rec["z"] = points.T
    rec["label"] = 7
    path = tmp_path / "rich.pcd"
    path.write_bytes(_pcd_header(["rgb", "x", "y", "z", "_", "normal", "label"], [4, 4, 4, 4, 1, 8, 2],
                                 ["U", "F", "F", "F", "U", "F", "I"], len(points), "binary",
                                 [1, 1, 1, 1, 4, 3, 1]) + rec.tobytes())
    np.testing.assert_array_equal(read_points(path), points.astype(np.float32).astype(np.float64))
    text = "\n".join(" ".join(["9", *(f"{v:.17g}" for v in p), "1 2 3 4", "0 0 1", "7"]) for p in points)
    path.write_bytes(_pcd_header(["rgb", "x", "y", "z", "_", "normal", "label"], [4, 8, 8, 8, 1, 8, 2],
                                 ["U", "F", "F", "F", "U", "F", "I"], len(points), "ascii",
                                 [1, 1, 1, 1, 4, 3, 1]) + text.encode())
    np.testing.assert_array_equal(read_points(path), points)


#: Open3D 0.20's binary_compressed (LZF) PCD of 6 copies of (0.5, -1.25, 2) then (k, 2k, -k), k < 6.
_O3D_COMPRESSED = ("TwAAAJAAAAAEAAAAPwDgDQMgAACAQBsAQCACIAMAgCADAKBAAwC/IAfgCgNgACAfQCcAwCAHBABBAAAgIANAE+AM"
                   "AyAAAIAgRwEAwCAeIAMAgCADAaDA")


def test_pcd_binary_compressed(tmp_path):
    import base64

    expected = np.array([[0.5, -1.25, 2.0]] * 6 + [[k, 2 * k, -k] for k in range(6)], dtype=np.float64)
    path = tmp_path / "o3d.pcd"
    header = _pcd_header(["x", "y", "z"], [4, 4, 4], ["F", "F", "F"], 12, "binary_compressed")
    path.write_bytes(header + base64.b64decode(_O3D_COMPRESSED))
    np.testing.assert_array_equal(read_points(path), expected)
    corrupt = bytearray(base64.b64decode(_O3D_COMPRESSED))
    corrupt[14] = 0xFF  # the first back reference now points before the start
    path.write_bytes(header + bytes(corrupt))
    with pytest.raises(PointFileError, match="corrupt compressed"):
        read_points(path)


@pytest.mark.parametrize("body, match", [
    (_pcd_header(["a", "b", "c"], [4, 4, 4], ["F", "F", "F"], 1, "ascii") + b"1 2 3\n", "no x, y, z"),
    (_pcd_header(["x", "y", "z"], [4, 4, 4], ["F", "F", "F"], 3, "binary") + b"\0" * 20, "truncated"),
    (_pcd_header(["x", "y", "z"], [4, 4, 4], ["F", "F", "F"], 1, "lzma") + b"", "DATA kind"),
    (_pcd_header(["x", "y", "z"], [4, 4, 4], ["F", "F", "F"], 2, "ascii") + b"1 2 3\n", "expected 2 points"),
    (_pcd_header(["x", "y", "z"], [4, 4, 4], ["F", "F", "F"], 1, "ascii") + b"nan 2 3\n", "NaN"),
    (_pcd_header(["x", "y", "z"], [2, 4, 4], ["F", "F", "F"], 1, "ascii") + b"1 2 3\n", "unsupported"),
    (b"VERSION 0.7\nFIELDS x y z\n", "no DATA line"),
])
def test_pcd_bad_files(tmp_path, body, match):
    path = tmp_path / "bad.pcd"
    path.write_bytes(body)
    with pytest.raises(PointFileError, match=match) as info:
        read_points(path)
    assert str(info.value).startswith(str(path))


# ------------------------------------------------------------------- matrices
def test_matrix_and_log_round_trip(tmp_path):
    from gatv.motion import RigidMotion

    rng = np.random.default_rng(4)
    m = np.eye(4)
    m[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0] * [1, 1, 1]
    m[:3, 3] = rng.normal(size=3)
    write_matrix(tmp_path / "m.txt", m)
    np.testing.assert_array_equal(read_matrix(tmp_path / "m.txt"), m)
    np.testing.assert_array_equal(np.loadtxt(tmp_path / "m.txt"), m)  # what Open3D's examples load
    motion = RigidMotion.from_matrix(m) if np.linalg.det(m[:3, :3]) > 0 else RigidMotion.from_matrix(np.eye(4))
    write_log(tmp_path / "t.log", [(0, 1, 2, m), (1, 2, 2, motion)])
    back = read_log(tmp_path / "t.log")
    assert [(i, j, n) for i, j, n, _ in back] == [(0, 1, 2), (1, 2, 2)]
    np.testing.assert_array_equal(back[0][3], m)
    np.testing.assert_array_equal(back[1][3], motion.matrix)
    with pytest.raises(ValueError, match=r"shape \(4, 4\)"):
        write_matrix(tmp_path / "bad.txt", np.eye(3))
    assert not (tmp_path / "bad.txt").exists()
    (tmp_path / "short.log").write_text("0 1 2\n1 0 0 0\n")
    with pytest.raises(PointFileError, match="blocks of 5 lines"):
        read_log(tmp_path / "short.log")


# ------------------------------------------------------------ per-point scalars
@pytest.mark.parametrize("ext", [".ply", ".vtk", ".vtp", ".csv"])
def test_scalars_round_trip(tmp_path, points, ext):
    labels = np.arange(len(points), dtype=np.int64) % 4 - 1  # -1 = unexplained, as segment writes
    weight = np.random.default_rng(1).uniform(0, 1, len(points))
    path = tmp_path / f"labelled{ext}"
    write_points(path, points, scalars={"motion": labels, "weight": weight})
    back, scalars = read_points(path, scalars=True)
    np.testing.assert_allclose(back, points, rtol=1e-6, atol=1e-6)  # PLY: float32 coordinates
    assert list(scalars) == ["motion", "weight"]
    np.testing.assert_array_equal(scalars["motion"], labels)
    np.testing.assert_array_equal(scalars["weight"], weight)  # float64 kept exactly
    if ext != ".csv":  # text holds numbers, binary formats keep the type
        assert scalars["motion"].dtype == np.int32
    np.testing.assert_array_equal(read_points(path), back)  # without scalars=: the points alone


@settings(max_examples=25, deadline=None)
@given(labels=st.lists(st.integers(-(2**31), 2**31 - 1), min_size=1, max_size=40),
       kind=st.sampled_from(["int8", "uint8", "int16", "int32", "float32", "float64"]))
def test_ply_scalars_keep_every_value_and_type(tmp_path_factory, labels, kind):
    values = np.array(labels, dtype=np.int64)
    info = np.iinfo(kind) if kind.startswith(("int", "uint")) else None
    if info is not None:
        values = np.clip(values, info.min, info.max)
    values = values.astype(kind)
    pts = np.column_stack([np.arange(len(values), dtype=float)] * 3)
    path = tmp_path_factory.mktemp("ply") / "s.ply"
    write_points(path, pts, scalars={"v": values})
    _, scalars = read_points(path, scalars=True)
    assert scalars["v"].dtype == values.dtype
    np.testing.assert_array_equal(scalars["v"], values)


def test_ply_scalars_from_other_writers(tmp_path):
    """An ascii PLY with a face element after the vertices, and a big-endian binary one."""
    path = tmp_path / "a.ply"
    path.write_text("ply\nformat ascii 1.0\ncomment made by hand\nelement vertex 3\nproperty float x\n"
                    "property float y\nproperty float z\nproperty uchar red\nproperty int motion\n"
                    "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
                    "0 0 0 255 2\n1 0 0 0 -1\n0 1 0 7 0\n3 0 1 2\n")
    pts, scalars = read_points(path, scalars=True)
    np.testing.assert_array_equal(pts, [[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    np.testing.assert_array_equal(scalars["motion"], [2, -1, 0])
    np.testing.assert_array_equal(scalars["red"], [255, 0, 7])
    rows = np.array([(0.0, 0.0, 0.0, 5), (1.0, 2.0, 3.0, -4)], dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4"),
                                                                      ("motion", ">i4")])
    path = tmp_path / "b.ply"
    path.write_bytes(b"ply\nformat binary_big_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                     b"property float z\nproperty int motion\nend_header\n" + rows.tobytes())
    pts, scalars = read_points(path, scalars=True)
    np.testing.assert_array_equal(pts, [[0, 0, 0], [1, 2, 3]])
    np.testing.assert_array_equal(scalars["motion"], [5, -4])


@pytest.mark.parametrize("ext", [".xyz", ".npy", ".pcd"])
def test_formats_without_named_scalars(tmp_path, points, ext):
    path = tmp_path / f"p{ext}"
    with pytest.raises(PointFileError, match="`scalars`"):
        write_points(path, points, scalars={"motion": np.zeros(len(points), int)})
    assert not path.exists()
    write_points(path, points)
    back, scalars = read_points(path, scalars=True)
    assert scalars == {} and back.shape == points.shape


@pytest.mark.parametrize("scalars, match", [
    ([1, 2, 3], "mapping"),
    ({"motion": np.zeros(29)}, r"scalars\['motion'\].*\(30,\).*\(29,\)"),
    ({"motion": np.zeros((30, 2))}, r"scalars\['motion'\]"),
    ({"x": np.zeros(30)}, "coordinates"),
    ({"two words": np.zeros(30)}, "letters, digits"),
    ({"m": np.zeros(30), "M": np.ones(30)}, "differ"),
    ({"motion": np.array(["a"] * 30)}, "numbers"),
    ({"motion": np.full(30, 2**40)}, "32-bit"),
])
def test_bad_scalars_name_the_argument_and_write_nothing(tmp_path, points, scalars, match):
    path = tmp_path / "out.ply"
    with pytest.raises(InputError, match=match):
        write_points(path, points, scalars=scalars)
    assert not path.exists() and not list(tmp_path.iterdir())


# ------------------------------------------------ what the Python API is handed (issue 42)
@pytest.mark.parametrize("path", ["a.ply", "scan.pcd"])
def test_register_given_file_paths_points_to_read_points(path):
    import pathlib

    import gatv

    for given in (path, pathlib.Path(path)):
        with pytest.raises(InputError, match=r"gatv\.io\.read_points") as info:
            gatv.register(given, given)
        assert "could not convert" not in str(info.value)


def test_pixels_given_an_image_path_point_to_detect_corners():
    from gatv._validation import as_points

    with pytest.raises(InputError, match=r"catadioptric\.corners\.detect_corners"):
        as_points("view.png", "pixels1", dim=2)


@given(n=st.integers(4, 60), imag=st.floats(-1e3, 1e3).filter(lambda v: v != 0))
@settings(max_examples=25, deadline=None)
def test_complex_points_are_refused(n, imag):
    from gatv._validation import as_points

    pts = np.random.default_rng(n).normal(size=(n, 3)) + 1j * imag
    with pytest.raises(InputError, match="complex"):
        as_points(pts, "source")
    with pytest.raises(InputError, match="complex"):
        as_points(pts.astype(np.complex64) * 0 + 1, "source")  # zero imaginary part: still refused


@given(n=st.integers(4, 60).filter(lambda n: n != 3))
@settings(max_examples=25, deadline=None)
def test_transposed_points_are_named_transposed(n):
    from gatv._validation import as_points

    pts = np.random.default_rng(n).normal(size=(n, 3))
    with pytest.raises(InputError, match=rf"transpose.*\({n}, 3\)"):
        as_points(pts.T, "source")


def test_read_only_points_come_back_writable_and_equal():
    from gatv._validation import as_points

    pts = np.random.default_rng(1).normal(size=(20, 3))
    pts.setflags(write=False)
    out = as_points(pts, "source")
    assert out.flags.writeable and out.flags.c_contiguous
    np.testing.assert_array_equal(out, pts)
    writable = np.ascontiguousarray(pts.copy())
    assert as_points(writable, "source") is writable  # no copy when none is needed


def _open3d_legacy_pcd(path) -> np.ndarray:
    """The coordinates Open3D's legacy PCD reader (io/file_format/FilePCD.cpp) gets: it
    unpacks binary ``F`` fields of size 4 only and gives 0.0 for any other size, while
    its ascii parser reads every ``F`` field with strtod."""
    raw = path.read_bytes()
    end = raw.index(b"DATA ")
    end = raw.index(b"\n", end) + 1
    head = dict(line.split(" ", 1) for line in raw[:end].decode().splitlines() if line and line[0] != "#")
    sizes = [int(v) for v in head["SIZE"].split()]
    n = int(head["POINTS"])
    if head["DATA"].strip() == "ascii":
        return np.loadtxt(raw[end:].decode().splitlines(), ndmin=2)[:, :3]
    rows = np.frombuffer(raw[end:], dtype="<f%d" % sizes[0], count=3 * n).reshape(n, 3)
    return rows.astype(np.float64) if sizes[0] == 4 else np.zeros((n, 3))


@given(n=st.integers(1, 40), double=st.booleans(), seed=st.integers(0, 2**16))
@settings(max_examples=30, deadline=None)
def test_pcd_as_written_reads_right_in_open3d_legacy(tmp_path_factory, n, double, seed):
    """Issue 42: binary float64 PCD read as zeros in o3d.io.read_point_cloud."""
    pts = np.random.default_rng(seed).uniform(-100, 100, (n, 3))
    path = tmp_path_factory.mktemp("pcd") / "c.pcd"
    write_points(path, pts, double=double)
    want = pts if double else pts.astype(np.float32).astype(np.float64)
    np.testing.assert_allclose(_open3d_legacy_pcd(path), want, rtol=1e-15 if double else 1e-7)
    np.testing.assert_array_equal(read_points(path), want)


def test_binary_double_pcd_is_refused_and_nothing_written(tmp_path, points):
    path = tmp_path / "c.pcd"
    with pytest.raises(PointFileError, match="Open3D's legacy reader"):
        write_points(path, points, ascii=False, double=True)
    assert not path.exists() and os.listdir(tmp_path) == []


def test_pcd_in_open3d_legacy_reader(tmp_path, points):
    o3d = pytest.importorskip("open3d")
    path = tmp_path / "c.pcd"
    write_points(path, points, double=True)
    np.testing.assert_allclose(np.asarray(o3d.io.read_point_cloud(str(path)).points), points, rtol=1e-15)
