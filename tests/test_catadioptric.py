"""Catadioptric front end: unified camera, corner detector, synthetic views."""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage
from scipy.spatial import cKDTree

from catadioptric import (
    SyntheticViews,
    UnifiedCamera,
    detect_corners,
    read_image,
    refine_corners,
    synthetic_views,
)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
MEI = DATA / "omni_mei_paracatadioptric"
needs_mei = pytest.mark.skipif(not MEI.is_dir(), reason="shared data absent")

# The shared calibration (calibration_mei_opencv.json), written out so that
# the distortion tests run without the data.
MEI_D = (-0.05273775236489735, 0.003546808333255818, 0.0007321390967993269, -0.00028427891525375766)
MEI_K = (301.78613925744975, 301.90663680244717, 643.7630015801574, 520.5161512148587)


def _points_in_domain(rng, camera, n, margin=0.05):
    """Random points of many norms whose sphere z is ``margin`` inside the limit."""
    pts = rng.normal(size=(8 * n, 3))
    pts /= np.linalg.norm(pts, axis=1)[:, None]
    pts = pts[pts[:, 2] > camera.sphere_limit() + margin][:n]
    return pts * rng.uniform(0.01, 100.0, size=(len(pts), 1))


def _unit(x):
    return x / np.linalg.norm(x, axis=1)[:, None]


