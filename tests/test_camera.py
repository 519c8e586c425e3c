"""Camera: intrinsics validation, projection, undistortion lookup table."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from cmax import Events
from cmax.camera import Camera


def test_project_backproject_round_trip():
    cam = Camera.from_intrinsics(200.0, 210.0, 120.0, 90.0, 240, 180)
    points = np.array([[0.1, -0.2, 2.0], [1.0, 0.5, 4.0], [0.0, 0.0, 1.0]])
    pixels = cam.project(points)
    np.testing.assert_allclose(pixels[2], [120.0, 90.0])
    np.testing.assert_allclose(pixels[0], [120 + 200 * 0.05, 90 - 210 * 0.1])
    np.testing.assert_allclose(cam.backproject(pixels, points[:, 2]), points, atol=1e-12)


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
