"""Off-screen pictures of gatv.render: non-blank, right colours, atomic writes."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gatv import render
from gatv.errors import InputError
from gatv.datasets import random_rotation, table2_trial
from gatv.motion import RigidMotion

PROBLEM = render.offscreen_problem()
pytestmark = pytest.mark.skipif(PROBLEM is not None, reason=f"no off-screen rendering here: {PROBLEM}")

SIZE = (240, 180)


def read_png(path) -> np.ndarray:
    """(H, W, 3) uint8 pixels of a PNG, read back with VTK's PNG reader."""
    import pyvista as pv

    img = pv.read(path)
    w, h, _ = img.dimensions
    arr = np.asarray(img.point_data.active_scalars).reshape(h, w, -1)[::-1, :, :3]
    return arr.astype(np.uint8)


def assert_not_blank(path, size=SIZE, floor=20.0):
    assert path.exists()
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    px = read_png(path)
    assert px.shape == (size[1], size[0], 3)
    assert float(px.astype(float).var()) > floor, "picture is (nearly) blank"


def count_color(px: np.ndarray, color: str) -> int:
    return int(np.all(px == np.array(render.rgb(color), np.uint8), axis=-1).sum())


@pytest.fixture
def rng():
    return np.random.default_rng(7)


def _points(rng, n=60):
    return rng.uniform(-5, 5, (n, 3))


DRAWERS = {
    "points": lambda pl, r: render.add_points(pl, _points(r), color=render.PALETTE[0], label="points"),
    "correspondences": lambda pl, r: render.add_correspondences(pl, _points(r, 20), _points(r, 20)),
    "tokens": lambda pl, r: render.add_tokens(pl, _points(r), r.uniform(0, 1, 60), title="saliency"),
    "normals": lambda pl, r: render.add_normals(pl, _points(r, 20), r.normal(size=(20, 3))),
    "plane": lambda pl, r: render.add_plane(pl, np.c_[_points(r)[:, :2], 0.1 * r.normal(size=60)]),
    "surface": lambda pl, r: render.add_surface(
        pl, (lambda p: np.c_[p[:, :2], 0.05 * (p[:, 0] ** 2 - p[:, 1] ** 2)])(_points(r, 200)),
        r.uniform(0, 1, 200)),
}


@pytest.mark.parametrize("name", sorted(DRAWERS))
def test_each_drawer_writes_a_picture(tmp_path, rng, name):
    pl = render.new_plotter(SIZE)
    assert DRAWERS[name](pl, rng) is not None
    render.add_axes_labels(pl, "dx", "dy", "dz")
    render.add_title(pl, name)
    render.add_legend(pl)
    render.set_view(pl)
    out = render.save(pl, tmp_path / f"{name}.png")
    assert out == tmp_path / f"{name}.png"
    assert_not_blank(out)
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{name}.png"]  # no temporary left


def test_points_are_drawn_in_the_exact_colour(tmp_path, rng):
    pl = render.new_plotter(SIZE)
    render.add_points(pl, _points(rng), color=render.PALETTE[2], size=10)
    px = read_png(render.save(pl, tmp_path / "p.png"))
    assert count_color(px, render.PALETTE[2]) > 500
    assert count_color(px, render.PALETTE[0]) == 0


def test_save_closes_the_plotter_and_overwrites(tmp_path, rng):
    path = tmp_path / "p.png"
    path.write_bytes(b"old")
    pl = render.new_plotter(SIZE)
    render.add_points(pl, _points(rng))
    render.save(pl, path, size=(200, 100))
    assert pl._closed
    assert_not_blank(path, size=(200, 100))


def test_save_into_a_missing_folder_fails_and_closes(tmp_path, rng):
    pl = render.new_plotter(SIZE)
    render.add_points(pl, _points(rng))
    with pytest.raises(FileNotFoundError, match="does not exist"):
        render.save(pl, tmp_path / "nope" / "p.png")
    assert pl._closed