# --------------------------------------------------------------------------- #
# Camera model
# --------------------------------------------------------------------------- #
@settings(max_examples=60, deadline=None)
@given(xi=st.floats(0.0, 1.0), seed=st.integers(0, 2**32 - 1), skew=st.sampled_from([0.0, 0.7]))
def test_lift_inverts_project_without_distortion(xi, seed, skew):
    cam = UnifiedCamera(xi, *MEI_K[:2], *MEI_K[2:], skew=skew)
    pts = _points_in_domain(np.random.default_rng(seed), cam, 200)
    rays = cam.lift(cam.project(pts))
    np.testing.assert_allclose(rays, _unit(pts), rtol=0, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(xi=st.floats(0.0, 1.0), seed=st.integers(0, 2**32 - 1))
def test_lift_inverts_project_with_distortion(xi, seed):
    cam = UnifiedCamera(xi, *MEI_K[:2], *MEI_K[2:], distortion=MEI_D)
    pts = _points_in_domain(np.random.default_rng(seed), cam, 200, margin=0.1)
    pix, ok = cam.project(pts, return_mask=True)
    assert ok.all()
    # Asked: 1e-8; the Newton undistortion reaches round-off (measured 9e-16).
    np.testing.assert_allclose(cam.lift(pix), _unit(pts), rtol=0, atol=1e-12)


def test_round_trip_beyond_xi_one_with_distortion():
    cam = UnifiedCamera(1.0286039706677872, *MEI_K[:2], *MEI_K[2:], distortion=MEI_D)
    pts = _points_in_domain(np.random.default_rng(3), cam, 2000, margin=0.01)
    np.testing.assert_allclose(cam.lift(cam.project(pts)), _unit(pts), rtol=0, atol=1e-10)


def test_parabolic_lift_is_inverse_stereographic_projection():
    fx, fy, cx, cy = 250.0, 260.0, 320.0, 240.0
    cam = UnifiedCamera(1.0, fx, fy, cx, cy)
    pixels = np.array([[320.0, 240.0], [570.0, 240.0], [320.0, 500.0], [100.0, 30.0], [1000.0, -400.0]])
    # Stereographic projection from the south pole onto the plane z = 0:
    # (x, y) = (X, Y) / (1 + Z); its inverse is (2x, 2y, 1 - r^2) / (1 + r^2).
    x = (pixels[:, 0] - cx) / fx
    y = (pixels[:, 1] - cy) / fy
    r2 = x**2 + y**2
    expected = np.column_stack([2 * x, 2 * y, 1 - r2]) / (1 + r2)[:, None]
    np.testing.assert_allclose(cam.lift(pixels), expected, rtol=0, atol=1e-14)
    np.testing.assert_allclose(cam.lift(pixels[:3]), [[0, 0, 1], [1, 0, 0], [0, 1, 0]], atol=1e-15)
    np.testing.assert_allclose(cam.project(expected), pixels, rtol=0, atol=1e-10)


@needs_mei
@pytest.mark.parametrize("image", range(1, 11))
def test_shared_calibration_reproduces_sphere_points(image):
    cam = UnifiedCamera.from_json(MEI / "calibration_mei_opencv.json")
    px = np.loadtxt(MEI / "corners" / f"img_para_{image:03d}_corners_px.txt")
    sphere = np.loadtxt(MEI / "corners" / f"img_para_{image:03d}_corners_sphere.txt")
    # The pixel files keep 4 decimals (rounding up to 5e-5 px, i.e. ~2e-7 on
    # the sphere); the achieved agreement is 3e-7 on the sphere, 5.1e-5 px.
    np.testing.assert_allclose(cam.lift(px), sphere, rtol=0, atol=1e-6)
    np.testing.assert_allclose(cam.project(sphere), px, rtol=0, atol=1e-4)


@needs_mei
def test_projection_reproduces_opencv_reprojection_errors_mei():
    # Posed board corners projected with the calibration: the per-image mean
    # reprojection error must be the one OpenCV reported in each pose file.
    cam = UnifiedCamera.from_json(MEI / "calibration_mei_opencv.json")
    board = np.loadtxt(MEI / "board_points_m.txt")
    for image in range(1, 11):
        pose_file = MEI / "corners" / f"img_para_{image:03d}_board_pose_cam_from_board.txt"
        reported = float(pose_file.read_text().splitlines()[0].split("mean reprojection")[1].split()[0])
        T = np.loadtxt(pose_file)
        px = np.loadtxt(MEI / "corners" / f"img_para_{image:03d}_corners_px.txt")
        err = np.linalg.norm(cam.project(board @ T[:3, :3].T + T[:3, 3]) - px, axis=1)
        assert err.mean() == pytest.approx(reported, abs=6e-4)


@pytest.mark.skipif(not (DATA / "omni_opencv_ccalib_corners").is_dir(), reason="shared data absent")
def test_projection_reproduces_opencv_rms_ccalib():
    # Second real camera (strong tangential distortion, p1 = 0.023): our
    # projection gives cv2.omnidir.calibrate's RMS to 1e-12 px.
    import xml.etree.ElementTree as ET

    from scipy.spatial.transform import Rotation

    folder = DATA / "omni_opencv_ccalib_corners"
    root = ET.parse(folder / "omni_calib_data.xml").getroot()

    def matrices(tag, dim):
        return [np.array(e.find("data").text.split(), float).reshape(-1, dim) for e in root.find(tag)]

    obj, img = matrices("objectPoints", 3), matrices("imagePoints", 2)
    calib = json.loads((folder / "calibration_mei_opencv_derived.json").read_text())
    cam = UnifiedCamera.from_json(folder / "calibration_mei_opencv_derived.json")
    sq = []
    for k, view in enumerate(calib["views_used"]):
        R = Rotation.from_rotvec(calib["rvecs"][k]).as_matrix()
        proj = cam.project(obj[view] @ R.T + np.asarray(calib["tvecs"][k]))
        sq.append(np.sum((proj - img[view]) ** 2, axis=1))
    rms = np.sqrt(np.concatenate(sq).mean())
    assert rms == pytest.approx(calib["rms_reprojection_px"], abs=1e-9)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"xi": -0.1}, "`xi` >= 0"),
        ({"fx": 0.0}, "`fx`.*> 0"),
        ({"fy": -3.0}, "`fy`.*> 0"),
        ({"cx": float("nan")}, "`cx` to be finite"),
        ({"xi": float("inf")}, "`xi` to be finite"),
        ({"fx": "300"}, "`fx` to be a real number"),
        ({"distortion": (0.1, 0.0, 0.0)}, "`distortion` to have 4"),
        ({"distortion": (0.1, 0.0, np.nan, 0.0)}, "`distortion` to be finite"),
        ({"image_size": (640,)}, "`image_size`"),
    ],
)
def test_bad_camera_parameters(kwargs, match):
    params = {"xi": 1.0, "fx": 300.0, "fy": 300.0, "cx": 320.0, "cy": 240.0} | kwargs
    with pytest.raises(ValueError, match=match):
        UnifiedCamera(**params)


