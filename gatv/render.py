"""Off-screen pictures of point sets, joint spaces and motions (PyVista).

Small drawing functions that take numpy arrays and draw on a
:class:`pyvista.Plotter` that needs no display, plus two figure-level
functions used by the command line and the gallery:

* :func:`render_registration` — source, aligned source, target and the
  correspondences of one :class:`~gatv.motion.RigidMotion`;
* :func:`render_motions` — several motions (Fig. 12 of Reyes, Medioni &
  Bayro, IJCV 2007), one colour per motion, an overview panel and one
  panel per motion; :func:`render_segmentation` draws a
  :class:`gatv.motions.Segmentation` the same way;
* :func:`add_image_pair` — two images side by side with their corners and
  matched corners linked (the catadioptric pictures of Fig. 15).

Style
-----
White background, labelled axes, points drawn flat (unlit discs, so that a
colour in the picture is exactly the colour asked for), one fixed
qualitative palette for motions (:data:`PALETTE`, Okabe & Ito's
colour-blind-safe colours) and :data:`NEUTRAL` grey for points no motion
claims.

Off-screen rendering
--------------------
Everything here renders off screen. :func:`configure_offscreen` (called
before the first plotter is made) sets ``pyvista.OFF_SCREEN`` and, on a
Linux machine with no ``DISPLAY``/``WAYLAND_DISPLAY``, asks VTK (>= 9.4)
for its EGL render window (``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow``,
Mesa's surfaceless software renderer when there is no GPU) instead of first
trying X and printing "bad X server connection". A value already in the
environment wins (e.g. ``vtkOSOpenGLRenderWindow`` for OSMesa). No X server
or ``xvfb`` is needed. :func:`offscreen_problem` tries one tiny render in a
child process and says why rendering is impossible, or returns ``None``.

Examples
--------
>>> import numpy as np
>>> from gatv import render
>>> rng = np.random.default_rng(0)
>>> pl = render.new_plotter((160, 120))
>>> _ = render.add_points(pl, rng.uniform(-1, 1, (30, 3)), color=render.PALETTE[0])
>>> pl.close()
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ._validation import as_points
from .errors import InputError

if TYPE_CHECKING:  # pragma: no cover
    import pyvista

    from .motion import RigidMotion

__all__ = [
    "PALETTE",
    "NEUTRAL",
    "LINE_COLOR",
    "motion_color",
    "configure_offscreen",
    "offscreen_problem",
    "new_plotter",
    "add_points",
    "add_correspondences",
    "add_tokens",
    "add_normals",
    "add_plane",
    "add_surface",
    "add_axes_labels",
    "add_legend",
    "add_title",
    "fit_plane",
    "nice_bounds",
    "set_view",
    "save",
    "render_registration",
    "sample_pairs",
    "render_motions",
    "render_segmentation",
    "add_image_pair",
]

#: Motion colours, in order (Okabe & Ito 2008, colour-blind safe; the
#: yellow and black are left out: unreadable on white, and black is the
#: colour of text and lines).
PALETTE = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9")
#: Points that no motion claims.
NEUTRAL = "#A0A0A0"
#: Correspondence lines of a single motion.
LINE_COLOR = "#303030"
#: Colour map for saliencies.
CMAP = "viridis"

_FONT = "arial"


def motion_color(k: int) -> str:
    """Colour of motion ``k`` (0-based); the palette repeats after 6."""
    return PALETTE[int(k) % len(PALETTE)]


def rgb(color: str) -> tuple[int, int, int]:
    """``(r, g, b)`` integers of a ``#rrggbb`` colour."""
    h = color.lstrip("#")
    return int(h[0:2], 16), int(h[2:4], 16), int(h[4:6], 16)


# ----------------------------------------------------------------- off screen
def configure_offscreen() -> None:
    """Switch PyVista to off-screen rendering; pick EGL where there is no display.

    Idempotent; called by :func:`new_plotter`. Sets ``pyvista.OFF_SCREEN``
    and, on Linux without ``DISPLAY`` or ``WAYLAND_DISPLAY``, the environment
    variable ``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow`` unless it is
    already set (VTK reads it when it makes a render window).
    """
    import pyvista as pv

    pv.OFF_SCREEN = True
    headless = not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    if sys.platform.startswith("linux") and headless:
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


_PROBE = """
import numpy as np
from gatv import render
pl = render.new_plotter((64, 48))
render.add_points(pl, np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), color="#000000", size=20)
img = pl.screenshot(None, return_img=True)
pl.close()
assert img.shape[:2] == (48, 64), img.shape
assert float(img.std()) > 1.0, "blank picture"
print("ok")
"""


