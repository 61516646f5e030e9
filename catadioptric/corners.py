"""Sub-pixel corner detection (Shi–Tomasi / Harris) and image reading.

The detector computes the structure tensor of the image from Gaussian
derivatives (:mod:`scipy.ndimage`), scores each pixel with the smaller
eigenvalue (Shi & Tomasi 1994) or Harris' ``det - k trace^2``, keeps local
maxima above ``quality`` times the best score at least ``min_distance``
pixels apart, and refines each corner with the gradient-orthogonality
iteration of OpenCV's ``cornerSubPix`` (Förstner 1987): the corner ``q`` is
the point for which every image gradient ``g(p)`` in a window is orthogonal
to ``p - q``, i.e. ``q = (sum w g g^T)^-1 sum w g g^T p``.

Pixel convention: ``(u, v)`` with ``u`` the column and ``v`` the row, the
centre of the top-left pixel at ``(0, 0)`` (as OpenCV and the shared
corner files).
"""

from __future__ import annotations

import numbers
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from gatv.validation import as_points, check_positive
from gatv.errors import InputError

if TYPE_CHECKING:
    from numpy.typing import ArrayLike, NDArray

__all__ = ["detect_corners", "read_image"]


def _read_pnm(path: Path) -> NDArray[np.float64]:
    """Read a binary or ASCII PGM/PPM (P2, P3, P5, P6) file."""
    data = path.read_bytes()
    tokens: list[bytes] = []
    pos = 0
    # Header: magic, width, height, maxval, separated by whitespace/comments.
    while len(tokens) < 4:
        while pos < len(data) and data[pos : pos + 1].isspace():
            pos += 1
        if data[pos : pos + 1] == b"#":
            while pos < len(data) and data[pos : pos + 1] not in (b"\n", b"\r"):
                pos += 1
            continue
        start = pos
        while pos < len(data) and not data[pos : pos + 1].isspace():
            pos += 1
        if start == pos:
            msg = f"`image` file {str(path)!r} has a truncated PNM header."
            raise InputError(msg)
        tokens.append(data[start:pos])
    magic = tokens[0]
    if magic not in (b"P2", b"P3", b"P5", b"P6"):
        msg = f"`image` file {str(path)!r} is not a PGM/PPM file (magic {magic!r})."
        raise InputError(msg)
    width, height, maxval = (int(t) for t in tokens[1:])
    channels = 3 if magic in (b"P3", b"P6") else 1
    count = width * height * channels
    if magic in (b"P5", b"P6"):
        dtype = np.dtype(">u2") if maxval > 255 else np.dtype("u1")
        raw = np.frombuffer(data, dtype=dtype, count=count, offset=pos + 1)
    else:
        raw = np.array(data[pos:].split()[:count], dtype=np.int64)
    if raw.size != count:
        msg = f"`image` file {str(path)!r} holds {raw.size} samples, expected {count}."
        raise InputError(msg)
    img = raw.astype(np.float64).reshape(height, width, channels)
    return img[..., 0] if channels == 1 else img


