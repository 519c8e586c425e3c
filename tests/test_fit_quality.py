"""The quality verdict of ``cmax.fit`` (ok / ambiguous / low parallax / failed), the ambiguity test
against the mirrored, rotation-flipped and bas-relief alternatives, and the resolution of ambiguous
windows from their neighbours in ``fit_sequence``."""
from __future__ import annotations

import functools
import math
import warnings
from dataclasses import replace

import numpy as np
import pytest

from benchmarks.synthetic_windows import make_window
from cmax import Events
from cmax.fitting import FitSettings, LowMotionWarning, LowParallaxWarning, QualitySettings, Verdict, fit, fit_sequence
from cmax.fitting import sequence as sequence_module
from cmax.fitting.quality import (Alternative, LowMotion, LowMotionCause, Quality, choose_from_neighbours,
                                  choose_from_run, rate_change, verdict_of)
from cmax.fitting.solvers import Solver, SolveResult


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


@functools.lru_cache(maxsize=None)
def clear_window():
    """A street seen driving forward (3 px of parallax): the fit is within about 20 deg of the true direction
    (17.5-20.0 deg over the fit seeds 0-5; float rounding alone moves it by 2 deg). Fitted with the small-parallax
    threshold unscaled (``min_ok_parallax_area=1``): at 120x90 the scaled one (8.7 px,
    :func:`cmax.fitting.quality.min_ok_parallax`) calls these 3 px ambiguous, and the tests that use this window
    are about the other rules. So is the flat-valley rule off (``bas_relief_valley_deg=0``): a motion 20 deg along
    the bas-relief trade scores at the edge of its noise on this fit (0.97 of it on an Intel Xeon host), a verdict
    that float rounding can flip."""
    w = make_window("driving", 2, width=120, height=90, focal=90.0, duration_s=0.1, max_frames=60)
    return w, fit(w.events, w.K, speed=float(np.linalg.norm(w.twist[:3])), depth_range=(1.0, 20.0),
                  quality=QualitySettings(min_ok_parallax_area=1, bas_relief_valley_deg=0.0))


# ----------------------------------------------------------------------------------------------
# The verdict of one window
# ----------------------------------------------------------------------------------------------
def _alt(name: str, gain: float, noise: float = 0.1) -> Alternative:
    return Alternative(name, np.array([-1.0, 0, 0]), np.zeros(3), gain, noise, gain <= noise)


def test_the_worst_verdict_wins():
    close, far = _alt("mirrored", 0.05), _alt("bas_relief", 0.5)
    parallax = LowMotion(LowMotionCause.PARALLAX, "parallax 0.2 px")
    failed = verdict_of(success=False, failed_stages=["local_refine"], low_motion=parallax, alternatives=[close])
    assert failed.verdict is Verdict.FAILED and failed.cause is None
    low = verdict_of(success=True, failed_stages=[], low_motion=parallax, alternatives=[close])
    assert low.verdict is Verdict.LOW_PARALLAX and "0.2 px" in low.reason and low.cause is LowMotionCause.PARALLAX
    assert low.summary()["cause"] == "parallax"
    ambiguous = verdict_of(success=True, failed_stages=[], low_motion=None, alternatives=[close, far])
    assert ambiguous.verdict is Verdict.AMBIGUOUS and "mirrored within noise" in ambiguous.reason
    assert "bas_relief" not in ambiguous.reason
    ok = verdict_of(success=True, failed_stages=[], low_motion=None, alternatives=[far])
    assert ok.verdict is Verdict.OK and "closest: bas_relief" in ok.reason


def test_an_alternative_that_scores_better_beyond_noise_is_not_called_within_noise():
    """A mirrored motion that beats the fit by 4.06 with a noise of 0.725 read 'mirrored within noise (gain -4.06
    <= noise 0.725)'; it is ambiguous (the fit missed it), said as such."""
    better, close = _alt("mirrored", -4.06, 0.725), _alt("bas_relief", -0.5, 0.725)
    quality = verdict_of(success=True, failed_stages=[], low_motion=None, alternatives=[better, close])
    assert quality.verdict is Verdict.AMBIGUOUS
    assert "mirrored scores better beyond noise (gain -4.06 < -noise 0.725" in quality.reason
    assert "bas_relief within noise (gain -0.5 <= noise 0.725)" in quality.reason


def test_a_window_the_ambiguity_test_cannot_hold_is_not_ok():
    """All events on one corner pixel: one patch, so no alternative can be scored; the fit found a
    direction with parallax, but nothing checks it against its mirror: ambiguous, never ok."""
    assert verdict_of(success=True, failed_stages=[], low_motion=None, alternatives=[], note="x",
                      untestable=True).verdict is Verdict.AMBIGUOUS
    assert verdict_of(success=True, failed_stages=[], low_motion=None, alternatives=[]).verdict is Verdict.OK
    rng = np.random.default_rng(0)
    n = 3000
    events = Events(np.full(n, 63), np.full(n, 47), np.sort(rng.integers(0, 100_000, n)), rng.integers(0, 2, n),
                    width=64, height=48)
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    # a pixel that fires alone at a steady rate is a hot pixel (cmax.hot_pixels.lone_steady_pixels): kept here
    with pytest.warns(LowParallaxWarning, match="not measured"):   # the permutation test sees no motion at all
        result = fit(events, K, speed=0.5, settings=FitSettings(hot_pixels=None))
    assert result.verdict is Verdict.LOW_PARALLAX and result.quality.cause is LowMotionCause.NO_MOTION
    # without it (and without the rotation-only test, which finds that a rotation explains the pixel as well)
    result = fit(events, K, speed=0.5, settings=FitSettings(
        hot_pixels=None, quality=QualitySettings(shuffle_test=False, rotation_test=False)))
    assert result.parallax_px > 1.0   # the parallax rules out low parallax (3.4 px measured)
    assert result.verdict is Verdict.AMBIGUOUS and "ambiguity not tested" in result.quality.reason
    assert result.quality.cause is None


@pytest.mark.parametrize("field, value", [("margin", -0.1), ("noise_sigmas", float("nan")), ("neighbours", 0),
                                          ("polish_iterations", -1), ("max_resolve_deg", "x"),
                                          ("distinct_deg", float("inf")), ("recheck_deg", -1.0),
                                          ("recheck_deg", float("nan")), ("max_rate_change", 1.0),
                                          ("max_rate_change", True), ("max_rate_change", "6"),
                                          ("max_rate_change", float("nan"))])
def test_quality_settings_are_checked(field, value):
    with pytest.raises(ValueError, match=field):
        QualitySettings(**{field: value})


def test_rate_change_is_the_busier_half_over_the_other():
    assert rate_change(np.arange(0, 1000, 10)) == 1.0                                  # 50 and 50 events
    stop = np.r_[np.arange(0, 500, 5), np.arange(500, 1001, 50)]                        # 100, then 11 events
    assert rate_change(stop) == pytest.approx(100 / 11)
    assert rate_change(stop[::-1].max() - stop[::-1]) == pytest.approx(101 / 10)       # a start (t = 500: 2nd half)
    assert rate_change(np.array([0, 1, 2, 1000])) == 3.0
    assert rate_change(np.array([0, 1, 50, 100])) == 1.0          # the event at the midpoint (50) counts in the second
    assert rate_change(np.array([0, 1, 2, 3, 2000, 2000])) == 2.0
    assert rate_change(np.array([0, 1, 2, 3, 4000])) == 4.0
    assert rate_change(np.array([5, 5, 5])) == 1.0 and rate_change(np.array([7])) == 1.0
    quality = verdict_of(success=True, failed_stages=[], low_motion=None, alternatives=[_alt("mirrored", 0.5)],
                         rate=float("inf"), max_rate_change=6.0)
    assert quality.verdict is Verdict.AMBIGUOUS and quality.unsteady
    assert quality.reason.startswith("one half of the window holds no event")
    assert quality.summary()["rate_change"] is None and quality.summary()["unsteady"] is True
    low = verdict_of(success=True, failed_stages=[], low_motion=LowMotion(LowMotionCause.PARALLAX, "0.2 px"),
                     alternatives=[], rate=9.0, max_rate_change=6.0)
    assert low.verdict is Verdict.LOW_PARALLAX and low.unsteady         # the worse verdict wins; measured still


