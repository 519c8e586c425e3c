"""The stages of :func:`cmax.fit`: the shared window, the coarse-to-fine driver, flow, rotation, se3.

Parameters are optimised in **pixels of displacement over the window** (a flow
``u`` as ``u T``, an angular rate as ``omega T f``, an inverse depth as
``rho |v| T f``) and objectives are normalised by their value for the unwarped
events, so one set of solver tolerances fits every window.

Stages of se3 without a known pose: (1) the twist from patch flows and the
motion-field equations (:mod:`cmax.fitting.patch_flow`), or with
``motion_init="starts"`` a rotation-only fit then translation directions
from several starts on the normalised multi-reference contrast plus the
deformation guard; (2) the twist refined on the patch-wise contrast
(:mod:`cmax.fitting.motion`); (3) the depth grid by the plane sweep of
:mod:`cmax.fitting.depth_sweep`; (4) ``alternations`` rounds of the motion
with that depth held and the sweep again. The depth is never a free
parameter of the global contrast: that is how a free depth collapses (issue 5).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

import numpy as np
import torch

from cmax.fitting.depth_sweep import sweep_inverse_depth
from cmax.fitting.patch_flow import motion_from_flows, patch_flows
from cmax.fitting.motion import refine_motion_local
from cmax.objectives import deformation, multi_reference_contrast
from cmax.fitting.solvers import Problem, Solver, SolveResult, make_solver
from cmax.warp import DepthGrid, WarpEvents, warp_flow, warp_rotation, warp_se3

if TYPE_CHECKING:  # pragma: no cover
    from cmax.events import Events
    from cmax.fitting import FitResult, FitSettings

__all__ = ["Window", "SE3Model", "coarse_to_fine", "fit_flow", "fit_rotation", "fit_se3", "directions"]


@dataclass(eq=False)
class Window:
    """Everything the stages share: events, reference times, grid, scales, solver counters."""

    ev: WarpEvents
    settings: "FitSettings"
    solver: Solver
    grid: DepthGrid
    dt: torch.Tensor = field(init=False)        # (B, N) for the references
    dt_mid: torch.Tensor = field(init=False)    # (1, N)
    focal: float = field(init=False)
    iterations: int = 0
    evaluations: int = 0
    message: str = ""
    success: bool = True

    def __post_init__(self) -> None:
        self.dt = self.ev.dt(self.settings.references)
        self.dt_mid = self.ev.dt((0.5,))
        self.focal = float(self.ev.K[0, 0] + self.ev.K[1, 1]) / 2
        self.index, self.weight = self.grid.weights(self.ev.x, self.ev.y)
        self.cell = self.grid.cell_of(self.ev.x, self.ev.y)
        self.on = (self.ev.polarity > 0) if self.settings.polarity_split else None  # None: polarities merged
        self._baselines: dict = {}

    @classmethod
    def from_events(cls, events: "Events", K: np.ndarray, settings: "FitSettings", solver: "str | Solver" = "scipy",
                    depth_grid: tuple[int, int] = (24, 32)) -> "Window":
        """The window of ``events`` with intrinsics ``K`` (3, 3), subsampled and dithered as ``settings`` say."""
        ev = WarpEvents.from_events(events, K, max_events=settings.max_events, seed=settings.seed)
        return cls(ev, settings, make_solver(solver), DepthGrid(tuple(depth_grid), events.width, events.height))

    @property
    def T(self) -> float:
        return self.ev.duration_s

    def contrast(self, x: torch.Tensor, y: torch.Tensor, scale: int = 1) -> torch.Tensor:
        """Normalised multi-reference contrast of warped coordinates (B, N) at an image scale."""
        H, W = math.ceil(self.ev.height / scale), math.ceil(self.ev.width / scale)
        kind, sigma = self.settings.contrast or "variance", self.settings.sigma
        if scale not in self._baselines:
            x0, y0 = self.ev.x[None] / scale, self.ev.y[None] / scale
            self._baselines[scale] = multi_reference_contrast(
                x0, y0, height=H, width=W, sigma=sigma, kind=kind, on=self.on).detach()
        return multi_reference_contrast(x / scale, y / scale, height=H, width=W, sigma=sigma, kind=kind,
                                        baseline=self._baselines[scale], on=self.on)

    def run(self, loss: Callable[[torch.Tensor], torch.Tensor], x0: np.ndarray, lower: np.ndarray,
            upper: np.ndarray, *, iterations: int | None = None, speed_slice: slice | None = None,
            relaxed: bool = False) -> SolveResult:
        """Minimise ``loss(params float64 tensor)`` with the backend; records counts and message."""
        def fun_and_grad(x: np.ndarray) -> tuple[float, np.ndarray]:
            p = torch.tensor(x, dtype=torch.float64, requires_grad=True)
            value = loss(p)
            (grad,) = torch.autograd.grad(value, p)
            return float(value.detach()), grad.numpy().copy()

        x0 = np.clip(np.asarray(x0, dtype=np.float64), lower, upper)
        problem = Problem(fun_and_grad, x0, np.asarray(lower, float), np.asarray(upper, float),
                          speed=1.0 if speed_slice is not None else None, v_slice=speed_slice)
        solver = self.solver.with_iterations(iterations or self.settings.iterations)
        solver = solver.relaxed() if relaxed else solver
        result = solver.solve(problem)
        self.iterations += result.iterations
        self.evaluations += result.evaluations
        self.message, self.success = result.message, result.success
        return result


def _scales(ev: WarpEvents) -> tuple[int, ...]:
    """Image scales of the coarse-to-fine driver: 4, 2, 1 for sensors of 256 px and more."""
    size = max(ev.width, ev.height)
    return (4, 2, 1) if size >= 256 else (2, 1) if size >= 96 else (1,)


def coarse_to_fine(window: Window, loss_at_scale: Callable[[torch.Tensor, int], torch.Tensor],
                   x0: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                   scales: tuple[int, ...] | None = None, relaxed: bool = False) -> np.ndarray:
    """The generic driver: solve at each image scale from coarse to fine, warm-starting the next."""
    x = np.asarray(x0, dtype=np.float64)
    for scale in scales or _scales(window.ev):
        iterations = None if scale == 1 else 20
        x = window.run(lambda p, s=scale: loss_at_scale(p, s), x, lower, upper, iterations=iterations,
                       relaxed=relaxed).x
    return x


def fit_flow(w: Window, flow0: np.ndarray) -> np.ndarray:
    """Constant optical flow [px/s] (2,)."""
    ev = w.ev
    bound = 2.0 * max(ev.width, ev.height)

    def loss(p: torch.Tensor, scale: int) -> torch.Tensor:
        x, y = warp_flow(ev.x, ev.y, w.dt_mid, (p / w.T).to(ev.x.dtype))
        return -w.contrast(x, y, scale)

    return coarse_to_fine(w, loss, flow0 * w.T, np.full(2, -bound), np.full(2, bound), relaxed=True) / w.T


def omega_scale(w: Window) -> float:
    """Pixels of displacement over the window per rad/s."""
    return w.T * w.focal


def fit_rotation(w: Window, omega0: np.ndarray) -> np.ndarray:
    """Angular velocity [rad/s] (3,) of a pure rotation."""
    ev, s = w.ev, omega_scale(w)
    bound = 6.0 * s  # 6 rad/s

    def loss(p: torch.Tensor, scale: int) -> torch.Tensor:
        x, y = warp_rotation(ev.rays, w.dt_mid, (p / s).to(ev.x.dtype), ev.K)
        return -w.contrast(x, y, scale)

    return coarse_to_fine(w, loss, omega0 * s, np.full(3, -bound), np.full(3, bound)) / s


def _probe_lattice(w: Window):
    """A 9 x 12 lattice of probe pixels, their rays, grid weights, and probe times (4, 1)."""
    ev = w.ev
    ys, xs = torch.meshgrid(torch.linspace(0.1, 0.9, 9, dtype=ev.x.dtype) * ev.height,
                            torch.linspace(0.1, 0.9, 12, dtype=ev.x.dtype) * ev.width, indexing="ij")
    Kinv = torch.linalg.inv(ev.K)
    rays = torch.stack([xs, ys, torch.ones_like(xs)], -1) @ Kinv.T
    index, weight = w.grid.weights(xs.reshape(-1), ys.reshape(-1))
    times = torch.tensor([-1.0, -0.5, 0.5, 1.0], dtype=ev.x.dtype)[:, None] * w.T
    return xs, ys, rays.reshape(-1, 3), (index, weight), times


class SE3Model:
    """Parameter layout and the motion objective of se3: ``x = (u (3), omega px (3), q (G or 1))``.

    ``u`` is the translation direction (``v = speed u / |u|`` for solvers without
    equality constraints), ``q = rho * speed * T * f`` the inverse depth in
    pixels of parallax over the window.
    """

    def __init__(self, w: Window, speed: float) -> None:
        self.w, self.speed = w, speed
        self.omega_scale = omega_scale(w)
        self.q_scale = speed * w.T * w.focal
        lo, hi = w.settings.depth_range
        self.q_bounds = (self.q_scale / hi, self.q_scale / lo)
        self.probes = _probe_lattice(w)
        self.unit_norm = not w.solver.takes_equality

    def velocity(self, u: torch.Tensor) -> torch.Tensor:
        if self.unit_norm:
            return self.speed * u / torch.sqrt((u * u).sum() + 1e-12)
        return self.speed * u

    def warp(self, v, omega, rho_events, dt):
        ev = self.w.ev
        return warp_se3(ev.rays, dt, v.to(ev.x.dtype), omega.to(ev.x.dtype), rho_events.to(ev.x.dtype), ev.K)

    def collapse(self, v, omega, rho_probes) -> torch.Tensor:
        xs, ys, rays, _, times = self.probes
        ev = self.w.ev
        x1, y1 = warp_se3(rays, times.expand(-1, rays.shape[0]), v.to(ev.x.dtype), omega.to(ev.x.dtype),
                          rho_probes.to(ev.x.dtype), ev.K)
        return deformation(xs, ys, x1.view(4, *xs.shape), y1.view(4, *xs.shape))

    def rho_events(self, q: torch.Tensor) -> torch.Tensor:
        if q.numel() == 1:
            return q.reshape(()).expand(len(self.w.ev)) / self.q_scale
        return DepthGrid.sample(q, self.w.index, self.w.weight) / self.q_scale

    def rho_probes(self, q: torch.Tensor) -> torch.Tensor:
        index, weight = self.probes[3]
        if q.numel() == 1:
            return q.reshape(()).expand(index.shape[0]) / self.q_scale
        return DepthGrid.sample(q, index, weight) / self.q_scale

    def objective(self, v: torch.Tensor, omega: torch.Tensor, rho_events: torch.Tensor,
                  rho_probes: torch.Tensor, scale: int = 1) -> torch.Tensor:
        """``-(normalised multi-reference contrast) + collapse_weight * deformation`` (lower is better)."""
        x, y = self.warp(v, omega, rho_events, self.w.dt)
        value = -self.w.contrast(x, y, scale)
        if self.w.settings.collapse_weight > 0:
            value = value + self.w.settings.collapse_weight * self.collapse(v, omega, rho_probes)
        return value

    def motion_loss(self, p: torch.Tensor, scale: int = 1, q_fixed: torch.Tensor | None = None) -> torch.Tensor:
        """The objective of parameters ``p = (u, omega px, q)``, or ``(u, omega px)`` with ``q_fixed``."""
        v = self.velocity(p[:3])
        omega = p[3:6] / self.omega_scale
        q = p[6:] if q_fixed is None else q_fixed
        return self.objective(v, omega, self.rho_events(q), self.rho_probes(q), scale)


def directions(count: int) -> list[np.ndarray]:
    """Start directions of the translation: the 6 camera axes, then the 8 diagonals."""
    axes = [np.array(a, float) for a in ((0, 0, 1), (0, 0, -1), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0))]
    if count <= 6:
        return axes[:max(count, 1)]
    diagonals = [np.array([a, b, c], float) / math.sqrt(3) for a in (1, -1) for b in (1, -1) for c in (1, -1)]
    return (axes + diagonals)[:count]


def sweep(w: Window, v: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """Inverse-depth grid (G,) [1/m] by the plane sweep of :mod:`cmax.fitting.depth_sweep`."""
    s, ev = w.settings, w.ev
    lo, hi = s.depth_range
    result = sweep_inverse_depth(
        ev.rays, w.dt_mid, ev.polarity, v, omega, ev.K, height=ev.height, width=ev.width,
        grid_shape=w.grid.shape, index=w.index, weight=w.weight, rho_range=(1.0 / hi, 1.0 / lo),
        candidates=s.depth_candidates, sigma=s.sigma, smoothness=tuple(s.depth_smoothness),
        coarsening=s.depth_coarsening,
        refinements=tuple(s.depth_refinements))
    return result.inverse_depth


def _omega_bounds(se3: SE3Model, omega: np.ndarray, hold: bool) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of the angular-velocity parameters [px]: +-6 rad/s, or equal to ``omega`` when it is held."""
    if hold:
        value = np.asarray(omega, float) * se3.omega_scale
        return value, value.copy()
    bound = 6.0 * se3.omega_scale
    return -np.full(3, bound), np.full(3, bound)


