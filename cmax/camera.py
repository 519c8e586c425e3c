"""Pinhole camera with OpenCV (radtan) or Kannala-Brandt (Kalibr ``equidistant``, ``cv2.fisheye``) distortion and
an optional stereo rectification, and undistortion of event coordinates."""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numpy as np

from cmax.events import Events, _check_sensor_size, require_events

__all__ = ["Camera", "DISTORTION_MODELS", "camera_and_intrinsics", "check_intrinsics", "check_principal_point",
           "check_rotation", "distort_equidistant", "intrinsics_matrix", "intrinsics_oddity", "nearest_pixels",
           "pinhole_events", "sensor_pixels"]

_DISTORTION_LENGTHS = (4, 5, 8, 12, 14)

#: Distortion models a :class:`Camera` knows: OpenCV's ``radtan`` (``plumb_bob``; 4, 5, 8, 12 or 14 coefficients)
#: and Kannala-Brandt's ``equidistant`` fisheye model (Kalibr's name; OpenCV's ``cv2.fisheye``; 4 coefficients).
DISTORTION_MODELS = ("radtan", "equidistant")

#: How far ``R R^T`` of a rectification may lie from the identity (entries; a rotation printed with 4 decimals is
#: about 1e-4 off): within it :func:`check_rotation` takes the nearest rotation, beyond it refuses the matrix.
ROTATION_TOLERANCE = 1e-3

#: Undistortion: OpenCV's fixed-point iterations for every pixel, the iterations for the pixels that have not
#: converged after those, and the distance [px] between a pixel and the re-distorted image of its undistorted
#: position under which it counts as solved (:meth:`Camera.undistort_points`).
UNDISTORT_ITERATIONS = 40
UNDISTORT_MAX_ITERATIONS = 2000
UNDISTORT_TOLERANCE_PX = 0.01


