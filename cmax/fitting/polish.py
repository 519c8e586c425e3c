"""se3's optional final stage: the fit's depth (and motion) refined on the objective :mod:`learned` trains on.

:class:`SharedPolishStage` minimises :data:`cmax.contrast.SHARED_OBJECTIVE` (the per-pixel average
timestamp of Zhu et al., CVPR 2019, as refined by Hagenaars et al., NeurIPS 2021, with the total
variation of the log inverse depth; ``docs/contrast_objective.md``) — the very object
:func:`learned.losses.student_loss` calls — over the window's inverse-depth grid and, with
``motion_free``, the translation direction and angular velocity, from the earlier stages' result,
through :func:`cmax.fitting.solvers.solve` (so ``scipy``, ``casadi`` and ``torch`` all run it, and it
never ends worse than its start).

Parameters (:func:`polish_layout`): ``x = (log inverse depth (G,), [u (3), omega px (3)])``; the log
keeps the inverse depth positive, ``v = speed u / |u|`` (the batch's known speed, the objective's own
:func:`cmax.contrast.twist_at_speed`), ``omega px = omega * T * f`` as in the other stages. Whether it
helps the accuracy: ``benchmarks/results/shared_polish.md``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import torch

from cmax.contrast import SHARED_OBJECTIVE, DepthMotion, EventWindows
from cmax.fitting.motion import omega_on_bound
from cmax.fitting.pipeline import Motion, StageLog, _log, _omega_bounds
from cmax.fitting.solvers import Solver, solve
from cmax.fitting.window import Window

__all__ = ["SharedPolishStage", "window_events", "polish_layout", "PolishLayout", "motion_objective"]


def window_events(w: Window, speed: float) -> EventWindows:
    """The events the fit uses (``w.ev``: subsampled, dithered) as a one-window :class:`EventWindows` in
    float64 with the known ``speed`` [m/s] (``|v|``; 1 when the scale is unknown)."""
    ev = w.ev
    batch = EventWindows(ev.x, ev.y, ev.t, ev.polarity, torch.zeros(len(ev), dtype=torch.int64), ev.K[None],
                         torch.tensor([ev.duration_s]), ev.width, ev.height)
    return batch.to(torch.float64).with_speed([float(speed)])


@dataclass(frozen=True)
class PolishLayout:
    """The polish's parameter vector: ``grid`` (gh, gw) log inverse depths, then (``motion_free``) the
    direction ``u`` (3,) and ``omega * omega_scale`` (3,) [px]."""

    grid: tuple[int, int]
    omega_scale: float
    motion_free: bool

    @property
    def nodes(self) -> int:
        return self.grid[0] * self.grid[1]

    def params(self, x: torch.Tensor, v: np.ndarray, omega: np.ndarray) -> DepthMotion:
        """:class:`DepthMotion` (B = 1) of ``x`` (float64); ``v`` (3,) [m/s], ``omega`` (3,) [rad/s] when held."""
        inverse_depth = torch.exp(x[:self.nodes]).reshape(1, 1, *self.grid)
        if self.motion_free:
            twist = torch.cat([x[self.nodes:self.nodes + 3], x[self.nodes + 3:self.nodes + 6] / self.omega_scale])
        else:
            twist = torch.as_tensor(np.r_[v, omega], dtype=torch.float64)
        return DepthMotion(inverse_depth, twist[None])

    def start(self, motion: Motion) -> np.ndarray:
        """The parameter vector of ``motion`` (its inverse-depth grid, direction and angular velocity)."""
        log_rho = np.log(np.asarray(motion.inverse_depth, dtype=np.float64).reshape(-1))
        if not self.motion_free:
            return log_rho
        u = np.asarray(motion.v, float) / max(float(np.linalg.norm(motion.v)), 1e-300)
        return np.r_[log_rho, u, np.asarray(motion.omega, float) * self.omega_scale]

    def motion(self, x: np.ndarray, motion: Motion) -> Motion:
        """``motion`` with the grid (and the direction and angular velocity) of ``x``."""
        inverse_depth = np.exp(x[:self.nodes]).reshape(self.grid)
        if not self.motion_free:
            return replace(motion, inverse_depth=inverse_depth)
        u = x[self.nodes:self.nodes + 3]
        return replace(motion, inverse_depth=inverse_depth, v=motion.speed * u / np.linalg.norm(u),
                       omega=x[self.nodes + 3:self.nodes + 6] / self.omega_scale)


def polish_layout(w: Window, motion_free: bool) -> PolishLayout:
    """The layout of ``w``'s depth grid with (or without) the motion."""
    return PolishLayout(tuple(w.grid.shape), w.omega_scale, motion_free)


