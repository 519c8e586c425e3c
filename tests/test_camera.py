"""Camera: intrinsics validation, projection, undistortion lookup table."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from cmax import Events
from cmax.camera import Camera


def test_undistort_events_matches_opencv():
    """Each event to its undistorted pixel (nearest integer), those landing outside dropped: as
    ``cv2.undistortPoints(..., P=K)`` rounds them (what ``cmax fit --calib`` does to the events)."""
    rng = np.random.default_rng(0)
    K = np.array([[200.0, 0, 120], [0, 200.0, 90], [0, 0, 1]])
    distortion = np.array([-0.3, 0.1, 0.001, -0.002])
    x, y = rng.integers(0, 240, 500), rng.integers(0, 180, 500)
    events = Events(x, y, np.arange(500), rng.integers(0, 2, 500), 240, 180)
    out = Camera(K, 240, 180, distortion).undistort_events(events)
    expected = cv2.undistortPoints(np.column_stack([x, y]).astype(np.float64).reshape(-1, 1, 2), K, distortion,
                                   P=K, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-9))
    expected = np.rint(expected.reshape(-1, 2))
    inside = (expected[:, 0] >= 0) & (expected[:, 0] < 240) & (expected[:, 1] >= 0) & (expected[:, 1] < 180)
    np.testing.assert_array_equal(out.x, expected[inside, 0])
    np.testing.assert_array_equal(out.y, expected[inside, 1])
    np.testing.assert_array_equal(out.t, events.t[inside])
    assert 0 < len(out) <= 500 and np.abs(out.x.astype(int) - x[inside]).max() > 1   # it did move them


def test_project_backproject_round_trip():
    cam = Camera.from_intrinsics(200.0, 210.0, 120.0, 90.0, 240, 180)
    points = np.array([[0.1, -0.2, 2.0], [1.0, 0.5, 4.0], [0.0, 0.0, 1.0]])
    pixels = cam.project(points)
    np.testing.assert_allclose(pixels[2], [120.0, 90.0])
    np.testing.assert_allclose(pixels[0], [120 + 200 * 0.05, 90 - 210 * 0.1])
    np.testing.assert_allclose(cam.backproject(pixels, points[:, 2]), points, atol=1e-12)


def test_an_ecd_calib_txt_with_a_byte_order_mark_is_the_same_camera(tmp_path):
    """Camera.from_ecd_calib of a calib.txt saved with a UTF-8 byte order mark and CRLF (a Windows editor) is the
    camera of the plain file, as cmax.io.read_calibration reads both (was: ValueError, could not convert string
    '\ufeff199.09...' to float64)."""
    line = "199.092366542 198.82882047 132.192071378 110.712660011 -0.368436311798 0.150947243557 " \
           "-0.000296130534385 -0.000759431726241 0.0"
    (tmp_path / "plain.txt").write_text(line + "\n")
    (tmp_path / "bom.txt").write_bytes(b"\xef\xbb\xbf" + line.encode() + b"\r\n")
    plain, marked = Camera.from_ecd_calib(tmp_path / "plain.txt"), Camera.from_ecd_calib(tmp_path / "bom.txt")
    np.testing.assert_array_equal(marked.K, plain.K)
    np.testing.assert_array_equal(marked.distortion, plain.distortion)
    np.testing.assert_array_equal(marked.K[[0, 1, 0, 1], [0, 1, 2, 2]], [float(v) for v in line.split()[:4]])


def test_from_ecd_calib_and_read_calibration_are_one_reader(tmp_path):
    """Camera.from_ecd_calib is cmax.io.read_calibration's camera: the same K and distortion for an ECD line, and the
    same refusal for the numbers of one line split over two (was: from_ecd_calib read any layout with np.loadtxt,
    read_calibration refused it, so the two readers disagreed on one file)."""
    from cmax.io import read_calibration

    line = "199.09 198.83 132.19 110.71 -0.368 0.151 -0.0003 -0.0008 0.0"
    one = tmp_path / "calib.txt"
    one.write_text(line + "  # ECD DAVIS240C\n")
    camera = Camera.from_ecd_calib(one)
    np.testing.assert_array_equal(camera.K, [[199.09, 0, 132.19], [0, 198.83, 110.71], [0, 0, 1]])
    np.testing.assert_array_equal(camera.distortion, [-0.368, 0.151, -0.0003, -0.0008, 0.0])
    assert (camera.width, camera.height) == (240, 180)
    np.testing.assert_array_equal(camera.K, read_calibration(one).K)
    split = tmp_path / "split.txt"
    split.write_text(" ".join(line.split()[:4]) + "\n" + " ".join(line.split()[4:]) + "\n")
    with pytest.raises(ValueError) as refused:
        read_calibration(split)
    with pytest.raises(ValueError, match="expected one line") as also:
        Camera.from_ecd_calib(split)
    assert str(also.value) == str(refused.value)


def test_undistort_inverts_opencv_distortion(shared_data):
    cam = Camera.from_ecd_calib(shared_data / "ecd_slider_depth" / "calib.txt")
    assert cam.is_distorted and (cam.width, cam.height) == (240, 180)
    rng = np.random.default_rng(0)
    ev = Events(rng.integers(0, 240, 500), rng.integers(0, 180, 500), np.arange(500), rng.integers(0, 2, 500), 240, 180)
    undistorted = cam.undistort(ev)
    assert undistorted.shape == (500, 2) and undistorted.dtype == np.float32
    # Re-distort with OpenCV's forward model: must land on the original integer pixels.
    normalized = np.column_stack([(undistorted[:, 0] - cam.cx) / cam.fx, (undistorted[:, 1] - cam.cy) / cam.fy, np.ones(500)])
    redistorted, _ = cv2.projectPoints(normalized, np.zeros(3), np.zeros(3), cam.K, cam.distortion)
    np.testing.assert_allclose(redistorted.reshape(-1, 2), np.column_stack([ev.x, ev.y]), atol=2e-3)


def test_undistort_keeps_the_skew_of_K():
    """pixel = K [distort(x_n); 1] with a skewed K: undistortion gives K [x_n; 1] back (OpenCV, handed K
    itself, drops K[0, 1]: it was 4.4 px off here)."""
    K = np.array([[300.0, 12.0, 160.0], [0.0, 290.0, 120.0], [0.0, 0.0, 1.0]])
    distortion = np.array([-0.2, 0.05, 0.001, -0.002, 0.0])
    cam = Camera(K, 320, 240, distortion)
    rng = np.random.default_rng(3)
    normalized = np.column_stack([rng.uniform(-0.45, 0.45, 200), rng.uniform(-0.35, 0.35, 200), np.ones(200)])
    distorted, _ = cv2.projectPoints(normalized, np.zeros(3), np.zeros(3), np.eye(3), distortion)  # K = I: no skew
    pixels = (np.column_stack([distorted.reshape(-1, 2), np.ones(200)]) @ K.T)[:, :2]
    expected = (normalized @ K.T)[:, :2]
    np.testing.assert_allclose(cam.undistort_points(pixels), expected, atol=1e-6)


def test_undistort_without_distortion_is_identity():
    cam = Camera.from_intrinsics(100, 100, 16, 12, 32, 24, distortion=[0, 0, 0, 0, 0])
    assert not cam.is_distorted
    ev = Events([0, 31], [0, 23], [1, 2], [0, 1], 32, 24)
    np.testing.assert_array_equal(cam.undistort(ev), [[0, 0], [31, 23]])


@pytest.mark.parametrize("K, match", [
    (np.eye(2), "3x3"),
    ([[100, 0, 10], [0, np.nan, 10], [0, 0, 1]], "finite"),
    ([[0, 0, 10], [0, 100, 10], [0, 0, 1]], "positive focal"),
    ([[100, 0, 10], [0, 100, 10], [1, 0, 1]], "form"),
])
def test_bad_intrinsics(K, match):
    with pytest.raises(ValueError, match=match):
        Camera(K, 32, 24)


def test_bad_distortion_and_sensor():
    K = np.diag([100.0, 100.0, 1.0])
    with pytest.raises(ValueError, match="coefficients"):
        Camera(K, 32, 24, np.zeros(3))
    with pytest.raises(ValueError, match="finite"):
        Camera(K, 32, 24, [np.inf, 0, 0, 0])
    cam = Camera(K, 32, 24, [0.1, 0, 0, 0])
    with pytest.raises(ValueError, match="sensor"):
        cam.undistort(Events([0], [0], [0], [1], 16, 12))


def test_scaled_camera_projects_consistently():
    cam = Camera.from_intrinsics(200.0, 200.0, 119.5, 89.5, 240, 180)
    half = cam.scaled(120, 90)
    point = np.array([[0.3, 0.2, 2.0]])
    # Pixel centres map as x' + 0.5 = (x + 0.5) / 2.
    np.testing.assert_allclose(half.project(point) + 0.5, (cam.project(point) + 0.5) / 2)


def _redistorted(cam: Camera, undistorted: np.ndarray) -> np.ndarray:
    """OpenCV's forward model (``cv2.projectPoints``) applied to undistorted pixels (N, 2): the pixels they come from."""
    normalised = np.column_stack([undistorted, np.ones(len(undistorted))]) @ np.linalg.inv(cam.K).T
    distorted, _ = cv2.projectPoints(normalised, np.zeros(3), np.zeros(3), cam.K, cam.distortion)
    return distorted.reshape(-1, 2)


