"""``cmax.fit``: depth and camera motion of one event window by contrast maximization.

The pieces (Gallego et al., CVPR 2018; the paper's section 4):

* the warp models of :mod:`cmax.warp` (flow, rotation, se3 + inverse-depth grid);
* the objectives of :mod:`cmax.objectives`: the multi-reference, normalised
  contrast for the motion, the per-cell local contrast plus total variation
  for the depth, the deformation guard against event collapse;
* a solver backend of :mod:`cmax.solvers` (scipy L-BFGS-B, casadi IPOPT, torch Adam);
* this module: the stages (rotation first, translation direction from several
  starts, depth by a per-cell sweep then refinement, a joint refinement), a
  coarse-to-fine driver, and :class:`FitResult`.

Parameters are optimised in **pixels of displacement over the window** (a flow
``u`` as ``u T``, an angular rate as ``omega T f``, an inverse depth as
``rho |v| T f``) and objectives are normalised by their value for the unwarped
events, so one set of solver tolerances fits every window.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
import torch

from cmax.camera import check_intrinsics
from cmax.events import Events
from cmax.geometry import se3_exp, se3_log
from cmax.iwe import accumulate_bilinear, blur
from cmax.objectives import deformation, local_contrast, multi_reference_contrast, total_variation
from cmax.solvers import Problem, Solver, SolveResult, make_solver
from cmax.warp import DepthGrid, WarpEvents, warp_flow, warp_rotation, warp_se3

__all__ = ["FitResult", "FitSettings", "SequenceResult", "fit", "fit_sequence"]

MODELS = ("flow", "rotation", "se3")


@dataclass(frozen=True)
class FitSettings:
    """Options of :func:`fit` beyond the model (keyword arguments of ``fit`` override them).

    Attributes
    ----------
    contrast : {"variance", "gradient"}
        Contrast of the IWEs.
    references : tuple of float
        Reference times of the multi-reference motion objective, as fractions
        of the window (0 = first event, 1 = last).
    sigma : float
        IWE blur [px].
    max_events : int
        Windows with more events are subsampled uniformly (seeded) to this many.
    depth_range : (float, float)
        Bounds of the depth [m] (in units of ``speed * 1 s`` when the scale is unknown).
    depth_candidates : int
        Inverse depths of the per-cell sweep that initialises the depth grid.
    tv_weight : float
        Weight of the total variation of the (normalised) inverse-depth grid.
    collapse_weight : float
        Weight of the deformation guard (:func:`cmax.objectives.deformation`).
    translation_starts : int
        Directions tried for the translation (6: +-x, +-y, +-z camera axes; 14 adds the diagonals).
    iterations : int
        Iteration limit of each solver stage.
    min_cell_events : int
        Depth cells with fewer events are outside the mask.
    seed : int
        Seed of the subsampling.
    """

    contrast: str = "variance"
    references: tuple[float, ...] = (0.0, 0.5, 1.0)
    sigma: float = 1.0
    max_events: int = 40_000
    depth_range: tuple[float, float] = (0.5, 60.0)
    depth_candidates: int = 32
    tv_weight: float = 0.02
    collapse_weight: float = 0.1
    translation_starts: int = 6
    iterations: int = 60
    min_cell_events: int = 15
    seed: int = 0


@dataclass(frozen=True, eq=False)
class FitResult:
    """The motion (and depth) of one event window.

    Attributes
    ----------
    model : str
        ``"flow"``, ``"rotation"`` or ``"se3"``.
    t0_us, t1_us : int
        Times of the window's first and last events [µs].
    t_ref_us : int
        The reference time: the depth map is the scene's depth seen from the
        camera at this time, the IWEs are warped to it (the window's middle).
    flow : ndarray (2,) or None
        Optical flow [px/s] (model ``flow``).
    v, omega : ndarray (3,)
        Linear [m/s] and angular [rad/s] velocity, camera frame (``v`` is a unit
        vector times an unknown scale when ``scale_known`` is False; zero for
        ``flow``/``rotation``).
    T : ndarray (4, 4)
        ``se3_exp((v, omega) (t1 - t0))``: the camera at ``t1`` in the frame of the camera at ``t0``.
    depth : ndarray (H, W) float32 or None
        z-depth [m] at ``t_ref_us``, dense (interpolated from the grid); see ``mask``.
    mask : ndarray (H, W) bool or None
        Pixels supported by events (event pixels of cells with enough events).
    inverse_depth_grid : ndarray (gh, gw) or None
        The optimised inverse depths [1/m] at the grid nodes.
    scale_known : bool
        Whether ``v`` and ``depth`` are metric (``speed`` or ``pose`` given).
    objective_before, objective_after : float
        Normalised multi-reference contrast (1 = unwarped events) of the start and the result.
    iterations, evaluations : int
    seconds : float
    message : str
        The last solver's message.
    success : bool
    iwe_before, iwe_after : ndarray (H, W) float32
        Event-count IWEs at ``t_ref_us`` without and with the fitted warp (blur sigma).
    events_used : int
    """

    model: str
    t0_us: int
    t1_us: int
    t_ref_us: int
    flow: np.ndarray | None
    v: np.ndarray
    omega: np.ndarray
    T: np.ndarray
    depth: np.ndarray | None
    mask: np.ndarray | None
    inverse_depth_grid: np.ndarray | None
    scale_known: bool
    objective_before: float
    objective_after: float
    iterations: int
    evaluations: int
    seconds: float
    message: str
    success: bool
    iwe_before: np.ndarray
    iwe_after: np.ndarray
    events_used: int

    @property
    def twist(self) -> np.ndarray:
        """``(v, omega)`` (6,)."""
        return np.r_[self.v, self.omega]

    def plot(self, path) -> "object":
        """Write a PNG: IWE before, after, and the depth map (when fitted); returns the path."""
        from cmax import viz

        def iwe_picture(image: np.ndarray) -> np.ndarray:
            scale = max(float(np.percentile(image[image > 0], 99)) if (image > 0).any() else 1.0, 1e-6)
            grey = (255 - np.clip(image / scale, 0, 1) * 255).astype(np.uint8)
            return np.repeat(grey[..., None], 3, axis=2)

        tiles = [viz.titled(iwe_picture(self.iwe_before), "IWE before"),
                 viz.titled(iwe_picture(self.iwe_after), "IWE after")]
        if self.depth is not None:
            depth = np.where(self.mask, self.depth, np.nan)
            tiles.append(viz.titled(viz.depth_image(depth), "depth" + ("" if self.scale_known else " (up to scale)")))
        return viz.save_png(path, viz.hstack(tiles))


# ----------------------------------------------------------------------------------------
# Validation and preparation
# ----------------------------------------------------------------------------------------
def _check_inputs(events: object, K: object, model: str) -> np.ndarray:
    if not isinstance(events, Events):
        raise TypeError(f"events must be cmax.Events, got {type(events).__name__}")
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    K = check_intrinsics(K)
    if abs(np.linalg.det(K)) < 1e-12:
        raise ValueError(f"K must be invertible, got {K.tolist()}")
    if len(events) < 10:
        raise ValueError(f"events: a window needs at least 10 events to fit a motion, got {len(events)}")
    if events.t[-1] == events.t[0]:
        raise ValueError("events all have the same timestamp: a window of zero duration shows no motion")
    return K


def _pose_twist(pose: object, duration_s: float) -> np.ndarray:
    """The constant twist of a known motion: a twist (6,) [m/s, rad/s], or T (4, 4) from t0 to t1."""
    array = np.asarray(pose, dtype=np.float64)
    if array.shape == (6,):
        xi = array
    elif array.shape == (4, 4):
        xi = se3_log(array) / duration_s
    else:
        raise ValueError(f"pose must be a twist (6,) [m/s, rad/s] or a (4, 4) motion over the window, got {array.shape}")
    if not np.isfinite(xi).all():
        raise ValueError("pose must be finite")
    return xi


@dataclass(eq=False)
class _Window:
    """Everything the stages share: events, reference times, grid, patches, scales."""

    ev: WarpEvents
    settings: FitSettings
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
        self.cell_counts = torch.bincount(self.cell, minlength=self.grid.shape[0] * self.grid.shape[1])
        self._baselines: dict = {}

    @property
    def T(self) -> float:
        return self.ev.duration_s

    def contrast(self, x: torch.Tensor, y: torch.Tensor, scale: int = 1) -> torch.Tensor:
        """Normalised multi-reference contrast of warped coordinates (B, N) at an image scale."""
        H, W = math.ceil(self.ev.height / scale), math.ceil(self.ev.width / scale)
        if scale not in self._baselines:
            x0, y0 = self.ev.x[None] / scale, self.ev.y[None] / scale
            self._baselines[scale] = multi_reference_contrast(
                x0, y0, height=H, width=W, sigma=self.settings.sigma, kind=self.settings.contrast).detach()
        return multi_reference_contrast(x / scale, y / scale, height=H, width=W, sigma=self.settings.sigma,
                                        kind=self.settings.contrast, baseline=self._baselines[scale])

    def run(self, loss: Callable[[torch.Tensor], torch.Tensor], x0: np.ndarray, lower: np.ndarray,
            upper: np.ndarray, *, iterations: int | None = None, speed_slice: slice | None = None) -> SolveResult:
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
        result = solver.solve(problem)
        self.iterations += result.iterations
        self.evaluations += result.evaluations
        self.message, self.success = result.message, result.success
        return result


def _scales(ev: WarpEvents) -> tuple[int, ...]:
    """Image scales of the coarse-to-fine driver: 4, 2, 1 for sensors of 256 px and more."""
    size = max(ev.width, ev.height)
    return (4, 2, 1) if size >= 256 else (2, 1) if size >= 96 else (1,)


def coarse_to_fine(window: _Window, loss_at_scale: Callable[[torch.Tensor, int], torch.Tensor],
                   x0: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """The generic driver: solve at each image scale from coarse to fine, warm-starting the next."""
    x = np.asarray(x0, dtype=np.float64)
    for scale in _scales(window.ev):
        iterations = None if scale == 1 else 20
        x = window.run(lambda p, s=scale: loss_at_scale(p, s), x, lower, upper, iterations=iterations).x
    return x


# ----------------------------------------------------------------------------------------
# Stages
# ----------------------------------------------------------------------------------------
def _fit_flow(w: _Window, flow0: np.ndarray) -> np.ndarray:
    ev = w.ev
    bound = 2.0 * max(ev.width, ev.height)

    def loss(p: torch.Tensor, scale: int) -> torch.Tensor:
        x, y = warp_flow(ev.x, ev.y, w.dt_mid, (p / w.T).to(ev.x.dtype))
        return -w.contrast(x, y, scale)

    p = coarse_to_fine(w, loss, flow0 * w.T, np.full(2, -bound), np.full(2, bound))
    return p / w.T


def _omega_scale(w: _Window) -> float:
    return w.T * w.focal  # px of displacement per rad/s


def _fit_rotation(w: _Window, omega0: np.ndarray) -> np.ndarray:
    ev, s = w.ev, _omega_scale(w)
    bound = 6.0 * s  # 6 rad/s

    def loss(p: torch.Tensor, scale: int) -> torch.Tensor:
        x, y = warp_rotation(ev.rays, w.dt_mid, (p / s).to(ev.x.dtype), ev.K)
        return -w.contrast(x, y, scale)

    return coarse_to_fine(w, loss, omega0 * s, np.full(3, -bound), np.full(3, bound)) / s


def _probe_lattice(w: _Window) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """A 9 x 12 lattice of probe pixels, their rays, grid weights, and probe times (4, 1, 1)."""
    ev = w.ev
    ys, xs = torch.meshgrid(torch.linspace(0.1, 0.9, 9, dtype=ev.x.dtype) * ev.height,
                            torch.linspace(0.1, 0.9, 12, dtype=ev.x.dtype) * ev.width, indexing="ij")
    Kinv = torch.linalg.inv(ev.K)
    rays = torch.stack([xs, ys, torch.ones_like(xs)], -1) @ Kinv.T
    index, weight = w.grid.weights(xs.reshape(-1), ys.reshape(-1))
    times = torch.tensor([-1.0, -0.5, 0.5, 1.0], dtype=ev.x.dtype)[:, None] * w.T
    return xs, ys, rays.reshape(-1, 3), (index, weight), times


class _SE3:
    """Parameter layout and losses of the se3 stages: ``x = (u (3), omega px (3), q (G or 1))``."""

    def __init__(self, w: _Window, speed: float, known_v: np.ndarray | None) -> None:
        self.w, self.speed, self.known_v = w, speed, known_v
        self.omega_scale = _omega_scale(w)
        self.q_scale = speed * w.T * w.focal  # px per (1/m) of inverse depth
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
        w = self.w
        if q.numel() == 1:
            return q.expand(len(w.ev)) / self.q_scale
        return DepthGrid.sample(q, w.index, w.weight) / self.q_scale

    def rho_probes(self, q: torch.Tensor) -> torch.Tensor:
        index, weight = self.probes[3]
        if q.numel() == 1:
            return q.expand(index.shape[0]) / self.q_scale
        return DepthGrid.sample(q, index, weight) / self.q_scale

    def motion_loss(self, p: torch.Tensor, scale: int = 1) -> torch.Tensor:
        """Global normalised multi-reference contrast + collapse guard; q may be a scalar or a grid."""
        v = self.known_v_tensor(p) if self.known_v is not None else self.velocity(p[:3])
        omega = p[3:6] / self.omega_scale
        q = p[6:]
        x, y = self.warp(v, omega, self.rho_events(q), self.w.dt)
        value = -self.w.contrast(x, y, scale)
        if self.w.settings.collapse_weight > 0:
            value = value + self.w.settings.collapse_weight * self.collapse(v, omega, self.rho_probes(q))
        return value

    def known_v_tensor(self, p: torch.Tensor) -> torch.Tensor:
        return torch.as_tensor(self.known_v, dtype=p.dtype)


def _sweep_depth(se3: _SE3, v: np.ndarray, omega: np.ndarray) -> tuple[np.ndarray, dict]:
    """Per-cell sweep of constant inverse depths with the local contrast; returns q (G,) and the patch setup."""
    w = se3.w
    s = w.settings
    ev = w.ev
    gh, gw = w.grid.shape
    count = gh * gw
    candidates = torch.linspace(se3.q_bounds[0], se3.q_bounds[1], s.depth_candidates, dtype=torch.float64)
    v_t, om_t = torch.as_tensor(v), torch.as_tensor(omega)
    # Margin: the largest displacement to the reference time, at the nearest candidate depth.
    with torch.no_grad():
        x, y = se3.warp(v_t, om_t, candidates[-1].expand(len(ev)) / se3.q_scale, w.dt_mid)
        reach = float(torch.quantile(torch.hypot(x - ev.x, y - ev.y).flatten()[:20000], 0.95))
    margin = int(min(max(math.ceil(reach) + 3, 4), 48))
    cell_h, cell_w = math.ceil(ev.height / gh), math.ceil(ev.width / gw)
    jj, ii = torch.meshgrid(torch.arange(gw), torch.arange(gh), indexing="xy")
    origins = torch.stack([jj.reshape(-1) * ev.width / gw - margin, ii.reshape(-1) * ev.height / gh - margin], -1)
    origins = origins.to(ev.x.dtype)
    patch = (cell_h + 2 * margin, cell_w + 2 * margin)
    setup = {"origins": origins, "patch": patch, "count": count}
    energies = []
    with torch.no_grad():
        for chunk in candidates.split(4):
            rho = (chunk[:, None] / se3.q_scale).expand(-1, len(ev))
            xs, ys = [], []
            for r in rho:
                x, y = se3.warp(v_t, om_t, r, w.dt_mid)
                xs.append(x[0]); ys.append(y[0])
            energies.append(local_contrast(torch.stack(xs), torch.stack(ys), w.cell, origins, count=count,
                                           patch=patch, sigma=s.sigma))
    energy = torch.cat(energies)  # (C, G)
    best = candidates[energy.argmax(0)]
    return best.numpy(), setup


def _refine_depth_loss(se3: _SE3, setup: dict, v: np.ndarray | None, omega_fixed: np.ndarray | None,
                       base_energy: torch.Tensor, q_norm: float):
    """Loss of the depth (and optionally joint) refinement: -local contrast + TV (+ global motion loss)."""
    w = se3.w
    s = w.settings
    gh, gw = w.grid.shape

    def loss(p: torch.Tensor) -> torch.Tensor:
        if v is not None:
            vv, om, q = torch.as_tensor(v), torch.as_tensor(omega_fixed), p
        else:
            vv, om, q = se3.velocity(p[:3]), p[3:6] / se3.omega_scale, p[6:]
        rho = se3.rho_events(q)
        x, y = se3.warp(vv, om, rho, w.dt_mid)
        energy = local_contrast(x[0], y[0], w.cell, setup["origins"], count=setup["count"],
                                patch=setup["patch"], sigma=s.sigma)
        value = -(energy.sum() / base_energy)
        value = value + s.tv_weight * total_variation(q.view(gh, gw) / q_norm)
        if v is None:
            value = value + se3.motion_loss(p)
        return value

    return loss


def _fit_se3(w: _Window, *, speed: float, pose_xi: np.ndarray | None, init: "FitResult | None"
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns v, omega, inverse-depth grid (gh, gw) [1/m]."""
    s = w.settings
    G = w.grid.shape[0] * w.grid.shape[1]
    known_v = None if pose_xi is None else pose_xi[:3]
    se3 = _SE3(w, speed, known_v)
    lo_q, hi_q = se3.q_bounds
    if pose_xi is not None:
        v, omega = pose_xi[:3], pose_xi[3:]
    else:
        # 1. rotation first (a rotation-only fit; warm start from init)
        omega0 = init.omega if init is not None else np.zeros(3)
        omega = _fit_rotation(w, omega0)
        # 2. translation direction from several starts, constant inverse depth
        starts = _directions(s.translation_starts)
        if init is not None and np.linalg.norm(init.v) > 0:
            starts = [init.v / np.linalg.norm(init.v)] + starts
        q0 = math.sqrt(lo_q * hi_q)
        bound_o = 6.0 * se3.omega_scale
        lower = np.r_[-np.ones(3) * 2, -np.ones(3) * bound_o, lo_q]
        upper = np.r_[np.ones(3) * 2, np.ones(3) * bound_o, hi_q]
        best = None
        for u0 in starts:
            x0 = np.r_[u0, omega * se3.omega_scale, q0]
            result = w.run(lambda p: se3.motion_loss(p, 2), x0, lower, upper, iterations=25,
                           speed_slice=None if se3.unit_norm else slice(0, 3))
            if best is None or result.fun < best.fun:
                best = result
        result = w.run(lambda p: se3.motion_loss(p, 1), best.x, lower, upper,
                       speed_slice=None if se3.unit_norm else slice(0, 3))
        u = result.x[:3] / np.linalg.norm(result.x[:3])
        v, omega = speed * u, result.x[3:6] / se3.omega_scale
    # 3. depth: per-cell sweep, then local contrast + TV
    q_sweep, setup = _sweep_depth(se3, v, omega)
    q_norm = float(np.median(q_sweep))
    with torch.no_grad():
        x, y = se3.warp(torch.as_tensor(v), torch.as_tensor(omega), se3.rho_events(torch.as_tensor(q_sweep)), w.dt_mid)
        base = local_contrast(x[0], y[0], w.cell, setup["origins"], count=setup["count"], patch=setup["patch"],
                              sigma=s.sigma).sum().double()
    loss = _refine_depth_loss(se3, setup, v, omega, base, q_norm)
    q = w.run(loss, q_sweep, np.full(G, lo_q), np.full(G, hi_q)).x
    # 4. joint refinement of motion and depth (unknown motion only)
    if pose_xi is None:
        bound_o = 6.0 * se3.omega_scale
        lower = np.r_[-np.ones(3) * 2, -np.ones(3) * bound_o, np.full(G, lo_q)]
        upper = np.r_[np.ones(3) * 2, np.ones(3) * bound_o, np.full(G, hi_q)]
        joint = _refine_depth_loss(se3, setup, None, None, base, q_norm)
        x = w.run(joint, np.r_[v / speed, omega * se3.omega_scale, q], lower, upper,
                  speed_slice=None if se3.unit_norm else slice(0, 3)).x
        v = speed * x[:3] / np.linalg.norm(x[:3])
        omega, q = x[3:6] / se3.omega_scale, x[6:]
    return v, omega, (q / se3.q_scale).reshape(w.grid.shape)


def _directions(count: int) -> list[np.ndarray]:
    axes = [np.array(a, float) for a in ((0, 0, 1), (0, 0, -1), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0))]
    if count <= 6:
        return axes[:max(count, 1)]
    diagonals = [np.array([a, b, c], float) / math.sqrt(3) for a in (1, -1) for b in (1, -1) for c in (1, -1)]
    return (axes + diagonals)[:count]


