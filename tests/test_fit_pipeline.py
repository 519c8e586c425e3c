"""The fit as a pipeline: one solve path (solver= matters on the default se3 path), the per-stage log,
success, never worse than the start, bounds reported, warm starts, typed settings."""
from __future__ import annotations

import functools
import warnings

import numpy as np
import pytest
import torch

from benchmarks.synthetic_windows import make_window
from cmax.fitting import (
    BoundWarning, FitSettings, LowMotionWarning, MotionInit, PatchFlowSettings, Refinement, fit, fit_sequence,
)
from cmax.fitting.solvers import ScipySolver, Solver, SolveResult, solve


@functools.lru_cache(maxsize=None)
def small_se3():
    """A constant-twist indoor_flying window at 120 x 90 (exact twist)."""
    return make_window("indoor_flying", 3, width=120, height=90, focal=90.0, duration_s=0.1, max_frames=60)


@functools.lru_cache(maxsize=None)
def small_rotation():
    return make_window("rotation", 1, width=120, height=90, focal=90.0, duration_s=0.05, max_frames=60)


# ----------------------------------------------------------------------------------------------
# The solver layer
# ----------------------------------------------------------------------------------------------
class _Wild(Solver):
    """A backend that always ends far from the start (a forced failure)."""

    def solve(self, problem):
        x = np.clip(problem.x0 + 3.0, problem.lower, problem.upper)
        return SolveResult(x, problem.fun_and_grad(x)[0], 1, 1, "wild", True, 0.0)


def test_solve_keeps_the_start_when_the_backend_ends_worse():
    def loss(p):                                         # minimum at (1, -2)
        return ((p - torch.tensor([1.0, -2.0], dtype=p.dtype)) ** 2).sum()

    start = np.array([1.0, -1.5])                        # loss 0.25; the wild solver ends at (4, 1.5): 21.25
    result = solve(loss, start, np.full(2, -10.0), np.full(2, 10.0), _Wild(), iterations=5)
    np.testing.assert_array_equal(result.x, start)
    assert result.kept_start and not result.success and result.fun == pytest.approx(0.25)
    assert "kept the start" in result.message
    good = solve(loss, start, np.full(2, -10.0), np.full(2, 10.0), ScipySolver(), iterations=50)
    np.testing.assert_allclose(good.x, [1.0, -2.0], atol=1e-6)
    assert good.success and not good.kept_start and good.fun_start == pytest.approx(0.25)


def test_a_forced_failure_keeps_the_start_and_reports_it():
    w = small_rotation()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LowMotionWarning)
        r = fit(w.events, w.K, model="rotation", solver=_Wild())
    assert not r.success and r.stages[0].stage == "rotation" and not r.stages[0].success
    assert "kept the start" in r.message
    np.testing.assert_array_equal(r.omega, np.zeros(3))   # the start, not the wild point
    assert r.objective_after == pytest.approx(1.0)        # the unwarped events' contrast


# ----------------------------------------------------------------------------------------------
# The default se3 path through the one solver layer
# ----------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=None)
def se3_fit(solver: str):
    w = small_se3()
    return fit(w.events, w.K, speed=float(np.linalg.norm(w.twist[:3])), solver=solver, depth_range=(1.0, 6.5))


def test_default_se3_path_logs_its_stages():
    r = se3_fit("scipy")
    assert [log.stage for log in r.stages] == ["patch_flow", "local_refine", "depth_sweep"]
    assert r.success and r.iterations == sum(log.iterations for log in r.stages) > 0
    refine = r.stages[1]
    assert refine.objective_after <= refine.objective_before and refine.seconds > 0 and refine.message


@pytest.mark.parametrize("solver", ["casadi", "torch"])
def test_solvers_reach_the_same_optimum_on_the_default_se3_path(solver):
    """scipy, casadi (|v| = speed as an equality constraint) and torch: each solves every stage (the
    results differ), and all reach the same contrast within 1%. (The objective is flat along some
    directions: on this window casadi's direction is ~10 deg from scipy's at the same contrast; on the
    refinement's own patch-wise objective torch's Adam ends 1.2% short of L-BFGS-B.)"""
    reference, other = se3_fit("scipy"), se3_fit(solver)
    assert not np.array_equal(reference.v, other.v)                     # the backend is used
    assert other.objective_after == pytest.approx(reference.objective_after, rel=0.01)
    assert other.stages[1].objective_after == pytest.approx(reference.stages[1].objective_after, rel=0.02)
    np.testing.assert_allclose(np.linalg.norm(other.v), np.linalg.norm(small_se3().twist[:3]), rtol=1e-9)