@pytest.mark.parametrize(
    ("pixels", "match"),
    [
        (np.zeros((4, 3)), r"`pixels` to have shape \(N, 2\), got \(4, 3\)"),
        (np.zeros(2), r"`pixels` to have shape \(N, 2\)"),
        ([[1.0, np.nan]], "`pixels` contains 1 NaN"),
        ([["a", "b"]], "`pixels` to be an"),
        (None, "`pixels`"),
    ],
)
def test_malformed_pixels(pixels, match):
    cam = UnifiedCamera(1.0, 300.0, 300.0, 320.0, 240.0)
    with pytest.raises(ValueError, match=match):
        cam.lift(pixels)


def test_malformed_points():
    cam = UnifiedCamera(1.0, 300.0, 300.0, 320.0, 240.0)
    with pytest.raises(ValueError, match=r"`points` to have shape \(N, 3\)"):
        cam.project(np.zeros((5, 2)))


def test_invalid_pixels_and_points_policy():
    # xi > 1: pixels beyond the disc 1 + (1 - xi^2) r^2 >= 0 cannot be lifted.
    cam = UnifiedCamera(2.0, 100.0, 100.0, 0.0, 0.0)
    r_lim = 1.0 / np.sqrt(3.0)  # normalised radius of the disc's rim
    pixels = np.array([[0.0, 0.0], [100 * 0.99 * r_lim, 0.0], [100 * 1.01 * r_lim, 0.0], [0.0, -500.0]])
    with pytest.raises(ValueError, match="2 of 4 rows of `pixels` cannot be lifted"):
        cam.lift(pixels)
    rays, ok = cam.lift(pixels, return_mask=True)
    np.testing.assert_array_equal(ok, [True, True, False, False])
    assert np.all(np.isnan(rays[~ok])) and np.allclose(np.linalg.norm(rays[ok], axis=1), 1)
    # Sphere z must exceed -min(xi, 1/xi) = -0.5; the zero vector never projects.
    pts = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, -0.4], [1.0, 0.0, -0.7], [0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="2 of 4 rows of `points` cannot be projected"):
        cam.project(pts)
    pix, ok = cam.project(pts, return_mask=True)
    np.testing.assert_array_equal(ok, [True, True, False, False])
    assert np.all(np.isnan(pix[~ok])) and np.all(np.isfinite(pix[ok]))
    # Pinhole: points behind the camera are invalid.
    _, ok = UnifiedCamera(0.0, 100.0, 100.0, 0.0, 0.0).project([[0, 0, -1.0]], return_mask=True)
    assert not ok[0]


def test_strong_distortion_fold_is_invalid():
    # k1 = -0.3: r (1 + k1 r^2) peaks at r^2 = 1/0.9; beyond it the
    # distortion folds back and neither projection nor lifting is defined.
    cam = UnifiedCamera(1.0, 100.0, 100.0, 0.0, 0.0, distortion=(-0.3, 0.0, 0.01, 0.0))
    pts = np.random.default_rng(0).normal(size=(5000, 3))
    pix, ok = cam.project(pts, return_mask=True)
    assert 0.3 < ok.mean() < 0.7
    rays, lifted = cam.lift(pix[ok], return_mask=True)
    assert lifted.all()
    np.testing.assert_allclose(rays, _unit(pts[ok]), rtol=0, atol=1e-10)
    r_d_max = 100.0 * np.sqrt(1 / 0.9) * (1 - 0.3 / 0.9)  # largest distorted radius, px
    _, ok = cam.lift([[0.9 * r_d_max, 0.0], [1.1 * r_d_max, 0.0], [0.0, -1.2 * r_d_max]], return_mask=True)
    np.testing.assert_array_equal(ok, [True, False, False])