def test_a_window_whose_camera_stops_halfway_is_unsteady_not_ok():
    """The clear street window with nine in ten of its second half's events dropped (the camera slowing to a
    near stop: events come at a rate proportional to the image's speed): no constant velocity explains it,
    and the fit says so (ambiguous, unsteady, the rate change in the reason) where the whole window is ok."""
    w, whole = clear_window()
    assert not whole.quality.unsteady and whole.quality.rate_change < 1.5 and whole.verdict is Verdict.OK
    t = w.events.t
    middle = t[0] + (t[-1] - t[0]) / 2
    keep = (t < middle) | (np.arange(len(t)) % 10 == 0)
    keep[-1] = True                                          # the window keeps its span
    stopping = w.events[np.flatnonzero(keep)]
    options = dict(speed=float(np.linalg.norm(w.twist[:3])), depth_range=(1.0, 20.0))
    r = fit(stopping, w.K, **options)
    assert r.quality.rate_change == pytest.approx(rate_change(stopping.t))
    assert r.quality.rate_change > QualitySettings().max_rate_change
    assert r.verdict is Verdict.AMBIGUOUS and r.quality.unsteady
    assert f"the event rate changes {r.quality.rate_change:.1f}x" in r.quality.reason
    off = fit(stopping, w.K, quality=QualitySettings(max_rate_change=float("inf")), **options)
    assert not off.quality.unsteady and "event rate" not in off.quality.reason    # the test turned off
    given = fit(stopping, w.K, pose=w.twist, depth_range=(1.0, 20.0))
    assert given.quality.rate_change is None and not given.quality.unsteady      # a given pose is not tested


def test_a_fronto_parallel_plane_under_pure_translation_is_ambiguous():
    """A textured wall, the camera sliding parallel to it, a narrow view: a rotation moves the events
    like the translation does, so ``-v`` with a rotation explains them about as well (bas-relief)."""
    w = make_window("slider", 4, width=120, height=90, focal=200.0, duration_s=0.3, max_frames=40)
    assert np.allclose(w.twist[3:], 0.0)                         # pure translation
    r = fit(w.events, w.K, speed=float(np.linalg.norm(w.twist[:3])), depth_range=(1.0, 20.0), max_events=4000)
    assert r.parallax_px > 3.0 and r.success                     # neither low parallax nor a failure
    assert r.verdict is Verdict.AMBIGUOUS, r.quality.reason
    close = [a for a in r.quality.alternatives if a.within_noise]
    assert close and all(a.gain <= a.noise for a in close)
    assert any(_angle_deg(a.v, r.v) > 30.0 for a in close)       # a genuinely other direction


def test_a_clear_window_is_ok_and_its_fit_is_right():
    w, r = clear_window()
    assert _angle_deg(r.v, w.twist[:3]) < 22.0                   # the ground truth agrees with the verdict
    assert r.verdict is Verdict.OK, r.quality.reason
    # the mirrored motion was tested: scored worse beyond noise, or polished back onto the fit (which of the
    # two depends on float rounding: the numba patch images against torch's moved it from one to the other)
    scored = {a.name for a in r.quality.alternatives}
    assert "mirrored" in scored or "mirrored" in r.quality.reason.split("polished back")[0].split(";")[-1]
    assert scored and all(a.gain > a.noise for a in r.quality.alternatives)


def _rotated(v: np.ndarray, degrees: float) -> np.ndarray:
    """``v`` (3,) turned by ``degrees`` about an axis perpendicular to it (its norm kept)."""
    axis = np.cross(v, [0.0, 0.0, 1.0] if abs(v[2]) < 0.9 * np.linalg.norm(v) else [1.0, 0.0, 0.0])
    axis /= np.linalg.norm(axis)
    a = np.radians(degrees)
    return v * np.cos(a) + np.cross(axis, v) * np.sin(a) + axis * np.dot(axis, v) * (1 - np.cos(a))


def test_a_polished_alternative_near_the_fit_that_scores_better_is_kept(monkeypatch):
    """Was: an alternative whose polish ended within ``distinct_deg`` (30 deg) of the fit was dropped as the fit
    itself, even where it scored better than the fit: on 160x120 street windows with a little noise the fit was a
    local optimum 37-39 deg off, the rotation-flipped alternative polished to 21-29 deg from it scoring better, and
    the verdict was ``ok``. Here the fit handed to the test is the window's own fit turned by 20 deg (no optimum),
    and every polish ends on the fit's optimum: that alternative scores better than the motion it is tested
    against, far beyond a tie (a gain of -0.8 against a margin of 0.03 on this host), and is kept (at least
    ``recheck_deg`` = 15 deg from it), so the verdict cannot be ``ok``; with ``recheck_deg`` at ``distinct_deg``
    (the old rule) it is dropped."""
    from types import SimpleNamespace

    from cmax.fitting.api import DEFAULT_CONTRAST, DEFAULT_POLARITY_SPLIT
    from cmax.fitting.quality import assess
    from cmax.fitting.solvers import make_solver
    from cmax.fitting.window import Window

    w, r = clear_window()
    speed = float(np.linalg.norm(w.twist[:3]))
    settings = FitSettings(depth_range=(1.0, 20.0), contrast=DEFAULT_CONTRAST["se3"],
                           polarity_split=DEFAULT_POLARITY_SPLIT["se3"])
    window = Window.from_events(w.events, w.K, settings, r.inverse_depth_grid.shape)
    monkeypatch.setattr("cmax.fitting.quality.refine_motion_local",
                        lambda *args, **kwargs: SimpleNamespace(v=r.v.copy(), omega=r.omega.copy()))
    off = _rotated(r.v, 20.0)
    assert abs(_angle_deg(off, r.v) - 20.0) < 1e-6
    for quality, kept in ((QualitySettings(), True), (QualitySettings(recheck_deg=30.0), False)):
        alternatives, note, tested = assess(window, off, r.omega, speed, quality, make_solver("scipy"),
                                            hold_omega=False)
        better = [a for a in alternatives if a.gain < 0]
        assert tested and bool(better) is kept, (alternatives, note)
        verdict = verdict_of(success=True, failed_stages=(), low_motion=None, alternatives=alternatives, note=note)
        assert (verdict.verdict is not Verdict.OK) is kept
        if kept:
            assert all(_angle_deg(a.v, r.v) < 1e-6 for a in better)


def test_without_the_test_or_with_a_known_pose_nothing_is_ambiguous():
    w, _ = clear_window()
    r = fit(w.events, w.K, pose=w.twist, depth_range=(1.0, 20.0))
    assert r.verdict is Verdict.OK and r.quality.alternatives == () and "pose is given" in r.quality.reason


class _Wild(Solver):
    """A backend that always ends far from the start (a forced failure)."""

    def solve(self, problem):
        x = np.clip(problem.x0 + 3.0, problem.lower, problem.upper)
        return SolveResult(x, problem.fun_and_grad(x)[0], 1, 1, "wild", True, 0.0)


def test_a_failed_stage_gives_failed():
    w = make_window("rotation", 1, width=120, height=90, focal=90.0, duration_s=0.05, max_frames=60)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LowMotionWarning)
        r = fit(w.events, w.K, model="rotation", solver=_Wild())
    assert not r.success and r.verdict is Verdict.FAILED and "rotation" in r.quality.reason


# ----------------------------------------------------------------------------------------------
# Resolution from neighbours
# ----------------------------------------------------------------------------------------------
def _ambiguous(v_alt, gain=0.01, noise=0.1) -> Quality:
    alt = Alternative("mirrored", np.asarray(v_alt, float), np.zeros(3), gain, noise, gain <= noise)
    return Quality(Verdict.AMBIGUOUS, "mirrored within noise", (alt,))