# ----------------------------------------------------------------------------------------
# Public entry point
# ----------------------------------------------------------------------------------------
def fit(
    events: Events, K: object, model: str = "se3", *, speed: float | None = None, pose: object = None,
    depth_grid: tuple[int, int] = (12, 16), solver: "str | Solver" = "scipy", init: FitResult | None = None,
    settings: FitSettings = FitSettings(), num_threads: int | None = 1, **options,
) -> FitResult:
    """Fit the motion (and the depth) of one window of events by contrast maximization.

    Parameters
    ----------
    events : Events
        One window (at least 10 events spanning a non-zero time). Both
        polarities are counted alike (the IWE counts events), so a window of
        one polarity is fine.
    K : array_like (3, 3)
        Pinhole intrinsics [px] of the (undistorted) events.
    model : {"se3", "rotation", "flow"}
        ``flow``: a constant optical flow [px/s]; ``rotation``: an angular
        velocity [rad/s]; ``se3``: linear and angular velocity plus an
        inverse-depth grid.
    speed : float, optional
        Known ``|v|`` [m/s] (se3): depth and ``v`` are metric.
    pose : array_like, optional
        Known motion of the window (se3): a twist ``(v, omega)`` (6,) [m/s,
        rad/s] or the (4, 4) transform from the camera at the first event to
        the camera at the last; only the depth is optimised.
    depth_grid : (rows, cols)
        Size of the inverse-depth grid (se3).
    solver : {"scipy", "casadi", "torch"} or cmax.solvers.Solver
    init : FitResult, optional
        Warm start (e.g. the previous window of a sequence).
    settings : FitSettings
        Further options; keyword arguments named like its fields override it
        (e.g. ``fit(..., contrast="gradient", max_events=20000)``).
    num_threads : int or None
        torch threads during the fit (restored afterwards); 1 is fastest on
        busy machines; None keeps the current setting.

    Returns
    -------
    FitResult
        With neither ``speed`` nor ``pose`` the translation and depth are up to
        one scale: ``|v| = 1`` and ``scale_known`` is False.

    Raises
    ------
    TypeError, ValueError
        Not an ``Events``; unknown model or solver; a bad K; fewer than 10
        events; all events at one time; ``speed`` not positive; a bad ``pose``.

    Notes
    -----
    Stages for se3 (without ``pose``): a rotation-only fit; the translation
    direction from several starts with a constant depth (normalised
    multi-reference contrast plus the deformation guard); a per-cell sweep of
    inverse depths on the local contrast; refinement of the grid (local
    contrast + total variation); a joint refinement of all parameters. The
    inverse depth of an event is read at its own pixel, so the depth map is
    exact for the reference time up to the image motion between an event and
    ``t_ref`` (a fraction of a grid cell for the windows this is made for).

    References
    ----------
    G. Gallego, H. Rebecq, D. Scaramuzza, "A unifying contrast maximization
    framework for event cameras", CVPR 2018, doi:10.1109/CVPR.2018.00407.
    S. Shiba, Y. Aoki, G. Gallego, "Event collapse in contrast maximization
    frameworks", Sensors 2022, doi:10.3390/s22145190.

    Examples
    --------
    >>> result = cmax.fit(events, K, model="rotation")       # doctest: +SKIP
    >>> result.omega                                          # doctest: +SKIP
    """
    start = time.perf_counter()
    K = _check_inputs(events, K, model)
    if options:
        unknown = set(options) - set(FitSettings.__dataclass_fields__)
        if unknown:
            raise TypeError(f"fit() got unexpected keyword arguments {sorted(unknown)}")
        settings = replace(settings, **options)
    if speed is not None and not (np.isfinite(speed) and speed > 0):
        raise ValueError(f"speed must be a positive number of m/s, got {speed}")
    if (speed is not None or pose is not None) and model != "se3":
        raise ValueError(f"speed and pose apply to model='se3', not {model!r}")
    if init is not None and not isinstance(init, FitResult):
        raise TypeError(f"init must be a FitResult, got {type(init).__name__}")
    backend = make_solver(solver)
    pose_xi = None if pose is None else _pose_twist(pose, (int(events.t[-1]) - int(events.t[0])) * 1e-6)
    previous_threads = torch.get_num_threads()
    if num_threads is not None:
        torch.set_num_threads(num_threads)
    try:
        ev = WarpEvents.from_events(events, K, max_events=settings.max_events, seed=settings.seed)
        w = _Window(ev, settings, backend, DepthGrid(tuple(depth_grid), events.width, events.height))
        flow, v, omega, grid = None, np.zeros(3), np.zeros(3), None
        if model == "flow":
            flow = _fit_flow(w, init.flow if init is not None and init.flow is not None else np.zeros(2))
        elif model == "rotation":
            omega = _fit_rotation(w, init.omega if init is not None else np.zeros(3))
        else:
            scale = float(np.linalg.norm(pose_xi[:3])) if pose_xi is not None else (speed or 1.0)
            if scale <= 0:
                raise ValueError("pose has no translation: depth is unobservable under a pure rotation")
            v, omega, grid = _fit_se3(w, speed=scale, pose_xi=pose_xi, init=init)
        return _result(w, model, flow, v, omega, grid, scale_known=pose is not None or speed is not None,
                       seconds=time.perf_counter() - start)
    finally:
        torch.set_num_threads(previous_threads)