def polish_loss(batch: EventWindows, layout: PolishLayout, motion: Motion, objective=SHARED_OBJECTIVE
                ) -> Callable[[torch.Tensor], torch.Tensor]:
    """``x (n,) float64 -> objective(batch, layout.params(x)) (scalar)``: what the polish minimises."""

    def loss(x: torch.Tensor) -> torch.Tensor:
        return objective(batch, layout.params(x, motion.v, motion.omega))[0]

    return loss


def motion_objective(batch: EventWindows, motion: Motion, objective=SHARED_OBJECTIVE) -> float:
    """``objective`` at ``motion``'s inverse-depth grid, ``v`` and ``omega`` as they are (what a caller of the
    fit's result evaluates), on the one-window ``batch``."""
    inverse_depth = torch.as_tensor(np.asarray(motion.inverse_depth, dtype=np.float64))
    twist = torch.as_tensor(np.r_[motion.v, motion.omega], dtype=torch.float64)[None]
    with torch.no_grad():
        return float(objective(batch, DepthMotion(inverse_depth.reshape(1, 1, *inverse_depth.shape), twist))[0])


@dataclass(frozen=True)
class SharedPolishStage:
    """Parameters: the log inverse-depth grid (G,) and, with ``motion_free``, the direction and angular
    velocity (6,), ``|v|`` held. Objective: :data:`cmax.contrast.SHARED_OBJECTIVE` (what :mod:`learned`
    trains on). Schedule: one solve at full resolution from the incoming motion, limited to
    ``settings.polish_iterations``. With ``hold_omega`` the angular velocity stays as it is."""

    motion_free: bool = True
    hold_omega: bool = False
    name: str = "shared_polish"

    def run(self, w: Window, motion: Motion, solver: Solver) -> tuple[Motion, StageLog]:
        start, s = time.perf_counter(), w.settings
        if motion.inverse_depth is None:
            raise ValueError("the shared polish needs an inverse-depth grid from an earlier stage")
        layout = polish_layout(w, self.motion_free)
        batch = window_events(w, motion.speed)
        lo, hi = s.depth_range
        x0 = layout.start(motion)
        lower, upper = np.full(layout.nodes, -np.log(hi)), np.full(layout.nodes, -np.log(lo))
        if self.motion_free:
            lower_o, upper_o = _omega_bounds(w, motion.omega, self.hold_omega)
            lower, upper = np.r_[lower, -2 * np.ones(3), lower_o], np.r_[upper, 2 * np.ones(3), upper_o]
        result = solve(polish_loss(batch, layout, motion), x0, lower, upper, solver, iterations=s.polish_iterations,
                       norm_slice=slice(layout.nodes, layout.nodes + 3) if self.motion_free else None)
        polished = layout.motion(result.x, motion)
        before, after = motion_objective(batch, motion), motion_objective(batch, polished)
        note = ""
        if not after <= before:   # the objective jumps where a vote enters a pixel: the motion's own rounding
            polished, after = motion, before   # can land on the other side of the solver's end point
            result, note = replace(result, kept_start=True), "the end scored worse as a motion: kept the start"
        bound = omega_on_bound(polished.omega, s.max_omega) if self.motion_free and not self.hold_omega else ()
        nodes = int(np.sum((result.x[:layout.nodes] <= lower[:layout.nodes] + 1e-9)
                           | (result.x[:layout.nodes] >= upper[:layout.nodes] - 1e-9)))
        log = _log(self.name, before, after, [result], time.perf_counter() - start, bound,
                   note="; ".join(filter(None, (note, f"{nodes} of {layout.nodes} depth nodes at the depth_range "
                                                             "bounds" if nodes else ""))))
        return polished, log
