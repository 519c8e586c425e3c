"""The fit as a pipeline of stages: the order of each model's stages on one screen, and the stages.

Each stage is a small frozen object that names its parameters, its objective and its schedule, and
solves through the one solver layer (:func:`cmax.fitting.solvers.solve`). A stage reads the frozen
:class:`~cmax.fitting.window.Window` and the :class:`Motion` so far and returns a new :class:`Motion`
with a :class:`StageLog`; it never hands back a motion that scores worse on its objective than the
one it got (the solver layer keeps the start when it ends worse, and the stage says so).

The order (:func:`stages_for`)::

    flow      FlowStage                                    (coarse to fine over image scales)
    rotation  RotationStage                                (coarse to fine over image scales)
    se3       pose known:          DepthSweepStage
              default:             PatchFlowStage -> LocalRefineStage -> DepthSweepStage
              motion_members > 1:  MotionMembersStage(PatchFlowStage -> LocalRefineStage) -> DepthSweepStage
              motion_init=starts:  RotationStage -> TranslationStartsStage -> DepthSweepStage
              then alternations x (MotionWithDepthStage -> DepthSweepStage)
              then, with settings.polish: SharedPolishStage  (cmax.fitting.polish: cmax.contrast.SHARED_OBJECTIVE,
                                                              the objective learned trains on)

References: G. Gallego, H. Rebecq, D. Scaramuzza, "A unifying contrast maximization framework for
event cameras", CVPR 2018 (the warps and the contrast); S. Shiba, Y. Aoki, G. Gallego, "Secrets of
event-based optical flow", ECCV 2022 (patch-wise contrast, multi-reference); "Event collapse in
contrast maximization frameworks", Sensors 2022 (the deformation guard).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Protocol

import numpy as np
import torch

from cmax.contrast._warp_kernels import warp_rotation_compiled
from cmax.fitting.depth_sweep import sweep_inverse_depth
from cmax.fitting.motion import omega_on_bound, refine_motion_local
from cmax.fitting.patch_flow import motion_from_flows, patch_flows
from cmax.fitting.quality import _distance_deg
from cmax.fitting.settings import MotionInit, Polish, Refinement
from cmax.fitting.solvers import Solver, SolveResult, Tolerances, solve
from cmax.fitting.window import SE3Model, Window
from cmax.warp import warp_flow, warp_rotation

__all__ = ["Motion", "StageLog", "Stage", "stages_for", "run_stages", "FlowStage", "RotationStage",
           "PatchFlowStage", "LocalRefineStage", "TranslationStartsStage", "MotionWithDepthStage",
           "DepthSweepStage", "MotionMembersStage", "consensus", "directions"]


@dataclass(frozen=True)
class Motion:
    """What the stages pass on: flow [px/s] (2,) or None, v [m/s] (3,), omega [rad/s] (3,), inverse-depth
    grid (gh, gw) [1/m] or None, and the se3 scale ``speed`` (``|v|``) [m/s]."""

    flow: np.ndarray | None = None
    v: np.ndarray = field(default_factory=lambda: np.zeros(3))
    omega: np.ndarray = field(default_factory=lambda: np.zeros(3))
    inverse_depth: np.ndarray | None = None
    speed: float = 1.0
    alternatives: tuple[tuple[np.ndarray, np.ndarray], ...] = ()
    """Further (v, omega) starts an earlier stage proposes to the refinement."""


@dataclass(frozen=True)
class StageLog:
    """One stage of one fit: the ``stage``'s name; its objective (lower is better; NaN where it has none) at its
    start and at its end (``objective_before``, ``objective_after``); the solver's ``iterations`` and
    ``evaluations``, wall ``seconds`` and last ``message``; its ``success``; and the parameters that ended on a
    bound (``at_bound``, their names)."""

    stage: str
    objective_before: float
    objective_after: float
    iterations: int
    evaluations: int
    seconds: float
    message: str
    success: bool
    at_bound: tuple[str, ...] = ()


class Stage(Protocol):
    """``run(window, motion, solver) -> (motion, log)``; a stage that runs other stages
    (:class:`MotionMembersStage`) returns their logs, a tuple, and :func:`run_stages` lists each."""

    name: str

    def run(self, w: Window, motion: Motion, solver: Solver) -> tuple[Motion, StageLog | tuple[StageLog, ...]]:
        """Improve ``motion`` on window ``w`` through ``solver``; the new motion and the stage's log
        (objective before / after, iterations, seconds, the solver's message, success)."""


# ----------------------------------------------------------------------------------------------
# The order
# ----------------------------------------------------------------------------------------------
def stages_for(model: str, w: Window, *, pose_known: bool, hold_omega: bool,
               warm_v: np.ndarray | None = None) -> tuple[Stage, ...]:
    """The stages of ``model`` for a window with these settings, in order; ``warm_v`` (3,) is the
    warm start's translation (se3 ``init=``), tried as one more start. The flow and rotation stages
    start from the incoming :class:`Motion` (which holds the warm start's flow or omega)."""
    s = w.settings
    if model == "flow":
        return (FlowStage(),)
    if model == "rotation":
        return (RotationStage(),)
    polish = _polish(s.polish, pose_known, hold_omega)
    if pose_known:
        return (DepthSweepStage(), *polish)
    warm = None if warm_v is None or not np.linalg.norm(warm_v) > 0 else np.asarray(warm_v, float)
    if s.motion_init is MotionInit.PATCHES:
        motion = [PatchFlowStage(hold_omega, s.zero_rotation_start and not hold_omega, warm)]
        if s.motion_refinement is Refinement.LOCAL:
            motion.append(LocalRefineStage(hold_omega=hold_omega, warm_start=warm))
        if s.motion_members > 1:
            motion = [MotionMembersStage(tuple(motion), s.motion_members, s.members_agree_deg)]
    else:
        motion = ([] if hold_omega else [RotationStage()]) + [TranslationStartsStage(hold_omega, warm)]
    alternations = [MotionWithDepthStage(hold_omega=hold_omega), DepthSweepStage()] * s.alternations
    return (*motion, DepthSweepStage(), *alternations, *polish)


def _polish(mode: Polish, pose_known: bool, hold_omega: bool) -> tuple[Stage, ...]:
    """The final :class:`cmax.fitting.polish.SharedPolishStage` of se3 (none with ``Polish.NONE``); the motion
    stays held when the pose is known."""
    from cmax.fitting.polish import SharedPolishStage   # polish builds on this module's pieces

    if mode is Polish.NONE:
        return ()
    return (SharedPolishStage(motion_free=mode is Polish.DEPTH_MOTION and not pose_known, hold_omega=hold_omega),)


def run_stages(stages: tuple[Stage, ...], w: Window, motion: Motion, solver: Solver
               ) -> tuple[Motion, tuple[StageLog, ...]]:
    """Run ``stages`` in order from ``motion``; the final motion and every stage's log."""
    logs = []
    for stage in stages:
        motion, log = stage.run(w, motion, solver)
        logs.extend(log if isinstance(log, tuple) else (log,))    # a stage of stages logs each of them
    return motion, tuple(logs)


# ----------------------------------------------------------------------------------------------
# Shared pieces: the log of a stage's solves, the coarse-to-fine driver
# ----------------------------------------------------------------------------------------------
def _log(name: str, before: float, after: float, solves: list[SolveResult] | tuple[SolveResult, ...],
         seconds: float, at_bound: tuple[str, ...] = (), note: str = "", winner: int | None = None) -> StageLog:
    """A stage's log from its solves: it failed when a solve kept its start or the end scores worse than
    the start, or when a parameter ended on a bound. ``winner``: of solves from several starts, the one whose
    end the stage returns; only its own failure counts (a losing start that its solver could not improve does
    not fail the stage), and its message is the stage's."""
    kept = solves[winner].kept_start if winner is not None else any(r.kept_start for r in solves)
    worse = np.isfinite(before) and not after <= before
    message = (solves[-1 if winner is None else winner].message) if solves else "no solver"
    message = "; ".join(m for m in (note, message) if m)
    return StageLog(name, float(before), float(after), sum(r.iterations for r in solves),
                    sum(r.evaluations for r in solves), seconds, message,
                    not (kept or worse or at_bound), tuple(at_bound))


def coarse_to_fine(w: Window, loss_at_scale: Callable[[torch.Tensor, int], torch.Tensor], x0: np.ndarray,
                   lower: np.ndarray, upper: np.ndarray, solver: Solver, *,
                   tolerances: Tolerances | None = None) -> tuple[np.ndarray, list[SolveResult], float, float]:
    """Solve at each image scale of ``w.scales()`` from coarse to fine, warm-starting the next.

    Returns the parameters, the solves, and the full-resolution objective at the start and at the end;
    when the end scores worse at full resolution than the start, the start is returned.
    """
    x = np.clip(np.asarray(x0, dtype=np.float64), lower, upper)
    with torch.no_grad():
        before = float(loss_at_scale(torch.from_numpy(x), 1))
    solves = []
    for scale in w.scales():
        iterations = w.settings.iterations if scale == 1 else w.settings.coarse_iterations
        solves.append(solve(lambda p, s=scale: loss_at_scale(p, s), x, lower, upper, solver,
                            iterations=iterations, tolerances=tolerances))
        x = solves[-1].x
    after = solves[-1].fun
    if not after <= before:
        return np.clip(np.asarray(x0, dtype=np.float64), lower, upper), solves, before, before
    return x, solves, before, after


def warm_or_cold(loss: Callable[[torch.Tensor], torch.Tensor], warm: np.ndarray, lower: np.ndarray,
                 upper: np.ndarray, cold: str) -> tuple[np.ndarray, str]:
    """The start of a stage and the note on it: the incoming (warm) parameters, or zero (``cold`` names it)
    when ``loss`` scores zero lower (each clipped to ``[lower, upper]``; a NaN loss ranks last). A motion
    carried over from another window can fit this one worse than no motion at all, and is then not solved from.
    Zero incoming parameters: they, without evaluating ``loss``, and no note."""
    warm = np.asarray(warm, dtype=np.float64)
    if not warm.any():
        return warm, ""
    zero = np.zeros_like(warm)
    with torch.no_grad():
        values = np.array([float(loss(torch.from_numpy(np.clip(x, lower, upper)))) for x in (warm, zero)])
    if int(np.argmin(np.where(np.isnan(values), np.inf, values))) == 0:
        return warm, f"from the warm start (it scores better than {cold})"
    return zero, f"from {cold} (it scores better than the warm start)"


def _omega_bounds(w: Window, omega: np.ndarray, hold: bool) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of the angular-velocity parameters [px]: ``+-max_omega``, or equal to ``omega`` when held."""
    if hold:
        value = np.asarray(omega, float) * w.omega_scale
        return value, value.copy()
    bound = w.settings.max_omega * w.omega_scale
    return -np.full(3, bound), np.full(3, bound)


# ----------------------------------------------------------------------------------------------
# Global-contrast stages: flow, rotation
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FlowStage:
    """Parameters: the flow as a displacement over the window [px] (2,). Objective: minus the normalised
    multi-reference contrast. Schedule: image scales coarse to fine, ``settings.flow_tolerances``, from the
    incoming flow (a warm start) or zero, whichever scores better (:func:`warm_or_cold`)."""

    name: str = "flow"

    def run(self, w: Window, motion: Motion, solver: Solver) -> tuple[Motion, StageLog]:
        start, ev = time.perf_counter(), w.ev
        bound = w.settings.max_flow_px * max(ev.width, ev.height)
        flow0 = np.zeros(2) if motion.flow is None else np.asarray(motion.flow, float)

        def loss(p: torch.Tensor, scale: int) -> torch.Tensor:
            x, y = warp_flow(ev.x, ev.y, w.dt_mid, (p / w.T).to(ev.x.dtype))
            return -w.contrast(x, y, scale)

        lower, upper = np.full(2, -bound), np.full(2, bound)
        x0, note = warm_or_cold(lambda p: loss(p, 1), flow0 * w.T, lower, upper, "zero flow")
        x, solves, before, after = coarse_to_fine(w, loss, x0, lower, upper, solver,
                                                  tolerances=w.settings.flow_tolerances)
        at_bound = tuple(f"flow_{a}" for a, value in zip("xy", x) if abs(value) >= 0.999 * bound)
        log = _log(self.name, before, after, solves, time.perf_counter() - start, at_bound, note=note)
        return replace(motion, flow=x / w.T), log


@dataclass(frozen=True)
class RotationStage:
    """Parameters: the angular velocity as pixels over the window (3,). Objective: minus the normalised
    multi-reference contrast of the rotation warp. Schedule: image scales coarse to fine, from the incoming
    rotation (a warm start) or zero, whichever scores better (:func:`warm_or_cold`)."""

    name: str = "rotation"

    def run(self, w: Window, motion: Motion, solver: Solver) -> tuple[Motion, StageLog]:
        start, ev, s = time.perf_counter(), w.ev, w.omega_scale
        bound = w.settings.max_omega * s

        def loss(p: torch.Tensor, scale: int) -> torch.Tensor:
            omega = (p / s).to(ev.x.dtype)
            warped = warp_rotation_compiled(ev.rays, w.dt_mid, omega, ev.K)   # CPU: the compiled warp
            x, y = warp_rotation(ev.rays, w.dt_mid, omega, ev.K) if warped is None else warped
            return -w.contrast(x, y, scale)

        lower, upper = np.full(3, -bound), np.full(3, bound)
        x0, note = warm_or_cold(lambda p: loss(p, 1), np.asarray(motion.omega, float) * s, lower, upper,
                                "no rotation")
        x, solves, before, after = coarse_to_fine(w, loss, x0, lower, upper, solver, tolerances=w.settings.tolerances)
        omega = x / s
        log = _log(self.name, before, after, solves, time.perf_counter() - start,
                   omega_on_bound(omega, w.settings.max_omega), note=note)
        return replace(motion, omega=omega), log


# ----------------------------------------------------------------------------------------------
# se3 stages
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PatchFlowStage:
    """Parameters: one flow per patch (2P,). Objective: the patches' summed normalised IWE variances
    (:class:`cmax.contrast.PatchFlowContrast`). Schedule: ``settings.patch_flow.sigmas`` wide to sharp. Then the
    twist from the motion-field equations (least squares over directions, no solver); with
    ``zero_rotation_start`` also the fit without rotation, passed on as a further start. With fewer
    than ``settings.patch_flow.min_patches`` patches holding events it runs :class:`RotationStage` and
    :class:`TranslationStartsStage`."""

    hold_omega: bool = False
    zero_rotation_start: bool = False
    warm_start: np.ndarray | None = None
    name: str = "patch_flow"

    def run(self, w: Window, motion: Motion, solver: Solver) -> tuple[Motion, StageLog]:
        start = time.perf_counter()
        flows = patch_flows(w, w.settings.patch_flow, solver)
        if len(flows.centres) < w.settings.patch_flow.min_patches:
            fallback = ([] if self.hold_omega else [RotationStage()]) + [
                TranslationStartsStage(self.hold_omega, self.warm_start)]
            motion, logs = run_stages(tuple(fallback), w, motion, solver)
            return motion, replace(logs[-1], stage=f"{self.name} (too few patches: {logs[-1].stage})",
                                   seconds=time.perf_counter() - start, success=all(log.success for log in logs))
        settings = w.settings.patch_flow

        def twist(omega):
            return motion_from_flows(flows.centres, flows.flows, flows.information, w.ev.K.double().numpy(),
                                     motion.speed, omega=omega, directions=settings.directions,
                                     cap_directions=settings.cap_directions, cap_radius=settings.cap_radius,
                                     negative_depth_penalty=settings.negative_depth_penalty,
                                     min_patches=settings.min_patches)

        v, omega, residual = twist(motion.omega if self.hold_omega else None)
        alternatives = (twist(np.zeros(3))[:2],) if self.zero_rotation_start else ()
        # the blur levels' objectives differ (blur, events): the stage has no one objective to compare
        solves = flows.solves
        log = StageLog(self.name, float("nan"), float("nan"), sum(r.iterations for r in solves),
                       sum(r.evaluations for r in solves), time.perf_counter() - start,
                       f"{len(flows.centres)} patches, motion-field residual {residual:.3g} px/s; "
                       f"{solves[-1].message}", not any(r.kept_start for r in solves))
        return replace(motion, v=v, omega=motion.omega if self.hold_omega else omega, alternatives=alternatives), log


@dataclass(frozen=True)
class LocalRefineStage:
    """Parameters: direction, angular velocity and one inverse depth per patch (6 + P,). Objective: the
    patch-wise normalised contrast (:class:`cmax.contrast.PatchMotionContrast`, in the parameters of
    :class:`cmax.fitting.motion.LocalMotionObjective`), ``|v|`` held.
    Schedule: one level, from the incoming motion, the earlier stages' alternatives and the warm start
    (``init=``); the best refined start wins. The refinement on the objective :mod:`learned` trains on
    is :class:`cmax.fitting.polish.SharedPolishStage` (``FitSettings.polish``), after the sweep."""

    hold_omega: bool = False
    warm_start: np.ndarray | None = None
    name: str = "local_refine"

    def run(self, w: Window, motion: Motion, solver: Solver) -> tuple[Motion, StageLog]:
        start = time.perf_counter()
        more = list(motion.alternatives)
        if self.warm_start is not None:
            more.append((motion.speed * self.warm_start / np.linalg.norm(self.warm_start), motion.omega))
        outcome = refine_motion_local(w, motion.v, motion.omega, motion.speed, w.settings.refine, solver,
                                      hold_omega=self.hold_omega, more_starts=more)
        log = _log(self.name, outcome.objective_before, outcome.objective_after, outcome.solves,
                   time.perf_counter() - start, outcome.at_bound, note=f"{1 + len(more)} starts",
                   winner=outcome.winner if outcome.solves else None)
        return replace(motion, v=outcome.v, omega=outcome.omega, alternatives=()), log


def member_seed(seed: int, member: int) -> int:
    """The subsampling and dither seed of member ``member`` of a fit with ``seed``: ``seed`` itself for
    member 0, then well-mixed draws of ``(seed, member)``."""
    if member == 0:
        return int(seed)
    return int(np.random.SeedSequence([int(seed), int(member)]).generate_state(1)[0])


def consensus(motions: list[Motion], agree_deg: float, duration_s: float) -> tuple[Motion, np.ndarray]:
    """The consensus of the members' se3 ``motions``: the mean direction (at the members' ``|v|``) and mean
    angular velocity of the members within ``agree_deg`` of their medoid (the member with the least summed
    distance to the others; distance: :func:`cmax.fitting.quality._distance_deg`, direction angle plus the
    rotation over ``duration_s``). Returns it (the medoid's other fields) and the members kept (M,) bool."""
    count = len(motions)
    distance = np.array([[_distance_deg(a.v, a.omega, b.v, b.omega, duration_s) for b in motions] for a in motions])
    medoid = int(np.argmin(distance.sum(1)))
    kept = distance[medoid] <= agree_deg
    units = np.array([m.v / np.linalg.norm(m.v) for m in motions])[kept]
    direction = units.mean(0)
    if not np.linalg.norm(direction) > 1e-9 * count:     # opposite members cancel (cannot pass agree_deg < 90)
        direction = units[0]
    speed = motions[medoid].speed
    v = speed * direction / np.linalg.norm(direction)
    omega = np.array([m.omega for m in motions])[kept].mean(0)
    return replace(motions[medoid], v=v, omega=omega, alternatives=()), kept


@dataclass(frozen=True)
class MotionMembersStage:
    """Runs the motion ``stages`` on ``members`` draws of the window (:meth:`Window.with_seed`: other
    subsamples and dithers of the same events, member 0 the window itself) from the same incoming motion,
    and passes on their :func:`consensus`. Each member's stages solve through the solver layer and log as
    usual (``"<stage> [member k]"``); this stage adds no solve of its own, so its log has no objective.

    Why: the local refinement's objective is nearly flat along the bas-relief valley (translation traded
    against rotation), so where the solve stops moves with details as small as the dither; the members'
    end points scatter around the truth and their mean lies nearer it (``docs/fitting.md``)."""

    stages: tuple[Stage, ...]
    members: int
    agree_deg: float
    name: str = "motion_members"

    def run(self, w: Window, motion: Motion, solver: Solver) -> tuple[Motion, tuple[StageLog, ...]]:
        start = time.perf_counter()
        ends, logs = [], []
        for member in range(self.members):
            drawn = w if member == 0 else w.with_seed(member_seed(w.settings.seed, member))
            end, member_logs = run_stages(self.stages, drawn, motion, solver)
            ends.append(end)
            logs += [replace(log, stage=f"{log.stage} [member {member}]") for log in member_logs]
        agreed, kept = consensus(ends, self.agree_deg, w.T)
        spread = max(_distance_deg(m.v, m.omega, agreed.v, agreed.omega, w.T) for m, k in zip(ends, kept) if k)
        log = StageLog(self.name, float("nan"), float("nan"), 0, 0, time.perf_counter() - start,
                       f"{int(kept.sum())} of {self.members} members within {self.agree_deg:g} deg of their medoid "
                       f"(farthest kept {spread:.1f} deg from the mean)", True)
        return agreed, (*logs, log)


def directions(count: int) -> list[np.ndarray]:
    """Start directions of the translation: the 6 camera axes, then the 8 diagonals."""
    axes = [np.array(a, float) for a in ((0, 0, 1), (0, 0, -1), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0))]
    if count <= 6:
        return axes[:max(count, 1)]
    diagonals = [np.array([a, b, c], float) / math.sqrt(3) for a in (1, -1) for b in (1, -1) for c in (1, -1)]
    return (axes + diagonals)[:count]