def test_choose_from_neighbours_takes_the_alternative_closest_to_them():
    fit_v, plus_x = np.array([-1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
    neighbours = [(np.array([1.0, 0.1, 0.0]), np.zeros(3)), (np.array([1.0, -0.1, 0.0]), np.zeros(3))]
    chosen, q = choose_from_neighbours(fit_v, np.zeros(3), _ambiguous(plus_x), neighbours, 0.1, 45.0)
    assert chosen is not None and np.allclose(chosen.v, plus_x) and q.resolved and "took the mirrored" in q.resolution
    # the neighbours agree with the fit: it is kept
    chosen, q = choose_from_neighbours(plus_x, np.zeros(3), _ambiguous(-plus_x), neighbours, 0.1, 45.0)
    assert chosen is None and q.resolved and "kept the fit" in q.resolution
    # no candidate near the neighbours, or no neighbours: unresolved, and said
    up = [(np.array([0.0, 1.0, 0.0]), np.zeros(3))]
    chosen, q = choose_from_neighbours(fit_v, np.zeros(3), _ambiguous(plus_x), up, 0.1, 45.0)
    assert chosen is None and not q.resolved and q.resolution.startswith("unresolved: the closest candidate")
    chosen, q = choose_from_neighbours(fit_v, np.zeros(3), _ambiguous(plus_x), [], 0.1, 45.0)
    assert chosen is None and not q.resolved and "no confident" in q.resolution
    # an alternative beyond noise is no candidate
    chosen, q = choose_from_neighbours(fit_v, np.zeros(3), _ambiguous(plus_x, gain=0.5), neighbours, 0.1, 45.0)
    assert chosen is None and not q.resolved


def _run(gains, noise=0.4):
    """Windows whose fit moves -x where their gain is negative (the mirrored +x scored better) and +x
    otherwise, each ambiguous with the mirrored motion within noise."""
    plus_x = np.array([1.0, 0.0, 0.0])
    motions = [(-plus_x if g < 0 else plus_x, np.zeros(3)) for g in gains]
    qualities = [Quality(Verdict.AMBIGUOUS, "mirrored within noise",
                         (Alternative("mirrored", -v, np.zeros(3), g, noise, abs(g) <= noise),))
                 for (v, _), g in zip(motions, gains)]
    return motions, qualities


def test_choose_from_run_takes_the_motion_the_run_favours_beyond_its_pooled_noise():
    """Three ambiguous windows, no confident neighbour: -x, +x, -x fits, the first and last preferring their
    mirrored +x (gains -0.3, -0.25), the middle its own +x (gain 0.2). Evidence for +x: 0.3 + 0 + 0.25 = 0.55,
    for -x: 0 - 0.2 + 0 = -0.2; 0.75 is above the pooled noise sqrt(3 * 0.4^2) = 0.69: +x for all three."""
    motions, qualities = _run([-0.3, 0.2, -0.25])
    chosen = choose_from_run(motions, qualities, [0.1] * 3, 45.0)
    assert [c is None for c, _ in chosen] == [False, True, False]
    assert all(np.allclose(c.v, [1, 0, 0]) for c, _ in chosen if c is not None)
    assert all(q.resolved and "pooled over the run of 3 ambiguous windows" in q.resolution for _, q in chosen)
    assert "0.55 beats the other motion's -0.2 by more than the pooled noise 0.693" in chosen[0][1].resolution
    # weaker preferences (0.05 + 0.04 against -0.1: 0.19 < 0.69): the run stays unresolved, and says why
    motions, qualities = _run([-0.05, 0.1, -0.04])
    chosen = choose_from_run(motions, qualities, [0.1] * 3, 45.0)
    assert all(c is None and not q.resolved and "within the pooled noise" in q.resolution for c, q in chosen)
    # one window cannot beat its own noise: unresolved, as with no neighbour at all
    motions, qualities = _run([-0.3])
    ((c, q),) = choose_from_run(motions, qualities, [0.1], 45.0)
    assert c is None and not q.resolved and q.resolution == "unresolved: no confident (ok) neighbour window"


def test_a_run_without_any_alternative_within_noise_is_not_resolved_by_agreeing_fits():
    """Two sparse windows (ambiguous for too few events per pixel; every alternative worse beyond noise) fitted
    one from the other agree: that was counted "resolved" ("one motion's evidence 0 beats no other motion covers
    the run ..."), and made them confident neighbours of the motion prior. Nothing was weighed: unresolved."""
    plus_x = np.array([1.0, 0.0, 0.0])
    motions = [(plus_x, np.zeros(3)), (plus_x * 0.99 + [0, 0.01, 0], np.zeros(3))]
    qualities = [Quality(Verdict.AMBIGUOUS, "60,000 events on 640x480 pixels (0.195 per pixel ...)",
                         (Alternative("mirrored", -plus_x, np.zeros(3), 3.0, 1.0, False),), sparse=True)
                 for _ in motions]
    chosen = choose_from_run(motions, qualities, [0.1] * 2, 45.0)
    assert all(c is None and not q.resolved and "none of them has an alternative within noise" in q.resolution
               for c, q in chosen)


def test_a_run_whose_winner_is_unrivalled_only_through_unweighed_windows_is_not_resolved():
    """Three ambiguous windows fitted one from the other (+x): the first and last have their mirrored -x within
    noise (gains 0.1, 0.1), the middle one is sparse (its mirrored worse beyond noise, so only its fit is a
    candidate). -x then has no candidate in the middle window and +x was called "the only motion with a candidate
    in every window": resolved, though the one window that excludes -x weighed nothing (an audit's sequence:
    10 of 10 windows "resolved", 5-79 deg off). The run stays unresolved and says why."""
    plus_x = np.array([1.0, 0.0, 0.0])
    motions = [(plus_x, np.zeros(3))] * 3
    within = (Alternative("mirrored", -plus_x, np.zeros(3), 0.1, 0.4, True),)
    beyond = (Alternative("mirrored", -plus_x, np.zeros(3), 3.0, 0.4, False),)
    qualities = [Quality(Verdict.AMBIGUOUS, "mirrored within noise", within),
                 Quality(Verdict.AMBIGUOUS, "sparse", beyond, sparse=True),
                 Quality(Verdict.AMBIGUOUS, "mirrored within noise", within)]
    chosen = choose_from_run(motions, qualities, [0.1] * 3, 45.0)
    assert all(c is None and not q.resolved for c, q in chosen)
    assert "but 1 of them has no alternative within noise" in chosen[0][1].resolution
    # the middle window weighed too (its mirrored within noise, gain 0.1): +x and -x both cover the run, their
    # evidence 0 and -0.3 within the pooled noise 0.69: unresolved as before, for that reason
    qualities[1] = Quality(Verdict.AMBIGUOUS, "mirrored within noise", within)
    chosen = choose_from_run(motions, qualities, [0.1] * 3, 45.0)
    assert all(c is None and not q.resolved and "within the pooled noise" in q.resolution for c, q in chosen)


def _constructed_sequence(monkeypatch, count: int, motion_of):
    """``fit_sequence`` over ``count`` windows of :func:`clear_window`'s events, with ``fit`` replaced: a
    re-fit with the pose held returns that pose (``ok``); otherwise window ``i`` returns ``motion_of(i)``,
    a ``(v (3,), quality)`` with zero rotation. Smoothing off, so that only the resolution acts."""
    base = clear_window()[1]
    events = clear_window()[0].events
    t_first = int(events.t[0])
    window_us = (int(events.t[-1]) - t_first) // count

    def constructed_fit(events, K, model="se3", *, speed=None, pose=None, omega=None, init=None, quality=None,
                        **options):
        t0, t1 = int(events.t[0]), int(events.t[-1])
        if pose is not None:
            pose = np.asarray(pose, float)
            return replace(base, t0_us=t0, t1_us=t1, v=pose[:3], omega=pose[3:], scale_known=True,
                           quality=Quality(Verdict.OK, "ambiguity not tested: the pose is given"))
        v, q = motion_of(min(round((t0 - t_first) / window_us), count - 1))
        return replace(base, t0_us=t0, t1_us=t1, v=np.array(v, float), omega=np.zeros(3), quality=q)

    monkeypatch.setattr(sequence_module, "fit", constructed_fit)
    result = fit_sequence(events, clear_window()[0].K, window_us=window_us, speed=0.5, min_events=10,
                          quality=QualitySettings(smoothing=False))
    assert len(result.results) == count
    return result


def test_fit_sequence_resolves_a_run_without_ok_windows_by_its_pooled_evidence(monkeypatch):
    """Four windows moving +x, all ambiguous and none ok; two of the fits are flipped (-x) while their
    own mirrored alternative (+x) scored better, the others prefer their +x fit slightly: fit_sequence takes
    +x for all four (the two flipped re-fitted with it held)."""
    truth = np.array([0.5, 0.0, 0.0])
    gains = [0.1, -0.4, 0.05, -0.35]

    def motion_of(i):
        v = truth if gains[i] > 0 else -truth
        alt = Alternative("mirrored", -v, np.zeros(3), gains[i], 0.3, True)
        return v, Quality(Verdict.AMBIGUOUS, "mirrored within noise", (alt,))

    result = _constructed_sequence(monkeypatch, 4, motion_of)
    for i, r in enumerate(result.results):
        np.testing.assert_allclose(r.v, truth, err_msg=f"window {i}")
        assert "pooled over the run of 4" in r.quality.resolution
    assert [r.quality.replaced is not None for r in result.results] == [False, True, False, True]
    assert result.counts()["resolved"] == 4


def test_a_run_of_ambiguous_windows_is_resolved_inwards_from_its_ends(monkeypatch):
    """Eight windows moving +x; the fits of windows 1-6 are flipped (-x), ambiguous with +x within noise.
    Windows 3 and 4 have no ok window within two on either side: they are resolved from windows 1-2 and 5-6,
    themselves resolved from windows 0 and 7 in the pass before (a run of ambiguous windows, as on the ECD
    slider, is not left unresolved), and the whole trajectory moves +x."""
    truth = np.array([0.5, 0.0, 0.0])

    def motion_of(i):
        if 1 <= i <= 6:
            return -truth, _ambiguous(truth)
        return truth, Quality(Verdict.OK, "every alternative scores worse beyond noise")

    result = _constructed_sequence(monkeypatch, 8, motion_of)
    for i, r in enumerate(result.results):
        np.testing.assert_allclose(r.v, truth, err_msg=f"window {i}")
    inner = [result.results[i].quality.resolution for i in (3, 4)]
    assert all("took the mirrored" in text and "resolved themselves" in text for text in inner)
    assert all("resolved themselves" not in result.results[i].quality.resolution for i in (1, 2, 5, 6))
    assert result.counts()["resolved"] == 6


def test_fit_sequence_resolves_a_flipped_window_from_its_neighbours(monkeypatch):
    """Five windows of a camera moving +x at 0.5 m/s; the fit of the middle one is flipped (-x) and
    ambiguous with +x within noise. fit_sequence takes +x for it (re-fitting it with that motion held),
    and the trajectory ends where the true one does."""
    base = clear_window()[1]
    speed, truth = 0.5, np.array([0.5, 0.0, 0.0])
    real_fit, calls = sequence_module.fit, []

    def constructed_fit(events, K, model="se3", *, speed=None, pose=None, omega=None, init=None, quality=None,
                        **options):
        window = len(calls)
        calls.append(pose)
        t0, t1 = int(events.t[0]), int(events.t[-1])
        if pose is not None:                     # the re-fit of a resolved window: its motion held
            pose = np.asarray(pose, float)
            return replace(base, t0_us=t0, t1_us=t1, v=pose[:3], omega=pose[3:], scale_known=True,
                           quality=Quality(Verdict.OK, "ambiguity not tested: the pose is given"))
        if window == 2:
            q = _ambiguous(truth, gain=0.01, noise=0.1)
            return replace(base, t0_us=t0, t1_us=t1, v=-truth, omega=np.zeros(3), quality=q)
        return replace(base, t0_us=t0, t1_us=t1, v=truth.copy(), omega=np.zeros(3),
                       quality=Quality(Verdict.OK, "every alternative scores worse beyond noise"))

    monkeypatch.setattr(sequence_module, "fit", constructed_fit)
    w = clear_window()[0]
    events = w.events
    span = int(events.t[-1]) - int(events.t[0])
    window_us = span // 5
    result = fit_sequence(events, w.K, window_us=window_us, speed=speed, min_events=10)
    assert len(result.results) == 5 and real_fit is not constructed_fit
    assert result.verdicts == (Verdict.OK, Verdict.OK, Verdict.AMBIGUOUS, Verdict.OK, Verdict.OK)
    middle = result.results[2]
    np.testing.assert_allclose(middle.v, truth)
    assert middle.quality.resolved and "took the mirrored" in middle.quality.resolution
    np.testing.assert_allclose(middle.quality.replaced[0], -truth)   # the fit it replaced, kept
    np.testing.assert_allclose(calls[-1], np.r_[truth, np.zeros(3)])   # re-fitted with the chosen motion held
    assert result.counts() == {"ok": 4, "ambiguous": 1, "low_parallax": 0, "failed": 0, "resolved": 1}
    travelled = result.poses[-1][:3, 3]
    expected = truth * (result.times_us[-1] - result.times_us[0]) * 1e-6
    np.testing.assert_allclose(travelled, expected, atol=1e-9)       # no step walks backwards


def test_a_sparse_window_is_never_ok():
    """Fewer events per pixel than QualitySettings.min_event_density: an ok becomes ambiguous and sparse, saying
    how many events on how many pixels and what gives more; the worse verdicts stay; 0 turns the rule off."""
    from cmax.fitting.quality import sparse_reason

    reason = sparse_reason(3000, 3000, 346, 260, 0.25)
    assert reason.startswith("3,000 events on 346x260 pixels (0.033 per pixel, under min_event_density=0.25)")
    assert "a longer window gives more events" in reason
    assert "219,551 were given: a larger FitSettings.max_events" in sparse_reason(20_000, 219_551, 1280, 720, 0.25)
    assert sparse_reason(23_000, 23_000, 346, 260, 0.25) == "" and sparse_reason(10, 10, 346, 260, 0.0) == ""
    ok = verdict_of(success=True, failed_stages=[], low_motion=None, alternatives=[_alt("mirrored", 1.0)],
                    sparse=reason)
    assert ok.verdict is Verdict.AMBIGUOUS and ok.sparse and ok.reason.startswith(reason + "; every alternative")
    assert ok.summary()["sparse"] is True
    low = LowMotion(LowMotionCause.PARALLAX, "parallax 0.4 px")
    for worse in (verdict_of(success=False, failed_stages=["local_refine"], low_motion=None, alternatives=[],
                             sparse=reason),
                  verdict_of(success=True, failed_stages=[], low_motion=low, alternatives=[], sparse=reason)):
        assert worse.verdict in (Verdict.FAILED, Verdict.LOW_PARALLAX) and not worse.sparse


def test_a_fit_on_few_events_per_pixel_is_flagged_sparse_with_its_motion_unchanged(monkeypatch):
    """indoor_flying at 346x260 cut to 3,000 events (0.033 per pixel): a draw the ambiguity test passes as ok
    (without the rule) comes back ambiguous and sparse, with the same motion; the same window at 30,000 events
    (0.33 per pixel) is not sparse. Across 18 such draws of seeds 100-105 the ok ones were 8-51 deg off
    (docs/quality.md)."""
    w = make_window("indoor_flying", 105, duration_s=0.1)
    speed = float(np.linalg.norm(w.twist[:3]))
    rng = np.random.default_rng(0)
    oks = 0
    for _ in range(4):
        events = w.events[np.sort(rng.choice(len(w.events), 3000, replace=False))]
        # the rule of small parallax left out of both (a tenth of a second of these draws has little of it)
        off = fit(events, w.K, speed=speed, quality=QualitySettings(min_event_density=0.0, min_ok_parallax_px=0.0))
        on = fit(events, w.K, speed=speed, quality=QualitySettings(min_ok_parallax_px=0.0))
        np.testing.assert_array_equal(on.v, off.v)
        if off.verdict is Verdict.OK:
            oks += 1
            assert on.verdict is Verdict.AMBIGUOUS and on.quality.sparse
            assert "3,000 events on 346x260 pixels (0.033 per pixel" in on.quality.reason
        else:
            assert on.verdict is off.verdict and not on.quality.sparse
    dense = fit(w.events[np.sort(rng.choice(len(w.events), 30_000, replace=False))], w.K, speed=speed)
    assert not dense.quality.sparse
    if not oks:   # which draws the ambiguity test passes turns on the host's float rounding: make one pass it
        monkeypatch.setattr("cmax.fitting.api.assess", lambda *args, **kwargs: ((_alt("mirrored", 1.0),), "", True))
        on = fit(events, w.K, speed=speed, quality=QualitySettings(min_ok_parallax_px=0.0))
        assert on.verdict is Verdict.AMBIGUOUS and on.quality.sparse
        assert "3,000 events on 346x260 pixels (0.033 per pixel" in on.quality.reason


def test_a_large_sensor_window_with_ample_events_is_not_sparse_but_a_thin_one_is(monkeypatch):
    """QualitySettings.min_event_density counts a sensor larger than min_event_density_area (346x260) over the
    geometric mean of the two areas (the events lie along edges, whose pixels grow with the image's side): a
    640x480 window fitted on 60,000 events (the default before it grew with the sensor) needs 0.25 sqrt(640 480 346 260) = 41,560 and is not sparse
    (it was: 0.195 per pixel of its whole image, so no 640x480 window could be ok with the defaults); one of
    8,000 events still is, and says over which pixels it counted; 1280x720 needs 71,984. The ambiguity test is made
    to pass both windows, so that only the rule decides."""
    from cmax.fitting.quality import density_pixels, sparse_reason

    monkeypatch.setattr("cmax.fitting.api.assess", lambda *args, **kwargs: ((_alt("mirrored", 1.0),), "", True))
    assert density_pixels(640, 480) == pytest.approx(math.sqrt(640 * 480 * 346 * 260))
    assert density_pixels(346, 260) == 346 * 260 and density_pixels(160, 120) == 160 * 120     # as before
    assert sparse_reason(41_000, 41_000, 640, 480, 0.25) and not sparse_reason(42_000, 42_000, 640, 480, 0.25)
    assert sparse_reason(71_000, 71_000, 1280, 720, 0.25) and not sparse_reason(73_000, 73_000, 1280, 720, 0.25)
    assert sparse_reason(60_000, 60_000, 640, 480, 0.25, 640 * 480)     # the whole image's density: as before
    ample, K = _dots_on_a_plane(3.0, (0.5, 0.0, 0.0), seed=6, width=640, height=480, focal=400.0, events=160_000)
    r = fit(ample, K, speed=0.5, max_events=60_000)
    assert r.events_used == 60_000 and len(ample) > 60_000
    assert r.success and r.quality.rate_change is not None and not r.quality.on_bound
    assert not r.quality.sparse and "events on 640x480 pixels" not in r.quality.reason
    thin = fit(ample[np.sort(np.random.default_rng(1).choice(len(ample), 8_000, replace=False))], K, speed=0.5)
    assert thin.events_used == 8_000
    assert thin.verdict is Verdict.AMBIGUOUS and thin.quality.sparse
    assert thin.quality.reason.startswith("8,000 events on 640x480 pixels (0.048 per pixel of sqrt(640 x 480 x "
                                          "min_event_density_area=89,960) = 166,240 px, under min_event_density=0.25)")
    with pytest.raises(ValueError, match="min_event_density_area must be an int >= 1"):
        QualitySettings(min_event_density_area=0)


def test_the_default_subsample_grows_with_a_larger_sensor(monkeypatch):
    """Was: ``FitSettings.max_events`` 60,000 on every sensor, under the 71,984 events the sparse-window rule asks of a
    1280x720 window, so that no Gen4 window could be ``ok`` with the defaults. Now the default (None) keeps 60,000
    up to 346x260 pixels and 60,000 sqrt(width height / (346 260)) on a larger image (the scale of the rule's
    pixels); a given count is kept on every sensor, the old 60,000 too. A 1280x720 window of about 87,000 events,
    the ambiguity test made to pass so that only the rules decide, is fitted on all of them and is not sparse (it
    was: fitted on 60,000, 0.208 per pixel of the rule's 287,936, under 0.25)."""
    from cmax.fitting.quality import density_pixels
    from cmax.fitting.settings import max_events_for
    from cmax.fitting.window import Window

    grows = {(640, 480): round(60_000 * math.sqrt(640 * 480 / 89_960)),       # 110,876 (worked out by hand)
             (1280, 720): round(60_000 * math.sqrt(1280 * 720 / 89_960))}     # 192,043
    assert grows == {(640, 480): 110_876, (1280, 720): 192_043}
    for (width, height), count in grows.items():
        assert max_events_for(FitSettings().max_events, width, height) == count
        assert count > 0.25 * density_pixels(width, height)       # clears the sparse rule: 41,560 and 71,984
        assert max_events_for(60_000, width, height) == 60_000     # the old value, given
    for width, height in ((346, 260), (240, 180), (160, 120), (96, 72)):
        assert max_events_for(None, width, height) == 60_000       # unchanged at 346x260 and below
    rng = np.random.default_rng(3)
    n = 130_000
    events = Events(rng.integers(0, 640, n), rng.integers(0, 480, n), np.sort(rng.integers(0, 100_000, n)),
                    rng.integers(0, 2, n), 640, 480)
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    assert len(Window.from_events(events, K, FitSettings(), (6, 8)).ev) == 110_876
    assert len(Window.from_events(events, K, FitSettings(max_events=60_000), (6, 8)).ev) == 60_000
    small = Events(events.x // 2, events.y // 2, events.t, events.p, 320, 240)
    assert len(Window.from_events(small, K / np.array([[2], [2], [1]]), FitSettings(), (6, 8)).ev) == 60_000
    with pytest.raises(ValueError, match=r"max_events must be >= 10 \(an int\) or None \(by the sensor\), got 5"):
        FitSettings(max_events=5)

    monkeypatch.setattr("cmax.fitting.api.assess", lambda *args, **kwargs: ((_alt("mirrored", 1.0),), "", True))
    hd, K = _dots_on_a_plane(3.0, (0.5, 0.0, 0.0), seed=6, width=1280, height=720, focal=800.0, events=220_000)
    assert 0.25 * density_pixels(1280, 720) < len(hd) < 192_043
    r = fit(hd, K, speed=0.5)
    assert r.events_used == len(hd) and not r.quality.sparse, r.quality
    assert "events on 1280x720 pixels" not in r.quality.reason


def _dots_on_a_plane(depth_m: float, v: tuple[float, float, float], seed: int, width: int = 240, height: int = 180,
                     focal: float = 200.0, events: int = 40_000, duration_s: float = 0.1) -> tuple[Events, np.ndarray]:
    """Events of random dots on a fronto-parallel plane ``depth_m`` ahead, the camera translating at ``v`` [m/s]
    (no rotation): each event a dot seen at a random time, its projection rounded to a pixel. And K."""
    rng = np.random.default_rng(seed)
    K = np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1.0]])
    u, w = rng.uniform(-0.3 * width, 1.3 * width, 4000), rng.uniform(-0.3 * height, 1.3 * height, 4000)
    dots = np.stack([(u - K[0, 2]) / focal * depth_m, (w - K[1, 2]) / focal * depth_m, np.full(4000, depth_m)], 1)
    t = np.sort(rng.uniform(0, duration_s, events))
    camera = dots[rng.integers(0, 4000, events)] - t[:, None] * np.asarray(v)     # the dot in the camera's frame
    x, y = np.rint(focal * camera[:, 0] / camera[:, 2] + K[0, 2]), np.rint(focal * camera[:, 1] / camera[:, 2] + K[1, 2])
    inside = (x >= 0) & (x < width) & (y >= 0) & (y < height)
    return Events(x[inside].astype(int), y[inside].astype(int), np.rint(t[inside] * 1e6).astype(np.int64),
                  rng.integers(0, 2, int(inside.sum())), width, height), K