def _warped_mid(w: _Window, flow, v, omega, grid) -> tuple[torch.Tensor, torch.Tensor]:
    ev = w.ev
    with torch.no_grad():
        if flow is not None:
            return warp_flow(ev.x, ev.y, w.dt_mid, torch.as_tensor(flow, dtype=ev.x.dtype))
        if grid is None:
            return warp_rotation(ev.rays, w.dt_mid, torch.as_tensor(omega, dtype=ev.x.dtype), ev.K)
        rho = DepthGrid.sample(torch.as_tensor(grid, dtype=ev.x.dtype), w.index, w.weight)
        return warp_se3(ev.rays, w.dt_mid, torch.as_tensor(v, dtype=ev.x.dtype),
                        torch.as_tensor(omega, dtype=ev.x.dtype), rho, ev.K)


def _objective(w: _Window, flow, v, omega, grid) -> float:
    ev = w.ev
    with torch.no_grad():
        if flow is not None:
            x, y = warp_flow(ev.x, ev.y, w.dt, torch.as_tensor(flow, dtype=ev.x.dtype))
        elif grid is None:
            x, y = warp_rotation(ev.rays, w.dt, torch.as_tensor(omega, dtype=ev.x.dtype), ev.K)
        else:
            rho = DepthGrid.sample(torch.as_tensor(grid, dtype=ev.x.dtype), w.index, w.weight)
            x, y = warp_se3(ev.rays, w.dt, torch.as_tensor(v, dtype=ev.x.dtype),
                            torch.as_tensor(omega, dtype=ev.x.dtype), rho, ev.K)
        return float(w.contrast(x, y, 1))