def test_empty_inputs_draw_nothing():
    pl = render.new_plotter(SIZE)
    try:
        assert render.add_points(pl, np.empty((0, 3))) is None
        assert render.add_correspondences(pl, np.zeros((3, 3)), np.zeros((3, 3)), np.empty((0, 2), int)) is None
        assert render.add_legend(pl) is None  # nothing labelled
    finally:
        pl.close()


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: render.new_plotter((10, 10)), "`size`"),
        (lambda: render.new_plotter("big"), "`size`"),
        (lambda: render.add_correspondences(render.new_plotter(SIZE), np.zeros((3, 3)), np.zeros((3, 3)), [[0, 5]]),
         "`pairs`"),
        (lambda: render.add_tokens(render.new_plotter(SIZE), np.zeros((3, 3)), [1.0, 2.0]), "`saliency`"),
        (lambda: render.add_normals(render.new_plotter(SIZE), np.zeros((3, 3)), np.ones((2, 3))), "`normals`"),
        (lambda: render.fit_plane(np.zeros((3, 3)), [0, 0, 0]), "`normal`"),
        (lambda: render.add_points(render.new_plotter(SIZE), np.zeros((3, 2))), "`points`"),
    ],
)
def test_bad_input_names_the_argument(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_fit_plane_recovers_a_planted_plane(rng):
    n = np.array([1.0, 2.0, 2.0]) / 3.0
    u = np.cross(n, [0, 0, 1.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    pts = 4.0 * n + rng.uniform(-3, 3, (100, 1)) * u + rng.uniform(-1, 1, (100, 1)) * v
    center, normal, axes, half = render.fit_plane(pts)
    assert abs(abs(normal @ n) - 1.0) < 1e-9
    assert abs(center @ n - 4.0) < 1e-9
    assert abs(abs(axes[0] @ u) - 1.0) < 0.01  # the long side
    assert 2.5 < half[0] <= 3.2 and 0.8 < half[1] <= 1.3


def test_nice_bounds_are_round():
    bounds, counts = render.nice_bounds((-9.8, 9.9, 0.1, 3.7, -1.0, 1.0), 3)
    assert bounds == (-10.0, 10.0, 0.0, 4.0, -1.0, 1.0)
    assert counts == (3, 3, 3)


def test_render_registration(tmp_path):
    from gatv import register

    trial = table2_trial(0.5, seed=4)
    motion = register(trial.source, trial.target)
    out = render.render_registration(trial.source, trial.target, motion, tmp_path / "reg.png", size=(480, 240))
    assert_not_blank(out, size=(480, 240))
    px = read_png(out)
    assert count_color(px, render.PALETTE[0]) > 50  # target
    assert count_color(px, render.PALETTE[1]) > 50  # source


def test_render_registration_of_a_failed_motion(tmp_path, rng):
    failed = RigidMotion(np.eye(3), np.zeros(3), info={"reason": "no plane"})
    out = render.render_registration(_points(rng), _points(rng), failed, tmp_path / "f.png", size=(320, 160))
    assert_not_blank(out, size=(320, 160))


def three_motions(rng, n=40, n_free=20):
    source, target, motions = [], [], []
    for k in range(3):
        x = rng.uniform(-5, 5, (n, 3))
        rot = random_rotation(rng, (20.0, 90.0))
        t = rng.uniform(-3, 3, 3)
        source.append(x)
        target.append(x @ rot.T + t)
        idx = np.arange(k * n, (k + 1) * n)
        motions.append(RigidMotion(rot, t, np.c_[idx, idx]))
    source.append(rng.uniform(-5, 5, (n_free, 3)))
    target.append(rng.uniform(-5, 5, (n_free, 3)))
    return np.vstack(source), np.vstack(target), motions


def test_render_motions_uses_one_palette_colour_per_motion(tmp_path, rng):
    source, target, motions = three_motions(rng)
    out = render.render_motions(source, target, motions, tmp_path / "m.png", size=(600, 480))
    assert_not_blank(out, size=(600, 480))
    px = read_png(out)
    present = [c for c in render.PALETTE if count_color(px, c) > 100]
    assert present == list(render.PALETTE[:3])
    assert all(count_color(px, c) <= 5 for c in render.PALETTE[3:])
    assert count_color(px, render.NEUTRAL) > 0  # the points no motion claims


def test_render_motions_with_two_motions_shows_two_colours(tmp_path, rng):
    source, target, motions = three_motions(rng)
    out = render.render_motions(source, target, motions[:2], tmp_path / "m2.png", size=(600, 240))
    px = read_png(out)
    assert [c for c in render.PALETTE if count_color(px, c) > 100] == list(render.PALETTE[:2])


def test_cli_uses_render_registration(tmp_path, monkeypatch):
    from gatv.cli import register as register_cmd

    calls = []
    monkeypatch.setattr(render, "render_registration", lambda *a, **k: calls.append(a))
    trial = table2_trial(0.5, seed=4)
    motion = RigidMotion(trial.rotation, trial.translation, trial.true_pairs)
    register_cmd.render(trial.source, trial.target, motion, tmp_path / "x.png")
    assert len(calls) == 1


def test_render_segmentation_draws_the_segmentation(tmp_path):
    from gatv.motions import fig12_scene, segment

    scene = fig12_scene(n_per_motion=20, seed=3)
    seg = segment(scene.source, scene.target, seed=0)
    assert len(seg) == 3
    out = render.render_segmentation(scene.source, scene.target, seg, tmp_path / "s.png", size=(480, 360))
    assert_not_blank(out, size=(480, 360))
    px = read_png(out)
    assert [c for c in render.PALETTE if count_color(px, c) > 50] == list(render.PALETTE[:3])


def test_cli_uses_render_segmentation(tmp_path, monkeypatch):
    from gatv.cli import segment as segment_cmd
    from gatv.motions import Segmentation

    calls = []
    monkeypatch.setattr(render, "render_segmentation", lambda *a, **k: calls.append(a))
    empty = Segmentation((), np.full(3, -1), np.full(3, -1), np.empty((0, 2), int), np.empty(0, int))
    segment_cmd.render_segmentation(np.zeros((3, 3)), np.zeros((3, 3)), empty, tmp_path / "x.png")
    assert len(calls) == 1


def test_add_image_pair_draws_images_corners_and_matches(tmp_path, rng):
    image = np.tile(np.linspace(0.0, 255.0, 64), (48, 1))
    p1 = rng.uniform([4, 4], [60, 44], (12, 2))
    p2 = p1 + [1.5, -2.0]
    pairs = np.c_[np.arange(8), np.arange(8)]
    right = np.arange(8) < 6
    pl = render.new_plotter((320, 160))
    render.add_image_pair(pl, image, image, p1, p2, pairs, right=right, title="pair", size=10)
    render.add_legend(pl, loc="lower right")
    px = read_png(render.save(pl, tmp_path / "pair.png"))
    assert px.shape == (160, 320, 3)
    assert count_color(px, render.PALETTE[2]) > 50  # right matches
    assert count_color(px, render.PALETTE[1]) > 10  # wrong matches
    assert count_color(px, render.PALETTE[4]) > 0  # unmatched corners


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"image1": np.zeros(5)}, "`image1`"), ({"pixels2": np.zeros((3, 3))}, "`pixels2`"),
     ({"right": [True]}, "`right`"), ({"pairs": [[0, 9]]}, "`pairs`")],
)
def test_add_image_pair_names_bad_input(kwargs, match):
    args = {"image1": np.zeros((8, 8)), "image2": np.zeros((8, 8)), "pixels1": np.ones((3, 2)),
            "pixels2": np.ones((3, 2)), "pairs": [[0, 0], [1, 1]]}
    args.update(kwargs)
    pl = render.new_plotter((64, 48))
    try:
        with pytest.raises(ValueError, match=match):
            render.add_image_pair(pl, **args)
    finally:
        pl.close()


