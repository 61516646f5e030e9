"""
Fig. 15: corner correspondences between two catadioptric images
================================================================

The corners of two catadioptric images are lifted to the unit sphere and
matched there (paper, end of section 5.1 and Fig. 15) with
:func:`catadioptric.match`: a dominant rotation from local triangles, then,
when the camera also moved, the epipolar geometry of the pair (an
essential matrix from matched local triangles) and matches along the
epipolar arcs at the inverse depth of locally planar neighbourhoods.

Every motion of the pair is found in turn: after the dominant one, the
corners it leaves unexplained are searched for a plane moved rigidly (a
homography of the sphere, :mod:`catadioptric.plane`), whose repeated
pattern is resolved by whole-pattern support.

Panel (a): a synthetic pair from :func:`catadioptric.synthetic_views` (a
parabolic mirror in a room, the camera turned by 30 degrees and moved,
30% outlier corners), drawn as dots on an image-like canvas (the mirror's
image disc); green matches are right, vermillion ones wrong. Panel (b),
when the shared data are present: two real para-catadioptric images of
Mei's calibration set with the corners :func:`catadioptric.detect_corners`
finds; it is a real two-motion scene: the corridor is static (blue
matches) and the hand-held checkerboard moved (green matches); vermillion
matches are wrong by the ground truth, which only colours the matches and
gives the printed precision and recall. Small dots are detected corners.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from catadioptric import UnifiedCamera, detect_corners, match, read_image, synthetic_views
from gatv import render
from gatv.datasets import correspondence_stats

SEED = 15
SIZE = (1300, 1100)
#: Mei's para-catadioptric images, in the real-data folder of
#: :func:`gatv.datasets.find_data_dir`; panel (b) is left out when absent.
REAL_PAIR = ("img_para_001", "img_para_002")
MAX_CORNERS = 250
#: A static corner of the corridor is "the same" in both images within this many pixels.
STATIC_PX = 3.0


def find_pair_folder(data_dir=None) -> Path | None:
    """``omni_mei_paracatadioptric/`` in the real-data folder, or None when absent."""
    from gatv.datasets import DataNotFoundError, find_data_dir

    try:
        folder = find_data_dir(data_dir) / "omni_mei_paracatadioptric"
    except DataNotFoundError:
        return None
    return folder if (folder / "images" / f"{REAL_PAIR[0]}.png").is_file() else None


# %%
# The synthetic canvas: the part of the image the mirror fills (rays within
# the field of view) in dark grey, the rest light, like a catadioptric frame.
def mirror_canvas(camera: UnifiedCamera, max_angle_deg: float, step: int = 4) -> np.ndarray:
    """(H, W) grey image: 70 inside the mirror's image disc, 240 outside."""
    w, h = camera.image_size
    vv, uu = np.mgrid[0:h:step, 0:w:step]
    rays, ok = camera.lift(np.column_stack([uu.ravel(), vv.ravel()]).astype(float), return_mask=True)
    inside = ok & (np.nan_to_num(rays[:, 2], nan=-2.0) >= np.cos(np.radians(max_angle_deg)))
    coarse = np.where(inside.reshape(vv.shape), 70.0, 240.0)
    return np.repeat(np.repeat(coarse, step, axis=0), step, axis=1)[:h, :w]


# %%
# Ground truth of the real pair. The camera and the corridor are static, so
# a background corner is the same pixel in both images; the checkerboard
# moved, and its 48 inner corners (detected with OpenCV, in the shared
# ``corners/`` files) correspond by index. A detected corner within 3 px of
# a board corner is that board corner; one within a board square of the
# board but on no board corner has no known partner.
def real_truth(p1, p2, board1, board2, *, half_turn=False) -> set:
    """True pairs ``(i, j)`` among the detected corners of the real pair.

    The 9x7-square board is symmetric under a half-turn and OpenCV's corner
    order may be turned between images (data README): with ``half_turn``
    the board corners correspond as ``k`` and ``47 - k``.
    """
    def board_ids(p, b):
        tree = cKDTree(b)
        d, k = tree.query(p)
        square = float(np.median(tree.query(b, k=2)[0][:, 1]))
        return np.where(d <= STATIC_PX, k, -1), d <= square

    k1, near1 = board_ids(p1, board1)
    k2, near2 = board_ids(p2, board2)
    truth = set()
    for i in np.flatnonzero(k1 >= 0):
        js = np.flatnonzero(k2 == (47 - k1[i] if half_turn else k1[i]))
        if js.size:
            truth.add((int(i), int(js[0])))
    d, j = cKDTree(p2).query(p1)
    for i in np.flatnonzero(~near1 & (d <= STATIC_PX)):
        if not near2[j[i]]:
            truth.add((int(i), int(j[i])))
    return truth


def _deg(angle) -> str:
    return "none (below chance)" if angle is None else f"{angle:.2f} deg"


