"""The shared-objective polish: the fit's last stage optimises the very objective learned trains on
(value = student_loss, a stationary point of it afterwards, never worse than its start, every solver)."""
from __future__ import annotations

import functools
import warnings
from dataclasses import replace

import numpy as np
import pytest
import torch

from benchmarks.synthetic_windows import make_window
from cmax import Camera, Events
from cmax.camera import sensor_pixels
from cmax.contrast import SHARED_OBJECTIVE, EventWindows
from cmax.fitting import FitSettings, fit
from cmax.geometry import se3_exp
from cmax.fitting.pipeline import Motion, stages_for
from cmax.fitting.polish import SharedPolishStage, polish_layout, polish_loss, window_events
from cmax.fitting.settings import Polish
from cmax.fitting.solvers import Solver, SolveResult
from cmax.fitting.window import SensorPixels, Window
from learned.losses import student_loss

GRID = (6, 8)


@functools.lru_cache(maxsize=None)
def small_window():
    """A constant-twist indoor_flying window at 120 x 90 (exact twist and depth)."""
    return make_window("indoor_flying", 3, width=120, height=90, focal=90.0, duration_s=0.1, max_frames=60)


def prepared(iterations: int = 30, max_events: int = 4000) -> tuple[Window, Motion]:
    """The window as the stages see it, and a start: the true twist, a constant inverse depth of 1/3 m^-1
    with a smooth ripple (a start that is not the optimum)."""
    sw = small_window()
    settings = FitSettings(max_events=max_events, depth_range=(1.0, 6.5), polish_iterations=iterations,
                           contrast="variance", polarity_split=False)
    w = Window.from_events(sw.events, sw.K, settings, GRID)
    rows, cols = np.meshgrid(np.linspace(0, 1, GRID[0]), np.linspace(0, 1, GRID[1]), indexing="ij")
    rho = (1.0 / 3.0) * (1.0 + 0.2 * np.sin(3 * rows + 2 * cols))
    speed = float(np.linalg.norm(sw.twist[:3]))
    return w, Motion(v=sw.twist[:3], omega=sw.twist[3:], inverse_depth=rho, speed=speed)


def student_value(motion: Motion) -> float:
    """learned's loss without a teacher at ``motion``, on events prepared independently of the stage."""
    sw = small_window()
    w, _ = prepared()
    events = EventWindows.from_events(sw.events, sw.K, max_events=w.settings.max_events, seed=w.settings.seed,
                                      speed=motion.speed).to(torch.float64)
    inverse_depth = torch.as_tensor(np.asarray(motion.inverse_depth, float)).reshape(1, 1, *GRID)
    twist = torch.as_tensor(np.r_[motion.v, motion.omega], dtype=torch.float64)[None]
    loss, _ = student_loss(inverse_depth, twist, events, teacher_inverse_depth=None)
    return float(loss)


@functools.lru_cache(maxsize=None)
def polished(solver: str, motion_free: bool):
    w, start = prepared()
    motion, log = SharedPolishStage(motion_free=motion_free).run(w, start, _solver(solver))
    return start, motion, log


def _solver(name: str) -> Solver:
    from cmax.fitting.solvers import make_solver

    return make_solver(name)


def test_the_polish_optimises_learned_student_loss():
    """Same events, same parameters: the stage's objective is learned's loss to 1e-6, at its start and end."""
    start, motion, log = polished("scipy", True)
    assert student_loss.__kwdefaults__["objective"] is SHARED_OBJECTIVE
    assert abs(log.objective_before - student_value(start)) <= 1e-6 * abs(log.objective_before)
    assert abs(log.objective_after - student_value(motion)) <= 1e-6 * abs(log.objective_after)
    assert log.objective_after < log.objective_before and log.success and log.stage == "shared_polish"


@functools.lru_cache(maxsize=None)
def lens_window():
    """``small_window``'s events as a camera with a barrel lens records them (OpenCV's projectPoints, nearest
    sensor pixel, those leaving the image dropped) and that camera (k1 = -0.25: up to about 10 px at the corners)."""
    import cv2

    sw = small_window()
    distortion = np.array([-0.25, 0.06, 0.0, 0.0])
    ev = sw.events
    rays = np.column_stack([ev.x, ev.y, np.ones(len(ev))]) @ np.linalg.inv(sw.K).T
    pixels, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), sw.K, distortion)
    xy = np.rint(pixels.reshape(-1, 2)).astype(np.int64)
    inside = (xy[:, 0] >= 0) & (xy[:, 0] < ev.width) & (xy[:, 1] >= 0) & (xy[:, 1] < ev.height)
    events = Events(xy[inside, 0], xy[inside, 1], ev.t[inside], ev.p[inside], ev.width, ev.height)
    return events, Camera(sw.K, ev.width, ev.height, distortion)


