"""Refinement of the se3 motion on a local objective: the contrast of patches, each with its own depth.

The patch-flow initialiser (:mod:`cmax.fitting.patch_flow`) fits constant
flows to patches, and a constant flow is a biased summary of a patch whose
flow varies (depth edges, the divergence of a forward motion, the rotation
field across ~70 px): on the tuning windows those flows are 5-15% off, which
costs 10-30 deg of translation direction. Here the events of each patch are
warped by the exact se3 warp of :mod:`cmax.warp` with the shared twist
``(v, omega)`` and one inverse depth ``rho_p`` per patch, and the objective is
the sum over patches of each patch's IWE variance normalised by its unwarped
value:

    J(v, omega, rho) = sum_p Var(I_p(v, omega, rho_p)) / Var(I_p(0))

Every patch weighs the same, whatever its events (the global contrast is ruled
by the densest regions and peaks 16-60 deg off the true direction on some
windows), and each patch's depth is free, so a wrong direction cannot be
hidden by one depth grid. The depths start from a sweep per patch (the best of
``rho_candidates`` inverse depths for the start motion), then direction,
rotation and depths are solved together by L-BFGS-B with ``|v|`` held.

References
----------
G. Gallego, H. Rebecq, D. Scaramuzza, "A unifying contrast maximization
framework for event cameras", CVPR 2018 (the se3 + depth warp). S. Shiba,
Y. Aoki, G. Gallego, "Secrets of event-based optical flow", ECCV 2022 (patch-wise
contrast with a shared motion).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from cmax.fitting.patch_flow import Patches, make_patches
from cmax.objectives import variance
from cmax.warp import warp_se3

__all__ = ["LocalMotionObjective", "refine_motion_local"]

#: Direction parameters are ``DIRECTION_SCALE * v / |v|`` so that a step of one
#: unit moves the direction by ~6 deg, like one pixel of the other parameters.
DIRECTION_SCALE = 10.0


@dataclass(frozen=True, eq=False)
class LocalMotionObjective:
    """The patch-wise contrast ``J(v, omega, rho)`` of a window (see the module docstring).

    Parameters live in pixels of displacement over the window: ``p = (DIRECTION_SCALE
    v / speed (3), omega T f (3), rho speed T f (P))``.

    Attributes
    ----------
    patches : Patches
    rays : Tensor (M, 3)
        ``K^-1 (x, y, 1)`` of the patches' events.
    K : Tensor (3, 3)
    speed : float
        ``|v|`` [m/s].
    omega_scale, rho_scale : float
        Pixels over the window per rad/s and per 1/m.
    sigma : float
        IWE blur [px].
    base : Tensor (P,)
        Variance of each patch's unwarped IWE.
    """

    patches: Patches
    rays: torch.Tensor
    K: torch.Tensor
    speed: float
    omega_scale: float
    rho_scale: float
    sigma: float
    base: torch.Tensor

    @classmethod
    def build(cls, w, patches: Patches, speed: float) -> "LocalMotionObjective":
        """The objective of ``patches`` of window ``w`` (a :class:`cmax.fitting.stages.Window`) at ``speed`` [m/s]."""
        ev, sigma = w.ev, w.settings.sigma
        rays = torch.stack([patches.x, patches.y, torch.ones_like(patches.x)], -1) @ torch.linalg.inv(ev.K).T
        with torch.no_grad():
            base = variance(patches.images(patches.x, patches.y, sigma)).clamp(min=1e-12)
        return cls(patches, rays, ev.K, float(speed), w.T * w.focal, float(speed) * w.T * w.focal, sigma, base)

    def params(self, v: np.ndarray, omega: np.ndarray, rho: np.ndarray) -> np.ndarray:
        """Parameter vector (6 + P,) of ``v`` (3,) [m/s], ``omega`` (3,) [rad/s], ``rho`` (P,) [1/m]."""
        return np.r_[DIRECTION_SCALE * np.asarray(v) / np.linalg.norm(v), np.asarray(omega) * self.omega_scale,
                     np.asarray(rho) * self.rho_scale]

    def motion(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``v`` (3,) [m/s, norm ``speed``], ``omega`` (3,) [rad/s], ``rho`` (P,) [1/m] of parameters ``p``."""
        return self.speed * p[:3] / np.linalg.norm(p[:3]), p[3:6] / self.omega_scale, p[6:] / self.rho_scale

    def values(self, p: torch.Tensor) -> torch.Tensor:
        """Normalised contrast (P,) of each patch for parameters ``p`` (6 + P,); differentiable."""
        dtype = self.rays.dtype
        u = p[:3] / DIRECTION_SCALE
        v = self.speed * u / torch.sqrt((u * u).sum() + 1e-12)
        rho = (p[6:] / self.rho_scale)[self.patches.patch]
        return self.contrast_at(v.to(dtype), (p[3:6] / self.omega_scale).to(dtype), rho.to(dtype))

    def contrast_at(self, v: torch.Tensor, omega: torch.Tensor, rho_events: torch.Tensor) -> torch.Tensor:
        """Normalised contrast (P,) of each patch for ``v`` (3,) [m/s], ``omega`` (3,) [rad/s] and any
        per-event inverse depth (M,) [1/m] (e.g. the ground truth, in ``benchmarks/cmax_limits.py``)."""
        x, y = warp_se3(self.rays, self.patches.dt, v, omega, rho_events, self.K)
        return variance(self.patches.images(x, y, self.sigma)) / self.base

    def sweep_rho(self, v: np.ndarray, omega: np.ndarray, candidates: np.ndarray) -> np.ndarray:
        """Best inverse depth (P,) [1/m] of each patch among ``candidates`` (C,) [1/m] for a fixed motion."""
        best = np.full(self.patches.count, -np.inf)
        rho = np.full(self.patches.count, float(candidates[0]))
        with torch.no_grad():
            for c in candidates:
                p = torch.from_numpy(self.params(v, omega, np.full(self.patches.count, c)))
                values = self.values(p).double().numpy()
                better = values > best
                best[better], rho[better] = values[better], c
        return rho