@lru_cache(maxsize=1)
def offscreen_problem(timeout: float = 120.0) -> str | None:
    """Why off-screen rendering cannot work here, or ``None`` when it does.

    Renders a tiny picture in a child process (a broken OpenGL set-up can
    abort the process instead of raising), with the configuration of
    :func:`configure_offscreen`. The answer is cached.

    Returns
    -------
    str or None
        ``None`` when a non-blank picture came back; else a one-line reason.
    """
    try:
        done = subprocess.run(
            [sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=timeout, check=False
        )
    except subprocess.TimeoutExpired:
        return f"a 64x48 off-screen render took more than {timeout:.0f} s"
    if done.returncode == 0 and done.stdout.strip().endswith("ok"):
        return None
    err = re.sub(r"\x1b\[[0-9;]*m", "", done.stderr).strip()
    tail = (err.splitlines() or [f"exit status {done.returncode}"])[-1].strip()
    window = os.environ.get("VTK_DEFAULT_OPENGL_WINDOW", "VTK's default")
    return f"off-screen rendering failed (render window: {window}): {tail}"


# -------------------------------------------------------------- the plotter
def new_plotter(size: Sequence[int] = (800, 600), *, shape: tuple[int, int] = (1, 1),
                groups=None) -> pyvista.Plotter:
    """An off-screen plotter with the gatv style (white background).

    Parameters
    ----------
    size : (int, int), default: (800, 600)
        Window width and height in pixels.
    shape : (int, int), default: (1, 1)
        Rows and columns of panels; pick one with ``plotter.subplot(r, c)``.
    groups : sequence of (rows, cols), optional
        Panels spanning several cells, as PyVista's ``groups`` (e.g.
        ``[(slice(None), 0)]``: the first column is one tall panel, picked
        with ``subplot(0, 0)``).

    Returns
    -------
    pyvista.Plotter
        Close it with :func:`save` (or ``plotter.close()``).
    """
    configure_offscreen()
    import pyvista as pv

    w, h = _check_size(size)
    pl = pv.Plotter(off_screen=True, window_size=[w, h], shape=shape, border=shape != (1, 1),
                    border_color="#D0D0D0", border_width=1.0, groups=groups)
    pl.set_background("white")
    return pl


def _check_size(size) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in size)
    except (TypeError, ValueError):
        msg = f"Expected `size` to be (width, height) in pixels, got {size!r}."
        raise InputError(msg) from None
    if w < 16 or h < 16:
        msg = f"Expected `size` of at least (16, 16) pixels, got {size!r}."
        raise InputError(msg)
    return w, h


def _panel_px(plotter) -> tuple[float, float]:
    w, h = plotter.window_size
    rows, cols = plotter.shape
    return w / max(1, cols), h / max(1, rows)


def font_size(plotter, base: float = 10.0) -> int:
    """Font size that scales with the panel (``base`` at 500x400 px)."""
    w, h = _panel_px(plotter)
    return max(6, round(base * min(h / 400.0, w / 500.0)))


# ------------------------------------------------------------------ drawing
def add_points(plotter, points, *, color: str = PALETTE[0], size: float = 8.0, label: str | None = None,
               opacity: float = 1.0):
    """Draw points as flat discs of one colour.

    Parameters
    ----------
    plotter : pyvista.Plotter
    points : (N, 3) array_like of float
    color : str, default: ``PALETTE[0]``
    size : float, default: 8
        Disc diameter in pixels.
    label : str, optional
        Legend entry.
    opacity : float, default: 1

    Returns
    -------
    vtkActor or None
        ``None`` when ``points`` is empty.
    """
    p = as_points(points, "points", min_points=0)
    if p.shape[0] == 0:
        return None
    kw = {"label": label} if label else {}
    return plotter.add_points(p, color=color, point_size=size, render_points_as_spheres=True,
                              lighting=False, opacity=opacity, reset_camera=True, **kw)


def add_correspondences(plotter, source, target, pairs=None, *, color: str = LINE_COLOR,
                        width: float = 1.0, label: str | None = None, opacity: float = 1.0):
    """Draw a line from ``source[i]`` to ``target[j]`` for each pair ``(i, j)``.

    Parameters
    ----------
    plotter : pyvista.Plotter
    source, target : (N, 3), (M, 3) array_like of float
    pairs : (K, 2) array_like of int, optional
        ``(source index, target index)`` rows; default: row ``i`` to row
        ``i`` (``source`` and ``target`` paired).
    color : str, default: :data:`LINE_COLOR`
    width : float, default: 1
    label : str, optional
    opacity : float, default: 1

    Returns
    -------
    vtkActor or None
        ``None`` when there are no pairs.
    """
    import pyvista as pv

    s = as_points(source, "source", min_points=0)
    t = as_points(target, "target", min_points=0)
    if pairs is None:
        if s.shape != t.shape:
            msg = f"Without `pairs`, `source` and `target` must be paired, got {s.shape} and {t.shape}."
            raise InputError(msg)
        a, b = s, t
    else:
        c = _as_pairs(pairs, s.shape[0], t.shape[0])
        a, b = s[c[:, 0]], t[c[:, 1]]
    if a.shape[0] == 0:
        return None
    seg = np.empty((2 * a.shape[0], 3))
    seg[0::2], seg[1::2] = a, b
    kw = {"label": label} if label else {}
    return plotter.add_mesh(pv.line_segments_from_points(seg), color=color, line_width=width,
                            opacity=opacity, lighting=False, **kw)


def _as_pairs(pairs, n_source: int, n_target: int) -> np.ndarray:
    c = np.asarray(pairs)
    if c.size == 0:
        return np.empty((0, 2), np.int64)
    if c.ndim != 2 or c.shape[1] != 2 or c.dtype.kind not in "iu":
        msg = f"Expected `pairs` to be a (K, 2) integer array, got shape {c.shape} and dtype {c.dtype}."
        raise InputError(msg)
    c = c.astype(np.int64)
    if (c < 0).any() or (c[:, 0] >= n_source).any() or (c[:, 1] >= n_target).any():
        msg = f"`pairs` index past the points ({n_source} source, {n_target} target)."
        raise InputError(msg)
    return c