def test_the_polish_optimises_learned_student_loss_through_a_lens():
    """The same through a lens: the fit's window holds each event dithered over its sensor pixel and mapped
    through the lens (cmax.fit with a Camera), and learned reads the same events (EventWindows.from_events with
    the camera), so the stage's objective is learned's loss to 1e-6 at its start and end; learned's events
    were the nearest undistorted pixels with a dither around them, whose loss is not the stage's."""
    events, camera = lens_window()
    w0, start = prepared()
    w = Window.from_events(camera.undistort_events(events), camera.pinhole_K, w0.settings, GRID,
                           SensorPixels(sensor_pixels(events, camera), camera))
    motion, log = SharedPolishStage(motion_free=True).run(w, start, _solver("scipy"))

    def student(motion: Motion, batch: EventWindows) -> float:
        inverse_depth = torch.as_tensor(np.asarray(motion.inverse_depth, float)).reshape(1, 1, *GRID)
        twist = torch.as_tensor(np.r_[motion.v, motion.omega], dtype=torch.float64)[None]
        return float(student_loss(inverse_depth, twist, batch.with_speed([motion.speed]),
                                  teacher_inverse_depth=None)[0])

    prepare = dict(max_events=w.settings.max_events, seed=w.settings.seed)
    learned_reads = EventWindows.from_events(events, camera, **prepare).to(torch.float64)
    assert abs(log.objective_before - student(start, learned_reads)) <= 1e-6 * abs(log.objective_before)
    assert abs(log.objective_after - student(motion, learned_reads)) <= 1e-6 * abs(log.objective_after)
    assert log.objective_after < log.objective_before and log.success
    rounded = EventWindows.from_events(camera.undistort_events(events), camera.pinhole_K, **prepare)
    assert abs(log.objective_after - student(motion, rounded.to(torch.float64))) > 1e-4 * abs(log.objective_after)


def _loss_at(motion_free: bool, motion: Motion):
    """``(x (n,), f)``: the polish parameters of ``motion`` and the polish's loss as a numpy function."""
    w, _ = prepared()
    layout = polish_layout(w, motion_free)
    loss = polish_loss(window_events(w, motion.speed), layout, motion)

    def f(x: np.ndarray) -> float:
        with torch.no_grad():
            return float(loss(torch.as_tensor(x, dtype=torch.float64)))

    return layout.start(motion), f, loss


def _gradient(motion_free: bool, motion: Motion) -> np.ndarray:
    x, _, loss = _loss_at(motion_free, motion)
    p = torch.tensor(x, requires_grad=True)
    (grad,) = torch.autograd.grad(loss(p), p)
    return grad.numpy()


@pytest.mark.parametrize("motion_free", [False, True])
def test_the_polished_point_is_nearly_a_local_minimum(motion_free):
    """Near-stationary at the parameters' scales: no step of 1e-3 to 1e-1 (log inverse depth, direction,
    px) along the end's own gradient, the start's gradient or random directions lowers the loss by more
    than 10 % of what the polish gained (measured: 4-5 %; the solver stops on the objective's kinks, see
    the xfail below); from the start, the start's gradient direction lowers it by more."""
    start, motion, log = polished("scipy", motion_free)
    gain = log.objective_before - log.objective_after
    assert gain > 0
    x, f, _ = _loss_at(motion_free, motion)
    rng = np.random.default_rng(0)
    g0, g1 = _gradient(motion_free, start), _gradient(motion_free, motion)
    directions = [-g0 / np.linalg.norm(g0), -g1 / np.linalg.norm(g1), *rng.normal(size=(4, x.size))]
    drops = [f(x) - f(x + h * d / np.linalg.norm(d)) for d in directions for h in (1e-3, 1e-2, 1e-1)]
    assert max(drops) < 0.1 * gain, (max(drops), gain)
    x0, f0, _ = _loss_at(motion_free, start)
    assert max(f0(x0) - f0(x0 + h * directions[0]) for h in (1e-3, 1e-2, 1e-1)) > 0.1 * gain


@pytest.mark.xfail(strict=True, reason="the shared objective is piecewise smooth: a bilinear vote entering or "
                   "leaving a pixel switches that pixel's average timestamp on or off (eps 1e-9), so the autograd "
                   "gradient at the polished point is dominated by one or two such events; the smooth variants "
                   "that pass lose the depth accuracy (docs/fitting.md)")