def refine_motion_local(w, v: np.ndarray, omega: np.ndarray, speed: float, *, grid: tuple[int, int] = (6, 8),
                        min_events: int = 100, max_events: int = 20_000, margin: float = 0.3,
                        rho_candidates: int = 24, iterations: int = 60, hold_omega: bool = False,
                        more_starts: Sequence[tuple[np.ndarray, np.ndarray]] = ()) -> tuple[np.ndarray, np.ndarray]:
    """Refine ``v`` (3,) [m/s] and ``omega`` (3,) [rad/s] on the patch-wise contrast; ``|v|`` stays ``speed``.

    Parameters
    ----------
    w : cmax.fitting.stages.Window
    v, omega : ndarray (3,)
        The start (e.g. :func:`cmax.fitting.patch_flow.motion_from_flows`).
    speed : float
        ``|v|`` [m/s].
    grid : (rows, cols)
        Patches (6 x 8 on a 346 x 260 sensor: 43 x 43 px; 4 x 5 patches hold
        too many depths each, 8 x 10 too few events).
    min_events, max_events, margin
        As in :func:`cmax.fitting.patch_flow.make_patches`.
    rho_candidates : int
        Inverse depths of the per-patch start sweep, log-uniform over the window's ``depth_range``.
    iterations : int
        L-BFGS-B iterations.
    hold_omega : bool
        Keep ``omega`` as given (a known rotation): only the direction and the depths move.
    more_starts : sequence of (v, omega)
        Further starts, each refined the same way; the refined motion with the
        highest patch-wise contrast wins (the objective is the same for all, so
        this is a multi-start of one optimisation).

    Returns
    -------
    v, omega : ndarray (3,)
        The start itself when fewer than 4 patches hold ``min_events``.
    """
    patches = make_patches(w, grid=grid, min_events=min_events, max_events=max_events, margin=margin)
    if patches is None or patches.count < 4:
        return np.asarray(v, float), np.asarray(omega, float)
    objective = LocalMotionObjective.build(w, patches, speed)
    near, far = w.settings.depth_range
    candidates = np.exp(np.linspace(np.log(1.0 / far), np.log(1.0 / near), rho_candidates))
    best = None
    for start_v, start_omega in [(v, omega), *more_starts]:
        value, v1, omega1 = _refine_from(w, objective, np.asarray(start_v, float), np.asarray(start_omega, float),
                                         candidates, iterations, hold_omega)
        if best is None or value < best[0]:
            best = (value, v1, omega1)
    return best[1], best[2]


def _refine_from(w, objective: LocalMotionObjective, v: np.ndarray, omega: np.ndarray, candidates: np.ndarray,
                 iterations: int, hold_omega: bool) -> tuple[float, np.ndarray, np.ndarray]:
    """One L-BFGS-B refinement from ``(v, omega)``: final ``-J``, ``v`` (3,), ``omega`` (3,)."""
    from scipy.optimize import minimize

    near, far = w.settings.depth_range
    rho0 = objective.sweep_rho(v, omega, candidates)
    x0 = objective.params(v, omega, rho0)
    P, s_o, s_r = objective.patches.count, objective.omega_scale, objective.rho_scale
    lower = np.r_[np.full(3, -2 * DIRECTION_SCALE), np.full(3, -6 * s_o), np.full(P, s_r / far)]
    upper = np.r_[np.full(3, 2 * DIRECTION_SCALE), np.full(3, 6 * s_o), np.full(P, s_r / near)]
    if hold_omega:  # equal bounds: L-BFGS-B keeps these parameters fixed
        lower[3:6] = upper[3:6] = x0[3:6]

    def fun_and_grad(x: np.ndarray) -> tuple[float, np.ndarray]:
        p = torch.tensor(x, dtype=torch.float64, requires_grad=True)
        value = -objective.values(p).sum()
        (grad,) = torch.autograd.grad(value, p)
        return float(value.detach()), grad.numpy().copy()

    result = minimize(fun_and_grad, np.clip(x0, lower, upper), jac=True, method="L-BFGS-B",
                      bounds=list(zip(lower, upper)), options={"maxiter": iterations})
    w.iterations += int(result.nit)
    w.evaluations += int(result.nfev)
    v1, omega1, _ = objective.motion(result.x)
    return float(result.fun), v1, omega1