def _result(w: _Window, model, flow, v, omega, grid, *, scale_known: bool, seconds: float) -> FitResult:
    ev, s = w.ev, w.settings
    H, W = ev.height, ev.width
    with torch.no_grad():
        before = blur(accumulate_bilinear(ev.x, ev.y, None, H, W), s.sigma).numpy()
        x, y = _warped_mid(w, flow, v, omega, grid)
        after = blur(accumulate_bilinear(x[0], y[0], None, H, W), s.sigma).numpy()
    depth = mask = None
    if grid is not None:
        depth = (1.0 / w.grid.upsample(grid)).astype(np.float32)
        counts = np.bincount(w.cell.numpy(), minlength=grid.size)
        supported = counts.reshape(grid.shape) >= s.min_cell_events
        import cv2
        hits = np.zeros((H, W), np.uint8)
        hits[ev.y.numpy().astype(int), ev.x.numpy().astype(int)] = 1
        hits = cv2.dilate(hits, np.ones((3, 3), np.uint8)).astype(bool)
        cell_map = w.grid.cell_of(*[torch.from_numpy(a.ravel().astype(np.float64)) for a in np.mgrid[0:H, 0:W][::-1]])
        mask = hits & supported.ravel()[cell_map.numpy()].reshape(H, W)
    xi = np.r_[v, omega]
    return FitResult(
        model=model, t0_us=ev.t0_us, t1_us=ev.t1_us, t_ref_us=ev.t0_us + (ev.t1_us - ev.t0_us) // 2,
        flow=None if flow is None else np.asarray(flow, float), v=np.asarray(v, float), omega=np.asarray(omega, float),
        T=se3_exp(xi * ev.duration_s), depth=depth, mask=mask,
        inverse_depth_grid=None if grid is None else np.asarray(grid, float), scale_known=scale_known,
        objective_before=1.0, objective_after=_objective(w, flow, v, omega, grid),
        iterations=w.iterations, evaluations=w.evaluations, seconds=seconds, message=w.message,
        success=w.success, iwe_before=before, iwe_after=after, events_used=len(ev),
    )


