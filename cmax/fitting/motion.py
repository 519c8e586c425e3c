"""Refinement of the se3 motion on a local objective: the contrast of patches, each with its own depth.

The patch-flow initialiser (:mod:`cmax.fitting.patch_flow`) fits constant
flows to patches, and a constant flow is a biased summary of a patch whose
flow varies (depth edges, the divergence of a forward motion, the rotation
field across a patch). Here the events of each patch are
warped by the exact se3 warp of :mod:`cmax.warp` with the shared twist
``(v, omega)`` and one inverse depth ``rho_p`` per patch, and the objective is
the sum over patches of each patch's IWE variance normalised by its unwarped
value (the contrast core's :class:`cmax.contrast.patches.PatchMotionContrast`):

    J(v, omega, rho) = sum_p Var(I_p(v, omega, rho_p)) / Var(I_p(0))

Every patch weighs the same, whatever its events (the global contrast is ruled
by the densest regions), and each patch's depth is free, so a wrong direction cannot be
hidden by one depth grid. The depths start from a sweep per patch (the best of
``rho_candidates`` inverse depths for the start motion), then direction,
rotation and depths are solved together through :func:`cmax.fitting.solvers.solve` with ``|v|``
held (normalised for L-BFGS-B and Adam, an equality constraint for IPOPT).

References
----------
G. Gallego, H. Rebecq, D. Scaramuzza, "A unifying contrast maximization
framework for event cameras", CVPR 2018 (the se3 + depth warp). S. Shiba,
Y. Aoki, G. Gallego, "Secrets of event-based optical flow", ECCV 2022 (patch-wise
contrast with a shared motion).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import torch

from cmax.contrast.patches import Patches, PatchMotionContrast
from cmax.fitting.patch_flow import make_patches
from cmax.fitting.settings import RefineSettings
from cmax.fitting.solvers import GradientLoss, Solver, SolveResult, solve, torch_fun_and_grad

__all__ = ["LocalMotionObjective", "RefineOutcome", "refine_motion_local", "omega_on_bound", "strided_argmax",
           "coarse_rows", "rows_scored", "sweep_stride"]


@dataclass(frozen=True, eq=False)
class LocalMotionObjective:
    """The patch-wise contrast ``J(v, omega, rho)`` of a window in the refinement's parameters (see the
    module docstring); the contrast itself is :class:`cmax.contrast.patches.PatchMotionContrast`.

    Parameters live in pixels of displacement over the window: ``p = (direction_scale
    v / speed (3), omega T f (3), rho speed T f (P))``.

    Attributes
    ----------
    contrast : PatchMotionContrast
        The patches, their rays, ``K``, the blur and each patch's unwarped variance.
    speed : float
        ``|v|`` [m/s].
    omega_scale, rho_scale : float
        Pixels over the window per rad/s and per 1/m.
    unit_norm : bool
        ``v = speed u / |u|`` (True) or ``speed u`` for solvers that hold ``|u| = direction_scale``.
    direction_scale : float
        :attr:`cmax.fitting.RefineSettings.direction_scale`.
    """

    contrast: PatchMotionContrast
    speed: float
    omega_scale: float
    rho_scale: float
    unit_norm: bool = True
    direction_scale: float = 10.0

    @classmethod
    def build(cls, w, patches: Patches, speed: float, *, unit_norm: bool = True,
              direction_scale: float | None = None) -> "LocalMotionObjective":
        """The objective of ``patches`` of window ``w`` (a :class:`cmax.fitting.window.Window`) at ``speed``
        [m/s]; ``unit_norm`` False for solvers that hold ``|u| = direction_scale`` as a constraint;
        ``direction_scale`` None: ``w.settings.refine.direction_scale``."""
        contrast = PatchMotionContrast.build(patches, w.ev.K, w.settings.sigma)
        scale = w.settings.refine.direction_scale if direction_scale is None else float(direction_scale)
        return cls(contrast, float(speed), w.T * w.focal, float(speed) * w.T * w.focal, unit_norm, scale)

    @property
    def patches(self) -> Patches:
        return self.contrast.patches

    @property
    def rays(self) -> torch.Tensor:
        """``K^-1 (x, y, 1)`` (M, 3) of the patches' events."""
        return self.contrast.rays

    @property
    def K(self) -> torch.Tensor:
        return self.contrast.K

    def params(self, v: np.ndarray, omega: np.ndarray, rho: np.ndarray) -> np.ndarray:
        """Parameter vector (6 + P,) of ``v`` (3,) [m/s], ``omega`` (3,) [rad/s], ``rho`` (P,) [1/m]."""
        return np.r_[self.direction_scale * np.asarray(v) / np.linalg.norm(v), np.asarray(omega) * self.omega_scale,
                     np.asarray(rho) * self.rho_scale]

    def motion(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``v`` (3,) [m/s, norm ``speed``], ``omega`` (3,) [rad/s], ``rho`` (P,) [1/m] of parameters ``p``."""
        return self.speed * p[:3] / np.linalg.norm(p[:3]), p[3:6] / self.omega_scale, p[6:] / self.rho_scale

    def values(self, p: torch.Tensor) -> torch.Tensor:
        """Normalised contrast (P,) of each patch for parameters ``p`` (6 + P,); differentiable."""
        dtype = self.rays.dtype
        u = p[:3] / self.direction_scale
        v = self.speed * u / torch.sqrt((u * u).sum() + 1e-12) if self.unit_norm else self.speed * u
        rho = (p[6:] / self.rho_scale)[self.patches.patch]
        return self.contrast_at(v.to(dtype), (p[3:6] / self.omega_scale).to(dtype), rho.to(dtype))

    def fun_and_grad(self, p: np.ndarray) -> tuple[float, np.ndarray]:
        """``(-sum(values(p)), its gradient (6 + P,))`` for parameters ``p`` (6 + P,) float64: the
        refinement's loss. With compiled patches (:attr:`cmax.contrast.patches.Patches.compiled`) the
        kernels' own gradients are chained through the parameterisation here (no autograd), else torch's
        autograd of :meth:`values`; both give the same value and gradient to float rounding."""
        if not self.patches.compiled:
            return torch_fun_and_grad(lambda q: -self.values(q).sum())(p)
        p = np.asarray(p, dtype=np.float64)
        u = p[:3] / self.direction_scale
        if self.unit_norm:
            norm = math.sqrt(float(u @ u) + 1e-12)
            v = self.speed * u / norm
        else:
            v = self.speed * u
        patch = self.patches.kernel_arrays[0]
        value, grad_v, grad_omega, grad_rho = self.contrast.sum_and_gradients(
            v, p[3:6] / self.omega_scale, (p[6:] / self.rho_scale)[patch])
        if self.unit_norm:   # d(speed u / |u|)/du = speed (I - u u^T / |u|^2) / |u|
            grad_u = self.speed * (grad_v - u * float(u @ grad_v) / norm ** 2) / norm
        else:
            grad_u = self.speed * grad_v
        grad_rho_patches = np.bincount(patch, grad_rho, minlength=self.patches.count)
        return -value, -np.r_[grad_u / self.direction_scale, grad_omega / self.omega_scale,
                              grad_rho_patches / self.rho_scale]

    def contrast_at(self, v: torch.Tensor, omega: torch.Tensor, rho_events: torch.Tensor) -> torch.Tensor:
        """Normalised contrast (P,) of each patch for ``v`` (3,) [m/s], ``omega`` (3,) [rad/s] and any
        per-event inverse depth (M,) [1/m] (e.g. the ground truth, in ``benchmarks/cmax_limits.py``)."""
        return self.contrast(v, omega, rho_events)

    def sweep_rho(self, v: np.ndarray, omega: np.ndarray, candidates: np.ndarray, stride: int = 1) -> np.ndarray:
        """Best inverse depth (P,) [1/m] of each patch among ``candidates`` (C,) [1/m] for a fixed motion
        (the first best on ties), found by :func:`strided_argmax` with ``stride`` (1: every candidate)."""
        dtype = self.rays.dtype
        candidates = np.asarray(candidates, float)
        v = torch.as_tensor(self.speed * np.asarray(v, float) / np.linalg.norm(v), dtype=dtype)
        omega = torch.as_tensor(omega, dtype=dtype)
        parts = self.contrast.depth_free_parts(v, omega)
        patch = self.patches.patch.cpu().numpy()

        def values(index: np.ndarray) -> np.ndarray:   # (R, P) candidate indices -> (R, P) contrasts
            rows = torch.as_tensor(candidates[index][:, patch], dtype=dtype)
            out = self.contrast.at_depths(v, omega, rows, parts).double().numpy()
            return np.where(np.isnan(out), -np.inf, out)   # a NaN never wins

        return candidates[strided_argmax(values, len(candidates), self.patches.count, stride)]


def strided_argmax(values: Callable[[np.ndarray], np.ndarray], count: int, columns: int, stride: int) -> np.ndarray:
    """The index (columns,) int of the largest of ``count`` values in each column (the first on ties), scoring
    only some rows: every ``stride``-th (the last one always among them), then in each column the ``stride - 1``
    rows on each side of its best so far. ``values(index (R, columns) int) -> (R, columns)`` scores row
    ``index[r, j]`` of column ``j``.

    About ``count / stride + 2 (stride - 1)`` rows instead of ``count``; the same index as the full argmax
    wherever a column's values rise strictly to one peak and fall strictly after it (the true best lies
    between the coarse rows around the coarse best), not always otherwise: a peak narrower than the stride
    away from the coarse best, or one behind a plateau whose coarse rows tie, is missed.

    Examples
    --------
    >>> import numpy as np
    >>> table = np.array([[0.0, 1.0, 5.0, 2.0, 1.0, 0.0, 0.0]]).T       # one column, one peak at row 2
    >>> strided_argmax(lambda index: np.take_along_axis(table, index, 0), 7, 1, 3).tolist()
    [2]
    """
    if stride <= 1:
        return values(np.repeat(np.arange(count)[:, None], columns, 1)).argmax(0)
    coarse = coarse_rows(count, stride)
    scores = values(np.repeat(coarse[:, None], columns, 1))
    best = coarse[scores.argmax(0)]
    steps = np.r_[np.arange(-stride + 1, 0), np.arange(1, stride)]
    near = np.clip(best[None, :] + steps[:, None], 0, count - 1)
    index = np.concatenate([best[None], near])
    score = np.concatenate([scores.max(0)[None], values(near)])
    return np.where(score == score.max(0)[None], index, count).min(0)


def coarse_rows(count: int, stride: int) -> np.ndarray:
    """The rows :func:`strided_argmax` scores first: every ``stride``-th of ``count``, the last one always
    among them (int, ascending)."""
    return np.unique(np.r_[np.arange(0, count, max(stride, 1)), count - 1])


def rows_scored(count: int, stride: int) -> int:
    """How many rows :func:`strided_argmax` scores in each column: ``count`` with ``stride`` 1, else the
    :func:`coarse_rows` and the ``stride - 1`` on each side of the coarse best."""
    return count if stride <= 1 else len(coarse_rows(count, stride)) + 2 * (stride - 1)


def sweep_stride(settings: RefineSettings, depth_range: tuple[float, float]) -> int:
    """The stride of the per-patch start sweep over ``depth_range`` (near, far) [m]: how many candidate steps
    (log-uniform in inverse depth) fit in ``settings.rho_coarse_step``, at least 1, and no more than the stride
    that scores the fewest candidates (:func:`rows_scored`: a wider one scores more around the best than it
    saves).

    Examples
    --------
    >>> sweep_stride(RefineSettings(), (1.0, 6.5)), sweep_stride(RefineSettings(), (0.5, 60.0))
    (3, 1)
    """
    near, far = depth_range
    count = settings.rho_candidates
    spacing = math.log(far / near) / (count - 1)
    widest = max(1, int(settings.rho_coarse_step / spacing + 1e-9)) if spacing > 0 else 1
    scored = [rows_scored(count, stride) for stride in range(1, widest + 1)]
    return 1 + scored.index(min(scored))


@dataclass(frozen=True)
class RefineOutcome:
    """Result of :func:`refine_motion_local`: the motion, the patch-wise objective (minus the summed
    normalised contrasts) at the first start and at the result, every solve, and which of them the result
    is (``winner``)."""

    v: np.ndarray
    omega: np.ndarray
    objective_before: float
    objective_after: float
    solves: tuple[SolveResult, ...]
    at_bound: tuple[str, ...] = ()
    winner: int = 0


def refine_motion_local(w, v: np.ndarray, omega: np.ndarray, speed: float, settings: RefineSettings,
                        solver: Solver, *, hold_omega: bool = False,
                        more_starts: Sequence[tuple[np.ndarray, np.ndarray]] = (),
                        objective: LocalMotionObjective | None = None) -> RefineOutcome:
    """Refine ``v`` (3,) [m/s] and ``omega`` (3,) [rad/s] on the patch-wise contrast; ``|v|`` stays ``speed``.

    Parameters
    ----------
    w : cmax.fitting.window.Window
    v, omega : ndarray (3,)
        The start (e.g. :func:`cmax.fitting.patch_flow.motion_from_flows`).
    speed : float
        ``|v|`` [m/s].
    settings : RefineSettings
        Patches, their per-patch start sweep and the iteration limit.
    solver : Solver
        The backend (:func:`cmax.fitting.solvers.solve`); with one that takes equality constraints the
        direction is held on its sphere by ``|u| = settings.direction_scale`` instead of being normalised.
    hold_omega : bool
        Keep ``omega`` as given (a known rotation): only the direction and the depths move.
    more_starts : sequence of (v, omega)
        Further starts, each refined the same way; the refined motion with the highest patch-wise
        contrast wins (a multi-start of one optimisation).
    objective : LocalMotionObjective, optional
        The window's objective at ``speed``, when the caller holds one built with these ``settings``' patches
        (the ambiguity test's polishes); used when its parameterisation is the one ``solver`` needs.

    Returns
    -------
    RefineOutcome
        The start itself (no solves) when fewer than ``settings.min_patches`` patches hold
        ``settings.min_events``.
    """
    v, omega = np.asarray(v, float), np.asarray(omega, float)
    if objective is None or objective.unit_norm == solver.takes_equality:   # none, or the other parameterisation
        patches = make_patches(w, grid=settings.grid, min_events=settings.min_events, max_events=settings.max_events,
                               margin=settings.margin, min_margin_px=settings.min_margin_px)
        if patches is None or patches.count < settings.min_patches:
            return RefineOutcome(v, omega, float("nan"), float("nan"), ())
        objective = LocalMotionObjective.build(w, patches, speed, unit_norm=not solver.takes_equality,
                                               direction_scale=settings.direction_scale)
    elif objective.patches.count < settings.min_patches:
        return RefineOutcome(v, omega, float("nan"), float("nan"), ())
    near, far = w.settings.depth_range
    candidates = np.exp(np.linspace(np.log(1.0 / far), np.log(1.0 / near), settings.rho_candidates))
    solves, best = [], None
    for start_v, start_omega in [(v, omega), *more_starts]:
        result, v1, omega1, bound = _refine_from(w, objective, np.asarray(start_v, float),
                                                 np.asarray(start_omega, float), candidates, settings, hold_omega,
                                                 solver)
        solves.append(result)
        if best is None or result.fun < best[0]:
            best = (result.fun, v1, omega1, bound, len(solves) - 1)
    return RefineOutcome(best[1], best[2], solves[0].fun_start, best[0], tuple(solves), best[3], best[4])


def _refine_from(w, objective: LocalMotionObjective, v: np.ndarray, omega: np.ndarray, candidates: np.ndarray,
                 settings: RefineSettings, hold_omega: bool, solver: Solver
                 ) -> tuple[SolveResult, np.ndarray, np.ndarray, tuple[str, ...]]:
    """One refinement from ``(v, omega)``: the solve, ``v`` (3,), ``omega`` (3,), the omega axes on a bound."""
    near, far = w.settings.depth_range
    rho0 = objective.sweep_rho(v, omega, candidates, sweep_stride(settings, w.settings.depth_range))
    x0 = objective.params(v, omega, rho0)
    P, s_o, s_r = objective.patches.count, objective.omega_scale, objective.rho_scale
    max_omega, scale = w.settings.max_omega, objective.direction_scale
    lower = np.r_[np.full(3, -2 * scale), np.full(3, -max_omega * s_o), np.full(P, s_r / far)]
    upper = np.r_[np.full(3, 2 * scale), np.full(3, max_omega * s_o), np.full(P, s_r / near)]
    if hold_omega:  # equal bounds: the solvers keep these parameters fixed
        lower[3:6] = upper[3:6] = x0[3:6]
    result = solve(GradientLoss(objective.fun_and_grad), x0, lower, upper, solver, iterations=settings.iterations,
                   tolerances=settings.tolerances, norm_slice=slice(0, 3), norm=scale)
    v1, omega1, _ = objective.motion(result.x)
    bound = () if hold_omega else omega_on_bound(omega1, max_omega)
    return result, v1, omega1, bound


def omega_on_bound(omega: np.ndarray, max_omega: float) -> tuple[str, ...]:
    """Names of the components of ``omega`` (3,) [rad/s] within 0.1% of the bound ``+-max_omega``."""
    return tuple(f"omega_{axis}" for axis, value in zip("xyz", omega) if abs(value) >= 0.999 * max_omega)