def _tdeg(estimate, truth) -> str:
    """Angle between an estimated translation direction and the true translation."""
    if estimate is None:
        return "not estimated"
    c = float(np.dot(estimate, truth) / np.linalg.norm(truth))
    return f"{np.degrees(np.arccos(min(1.0, max(-1.0, c)))):.2f} deg off"


def _mirror_mask(camera: UnifiedCamera, shape) -> np.ndarray:
    """Pixels the camera can lift (the mirror's disc)."""
    h, w = shape
    step = 4
    vv, uu = np.mgrid[0:h:step, 0:w:step]
    _, ok = camera.lift(np.column_stack([uu.ravel(), vv.ravel()]).astype(float), return_mask=True)
    return np.repeat(np.repeat(ok.reshape(vv.shape), step, axis=0), step, axis=1)[:h, :w]


# %%
# Both motions in one panel: the first motion's matches through
# :func:`gatv.render.add_image_pair`, each further motion's drawn on top in
# its own colour, in the same image coordinates (image 2 right of image 1,
# ``gap`` pixels apart, rows top to bottom).
MOTION_COLORS = (render.PALETTE[0], render.PALETTE[2], render.PALETTE[3], render.PALETTE[4])
NAMES = ("static corridor", "moving board", "motion 3", "motion 4")


def add_motions(pl, img1, img2, c1, c2, motions, *, title, gap=40.0, size=9.0):
    """The images, their corners and every motion's matches.

    ``motions``: ``(SphereMotion, verdict)`` with ``verdict`` per match 1
    (right: the motion's colour), 0 (wrong: vermillion) or -1 (no ground
    truth for either corner, e.g. the board's outer corners: grey).
    """
    render.add_image_pair(pl, img1, img2, c1, c2, np.empty((0, 2), np.int64), title=title, gap=gap, size=size)
    h = max(np.shape(img1)[0], np.shape(img2)[0])
    dx = float(np.shape(img1)[1] + gap)

    def xyz(p, x0):
        return np.column_stack([p[:, 0] + x0, (h - 1) - p[:, 1], np.full(len(p), 2.0 + 0.1 * k)])

    for k, (mo, verdict) in enumerate(motions):
        for flags, color, name in ((verdict == 1, MOTION_COLORS[k % len(MOTION_COLORS)], NAMES[k % len(NAMES)]),
                                   (verdict == 0, render.PALETTE[1], "wrong"),
                                   (verdict < 0, render.NEUTRAL, "no ground truth")):
            if not flags.any():
                continue
            c = mo.correspondences[flags]
            s, t = xyz(c1[c[:, 0]], 0.0), xyz(c2[c[:, 1]], dx)
            render.add_correspondences(pl, s, t, color=color, width=1.2, opacity=0.7)
            render.add_points(pl, np.vstack([s, t]), color=color, size=size,
                              label=f"{int(flags.sum())} matches, {name}" + (f" ({NAMES[k]})" if name in (
                                  "wrong", "no ground truth") else ""))