def test_strong_distortion_is_undistorted_to_pixels_that_distort_back():
    """k1 = -0.9, k2 = 0.4: an invertible (monotonic) radial model on which OpenCV's fixed-point iteration
    converges slowly: 40 iterations left 977 of the 240x180 pixels more than 0.01 px off, up to 2.5 px (the
    events placed there without a word); every pixel now distorts back onto itself."""
    cam = Camera(np.array([[200.0, 0, 120], [0, 200, 90], [0, 0, 1]]), 240, 180, [-0.9, 0.4, 0.0, 0.0])
    ys, xs = np.mgrid[0:180, 0:240]
    pixels = np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float64)
    undistorted = cam.undistort_points(pixels)
    assert np.isfinite(undistorted).all()
    assert np.linalg.norm(_redistorted(cam, undistorted) - pixels, axis=1).max() < 0.02


def test_pixels_beyond_the_reach_of_the_distortion_have_no_undistorted_position():
    """k1 = -0.5, k2 = 0.3, k3 = -0.1: the distorted radius peaks at 0.727 (at r = 1.157), the image's corners
    lie at 0.75: no point distorts onto them. They were given positions 6-8 px off; now NaN, and their events
    are dropped by undistort_events and kept out of EMVS (undistort gives NaN)."""
    distortion = [-0.5, 0.3, 0.0, 0.0, -0.1]
    cam = Camera(np.array([[200.0, 0, 120], [0, 200, 90], [0, 0, 1]]), 240, 180, distortion)
    ys, xs = np.mgrid[0:180, 0:240]
    pixels = np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float64)
    undistorted = cam.undistort_points(pixels)
    solved = np.isfinite(undistorted).all(axis=1)
    radius = np.linalg.norm((pixels - [120, 90]) / 200.0, axis=1)
    assert not solved[radius > 0.7275].any()              # beyond the model's largest distorted radius
    assert solved[radius < 0.70].all()
    assert np.linalg.norm(_redistorted(cam, undistorted[solved]) - pixels[solved], axis=1).max() < 0.02
    corner = Events([0, 120], [0, 90], [0, 1], [1, 1], 240, 180)
    assert np.isnan(cam.undistort(corner)[0]).all() and np.isfinite(cam.undistort(corner)[1]).all()
    kept = cam.undistort_events(corner)
    assert len(kept) == 1 and (kept.x[0], kept.y[0]) == (120, 90)