def _fit_motion(w: Window, se3: SE3Model, omega: np.ndarray, init: "FitResult | None", hold_omega: bool = False
                ) -> tuple[np.ndarray, np.ndarray]:
    """Translation direction from several starts (constant depth), then at full resolution."""
    s = w.settings
    lo_q, hi_q = se3.q_bounds
    starts = directions(s.translation_starts)
    if init is not None and np.linalg.norm(init.v) > 0:
        starts = [init.v / np.linalg.norm(init.v)] + starts
    q0 = math.sqrt(lo_q * hi_q)
    lower_o, upper_o = _omega_bounds(se3, omega, hold_omega)
    lower = np.r_[-np.ones(3) * 2, lower_o, lo_q]
    upper = np.r_[np.ones(3) * 2, upper_o, hi_q]
    speed_slice = None if se3.unit_norm else slice(0, 3)
    best = None
    for u0 in starts:
        x0 = np.r_[u0, omega * se3.omega_scale, q0]
        result = w.run(lambda p: se3.motion_loss(p, 2), x0, lower, upper, iterations=25, speed_slice=speed_slice)
        if best is None or result.fun < best.fun:
            best = result
    x = w.run(lambda p: se3.motion_loss(p, 1), best.x, lower, upper, speed_slice=speed_slice).x
    return se3.speed * x[:3] / np.linalg.norm(x[:3]), x[3:6] / se3.omega_scale