def test_empty_inputs():
    cam = UnifiedCamera(1.0, 300.0, 300.0, 320.0, 240.0, distortion=MEI_D)
    assert cam.project(np.empty((0, 3))).shape == (0, 2)
    assert cam.lift(np.empty((0, 2))).shape == (0, 3)


def test_json_round_trip(tmp_path):
    cam = UnifiedCamera(0.9, 301.5, 302.5, 640.0, 512.0, skew=0.25, distortion=MEI_D, image_size=(1280, 1024))
    path = tmp_path / "cam.json"
    cam.to_json(path)
    back = UnifiedCamera.from_json(path)
    assert back == cam
    assert back.distortion == MEI_D and back.image_size == (1280, 1024)
    assert [p.name for p in tmp_path.iterdir()] == ["cam.json"]  # no temp file left
    # Overwriting replaces the file whole.
    UnifiedCamera(1.0, 1.0, 1.0, 0.0, 0.0).to_json(path)
    assert json.loads(path.read_text())["distortion"] == [0.0, 0.0, 0.0, 0.0]


def test_opencv_layout_and_bad_json(tmp_path):
    K = [[300.0, 0.5, 640.0], [0.0, 310.0, 500.0], [0.0, 0.0, 1.0]]
    path = tmp_path / "cv.json"
    path.write_text(json.dumps({"K": K, "xi": [[1.02]], "D": [[0.01, 0.002, 0.0, 0.0]]}))
    cam = UnifiedCamera.from_opencv_json(path)
    assert (cam.xi, cam.fx, cam.fy, cam.cx, cam.cy, cam.skew) == (1.02, 300.0, 310.0, 640.0, 500.0, 0.5)
    np.testing.assert_array_equal(cam.K, K)
    path.write_text(json.dumps({"fx": 1.0}))
    with pytest.raises(ValueError, match="lack the key 'xi'"):
        UnifiedCamera.from_json(path)
    path.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        UnifiedCamera.from_json(path)


@needs_mei
def test_shared_calibration_is_read():
    cam = UnifiedCamera.from_json(MEI / "calibration_mei_opencv.json")
    assert cam.xi == pytest.approx(1.0286039706677872)
    assert cam.distortion == MEI_D and cam.image_size == (1280, 1024)


def test_yaml_needs_pyyaml(tmp_path):
    path = tmp_path / "cam.yaml"
    path.write_text(
        "%YAML:1.0\n---\nxi: !!opencv-matrix\n   rows: 1\n   cols: 1\n   dt: d\n   data: [ 1.05 ]\n"
        "K: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        "   data: [ 400., 0., 630., 0., 401., 430., 0., 0., 1. ]\n"
        "D: !!opencv-matrix\n   rows: 1\n   cols: 4\n   dt: d\n   data: [ 0.01, 0.02, 0.0, 0.0 ]\n"
    )
    try:
        import yaml  # noqa: F401
    except ImportError:
        with pytest.raises(ImportError, match="pip install pyyaml"):
            UnifiedCamera.from_file(path)
    else:
        cam = UnifiedCamera.from_file(path)
        assert (cam.xi, cam.fx, cam.cy, cam.distortion[1]) == (1.05, 400.0, 430.0, 0.02)