@dataclass(frozen=True)
class TranslationStartsStage:
    """Parameters: direction, angular velocity, one constant inverse depth (7,). Objective: the global
    se3 objective (:class:`cmax.fitting.window.SE3Model`). Schedule: every start direction (and the
    warm start) at image scale 2, then the best at full resolution."""

    hold_omega: bool = False
    warm_start: np.ndarray | None = None
    name: str = "translation_starts"

    def run(self, w: Window, motion: Motion, solver: Solver) -> tuple[Motion, StageLog]:
        start, s = time.perf_counter(), w.settings
        se3 = SE3Model(w, motion.speed, unit_norm=not solver.takes_equality)
        lo_q, hi_q = se3.q_bounds
        starts = directions(s.translation_starts)
        if self.warm_start is not None and np.linalg.norm(self.warm_start) > 0:
            starts = [self.warm_start / np.linalg.norm(self.warm_start)] + starts
        lower_o, upper_o = _omega_bounds(w, motion.omega, self.hold_omega)
        lower, upper = np.r_[-np.ones(3) * 2, lower_o, lo_q], np.r_[np.ones(3) * 2, upper_o, hi_q]
        solves, best = [], None
        for u0 in starts:
            x0 = np.r_[u0, motion.omega * se3.omega_scale, math.sqrt(lo_q * hi_q)]
            solves.append(solve(lambda p: se3.motion_loss(p, 2), x0, lower, upper, solver,
                                iterations=s.start_iterations, tolerances=s.tolerances, norm_slice=slice(0, 3)))
            if best is None or solves[-1].fun < best.fun:
                best = solves[-1]
        solves.append(solve(lambda p: se3.motion_loss(p, 1), best.x, lower, upper, solver,
                            iterations=s.iterations, tolerances=s.tolerances, norm_slice=slice(0, 3)))
        x = solves[-1].x
        omega = x[3:6] / se3.omega_scale
        bound = () if self.hold_omega else omega_on_bound(omega, s.max_omega)
        log = _log(self.name, solves[-1].fun_start, solves[-1].fun, solves, time.perf_counter() - start, bound,
                   note=f"{len(starts)} starts")
        return replace(motion, v=se3.speed * x[:3] / np.linalg.norm(x[:3]), omega=omega), log