def _refine_motion(w: Window, se3: SE3Model, v: np.ndarray, omega: np.ndarray, rho_grid: np.ndarray,
                   hold_omega: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The motion with the depth grid held (one solve at full resolution)."""
    lower_o, upper_o = _omega_bounds(se3, omega, hold_omega)
    q = torch.as_tensor(rho_grid * se3.q_scale, dtype=torch.float64)
    lower, upper = np.r_[-np.ones(3) * 2, lower_o], np.r_[np.ones(3) * 2, upper_o]
    x = w.run(lambda p: se3.motion_loss(p, 1, q_fixed=q), np.r_[v / se3.speed, omega * se3.omega_scale],
              lower, upper, speed_slice=None if se3.unit_norm else slice(0, 3)).x
    return se3.speed * x[:3] / np.linalg.norm(x[:3]), x[3:6] / se3.omega_scale


def fit_se3(w: Window, *, speed: float, pose_xi: np.ndarray | None, init: "FitResult | None",
            omega: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns v [m/s], omega [rad/s], inverse-depth grid (gh, gw) [1/m].

    A known ``omega`` (3,) [rad/s] (a gyroscope's) is held through every stage:
    only the translation direction and the depth are fitted.
    """
    if pose_xi is not None:
        v, omega = pose_xi[:3], pose_xi[3:]
        return v, omega, sweep(w, v, omega).reshape(w.grid.shape)
    hold = omega is not None
    known = None if omega is None else np.asarray(omega, dtype=np.float64).copy()
    se3 = SE3Model(w, speed)
    centres = None
    if w.settings.motion_init == "patches":
        centres, flows, _, information = patch_flows(w)
    if centres is not None and len(centres) >= 4:
        K = w.ev.K.double().numpy()
        v, omega, _ = motion_from_flows(centres, flows, information, K, speed, omega=omega)
        if w.settings.motion_refinement == "local":
            more_starts = []
            if w.settings.zero_rotation_start and not hold:  # the flows explained without rotation
                v_still, omega_still, _ = motion_from_flows(centres, flows, information, K, speed, omega=np.zeros(3))
                more_starts.append((v_still, omega_still))
            v, omega = refine_motion_local(w, v, omega, speed, hold_omega=hold, more_starts=more_starts)
    else:  # "starts", or too few patches with events for the motion-field fit
        if not hold:
            omega = fit_rotation(w, init.omega if init is not None else np.zeros(3))
        v, omega = _fit_motion(w, se3, omega, init, hold_omega=hold)
    rho = sweep(w, v, omega)
    for _ in range(w.settings.alternations):
        v, omega = _refine_motion(w, se3, v, omega, rho, hold_omega=hold)
        rho = sweep(w, v, omega)
    return v, (known if hold else omega), rho.reshape(w.grid.shape)