# --------------------------------------------------------------------------- #
# Synthetic views
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("xi", [0.0, 0.6, 1.0])
def test_synthetic_views_ground_truth(xi):
    views = synthetic_views(300, xi=xi, noise_px=0.5, outlier_fraction=0.25, rotation_deg=20.0, seed=7)
    assert isinstance(views, SyntheticViews)
    R, t = views.rotation, views.translation
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.degrees(np.arccos((np.trace(R) - 1) / 2)) == pytest.approx(20.0)
    for pixels, ids, cam, pts in (
        (views.pixels1, views.ids1, views.camera1, views.points),
        (views.pixels2, views.ids2, views.camera2, views.points @ R.T + t),
    ):
        inl = ids >= 0
        err = cam.project(pts[ids[inl]]) - pixels[inl]
        assert np.abs(err).max() < 6 * 0.5  # up to the noise
        assert 0.5 * 0.8 < err.std() < 0.5 * 1.2
        assert abs(np.mean(~inl) - 0.25) < 0.02
        assert not np.all(np.diff(ids[inl]) > 0)  # shuffled
        w, h = cam.image_size
        assert np.all((pixels >= -0.5) & (pixels <= [w - 0.5, h - 0.5]))
        cam.lift(pixels)  # every row lifts
    i, j = views.pairs.T
    np.testing.assert_array_equal(views.ids1[i], views.ids2[j])
    assert len(views.pairs) > 150
    # Every point seen in both views is paired.
    both = np.intersect1d(views.ids1[views.ids1 >= 0], views.ids2[views.ids2 >= 0])
    assert len(both) == len(views.pairs)
    depth = np.linalg.norm(views.points, axis=1)
    assert depth.min() > 1.4 and depth.max() < 6.0
    with pytest.raises(ValueError, match="read-only"):
        views.pixels1[0, 0] = 0.0


def test_synthetic_views_noise_free_rays_match_motion():
    cam = UnifiedCamera(1.0286, *MEI_K[:2], *MEI_K[2:], distortion=MEI_D, image_size=(1280, 1024))
    views = synthetic_views(100, camera=cam, noise_px=0.0, axis=(0, 0, 1), rotation_deg=-30, seed=2)
    rays1, rays2 = views.rays()
    i, j = views.pairs.T
    X1 = views.points[views.ids1[i]]
    np.testing.assert_allclose(rays1[i], _unit(X1), atol=1e-10)
    np.testing.assert_allclose(rays2[j], _unit(X1 @ views.rotation.T + views.translation), atol=1e-10)
    # Same seed, same scene.
    again = synthetic_views(100, camera=cam, noise_px=0.0, axis=(0, 0, 1), rotation_deg=-30, seed=2)
    np.testing.assert_array_equal(again.pixels2, views.pixels2)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"n_points": 0}, "`n_points`"),
        ({"outlier_fraction": 1.0}, "`outlier_fraction`"),
        ({"noise_px": -1.0}, "`noise_px`"),
        ({"translation": (1.0, 2.0)}, "`translation`"),
        ({"translation": (10.0, 0.0, 0.0)}, "outside the room"),
        ({"axis": (0.0, 0.0, 0.0)}, "`axis`"),
        ({"xi": -1.0}, "`xi`"),
        ({"camera": "cam"}, "`camera`"),
    ],
)
def test_synthetic_views_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        synthetic_views(**kwargs)


# --------------------------------------------------------------------------- #
# Corner detector
# --------------------------------------------------------------------------- #
def _checkerboard(h=120, w=160, square=14.0, angle=0.35, origin=(80.3, 60.7), supersample=8, blur=0.8):
    """Anti-aliased rotated checkerboard and its inner corners (u, v)."""
    o = (np.arange(supersample) + 0.5) / supersample - 0.5
    v, u = np.mgrid[0:h, 0:w].astype(float)
    uu = u[..., None, None] + o[None, None, :, None]
    vv = v[..., None, None] + o[None, None, None, :]
    c, s = np.cos(angle), np.sin(angle)
    a = (c * (uu - origin[0]) + s * (vv - origin[1])) / square
    b = (-s * (uu - origin[0]) + c * (vv - origin[1])) / square
    img = 30.0 + 200.0 * ((np.floor(a) + np.floor(b)) % 2).mean(axis=(2, 3))
    img = ndimage.gaussian_filter(img, blur)
    k = np.arange(-20, 21)
    A, B = np.meshgrid(k, k)
    corners = np.column_stack(
        [(origin[0] + square * (c * A - s * B)).ravel(), (origin[1] + square * (s * A + c * B)).ravel()]
    )
    inside = np.all((corners > 12) & (corners < [w - 13, h - 13]), axis=1)
    return img, corners[inside]


