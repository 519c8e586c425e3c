"""SE(3) and so(3) in numpy: hat, exponential and logarithm maps, pose interpolation.

One convention everywhere in the project (as kornia's ``Se3`` and pypose):

* a **twist** ``xi = (v, omega)`` has shape (..., 6): translation part ``v``
  first (m, or m/s for a velocity), rotation part ``omega`` second (rad, or
  rad/s);
* a **pose** ``T_w_c`` is a (..., 4, 4) homogeneous matrix mapping points of
  the camera frame to the world frame, ``X_w = R_w_c X_c + t_w_c``;
* a camera moving with the body-frame twist ``xi`` obeys
  ``d/dt T_w_c = T_w_c hat(xi)``, so over a time ``dt`` with constant twist
  ``T_w_c(t + dt) = T_w_c(t) se3_exp(xi dt)``.

All functions accept leading batch dimensions and return float64 arrays; none
modifies its inputs.
"""
from __future__ import annotations

import numpy as np

__all__ = [
    "hat", "vee", "so3_exp", "so3_log", "so3_left_jacobian", "so3_left_jacobian_inv",
    "so3_right_jacobian", "se3_exp", "se3_log", "invert_pose", "relative_pose",
    "transform_points", "interpolate_pose", "interpolate_poses",
]

# Below this angle (rad) the series expansions replace the closed forms.
_SMALL_ANGLE = 1e-4

# Above this angle (rad) so3_log takes the axis from the symmetric part of R: ``theta / (2 sin theta)`` of the
# skew part amplifies the rounding of R by ``1 / sin theta`` (a float32 R at pi - 1e-3: 5e-5 rad off).
_SYMMETRIC_ANGLE = 2.0


# A rotation's ``R^T R`` may differ from the identity by this much (float32 round trips).
_ROTATION_TOLERANCE = 1e-3


def _floats(x: object, name: str) -> np.ndarray:
    try:
        array = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be an array of numbers, got {x!r}") from None
    if not np.isfinite(array).all():
        raise ValueError(f"{name} must be finite (it holds NaN or infinite values)")
    return array


def _vectors(x: object, size: int, name: str) -> np.ndarray:
    array = _floats(x, name)
    if array.ndim < 1 or array.shape[-1] != size:
        raise ValueError(f"{name} must have shape (..., {size}), got {array.shape}")
    return array


def _matrices(x: object, size: int, name: str) -> np.ndarray:
    array = _floats(x, name)
    if array.ndim < 2 or array.shape[-2:] != (size, size):
        raise ValueError(f"{name} must have shape (..., {size}, {size}), got {array.shape}")
    return array


def _check_rotations(R: np.ndarray, name: str) -> None:
    """Raise :class:`ValueError` unless every (3, 3) block is a rotation (orthonormal, det +1)."""
    error = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(initial=0.0)
    if error > _ROTATION_TOLERANCE or (np.linalg.det(R) <= 0).any():
        raise ValueError(
            f"{name} must be a rotation matrix (orthonormal, determinant +1); "
            f"max |R^T R - I| = {error:.3g}"
        )