@dataclass(frozen=True, eq=False)
class SequenceResult:
    """Window-by-window fits and the integrated trajectory.

    Attributes
    ----------
    results : tuple of FitResult
    times_us : ndarray (M + 1,)
        Start of every window, then the end of the last.
    poses : ndarray (M + 1, 4, 4)
        ``T_w_c`` at ``times_us``, the first the identity; between two starts the
        camera moves with the window's constant twist (metric only when every
        window's ``scale_known``).
    """

    results: tuple
    times_us: np.ndarray
    poses: np.ndarray


def fit_sequence(source, K: object, model: str = "se3", *, window_us: int = 166_500, step_us: int | None = None,
                 speed: float | None = None, min_events: int = 1000, **fit_options) -> SequenceResult:
    """Fit consecutive windows of a recording, warm-starting each from the previous.

    Parameters
    ----------
    source : Events or cmax.io.H5Reader
        Anything with ``window(t0_us, t1_us)`` (a reader) or an :class:`Events`.
    K : array_like (3, 3)
    model : str
    window_us, step_us : int
        Window length and the step between window starts [µs] (``step_us`` defaults to ``window_us``).
    speed : float, optional
        Known speed [m/s] of every window.
    min_events : int
        Windows with fewer events are skipped (the pose is held by the last twist).
    **fit_options
        Passed to :func:`fit`.
    """
    step_us = window_us if step_us is None else int(step_us)
    if window_us <= 0 or step_us <= 0:
        raise ValueError(f"window_us and step_us must be positive, got {window_us}, {step_us}")
    if isinstance(source, Events):
        t_start, t_end = int(source.t[0]), int(source.t[-1])
        take = lambda a, b: source.slice_time(a, b) if hasattr(source, "slice_time") else _slice(source, a, b)  # noqa: E731
    elif hasattr(source, "window"):
        t_start, t_end = int(source.t_start), int(source.t_end)
        take = source.window
    else:
        raise TypeError(f"source must be Events or a reader with window(t0_us, t1_us), got {type(source).__name__}")
    results, times, poses = [], [t_start], [np.eye(4)]
    previous: FitResult | None = None
    t0 = t_start
    while t0 + window_us <= t_end + 1:
        events = take(t0, t0 + window_us)
        twist = previous.twist if previous is not None else np.zeros(6)
        if len(events) >= min_events and events.t[-1] > events.t[0]:
            previous = fit(events, K, model, speed=speed if model == "se3" else None, init=previous, **fit_options)
            results.append(previous)
            twist = previous.twist
        poses.append(poses[-1] @ se3_exp(twist * step_us * 1e-6))
        times.append(t0 + step_us)
        t0 += step_us
    return SequenceResult(tuple(results), np.asarray(times, np.int64), np.stack(poses))


def _slice(events: Events, t0_us: int, t1_us: int) -> Events:
    i, j = np.searchsorted(events.t, [t0_us, t1_us])
    return events[int(i):int(j)]