def test_detector_subpixel_on_synthetic_board():
    img, truth = _checkerboard()
    found = detect_corners(img, max_corners=200)
    dist, _ = cKDTree(found).query(truth)
    # Measured: max 0.040 px, RMS 0.025 px.
    assert dist.max() < 0.2, dist.max()
    noisy = img + np.random.default_rng(0).normal(0.0, 2.0, img.shape)
    dist, _ = cKDTree(detect_corners(noisy, max_corners=200)).query(truth)
    assert dist.max() < 0.2, dist.max()


def test_refine_corners_converges_from_a_few_pixels_off():
    img, truth = _checkerboard()
    start = truth + np.random.default_rng(1).uniform(-2.5, 2.5, truth.shape)
    refined = refine_corners(img, start)
    assert np.abs(refined - truth).max() < 0.2


def test_detector_options_and_errors():
    img, truth = _checkerboard()
    roi = (40.0, 30.0, 120.0, 90.0)
    found = detect_corners(img, roi=roi, method="harris")
    assert np.all((found >= [39.0, 29.0]) & (found <= [121.0, 91.0]))
    assert len(detect_corners(img, max_corners=5)) == 5
    mask = np.zeros(img.shape, dtype=bool)
    assert detect_corners(img, mask=mask).shape == (0, 2)
    raw = detect_corners(img, subpixel=False)
    assert np.all(raw == np.rint(raw))
    for kwargs, match in [
        ({"max_corners": 0}, "`max_corners`"),
        ({"quality": 2.0}, "`quality`"),
        ({"sigma": 0.0}, "`sigma`"),
        ({"method": "fast"}, "`method`"),
        ({"mask": np.ones((3, 3), bool)}, "`mask`"),
        ({"roi": (5, 5, 1, 1)}, "`roi`"),
    ]:
        with pytest.raises(ValueError, match=match):
            detect_corners(img, **kwargs)
    with pytest.raises(ValueError, match="`image` to have shape"):
        detect_corners(np.zeros((4, 4, 4, 4)))
    with pytest.raises(ValueError, match="does not exist"):
        detect_corners("/nonexistent/image.png")


def _write_png(path, img):
    """Minimal 8-bit grey PNG writer (independent of VTK)."""
    h, w = img.shape
    raw = b"".join(b"\x00" + img[r].astype(np.uint8).tobytes() for r in range(h))

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def test_read_image_png_and_pgm_orientation(tmp_path):
    img = (np.arange(6 * 9).reshape(6, 9) * 4).astype(np.uint8)  # row 0 on top
    _write_png(tmp_path / "a.png", img)
    np.testing.assert_array_equal(read_image(tmp_path / "a.png"), img)
    (tmp_path / "a.pgm").write_bytes(b"P5\n# comment\n9 6\n255\n" + img.tobytes())
    np.testing.assert_array_equal(read_image(str(tmp_path / "a.pgm")), img)
    (tmp_path / "b.pgm").write_text("P2 2 2 65535\n0 1000\n65535 7\n")
    np.testing.assert_array_equal(read_image(tmp_path / "b.pgm"), [[0, 1000], [65535, 7]])
    rgb = np.stack([img, img, img], axis=-1)
    np.testing.assert_allclose(read_image(rgb), img, atol=1e-9)


@needs_mei
def test_detector_recall_on_real_paracatadioptric_image():
    truth = np.loadtxt(MEI / "corners" / "img_para_001_corners_px.txt")
    img = read_image(MEI / "images" / "img_para_001.png")
    assert img.shape == (1024, 1280)
    # Whole image, the 100 strongest corners (the corridor has many more).
    found = detect_corners(img, max_corners=100)
    dist, _ = cKDTree(found).query(truth)
    # Measured: 48/48 within 1.5 px, median 0.042 px, max 0.088 px from
    # OpenCV's findChessboardCorners + cornerSubPix.
    assert np.mean(dist < 1.5) >= 0.95
    assert np.median(dist) < 0.1
    # Region of interest around the board, 60 corners.
    lo, hi = truth.min(0) - 15, truth.max(0) + 15
    found = detect_corners(MEI / "images" / "img_para_001.png", max_corners=60, roi=(*lo, *hi))
    dist, _ = cKDTree(found).query(truth)
    assert np.mean(dist < 1.5) >= 0.95