# The left DAVIS of MVSEC's indoor_flying camchain (camchain-imucam-indoor_flying.yaml, cam0), as published
# by several public MVSEC loaders: Kalibr's equidistant (Kannala-Brandt) model, its rectification and projection.
MVSEC_K = np.array([[226.38018519795807, 0.0, 173.6470807871759], [0.0, 226.15002947047415, 133.73271487507847],
                    [0.0, 0.0, 1.0]])
MVSEC_D = np.array([-0.048031442223833355, 0.011330957517194437, -0.055378166304281135, 0.021500973881459395])
MVSEC_R = np.array([[0.999877311526236, 0.015019439766575743, -0.004447282784398257],
                    [-0.014996983873604017, 0.9998748347535599, 0.005040367172759556],
                    [0.004522429630305261, -0.004973052949604937, 0.9999774079320989]])
MVSEC_P = np.array([[199.6530123165822, 0.0, 177.43276376280926], [0.0, 199.6530123165822, 126.81215684365904],
                    [0.0, 0.0, 1.0]])


def _every_pixel(width, height):
    ys, xs = np.mgrid[0:height, 0:width]
    return np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float64)


def test_equidistant_distortion_is_the_kannala_brandt_formula():
    """Camera had only OpenCV's radtan model: MVSEC's fisheye calibration could not be stated at all."""
    cam = Camera(MVSEC_K, 346, 260, MVSEC_D, "equidistant")
    rng = np.random.default_rng(1)
    xn = rng.uniform(-0.9, 0.9, (400, 2))
    k1, k2, k3, k4 = MVSEC_D
    r = np.sqrt(xn[:, 0] ** 2 + xn[:, 1] ** 2)
    theta = np.arctan(r)
    theta_d = theta * (1 + k1 * theta ** 2 + k2 * theta ** 4 + k3 * theta ** 6 + k4 * theta ** 8)
    expected = np.column_stack([MVSEC_K[0, 0] * xn[:, 0] * theta_d / r + MVSEC_K[0, 2],
                                MVSEC_K[1, 1] * xn[:, 1] * theta_d / r + MVSEC_K[1, 2]])
    undistorted_px = np.column_stack([MVSEC_K[0, 0] * xn[:, 0] + MVSEC_K[0, 2], MVSEC_K[1, 1] * xn[:, 1] + MVSEC_K[1, 2]])
    np.testing.assert_allclose(cam.distort_points(undistorted_px), expected, atol=1e-9)
    # zero coefficients are still a fisheye (r_d = atan r), not a pinhole
    assert not Camera(MVSEC_K, 346, 260, np.zeros(4), "equidistant").is_pinhole
    same = Camera.from_intrinsics(*MVSEC_K[[0, 1, 0, 1], [0, 1, 2, 2]], 346, 260, MVSEC_D, model="equidistant")
    np.testing.assert_array_equal(same.distort_points(undistorted_px), cam.distort_points(undistorted_px))