def test_a_free_motion_that_keeps_just_under_half_the_depth_off_a_bound_is_not_ok():
    """A wall at 120 m seen at 20 m/s sideways (3.3 px of parallax), fitted with the default depth_range
    (0.5-60 m) and only the speed: the motion tilted 34 deg until 48% of the events' depth sat on the far end,
    just under the 50% that fails a fit, and came back ok, success True, without a warning (an audit's case).
    Now ambiguous and on_bound, with a BoundWarning naming the share; with the range widened past the wall it is
    not on_bound. With the pose given the 50% rule fails it (as before)."""
    events, K = _dots_on_a_plane(120.0, (20.0, 0.0, 0.0), seed=4)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = fit(events, K, speed=20.0)
    bound = [str(c.message) for c in caught if c.category.__name__ == "BoundWarning"]
    assert r.verdict is Verdict.AMBIGUOUS and r.quality.on_bound and r.quality.summary()["on_bound"], r.quality
    assert len(bound) == 1 and "of the events' depth on the far end (60 m) of depth_range" in bound[0], bound
    share = float(r.quality.reason.split("%")[0])   # rounded to a whole percent: 49.96% reads 50%
    assert QualitySettings().max_bound_share * 100 <= share <= FitSettings().depth_bound_fraction * 100, r.quality
    assert r.success
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        wide = fit(events, K, speed=20.0, depth_range=(0.5, 500.0))
        off = fit(events, K, speed=20.0, quality=QualitySettings(max_bound_share=1.0))
    assert not wide.quality.on_bound and "depth_range" not in wide.quality.reason
    assert not off.quality.on_bound
    with pytest.raises(ValueError, match="max_bound_share must lie in"):
        QualitySettings(max_bound_share=0)


