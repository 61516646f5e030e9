"""Every gallery figure renders off screen at a small size; the Hough helper is honest."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from gatv import render

GALLERY = Path(__file__).resolve().parents[1] / "gallery"
PROBLEM = render.offscreen_problem()
needs_rendering = pytest.mark.skipif(PROBLEM is not None, reason=f"no off-screen rendering here: {PROBLEM}")


def _load(path: Path):
    spec = importlib.util.spec_from_file_location(f"gallery_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


make_all = _load(GALLERY / "make_all.py")
SCRIPTS = make_all.figure_scripts(GALLERY)


def _pixels(path: Path) -> np.ndarray:
    import pyvista as pv

    img = pv.read(path)
    w, h, _ = img.dimensions
    return np.asarray(img.point_data.active_scalars).reshape(h, w, -1)[..., :3]


#: Figures whose picture shows one palette colour per detected motion: how many.
MOTION_COLOURS = {"fig12_three_motions": 3}


def _count_colour(px: np.ndarray, color: str) -> int:
    return int(np.all(px == np.array(render.rgb(color), np.uint8), axis=-1).sum())


def test_gallery_has_figures():
    names = [p.name for p in SCRIPTS]
    assert "fig08_joint_space.py" in names
    assert "fig12_three_motions.py" in names
    assert "fig13_twisted_plane.py" in names
    assert "fig14_local_eq41.py" in names
    assert "fig15_catadioptric.py" in names


@pytest.mark.parametrize("script", SCRIPTS, ids=[p.stem for p in SCRIPTS])
def test_script_shape(script):
    text = script.read_text()
    assert text.startswith('"""'), "docstring title first"
    assert "# %%" in text
    assert "default_rng" in text
    assert 'if __name__ == "__main__":' in text and "--out" in text and "--size" in text
    module = _load(script)
    assert callable(module.main)
    assert module.__doc__.strip().splitlines()[0].strip()


#: Figures whose render runs a long pipeline (15-35 s each); their numbers are checked by the fast
#: tests below (fig08's story, fig15 without the real pair), the renders by ``make test-slow``.
SLOW_RENDERS = ("fig08_joint_space", "fig12_three_motions", "fig15_catadioptric")


@needs_rendering
@pytest.mark.parametrize("script", [pytest.param(p, marks=pytest.mark.slow) if p.stem in SLOW_RENDERS else p
                                    for p in SCRIPTS], ids=[p.stem for p in SCRIPTS])
def test_figure_renders(tmp_path, script, capsys):
    size = (360, 200)
    result = _load(script).main(tmp_path, size=size)
    pngs = [Path(p) for p in result["pngs"]]
    assert pngs
    for png in pngs:
        assert png.parent == tmp_path and png.exists()
        px = _pixels(png)
        assert px.shape == (size[1], size[0], 3)
        assert float(px.astype(float).var()) > 20.0, f"{png.name} is blank"
    out = capsys.readouterr().out
    assert out.strip(), "a figure script prints its numbers"
    assert str(tmp_path) not in out, "a gallery page shows what the script prints: no build path"
    if script.stem in MOTION_COLOURS:
        px = _pixels(pngs[0]).astype(np.uint8)
        shown = [c for c in render.PALETTE if _count_colour(px, c) > 20]
        assert shown == list(render.PALETTE[:MOTION_COLOURS[script.stem]])
        assert result["colors"] == shown


def test_fig08_numbers_are_the_paper_story(tmp_path):
    """The Hough peak is a wrong plane; gatv recovers the true pairs."""
    if PROBLEM is not None:
        pytest.skip(f"no off-screen rendering here: {PROBLEM}")
    r = _load(GALLERY / "fig08_joint_space.py").main(tmp_path, size=(300, 120))
    assert r["hough_votes"] > r["true_plane_votes"]
    assert r["hough_true"] < 10
    assert r["true_plane_rank"] > 1
    assert r["precision"] == 1.0 and r["recall"] == 1.0


def test_hough_finds_a_planted_plane():
    fig08 = _load(GALLERY / "fig08_joint_space.py")
    rng = np.random.default_rng(3)
    n = np.array([2.0, -1.0, 2.0]) / 3.0
    u = np.cross(n, [1.0, 0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    plane = 2.0 * n + rng.uniform(-6, 6, (400, 1)) * u + rng.uniform(-6, 6, (400, 1)) * v
    noise = rng.uniform(-8, 8, (300, 3))
    normals, acc, rho0 = fig08.hough_planes(np.vstack([plane, noise]), n_normals=3000, bin_width=0.5)
    i, j = np.unravel_index(int(np.argmax(acc)), acc.shape)
    assert abs(normals[i] @ n) > np.cos(np.radians(4.0))
    assert abs(abs(rho0 + (j + 0.5) * 0.5) - 2.0) <= 0.5
    assert acc.sum() == 700 * len(normals)  # one vote per token per normal
    assert fig08.in_slab(plane, n, 2.0, 0.1).all()


def test_make_all_runs_discovered_scripts(tmp_path, capsys):
    folder = tmp_path / "g"
    folder.mkdir()
    (folder / "fig99_dummy.py").write_text(
        '"""Dummy."""\n'
        "from pathlib import Path\n"
        "def main(out_dir, size=(40, 30)):\n"
        "    p = Path(out_dir) / 'dummy.png'\n"
        "    p.write_bytes(b'\\x89PNG\\r\\n\\x1a\\n' + b'\\0\\0\\0\\rIHDR' + size[0].to_bytes(4, 'big')"
        " + size[1].to_bytes(4, 'big'))\n"
        "    print('dummy numbers')\n"
        "    return {'pngs': [p]}\n"
    )
    (folder / "helper.py").write_text("raise RuntimeError('not a figure')\n")
    records = make_all.main(tmp_path / "out", size=(64, 48), scripts=make_all.figure_scripts(folder))
    assert [r["script"] for r in records] == ["fig99_dummy.py"]
    out = capsys.readouterr().out
    assert "dummy numbers" in out and "dummy.png 64x48" in out


@needs_rendering
def test_fig15_leaves_out_the_real_pair_without_the_data(tmp_path, capsys):
    r = _load(GALLERY / "fig15_catadioptric.py").main(tmp_path, size=(300, 160), data_dir=tmp_path / "absent")
    assert "real_precision" not in r
    assert "panel (b) left out" in capsys.readouterr().out
    assert float(_pixels(r["pngs"][0]).astype(float).var()) > 20.0
    assert r["synthetic_precision"] >= 0.9 and r["synthetic_recall"] >= 0.8