@pytest.mark.parametrize("rectified", [False, True])
def test_equidistant_undistortion_round_trips_over_the_image(rectified):
    rect = (MVSEC_R, MVSEC_P) if rectified else (None, None)
    cam = Camera(MVSEC_K, 346, 260, MVSEC_D, "equidistant", *rect)
    pixels = _every_pixel(346, 260)
    undistorted = cam.undistort_points(pixels)
    assert np.isfinite(undistorted).all()
    np.testing.assert_allclose(cam.distort_points(undistorted), pixels, atol=1e-6)
    # the same map as the one MVSEC users build with OpenCV (cv2.fisheye.undistortPoints with R_rect, P_rect)
    reference = cv2.fisheye.undistortPoints(pixels.reshape(-1, 1, 2), MVSEC_K, MVSEC_D,
                                            R=MVSEC_R if rectified else np.eye(3),
                                            P=MVSEC_P if rectified else MVSEC_K).reshape(-1, 2)
    np.testing.assert_allclose(undistorted, reference, atol=1e-4)
    table = cam.undistort(Events(pixels[:, 0], pixels[:, 1], np.arange(len(pixels)), np.ones(len(pixels)), 346, 260))
    np.testing.assert_allclose(table, reference, atol=1e-3)     # float32 lookup


def test_rectified_camera_puts_a_point_where_the_rectified_pinhole_projects_it():
    cam = Camera(MVSEC_K, 346, 260, MVSEC_D, "equidistant", MVSEC_R, MVSEC_P)
    rng = np.random.default_rng(2)
    points = np.column_stack([rng.uniform(-1, 1, 200), rng.uniform(-0.8, 0.8, 200), rng.uniform(1.5, 4, 200)])
    # the sensor's pixel: K [distort(x / z, y / z)] with OpenCV's own fisheye projection
    sensor = cv2.fisheye.projectPoints(points.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), MVSEC_K,
                                       MVSEC_D)[0].reshape(-1, 2)
    rectified = (points @ MVSEC_R.T) @ MVSEC_P.T
    np.testing.assert_allclose(cam.undistort_points(sensor), rectified[:, :2] / rectified[:, 2:], atol=1e-6)
    np.testing.assert_array_equal(cam.pinhole_K, MVSEC_P)


