from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from gatv import cli
from gatv.cli import register as register_cmd
from gatv.cli import segment as segment_cmd
from gatv.datasets import correspondence_stats, table2_trial
from gatv.errors import InputError
from gatv.io import read_points, write_points
from gatv.motion import RigidMotion

try:
    import gatv.registration  # noqa: F401

    HAVE_REGISTRATION = True
except ImportError:
    HAVE_REGISTRATION = False


@pytest.fixture
def trial():
    return table2_trial(0.5, seed=4)


@pytest.fixture
def files(tmp_path, trial):
    src, tgt = tmp_path / "source.xyz", tmp_path / "target.npy"
    write_points(src, trial.source)
    write_points(tgt, trial.target)
    return src, tgt


@pytest.fixture
def fake(monkeypatch, trial):
    """Replace gatv.register by a fake returning the true motion."""
    calls = []

    def register(source, target, *, seed=0, progress=None, **options):
        calls.append({"seed": seed, "options": options, "progress": progress, "n": len(source)})
        if progress is not None:
            progress(0.5, "halfway")
            progress(1.0, "done")
        return RigidMotion(
            trial.rotation, trial.translation, trial.true_pairs, score=1.0, rms=0.0,
            info={"mode": "fake", "array": np.arange(3)},
        )

    monkeypatch.setattr(register_cmd, "load_register", lambda scans=False: register)
    return calls


def _listing(folder):
    return sorted(p.name for p in folder.iterdir())


def test_register_end_to_end(tmp_path, files, fake, trial, capsys):
    src, tgt = files
    out, aligned = tmp_path / "result.json", tmp_path / "aligned.npy"
    rc = cli.main([
        "register", str(src), str(tgt), "--out", str(out), "--aligned", str(aligned),
        "--seed", "3", "--max-angle", "5", "--max-translation", "2.5",
    ])
    assert rc == 0
    stdout = capsys.readouterr().out
    assert f"rotation:        {trial.angle_deg:.4f} deg" in stdout
    assert "correspondences: 50" in stdout and "rms:" in stdout and "time:" in stdout
    assert fake == [{"seed": 3, "options": {"max_angle": 5.0, "max_translation": 2.5}, "progress": None, "n": 100}]
    data = json.loads(out.read_text())
    assert data["source"] == str(src) and data["target"] == str(tgt)
    assert data["seed"] == 3 and data["success"] is True and data["support"] == 50
    np.testing.assert_allclose(data["rotation"], trial.rotation)
    np.testing.assert_allclose(data["translation"], trial.translation)
    assert data["correspondences"] == trial.true_pairs.tolist()
    assert data["info"] == {"mode": "fake", "array": [0, 1, 2]}
    assert data["model"] == "rigid" and "model:           rigid" in stdout
    np.testing.assert_allclose(np.asarray(data["matrix"])[:3, :3], trial.rotation)
    np.testing.assert_allclose(np.asarray(data["matrix"])[:3, 3], trial.translation)
    np.testing.assert_allclose(np.asarray(data["matrix"])[3], [0, 0, 0, 1])
    moved = read_points(aligned)
    pairs = trial.true_pairs
    np.testing.assert_allclose(moved[pairs[:, 0]], trial.target[pairs[:, 1]], atol=1e-9)
    assert _listing(tmp_path) == ["aligned.npy", "result.json", "source.xyz", "target.npy"]


def test_quiet_and_progress(files, fake, capsys):
    src, tgt = files
    assert cli.main(["register", str(src), str(tgt), "--quiet", "--progress"]) == 0
    captured = capsys.readouterr()
    assert captured.out == ""
    assert "[ 50.0%] halfway" in captured.err and "[100.0%] done" in captured.err
    assert callable(fake[0]["progress"])