def _dots_on_two_planes(near_m: float, far_m: float, near_rows: float, v: tuple[float, float, float], seed: int,
                        width: int = 240, height: int = 180, focal: float = 200.0, events: int = 40_000,
                        duration_s: float = 0.1) -> tuple[Events, np.ndarray]:
    """As :func:`_dots_on_a_plane`, the dots of the top ``near_rows`` share of the view on a fronto-parallel plane
    ``near_m`` ahead, the others ``far_m`` ahead."""
    rng = np.random.default_rng(seed)
    K = np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1.0]])
    u, w = rng.uniform(-0.3 * width, 1.3 * width, 4000), rng.uniform(-0.3 * height, 1.3 * height, 4000)
    z = np.where(w < near_rows * height, near_m, far_m)
    dots = np.stack([(u - K[0, 2]) / focal * z, (w - K[1, 2]) / focal * z, z], 1)
    t = np.sort(rng.uniform(0, duration_s, events))
    camera = dots[rng.integers(0, 4000, events)] - t[:, None] * np.asarray(v)
    x, y = np.rint(focal * camera[:, 0] / camera[:, 2] + K[0, 2]), np.rint(focal * camera[:, 1] / camera[:, 2] + K[1, 2])
    inside = (x >= 0) & (x < width) & (y >= 0) & (y < height)
    return Events(x[inside].astype(int), y[inside].astype(int), np.rint(t[inside] * 1e6).astype(np.int64),
                  rng.integers(0, 2, int(inside.sum())), width, height), K


