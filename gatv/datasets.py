"""Synthetic trials of the paper's protocols, scoring helpers and real data.

Synthetic trials follow section 4 of Reyes, Medioni & Bayro (IJCV 2007):
inlier points uniform in a 10×10×10 cube centred at the origin, a random
rigid motion, and the same number of uniform outliers added to *each* set
inside that set's bounding box.

* :func:`table2_trial` — the Table 2 protocol (tensor voting): rotation
  angle uniform in 0..360° about an axis uniform on the sphere, translation
  uniform in [−10, 10]³.
* :func:`table1_trial` — the Table 1 protocol (F-ICP): angle uniform in
  −5..5°, translation uniform in [−1.5, 1.5]³.

The motion convention is the one of :mod:`gatv.motion`:
``target = source @ rotation.T + translation`` for true pairs.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._validation import check_nonnegative
from ._validation import frozen_array as _frozen
from .errors import InputError
from .motion import rotation_angle_deg

__all__ = [
    "Trial",
    "synthetic_trial",
    "table1_trial",
    "table2_trial",
    "outlier_count",
    "random_rotation",
    "correspondence_stats",
    "paper_success",
    "rotation_error_deg",
    "translation_error",
    "DataNotFoundError",
    "find_data_dir",
    "load_bunny_pair",
    "load_uwa_pair",
    "demo_mesh",
    "DEMO_MESHES",
]


@dataclass(frozen=True, eq=False)
class Trial:
    """One synthetic registration problem with its ground truth.

    Attributes
    ----------
    source : (N, 3) ndarray of float
        Inliers and outliers of the source set, shuffled.
    target : (M, 3) ndarray of float
        Moved inliers and outliers of the target set, shuffled independently.
    rotation : (3, 3) ndarray of float
        True rotation; ``target[j] = rotation @ source[i] + translation`` for
        every true pair ``(i, j)``.
    translation : (3,) ndarray of float
    true_pairs : (K, 2) ndarray of int
        ``(source index, target index)`` of the inliers, sorted by source
        index.
    outlier_fraction : float
        Fraction ``f`` of outliers in each set.
    """

    source: np.ndarray
    target: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    true_pairs: np.ndarray
    outlier_fraction: float

    def __post_init__(self):
        object.__setattr__(self, "source", _frozen(self.source))
        object.__setattr__(self, "target", _frozen(self.target))
        object.__setattr__(self, "rotation", _frozen(self.rotation))
        object.__setattr__(self, "translation", _frozen(self.translation))
        object.__setattr__(self, "true_pairs", _frozen(self.true_pairs, np.int64))
        object.__setattr__(self, "outlier_fraction", float(self.outlier_fraction))

    @property
    def n_inliers(self) -> int:
        return int(self.true_pairs.shape[0])

    @property
    def n_outliers(self) -> int:
        """Outliers added to each set."""
        return int(self.source.shape[0] - self.true_pairs.shape[0])

    @property
    def angle_deg(self) -> float:
        """True rotation angle in degrees."""
        return rotation_angle_deg(self.rotation)


def outlier_count(outlier_fraction: float, n_inliers: int) -> int:
    """Outliers per set so that they form the fraction ``f`` of it.

    ``round(n_inliers * f / (1 - f))``; e.g. 150 for ``f = 0.75`` and 50
    inliers.
    """
    f = _check_fraction(outlier_fraction)
    return int(round(n_inliers * f / (1.0 - f)))


def _check_fraction(value) -> float:
    try:
        f = float(value)
    except (TypeError, ValueError):
        msg = f"Expected `outlier_fraction` to be a number in [0, 1), got {value!r}."
        raise InputError(msg) from None
    if not (0.0 <= f < 1.0):
        msg = f"Expected `outlier_fraction` to be in [0, 1), got {value!r}."
        raise InputError(msg)
    return f


def _check_count(value, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        msg = f"Expected `{name}` to be an integer >= {minimum}, got {value!r}."
        raise InputError(msg)
    return int(value)


def random_rotation(rng: np.random.Generator, angle_range_deg: tuple[float, float]) -> np.ndarray:
    """Rotation about an axis uniform on the sphere, angle uniform in a range.

    Parameters
    ----------
    rng : numpy.random.Generator
    angle_range_deg : (float, float)
        Lower and upper bound of the angle, degrees.

    Returns
    -------
    (3, 3) ndarray
        Rodrigues' matrix of the drawn axis–angle (right-handed).
    """
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    theta = np.radians(rng.uniform(*angle_range_deg))
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(theta) * k + (1.0 - np.cos(theta)) * (k @ k)


def synthetic_trial(
    outlier_fraction: float,
    *,
    n_inliers: int = 50,
    angle_range_deg: tuple[float, float] = (0.0, 360.0),
    max_translation: float = 10.0,
    cube_size: float = 10.0,
    inliers=None,
    noise: float = 0.0,
    seed=None,
) -> Trial:
    """A trial of the paper's synthetic protocol with chosen motion ranges.

    Parameters
    ----------
    outlier_fraction : float
        Fraction ``f`` in [0, 1) of outliers in each set;
        ``round(n_inliers f / (1 − f))`` outliers are added to each set.
    n_inliers : int, default: 50
        Points in correspondence, uniform in the cube.
    angle_range_deg : (float, float), default: (0, 360)
        Range of the uniform rotation angle; the axis is uniform on the
        sphere.
    max_translation : float, default: 10
        Each translation component is uniform in
        ``[-max_translation, max_translation]``.
    cube_size : float, default: 10
        Edge of the cube, centred at the origin, holding the inliers.
    inliers : (K, 3) array_like, optional
        Use these points (e.g. a real mesh's vertices) as the source inliers
        instead of drawing ``n_inliers`` points in the cube; ``n_inliers``
        and ``cube_size`` are then ignored.
    noise : float, default: 0
        Isotropic Gaussian noise added to every inlier coordinate of both
        sets, its standard deviation given as a share of the inlier set's
        RMS radius (about its centroid; 5 for the 10-cube). Outliers stay
        uniform. ``0`` draws nothing, so a noise-free trial is the same as
        before this option existed.
    seed : int, numpy.random.Generator or SeedSequence
        Everything is drawn from ``numpy.random.default_rng(seed)``; the same
        seed gives the same trial.

    Returns
    -------
    Trial
    """
    f = _check_fraction(outlier_fraction)
    if inliers is not None:
        from ._validation import as_points

        given = as_points(inliers, "inliers", min_points=3)
        n_inliers = given.shape[0]
    n = _check_count(n_inliers, "n_inliers", 3)
    noise = check_nonnegative(noise, "noise", hint="a share of the inlier RMS radius")
    if seed is None:
        msg = "Pass `seed` (an int or a numpy Generator) so that the trial is reproducible."
        raise InputError(msg)
    rng = np.random.default_rng(seed)
    half = 0.5 * float(cube_size)
    n_out = outlier_count(f, n)

    rotation = random_rotation(rng, angle_range_deg)
    translation = rng.uniform(-max_translation, max_translation, size=3)
    if inliers is None:
        inliers = rng.uniform(-half, half, size=(n, 3))
    else:
        inliers = given
    moved = inliers @ rotation.T + translation

    def outliers(points):
        lo, hi = points.min(axis=0), points.max(axis=0)
        return rng.uniform(lo, hi, size=(n_out, 3))

    source = np.vstack([inliers, outliers(inliers)])
    target = np.vstack([moved, outliers(moved)])
    if noise > 0:
        centred = inliers - inliers.mean(axis=0)
        sd = noise * float(np.sqrt(np.mean(np.sum(centred**2, axis=1))))
        source[:n] += rng.normal(0.0, sd, size=(n, 3))
        target[:n] += rng.normal(0.0, sd, size=(n, 3))
    perm_s = rng.permutation(n + n_out)  # new position k holds old row perm_s[k]
    perm_t = rng.permutation(n + n_out)
    where_s = np.argsort(perm_s)  # old row i is now at where_s[i]
    where_t = np.argsort(perm_t)
    pairs = np.column_stack([where_s[:n], where_t[:n]])
    pairs = pairs[np.argsort(pairs[:, 0])]
    return Trial(
        source=source[perm_s],
        target=target[perm_t],
        rotation=rotation,
        translation=translation,
        true_pairs=pairs,
        outlier_fraction=f,
    )


def table2_trial(outlier_fraction: float, *, n_inliers: int = 50, noise: float = 0.0, seed=None) -> Trial:
    """A trial of the paper's Table 2 protocol (section 4).

    50 inliers uniform in a 10×10×10 cube centred at the origin; rotation
    angle uniform in 0..360° about an axis uniform on the sphere;
    translation uniform in [−10, 10]³; ``round(n_inliers f / (1 − f))``
    outliers added to each set, uniform in that set's inlier bounding box;
    both sets shuffled independently.

    Parameters
    ----------
    outlier_fraction : float
        ``f`` in [0, 1); the paper uses 0.75–0.93.
    n_inliers : int, default: 50
    noise : float, default: 0
        Gaussian noise on the inliers of both sets, as a share of the inlier
        RMS radius (see :func:`synthetic_trial`).
    seed : int or numpy.random.Generator
        Required; the trial is a pure function of it.

    Returns
    -------
    Trial

    Examples
    --------
    >>> from gatv.datasets import table2_trial
    >>> trial = table2_trial(0.75, seed=0)
    >>> trial.source.shape, trial.target.shape, trial.true_pairs.shape
    ((200, 3), (200, 3), (50, 2))
    """
    return synthetic_trial(
        outlier_fraction,
        n_inliers=n_inliers,
        angle_range_deg=(0.0, 360.0),
        max_translation=10.0,
        noise=noise,
        seed=seed,
    )


def table1_trial(outlier_fraction: float, *, n_inliers: int = 50, seed=None) -> Trial:
    """A trial of the paper's Table 1 (F-ICP) protocol (section 4).

    As :func:`table2_trial`, but the rotation angle is uniform in −5..5°
    (axis uniform on the sphere) and the translation uniform in
    [−1.5, 1.5]³, so that an ICP started at the identity has a fair chance.

    Examples
    --------
    >>> from gatv.datasets import table1_trial
    >>> trial = table1_trial(0.5, seed=0)
    >>> trial.n_outliers, trial.angle_deg <= 5
    (50, True)
    """
    return synthetic_trial(
        outlier_fraction,
        n_inliers=n_inliers,
        angle_range_deg=(-5.0, 5.0),
        max_translation=1.5,
        seed=seed,
    )


# --------------------------------------------------------------------- scoring
def _as_pairs(pairs, name: str) -> np.ndarray:
    arr = np.asarray(pairs)
    if arr.size == 0:
        return np.empty((0, 2), np.int64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        msg = f"Expected `{name}` to have shape (K, 2), got {arr.shape}."
        raise InputError(msg)
    if arr.dtype.kind not in "iu":
        if arr.dtype.kind != "f" or not np.all(arr == np.round(arr)):
            msg = f"Expected `{name}` to hold integer indices, got dtype {arr.dtype}."
            raise InputError(msg)
    return arr.astype(np.int64)


def correspondence_stats(found_pairs, true_pairs) -> tuple[float, float]:
    """Precision and recall of found correspondences.

    Parameters
    ----------
    found_pairs, true_pairs : (K, 2) array_like of int
        ``(source index, target index)`` rows; duplicates count once.

    Returns
    -------
    precision : float
        Correct found pairs / distinct found pairs; 0.0 when nothing was
        found.
    recall : float
        Correct found pairs / distinct true pairs; 1.0 when there are no true
        pairs.

    Examples
    --------
    >>> from gatv.datasets import correspondence_stats
    >>> correspondence_stats([[0, 1], [1, 2], [5, 5]], [[0, 1], [1, 2], [2, 3], [3, 4]])
    (0.6666666666666666, 0.5)
    """
    found = {tuple(r) for r in _as_pairs(found_pairs, "found_pairs").tolist()}
    true = {tuple(r) for r in _as_pairs(true_pairs, "true_pairs").tolist()}
    hits = len(found & true)
    precision = hits / len(found) if found else 0.0
    recall = hits / len(true) if true else 1.0
    return precision, recall


def paper_success(found_pairs, true_pairs, *, threshold: float = 0.5) -> bool:
    """The paper's success criterion: at least half the true pairs are found.

    Section 4: "An experiment is deemed a success if at least 50% of the
    correspondences are correctly identified". Because a method could find
    every true pair by listing all pairs, ``found_pairs`` must be one-to-one
    (no source or target index twice), as :class:`gatv.RigidMotion`
    correspondences are.

    Parameters
    ----------
    found_pairs, true_pairs : (K, 2) array_like of int
    threshold : float, default: 0.5
        Minimum recall.

    Raises
    ------
    ValueError
        If ``found_pairs`` is not one-to-one.
    """
    found = np.unique(_as_pairs(found_pairs, "found_pairs"), axis=0)
    if len(np.unique(found[:, 0])) != len(found) or len(np.unique(found[:, 1])) != len(found):
        msg = "Expected `found_pairs` to be one-to-one (each source and target index at most once)."
        raise InputError(msg)
    return correspondence_stats(found, true_pairs)[1] >= threshold


def rotation_error_deg(R_est, R_true) -> float:
    """Angle in degrees of the rotation ``R_est @ R_true.T``."""
    a = np.asarray(R_est, dtype=np.float64)
    b = np.asarray(R_true, dtype=np.float64)
    if a.shape != (3, 3) or b.shape != (3, 3):
        msg = f"Expected `R_est` and `R_true` of shape (3, 3), got {a.shape} and {b.shape}."
        raise InputError(msg)
    return rotation_angle_deg(a @ b.T)


def translation_error(t_est, t_true) -> float:
    """Euclidean distance between two translations."""
    a = np.asarray(t_est, dtype=np.float64).reshape(-1)
    b = np.asarray(t_true, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or b.shape != (3,):
        msg = f"Expected `t_est` and `t_true` with 3 entries, got {a.shape} and {b.shape}."
        raise InputError(msg)
    return float(np.linalg.norm(a - b))


# ------------------------------------------------------------------- real data
class DataNotFoundError(FileNotFoundError):
    """The optional real data set is not where it was looked for."""


#: Environment variable naming the data folder (the one holding
#: ``stanford_bunny_scans/``).
DATA_ENV = "GATV_DATA_DIR"


def find_data_dir(data_dir=None) -> Path:
    """Locate the real-data folder (the one holding ``stanford_bunny_scans``).

    Looks at ``data_dir``, then the ``GATV_DATA_DIR`` environment variable,
    then ``../shared/data`` beside a source checkout of gatv.

    Raises
    ------
    DataNotFoundError
        When none of them exists.
    """
    candidates = []
    if data_dir is not None:
        candidates.append(Path(data_dir))
    else:
        if os.environ.get(DATA_ENV):
            candidates.append(Path(os.environ[DATA_ENV]))
        candidates.append(Path(__file__).resolve().parents[2] / "shared" / "data")
    for c in candidates:
        if c.is_dir():
            return c
    msg = (
        f"Real data folder not found (looked in {', '.join(map(str, candidates))}). "
        f"Pass `data_dir=` or set the {DATA_ENV} environment variable."
    )
    raise DataNotFoundError(msg)


def _read_matrices(path: Path) -> dict[str, np.ndarray]:
    """Parse ``name``/``pair ...`` header lines each followed by 4 rows."""
    out: dict[str, np.ndarray] = {}
    lines = [ln.strip() for ln in path.read_text().splitlines()]
    lines = [ln for ln in lines if ln and not ln.startswith("#")]
    i = 0
    while i < len(lines):
        head = lines[i]
        if head.startswith("pair"):
            fields = dict(tok.split("=", 1) for tok in head.split()[1:] if "=" in tok)
            key = f"{fields['target']}<-{fields['source']}"
        else:
            key = head.split()[0]
        rows = [[float(v) for v in lines[i + k].split()] for k in range(1, 5)]
        out[key] = np.array(rows)
        i += 5
    return out


def _scan_name(name: str) -> str:
    stem = Path(str(name)).name
    return stem[:-4] if stem.lower().endswith(".ply") else stem


def load_bunny_pair(target_name: str, source_name: str, data_dir=None):
    """Two Stanford bunny range scans and the true motion between them.

    Parameters
    ----------
    target_name, source_name : str
        Scan names, ``"bun000"``, ``"bun045"``, ``"bun090"`` or ``"bun315"``
        (with or without ``.ply``).
    data_dir : path-like, optional
        Folder holding ``stanford_bunny_scans/`` (or that folder itself);
        default: see :func:`find_data_dir`.

    Returns
    -------
    target, source : (N, 3), (M, 3) ndarray of float
        Scan points, metres.
    rotation : (3, 3) ndarray
    translation : (3,) ndarray
        ``p_target = rotation @ p_source + translation``, taken from
        ``gt_pairs.txt`` when it lists the pair, otherwise composed from
        ``gt_world_from_scan.txt`` (``T_target^-1 T_source``).

    Raises
    ------
    DataNotFoundError
        (a :class:`FileNotFoundError`) when the data or a scan is absent.
    """
    from .io import read_points

    root = find_data_dir(data_dir)
    folder = root if (root / "gt_world_from_scan.txt").exists() else root / "stanford_bunny_scans"
    if not folder.is_dir():
        msg = f"No stanford_bunny_scans folder in {root}."
        raise DataNotFoundError(msg)
    tname, sname = _scan_name(target_name), _scan_name(source_name)
    files = {}
    for name in (tname, sname):
        f = folder / f"{name}.ply"
        if not f.exists():
            have = sorted(p.stem for p in folder.glob("*.ply"))
            msg = f"No scan {name!r} in {folder} (available: {', '.join(have)})."
            raise DataNotFoundError(msg)
        files[name] = f
    pairs_file, world_file = folder / "gt_pairs.txt", folder / "gt_world_from_scan.txt"
    T = None
    if pairs_file.exists():
        T = _read_matrices(pairs_file).get(f"{tname}<-{sname}")
    if T is None and world_file.exists():
        world = _read_matrices(world_file)
        if tname in world and sname in world:
            T = np.linalg.inv(world[tname]) @ world[sname]
    if T is None:
        msg = f"No ground truth for {tname} <- {sname} in {folder}."
        raise DataNotFoundError(msg)
    R, t = T[:3, :3].copy(), T[:3, 3].copy()
    return read_points(files[tname]), read_points(files[sname]), R, t


#: Objects of the UWA views in ``uwa_views_bcpd/``.
UWA_OBJECTS = ("chef", "parasaurolophus")


def load_uwa_pair(name: str, data_dir=None):
    """Two real UWA range views of one object and their pseudo ground truth.

    Parameters
    ----------
    name : {"chef", "parasaurolophus"}
    data_dir : path-like, optional
        Folder holding ``uwa_views_bcpd/`` (or that folder itself); default:
        see :func:`find_data_dir`.

    Returns
    -------
    target, source : (N, 3), (M, 3) ndarray of float
        View 001 and view 002, millimetres.
    rotation : (3, 3) ndarray
    translation : (3,) ndarray
        ``p_view001 = rotation @ p_view002 + translation``: a *pseudo* ground
        truth (Open3D FPFH+RANSAC then ICP, about ±0.1° and ±0.3 mm; see the
        data's README), not the authors'.

    Raises
    ------
    DataNotFoundError
        When the data is absent.
    """
    if name not in UWA_OBJECTS:
        raise InputError(f"Expected `name` one of {UWA_OBJECTS}, got {name!r}.")
    root = find_data_dir(data_dir)
    folder = root if (root / f"{name}_view001.txt").exists() else root / "uwa_views_bcpd"
    files = [folder / f"{name}_view001.txt", folder / f"{name}_view002.txt",
             folder / f"{name}_pseudo_gt_view001_from_view002.txt"]
    missing = [str(f) for f in files if not f.exists()]
    if missing:
        raise DataNotFoundError(f"UWA view files missing: {', '.join(missing)}.")
    T = np.loadtxt(files[2], comments="#")
    target = np.loadtxt(files[0], dtype=np.float64)
    source = np.loadtxt(files[1], dtype=np.float64)
    return target, source, T[:3, :3].copy(), T[:3, 3].copy()


#: Meshes shipped inside the PyVista wheel (no download needed).
DEMO_MESHES = ("ant", "airplane", "nut")


def demo_mesh(name: str = "ant") -> np.ndarray:
    """Vertices of a small real mesh shipped inside the PyVista wheel.

    Parameters
    ----------
    name : {"ant", "airplane", "nut"}, default: "ant"
        ``ant`` has 486 vertices, ``nut`` 523, ``airplane`` 1335. The files
        are in ``pyvista/examples/`` and load without network access.

    Returns
    -------
    (N, 3) ndarray of float

    Examples
    --------
    >>> from gatv.datasets import demo_mesh
    >>> demo_mesh("ant").shape
    (486, 3)
    """
    if name not in DEMO_MESHES:
        msg = f"Expected `name` to be one of {DEMO_MESHES}, got {name!r}."
        raise InputError(msg)
    from pyvista import examples

    from .io import read_points

    path = Path(examples.__file__).parent / f"{name}.ply"
    if not path.exists():  # pragma: no cover - wheel layout changed
        msg = f"PyVista's example mesh {name}.ply is missing at {path}."
        raise DataNotFoundError(msg)
    return read_points(path)
