"""Smooth 6-DoF camera trajectories with analytic velocities.

A trajectory gives the pose ``T_w_c(t)`` (4x4, camera-to-world) and the body
twist ``xi(t) = (v, omega)`` in the camera frame, defined by
``d/dt T_w_c = T_w_c hat(xi)``, i.e. ``v = R^T dp/dt`` and
``hat(omega) = R^T dR/dt``. Times are float seconds from the start of the
sequence.

:class:`SinusoidalTrajectory` uses sums of sinusoids (smooth, bounded, with
closed-form derivatives):

* position ``p(t) = p0 + velocity * t + sum_k A_k sin(2 pi f_k t + phi_k)``;
* orientation ``R(t) = R0 so3_exp(theta(t))`` with
  ``theta(t) = rate * t + sum_k B_k sin(2 pi g_k t + psi_k)`` a rotation
  vector in the frame of ``R0``; the body angular velocity is
  ``omega = J_r(theta) dtheta/dt`` (right Jacobian of SO(3)), valid while
  ``|theta| < 2 pi``.

Its speed bounds follow from the amplitudes:
``|dp/dt| <= |velocity| + sum_k 2 pi f_k |A_k|``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from cmax.geometry import so3_exp, so3_right_jacobian

__all__ = ["Trajectory", "SinusoidalTrajectory", "look_at_rotation"]


@runtime_checkable
class Trajectory(Protocol):
    """Anything with ``pose(t_s) -> (4, 4)`` and ``twist(t_s) -> (6,)``."""

    def pose(self, t_s: float) -> np.ndarray:
        """``T_w_c`` (4, 4) float64, the camera-to-world pose at ``t_s`` [s]."""

    def twist(self, t_s: float) -> np.ndarray:
        """Body twist ``(v [m/s], omega [rad/s])`` (6,) float64 in the camera frame at ``t_s`` [s]."""


def look_at_rotation(forward, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``R_w_c`` (3, 3) of a camera looking along ``forward`` (world) with image-up near ``up``.

    Camera axes (OpenCV): x right, y down, z forward.
    """
    z = np.asarray(forward, dtype=np.float64)
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("forward must not be parallel to up")
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def _array(value, shape: tuple[int, ...], name: str) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} must be finite")
    return array