@dataclass(frozen=True)
class MotionWithDepthStage:
    """Parameters: direction and angular velocity (6,). Objective: the global se3 objective with the
    depth grid held. Schedule: one solve at full resolution."""

    hold_omega: bool = False
    name: str = "motion_with_depth"

    def run(self, w: Window, motion: Motion, solver: Solver) -> tuple[Motion, StageLog]:
        start = time.perf_counter()
        se3 = SE3Model(w, motion.speed, unit_norm=not solver.takes_equality)
        lower_o, upper_o = _omega_bounds(w, motion.omega, self.hold_omega)
        q = torch.as_tensor(motion.inverse_depth.reshape(-1) * se3.q_scale, dtype=torch.float64)
        result = solve(lambda p: se3.motion_loss(p, 1, q_fixed=q), np.r_[motion.v / se3.speed,
                       motion.omega * se3.omega_scale], np.r_[-np.ones(3) * 2, lower_o],
                       np.r_[np.ones(3) * 2, upper_o], solver, iterations=w.settings.iterations,
                       tolerances=w.settings.tolerances, norm_slice=slice(0, 3))
        omega = result.x[3:6] / se3.omega_scale
        bound = () if self.hold_omega else omega_on_bound(omega, w.settings.max_omega)
        log = _log(self.name, result.fun_start, result.fun, [result], time.perf_counter() - start, bound)
        return replace(motion, v=se3.speed * result.x[:3] / np.linalg.norm(result.x[:3]), omega=omega), log