def test_a_fifth_of_the_depth_on_a_bound_is_not_ok():
    """A third of the view (dots 1.5 m ahead over its top rows, 5 m below) nearer than depth_range=(3, 20), the
    camera sliding at 3.3 m/s: about a fifth of the events' depth ends on the near end (22% here), a share of the
    depth map clipped by half and more. Under the rule's quarter it was ok; an audit of unseen scenes found ok windows
    40-100 deg off with 21-23% on the near end (benchmarks/results/unseen_scenes.md). Now ambiguous and on_bound,
    with a BoundWarning naming the near end; the motion is the same fit (the rule judges it, it does not change it)."""
    v = np.array([1.0, 0.4, 0.2]) * 3.0
    events, K = _dots_on_two_planes(1.5, 5.0, 0.35, tuple(v), seed=1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = fit(events, K, speed=float(np.linalg.norm(v)), depth_range=(3.0, 20.0))
    bound = [str(c.message) for c in caught if c.category.__name__ == "BoundWarning"]
    assert r.verdict is Verdict.AMBIGUOUS and r.quality.on_bound, r.quality
    assert len(bound) == 1 and "of the events' depth on the near end (3 m) of depth_range" in bound[0], bound
    share = float(r.quality.reason.split("%")[0])
    assert QualitySettings().max_bound_share * 100 <= share < FitSettings().depth_bound_fraction * 100, r.quality
    assert r.success and _angle_deg(r.v, v) < 20.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        off = fit(events, K, speed=float(np.linalg.norm(v)), depth_range=(3.0, 20.0),
                  quality=QualitySettings(max_bound_share=1.0))
    assert not off.quality.on_bound
    np.testing.assert_array_equal(off.v, r.v)
    np.testing.assert_array_equal(off.omega, r.omega)


def test_the_planar_dual_moves_a_plane_as_the_fit_does():
    """Closed form (Longuet-Higgins 1984): a plane rho = q . ray under (v, omega) moves its points as the plane
    q' = |q| v / s under v' = s q / |q| (s = |v|) with another rotation. Pixels of a 240x180 camera, a wall 2 m
    ahead tilted 20 deg, the audit's diagonal motion: the dual's direction is the wall's normal, and its flow
    (the exact warp over 1 ms) equals the fit's to 1% of the flow's size."""
    import torch

    from cmax.fitting.quality import _planar_dual, _unit_flows

    K = torch.tensor([[200.0, 0, 119.5], [0, 200.0, 89.5], [0, 0, 1]], dtype=torch.float64)
    u, w = np.meshgrid(np.linspace(0, 239, 24), np.linspace(0, 179, 18))
    rays = torch.as_tensor(np.stack([(u.ravel() - 119.5) / 200, (w.ravel() - 89.5) / 200, np.ones(u.size)], 1))
    normal = np.array([np.sin(np.radians(20)), 0.0, np.cos(np.radians(20))])
    q = normal / 2.0                                              # n . X = 2 m
    rho = rays.numpy() @ q
    v, omega = np.array([0.3, -0.3, 0.4]), np.array([0.1, 0.2, -0.3])
    translation, rotation = _unit_flows(rays, K, torch.as_tensor(rho), v, 1e-3)
    v_dual, omega_dual = _planar_dual(rays, K, torch.as_tensor(rho), v, omega, translation, rotation, 1e-3)
    np.testing.assert_allclose(v_dual, np.linalg.norm(v) * normal, atol=1e-9)
    rho_dual = rays.numpy() @ (np.linalg.norm(q) * v / np.linalg.norm(v))
    moved, _ = _unit_flows(rays, K, torch.as_tensor(rho_dual), v_dual, 1e-3)
    fitted = translation + rotation @ omega
    dual = moved + rotation @ omega_dual
    assert np.abs(dual - fitted).max() < 0.01 * np.abs(fitted).max()
    assert np.degrees(np.arccos(v_dual @ v / np.linalg.norm(v) ** 2)) > 30     # another motion, not the fit


def _sliding_plane(v: np.ndarray, seed: int, distance: float = 2.0, duration: float = 0.1, frames: int = 300):
    """Events (160x120, f = 110 px: 72 deg across) of a camera sliding by ``v`` [m/s] without rotation past one
    textured fronto-parallel plane ``distance`` [m] ahead, for ``duration`` [s] (a sum of random gratings, its
    ``seed``; :class:`cmax.sim.EventSimulator`), and the intrinsics K (3, 3)."""
    from cmax.sim import EventSimulator

    width, height, f = 160, 120, 110.0
    K = np.array([[f, 0, width / 2 - 0.5], [0, f, height / 2 - 0.5], [0, 0, 1.0]])
    rng = np.random.default_rng(seed)
    waves, phase = rng.normal(0, 10, (30, 2)), rng.uniform(0, 2 * np.pi, 30)
    ys, xs = np.mgrid[0:height, 0:width].astype(float)
    rays = np.stack([xs, ys, np.ones_like(xs)], -1) @ np.linalg.inv(K).T
    times = np.linspace(0, duration, frames)
    images = [128 + 90 * np.tanh(2 * np.sin((rays[..., :2] * distance + v[:2] * t) @ waves.T + phase).sum(-1)
                                 / np.sqrt(30)) for t in times]
    events = EventSimulator(cp=0.2, cn=0.2, seed=0).simulate(np.asarray(images, np.float32),
                                                             np.rint(times * 1e6).astype(np.int64))
    return events, K


@pytest.mark.parametrize("seed", [2001, 2004])
def test_a_direction_of_a_few_pixels_of_parallax_with_a_free_rotation_is_never_ok(seed, monkeypatch):
    """Was: a plane slid past sideways with 1.5 px of true parallax, rotation free: ``ok``, 50-70 deg off, the
    contrast preferring a rotation traded for the translation beyond the test's noise (an audit's scenes: 6 of
    14 windows ``ok`` at 33-77 deg; these seeds: ``ok`` at 68.8 and 71.5 deg). Under
    ``QualitySettings.min_ok_parallax_px`` an ``ok`` becomes ambiguous and ``small_parallax``, the motion
    unchanged; 0 turns the rule off; with the rotation held (``omega=``) the rule does not apply."""
    from cmax.fitting.quality import small_parallax_reason

    v = np.array([0.27, 0.081, 0.0])
    events, K = _sliding_plane(v, seed)
    off = FitSettings(depth_range=(0.5, 10.0), quality=QualitySettings(min_ok_parallax_px=0.0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        without = fit(events, K, speed=float(np.linalg.norm(v)), settings=off)
        default = fit(events, K, speed=float(np.linalg.norm(v)), depth_range=(0.5, 10.0))
        held = fit(events, K, speed=float(np.linalg.norm(v)), depth_range=(0.5, 10.0), omega=np.zeros(3))
    np.testing.assert_allclose(default.v, without.v, rtol=1e-9)             # the rule changes the verdict alone
    assert without.parallax_px < 3.0 and not held.quality.small_parallax
    if without.verdict is Verdict.OK:   # (on the hosts measured: ok at 68.8 and 71.5 deg) now ambiguous
        assert default.verdict is Verdict.AMBIGUOUS and default.quality.small_parallax
        assert default.quality.reason.startswith(small_parallax_reason(default.parallax_px, 3.0, (160, 120))
                                                 + "; every")
        assert default.quality.summary()["small_parallax"] is True
    else:               # another host's rounding let the test flag it already: make the test pass it, as measured
        assert without.verdict is not Verdict.OK and default.verdict is without.verdict
        monkeypatch.setattr("cmax.fitting.api.assess", lambda *args, **kwargs: ((_alt("mirrored", 1.0),), "", True))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            forced = fit(events, K, speed=float(np.linalg.norm(v)), depth_range=(0.5, 10.0))
        assert forced.verdict is Verdict.AMBIGUOUS and forced.quality.small_parallax
    assert _angle_deg(without.v, v) > 30.0         # what the rule is for: this little parallax, a wrong direction


def test_a_small_image_needs_more_parallax_for_ok(monkeypatch):
    """A plane slid past at 160x120 with about 4 px of fitted parallax: over the 3 px of ``min_ok_parallax_px`` but
    under its scaled 6.49 px (:func:`cmax.fitting.quality.min_ok_parallax`), so ``ambiguous`` and
    ``small_parallax`` even when every alternative scores worse beyond noise (the ambiguity test is made to say
    so, to test this rule alone); unscaled (``min_ok_parallax_area=1``, the flat-valley rule off) the same fit is
    ``ok``."""
    monkeypatch.setattr("cmax.fitting.api.assess", lambda *args, **kwargs: ((_alt("mirrored", 1.0),), "", True))
    v = 3.0 * np.array([0.27, 0.081, 0.0])
    events, K = _sliding_plane(v, 2001)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scaled = fit(events, K, speed=float(np.linalg.norm(v)), depth_range=(0.5, 10.0))
        unscaled = fit(events, K, speed=float(np.linalg.norm(v)), depth_range=(0.5, 10.0),
                       quality=QualitySettings(min_ok_parallax_area=1, bas_relief_valley_deg=0.0))
    assert 3.0 <= scaled.parallax_px < 6.4      # measured 4.0 px: the band the scaling adds at 160x120
    np.testing.assert_allclose(scaled.v, unscaled.v, rtol=1e-9)          # the rule changes the verdict alone
    assert unscaled.verdict is Verdict.OK and not unscaled.quality.small_parallax
    assert scaled.verdict is Verdict.AMBIGUOUS and scaled.quality.small_parallax
    assert scaled.quality.reason.startswith(f"parallax {scaled.parallax_px:.2f} px, under 6.49 px (min_ok_parallax_px=3 "
                                            "scaled to a 160x120 image")


def test_small_parallax_reason_and_its_place_among_the_verdicts():
    from cmax.fitting.quality import small_parallax_reason

    assert small_parallax_reason(2.999, 3.0).startswith("parallax 3.00 px, under min_ok_parallax_px=3")
    assert small_parallax_reason(3.0, 3.0) == small_parallax_reason(None, 3.0) == small_parallax_reason(1.0, 0) == ""
    reason = small_parallax_reason(2.0, 3.0)
    low = LowMotion(LowMotionCause.PARALLAX, "parallax 0.4 px")
    for worse in (verdict_of(success=False, failed_stages=["local_refine"], low_motion=None, alternatives=[],
                             small_parallax=reason),
                  verdict_of(success=True, failed_stages=[], low_motion=low, alternatives=[], small_parallax=reason),
                  verdict_of(success=True, failed_stages=[], low_motion=None, alternatives=[_alt("mirrored", 1.0)],
                             sparse="sparse", small_parallax=reason)):
        assert not worse.small_parallax
    with pytest.raises(ValueError, match="min_ok_parallax_px"):
        QualitySettings(min_ok_parallax_px=-1.0)


def test_the_least_parallax_of_an_ok_window_grows_on_a_smaller_image():
    """Was: ``ok`` windows 37-98 deg off at 160x120 with 3.0-5.5 px of parallax (held-out ``indoor_flying`` seed
    111: 74.5 deg, 4.75 px) and on the ECD slider at 240x180 (43.9 deg, 3.47 px), over the 3 px that suffice at
    346x260. The threshold is ``min_ok_parallax_px`` times ``sqrt(346*260 / (width*height))`` on a smaller image."""
    from cmax.fitting.quality import min_ok_parallax, small_parallax_reason

    # 346*260 = 89,960 pixels; 160*120 = 19,200; 240*180 = 43,200 (worked out by hand)
    assert min_ok_parallax(3.0, 346, 260, 89_960) == pytest.approx(3.0, abs=1e-12)
    assert min_ok_parallax(3.0, 160, 120, 89_960) == pytest.approx(3.0 * 2.164581, rel=1e-6)      # 6.4937 px
    assert min_ok_parallax(3.0, 240, 180, 89_960) == pytest.approx(3.0 * 1.443055, rel=1e-6)      # 4.3292 px
    assert min_ok_parallax(3.0, 1280, 720, 89_960) == 3.0          # a larger image: never less than the setting
    assert min_ok_parallax(3.0, 160, 120, 1) == 3.0                 # min_ok_parallax_area=1: not scaled
    assert min_ok_parallax(0.0, 96, 72, 89_960) == 0.0              # the rule off stays off
    with pytest.raises(ValueError, match="pixels"):
        min_ok_parallax(3.0, 0, 120, 89_960)

    assert small_parallax_reason(4.75, 3.0, (160, 120)).startswith("parallax 4.75 px, under 6.49 px (")
    assert small_parallax_reason(3.47, 3.0, (240, 180)).startswith("parallax 3.47 px, under 4.33 px (")
    assert small_parallax_reason(6.6, 3.0, (160, 120)) == small_parallax_reason(4.75, 3.0, (346, 260)) == ""
    assert small_parallax_reason(4.75, 3.0, (160, 120), reference_area=1) == ""
    assert small_parallax_reason(2.0, 3.0, (346, 260)) == small_parallax_reason(2.0, 3.0)   # unchanged at 346x260
    reason = small_parallax_reason(4.75, 3.0, (160, 120))
    ok = verdict_of(success=True, failed_stages=[], low_motion=None, alternatives=[_alt("mirrored", 1.0)],
                    small_parallax=reason)
    assert ok.small_parallax
    assert ok.verdict is Verdict.AMBIGUOUS and ok.reason.startswith(reason + "; every alternative")

    assert QualitySettings().min_ok_parallax_area == 89_960
    for bad in (0, -5, 2.5, True):
        with pytest.raises(ValueError, match="min_ok_parallax_area"):
            QualitySettings(min_ok_parallax_area=bad)


def _moved_along_the_trade(degrees: float):
    """:func:`clear_window`'s window, its fit's speed, and that fit moved ``degrees`` along the bas-relief trade (its
    translation turned towards ``+b``, with the rotation that makes up the change of its flow:
    :func:`cmax.fitting.quality.turned_motions`): ``(w, r, speed, window, v_off, omega_off)``."""
    from cmax.fitting.api import DEFAULT_CONTRAST, DEFAULT_POLARITY_SPLIT
    from cmax.fitting.quality import MotionScorer, turned_motions
    from cmax.fitting.window import Window

    w, r = clear_window()
    speed = float(np.linalg.norm(w.twist[:3]))
    settings = FitSettings(depth_range=(1.0, 20.0), contrast=DEFAULT_CONTRAST["se3"],
                           polarity_split=DEFAULT_POLARITY_SPLIT["se3"])
    window = Window.from_events(w.events, w.K, settings, r.inverse_depth_grid.shape)
    scorer = MotionScorer.build(window, r.v, r.omega, speed, QualitySettings())
    moved = dict((name, (v, omega)) for name, v, omega in turned_motions(scorer.objective, r.v, r.omega, scorer.rho,
                                                                         degrees))
    v_off, omega_off = moved["turned_+b"]
    return w, r, speed, window, v_off, omega_off


def test_turned_motions_keep_the_speed_and_turn_by_the_angle():
    """Each of the four turned motions keeps ``|v|``, lies ``degrees`` from ``v``, and the four directions are two
    perpendicular pairs of opposite turns (closed form: the angle between ``+a`` and ``-a`` is twice the turn)."""
    w, r, speed, window, v_off, _ = _moved_along_the_trade(20.0)
    assert abs(np.linalg.norm(v_off) - np.linalg.norm(r.v)) < 1e-9 * np.linalg.norm(r.v)
    assert abs(_angle_deg(v_off, r.v) - 20.0) < 1e-6
    from cmax.fitting.quality import MotionScorer, turned_motions

    scorer = MotionScorer.build(window, r.v, r.omega, speed, QualitySettings())
    turned = {name: v for name, v, _ in turned_motions(scorer.objective, r.v, r.omega, scorer.rho, 12.0)}
    assert sorted(turned) == ["turned_+a", "turned_+b", "turned_-a", "turned_-b"]
    assert all(abs(_angle_deg(v, r.v) - 12.0) < 1e-6 for v in turned.values())
    assert abs(_angle_deg(turned["turned_+a"], turned["turned_-a"]) - 24.0) < 1e-6
    assert abs(_angle_deg(turned["turned_+b"], turned["turned_-b"]) - 24.0) < 1e-6


def test_a_fit_off_the_optimum_along_the_bas_relief_trade_is_not_ok(monkeypatch):
    """Was: a se3 fit part of whose translation's flow a rotation of the wrong size explained (the bas-relief trade:
    the direction tens of degrees off, the depth offset) was ``ok`` when the mirrored, bas-relief, planar-dual and
    rotation-flipped alternatives all scored worse beyond noise, as on the README's ``cmax fit room.h5`` example
    (docs/quality.md). Here the fit handed to the verdict is the window's own fit moved 20 deg along that trade, and
    the ambiguity test is made to find every alternative worse beyond noise: with ``bas_relief_turn_deg`` 0 (the old
    rule; the flat-valley rule off too) the verdict is ``ok``; by default a motion 10 deg back along the trade scores better than it beyond its
    noise, so the verdict is ``ambiguous`` and ``turned``, the motion unchanged. The fit itself, at its optimum, stays
    ``ok`` (:func:`test_a_clear_window_is_ok_and_its_fit_is_right`)."""
    import cmax.fitting.api as api
    from cmax.fitting.quality import best_turned, turned_reason

    w, r, speed, window, v_off, omega_off = _moved_along_the_trade(20.0)
    back = best_turned(window, v_off, omega_off, speed, QualitySettings())
    assert back.gain < -back.noise                            # better than the moved fit, beyond its noise
    assert _angle_deg(back.v, r.v) < _angle_deg(v_off, r.v)    # back towards the optimum
    run_stages = api.run_stages

    def moved_stages(*args, **kwargs):
        motion, logs = run_stages(*args, **kwargs)
        return replace(motion, v=v_off, omega=omega_off), logs

    monkeypatch.setattr(api, "run_stages", moved_stages)
    monkeypatch.setattr(api, "assess", lambda *args, **kwargs: ((_alt("mirrored", 1.0),), "", True))
    old, new = (QualitySettings(min_ok_parallax_area=1, bas_relief_turn_deg=0.0, bas_relief_valley_deg=0.0),
                QualitySettings(min_ok_parallax_area=1))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        before, after = (fit(w.events, w.K, speed=speed, depth_range=(1.0, 20.0), quality=q) for q in (old, new))
    np.testing.assert_allclose(after.v, v_off, rtol=1e-12)
    np.testing.assert_allclose(before.v, after.v, rtol=1e-12)               # the rule changes the verdict alone
    assert before.verdict is Verdict.OK and not before.quality.turned
    assert after.verdict is Verdict.AMBIGUOUS and after.quality.turned
    assert after.quality.reason.startswith("a motion turned 10 deg along the bas-relief trade (turned_")
    assert after.quality.summary()["turned"] is True
    assert turned_reason(back, 10.0) and after.quality.reason.endswith(before.quality.reason)


def _assert_it_only_turns_an_ok_ambiguous(field: str, reason: str) -> None:
    """A verdict rule given to :func:`verdict_of` as ``field`` with a ``reason`` turns an ``ok`` into ``ambiguous``
    (its reason first) and leaves a worse verdict with its own reason."""
    ok = verdict_of(success=True, failed_stages=[], low_motion=None, alternatives=[_alt("mirrored", 1.0)],
                    **{field: reason})
    assert ok.verdict is Verdict.AMBIGUOUS and getattr(ok, field)
    assert ok.reason.startswith(reason + "; every alternative")
    ambiguous = verdict_of(success=True, failed_stages=[], low_motion=None, alternatives=[_alt("mirrored", 0.01)],
                           **{field: reason})
    assert ambiguous.verdict is Verdict.AMBIGUOUS and not getattr(ambiguous, field)
    failed = verdict_of(success=False, failed_stages=["refine"], low_motion=None, alternatives=[], **{field: reason})
    assert failed.verdict is Verdict.FAILED and not getattr(failed, field)


def test_turned_reason_and_its_place_among_the_verdicts():
    """``turned_reason`` is empty unless the turned motion scores better than the fit (gain < 0), and the rule only
    turns an ``ok`` into ``ambiguous``: a worse verdict keeps its own reason; the setting is checked."""
    from cmax.fitting.quality import turned_reason

    better, worse = _alt("turned_+a", -0.01, 0.5), _alt("turned_+a", 0.01, 0.5)
    assert turned_reason(worse, 10.0) == turned_reason(None, 10.0) == ""
    reason = turned_reason(better, 10.0)
    _assert_it_only_turns_an_ok_ambiguous("turned", reason)
    with pytest.raises(ValueError, match="bas_relief_turn_deg"):
        QualitySettings(bas_relief_turn_deg=-1.0)


#: The flat-valley rule at the value measured in docs/quality.md (off by default: it reversed ECD slider windows
#: through fit_sequence's resolution).
VALLEY = QualitySettings(bas_relief_valley_deg=20.0)


def test_a_direction_the_bas_relief_valley_does_not_fix_is_not_ok(monkeypatch):
    """Was: ``ok`` when every alternative of the ambiguity test scored worse beyond noise and no motion 10 deg along
    the bas-relief trade scored better than the fit, while motions 20 deg along it scored within noise of the fit: the
    README's ``cmax fit room.h5`` example (window 1: 15 deg off, depth abs_rel 0.39, docs/quality.md), and this plane
    slid past sideways at 160x120 with 8.6 px of fitted parallax (``ok`` 42 deg off on an Intel Xeon host). Now such a
    window is ``ambiguous`` and ``flat_valley`` with ``bas_relief_valley_deg=20``, its motion unchanged (0, the
    default, turns the rule off);
    with the rotation held (``omega=``) the trade does not exist and the rule does not apply."""
    from cmax.fitting.quality import valley_reason, valley_turned

    v = 5.0 * np.array([0.27, 0.081, 0.0])
    events, K = _sliding_plane(v, 2002)
    speed = float(np.linalg.norm(v))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        without = fit(events, K, speed=speed, depth_range=(0.5, 10.0), quality=QualitySettings(bas_relief_valley_deg=0.0))
        default = fit(events, K, speed=speed, depth_range=(0.5, 10.0), quality=VALLEY)
        held = fit(events, K, speed=speed, depth_range=(0.5, 10.0), omega=np.zeros(3), quality=VALLEY)
    np.testing.assert_allclose(default.v, without.v, rtol=1e-9)             # the rule changes the verdict alone
    assert _angle_deg(without.v, v) > 10.0         # the ground truth: this direction must not be called ok
    assert not held.quality.flat_valley
    if without.verdict is Verdict.OK:   # (on the host measured: ok at 42 deg) now ambiguous
        assert default.verdict is Verdict.AMBIGUOUS and default.quality.flat_valley
        assert default.quality.reason.startswith("a motion turned 20 deg along the bas-relief trade (turned_")
        assert default.quality.reason.endswith(without.quality.reason)
        assert default.quality.summary()["flat_valley"] is True
    else:               # another host's rounding let another rule flag it: make the others pass it, as measured
        monkeypatch.setattr("cmax.fitting.api.assess", lambda *args, **kwargs: ((_alt("mirrored", 1.0),), "", True))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            forced = fit(events, K, speed=speed, depth_range=(0.5, 10.0),
                         quality=QualitySettings(bas_relief_turn_deg=0.0, min_ok_parallax_area=1,
                                                 bas_relief_valley_deg=20.0))
        assert forced.verdict is Verdict.AMBIGUOUS and forced.quality.flat_valley
    # the motion the rule found: 20 deg from the fit, its speed kept, within noise
    from cmax.fitting.api import DEFAULT_CONTRAST, DEFAULT_POLARITY_SPLIT
    from cmax.fitting.window import Window

    settings = FitSettings(depth_range=(0.5, 10.0), contrast=DEFAULT_CONTRAST["se3"],
                           polarity_split=DEFAULT_POLARITY_SPLIT["se3"])
    window = Window.from_events(events, K, settings, without.inverse_depth_grid.shape)
    valley = valley_turned(window, without.v, without.omega, speed, VALLEY)
    assert abs(_angle_deg(valley.v, without.v) - 20.0) < 1e-6
    assert abs(np.linalg.norm(valley.v) - speed) < 1e-9 * speed
    assert valley.gain <= valley.noise and valley_reason(valley, 20.0)


def test_the_valley_rule_is_off_by_default():
    """``bas_relief_valley_deg`` defaults to 0 (the rule off): on by default it made every ECD slider window
    ambiguous and fit_sequence's resolution then left windows reversed at 2 of 5 fit seeds (docs/quality.md)."""
    assert QualitySettings().bas_relief_valley_deg == 0.0


def test_valley_reason_and_its_place_among_the_verdicts():
    """``valley_reason`` is empty unless the motion along the trade scores within noise of the fit (gain at most its
    noise), and the rule only turns an ``ok`` into ``ambiguous``: a worse verdict keeps its own reason; the setting
    is checked."""
    from cmax.fitting.quality import valley_reason

    within, beyond = _alt("turned_+a", 0.2, 0.5), _alt("turned_+a", 0.6, 0.5)
    assert valley_reason(beyond, 20.0) == valley_reason(None, 20.0) == ""
    reason = valley_reason(within, 20.0)
    assert "within noise" in reason and "bas_relief_valley_deg=20" in reason
    _assert_it_only_turns_an_ok_ambiguous("flat_valley", reason)
    with pytest.raises(ValueError, match="bas_relief_valley_deg"):
        QualitySettings(bas_relief_valley_deg=-1.0)