def add_tokens(plotter, tokens, saliency=None, *, title: str = "saliency", cmap: str = CMAP,
               clim: tuple[float, float] | None = None, size: float = 5.0, color: str = NEUTRAL,
               label: str | None = None, opacity: float = 1.0):
    """Draw joint-space tokens, coloured by saliency with a scalar bar.

    Parameters
    ----------
    plotter : pyvista.Plotter
    tokens : (N, 3) array_like of float
    saliency : (N,) array_like of float, optional
        Colour values (e.g. ``TensorVotes.surfaceness``); without it the
        tokens are drawn in ``color`` and no scalar bar is added.
    title : str, default: "saliency"
        Scalar-bar title (must differ between bars of one plotter).
    cmap : str, default: "viridis"
    clim : (float, float), optional
        Colour range; default the saliency's range.
    size : float, default: 5
    color : str, default: :data:`NEUTRAL`
    label : str, optional
    opacity : float, default: 1

    Returns
    -------
    vtkActor or None
    """
    import pyvista as pv

    p = as_points(tokens, "tokens", min_points=0)
    if p.shape[0] == 0:
        return None
    if saliency is None:
        return add_points(plotter, p, color=color, size=size, label=label, opacity=opacity)
    s = np.asarray(saliency, dtype=np.float64).reshape(-1)
    if s.shape[0] != p.shape[0] or not np.all(np.isfinite(s)):
        msg = f"Expected `saliency` to hold {p.shape[0]} finite values, got shape {np.shape(saliency)}."
        raise InputError(msg)
    cloud = pv.PolyData(p)
    cloud[title] = s
    fs = font_size(plotter, 13.0)
    bar = {"title": title, "color": "black", "vertical": True, "position_x": 0.87, "position_y": 0.1,
           "width": 0.05, "height": 0.55, "title_font_size": fs, "label_font_size": fs, "n_labels": 4,
           "fmt": "%.3g", "font_family": _FONT, "unconstrained_font_size": True}
    kw = {"label": label} if label else {}
    return plotter.add_mesh(cloud, scalars=title, cmap=cmap, clim=clim, point_size=size,
                            render_points_as_spheres=True, lighting=False, opacity=opacity,
                            scalar_bar_args=bar, **kw)


def add_normals(plotter, points, normals, *, scale: float | None = None, color: str = LINE_COLOR,
                label: str | None = None):
    """Draw normals (or any directions) as arrow glyphs at ``points``.

    Parameters
    ----------
    plotter : pyvista.Plotter
    points : (N, 3) array_like of float
    normals : (N, 3) array_like of float
        Directions; normalised here (zero rows are dropped).
    scale : float, optional
        Arrow length in data units; default 6% of the points' bounding-box
        diagonal (or 1 for a single point).
    color : str, default: :data:`LINE_COLOR`
    label : str, optional

    Returns
    -------
    vtkActor or None
    """
    import pyvista as pv

    p = as_points(points, "points", min_points=0)
    n = as_points(normals, "normals", min_points=0)
    if n.shape != p.shape:
        msg = f"Expected `normals` to have shape {p.shape}, got {n.shape}."
        raise InputError(msg)
    length = np.linalg.norm(n, axis=1)
    keep = length > 0
    if not keep.any():
        return None
    p, n = p[keep], n[keep] / length[keep, None]
    if scale is None:
        diag = float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))
        scale = 0.06 * diag if diag > 0 else 1.0
    cloud = pv.PolyData(p)
    cloud["normals"] = n
    arrows = cloud.glyph(orient="normals", scale=False, factor=float(scale),
                         geom=pv.Arrow(tip_length=0.3, tip_radius=0.12, shaft_radius=0.04))
    kw = {"label": label} if label else {}
    return plotter.add_mesh(arrows, color=color, **kw)