@dataclass(frozen=True)
class DepthSweepStage:
    """Parameters: the inverse-depth grid. Objective: the sweep's per-event normalised vote
    (:class:`cmax.contrast.SweepNodeCost`), maximised per node by a discrete search with semi-global
    matching (no solver). Schedule: the whole ``depth_range`` on a coarser grid, then relative sweeps."""

    name: str = "depth_sweep"

    def run(self, w: Window, motion: Motion, solver: Solver) -> tuple[Motion, StageLog]:
        start, s, ev = time.perf_counter(), w.settings, w.ev
        lo, hi = s.depth_range
        result = sweep_inverse_depth(
            ev.rays, w.dt_mid, ev.polarity, motion.v, motion.omega, ev.K, height=ev.height, width=ev.width,
            grid_shape=w.grid.shape, index=w.index, weight=w.weight, rho_range=(1.0 / hi, 1.0 / lo),
            candidates=s.depth_candidates, sigma=s.sigma, smoothness=tuple(s.depth_smoothness),
            coarsening=s.depth_coarsening, refinements=tuple(s.depth_refinements),
            refine_candidates=s.sweep.refine_candidates, chunk=s.sweep.chunk, border_px=s.sweep.border_px,
            vote_scale_quantile=s.sweep.vote_scale_quantile)
        shares = depth_on_bounds(result.inverse_depth, w.index, w.weight, (1.0 / hi, 1.0 / lo), s.depth_candidates)
        bound = tuple(name for name, share in shares.items() if share >= s.depth_bound_fraction)
        message = (f"plane sweep over {len(result.candidates)} inverse depths (no solver); events' depth on the near "
                   f"bound {shares['depth_near']:.0%}, on the far bound {shares['depth_far']:.0%}")
        log = StageLog(self.name, float("nan"), float("nan"), 0, 0, time.perf_counter() - start, message, not bound,
                       bound)
        return replace(motion, inverse_depth=result.inverse_depth.reshape(w.grid.shape)), log


