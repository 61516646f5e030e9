"""Fig. 15-style picture: two catadioptric images side by side, matches linked."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["render_matches"]

#: Gap between the two images, in pixels.
GAP = 20


def _as_grey(image) -> np.ndarray:
    arr = np.asarray(image, dtype=np.float64)
    if arr.ndim == 3:
        arr = arr[..., :3] @ np.array([0.299, 0.587, 0.114])
    return arr


def render_matches(image1, image2, pixels1, pixels2, correspondences, path, *, title: str | None = None,
                   size: tuple[int, int] | None = None, motion=None) -> Path:
    """Write the two images side by side with the matched corners linked.

    Image 1 on the left, image 2 on the right; every detected corner is a
    small grey dot, matched corners are circles of one colour per match
    joined by a line (as the paper's Fig. 15). Rendered off-screen with
    PyVista and written atomically with :func:`gatv.render.save`.

    Parameters
    ----------
    image1, image2 : (H, W) array_like
        Grey images (rows top to bottom, see :func:`catadioptric.read_image`).
    pixels1, pixels2 : (N1, 2), (N2, 2) array_like of float
        Corner pixels ``(u, v)``.
    correspondences : (K, 2) array_like of int
        Rows of ``pixels1`` and ``pixels2``.
    path : str or path-like
        ``.png`` file; its folder must exist.
    title : str, optional
    size : (int, int), optional
        Picture size; default about 1600 pixels wide.
    motion : (K,) array_like of int, optional
        Motion of each match (0-based): the matches are then coloured by
        motion (:func:`gatv.render.motion_color`), not one colour each.

    Returns
    -------
    pathlib.Path
    """
    import pyvista as pv

    from gatv import render

    a, b = _as_grey(image1), _as_grey(image2)
    h = max(a.shape[0], b.shape[0])
    w = a.shape[1] + GAP + b.shape[1]
    canvas = np.full((h, w), 255.0)
    canvas[: a.shape[0], : a.shape[1]] = a
    canvas[: b.shape[0], a.shape[1] + GAP:] = b
    lo, hi = float(np.nanmin(canvas)), float(np.nanmax(canvas))
    # One point per pixel, y up: row 0 of the picture is at the top.
    grid = pv.ImageData(dimensions=(w, h, 1))
    grid.point_data["grey"] = canvas[::-1].ravel()
    p1 = np.asarray(pixels1, dtype=np.float64).reshape(-1, 2)
    p2 = np.asarray(pixels2, dtype=np.float64).reshape(-1, 2)
    pairs = np.asarray(correspondences, dtype=np.int64).reshape(-1, 2)

    def xyz(p, dx):
        return np.column_stack([p[:, 0] + dx, (h - 1) - p[:, 1], np.full(len(p), 1.0)])

    q1 = xyz(p1, 0.0)
    q2 = xyz(p2, float(a.shape[1] + GAP))
    if size is None:
        size = (1600, max(200, int(round(1600 * h / w))))
    plotter = render.new_plotter(size)
    plotter.add_mesh(grid, scalars="grey", cmap="gray", clim=(lo, hi if hi > lo else lo + 1.0),
                     show_scalar_bar=False, lighting=False)
    for q in (q1, q2):
        ok = np.all(np.isfinite(q), axis=1)
        if ok.any():
            plotter.add_points(q[ok], color="#9E9E9E", point_size=4, render_points_as_spheres=True)
    if pairs.size:
        colors = np.array([render.rgb(render.motion_color(k)) for k in range(8)], dtype=np.uint8)
        which = np.arange(len(pairs)) if motion is None else np.asarray(motion, dtype=np.int64).reshape(-1)
        c = colors[which % len(colors)]
        ends = np.vstack([q1[pairs[:, 0]], q2[pairs[:, 1]]])
        ends[:, 2] = 2.0
        n = len(pairs)
        lines = np.column_stack([np.full(n, 2), np.arange(n), np.arange(n) + n]).ravel()
        seg = pv.PolyData(ends, lines=lines)
        seg.cell_data["rgb"] = c
        plotter.add_mesh(seg, scalars="rgb", rgb=True, line_width=1.0, opacity=0.6)
        circles = pv.PolyData(ends)
        circles.point_data["rgb"] = np.vstack([c, c])
        plotter.add_mesh(circles, scalars="rgb", rgb=True, style="points", point_size=11,
                         render_points_as_spheres=True)
    if title:
        render.add_title(plotter, title)
    plotter.view_xy()
    plotter.enable_parallel_projection()
    plotter.camera.focal_point = (w / 2.0, h / 2.0, 0.0)
    plotter.camera.position = (w / 2.0, h / 2.0, 1000.0)
    plotter.camera.up = (0.0, 1.0, 0.0)
    plotter.camera.parallel_scale = h / 2.0 * 1.02
    return render.save(plotter, path)