def test_render_motions_numbers_motions_from_0_as_the_cli_and_labels_do(tmp_path, rng, monkeypatch):
    """Issue 42: stdout and the labelled file say motion 0, 1, ...; the picture must too."""
    source, target, motions = three_motions(rng)
    said = []
    real_title, real_points = render.add_title, render.add_points
    monkeypatch.setattr(render, "add_title", lambda pl, text, **k: (said.append(text), real_title(pl, text, **k))[1])
    monkeypatch.setattr(render, "add_points", lambda pl, pts, **k: (said.append(k.get("label") or ""),
                                                                  real_points(pl, pts, **k))[1])
    render.render_motions(source, target, motions[:2], tmp_path / "m.png", size=(600, 240))
    named = {w for text in said for w in __import__("re").findall(r"motion (\d+)", text)}
    assert named == {"0", "1"}


# ------------------------------------------------ the registration picture (issue 42)
@given(n=st.integers(0, 3000), k=st.integers(1, 400), seed=st.integers(0, 5))
@settings(max_examples=40, deadline=None)
def test_sample_pairs_is_a_sorted_subset_of_at_most_k(n, k, seed):
    pairs = np.c_[np.arange(n), np.arange(n)[::-1]]
    got = render.sample_pairs(pairs, k, seed)
    assert len(got) == min(n, k)
    assert np.all(np.diff(got[:, 0]) > 0) if len(got) > 1 else True
    assert set(map(tuple, got)) <= set(map(tuple, pairs))
    np.testing.assert_array_equal(got, render.sample_pairs(pairs, k, seed))


