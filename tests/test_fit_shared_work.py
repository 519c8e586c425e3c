"""Work the default se3 fit shares between its result and its verdict instead of doing it twice: each shortcut
gives exactly what the fresh computation gives (the fresh computation is the expectation)."""
from __future__ import annotations

import functools
import warnings

import numpy as np
import pytest
import torch

from benchmarks.synthetic_windows import make_window
from cmax.fitting import FitSettings, QualitySettings, Verdict, fit
from cmax.fitting.api import DEFAULT_CONTRAST, DEFAULT_POLARITY_SPLIT, _low_motion, _result, _rotation_only, _warped
from cmax.fitting.pipeline import Motion
from cmax.fitting.quality import Alternative, MotionScorer, assess, best_turned
from cmax.fitting.solvers import make_solver
from cmax.fitting.window import Window


@functools.lru_cache(maxsize=None)
def driving():
    """A street seen driving forward at 120x90, its default se3 fit, the window as the fit builds it and the fit's
    motion."""
    w = make_window("driving", 2, width=120, height=90, focal=90.0, duration_s=0.1, max_frames=60)
    speed = float(np.linalg.norm(w.twist[:3]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = fit(w.events, w.K, speed=speed, depth_range=(1.0, 20.0))
    settings = FitSettings(depth_range=(1.0, 20.0), contrast=DEFAULT_CONTRAST["se3"],
                           polarity_split=DEFAULT_POLARITY_SPLIT["se3"])
    window = Window.from_events(w.events, w.K, settings, r.inverse_depth_grid.shape)
    motion = Motion(v=r.v, omega=r.omega, inverse_depth=r.inverse_depth_grid, speed=speed)
    return w, r, speed, window, motion


def test_the_fits_warped_events_shared_by_its_result_and_tests_give_what_warping_again_gives():
    """The fit warps its events by its motion to the reference times once (``_warped``) and hands them to the result
    (its objective), the cell and permutation tests and the rotation-only test: each gives what it gives when it
    warps them itself, and the result's objective is the contrast of a fresh warp to 1e-12."""
    w, r, _, window, motion = driving()
    warped = _warped(window, motion, window.dt)
    fresh = _result(window, w.events, w.K, "se3", motion, r.stages, scale_known=True, seconds=0.0)
    shared = _result(window, w.events, w.K, "se3", motion, r.stages, scale_known=True, seconds=0.0, warped=warped)
    x, y = _warped(window, motion, window.dt)
    with torch.no_grad():
        expected = float(window.contrast(x, y, 1))
    assert abs(shared.objective_after - expected) <= 1e-12 * abs(expected)
    assert shared.objective_after == fresh.objective_after and shared.parallax_px == fresh.parallax_px
    assert _low_motion(window, fresh, motion) == _low_motion(window, fresh, motion, warped=warped)
    solver = make_solver("scipy")
    (a, low_a, own_a), (b, low_b, own_b) = (_rotation_only(window, fresh, motion, solver),
                                            _rotation_only(window, fresh, motion, solver, warped))
    assert np.array_equal(a.omega, b.omega) and low_a == low_b and (own_a is None) == (own_b is None)


def test_the_bas_relief_turn_scores_on_the_ambiguity_tests_scorer():
    """The turn scores on the scorer the ambiguity test built for the fit (built once per verdict, was twice): its
    best turned motion is the one a scorer built anew gives, to the bit."""
    import cmax.fitting.quality as quality

    w, r, speed, window, _ = driving()
    settings = QualitySettings()
    scorer = MotionScorer.build(window, r.v, r.omega, speed, settings)
    fresh, shared = (best_turned(window, r.v, r.omega, speed, settings),
                     best_turned(window, r.v, r.omega, speed, settings, scorer))
    assert (fresh.name, fresh.gain, fresh.noise) == (shared.name, shared.gain, shared.noise)
    assert np.array_equal(fresh.v, shared.v) and np.array_equal(fresh.omega, shared.omega)
    solver = make_solver("scipy")
    alone, given = (assess(window, r.v, r.omega, speed, settings, solver, hold_omega=False),
                    assess(window, r.v, r.omega, speed, settings, solver, hold_omega=False, scorer=scorer))
    assert [(a.name, a.gain, a.noise) for a in alone[0]] == [(a.name, a.gain, a.noise) for a in given[0]]
    assert alone[1:] == given[1:]
    builds = []
    build = quality.MotionScorer.build.__func__

    def counted(cls, *args, **kwargs):
        builds.append(1)
        return build(cls, *args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(quality.MotionScorer, "build", classmethod(counted))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            flat = fit(w.events, w.K, speed=speed, depth_range=(1.0, 20.0),
                       quality=QualitySettings(min_ok_parallax_area=1, bas_relief_valley_deg=20.0))
    # the ambiguity test's, shared by the turn (scored: it did not fire) and the valley (scored: it fired)
    assert flat.verdict is Verdict.AMBIGUOUS and flat.quality.flat_valley and len(builds) == 1, flat.quality.reason


def test_the_turn_is_not_scored_where_another_rule_already_keeps_the_window_from_ok(monkeypatch):
    """The bas-relief turn can only make an ``ok`` ambiguous: on a window too sparse to be ``ok`` (``min_event_density``
    far above its events) it is not scored, and the verdict is the one the window gets with the turn off
    (``bas_relief_turn_deg`` 0), though a turned motion here always beats the fit; with the sparse rule off the same
    window's turn is scored and turns its ``ok`` into ``ambiguous``."""
    import cmax.fitting.api as api

    w, r, speed, _, _ = driving()
    calls = []

    def better(*args, **kwargs):                 # a turned motion that beats the fit: the turn's verdict if scored
        calls.append(1)
        return Alternative("turned_+a", r.v, r.omega, -1.0, 0.1, True)

    monkeypatch.setattr(api, "best_turned", better)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sparse, scored = (fit(w.events, w.K, speed=speed, depth_range=(1.0, 20.0),
                              quality=QualitySettings(min_ok_parallax_area=1, min_event_density=density))
                          for density in (1e9, 0.0))
    assert len(calls) == 1                                              # the second fit's only
    assert scored.verdict is Verdict.AMBIGUOUS and scored.quality.turned
    assert sparse.verdict is Verdict.AMBIGUOUS and sparse.quality.sparse and not sparse.quality.turned
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        unturned = fit(w.events, w.K, speed=speed, depth_range=(1.0, 20.0),
                       quality=QualitySettings(min_ok_parallax_area=1, min_event_density=1e9, bas_relief_turn_deg=0.0))
    assert len(calls) == 1 and unturned.quality.summary() == sparse.quality.summary()   # as without the turn at all