def test_render_writes_picture(tmp_path, files, fake):
    src, tgt = files
    png = tmp_path / "picture.png"
    assert cli.main(["register", str(src), str(tgt), "--render", str(png), "-q"]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _assert_one_error_line(capsys, *fragments):
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("gatv: error: ")
    assert "Traceback" not in captured.err
    for fragment in fragments:
        assert fragment in lines[0]


@pytest.mark.parametrize(
    ("content", "fragment"),
    [
        (None, "no such file"),
        ("1 2\n3 4\n5 6\n", "at least 3 columns"),
        ("1 2 3\nnan 0 0\n4 5 6\n", "NaN"),
        ("1 2 3\n4 5 6\n", "at least 3 points"),
        ("x y z\n", "no points"),
    ],
)
def test_bad_input_one_line_exit_2_nothing_written(tmp_path, files, fake, capsys, content, fragment):
    src, _ = files
    bad = tmp_path / "bad.xyz"
    if content is not None:
        bad.write_text(content)
    before = _listing(tmp_path)
    rc = cli.main([
        "register", str(src), str(bad), "--out", str(tmp_path / "r.json"),
        "--aligned", str(tmp_path / "a.ply"), "--render", str(tmp_path / "p.png"),
    ])
    assert rc == 2
    _assert_one_error_line(capsys, str(bad), fragment)
    assert _listing(tmp_path) == before
    assert fake == []


def test_register_input_error_is_one_line(tmp_path, files, monkeypatch, capsys):
    src, tgt = files

    def register(source, target, **kwargs):
        raise InputError("Expected `max_angle` in degrees,\nat most 180, got 500.0.")

    monkeypatch.setattr(register_cmd, "load_register", lambda scans=False: register)
    before = _listing(tmp_path)
    rc = cli.main(["register", str(src), str(tgt), "--max-angle", "500", "--out", str(tmp_path / "r.json")])
    assert rc == 2
    _assert_one_error_line(capsys, "max_angle", "at most 180")
    assert "InputError" not in capsys.readouterr().err
    assert _listing(tmp_path) == before


@pytest.mark.parametrize("error", [ValueError("operands could not be broadcast\ntogether"),
                                   RuntimeError("kernel failed"), IndexError("index 7 is out of bounds")])
def test_internal_error_is_exit_1_one_line_no_traceback(tmp_path, files, monkeypatch, capsys, error):
    """Only InputError and OSError are bad input: a plain ValueError deep inside is a bug, status 1."""
    src, tgt = files

    def register(source, target, **kwargs):
        raise error

    monkeypatch.setattr(register_cmd, "load_register", lambda scans=False: register)
    monkeypatch.delenv("GATV_DEBUG", raising=False)
    before = _listing(tmp_path)
    rc = cli.main(["register", str(src), str(tgt), "--out", str(tmp_path / "r.json")])
    assert rc == 1
    message = " ".join(str(error).split())
    _assert_one_error_line(capsys, f"gatv: error: {type(error).__name__}: {message}",
                           "(set GATV_DEBUG=1 for a traceback)")
    assert _listing(tmp_path) == before


def test_internal_error_with_gatv_debug_raises(files, monkeypatch):
    src, tgt = files

    def register(source, target, **kwargs):
        raise ValueError("deep inside")

    monkeypatch.setattr(register_cmd, "load_register", lambda scans=False: register)
    monkeypatch.setenv("GATV_DEBUG", "1")
    with pytest.raises(ValueError, match="deep inside"):
        cli.main(["register", str(src), str(tgt)])


def test_internal_error_in_segment_is_exit_1(files, monkeypatch, capsys):
    def segment(source, target, **kwargs):
        raise ValueError("plain ValueError from numpy")

    monkeypatch.setattr(segment_cmd, "load_segment", lambda: segment)
    src, tgt = files
    assert cli.main(["segment", str(src), str(tgt), "-q"]) == 1
    _assert_one_error_line(capsys, "ValueError: plain ValueError from numpy", "GATV_DEBUG=1")


@pytest.mark.parametrize("command", ["register", "segment"])
def test_unknown_model_is_exit_2_and_lists_models(files, fake, capsys, command):
    src, tgt = files
    assert cli.main([command, str(src), str(tgt), "--model", "projective"]) == 2
    _assert_one_error_line(capsys, "--model", "projective", "rigid", "similarity")
    assert fake == []


def test_model_option_is_passed_only_when_not_rigid(files, fake, capsys):
    src, tgt = files
    assert cli.main(["register", str(src), str(tgt), "-q", "--model", "rigid"]) == 0
    assert cli.main(["register", str(src), str(tgt), "-q", "--model", "similarity"]) == 0
    assert [call["options"] for call in fake] == [{}, {"model": "similarity"}]
    assert cli.main(["register", str(src), str(tgt), "--scans", "--model", "similarity"]) == 2
    _assert_one_error_line(capsys, "--scans takes no --model")


class _FakeSegmentation:
    """What `gatv segment` reads of a gatv.motions.Segmentation."""

    def __init__(self, motions, source_labels, target_labels):
        self.motions, self.source_labels, self.target_labels = motions, source_labels, target_labels
        self.info = {}

    def __len__(self):
        return len(self.motions)

    def __bool__(self):
        return bool(self.motions)

    def to_dict(self):
        return {"n_motions": len(self), "motions": [m.to_dict() for m in self.motions]}


def test_segment_passes_model_and_prints_generic_summary(tmp_path, files, monkeypatch, capsys, trial):
    calls = []
    motion = RigidMotion(trial.rotation, trial.translation, trial.true_pairs, score=1.0, rms=0.0)

    def segment(source, target, **kwargs):
        calls.append(kwargs)
        src_lab = np.full(len(source), -1)
        tgt_lab = np.full(len(target), -1)
        src_lab[trial.true_pairs[:, 0]] = 0
        tgt_lab[trial.true_pairs[:, 1]] = 0
        return _FakeSegmentation((motion,), src_lab, tgt_lab)

    monkeypatch.setattr(segment_cmd, "load_segment", lambda: segment)
    src, tgt = files
    out = tmp_path / "s.json"
    assert cli.main(["segment", str(src), str(tgt), "--out", str(out)]) == 0
    assert cli.main(["segment", str(src), str(tgt), "-q", "--model", "similarity", "--time-limit", "5"]) == 0
    assert "model" not in calls[0] and calls[1]["model"] == "similarity"
    assert "time_limit" not in calls[0] and calls[1]["time_limit"] == 5.0
    stdout = capsys.readouterr().out
    assert "model:           rigid" in stdout and "motions:         1" in stdout
    assert f"motion 0:        {trial.angle_deg:.4f} deg about axis" in stdout
    assert "50 correspondences" in stdout
    data = json.loads(out.read_text())
    assert data["success"] is True and data["source"] == str(src) and data["n_motions"] == 1
    assert data["motions"][0]["model"] == "rigid" and len(data["motions"][0]["matrix"]) == 4


def test_register_summary_names_an_ambiguous_motion():
    from gatv.cli.register import summary

    motion = RigidMotion(np.eye(3), np.zeros(3), np.array([[0, 0], [1, 1], [2, 2]]), score=3.0, rms=0.0,
                         info={"ambiguous": True, "rival": {"angle_deg": 90.0}})
    assert "ambiguous:       a distinct motion 90 deg away fits nearly as well (a symmetric object?)" in summary(
        motion, 0.1)
    plain = RigidMotion(np.eye(3), np.zeros(3), np.array([[0, 0], [1, 1], [2, 2]]), score=3.0, rms=0.0,
                        info={"ambiguous": False})
    assert not any(line.startswith("ambiguous") for line in summary(plain, 0.1))


def test_segment_prints_degenerate_and_ambiguous_parts(files, monkeypatch, capsys):
    """Parts a scan segmentation saw and left unexplained on purpose are named, one line each."""
    def segment(source, target, **kwargs):
        result = _FakeSegmentation((), np.full(len(source), -1), np.full(len(target), -1))
        result.info = {"degenerate": [{"points": 120}],
                       "ambiguous": [{"points": 248, "rival_angle_deg": 31.6},
                                     {"points": 90, "rival_angle_deg": None}]}
        return result

    monkeypatch.setattr(segment_cmd, "load_segment", lambda: segment)
    src, tgt = files
    cli.main(["segment", str(src), str(tgt)])
    lines = capsys.readouterr().out.splitlines()
    assert "degenerate:      a plane-like part of 120 points (a motion could slide along it)" in lines
    assert ("ambiguous:       a part of 248 points fits two distinct motions (32 deg apart); none reported"
            in lines)
    assert "ambiguous:       a part of 90 points fits two distinct motions; none reported" in lines


@pytest.mark.parametrize(
    ("option", "name", "fragment"),
    [
        ("--aligned", "aligned.stl", "cannot write aligned points"),
        ("--render", "picture.ply", "cannot write a picture"),
        ("--out", "missing_folder/r.json", "does not exist"),
    ],
)
def test_bad_output_fails_before_work(tmp_path, files, fake, capsys, option, name, fragment):
    src, tgt = files
    rc = cli.main(["register", str(src), str(tgt), option, str(tmp_path / name)])
    assert rc == 2
    _assert_one_error_line(capsys, fragment)
    assert fake == []


def test_failure_in_last_output_leaves_no_output(tmp_path, files, fake, monkeypatch, capsys):
    src, tgt = files

    def broken(*args):
        raise OSError("disk full")

    monkeypatch.setattr(register_cmd, "render", broken)
    before = _listing(tmp_path)
    rc = cli.main([
        "register", str(src), str(tgt), "--out", str(tmp_path / "r.json"),
        "--aligned", str(tmp_path / "a.xyz"), "--render", str(tmp_path / "p.png"), "-q",
    ])
    assert rc == 2
    _assert_one_error_line(capsys, "disk full")
    assert _listing(tmp_path) == before


def test_no_motion_found_exit_1_json_only(tmp_path, files, monkeypatch, capsys):
    src, tgt = files
    failed = RigidMotion(np.eye(3), np.zeros(3), info={"reason": "no plane above chance"})
    monkeypatch.setattr(register_cmd, "load_register", lambda scans=False: lambda s, t, **kw: failed)
    out = tmp_path / "r.json"
    rc = cli.main(["register", str(src), str(tgt), "--out", str(out), "--aligned", str(tmp_path / "a.xyz")])
    assert rc == 1
    assert "registration failed: no plane above chance" in capsys.readouterr().err
    data = json.loads(out.read_text())
    assert data["success"] is False and data["support"] == 0 and data["rms"] is None
    assert not (tmp_path / "a.xyz").exists()


def test_usage_errors(capsys):
    assert cli.main(["register", "only-one.xyz"]) == 2
    _assert_one_error_line(capsys, "required")
    assert cli.main(["register", "a.xyz", "b.xyz", "--seed", "x"]) == 2
    _assert_one_error_line(capsys, "--seed")
    assert cli.main(["--help"]) == 0
    assert cli.main([]) == 2


def test_missing_registration_module(files, monkeypatch, capsys):
    src, tgt = files
    monkeypatch.setitem(sys.modules, "gatv.registration", None)  # import fails
    assert cli.main(["register", str(src), str(tgt)]) == 1
    _assert_one_error_line(capsys, "gatv.registration cannot be imported")


def test_python_dash_m_missing_file(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "gatv", "register", str(tmp_path / "nope.ply"), str(tmp_path / "b.ply")],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [f"gatv: error: {tmp_path / 'nope.ply'}: no such file."]


@pytest.mark.skipif(not HAVE_REGISTRATION, reason="gatv.registration (gatv.register) cannot be imported yet")
def test_real_register_end_to_end(tmp_path, files, trial):
    src, tgt = files
    out = tmp_path / "r.json"
    assert cli.main(["register", str(src), str(tgt), "--out", str(out), "-q"]) == 0
    data = json.loads(out.read_text())
    precision, recall = correspondence_stats(data["correspondences"], trial.true_pairs)
    assert recall >= 0.9 and precision >= 0.9


def test_scans_option_forces_the_scans_pipeline(tmp_path, monkeypatch, capsys):
    """``--scans`` (= ``--pipeline scans``) forces the scans pipeline and refuses options it does not take."""
    rng = np.random.default_rng(0)
    u = rng.normal(size=(3000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    src, tgt = tmp_path / "a.npy", tmp_path / "b.npy"
    write_points(src, u * [1.0, 0.7, 0.5])
    write_points(tgt, u * [1.0, 0.7, 0.5] + 0.01)
    seen = []
    monkeypatch.setattr(register_cmd, "load_register",
                        lambda: (lambda s, t, **kw: seen.append(kw.get("pipeline", "auto")) or RigidMotion(
                            np.eye(3), np.full(3, 0.01), np.c_[np.arange(5), np.arange(5)])))
    assert cli.main(["register", str(src), str(tgt), "--scans", "-q"]) == 0
    assert cli.main(["register", str(src), str(tgt), "--pipeline", "exact", "-q"]) == 0
    assert cli.main(["register", str(src), str(tgt), "-q"]) == 0
    assert seen == ["scans", "exact", "auto"]
    assert cli.main(["register", str(src), str(tgt), "--scans", "--noise", "0.1"]) == 2
    _assert_one_error_line(capsys, "--scans takes no --noise")
    assert cli.main(["register", str(src), str(tgt), "--scans", "--pipeline", "exact"]) == 2
    _assert_one_error_line(capsys, "--scans contradicts --pipeline exact")


def test_nonrigid_subcommand_is_wired(tmp_path, capsys):
    assert cli.main(["nonrigid", str(tmp_path / "nope.ply"), str(tmp_path / "b.ply")]) == 2
    _assert_one_error_line(capsys, "nope.ply")


def test_catadioptric_subcommand_is_wired(tmp_path, capsys):
    args = ["catadioptric", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--camera", "c.json"]
    assert cli.main(args) == 2
    _assert_one_error_line(capsys, "a.png")


def test_catadioptric_package_missing_is_one_line_exit_1(tmp_path, monkeypatch, capsys):
    """The catadioptric package is imported only when its command runs."""
    for name in ("a.png", "b.png", "c.json"):
        (tmp_path / name).write_bytes(b"x")
    monkeypatch.setitem(sys.modules, "catadioptric", None)  # import fails
    assert cli.main(["--help"]) == 0
    capsys.readouterr()
    args = ["catadioptric", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--camera", str(tmp_path / "c.json")]
    assert cli.main(args) == 1
    _assert_one_error_line(capsys, "RuntimeError: the catadioptric package cannot be imported")


def test_matrix_output_is_the_motion_as_4x4_text(tmp_path, monkeypatch):
    """``--matrix`` writes the 4x4 homogeneous matrix that numpy.loadtxt reads back."""
    src, tgt = tmp_path / "a.npy", tmp_path / "b.npy"
    pts = np.random.default_rng(0).normal(size=(20, 3))
    write_points(src, pts)
    write_points(tgt, pts)
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    motion = RigidMotion(R, np.array([1.0, 2.0, 3.0]), np.c_[np.arange(5), np.arange(5)])
    monkeypatch.setattr(register_cmd, "load_register", lambda: (lambda s, t, **kw: motion))
    out = tmp_path / "m.txt"
    assert cli.main(["register", str(src), str(tgt), "--matrix", str(out), "-q"]) == 0
    np.testing.assert_array_equal(np.loadtxt(out), motion.matrix)
    assert cli.main(["register", str(src), str(tgt), "--matrix", str(tmp_path / "no" / "m.txt")]) == 2


# ------------------------------------------------------------ labelled PLY (issue 42)
@pytest.mark.parametrize("labels", [[0, 0, 1, 1, -1, 2, 0, 1, -1, 5], [-1] * 10, list(range(10))])
def test_labelled_ply_is_read_by_gatv_pyvista_and_open3d(tmp_path, labels):
    """gatv reads `motion`; PyVista (whose PLY reader takes no custom property) shows one
    colour per motion, the picture's; Open3D's tensor reader reads `motion` (when installed)."""
    from gatv import render

    pts = np.random.default_rng(0).uniform(-1, 1, (10, 3))
    labels = np.asarray(labels)
    path = tmp_path / "l.ply"
    segment_cmd.write_labelled(path, pts, labels)
    back, scalars = read_points(path, scalars=True)
    np.testing.assert_array_equal(scalars["motion"], labels)
    np.testing.assert_allclose(back, pts, atol=1e-6)
    pv = pytest.importorskip("pyvista")
    mesh = pv.read(path)
    colours = np.asarray(mesh["RGB"])
    for k in np.unique(labels):
        want = segment_cmd.UNEXPLAINED_RGB if k < 0 else render.rgb(render.motion_color(k))
        assert (colours[labels == k] == want).all()


def test_labelled_ply_is_read_by_open3d(tmp_path):
    o3d = pytest.importorskip("open3d")
    labels = np.array([0, 1, 1, -1, 2, 0])
    path = tmp_path / "l.ply"
    segment_cmd.write_labelled(path, np.random.default_rng(1).normal(size=(6, 3)), labels)
    cloud = o3d.t.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(cloud.point["motion"].numpy().ravel(), labels)
    legacy = o3d.io.read_point_cloud(str(path))
    assert np.asarray(legacy.colors).shape == (6, 3)


# ----------------------------------------------------- help, models (issues 42, 37)
@pytest.mark.parametrize("command", ["register", "segment", "nonrigid"])
def test_help_lists_every_point_format(command, capsys):
    from gatv.io import READ_EXTENSIONS

    assert cli.main([command, "--help"]) == 0
    text = capsys.readouterr().out
    assert all(ext in text.split() or f"{ext}." in text.split() or f"{ext})" in text.split()
               for ext in READ_EXTENSIONS), text


def test_model_choices_come_from_the_registry():
    from gatv.cli import build_parser
    from gatv.models import MODEL_NAMES

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    for command in ("register", "segment"):
        (model,) = [a for a in sub.choices[command]._actions if a.dest == "model"]
        assert tuple(model.choices) == MODEL_NAMES


@pytest.mark.parametrize("command", ["register", "segment"])
def test_a_model_of_2d_points_is_exit_2_before_reading(command, tmp_path, capsys):
    missing = tmp_path / "nowhere.ply"
    assert cli.main([command, str(missing), str(missing), "--model", "affine2d"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "2D points" in err[0] and "nowhere" not in err[0]