def fit_plane(tokens, normal=None, offset: float | None = None):
    """A plane patch through ``tokens``: centre, unit normal, in-plane axes, half sizes.

    Parameters
    ----------
    tokens : (N, 3) array_like of float
        At least 3 tokens without a normal, 1 with.
    normal : (3,) array_like of float, optional
        Plane normal; default the direction of least variance (PCA).
    offset : float, optional
        Plane ``normal · u = offset`` (with the unit normal); default the
        tokens' mean along the normal.

    Returns
    -------
    center : (3,) ndarray
        The tokens' centroid projected onto the plane.
    normal : (3,) ndarray
        Unit normal.
    axes : (2, 3) ndarray
        In-plane unit axes (the tokens' principal directions in the plane).
    half_sizes : (2,) ndarray
        Half extents along ``axes`` covering every token (at least 1e-3 of
        the larger one).
    """
    p = as_points(tokens, "tokens", min_points=1 if normal is not None else 3)
    c = p.mean(axis=0)
    if normal is None:
        _, _, vt = np.linalg.svd(p - c, full_matrices=False)
        nrm = vt[2]
    else:
        nrm = np.asarray(normal, dtype=np.float64).reshape(-1)
        if nrm.shape != (3,) or not np.all(np.isfinite(nrm)) or np.linalg.norm(nrm) == 0:
            msg = f"Expected `normal` to be 3 finite numbers, not all zero, got {normal!r}."
            raise InputError(msg)
        nrm = nrm / np.linalg.norm(nrm)
    off = float(c @ nrm) if offset is None else float(offset)
    center = c - (c @ nrm - off) * nrm
    q = p - center
    q = q - np.outer(q @ nrm, nrm)
    if p.shape[0] >= 2 and np.abs(q).max() > 0:
        _, _, vt = np.linalg.svd(q, full_matrices=False)
        u = vt[0] - (vt[0] @ nrm) * nrm
        u /= np.linalg.norm(u)
    else:
        u = np.cross(nrm, [1.0, 0.0, 0.0] if abs(nrm[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
    v = np.cross(nrm, u)
    half = np.array([np.abs(q @ u).max(), np.abs(q @ v).max()])
    half = np.maximum(half, 1e-3 * max(half.max(), 1.0))
    return center, nrm, np.stack([u, v]), half


def add_plane(plotter, tokens, normal=None, offset: float | None = None, *, color: str = PALETTE[0],
              opacity: float = 0.35, margin: float = 0.08, label: str | None = None, edges: bool = True):
    """Draw a translucent rectangular plane patch fitted to ``tokens``.

    The patch lies on the plane of :func:`fit_plane` and covers the tokens'
    projections plus ``margin`` of its size on each side.

    Parameters
    ----------
    plotter : pyvista.Plotter
    tokens : (N, 3) array_like of float
    normal : (3,) array_like, optional
        Fixed normal (e.g. the rotation axis, eq. 30); default: PCA.
    offset : float, optional
        Fixed ``normal · u = offset``; default: through the tokens.
    color : str, default: ``PALETTE[0]``
    opacity : float, default: 0.35
    margin : float, default: 0.08
    label : str, optional
    edges : bool, default: True
        Outline the patch in ``color``.

    Returns
    -------
    vtkActor
    """
    import pyvista as pv

    center, _, (u, v), half = fit_plane(tokens, normal, offset)
    a, b = half * (1.0 + 2.0 * margin)
    corners = np.array([center - a * u - b * v, center + a * u - b * v,
                        center + a * u + b * v, center - a * u + b * v])
    quad = pv.PolyData(corners, faces=[4, 0, 1, 2, 3])
    kw = {"label": label} if label else {}
    actor = plotter.add_mesh(quad, color=color, opacity=opacity, ambient=0.5, diffuse=0.6,
                             specular=0.0, **kw)
    if edges:
        ring = pv.lines_from_points(np.vstack([corners, corners[:1]]))
        plotter.add_mesh(ring, color=color, line_width=2, lighting=False)
    return actor


def add_surface(plotter, tokens, scalars=None, *, color: str = PALETTE[0], title: str = "surfaceness",
                cmap: str = CMAP, opacity: float = 0.6, label: str | None = None, max_edge: float | None = None):
    """Draw a surface through ``tokens`` (a triangulation over their best-fit plane).

    For the curved surfaces of non-rigid motions (Figs. 13–14): the tokens
    are projected on their PCA plane and triangulated there (Delaunay), so
    the surface must be a height field over that plane.

    Parameters
    ----------
    plotter : pyvista.Plotter
    tokens : (N, 3) array_like of float
        At least 3 tokens, not collinear.
    scalars : (N,) array_like of float, optional
        Values to colour the surface by (with a scalar bar titled ``title``).
    color : str, default: ``PALETTE[0]``
    title : str, default: "surfaceness"
    cmap : str, default: "viridis"
    opacity : float, default: 0.6
    label : str, optional
    max_edge : float, optional
        Drop triangles with an edge longer than this (data units; holes in
        the token set); default 4x the median token spacing.

    Returns
    -------
    vtkActor
    """
    import pyvista as pv
    from scipy.spatial import Delaunay, cKDTree

    p = as_points(tokens, "tokens", min_points=3)
    center, _, (u, v), _ = fit_plane(p)
    uv = np.c_[(p - center) @ u, (p - center) @ v]
    tri = Delaunay(uv).simplices
    if max_edge is None:
        d, _ = cKDTree(p).query(p, k=2)
        max_edge = 4.0 * float(np.median(d[:, 1]))
    e = np.stack([np.linalg.norm(p[tri[:, i]] - p[tri[:, (i + 1) % 3]], axis=1) for i in range(3)], axis=1)
    tri = tri[e.max(axis=1) <= max_edge] if (e.max(axis=1) <= max_edge).any() else tri
    faces = np.c_[np.full(len(tri), 3), tri].ravel()
    mesh = pv.PolyData(p, faces=faces)
    kw = {"label": label} if label else {}
    if scalars is None:
        return plotter.add_mesh(mesh, color=color, opacity=opacity, smooth_shading=True, **kw)
    s = np.asarray(scalars, dtype=np.float64).reshape(-1)
    if s.shape[0] != p.shape[0]:
        msg = f"Expected `scalars` to hold {p.shape[0]} values, got {s.shape[0]}."
        raise InputError(msg)
    mesh[title] = s
    fs = font_size(plotter, 13.0)
    bar = {"title": title, "color": "black", "vertical": True, "position_x": 0.87, "position_y": 0.1,
           "width": 0.05, "height": 0.55, "title_font_size": fs, "label_font_size": fs, "fmt": "%.3g",
           "font_family": _FONT, "unconstrained_font_size": True}
    return plotter.add_mesh(mesh, scalars=title, cmap=cmap, opacity=opacity, smooth_shading=True,
                            scalar_bar_args=bar, **kw)


def _nice_step(span: float, n: int) -> float:
    raw = max(span, 1e-12) / max(1, n)
    mag = 10.0 ** np.floor(np.log10(raw))
    for m in (1.0, 2.0, 2.5, 5.0, 10.0):
        if m * mag >= raw:
            return m * mag
    return 10.0 * mag  # pragma: no cover


def nice_bounds(bounds, ticks: int = 3):
    """Bounds widened to round tick values, and the tick count per axis.

    Parameters
    ----------
    bounds : (6,) sequence of float
        ``(xmin, xmax, ymin, ymax, zmin, zmax)``.
    ticks : int, default: 3
        Wanted intervals per axis (a few more may come out).

    Returns
    -------
    bounds : tuple of 6 float
    counts : tuple of 3 int
        Labels per axis (intervals + 1).
    """
    out, counts = [], []
    for lo, hi in zip(bounds[0::2], bounds[1::2], strict=True):
        step = _nice_step(hi - lo, ticks)
        a, b = np.floor(lo / step) * step, np.ceil(hi / step) * step
        if b <= a:
            a, b = a - step, b + step
        out += [float(a), float(b)]
        counts.append(int(round((b - a) / step)) + 1)
    return tuple(out), tuple(counts)


#: Default camera direction (from the focal point towards the camera).
VIEW = (-0.55, -0.75, 0.4)


def set_view(plotter, direction=VIEW, *, zoom: float = 1.0):
    """Point the current panel's camera along ``direction`` (z up) and fit the data.

    ``direction`` points from the data towards the camera.
    """
    plotter.view_vector(direction, viewup=(0.0, 0.0, 1.0))
    plotter.reset_camera()
    if zoom != 1.0:
        plotter.camera.zoom(zoom)


def add_axes_labels(plotter, xlabel: str = "x", ylabel: str = "y", zlabel: str = "z", *, ticks: int = 3,
                    unlabelled: str | None = None):
    """Label the axes of the current panel: a box with round ticks and titles.

    Call after the data are drawn; the box encloses everything in the panel
    (widened to round numbers, see :func:`nice_bounds`).

    Parameters
    ----------
    plotter : pyvista.Plotter
    xlabel, ylabel, zlabel : str
    ticks : int, default: 3
        Wanted tick intervals per axis.
    unlabelled : {"x", "y", "z"}, optional
        An axis drawn with its title but without tick labels: the one
        pointing most nearly at the camera, whose foreshortened labels
        crowd each other and the next axis's at their shared corner.
    """
    bounds, (nx, ny, nz) = nice_bounds(plotter.renderer.bounds, ticks)
    fs = font_size(plotter, 12.0)
    shown = {f"show_{a}labels": a != unlabelled for a in "xyz"}
    plotter.show_bounds(bounds=bounds, xtitle=xlabel, ytitle=ylabel, ztitle=zlabel, color="#202020",
                        font_size=fs, font_family=_FONT, bold=False, location="outer", ticks="outside",
                        n_xlabels=nx, n_ylabels=ny, n_zlabels=nz, fmt=_tick_format(bounds, (nx, ny, nz)),
                        grid=False, use_3d_text=False, **shown)


def _tick_format(bounds, counts) -> str:
    """printf format of tick labels: fixed decimals for fractional steps.

    VTK computes the labels as ``lo + k * step`` in floating point, so a
    zero tick can come out as ``2.776e-17`` under ``%g``; fixed decimals
    (as many as the finest step needs) print it as ``0.0``.
    """
    steps = [(hi - lo) / max(1, n - 1) for lo, hi, n in zip(bounds[0::2], bounds[1::2], counts, strict=True)]
    finest = min(step for step in steps if step > 0) if any(step > 0 for step in steps) else 1.0
    if finest >= 1.0:
        return "%.4g"
    decimals = min(6, int(np.ceil(-np.log10(finest) - 1e-9)) + (0 if _is_decade(finest) else 1))
    return f"%.{decimals}f"


def _is_decade(step: float) -> bool:
    """Whether ``step`` is 1, 2 or 5 times a power of ten with one significant digit (0.1, 0.2, 0.5)."""
    mag = 10.0 ** np.floor(np.log10(step))
    return any(abs(step - m * mag) <= 1e-9 * mag for m in (1.0, 2.0, 5.0))


def add_legend(plotter, *, loc: str = "upper right"):
    """Legend of the current panel's labelled items (white box, grey border).

    The box is sized from the number and length of the labels and the
    panel's size, and placed inside the panel (below the title line when
    at the top). Does nothing when the
    panel has no labelled item.

    Parameters
    ----------
    plotter : pyvista.Plotter
    loc : {"upper right", "upper left", "lower right", "lower left"}, default: "upper right"
    """
    labels = getattr(plotter.renderer, "_labels", None)
    if not labels:
        return None
    corners = {"upper right": (1, 1), "upper left": (0, 1), "lower right": (1, 0), "lower left": (0, 0)}
    if loc not in corners:
        msg = f"Expected `loc` to be one of {sorted(corners)}, got {loc!r}."
        raise InputError(msg)
    pw, ph = _panel_px(plotter)
    n = len(labels)
    longest = max(len(text) for _, text, _ in labels.values())
    line = min(max(0.036 * ph, 11.0), 18.0)  # entry height, px
    w = min(0.6, (line * (1.6 + 0.55 * longest)) / pw)
    h = min(0.5, (line * n * 1.25 + 6.0) / ph)
    leg = plotter.add_legend(bcolor="white", border=True, size=(w, h), face="circle", font_family=_FONT)
    right, top = corners[loc]
    title = 2.2 * font_size(plotter, 10.0) / ph  # room for the panel title
    leg.SetPosition(1.0 - w - 0.01 if right else 0.01, 1.0 - h - title if top else 0.01)
    leg.GetProperty().SetColor(0.6, 0.6, 0.6)
    return leg


def add_title(plotter, text: str, *, position: str = "upper_left"):
    """A title in the current panel's corner, scaled to its height."""
    plotter.add_text(text, position=position, font_size=font_size(plotter, 10.0), color="black", font=_FONT)


# ------------------------------------------------------------ image pairs
def _grey(image, name: str) -> np.ndarray:
    a = np.asarray(image, dtype=np.float64)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        a = a[..., :3] @ np.array([0.299, 0.587, 0.114])
    if a.ndim != 2 or min(a.shape) < 2 or not np.all(np.isfinite(a)):
        msg = f"Expected `{name}` to be a finite (H, W) grey or (H, W, 3) colour image, got shape {np.shape(image)}."
        raise InputError(msg)
    return a


def _pixels(pixels, name: str) -> np.ndarray:
    p = np.asarray(pixels, dtype=np.float64)
    if p.size == 0:
        return np.empty((0, 2))
    if p.ndim != 2 or p.shape[1] != 2:
        msg = f"Expected `{name}` to have shape (N, 2), got {p.shape}."
        raise InputError(msg)
    return p


def add_image_pair(plotter, image1, image2, pixels1, pixels2, pairs=None, *, right=None, gap: float = 40.0,
                   title: str | None = None, corner_color: str = PALETTE[4], right_color: str = PALETTE[2],
                   wrong_color: str = PALETTE[1], size: float = 9.0, clim: tuple[float, float] | None = None):
    """Two images side by side in the current panel, their corners and matched corners linked (Fig. 15).

    Image 1 on the left, image 2 on the right, rows top to bottom as in an
    image; every corner is a small dot, matched corners are larger discs
    joined by a line. The panel gets a 2D camera (parallel projection)
    framing both images.

    Parameters
    ----------
    plotter : pyvista.Plotter
    image1, image2 : (H, W) or (H, W, 3) array_like
        Grey (or colour, drawn grey) images.
    pixels1, pixels2 : (N1, 2), (N2, 2) array_like of float
        Corner pixels ``(u, v)``: column, row.
    pairs : (K, 2) array_like of int, optional
        Matched rows of ``pixels1`` and ``pixels2``.
    right : (K,) array_like of bool, optional
        Which pairs are right (e.g. against a ground truth): drawn in
        ``right_color``, the others in ``wrong_color``; default all in
        ``right_color``.
    gap : float, default: 40
        Pixels between the two images.
    title : str, optional
        Panel title.
    corner_color, right_color, wrong_color : str
    size : float, default: 9
        Disc diameter of a matched corner, pixels on screen.
    clim : (float, float), optional
        Grey values drawn black and white; default the images' range.

    Notes
    -----
    The images are drawn at about the panel's resolution: averaged over
    ``f x f`` blocks when the panel shows more than one image pixel per
    screen pixel (the corners keep their sub-pixel positions).
    """
    import pyvista as pv

    a, b = _grey(image1, "image1"), _grey(image2, "image2")
    p1, p2 = _pixels(pixels1, "pixels1"), _pixels(pixels2, "pixels2")
    c = _as_pairs(pairs if pairs is not None else np.empty((0, 2), np.int64), p1.shape[0], p2.shape[0])
    ok = np.ones(c.shape[0], bool) if right is None else np.asarray(right, bool).reshape(-1)
    if ok.shape[0] != c.shape[0]:
        msg = f"Expected `right` to hold {c.shape[0]} flags, got {ok.shape[0]}."
        raise InputError(msg)
    h = max(a.shape[0], b.shape[0])
    dx = float(a.shape[1] + gap)
    w = dx + b.shape[1]
    lo, hi = (min(float(a.min()), float(b.min())), max(float(a.max()), float(b.max()))) if clim is None else clim
    f = max(1, int(w // max(1.0, _panel_px(plotter)[0])))
    for img, x0 in ((a, 0.0), (b, dx)):
        ny, nx = img.shape[0] // f, img.shape[1] // f
        small = img[: ny * f, : nx * f].reshape(ny, f, nx, f).mean(axis=(1, 3))
        grid = pv.ImageData(dimensions=(nx, ny, 1), spacing=(f, f, 1.0),
                            origin=(x0 + 0.5 * (f - 1), h - ny * f + 0.5 * (f - 1), 0.0))
        grid.point_data["grey"] = small[::-1].ravel()
        plotter.add_mesh(grid, scalars="grey", cmap="gray", clim=(lo, hi if hi > lo else lo + 1.0),
                         show_scalar_bar=False, lighting=False)

    def xyz(p, x0, z):
        return np.column_stack([p[:, 0] + x0, (h - 1) - p[:, 1], np.full(len(p), z)])

    q1, q2 = xyz(p1, 0.0, 1.0), xyz(p2, dx, 1.0)
    for q, label in ((q1, "corners"), (q2, None)):
        q = q[np.all(np.isfinite(q), axis=1)]
        add_points(plotter, q, color=corner_color, size=max(2.0, 0.45 * size), label=label)
    for flags, color, name in ((ok, right_color, "right"), (~ok, wrong_color, "wrong")):
        if not flags.any():
            continue
        s, t = xyz(p1[c[flags, 0]], 0.0, 2.0), xyz(p2[c[flags, 1]], dx, 2.0)
        add_correspondences(plotter, s, t, color=color, width=1.0, opacity=0.55)
        add_points(plotter, np.vstack([s, t]), color=color, size=size,
                   label=f"{int(flags.sum())} match{'es' * (int(flags.sum()) != 1)}" + ("" if right is None else f", {name}"))
    if title:
        add_title(plotter, title)
    plotter.enable_parallel_projection()
    cam = plotter.camera
    cam.focal_point = (w / 2.0, h / 2.0, 0.0)
    cam.position = (w / 2.0, h / 2.0, 10.0 * w)
    cam.up = (0.0, 1.0, 0.0)
    pw, ph = _panel_px(plotter)
    cam.parallel_scale = 0.5 * max(h * 1.16, w * ph / pw * 1.02)  # room for the title line
    plotter.renderer.ResetCameraClippingRange()


# ---------------------------------------------------------------- writing
def save(plotter, path, size: Sequence[int] | None = None) -> Path:
    """Screenshot ``plotter`` to ``path`` atomically, then close it.

    The picture is written to a temporary file in the destination's folder
    (same extension, so VTK picks the format) and moved onto ``path`` with
    :func:`os.replace`: readers never see half a file, and an error leaves
    ``path`` untouched. The plotter is closed in every case.

    Parameters
    ----------
    plotter : pyvista.Plotter
    path : str or path-like
        ``.png`` (or another extension VTK writes: ``.jpg``, ``.bmp``,
        ``.tif``); its folder must exist.
    size : (int, int), optional
        Width and height in pixels; default the plotter's window size.

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    dest = Path(path)
    try:
        folder = dest.parent if str(dest.parent) else Path(".")
        if not folder.is_dir():
            msg = f"Cannot write {dest}: folder {str(folder)!r} does not exist."
            raise FileNotFoundError(msg)
        window = list(_check_size(size)) if size is not None else None
        fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=f".tmp{dest.suffix}", dir=folder)
        os.close(fd)
        try:
            plotter.screenshot(tmp, window_size=window, return_img=False)
            mask = os.umask(0)
            os.umask(mask)
            os.chmod(tmp, 0o666 & ~mask)
            os.replace(tmp, dest)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    finally:
        plotter.close()
    return dest


# ------------------------------------------------------------ figure level
#: Most correspondence lines :func:`render_registration` draws: a sample of
#: the correspondences, so that the lines stay lines (27,000 of them between
#: two range scans fill in as a black sheet).
MAX_LINES = 150
#: Camera direction for data with y up (range scans: the scanner's frame, y
#: up and the scanner on the +z side).
VIEW_Y_UP = (0.4, 0.3, 1.0)


def _up_axis(motion, up) -> str:
    """``"x"``, ``"y"`` or ``"z"``: ``up`` as given, else y for scans (their frame is y up), z otherwise."""
    if up is None:
        info = getattr(motion, "info", None) or {}
        return "y" if info.get("pipeline") == "scans" else "z"
    if up not in ("x", "y", "z"):
        msg = f"Expected `up` to be 'x', 'y', 'z' or None, got {up!r}."
        raise InputError(msg)
    return up


def _view(up: str) -> tuple[tuple, tuple]:
    """Camera direction and view-up vector of a panel whose ``up`` axis points up."""
    if up == "z":
        return VIEW, (0.0, 0.0, 1.0)
    if up == "y":
        return VIEW_Y_UP, (0.0, 1.0, 0.0)
    return (1.0, 0.4, 0.3), (1.0, 0.0, 0.0)


def sample_pairs(pairs, k: int = MAX_LINES, seed: int = 0) -> np.ndarray:
    """At most ``k`` rows of ``pairs``, drawn without replacement (same seed, same rows), in order."""
    c = np.asarray(pairs)
    if len(c) <= k:
        return c
    rows = np.sort(np.random.default_rng(seed).choice(len(c), size=k, replace=False))
    return c[rows]


def render_registration(source, target, motion: RigidMotion, path, *, size: Sequence[int] = (1200, 800),
                        up: str | None = None, max_lines: int = MAX_LINES) -> Path:
    """Picture of one registration: before (left) and after (right).

    Left: source and target with a line for a sample of the correspondences
    (at most ``max_lines``, drawn thin; the legend says how many of how
    many). Right: the source moved by ``motion`` over the target, matched
    target points highlighted. Unmatched points are drawn smaller. One
    legend, in the left panel; both panels look at the data with its ``up``
    axis up.

    Parameters
    ----------
    source, target : (N, 3), (M, 3) array_like of float
    motion : RigidMotion
        ``target ≈ motion.transform(source)``; a falsy (failed) motion draws
        the inputs and its reason.
    path : str or path-like
        Output picture (``.png``); written atomically.
    size : (int, int), default: (1200, 800)
    up : {"x", "y", "z"}, optional
        The axis drawn upwards.  Default: y for a result of the scans
        pipeline (range scans and most meshes are y up, e.g. the Stanford
        bunny), z otherwise.
    max_lines : int, default: :data:`MAX_LINES`

    Returns
    -------
    pathlib.Path
    """
    s = as_points(source, "source", min_points=1)
    t = as_points(target, "target", min_points=1)
    c = _as_pairs(motion.correspondences, s.shape[0], t.shape[0])
    direction, viewup = _view(_up_axis(motion, up))
    depth = _depth_axis(direction)
    lines = sample_pairs(c, max(0, int(max_lines)))
    moved = motion.transform(s)
    src_col, tgt_col = PALETTE[1], PALETTE[0]
    matched_s = np.zeros(s.shape[0], bool)
    matched_s[c[:, 0]] = True
    matched_t = np.zeros(t.shape[0], bool)
    matched_t[c[:, 1]] = True
    small, large = (2, 4) if max(s.shape[0], t.shape[0]) > 5000 else (5, 9)
    pl = new_plotter(size, shape=(1, 2))
    try:
        pl.subplot(0, 0)
        add_points(pl, t[~matched_t], color=tgt_col, size=small)
        add_points(pl, s[~matched_s], color=src_col, size=small)
        add_points(pl, t[matched_t], color=tgt_col, size=large, label="target")
        add_points(pl, s[matched_s], color=src_col, size=large, label="source (right: aligned)")
        shown = f"{len(lines)} of {len(c)}" if len(lines) < len(c) else f"{len(c)}"
        add_correspondences(pl, s, t, lines, width=1, opacity=0.8, label=f"{shown} correspondences")
        add_axes_labels(pl, unlabelled=depth)
        add_title(pl, "(a) source and target")
        add_legend(pl, loc="lower left")
        _look(pl, direction, viewup)
        pl.subplot(0, 1)
        add_points(pl, t[~matched_t], color=tgt_col, size=small)
        add_points(pl, moved[~matched_s], color=src_col, size=small)
        # matched target points inside translucent halos of the aligned source
        add_points(pl, t[matched_t], color=tgt_col, size=max(small + 1, large - 2))
        add_points(pl, moved[matched_s], color=src_col, size=large + (6 if large > 4 else 3), opacity=0.45)
        add_axes_labels(pl, unlabelled=depth)
        if motion:
            add_title(pl, f"(b) aligned: {motion.angle_deg:.2f} deg, {motion.support} pairs")
        else:
            reason = motion.info.get("reason", "no motion found") if hasattr(motion, "info") else "no motion"
            add_title(pl, f"(b) registration failed: {reason}")
        _look(pl, direction, viewup)
    except BaseException:
        pl.close()
        raise
    return save(pl, path)


def _look(plotter, direction, viewup) -> None:
    plotter.view_vector(direction, viewup=viewup)
    plotter.reset_camera()
    plotter.camera.zoom(0.9)  # room for the axis titles at the panel's edges


def _depth_axis(direction) -> str:
    """The axis pointing most nearly at the camera."""
    return "xyz"[int(np.argmax(np.abs(direction)))]


def _grid(n: int) -> tuple[int, int]:
    if n <= 3:
        return 1, n
    cols = int(np.ceil(np.sqrt(n)))
    return int(np.ceil(n / cols)), cols


def render_motions(source, target, motions: Sequence[RigidMotion], path, *,
                   size: Sequence[int] | None = None) -> Path:
    """Several rigid motions between two point sets, one colour each (Fig. 12).

    Panel (a), the overview: every point coloured by the motion whose
    correspondences use it (target points large, source points small),
    unclaimed points grey. Then one panel per motion: its source points
    (small), their images under the motion (dark dots) inside its target
    points (translucent halos), with its correspondences as lines. Panels
    share one camera.

    Parameters
    ----------
    source, target : (N, 3), (M, 3) array_like of float
    motions : sequence of RigidMotion
        In the order found; motion ``k`` is drawn in ``motion_color(k)``.
        A point claimed by two motions takes the first one's colour.
    path : str or path-like
        Output picture (``.png``); written atomically.
    size : (int, int), optional
        Default 500x420 pixels per panel.

    Returns
    -------
    pathlib.Path
    """
    s = as_points(source, "source", min_points=1)
    t = as_points(target, "target", min_points=1)
    motions = list(motions)
    pairs = [_as_pairs(m.correspondences, s.shape[0], t.shape[0]) for m in motions]
    rows, cols = _grid(1 + len(motions))
    if size is None:
        size = (500 * cols, 420 * rows)
    owner_s = np.full(s.shape[0], -1)
    owner_t = np.full(t.shape[0], -1)
    for k in range(len(motions) - 1, -1, -1):
        owner_s[pairs[k][:, 0]] = k
        owner_t[pairs[k][:, 1]] = k
    pl = new_plotter(size, shape=(rows, cols))
    try:
        pl.subplot(0, 0)
        add_points(pl, t[owner_t < 0], color=NEUTRAL, size=6, label="no motion")
        add_points(pl, s[owner_s < 0], color=NEUTRAL, size=4)
        for k in range(len(motions)):
            col = motion_color(k)
            add_points(pl, s[owner_s == k], color=col, size=5)
            add_points(pl, t[owner_t == k], color=col, size=9, label=f"motion {k}")
        add_axes_labels(pl)
        add_title(pl, f"(a) {len(motions)} motions (large: target, small: source)")
        add_legend(pl)
        for k, (m, c) in enumerate(zip(motions, pairs, strict=True)):
            pl.subplot(*divmod(k + 1, cols))
            col = motion_color(k)
            add_points(pl, t[owner_t != k], color=NEUTRAL, size=3, opacity=0.5)
            add_points(pl, s[c[:, 0]], color=col, size=5, label="source (small)")
            add_correspondences(pl, s, t, c, color=col, width=1)
            # target points as translucent halos, so that the moved source
            # points (dark dots) show inside them
            add_points(pl, m.transform(s[c[:, 0]]), color=LINE_COLOR, size=4, label="source, moved")
            add_points(pl, t[c[:, 1]], color=col, size=13, opacity=0.45, label="target (halo)")
            add_axes_labels(pl)
            add_title(pl, f"({chr(ord('b') + k)}) motion {k}: {m.angle_deg:.1f} deg, {m.support} pairs")
            add_legend(pl)
        pl.subplot(0, 0)
        set_view(pl, zoom=0.92)  # room for the tick labels of the near edges
        pl.link_views()
    except BaseException:
        pl.close()
        raise
    return save(pl, path)


def render_segmentation(source, target, segmentation, path, *, size: Sequence[int] | None = None) -> Path:
    """Picture of a :class:`gatv.motions.Segmentation` (Fig. 12): one colour per motion.

    The same picture as :func:`render_motions` with the segmentation's
    motions, in its order (largest support first). An empty (falsy)
    segmentation draws the overview panel alone, every point grey.

    Parameters
    ----------
    source, target : (N, 3), (M, 3) array_like of float
    segmentation : Segmentation
        From :func:`gatv.motions.segment` on ``source`` and ``target``.
    path : str or path-like
        Output picture (``.png``); written atomically.
    size : (int, int), optional
        Default 500x420 pixels per panel.

    Returns
    -------
    pathlib.Path
    """
    return render_motions(source, target, tuple(segmentation.motions), path, size=size)