def depth_on_bounds(inverse_depth: np.ndarray, index: torch.Tensor, weight: torch.Tensor,
                    rho_range: tuple[float, float], candidates: int) -> dict[str, float]:
    """Shares of the events' depth on each end of the range: ``{"depth_near": ..., "depth_far": ...}``.

    ``inverse_depth`` (G,) [1/m] of the grid's nodes, each event's nodes and bilinear weights ``index``,
    ``weight`` (N, 4) (:meth:`cmax.warp.DepthGrid.weights`), ``rho_range = (1/far, 1/near)`` [1/m]; a node is on
    an end within half a step of a ``candidates``-plane sweep over the range (uniform in log inverse depth).
    """
    rho = np.asarray(inverse_depth, float).reshape(-1)
    low, high = rho_range
    half_step = 0.5 * np.log(high / low) / max(candidates - 1, 1)
    mass = np.bincount(index.reshape(-1).numpy(), weight.reshape(-1).double().numpy(), minlength=rho.size)
    total = float(mass.sum())
    if total <= 0:
        return {"depth_near": 0.0, "depth_far": 0.0}
    with np.errstate(divide="ignore", invalid="ignore"):
        near = np.log(high / rho) <= half_step
        far = np.log(rho / low) <= half_step
    return {"depth_near": float(mass[near].sum()) / total, "depth_far": float(mass[far].sum()) / total}