def check_intrinsics(K: object, name: str = "K") -> np.ndarray:
    """Validate a pinhole matrix; returns it as a (3, 3) float64 array.

    Expects ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` with finite entries and
    positive focal lengths (pixels).
    """
    try:
        matrix = np.asarray(K, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a 3x3 matrix of numbers, got {K!r}") from None
    if matrix.shape != (3, 3):
        hint = (" (four numbers fx, fy, cx, cy? np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]) is the matrix)"
                if matrix.shape == (4,) else "")
        raise ValueError(f"{name} must be a 3x3 matrix, got shape {matrix.shape}{hint}")
    if not np.isfinite(matrix).all():
        raise ValueError(f"{name} must be finite, got {matrix.tolist()}")
    if not (matrix[0, 0] > 0 and matrix[1, 1] > 0):
        raise ValueError(f"{name} must have positive focal lengths fx, fy; got {matrix[0, 0]}, {matrix[1, 1]}")
    if not np.allclose(matrix[2], [0, 0, 1]) or matrix[1, 0] != 0:
        raise ValueError(f"{name} must have the form [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {matrix.tolist()}")
    return matrix


def intrinsics_matrix(K: object, name: str = "K") -> np.ndarray:
    """``K`` given as ``[fx, fy, cx, cy]`` [px] or a (3, 3) pinhole matrix, as the checked (3, 3) float64 matrix
    (:func:`check_intrinsics`): TypeError / ValueError in one line naming ``name`` for anything else (NaN, a focal
    length <= 0, a transposed or non-pinhole matrix).

    >>> intrinsics_matrix([200, 210, 120, 90]).tolist()
    [[200.0, 0.0, 120.0], [0.0, 210.0, 90.0], [0.0, 0.0, 1.0]]
    """
    try:
        flat = np.asarray(K, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be [fx, fy, cx, cy] or a 3x3 matrix of numbers, got {K!r}") from None
    if flat.shape == (4,):
        fx, fy, cx, cy = flat
        flat = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return check_intrinsics(flat, name)


def check_principal_point(K: np.ndarray, width: int, height: int, name: str = "K") -> None:
    """ValueError naming ``name`` when the principal point of ``K`` (3, 3) [px] lies outside the ``width`` x
    ``height`` image (beyond half a pixel past its edge pixels' centres): such a K is another sensor size's or
    crop's, e.g. the calibration of frames that ``cmax simulate --size`` resized (``cmax.fit`` refuses it too).

    >>> import numpy as np
    >>> check_principal_point(np.array([[335.4, 0, 129.9], [0, 335.4, 99.2], [0, 0, 1]]), 240, 180)
    >>> check_principal_point(np.array([[335.4, 0, 129.9], [0, 335.4, 99.2], [0, 0, 1]]), 120, 90)
    Traceback (most recent call last):
    ...
    ValueError: K's principal point (129.9, 99.2) lies outside the 120x90 image: K belongs to another sensor size or crop (give the K of these pixels)
    """
    cx, cy = float(K[0, 2]), float(K[1, 2])
    if not (-0.5 <= cx <= width - 0.5 and -0.5 <= cy <= height - 0.5):
        raise ValueError(f"{name}'s principal point ({cx:g}, {cy:g}) lies outside the {width}x{height} image: "
                         f"{name} belongs to another sensor size or crop (give the K of these pixels)")


#: How far a plausible principal point lies from the image's centre (a fraction of the image's size), and
#: how far a plausible pixel aspect fy / fx lies from 1: beyond either, K was probably given in another order.
ODD_PRINCIPAL_POINT = 0.25
ODD_ASPECT = 0.1


def intrinsics_oddity(K: np.ndarray, width: int, height: int) -> str | None:
    """Why a valid ``K`` (3, 3) [px] is unlike any camera's for a ``width`` x ``height`` sensor, or None: the
    principal point more than :data:`ODD_PRINCIPAL_POINT` of the image's size from its centre, or ``fy / fx``
    more than :data:`ODD_ASPECT` from 1. The usual cause is the order of the numbers (``fx, fy, cx, cy``
    against ROS's row order ``fx, cx, fy, cy``, or ``cx, cy, fx, fy``); a crop can move the centre, so
    callers warn, they do not refuse.

    >>> import numpy as np
    >>> intrinsics_oddity(np.array([[226.38, 0, 173.64], [0, 226.15, 133.73], [0, 0, 1]]), 346, 260) is None
    True
    >>> intrinsics_oddity(np.array([[226.38, 0, 226.15], [0, 173.64, 133.73], [0, 0, 1]]), 346, 260)[:40]
    'K (fx 226.38, fy 173.64, cx 226.15, cy 1'
    """
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    off = max(abs(cx - (width - 1) / 2) / width, abs(cy - (height - 1) / 2) / height)
    aspect = fy / fx
    if off <= ODD_PRINCIPAL_POINT and abs(aspect - 1.0) <= ODD_ASPECT:
        return None
    return (f"K (fx {fx:g}, fy {fy:g}, cx {cx:g}, cy {cy:g}) is unlike a camera's for a {width}x{height} sensor: "
            f"the principal point is {off:.0%} of the image from its centre and fy / fx = {aspect:.2f} (cameras: "
            "within a few per cent of the centre, fy / fx near 1); check the order of the numbers (fx, fy, cx, cy; "
            "ROS's rows read fx, cx, fy, cy)")


def distort_equidistant(xy: np.ndarray, distortion: np.ndarray) -> np.ndarray:
    """Kannala-Brandt (Kalibr ``equidistant``, ``cv2.fisheye``) distortion of normalised coordinates ``xy`` (N, 2)
    (a ray ``(x, y, 1)``) -> (N, 2), with ``distortion = (k1, k2, k3, k4)``: the ray's angle from the optical
    axis ``theta = atan(r)``, ``r = |xy|``, becomes ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 +
    k4 theta^8)`` and the point ``xy theta_d / r`` (``xy`` itself at ``r = 0``).

    >>> distort_equidistant(np.array([[1.0, 0.0]]), np.zeros(4)).round(6).tolist()   # 45 degrees: pi / 4
    [[0.785398, 0.0]]
    """
    k1, k2, k3, k4 = np.asarray(distortion, dtype=np.float64).ravel()
    r = np.hypot(xy[:, 0], xy[:, 1])
    theta = np.arctan(r)
    t2 = theta * theta
    theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(r > 0, theta_d / np.where(r > 0, r, 1.0), 1.0)
    return xy * scale[:, None]


def _distort_normalised(xy: np.ndarray, distortion: np.ndarray) -> np.ndarray:
    """OpenCV's distortion of normalised coordinates (N, 2) -> (N, 2) (``cv2.projectPoints`` with ``K = I``).

    Closed form for 4, 5, 8 and 12 coefficients ``(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4]]])``:
    ``radial = (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)``,
    ``x' = x radial + 2 p1 x y + p2 (r^2 + 2 x^2) + s1 r^2 + s2 r^4`` and
    ``y' = y radial + p1 (r^2 + 2 y^2) + 2 p2 x y + s3 r^2 + s4 r^4``; the tilted model (14) through OpenCV.
    """
    if distortion.size == 14:
        points = np.column_stack([xy, np.ones(len(xy))]).reshape(-1, 1, 3)
        return cv2.projectPoints(points, np.zeros(3), np.zeros(3), np.eye(3), distortion)[0].reshape(-1, 2)
    k = np.zeros(12)
    k[: distortion.size] = distortion
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = k
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        return np.column_stack([
            x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + r2 * (s1 + s2 * r2),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + r2 * (s3 + s4 * r2),
        ])


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera of ``width`` x ``height`` pixels with optional lens distortion and rectification.

    A point's ray ``(x, y, 1)`` in the camera frame reaches the sensor at the pixel ``K [distort(x, y); 1]``.
    Undistortion (:meth:`undistort_points`, :meth:`undistort`, :meth:`undistort_events`) inverts that and gives
    the pixel of an ideal pinhole with :attr:`pinhole_K`: ``rectified_K [R x; 1]`` (up to scale) with
    ``R = rectification``, as ``cv2.undistortPoints(..., R, P)`` and ``cv2.fisheye.undistortPoints`` give it (a
    stereo rig's rectified frame, e.g. MVSEC's ``depth_image_rect``); ``K`` itself without them.

    Parameters
    ----------
    K : array_like, shape (3, 3)
        Intrinsic matrix of the (distorted) lens in pixels.
    width, height : int
        Image size in pixels.
    distortion : array_like, optional
        ``model="radtan"``: OpenCV coefficients ``(k1, k2, p1, p2[, k3[, k4, k5, k6[, ...]]])``, shape (4,), (5,),
        (8,), (12,) or (14,); ``None`` (or all zero) for an ideal pinhole. ``model="equidistant"``: exactly the
        four Kannala-Brandt coefficients ``(k1, k2, k3, k4)`` (:func:`distort_equidistant`; all zero is still a
        fisheye, not a pinhole).
    model : str
        ``"radtan"`` (default; ``"plumb_bob"`` is read as it) or ``"equidistant"`` (:data:`DISTORTION_MODELS`).
    rectification : array_like, shape (3, 3), optional
        Rotation ``R`` [unitless] from the camera frame to the rectified frame (Kalibr's / ROS's
        ``rectification_matrix``); ``None``: no rotation.
    rectified_K : array_like, shape (3, 3), optional
        Pinhole matrix [px] of the rectified frame (the left 3x3 of Kalibr's / ROS's ``projection_matrix``);
        ``None``: ``K``.

    Examples
    --------
    >>> import numpy as np
    >>> cam = Camera.from_intrinsics(200.0, 200.0, 120.0, 90.0, 240, 180)
    >>> cam.project(np.array([[0.0, 0.0, 2.0]])).tolist()
    [[120.0, 90.0]]
    """

    K: np.ndarray
    width: int
    height: int
    distortion: np.ndarray | None = field(default=None)
    model: str = "radtan"
    rectification: np.ndarray | None = field(default=None)
    rectified_K: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", check_intrinsics(self.K))
        width, height = _check_sensor_size(self.width, self.height)
        object.__setattr__(self, "width", width)
        object.__setattr__(self, "height", height)
        model = "radtan" if self.model == "plumb_bob" else self.model
        if model not in DISTORTION_MODELS:
            raise ValueError(f"model must be one of {DISTORTION_MODELS} (OpenCV's radtan / plumb_bob, Kannala-Brandt's "
                             f"equidistant fisheye), got {self.model!r}")
        object.__setattr__(self, "model", model)
        if model == "equidistant" and self.distortion is None:
            raise ValueError("distortion of an equidistant (fisheye) camera must be its 4 coefficients k1, k2, k3, k4, "
                             "got None")
        if self.distortion is not None:
            coefficients = np.asarray(self.distortion, dtype=np.float64).ravel()
            lengths = (4,) if model == "equidistant" else _DISTORTION_LENGTHS
            if coefficients.size not in lengths:
                what = "k1, k2, k3, k4" if model == "equidistant" else "k1, k2, p1, p2[, k3, ...]"
                article = "an" if model == "equidistant" else "a"
                raise ValueError(f"distortion of {article} {model} camera must have {' or '.join(map(str, lengths))} "
                                 f"coefficients ({what}), got {coefficients.size}")
            if not np.isfinite(coefficients).all():
                raise ValueError(f"distortion must be finite, got {coefficients.tolist()}")
            object.__setattr__(
                self, "distortion", None if model == "radtan" and not coefficients.any() else coefficients
            )
        if self.rectification is not None:
            object.__setattr__(self, "rectification", check_rotation(self.rectification, "rectification"))
        if self.rectified_K is not None:
            object.__setattr__(self, "rectified_K", check_intrinsics(self.rectified_K, "rectified_K"))

    # -- constructors -----------------------------------------------------------------
    @classmethod
    def from_intrinsics(
        cls, fx: float, fy: float, cx: float, cy: float, width: int, height: int,
        distortion: object = None, model: str = "radtan",
    ) -> "Camera":
        """Camera from focal lengths ``fx``, ``fy`` and principal point ``cx``, ``cy`` [px], the sensor's ``width`` x
        ``height`` [px] and the ``distortion`` coefficients of ``model``: OpenCV's ``(k1, k2, p1, p2[, k3, ...])``
        for ``"radtan"`` (None: a pinhole), Kannala-Brandt's ``(k1, k2, k3, k4)`` for ``"equidistant"``."""
        K = intrinsics_matrix([fx, fy, cx, cy])
        return cls(K, width, height, None if distortion is None else np.asarray(distortion), model)

    @classmethod
    def from_ecd_calib(cls, path: str | os.PathLike, width: int = 240, height: int = 180) -> "Camera":
        """Camera from an ECD ``calib.txt`` at ``path`` (one line ``fx fy cx cy k1 k2 p1 p2 k3``), of a sensor
        ``width`` x ``height`` [px] (the file states no size; ECD's DAVIS240C: 240 x 180), read by
        :func:`cmax.io.read_calibration`, the one reader of calibration files (the same checks and messages)."""
        from cmax.io.calibration import read_calibration     # cmax.io.calibration imports this module

        return read_calibration(path).camera(width, height)

    # -- properties -------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def is_distorted(self) -> bool:
        return self.distortion is not None

    @property
    def pinhole_K(self) -> np.ndarray:
        """(3, 3) [px]: the pinhole matrix of the undistorted (and rectified) pixels: ``rectified_K`` or ``K``."""
        return self.K if self.rectified_K is None else self.rectified_K

    @property
    def is_pinhole(self) -> bool:
        """True when the events' pixels are already the pinhole's of :attr:`pinhole_K`: no distortion, no
        rectification, no other K (undistortion then returns them as they are)."""
        return self.distortion is None and self.rectification is None and self.rectified_K is None

    # -- geometry ---------------------------------------------------------------------
    def project(self, points_c: np.ndarray) -> np.ndarray:
        """Pinhole projection of camera-frame points ``points_c`` (N, 3) [m] to pixels (N, 2) float64 with ``K`` (no
        distortion, no rectification: :meth:`distort_points` gives the sensor's pixel of a rectified pinhole's).

        Points must be finite and in front of the camera (z > 0); others have no
        image and raise :class:`ValueError`.
        """
        points_c = np.asarray(points_c, dtype=np.float64)
        if points_c.ndim != 2 or points_c.shape[1] != 3:
            raise ValueError(f"points_c must have shape (N, 3), got {points_c.shape}")
        if not np.isfinite(points_c).all():
            raise ValueError("points_c must be finite (no NaN or infinite coordinates)")
        if (points_c[:, 2] <= 0).any():
            bad = int(np.flatnonzero(points_c[:, 2] <= 0)[0])
            raise ValueError(
                f"points_c must lie in front of the camera (z > 0); point {bad} has z={points_c[bad, 2]}"
            )
        homogeneous = points_c @ self.K.T
        return homogeneous[:, :2] / homogeneous[:, 2:3]

    def backproject(self, pixels: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) [m] of undistorted pixels (N, 2) at z-depth (N,) [m].

        Depth ``NaN`` means unknown (the project's convention) and gives a NaN
        point; depth must otherwise be positive and finite, pixels finite.
        """
        pixels = np.asarray(pixels, dtype=np.float64)
        depth = np.asarray(depth, dtype=np.float64)
        if pixels.ndim != 2 or pixels.shape[1] != 2:
            raise ValueError(f"pixels must have shape (N, 2), got {pixels.shape}")
        if depth.shape != pixels.shape[:1]:
            raise ValueError(f"depth must have shape {pixels.shape[:1]}, got {depth.shape}")
        if not np.isfinite(pixels).all():
            raise ValueError("pixels must be finite (no NaN or infinite coordinates)")
        known = depth[~np.isnan(depth)]
        if not (np.isfinite(known) & (known > 0)).all():
            raise ValueError("depth must be positive and finite metres (NaN where unknown)")
        homogeneous = np.column_stack([pixels, np.ones(len(pixels))])
        rays = homogeneous @ np.linalg.inv(self.K).T
        return rays * depth[:, None]

    def undistort_points(self, pixels: np.ndarray) -> np.ndarray:
        """Undistorted pixel coordinates (N, 2) float64 of distorted pixels (N, 2) (same K); NaN rows for pixels
        that have no undistorted position.

        The model is ``pixel = K [distort(x_n); 1]`` with the full ``K``, skew
        included: pixels are normalised by ``K^-1`` and OpenCV's iterative
        ``undistortPoints`` runs on normalised coordinates (given ``K`` itself,
        OpenCV would read only fx, fy, cx, cy and drop the skew ``K[0, 1]``).

        Every result is checked with the forward model (``cv2.projectPoints``): a pixel whose undistorted
        position does not distort back to within :data:`UNDISTORT_TOLERANCE_PX` of it is solved again with
        :data:`UNDISTORT_MAX_ITERATIONS` iterations (strong distortion converges slowly), and stays NaN if it
        still does not: beyond the largest radius the model reaches (a polynomial that folds back, e.g. a
        strong negative k1 with a negative k3) no undistorted position maps onto the pixel.
        """
        pixels = np.asarray(pixels, dtype=np.float64)
        if pixels.ndim != 2 or pixels.shape[1] != 2:
            raise ValueError(f"pixels must have shape (N, 2), got {pixels.shape}")
        if self.is_pinhole or not len(pixels):
            return pixels.copy()
        ones = np.ones((len(pixels), 1))
        normalised = (np.hstack([pixels, ones]) @ np.linalg.inv(self.K).T)[:, :2]
        if self.distortion is None:
            undistorted = normalised
        else:
            undistorted = self._undistort_normalised(normalised, UNDISTORT_ITERATIONS)
            unsolved = np.flatnonzero(self._residual_px(undistorted, pixels) > UNDISTORT_TOLERANCE_PX)
            if unsolved.size:
                undistorted[unsolved] = self._undistort_normalised(normalised[unsolved], UNDISTORT_MAX_ITERATIONS)
                still = unsolved[self._residual_px(undistorted[unsolved], pixels[unsolved]) > UNDISTORT_TOLERANCE_PX]
                undistorted[still] = np.nan
        rays = np.hstack([undistorted, ones])
        if self.rectification is not None:
            rays = rays @ self.rectification.T
            with np.errstate(invalid="ignore", divide="ignore"):
                rays = np.where(rays[:, 2:3] > 0, rays / rays[:, 2:3], np.nan)   # behind the rectified camera: none
        return (rays @ self.pinhole_K.T)[:, :2]

    def distort_points(self, pixels: np.ndarray) -> np.ndarray:
        """The forward model: the sensor's pixels (N, 2) float64 of undistorted pixels ``pixels`` (N, 2) of
        :attr:`pinhole_K` (rectified when the camera has a rectification), the inverse of
        :meth:`undistort_points`; NaN rows for pixels whose rays point behind the camera."""
        pixels = np.asarray(pixels, dtype=np.float64)
        if pixels.ndim != 2 or pixels.shape[1] != 2:
            raise ValueError(f"pixels must have shape (N, 2), got {pixels.shape}")
        rays = np.hstack([pixels, np.ones((len(pixels), 1))]) @ np.linalg.inv(self.pinhole_K).T
        if self.rectification is not None:
            rays = rays @ self.rectification      # R^-1 = R^T, applied to row vectors
        with np.errstate(invalid="ignore", divide="ignore"):
            normalised = np.where(rays[:, 2:3] > 0, rays[:, :2] / rays[:, 2:3], np.nan)
        if self.distortion is not None:
            normalised = self._distort(normalised)
        return (np.hstack([normalised, np.ones((len(pixels), 1))]) @ self.K.T)[:, :2]

    def _distort(self, normalised: np.ndarray) -> np.ndarray:
        """The lens model's distortion of normalised coordinates (N, 2) -> (N, 2)."""
        if self.model == "equidistant":
            return distort_equidistant(normalised, self.distortion)
        return _distort_normalised(normalised, self.distortion)

    def _undistort_normalised(self, normalised: np.ndarray, iterations: int) -> np.ndarray:
        """OpenCV's iterative inverse of the distortion on normalised coordinates (N, 2) -> (N, 2)
        (``cv2.fisheye.undistortPoints`` for the equidistant model)."""
        points = np.ascontiguousarray(normalised).reshape(-1, 1, 2)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, 1e-12)
        if self.model == "equidistant":
            out = cv2.fisheye.undistortPoints(points, np.eye(3), self.distortion, R=np.eye(3), P=np.eye(3),
                                              criteria=criteria)
        else:
            out = cv2.undistortPoints(points, np.eye(3), self.distortion, R=None, P=np.eye(3), criteria=criteria)
        return out.reshape(-1, 2).astype(np.float64)

    def _residual_px(self, undistorted: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """Distance [px] (N,) between ``pixels`` (N, 2) and the forward model's image of their normalised
        ``undistorted`` positions (N, 2); inf where that image is not finite."""
        distorted = self._distort(undistorted)
        back = (np.column_stack([distorted, np.ones(len(distorted))]) @ self.K.T)[:, :2]
        with np.errstate(invalid="ignore"):
            residual = np.linalg.norm(back - pixels, axis=1)
        return np.where(np.isfinite(residual), residual, np.inf)

    @cached_property
    def undistortion_map(self) -> np.ndarray:
        """(H, W, 2) float32: the undistorted (and rectified) coordinates [px of :attr:`pinhole_K`] of every integer
        pixel, NaN for the pixels that have none (beyond the radius the distortion model reaches:
        :meth:`undistort_points`).

        Computed once per camera (OpenCV's iterative ``undistortPoints``, checked with the forward model);
        :meth:`undistort` then looks events up in it.
        """
        return self._undistortion_map64.astype(np.float32)

    @cached_property
    def _undistortion_map64(self) -> np.ndarray:
        """(H, W, 2) float64: :attr:`undistortion_map` before its rounding to float32."""
        ys, xs = np.mgrid[0: self.height, 0: self.width]
        pixels = np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float64)
        return self.undistort_points(pixels).reshape(self.height, self.width, 2)

    def undistort(self, events: Events) -> np.ndarray:
        """Undistorted, sub-pixel coordinates (N, 2) float32 ``(x, y)`` of the events.

        A table lookup in :attr:`undistortion_map` (no per-event solve). The
        result may fall outside the image for strongly distorted borders, and is NaN for an event on a pixel
        that has no undistorted position (:meth:`undistort_points`).
        """
        self._check_events(events)
        if self.is_pinhole:
            return np.column_stack([events.x, events.y]).astype(np.float32)
        return self.undistortion_map[events.y, events.x]

    def _check_events(self, events: object) -> None:
        require_events(events)
        if events.sensor_size != (self.width, self.height):
            raise ValueError(
                f"events come from a {events.width}x{events.height} sensor, "
                f"the camera is {self.width}x{self.height}"
            )

    def undistorted_pixels(self, events: Events) -> np.ndarray:
        """The exact undistorted (and rectified) position (N, 2) float64 ``(x, y)`` [px of :attr:`pinhole_K`] of
        each event's pixel centre, unrounded: ``cv2.undistortPoints`` (``cv2.fisheye.undistortPoints`` for the
        equidistant model) with ``R = rectification`` and ``P = pinhole_K``, checked with the forward model
        (:meth:`undistort_points`, looked up per pixel); NaN rows for events on pixels that have none. Positions
        may lie outside the image (a strongly distorted border). A pinhole camera gives the events' own pixels.

        Raises ``ValueError`` when the events come from a sensor of another size than the camera's.
        """
        self._check_events(events)
        if self.is_pinhole:
            return np.column_stack([events.x, events.y]).astype(np.float64)
        return self._undistortion_map64[events.y, events.x]

    def undistorted_kept(self, events: Events) -> np.ndarray:
        """Indices (M,) int64, increasing, of the events that :meth:`undistort_events` keeps: those whose nearest
        undistorted pixel lies inside the image (all of them for a pinhole camera); ``events[kept]`` pairs them
        with their exact positions ``undistorted_pixels(events)[kept]``.

        Raises ``ValueError`` when the events come from a sensor of another size than the camera's.
        """
        self._check_events(events)
        if self.is_pinhole:
            return np.arange(len(events), dtype=np.int64)
        return np.flatnonzero(self._nearest_pixels(events)[1]).astype(np.int64)

    def _nearest_pixels(self, events: Events) -> tuple[np.ndarray, np.ndarray]:
        """The nearest integer undistorted pixel (N, 2) int64 of each event (-1 where none) and whether it lies
        inside the image (N,) bool (:func:`nearest_pixels` of :attr:`undistortion_map`)."""
        return nearest_pixels(self.undistortion_map[events.y, events.x], self.width, self.height)

    def undistort_events_and_pixels(self, events: Events) -> tuple[Events, np.ndarray, np.ndarray]:
        """``(undistorted, pixels, kept)``: the events at their nearest undistorted pixels, as
        :meth:`undistort_events` gives them; their exact positions (M, 2) float64 [px], as
        :meth:`undistorted_pixels` gives them; and which events those are, (M,) int64 indices into ``events``
        (:meth:`undistorted_kept`), the nearest pixels found once for all three.

        Raises ``ValueError`` when the events come from a sensor of another size than the camera's.
        """
        kept = self.undistorted_kept(events)
        if self.is_pinhole:
            return events, np.column_stack([events.x, events.y]).astype(np.float64), kept
        x, y = events.x[kept], events.y[kept]
        xy = np.rint(self.undistortion_map[y, x]).astype(np.int64)    # finite and inside: those kept
        return (Events(xy[:, 0], xy[:, 1], events.t[kept], events.p[kept], self.width, self.height, time_unit="us"),
                self._undistortion_map64[y, x], kept)

    def undistort_events(self, events: Events) -> Events:
        """The events at their undistorted (and rectified) pixels rounded to the nearest integer ones, for a
        pinhole model with :attr:`pinhole_K`: the integer positions of the pixel tests (masks, hot pixels,
        neighbour counts); events whose undistorted pixel lies outside the image, or that have none (NaN in
        :attr:`undistortion_map`), are dropped. :meth:`undistorted_pixels` gives the unrounded positions (what
        :func:`cmax.fit` warps and what ``cmax.representations.voxel_grid(..., pixels=)`` spreads bilinearly), and
        :meth:`undistorted_kept` which events are kept. A pinhole camera (:attr:`is_pinhole`) returns ``events``
        themselves.

        Raises ``ValueError`` when the events come from a sensor of another size than the camera's.
        """
        self._check_events(events)
        if self.is_pinhole:
            return events
        xy, inside = self._nearest_pixels(events)
        return Events(xy[inside, 0], xy[inside, 1], events.t[inside], events.p[inside], self.width, self.height,
                      time_unit="us")

    def scaled(self, width: int, height: int) -> "Camera":
        """The same camera resampled to ``width`` x ``height`` pixels (distortion, model and rectification kept;
        ``rectified_K`` scaled as ``K``)."""
        sx, sy = width / self.width, height / self.height
        return Camera(_scaled_K(self.K, sx, sy), width, height, self.distortion, self.model, self.rectification,
                      None if self.rectified_K is None else _scaled_K(self.rectified_K, sx, sy))


def _scaled_K(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """``K`` (3, 3) [px] of an image resampled by ``sx``, ``sy``; pixel centres: ``x' + 0.5 = sx (x + 0.5)``."""
    cx, cy = float(K[0, 2]), float(K[1, 2])
    K = K.copy()
    K[0] *= sx
    K[1] *= sy
    K[0, 2] = sx * (cx + 0.5) - 0.5
    K[1, 2] = sy * (cy + 0.5) - 0.5
    return K


def check_rotation(R: object, name: str = "R") -> np.ndarray:
    """Validate a rotation matrix ``R`` (3, 3); returns it, or the nearest rotation to it (SVD) where it is not one
    to 1e-12, as a (3, 3) float64 array. It must be finite, ``R R^T`` within :data:`ROTATION_TOLERANCE` of the
    identity (a matrix printed with 4 or more decimals, as calibration files print them) and its determinant +1 (a
    reflection or a scaled matrix is refused, naming ``name``).

    >>> check_rotation(np.eye(3)).tolist()[0]
    [1.0, 0.0, 0.0]
    """
    try:
        matrix = np.asarray(R, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a 3x3 rotation matrix of numbers, got {R!r}") from None
    if matrix.shape != (3, 3):
        raise ValueError(f"{name} must be a 3x3 rotation matrix, got shape {matrix.shape}")
    if not np.isfinite(matrix).all():
        raise ValueError(f"{name} must be finite, got {matrix.tolist()}")
    if not np.allclose(matrix @ matrix.T, np.eye(3), rtol=0, atol=ROTATION_TOLERANCE) or np.linalg.det(matrix) < 0:
        raise ValueError(f"{name} must be a rotation (R R^T = I, det R = +1), got {matrix.tolist()}")
    if np.allclose(matrix @ matrix.T, np.eye(3), rtol=0, atol=1e-12):
        return matrix                      # a rotation to the digits given: kept as it is
    u, _, vt = np.linalg.svd(matrix)
    return u @ vt


def camera_and_intrinsics(K: object) -> tuple["Camera | None", np.ndarray]:
    """``(camera, K (3, 3))`` of a ``K`` that is a matrix (checked; camera None) or a :class:`Camera` (its ``K``)."""
    camera = K if isinstance(K, Camera) else None
    return camera, check_intrinsics(K.pinhole_K if camera is not None else K)


def pinhole_events(events: Events, K: object) -> tuple[Events, np.ndarray]:
    """``(events, K (3, 3))`` for a pinhole fit: a matrix ``K`` is returned as given (checked later by the
    caller); a :class:`Camera` gives its :attr:`Camera.pinhole_K` and the events through
    :meth:`Camera.undistort_events` (undistorted and rectified when it has a distortion or a rectification;
    refused when they come from a sensor of another size)."""
    if isinstance(K, Camera):
        return K.undistort_events(events), K.pinhole_K
    return events, K


def nearest_pixels(positions: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """The nearest integer pixel (N, 2) int64 ``(x, y)`` of each position (N, 2) [px] (-1 where it is not finite)
    and whether it lies inside a ``width`` x ``height`` [px] image (N,) bool: where undistorted (or rectified)
    events land when rounded (:meth:`Camera.undistort_events`, DSEC's ``rectify_map`` in ``learned.data``)."""
    solved = np.isfinite(positions).all(axis=1)
    xy = np.rint(np.where(solved[:, None], positions, -1.0)).astype(np.int64)
    inside = solved & (xy[:, 0] >= 0) & (xy[:, 0] < width) & (xy[:, 1] >= 0) & (xy[:, 1] < height)
    return xy, inside


def sensor_pixels(events: Events, K: object) -> np.ndarray | None:
    """The sensor pixels (M, 2) ``(x, y)`` [px] (integers, the events' dtype) of the events that ``pinhole_events(events, K)`` keeps, in
    their order, when ``K`` is a :class:`Camera` with a lens (not :attr:`Camera.is_pinhole`): with
    ``lens=K.undistort_points`` they are the ``pixels`` from which :meth:`cmax.warp.WarpEvents.from_events` dithers
    each event over its sensor pixel and maps it through the lens, unrounded (what :func:`cmax.fit` warps). None for
    a matrix ``K``, a pinhole camera, or events :func:`pinhole_events` refuses (it says why).

    ``events``: :class:`cmax.Events` of the camera's sensor; ``K``: (3, 3) [px] or a :class:`Camera`.
    """
    if not isinstance(K, Camera) or K.is_pinhole or not isinstance(events, Events) or \
            events.sensor_size != (K.width, K.height):
        return None
    kept = K.undistorted_kept(events)
    return np.column_stack([events.x[kept], events.y[kept]])