def main(out_dir, size=SIZE, data_dir=None) -> dict:
    """Match the synthetic (and real) pair, print precision/recall, write ``fig15_catadioptric.png``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    result: dict = {}

    # %%
    # The synthetic pair: 200 scene corners around a parabolic-mirror camera
    # (xi = 1), a second view turned by 30 deg and moved by (0.3, 0.1, 0.05) m,
    # 1 px noise, 30% outlier corners in each view.
    rng = np.random.default_rng(SEED)
    views = synthetic_views(200, xi=1.0, rotation_deg=30.0, translation=(0.3, 0.1, 0.05), noise_px=1.0,
                            outlier_fraction=0.3, seed=rng)
    t0 = time.perf_counter()
    syn = match(views.pixels1, views.pixels2, views.camera1)
    t_syn = time.perf_counter() - t0
    p_syn, r_syn = correspondence_stats(syn.correspondences, views.pairs)
    true = {tuple(r) for r in views.pairs.tolist()}
    right_syn = np.array([tuple(r) in true for r in syn.correspondences.tolist()], bool)
    print(f"synthetic: {len(views.pixels1)} / {len(views.pixels2)} corners, {len(views.pairs)} true pairs; "
          f"catadioptric.match ({t_syn:.2f} s, strategy '{syn.strategy}', rotation {_deg(syn.rotation_deg)} "
          f"vs 30.00, translation direction {_tdeg(syn.translation, views.translation)}): {syn.support} matches, {int(right_syn.sum())} right; precision {p_syn:.3f}, "
          f"recall {r_syn:.3f}")
    result.update(synthetic_precision=p_syn, synthetic_recall=r_syn, synthetic_support=syn.support)

    # %%
    # The real pair, when the shared data are here: corners detected inside
    # the mirror's disc, matched, and checked against the static corridor and
    # the board corners.
    folder = find_pair_folder(data_dir)
    real = None
    if folder is not None:
        cam = UnifiedCamera.from_file(folder / "calibration_mei_opencv.json")
        img1, img2 = (read_image(folder / "images" / f"{name}.png") for name in REAL_PAIR)
        t0 = time.perf_counter()
        c1 = detect_corners(img1, max_corners=MAX_CORNERS, mask=_mirror_mask(cam, img1.shape))
        c2 = detect_corners(img2, max_corners=MAX_CORNERS, mask=_mirror_mask(cam, img2.shape))
        t_det = time.perf_counter() - t0
        t0 = time.perf_counter()
        got = match(c1, c2, cam)
        t_real = time.perf_counter() - t0
        board1, board2 = (np.loadtxt(folder / "corners" / f"{name}_corners_px.txt") for name in REAL_PAIR)
        # the board's labelling (as given or turned) that agrees with more matches
        truths = [real_truth(c1, c2, board1, board2, half_turn=h) for h in (False, True)]
        truth = max(truths, key=lambda t: sum(tuple(r) in t for r in got.correspondences.tolist()))
        truth_pairs = np.array(sorted(truth), np.int64).reshape(-1, 2)
        # precision over the matches with a corner in the ground truth (the
        # board's outer corners and other corners have no known partner)
        rows1, rows2 = {i for i, _ in truth}, {j for _, j in truth}
        judged = np.array([[i, j] for i, j in got.correspondences.tolist() if i in rows1 or j in rows2],
                          np.int64).reshape(-1, 2)
        p_real = correspondence_stats(judged, truth_pairs)[0]
        r_real = correspondence_stats(got.correspondences, truth_pairs)[1]
        at_board = cKDTree(board1).query(c1)[0] <= STATIC_PX  # detected corners on a board corner
        n_board = int(sum(at_board[i] for i, _ in truth))
        rows1, rows2 = {i for i, _ in truth}, {j for _, j in truth}
        motions = []
        for k, mo in enumerate(got.motions):
            right = np.array([tuple(r) in truth for r in mo.correspondences.tolist()], bool)
            known = np.array([i in rows1 or j in rows2 for i, j in mo.correspondences.tolist()], bool)
            on_board = at_board[mo.correspondences[:, 0]]
            motions.append((mo, np.where(right, 1, np.where(known, 0, -1))))
            print(f"  motion {k + 1} ({mo.strategy}): {mo.support} matches, {int(right.sum())} right "
                  f"({int((right & on_board).sum())} of the {n_board} true pairs on the moving board, "
                  f"{int((right & ~on_board).sum())} of the {len(truth) - n_board} of the static corridor), "
                  f"rotation {_deg(mo.angle_deg)}")
        print(f"real ({REAL_PAIR[0]} / {REAL_PAIR[1]}): {len(c1)} / {len(c2)} corners detected ({t_det:.1f} s), "
              f"{len(truth)} true pairs (static corridor within {STATIC_PX:.0f} px, board corners by index"
              f"{', half-turned' if truth is truths[1] else ''}); catadioptric.match ({t_real:.2f} s, "
              f"{len(got.motions)} motions): {got.support} matches, {len(judged)} with a corner in the ground "
              f"truth; precision {p_real:.3f}, recall {r_real:.3f}")
        real = (img1, img2, c1, c2, got, motions, p_real, r_real)
        result.update(real_precision=p_real, real_recall=r_real, real_support=got.support)
    else:
        print("real pair: shared data not found, panel (b) left out")

    # %%
    # The picture: one row per pair.
    t0 = time.perf_counter()
    pl = render.new_plotter(size, shape=(2 if real is not None else 1, 1))
    pl.subplot(0, 0)
    canvas = mirror_canvas(views.camera1, 120.0)
    render.add_image_pair(pl, canvas, canvas, views.pixels1, views.pixels2, syn.correspondences, right=right_syn,
                          clim=(0.0, 255.0),
                          title=f"(a) synthetic pair, camera turned 30 deg and moved: {syn.support} matches, "
                                f"precision {p_syn:.2f}, recall {r_syn:.2f}")
    render.add_legend(pl, loc="lower right")
    if real is not None:
        img1, img2, c1, c2, got, motions, p_real, r_real = real
        pl.subplot(1, 0)
        add_motions(pl, img1, img2, c1, c2, motions,
                    title=f"(b) real pair {REAL_PAIR[0]} / {REAL_PAIR[1]}: {len(motions)} motions, "
                          f"{got.support} matches, precision {p_real:.2f}, recall {r_real:.2f}")
        render.add_legend(pl, loc="lower right")
    png = render.save(pl, out_dir / "fig15_catadioptric.png")
    print(f"wrote {Path(png).name} ({size[0]}x{size[1]}, rendered in {time.perf_counter() - t0:.1f} s)")
    result["pngs"] = [png]
    return result


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=(__doc__ or "").strip().split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("gallery_out"), help="output folder")
    parser.add_argument("--size", type=int, nargs=2, default=SIZE, metavar=("W", "H"), help="picture size")
    parser.add_argument("--data", type=Path, help="folder holding omni_mei_paracatadioptric/")
    args = parser.parse_args()
    main(args.out, size=tuple(args.size), data_dir=args.data)