def test_warm_start_is_one_more_start_and_never_scores_worse():
    w = small_se3()
    cold = se3_fit("scipy")
    warm = fit(w.events, w.K, speed=float(np.linalg.norm(w.twist[:3])), depth_range=(1.0, 6.5), init=cold)
    assert "2 starts" in warm.stages[1].message and "1 starts" in cold.stages[1].message
    assert warm.stages[1].objective_after <= cold.stages[1].objective_after


def test_fit_sequence_warm_starts_se3_windows():
    w = small_se3()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")                   # short windows: little parallax
        sequence = fit_sequence(w.events, w.K, "se3", window_us=45_000, speed=float(np.linalg.norm(w.twist[:3])),
                                depth_range=(1.0, 6.5))
    first, second = sequence.results[:2]
    assert "1 starts" in first.stages[1].message and "2 starts" in second.stages[1].message


def test_warm_start_moves_the_start_of_flow_and_rotation():
    w = small_rotation()
    cold = fit(w.events, w.K, model="rotation")
    warm = fit(w.events, w.K, model="rotation", init=cold)
    assert warm.stages[0].objective_before < cold.stages[0].objective_before      # starts at the optimum
    assert warm.objective_after == pytest.approx(cold.objective_after, rel=1e-3)


# ----------------------------------------------------------------------------------------------
# Bounds and too little motion
# ----------------------------------------------------------------------------------------------
def test_a_rotation_beyond_the_bound_is_reported_not_clipped_silently():
    w = small_rotation()
    rate = float(np.linalg.norm(w.twist[3:]))
    with pytest.warns(BoundWarning, match="ended on its bound"):
        r = fit(w.events, w.K, model="rotation", max_omega=0.3 * rate)
    assert not r.success and r.stages[0].at_bound
    free = fit(w.events, w.K, model="rotation")
    assert free.success and not free.stages[0].at_bound


def _fit_warned(*args, **kwargs):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = fit(*args, **kwargs)
    return r, any(issubclass(c.category, LowMotionWarning) for c in caught)


def test_a_flow_of_one_to_two_pixels_is_within_target_or_warned():
    """The issue's case: a textured two-plane scene, lateral motion of ~1.4 px over the window."""
    w = make_window("two_planes", 1, duration_s=0.03)
    T = (w.events.t[-1] - w.events.t[0]) * 1e-6
    true_px = w.K[0, 0] * np.linalg.norm(w.twist[:2]) / np.nanmedian(w.depth) * T
    assert 1.0 < true_px < 2.0
    r, warned = _fit_warned(w.events, w.K, model="flow")
    assert r.objective_after >= r.objective_before                     # never worse than the unwarped start
    flow_px = w.K[0, 0] * w.twist[:2] / np.nanmedian(w.depth) * T       # the median depth's flow
    within = np.linalg.norm(np.abs(r.flow * T) - np.abs(flow_px)) <= 0.2
    assert warned or within, (r.flow * T, flow_px)


def test_a_rotation_of_about_one_pixel_is_within_target_or_warned():
    w = make_window("rotation", 0, duration_s=0.008)
    truth = w.twist[3:]
    T = (w.events.t[-1] - w.events.t[0]) * 1e-6
    assert 0.5 < np.linalg.norm(truth) * w.K[0, 0] * T < 2.0
    r, warned = _fit_warned(w.events, w.K, model="rotation")
    assert r.objective_after >= r.objective_before
    within = np.linalg.norm(r.omega - truth) <= 0.02 * np.linalg.norm(truth)
    assert warned or within, (r.omega, truth)


def test_enough_motion_does_not_warn():
    w = small_rotation()
    r, warned = _fit_warned(w.events, w.K, model="rotation")
    assert not warned and r.motion_px > 2.0 and r.success


# ----------------------------------------------------------------------------------------------
# Typed settings
# ----------------------------------------------------------------------------------------------
def test_settings_take_strategies_as_enums_and_check_them():
    s = FitSettings(motion_init="starts", motion_refinement="none")
    assert s.motion_init is MotionInit.STARTS and s.motion_refinement is Refinement.NONE
    with pytest.raises(ValueError, match="motion_init"):
        FitSettings(motion_init="random")
    with pytest.raises(ValueError, match="patch_flow.grid"):
        PatchFlowSettings(grid=(0, 3))
    with pytest.raises(ValueError, match="max_omega"):
        FitSettings(max_omega=-1.0)
    with pytest.raises(TypeError, match="patch_flow"):
        FitSettings(patch_flow={"grid": (4, 5)})


def test_settings_and_keyword_options_do_not_mix():
    w = small_rotation()
    with pytest.raises(TypeError, match="not both"):
        fit(w.events, w.K, model="rotation", settings=FitSettings(), max_events=1000)