def hat(x: object) -> np.ndarray:
    """The Lie-algebra matrix of ``x``, a rotation vector or a twist.

    A rotation vector ``x = omega`` (..., 3) gives the skew-symmetric (..., 3, 3) matrix with
    ``hat(omega) @ u = cross(omega, u)``::

        hat(w) = [[0, -w3, w2], [w3, 0, -w1], [-w2, w1, 0]]

    A twist ``xi = (v, omega)`` (..., 6) gives the (..., 4, 4) matrix
    ``[[hat(omega), v], [0, 0]]``.

    Examples
    --------
    >>> import numpy as np
    >>> hat([0.0, 0.0, 1.0]) @ np.array([1.0, 0.0, 0.0])
    array([0., 1., 0.])
    """
    array = np.asarray(x, dtype=np.float64)
    if array.ndim < 1 or array.shape[-1] not in (3, 6):
        raise ValueError(f"x must have shape (..., 3) or (..., 6), got {array.shape}")
    if array.shape[-1] == 6:
        out = np.zeros(array.shape[:-1] + (4, 4))
        out[..., :3, :3] = hat(array[..., 3:])
        out[..., :3, 3] = array[..., :3]
        return out
    w1, w2, w3 = array[..., 0], array[..., 1], array[..., 2]
    out = np.zeros(array.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w3, w2
    out[..., 1, 0], out[..., 1, 2] = w3, -w1
    out[..., 2, 0], out[..., 2, 1] = -w2, w1
    return out


def vee(X: object) -> np.ndarray:
    """Inverse of :func:`hat`: ``X`` (..., 3, 3) -> (..., 3) and (..., 4, 4) -> (..., 6)."""
    array = np.asarray(X, dtype=np.float64)
    if array.ndim < 2 or array.shape[-2:] not in ((3, 3), (4, 4)):
        raise ValueError(f"X must have shape (..., 3, 3) or (..., 4, 4), got {array.shape}")
    omega = np.stack([array[..., 2, 1], array[..., 0, 2], array[..., 1, 0]], axis=-1)
    if array.shape[-1] == 4:
        return np.concatenate([array[..., :3, 3], omega], axis=-1)
    return omega


def _rodrigues_coefficients(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``A = sin(t)/t``, ``B = (1-cos t)/t^2``, ``C = (t - sin t)/t^3`` with Taylor series near 0."""
    small = theta < _SMALL_ANGLE
    t = np.where(small, 1.0, theta)
    t2 = theta * theta
    A = np.where(small, 1.0 - t2 / 6.0, np.sin(t) / t)
    B = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(t)) / (t * t))
    C = np.where(small, 1.0 / 6.0 - t2 / 120.0, (t - np.sin(t)) / (t * t * t))
    return A, B, C


def so3_exp(omega: object) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors ``omega`` (..., 3) [rad] (Rodrigues).

    ``R = I + sin(t)/t W + (1 - cos t)/t^2 W^2`` with ``W = hat(omega)``,
    ``t = |omega|``; a Taylor series for ``t < 1e-4``.

    Examples
    --------
    >>> import numpy as np
    >>> np.round(so3_exp([0.0, 0.0, np.pi / 2]) @ [1.0, 0.0, 0.0], 12)
    array([0., 1., 0.])
    """
    omega = _vectors(omega, 3, "omega")
    theta = np.linalg.norm(omega, axis=-1)
    A, B, _ = _rodrigues_coefficients(theta)
    W = hat(omega)
    return np.eye(3) + A[..., None, None] * W + B[..., None, None] * (W @ W)


def so3_log(R: object) -> np.ndarray:
    """Rotation vectors (..., 3) [rad] of rotation matrices (..., 3, 3), angle in [0, pi].

    ``t = atan2(|vee(R - R^T)|/2, (tr R - 1)/2)``, ``omega = t / (2 sin t) vee(R - R^T)``;
    near ``t = 0`` the series ``omega = (1/2 + t^2/12) vee(R - R^T)``; above ``t = 2`` rad
    the axis from the symmetric part ``((R + R^T)/2 - cos t I) / (1 - cos t) = a a^T``, its sign
    from the skew part (accurate up to ``t = pi``, where ``1 / sin t`` is not).
    """
    R = _matrices(R, 3, "R")
    _check_rotations(R, "R")
    skew = vee(R - np.swapaxes(R, -1, -2))  # = 2 sin(t) a
    # atan2 keeps full precision at small angles, where arccos does not.
    theta = np.arctan2(np.linalg.norm(skew, axis=-1) / 2.0, (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0)
    sin = np.sin(theta)
    small = theta < _SMALL_ANGLE
    near_pi = theta > _SYMMETRIC_ANGLE
    regular = ~(small | near_pi)
    factor = np.where(small, 0.5 + theta * theta / 12.0, theta / (2.0 * np.where(regular, sin, 1.0)))
    omega = factor[..., None] * skew
    if np.any(near_pi):    # only where it applies: elsewhere 1 - cos t may be 0
        omega[near_pi] = _so3_log_near_pi(R[near_pi], theta[near_pi], skew[near_pi])
    return omega


def _so3_log_near_pi(R: np.ndarray, theta: np.ndarray, skew: np.ndarray) -> np.ndarray:
    """Rotation vector from the symmetric part of R (robust for angles near pi)."""
    # Symmetric part of R = cos(t) I + (1 - cos t) a a^T, solved for a a^T.
    cos = np.cos(theta)[..., None, None]
    S = ((R + np.swapaxes(R, -1, -2)) / 2.0 - cos * np.eye(3)) / (1.0 - cos)
    diag = np.diagonal(S, axis1=-2, axis2=-1)
    k = np.argmax(diag, axis=-1)
    column = np.take_along_axis(S, k[..., None, None].repeat(3, axis=-1), axis=-2)[..., 0, :]
    axis = column / np.linalg.norm(column, axis=-1, keepdims=True)
    # Sign from the skew part (2 sin t a), which is tiny but informative when t < pi.
    sign = np.where(np.sum(axis * skew, axis=-1) < 0, -1.0, 1.0)
    return (sign * theta)[..., None] * axis


def so3_left_jacobian(omega: object) -> np.ndarray:
    """Left Jacobian of SO(3) (..., 3, 3): ``J = I + (1-cos t)/t^2 W + (t-sin t)/t^3 W^2``.

    It maps the translation part of a twist to the translation of its
    exponential: ``se3_exp((v, omega))[:3, 3] = J(omega) v``.
    """
    omega = _vectors(omega, 3, "omega")
    _, B, C = _rodrigues_coefficients(np.linalg.norm(omega, axis=-1))
    W = hat(omega)
    return np.eye(3) + B[..., None, None] * W + C[..., None, None] * (W @ W)


def so3_right_jacobian(omega: object) -> np.ndarray:
    """Right Jacobian of SO(3) (..., 3, 3): ``J_r(omega) = J_l(-omega)``.

    For ``R(t) = R0 so3_exp(theta(t))`` the body angular velocity is
    ``omega_b = J_r(theta) dtheta/dt`` (``hat(omega_b) = R^T dR/dt``).
    """
    return so3_left_jacobian(-_vectors(omega, 3, "omega"))


def so3_left_jacobian_inv(omega: object) -> np.ndarray:
    """Inverse of :func:`so3_left_jacobian` (..., 3, 3) at rotation vectors ``omega`` (..., 3) [rad].

    ``J^-1 = I - W/2 + (1/t^2 - (1 + cos t)/(2 t sin t)) W^2``; series
    ``1/12 + t^2/720`` for the last coefficient near 0.
    """
    omega = _vectors(omega, 3, "omega")
    theta = np.linalg.norm(omega, axis=-1)
    small = theta < _SMALL_ANGLE
    t = np.where(small, 1.0, theta)
    D = np.where(
        small, 1.0 / 12.0 + theta * theta / 720.0,
        1.0 / (t * t) - (1.0 + np.cos(t)) / (2.0 * t * np.sin(t)),
    )
    W = hat(omega)
    return np.eye(3) - 0.5 * W + D[..., None, None] * (W @ W)


def se3_exp(xi: object) -> np.ndarray:
    """Poses (..., 4, 4) of twists ``xi = (v, omega)`` (..., 6).

    ``exp(hat(xi)) = [[so3_exp(omega), J(omega) v], [0, 1]]`` with ``J`` the
    left Jacobian (:func:`so3_left_jacobian`).

    Examples
    --------
    >>> se3_exp([1.0, 2.0, 3.0, 0.0, 0.0, 0.0])[:3, 3]
    array([1., 2., 3.])
    """
    xi = _vectors(xi, 6, "xi")
    T = np.zeros(xi.shape[:-1] + (4, 4))
    T[..., :3, :3] = so3_exp(xi[..., 3:])
    T[..., :3, 3] = (so3_left_jacobian(xi[..., 3:]) @ xi[..., :3, None])[..., 0]
    T[..., 3, 3] = 1.0
    return T


def se3_log(T: object) -> np.ndarray:
    """Twists ``(v, omega)`` (..., 6) of poses ``T`` (..., 4, 4); inverse of :func:`se3_exp`.

    ``omega = so3_log(R)``, ``v = J(omega)^-1 t``.
    """
    T = _matrices(T, 4, "T")
    if np.abs(T[..., 3, :] - [0.0, 0.0, 0.0, 1.0]).max(initial=0.0) > 1e-9:
        raise ValueError("T must be a rigid transform with last row (0, 0, 0, 1)")
    _check_rotations(T[..., :3, :3], "T[:3, :3]")
    omega = so3_log(T[..., :3, :3])
    v = (so3_left_jacobian_inv(omega) @ T[..., :3, 3, None])[..., 0]
    return np.concatenate([v, omega], axis=-1)


def invert_pose(T: object) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4): ``[[R^T, -R^T t], [0, 1]]``."""
    T = _matrices(T, 4, "T")
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ T[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def relative_pose(T_w_a: object, T_w_b: object) -> np.ndarray:
    """Pose of frame b in frame a, ``T_a_b = T_w_a^-1 T_w_b`` (..., 4, 4).

    ``T_a_b`` maps points of frame b to frame a: ``X_a = T_a_b X_b``.
    """
    return invert_pose(T_w_a) @ _matrices(T_w_b, 4, "T_w_b")


def transform_points(T_a_b: object, points_b: object) -> np.ndarray:
    """Points ``points_b`` (..., N, 3) of frame b expressed in frame a by the pose ``T_a_b`` (..., 4, 4):
    ``R_a_b X_b + t_a_b``, (..., N, 3)."""
    T_a_b = _matrices(T_a_b, 4, "T_a_b")
    points_b = _vectors(points_b, 3, "points_b")
    return points_b @ np.swapaxes(T_a_b[..., :3, :3], -1, -2) + T_a_b[..., None, :3, 3]


def interpolate_pose(T0: object, T1: object, alpha: float | np.ndarray) -> np.ndarray:
    """Geodesic interpolation on SE(3): ``T0 se3_exp(alpha se3_log(T0^-1 T1))``.

    ``alpha = 0`` gives ``T0``, ``alpha = 1`` gives ``T1``; the camera moves
    with a constant body twist in between (a screw motion). ``alpha`` may be
    an array broadcasting against the batch shape of the poses.
    """
    T0 = _matrices(T0, 4, "T0")
    T1 = _matrices(T1, 4, "T1")
    alpha = np.asarray(alpha, dtype=np.float64)
    xi = se3_log(relative_pose(T0, T1))
    return T0 @ se3_exp(alpha[..., None] * xi)


def interpolate_poses(
    times_us: object, poses: object, query_times_us: object
) -> np.ndarray:
    """Poses at ``query_times_us`` (Q,) from a sampled trajectory, shape (Q, 4, 4).

    Parameters
    ----------
    times_us : array_like, shape (M,)
        Strictly increasing sample times (int64 µs, or any numbers).
    poses : array_like, shape (M, 4, 4)
        ``T_w_c`` at those times.
    query_times_us : array_like, shape (Q,)
        Times inside ``[times_us[0], times_us[-1]]``; outside raises ``ValueError``.

    Each query is interpolated geodesically (:func:`interpolate_pose`) between
    the two samples around it; the differences of the times are taken in
    int64 before conversion to float, so absolute µs keep their precision.
    """
    times = np.asarray(times_us)
    poses = _matrices(poses, 4, "poses")
    query = np.asarray(query_times_us)
    if times.ndim != 1 or len(times) < 1:
        raise ValueError(f"times_us must have shape (M,) with M >= 1, got {times.shape}")
    if poses.shape != (len(times), 4, 4):
        raise ValueError(f"poses must have shape ({len(times)}, 4, 4), got {poses.shape}")
    if query.ndim != 1:
        raise ValueError(f"query_times_us must have shape (Q,), got {query.shape}")
    for name, values in (("times_us", times), ("query_times_us", query)):
        if values.dtype.kind not in "iuf" or (values.dtype.kind == "f" and not np.isfinite(values).all()):
            raise ValueError(f"{name} must hold finite numbers, got dtype {values.dtype}")
    if len(times) > 1 and not np.all(np.diff(times) > 0):
        raise ValueError("times_us must be strictly increasing")
    if query.size and (query.min() < times[0] or query.max() > times[-1]):
        raise ValueError(
            f"query_times_us must lie in [{times[0]}, {times[-1]}], "
            f"got [{query.min()}, {query.max()}]"
        )
    if len(times) == 1:
        return np.repeat(poses, len(query), axis=0)
    i = np.clip(np.searchsorted(times, query, side="right") - 1, 0, len(times) - 2)
    alpha = (query - times[i]).astype(np.float64) / (times[i + 1] - times[i]).astype(np.float64)
    return interpolate_pose(poses[i], poses[i + 1], alpha)