@dataclass(frozen=True, eq=False)
class SinusoidalTrajectory:
    """Pose and twist from sums of sinusoids (see the module docstring for the formulas).

    Parameters
    ----------
    R0 : ndarray, shape (3, 3)
        Orientation ``R_w_c`` at ``theta = 0``.
    p0 : ndarray, shape (3,)
        Position of the camera centre at t = 0 offset [m] (world).
    velocity : ndarray, shape (3,)
        Constant drift velocity [m/s] (world).
    position_terms : ndarray, shape (K, 7)
        Rows ``(f_k [Hz], A_k (3,) [m], phi_k (3,) [rad])``.
    rate : ndarray, shape (3,)
        Constant rate of the rotation vector [rad/s] (in the frame of R0).
    rotation_terms : ndarray, shape (J, 7)
        Rows ``(g_j [Hz], B_j (3,) [rad], psi_j (3,) [rad])``.
    """

    R0: np.ndarray
    p0: np.ndarray
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    position_terms: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))
    rate: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rotation_terms: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))

    def __post_init__(self) -> None:
        R0 = _array(self.R0, (3, 3), "R0")
        if not np.allclose(R0.T @ R0, np.eye(3), atol=1e-9) or np.linalg.det(R0) < 0:
            raise ValueError("R0 must be a rotation matrix")
        object.__setattr__(self, "R0", R0)
        object.__setattr__(self, "p0", _array(self.p0, (3,), "p0"))
        object.__setattr__(self, "velocity", _array(self.velocity, (3,), "velocity"))
        object.__setattr__(self, "rate", _array(self.rate, (3,), "rate"))
        for name in ("position_terms", "rotation_terms"):
            terms = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1, 7)
            object.__setattr__(self, name, _array(terms, (len(terms), 7), name))

    # -- components -------------------------------------------------------------------
    @staticmethod
    def _sum(terms: np.ndarray, t: np.ndarray, order: int) -> np.ndarray:
        """Sum of ``A sin(2 pi f t + phi)`` (order 0) or its time derivative (order 1); (N, 3)."""
        if not len(terms):
            return np.zeros((len(t), 3))
        f, A, phi = terms[:, 0], terms[:, 1:4], terms[:, 4:7]
        arg = 2 * np.pi * f[None, :, None] * t[:, None, None] + phi[None]
        if order == 0:
            return (A[None] * np.sin(arg)).sum(axis=1)
        return (A[None] * (2 * np.pi * f)[None, :, None] * np.cos(arg)).sum(axis=1)

    def _times(self, t_s) -> tuple[np.ndarray, bool]:
        t = np.asarray(t_s, dtype=np.float64)
        if t.ndim > 1 or not np.isfinite(t).all():
            raise ValueError(f"t_s must be a finite scalar or (N,) array of seconds, got shape {t.shape}")
        return np.atleast_1d(t), t.ndim == 0

    def positions(self, t_s) -> np.ndarray:
        """Camera centres (N, 3) [m] in the world frame."""
        t, _ = self._times(t_s)
        return self.p0 + self.velocity * t[:, None] + self._sum(self.position_terms, t, 0)

    def rotation_vectors(self, t_s) -> np.ndarray:
        """theta(t) (N, 3) [rad]."""
        t, _ = self._times(t_s)
        return self.rate * t[:, None] + self._sum(self.rotation_terms, t, 0)

    # -- interface --------------------------------------------------------------------
    def pose(self, t_s) -> np.ndarray:
        """``T_w_c`` (4, 4) at a time, or (N, 4, 4) at an array of times [s]."""
        t, scalar = self._times(t_s)
        T = np.zeros((len(t), 4, 4))
        T[:, :3, :3] = self.R0 @ so3_exp(self.rotation_vectors(t))
        T[:, :3, 3] = self.positions(t)
        T[:, 3, 3] = 1.0
        return T[0] if scalar else T

    def twist(self, t_s) -> np.ndarray:
        """Body twist ``(v [m/s], omega [rad/s])`` (6,) at a time, or (N, 6), camera frame."""
        t, scalar = self._times(t_s)
        theta = self.rotation_vectors(t)
        R = self.R0 @ so3_exp(theta)
        p_dot = self.velocity + self._sum(self.position_terms, t, 1)
        theta_dot = self.rate + self._sum(self.rotation_terms, t, 1)
        v = np.einsum("nji,nj->ni", R, p_dot)  # R^T p_dot
        omega = np.einsum("nij,nj->ni", so3_right_jacobian(theta), theta_dot)
        xi = np.concatenate([v, omega], axis=1)
        return xi[0] if scalar else xi

    def speed_bounds(self) -> tuple[float, float]:
        """Upper bounds of ``|v|`` [m/s] and ``|dtheta/dt|`` [rad/s] from the amplitudes."""
        def bound(drift: np.ndarray, terms: np.ndarray) -> float:
            return float(np.linalg.norm(drift) + np.sum(2 * np.pi * terms[:, 0] * np.linalg.norm(terms[:, 1:4], axis=1)))
        return bound(self.velocity, self.position_terms), bound(self.rate, self.rotation_terms)

    @classmethod
    def random(
        cls, rng: np.random.Generator, *, R0: np.ndarray, p0, velocity=(0.0, 0.0, 0.0),
        position_amplitude=(0.0, 0.0, 0.0), rotation_amplitude=(0.0, 0.0, 0.0),
        frequencies: tuple[float, float] = (0.1, 0.5), terms: int = 3,
    ) -> "SinusoidalTrajectory":
        """A random smooth trajectory: ``terms`` sinusoids per part with frequencies in ``frequencies`` [Hz].

        ``position_amplitude`` [m] and ``rotation_amplitude`` [rad] (3,) bound
        the total oscillation per axis (split randomly among the terms);
        position axes are world axes, rotation axes those of ``R0``.
        """
        def make(amplitude) -> np.ndarray:
            amplitude = np.asarray(amplitude, float)
            if not amplitude.any():
                return np.zeros((0, 7))
            f = rng.uniform(*frequencies, terms)
            weights = rng.dirichlet(np.ones(terms), size=3).T  # (terms, 3), columns sum to 1
            return np.column_stack([f, weights * amplitude, rng.uniform(0, 2 * np.pi, (terms, 3))])

        return cls(R0=R0, p0=np.asarray(p0, float), velocity=np.asarray(velocity, float),
                   position_terms=make(position_amplitude), rotation_terms=make(rotation_amplitude))