def test_the_gradient_vanishes_at_the_polished_point():
    start, motion, _ = polished("scipy", False)
    assert np.linalg.norm(_gradient(False, motion)) < 1e-2 * np.linalg.norm(_gradient(False, start))


class _Wild(Solver):
    """A backend that always ends far from its start (a forced failure)."""

    def solve(self, problem):
        x = np.clip(problem.x0 + 1.5, problem.lower, problem.upper)
        return SolveResult(x, problem.fun_and_grad(x)[0], 1, 1, "wild", True, 0.0)


def test_the_polish_never_returns_a_worse_objective_than_its_start():
    w, start = prepared()
    motion, log = SharedPolishStage().run(w, start, _Wild())
    assert not log.success and "kept the start" in log.message
    np.testing.assert_allclose(motion.inverse_depth, start.inverse_depth, rtol=1e-12)
    np.testing.assert_allclose(motion.v, start.v, rtol=1e-12)
    assert log.objective_after == log.objective_before == pytest.approx(student_value(start), rel=1e-9)


class _Boasting(Solver):
    """A backend that ends far from its start and reports a value far below the start's for it."""

    def solve(self, problem):
        x = np.clip(problem.x0 + 1.5, problem.lower, problem.upper)
        return SolveResult(x, problem.fun_and_grad(problem.x0)[0] - 1.0, 1, 1, "boasting", True, 0.0)


def test_the_polish_judges_the_motion_it_returns_not_the_solver_s_word():
    """The stage scores the motion it would hand back (learned's loss at that inverse depth and twist); when
    that scores worse than the start, whatever the backend reported, it keeps the start and says so."""
    w, start = prepared()
    motion, log = SharedPolishStage().run(w, start, _Boasting())
    assert not log.success and "kept the start" in log.message
    np.testing.assert_allclose(motion.inverse_depth, start.inverse_depth, rtol=1e-12)
    assert log.objective_after == log.objective_before == pytest.approx(student_value(start), rel=1e-9)


@pytest.mark.parametrize("solver", ["scipy", "torch", "casadi"])
def test_every_solver_runs_the_polish_and_lowers_the_loss(solver):
    if solver == "casadi":
        pytest.importorskip("casadi")
    start, motion, log = polished(solver, True)
    assert log.objective_after < log.objective_before
    assert abs(log.objective_after - student_value(motion)) <= 1e-6 * abs(log.objective_after)
    assert np.linalg.norm(motion.v) == pytest.approx(start.speed, rel=1e-9)     # |v| held
    best = polished("scipy", True)[2].objective_after
    assert log.objective_after <= best + 0.5 * (log.objective_before - best)    # most of scipy's decrease


def test_polish_settings_are_typed_and_placed_last():
    assert FitSettings(polish="depth_motion").polish is Polish.DEPTH_MOTION
    with pytest.raises(ValueError, match="polish must be one of"):
        FitSettings(polish="sometimes")
    with pytest.raises(ValueError, match="polish_iterations"):
        FitSettings(polish_iterations=0)
    w, _ = prepared()
    settings = replace(w.settings, polish=Polish.DEPTH_MOTION)
    wp = Window(w.ev, settings, w.grid)
    default = stages_for("se3", wp, pose_known=False, hold_omega=False)
    assert isinstance(default[-1], SharedPolishStage) and default[-1].motion_free
    known = stages_for("se3", wp, pose_known=True, hold_omega=False)
    assert [type(s).__name__ for s in known] == ["DepthSweepStage", "SharedPolishStage"] and not known[-1].motion_free
    none = Window(w.ev, replace(settings, polish=Polish.NONE), w.grid)
    assert not any(isinstance(s, SharedPolishStage) for s in stages_for("se3", none, pose_known=False,
                                                                          hold_omega=False))


def test_fit_with_the_polish_returns_the_polished_depth():
    sw = small_window()
    speed = float(np.linalg.norm(sw.twist[:3]))
    duration_s = (int(sw.events.t[-1]) - int(sw.events.t[0])) * 1e-6
    with warnings.catch_warnings():    # 120 x 90 px: under 1 px of parallax (LowParallaxWarning)
        warnings.simplefilter("ignore")
        r = fit(sw.events, sw.K, pose=se3_exp(sw.twist * duration_s), depth_range=(1.0, 6.5), max_events=6000,
                polish="depth")
    assert [log.stage for log in r.stages] == ["depth_sweep", "shared_polish"]
    log = r.stages[-1]
    assert log.objective_after <= log.objective_before
    assert np.isfinite(r.depth[r.mask]).all() and speed > 0
