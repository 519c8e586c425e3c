"""Tests of cmax.geometry: SE(3)/so(3) maps and pose interpolation."""
import numpy as np
import pytest

from cmax import geometry as g


def _random_twists(n: int, seed: int = 0, scale: float = 1.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xi = rng.normal(size=(n, 6)) * scale
    # Keep rotation angles below pi so that log(exp(xi)) = xi.
    angles = np.linalg.norm(xi[:, 3:], axis=1, keepdims=True)
    xi[:, 3:] *= np.minimum(1.0, 3.0 / np.maximum(angles, 1e-12))
    return xi


def test_hat_vee_round_trip_and_cross_product():
    w = np.array([0.3, -1.2, 2.0])
    u = np.array([1.0, 2.0, -0.5])
    np.testing.assert_allclose(g.hat(w) @ u, np.cross(w, u))
    np.testing.assert_allclose(g.vee(g.hat(w)), w)
    xi = np.arange(6.0)
    X = g.hat(xi)
    assert X.shape == (4, 4)
    np.testing.assert_allclose(X[:3, 3], xi[:3])
    np.testing.assert_allclose(g.vee(X), xi)
    assert g.hat(np.zeros((5, 2, 3))).shape == (5, 2, 3, 3)


def test_so3_exp_rotation_about_z_closed_form():
    for angle in (0.0, 1e-9, 0.3, np.pi / 2, 3.0):
        R = g.so3_exp([0.0, 0.0, angle])
        c, s = np.cos(angle), np.sin(angle)
        np.testing.assert_allclose(R, [[c, -s, 0], [s, c, 0], [0, 0, 1]], atol=1e-15)


def test_se3_exp_screw_about_z_closed_form():
    # Rotation about z by a while translating with v = (0, 0, h): a helix, t = (0, 0, h).
    T = g.se3_exp([0.0, 0.0, 2.0, 0.0, 0.0, np.pi / 2])
    np.testing.assert_allclose(T[:3, 3], [0.0, 0.0, 2.0], atol=1e-15)
    # v along x with rotation about z by pi/2: J v = (sin a / a, (1 - cos a)/a, 0).
    a = np.pi / 2
    T = g.se3_exp([1.0, 0.0, 0.0, 0.0, 0.0, a])
    np.testing.assert_allclose(T[:3, 3], [np.sin(a) / a, (1 - np.cos(a)) / a, 0.0], atol=1e-15)
    np.testing.assert_allclose(T[3], [0, 0, 0, 1])


def test_exp_log_round_trip():
    xi = _random_twists(200)
    T = g.se3_exp(xi)
    np.testing.assert_allclose(g.se3_log(T), xi, atol=1e-10)
    R = T[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(g.so3_log(g.so3_exp(xi[:, 3:])), xi[:, 3:], atol=1e-10)


def test_small_angle_stability():
    for angle in (0.0, 1e-12, 1e-9, 1e-6, 1e-5, 1.1e-4, 1e-3):
        w = np.array([1.0, -2.0, 0.5]) / np.sqrt(5.25) * angle
        xi = np.concatenate([[0.1, 0.2, -0.3], w])
        T = g.se3_exp(xi)
        assert np.isfinite(T).all()
        np.testing.assert_allclose(g.se3_log(T), xi, rtol=1e-9, atol=1e-15)
        # First order: R = I + hat(w).
        np.testing.assert_allclose(T[:3, :3], np.eye(3) + g.hat(w), atol=angle**2)
        np.testing.assert_allclose(
            g.so3_left_jacobian(w) @ g.so3_left_jacobian_inv(w), np.eye(3), atol=1e-12
        )


def test_log_near_pi():
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    for angle in (np.pi - 1e-2, np.pi - 1e-5, np.pi):
        w = angle * axis
        out = g.so3_log(g.so3_exp(w))
        if angle < np.pi:
            np.testing.assert_allclose(out, w, atol=1e-8)
        else:  # +axis and -axis are the same rotation at pi
            assert min(np.abs(out - w).max(), np.abs(out + w).max()) < 1e-8


def test_right_jacobian_gives_body_angular_velocity():
    theta = np.array([0.4, -0.7, 1.1])
    dtheta = np.array([0.3, 0.2, -0.5])
    h = 1e-6
    R0, R1 = g.so3_exp(theta - h * dtheta), g.so3_exp(theta + h * dtheta)
    omega_numeric = g.vee(g.so3_exp(theta).T @ (R1 - R0) / (2 * h))
    np.testing.assert_allclose(g.so3_right_jacobian(theta) @ dtheta, omega_numeric, atol=1e-8)


def test_relative_and_inverse_pose():
    T_w_a, T_w_b = g.se3_exp(_random_twists(2, seed=3))
    T_a_b = g.relative_pose(T_w_a, T_w_b)
    np.testing.assert_allclose(T_w_a @ T_a_b, T_w_b, atol=1e-12)
    np.testing.assert_allclose(g.invert_pose(T_w_a) @ T_w_a, np.eye(4), atol=1e-12)
    points_b = np.random.default_rng(1).normal(size=(7, 3))
    points_w = g.transform_points(T_w_b, points_b)
    np.testing.assert_allclose(g.transform_points(T_a_b, points_b), g.transform_points(g.invert_pose(T_w_a), points_w), atol=1e-12)


def test_interpolate_pose_endpoints_and_midpoint_of_pure_rotation():
    T0 = g.se3_exp([1.0, 2.0, 3.0, 0.1, 0.2, 0.3])
    T1 = T0 @ g.se3_exp([0.0, 0.0, 0.0, 0.0, 0.0, 1.2])
    np.testing.assert_allclose(g.interpolate_pose(T0, T1, 0.0), T0, atol=1e-12)
    np.testing.assert_allclose(g.interpolate_pose(T0, T1, 1.0), T1, atol=1e-12)
    mid = g.interpolate_pose(T0, T1, 0.5)
    np.testing.assert_allclose(mid, T0 @ g.se3_exp([0, 0, 0, 0, 0, 0.6]), atol=1e-12)
    np.testing.assert_allclose(mid[:3, 3], T0[:3, 3], atol=1e-12)  # pure rotation: centre stays


def test_interpolate_poses_vectorized():
    times = np.array([0, 1_000_000, 3_000_000], dtype=np.int64) + 1_700_000_000_000_000
    xi = _random_twists(3, seed=5, scale=0.5)
    poses = g.se3_exp(xi)
    query = times[[0, 0, 1, 2]] + np.array([0, 500_000, 1_000_000, 0])
    out = g.interpolate_poses(times, poses, query)
    assert out.shape == (4, 4, 4)
    np.testing.assert_allclose(out[0], poses[0], atol=1e-12)
    np.testing.assert_allclose(out[1], g.interpolate_pose(poses[0], poses[1], 0.5), atol=1e-12)
    np.testing.assert_allclose(out[2], g.interpolate_pose(poses[1], poses[2], 0.5), atol=1e-12)
    np.testing.assert_allclose(out[3], poses[2], atol=1e-12)


def test_twist_integration_matches_exponential():
    xi = np.array([0.5, -0.2, 1.0, 0.3, 0.1, -0.4])
    T = np.eye(4)
    for _ in range(1000):
        T = T @ g.se3_exp(xi * 1e-3)
    np.testing.assert_allclose(T, g.se3_exp(xi), atol=1e-12)


@pytest.mark.parametrize(
    "call",
    [
        lambda: g.hat(np.zeros(4)),
        lambda: g.so3_exp(np.zeros((2, 2))),
        lambda: g.se3_exp(np.zeros(5)),
        lambda: g.se3_log(np.eye(3)),
        lambda: g.interpolate_poses([0, 1], np.stack([np.eye(4)] * 2), [2]),
        lambda: g.interpolate_poses([1, 0], np.stack([np.eye(4)] * 2), [0]),
        lambda: g.interpolate_poses([0, 1], np.eye(4), [0]),
    ],
)
def test_bad_input_raises(call):
    with pytest.raises(ValueError):
        call()


def test_so3_log_of_float32_rotations_near_pi_is_accurate():
    """``theta / (2 sin theta)`` of the skew part amplified the rounding of a float32 R by 1 / sin: at
    pi - 1.001e-3 (just outside the old near-pi branch) the angle was 4.9e-5 rad off (scipy: 1.2e-8). The axis
    now comes from the symmetric part above 2 rad."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(5)
    for angle in (2.5, np.pi - 0.02, np.pi - 1.001e-3, np.pi - 1e-5):
        for _ in range(50):
            axis = rng.normal(size=3)
            truth = axis / np.linalg.norm(axis) * angle
            R32 = Rotation.from_rotvec(truth).as_matrix().astype(np.float32)
            error = (Rotation.from_rotvec(g.so3_log(R32)).inv() * Rotation.from_rotvec(truth)).magnitude()
            assert error < 5e-7, (angle, error)


def test_so3_log_of_a_batch_mixing_the_identity_and_a_half_turn_warns_nothing():
    """The near-pi formula divided by 1 - cos t for every rotation of a batch that held one near pi: 0 / 0,
    'invalid value encountered in divide', for the identity beside it."""
    import warnings

    omega = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, np.pi - 1e-4], [1e-6, 0.0, 0.0], [0.0, 2.5, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_allclose(g.so3_log(g.so3_exp(omega)), omega, atol=1e-12)