@pytest.mark.parametrize("kwargs, match", [
    ({"distortion": MVSEC_D[:3], "model": "equidistant"}, r"equidistant camera must have 4 coefficients .*got 3"),
    ({"distortion": np.r_[MVSEC_D, 0.0], "model": "equidistant"}, r"must have 4 coefficients .*got 5"),
    ({"distortion": None, "model": "equidistant"}, r"4 coefficients k1, k2, k3, k4, got None"),
    ({"distortion": np.zeros(6)}, r"radtan camera must have 4 or 5 or 8 or 12 or 14 coefficients .*got 6"),
    ({"distortion": MVSEC_D, "model": "fisheye"}, r"model must be one of \('radtan', 'equidistant'\)"),
    ({"distortion": MVSEC_D, "model": "equidistant", "rectification": 2 * np.eye(3)}, "rectification must be a rotation"),
    ({"distortion": MVSEC_D, "model": "equidistant", "rectification": np.diag([1.0, 1.0, -1.0])}, "must be a rotation"),
    ({"distortion": MVSEC_D, "model": "equidistant", "rectified_K": np.eye(3)[:, ::-1]}, "rectified_K must"),
])
def test_camera_models_are_validated_at_construction(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Camera(MVSEC_K, 346, 260, **kwargs)


def test_scaled_rectified_camera_keeps_its_model():
    cam = Camera(MVSEC_K, 346, 260, MVSEC_D, "equidistant", MVSEC_R, MVSEC_P).scaled(173, 130)
    assert cam.model == "equidistant" and cam.rectified_K[0, 0] == pytest.approx(MVSEC_P[0, 0] / 2)
    np.testing.assert_array_equal(cam.rectification, MVSEC_R)


def test_a_rectification_printed_with_few_decimals_is_taken_as_the_nearest_rotation():
    """A rectification_matrix printed with 6 decimals is 8e-7 from orthonormal (4 decimals: 7e-5): refused at a
    1e-6 tolerance, it would hang on the digits a tool prints. Taken now, as the nearest rotation."""
    from cmax.camera import check_rotation

    rounded = np.round(MVSEC_R, 4)
    R = check_rotation(rounded)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0) and np.abs(R - MVSEC_R).max() < 1e-4
    with pytest.raises(ValueError, match="must be a rotation"):
        check_rotation(1.01 * MVSEC_R)             # R R^T 2% off: not a rotation


_TIGHT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)


@pytest.mark.parametrize("model", ["radtan", "equidistant"])
def test_undistorted_pixels_are_opencvs_unrounded_positions(model):
    """Camera.undistorted_pixels: each event's exact undistorted and rectified position (float64, not rounded to
    a pixel), OpenCV's undistortPoints with R and P on the event's sensor pixel; undistorted_kept pairs them with
    the events undistort_events keeps, whose integer pixels are those positions rounded."""
    if model == "equidistant":
        cam = Camera(MVSEC_K, 346, 260, MVSEC_D, "equidistant", MVSEC_R, MVSEC_P)
    else:
        cam = Camera(MVSEC_K, 346, 260, np.array([-0.3, 0.09, 0.001, -0.002, 0.0]), "radtan", MVSEC_R, MVSEC_P)
    rng = np.random.default_rng(11)
    n = 3000
    ev = Events(rng.integers(0, 346, n), rng.integers(0, 260, n), np.arange(n), rng.integers(0, 2, n), 346, 260)
    pixels = np.column_stack([ev.x, ev.y]).astype(np.float64).reshape(-1, 1, 2)
    if model == "equidistant":
        reference = cv2.fisheye.undistortPoints(pixels, MVSEC_K, MVSEC_D, R=MVSEC_R, P=MVSEC_P, criteria=_TIGHT)
    else:
        reference = cv2.undistortPoints(pixels, MVSEC_K, cam.distortion, R=MVSEC_R, P=MVSEC_P, criteria=_TIGHT)
    exact = cam.undistorted_pixels(ev)
    assert exact.shape == (n, 2) and exact.dtype == np.float64
    np.testing.assert_allclose(exact, reference.reshape(-1, 2), atol=1e-6)
    assert np.abs(exact - np.rint(exact)).max() > 0.4          # not rounded: positions between pixels
    kept = cam.undistorted_kept(ev)
    rounded = cam.undistort_events(ev)
    assert len(kept) == len(rounded) and np.all(np.diff(kept) > 0)
    np.testing.assert_array_equal(np.column_stack([rounded.x, rounded.y]), np.rint(exact[kept]))
    np.testing.assert_array_equal(rounded.t, ev.t[kept])


def test_undistorted_pixels_of_a_pinhole_are_the_events_pixels():
    cam = Camera.from_intrinsics(200.0, 200.0, 120.0, 90.0, 240, 180)
    ev = Events([3, 239], [0, 179], [0, 1], [1, 0], 240, 180)
    np.testing.assert_array_equal(cam.undistorted_pixels(ev), [[3.0, 0.0], [239.0, 179.0]])
    np.testing.assert_array_equal(cam.undistorted_kept(ev), [0, 1])
    with pytest.raises(ValueError, match="events come from a 240x180 sensor, the camera is 241x180"):
        Camera.from_intrinsics(200.0, 200.0, 120.0, 90.0, 241, 180).undistorted_pixels(ev)