def read_image(image) -> NDArray[np.float64]:
    """Return a grey image as a ``(H, W)`` float64 array, rows top to bottom.

    Parameters
    ----------
    image : str, os.PathLike or array_like
        A path to a PNG/JPEG (read through PyVista/VTK) or PGM/PPM file
        (read here), or an array ``(H, W)`` (grey) or ``(H, W, 3|4)``
        (colour, converted with the Rec. 601 luma weights; alpha dropped).

    Returns
    -------
    (H, W) ndarray of float
        Intensities in the file's units (0–255 for 8-bit images). Row 0 is
        the top of the picture: VTK's bottom-up rows are flipped.

    Raises
    ------
    ValueError
        Missing file, unsupported format, or an array of the wrong shape.
    """
    if isinstance(image, (str, Path)) or hasattr(image, "__fspath__"):
        path = Path(image)
        if not path.is_file():
            msg = f"`image` file {str(path)!r} does not exist."
            raise InputError(msg)
        suffix = path.suffix.lower()
        if suffix in (".pgm", ".ppm", ".pnm"):
            arr = _read_pnm(path)
        elif suffix in (".png", ".jpg", ".jpeg"):
            import pyvista

            grid = pyvista.read(str(path))
            w, h = grid.dimensions[:2]
            scalars = np.asarray(grid.point_data[grid.point_data.keys()[0]])
            ncomp = 1 if scalars.ndim == 1 else scalars.shape[1]
            # VTK stores rows from the bottom of the picture up.
            arr = scalars.reshape(h, w, ncomp)[::-1].astype(np.float64)
            arr = arr[..., 0] if ncomp == 1 else arr
        else:
            msg = f"`image` file {str(path)!r}: unsupported format {suffix!r} (use PNG, JPEG or PGM)."
            raise InputError(msg)
    else:
        try:
            arr = np.asarray(image, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            msg = f"Expected `image` to be a 2D array of numbers or a path: {exc}."
            raise InputError(msg) from exc
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        arr = arr[..., :3] @ np.array([0.299, 0.587, 0.114])
    elif arr.ndim == 3 and arr.shape[2] in (1, 2):
        arr = arr[..., 0]
    if arr.ndim != 2:
        msg = f"Expected `image` to have shape (H, W) or (H, W, 3), got {arr.shape}."
        raise InputError(msg)
    if not np.all(np.isfinite(arr)):
        msg = "`image` contains NaN or infinite values."
        raise InputError(msg)
    return np.ascontiguousarray(arr)


def _structure_tensor(img, gradient_sigma, sigma):
    gy = ndimage.gaussian_filter(img, gradient_sigma, order=(1, 0))
    gx = ndimage.gaussian_filter(img, gradient_sigma, order=(0, 1))
    sxx = ndimage.gaussian_filter(gx * gx, sigma)
    sxy = ndimage.gaussian_filter(gx * gy, sigma)
    syy = ndimage.gaussian_filter(gy * gy, sigma)
    return gx, gy, sxx, sxy, syy


def _greedy_min_distance(cand_uv, min_distance, max_corners, shape):
    """Keep candidates (sorted best first) at least ``min_distance`` apart."""
    h, w = shape
    occupied = np.zeros(shape, dtype=bool)
    r = int(np.ceil(min_distance))
    dv, du = np.mgrid[-r : r + 1, -r : r + 1]
    disc = (du * du + dv * dv) < min_distance * min_distance
    du, dv = du[disc], dv[disc]
    keep = []
    for i, (u, v) in enumerate(cand_uv):
        if occupied[v, u]:
            continue
        keep.append(i)
        if len(keep) >= max_corners:
            break
        uu, vv = u + du, v + dv
        inside = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
        occupied[vv[inside], uu[inside]] = True
    return np.asarray(keep, dtype=np.intp)


def refine_corners(
    image: ArrayLike,
    corners: ArrayLike,
    *,
    window: int = 5,
    gradient_sigma: float = 0.7,
    max_iter: int = 30,
    eps: float = 1e-4,
) -> NDArray[np.float64]:
    """Refine corner positions to sub-pixel accuracy (``cornerSubPix``).

    Parameters
    ----------
    image : (H, W) array_like or path
        Grey image (see :func:`read_image`).
    corners : (N, 2) array_like of float
        Initial ``(u, v)`` positions.
    window : int, default: 5
        Half-size of the square window, in pixels (OpenCV's ``winSize``).
    gradient_sigma : float, default: 0.7
        Scale of the Gaussian derivative filters, in pixels.
    max_iter : int, default: 30
        Maximum number of iterations.
    eps : float, default: 1e-4
        Stop when no corner moves by more than ``eps`` pixels.

    Returns
    -------
    (N, 2) ndarray of float
        Refined ``(u, v)``. A corner whose refinement leaves its window or
        meets a singular system keeps its initial position.
    """
    img = read_image(image)
    q0 = as_points(corners, "corners", min_points=0, dim=2)
    if isinstance(window, bool) or not isinstance(window, numbers.Integral) or window < 1:
        msg = f"Expected `window` to be an integer >= 1, got {window!r}."
        raise InputError(msg)
    check_positive(gradient_sigma, "gradient_sigma")
    gx = ndimage.gaussian_filter(img, gradient_sigma, order=(0, 1))
    gy = ndimage.gaussian_filter(img, gradient_sigma, order=(1, 0))
    return _refine(gx * gx, gx * gy, gy * gy, q0, window, max_iter, eps)


def _refine(gxx, gxy, gyy, q0, window, max_iter, eps):
    h, w = gxx.shape
    dv, du = np.mgrid[-window : window + 1, -window : window + 1]
    du, dv = du.ravel(), dv.ravel()
    # Gaussian weights over the window, as in cornerSubPix (sigma = window/2).
    s2 = 2.0 * (0.5 * window + 0.5) ** 2
    q = q0.copy()
    active = np.ones(len(q), dtype=bool)
    for _ in range(max_iter):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        cur = q[idx]
        cu = np.rint(cur[:, 0]).astype(np.intp)
        cv = np.rint(cur[:, 1]).astype(np.intp)
        pu = np.clip(cu[:, None] + du[None, :], 0, w - 1)
        pv = np.clip(cv[:, None] + dv[None, :], 0, h - 1)
        wgt = np.exp(-((pu - cur[:, :1]) ** 2 + (pv - cur[:, 1:]) ** 2) / s2)
        a = wgt * gxx[pv, pu]
        b = wgt * gxy[pv, pu]
        c = wgt * gyy[pv, pu]
        A, B, C = a.sum(1), b.sum(1), c.sum(1)
        bx = (a * pu + b * pv).sum(1)
        by = (b * pu + c * pv).sum(1)
        det = A * C - B * B
        good = det > 1e-12 * (A + C) ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            nu = (C * bx - B * by) / det
            nv = (A * by - B * bx) / det
        new = np.column_stack([nu, nv])
        good &= np.all(np.isfinite(new), axis=1)
        good &= np.max(np.abs(new - q0[idx]), axis=1) <= window
        # Failed refinements go back to the initial position and stop.
        q[idx[~good]] = q0[idx[~good]]
        active[idx[~good]] = False
        moved = np.max(np.abs(new[good] - cur[good]), axis=1)
        q[idx[good]] = new[good]
        active[idx[good][moved <= eps]] = False
    return q


def detect_corners(
    image,
    *,
    max_corners: int = 500,
    min_distance: float = 5.0,
    quality: float = 0.01,
    sigma: float = 1.5,
    gradient_sigma: float = 1.0,
    method: str = "shi-tomasi",
    harris_k: float = 0.04,
    roi: tuple[float, float, float, float] | None = None,
    mask: ArrayLike | None = None,
    subpixel: bool = True,
    window: int = 5,
) -> NDArray[np.float64]:
    """Detect corners with sub-pixel accuracy.

    Parameters
    ----------
    image : (H, W) array_like, or str or os.PathLike
        Grey image, or a path to a PNG/JPEG/PGM file (see :func:`read_image`).
    max_corners : int, default: 500
        Return at most this many corners, the strongest first.
    min_distance : float, default: 5.0
        Minimum distance between two corners, in pixels.
    quality : float, default: 0.01
        Keep corners whose response is at least ``quality`` times the best
        response in the searched region (``0 < quality <= 1``).
    sigma : float, default: 1.5
        Integration scale of the structure tensor, in pixels.
    gradient_sigma : float, default: 1.0
        Scale of the Gaussian derivative filters, in pixels.
    method : {"shi-tomasi", "harris"}, default: "shi-tomasi"
        Corner response: smaller eigenvalue of the structure tensor, or
        ``det - harris_k * trace**2``.
    harris_k : float, default: 0.04
        Harris' constant.
    roi : (u_min, v_min, u_max, v_max), optional
        Search only this pixel rectangle (inclusive bounds).
    mask : (H, W) array_like of bool, optional
        Search only where ``mask`` is True (e.g. the mirror's image disc).
    subpixel : bool, default: True
        Refine with the gradient-orthogonality iteration; otherwise return
        integer pixel positions.
    window : int, default: 5
        Half-size of the refinement window, in pixels.

    Returns
    -------
    (N, 2) ndarray of float
        Corner positions ``(u, v)`` (column, row; the centre of the
        top-left pixel is ``(0, 0)``), sorted by decreasing response of
        their initial pixel. Every corner lies (to the nearest pixel) in
        the searched region: ``roi``, ``mask`` and away from the image
        border by ``3 * max(sigma, gradient_sigma) + 1`` pixels.

    Raises
    ------
    ValueError
        Invalid image or option; the message names the argument.

    References
    ----------
    J. Shi and C. Tomasi, "Good features to track", CVPR 1994.
    W. Förstner and E. Gülch, "A fast operator for detection and precise
    location of distinct points, corners and centres of circular
    features", 1987.

    Examples
    --------
    >>> import numpy as np
    >>> u, v = np.meshgrid(np.arange(40), np.arange(40))
    >>> board = 255.0 * (((u - 19.5) > 0) ^ ((v - 19.5) > 0))
    >>> detect_corners(board, max_corners=1).round(3)
    array([[19.5, 19.5]])
    """
    img = read_image(image)
    if isinstance(max_corners, bool) or not isinstance(max_corners, numbers.Integral) or max_corners < 1:
        msg = f"Expected `max_corners` to be an integer >= 1, got {max_corners!r}."
        raise InputError(msg)
    min_distance = check_positive(min_distance, "min_distance")
    quality = check_positive(quality, "quality")
    if quality > 1:
        msg = f"Expected `quality` in (0, 1], got {quality!r}."
        raise InputError(msg)
    sigma = check_positive(sigma, "sigma")
    gradient_sigma = check_positive(gradient_sigma, "gradient_sigma")
    if method not in ("shi-tomasi", "harris"):
        msg = f"Expected `method` to be 'shi-tomasi' or 'harris', got {method!r}."
        raise InputError(msg)
    if isinstance(window, bool) or not isinstance(window, numbers.Integral) or window < 1:
        msg = f"Expected `window` to be an integer >= 1, got {window!r}."
        raise InputError(msg)
    h, w = img.shape

    allowed = np.zeros((h, w), dtype=bool)
    border = int(np.ceil(3.0 * max(sigma, gradient_sigma))) + 1
    allowed[border : h - border, border : w - border] = True
    if roi is not None:
        try:
            u0, v0, u1, v1 = (float(x) for x in roi)
        except (TypeError, ValueError) as exc:
            msg = f"Expected `roi` to be (u_min, v_min, u_max, v_max), got {roi!r}."
            raise InputError(msg) from exc
        if not (u0 <= u1 and v0 <= v1):
            msg = f"Expected `roi` with u_min <= u_max and v_min <= v_max, got {roi!r}."
            raise InputError(msg)
        box = np.zeros_like(allowed)
        box[max(int(np.ceil(v0)), 0) : max(int(np.floor(v1)) + 1, 0),
            max(int(np.ceil(u0)), 0) : max(int(np.floor(u1)) + 1, 0)] = True  # fmt: skip
        allowed &= box
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != (h, w):
            msg = f"Expected `mask` to have the image's shape {(h, w)}, got {m.shape}."
            raise InputError(msg)
        allowed &= m.astype(bool)
    if not allowed.any():
        return np.empty((0, 2))

    gx, gy, sxx, sxy, syy = _structure_tensor(img, gradient_sigma, sigma)
    if method == "shi-tomasi":
        half_tr = 0.5 * (sxx + syy)
        resp = half_tr - np.sqrt(np.maximum(0.25 * (sxx - syy) ** 2 + sxy * sxy, 0.0))
    else:
        resp = sxx * syy - sxy * sxy - harris_k * (sxx + syy) ** 2
    best = resp[allowed].max()
    if not best > 0:
        return np.empty((0, 2))
    # Candidates: local maxima at least half of `min_distance` apart (a
    # blurred or saturated X-junction can peak twice, a few pixels off the
    # saddle point, on either side); the final spacing is enforced after
    # the sub-pixel refinement has pulled such pairs together.
    pool_distance = max(1.0, 0.5 * min_distance) if subpixel else min_distance
    size = 2 * int(np.floor(pool_distance)) + 1
    local_max = resp >= ndimage.maximum_filter(resp, size=size, mode="nearest")
    cand = allowed & local_max & (resp >= quality * best)
    vv, uu = np.nonzero(cand)
    order = np.argsort(-resp[vv, uu], kind="stable")
    uv = np.column_stack([uu[order], vv[order]])
    if not subpixel:
        keep = _greedy_min_distance(uv, min_distance, max_corners, (h, w))
        return uv[keep].astype(np.float64)
    keep = _greedy_min_distance(uv, pool_distance, 4 * max_corners + 100, (h, w))
    pool = uv[keep].astype(np.float64)
    fine = min(gradient_sigma, 0.7)
    fx = ndimage.gaussian_filter(img, fine, order=(0, 1))
    fy = ndimage.gaussian_filter(img, fine, order=(1, 0))
    refined = _refine(fx * fx, fx * fy, fy * fy, pool, int(window), 30, 1e-4)
    # Keep the corners that stayed in the searched region.
    iu = np.clip(np.rint(refined[:, 0]).astype(np.intp), 0, w - 1)
    iv = np.clip(np.rint(refined[:, 1]).astype(np.intp), 0, h - 1)
    refined = refined[allowed[iv, iu]]
    return refined[_dedupe(refined, min_distance, max_corners)]


def _dedupe(points, radius, max_points):
    """Indices of ``points`` (best first) at least ``radius`` apart."""
    if len(points) == 0:
        return np.empty(0, dtype=np.intp)
    tree = cKDTree(points)
    removed = np.zeros(len(points), dtype=bool)
    keep = []
    for i in range(len(points)):
        if removed[i]:
            continue
        keep.append(i)
        if len(keep) >= max_points:
            break
        removed[tree.query_ball_point(points[i], radius * (1.0 - 1e-9))] = True
    return np.asarray(keep, dtype=np.intp)