@pytest.mark.parametrize("pipeline, up, viewup, depth", [("scans", None, (0, 1, 0), "z"),
                                                         ("exact", None, (0, 0, 1), "y"),
                                                         ("scans", "z", (0, 0, 1), "y")])
def test_registration_picture_is_upright_sampled_with_one_legend(tmp_path, rng, monkeypatch, pipeline, up,
                                                                viewup, depth):
    """Scans (y up) drawn y up; at most MAX_LINES lines of many correspondences; one legend;
    no tick labels on the axis facing the camera (they crowded the next axis's)."""
    n = 3000
    src = rng.uniform(-1, 1, (n, 3))
    motion = RigidMotion(random_rotation(rng, (20, 40)), np.zeros(3), np.c_[np.arange(n), np.arange(n)],
                         info={"pipeline": pipeline})
    seen = {"legends": 0, "lines": [], "views": [], "unlabelled": []}
    real = {name: getattr(render, name) for name in ("add_legend", "add_correspondences", "_look",
                                                     "add_axes_labels")}

    def legend(pl, **k):
        seen["legends"] += 1
        return real["add_legend"](pl, **k)

    def lines(pl, s, t, pairs=None, **k):
        seen["lines"].append(len(pairs))
        return real["add_correspondences"](pl, s, t, pairs, **k)

    def look(pl, direction, viewup):
        seen["views"].append(tuple(viewup))
        return real["_look"](pl, direction, viewup)

    def axes(pl, *a, unlabelled=None, **k):
        seen["unlabelled"].append(unlabelled)
        return real["add_axes_labels"](pl, *a, unlabelled=unlabelled, **k)

    for name, fn in (("add_legend", legend), ("add_correspondences", lines), ("_look", look),
                     ("add_axes_labels", axes)):
        monkeypatch.setattr(render, name, fn)
    out = render.render_registration(src, motion.transform(src), motion, tmp_path / "r.png", size=(480, 240),
                                     up=up)
    assert_not_blank(out, size=(480, 240))
    assert seen["legends"] == 1
    assert seen["lines"] == [render.MAX_LINES]
    assert seen["views"] == [viewup, viewup]
    assert seen["unlabelled"] == [depth, depth]


def test_registration_picture_names_a_bad_up(tmp_path, rng):
    motion = RigidMotion(np.eye(3), np.zeros(3), np.c_[np.arange(5), np.arange(5)])
    with pytest.raises(InputError, match="`up`"):
        render.render_registration(_points(rng), _points(rng), motion, tmp_path / "r.png", up="w")
    assert not (tmp_path / "r.png").exists()
