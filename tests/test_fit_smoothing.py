"""The motion prior across windows of ``fit_sequence`` (``QualitySettings.smoothing``): the neighbours'
consensus, the test of a window's motion against it on the fit's own objective, and the choice."""
from __future__ import annotations

import functools
import math
from dataclasses import replace

import numpy as np
import pytest

from benchmarks.synthetic_windows import make_window
from cmax.fitting import QualitySettings, Verdict, fit, fit_sequence
from cmax.fitting import sequence as sequence_module
from cmax.fitting.quality import Alternative, MotionScorer, Quality
from cmax.fitting.sequence import neighbour_consensus
from cmax.fitting.settings import FitSettings
from cmax.fitting.window import Window


def _rotate_z(v: np.ndarray, degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]])


@functools.lru_cache(maxsize=None)
def street():
    """A street seen driving forward (3 px of parallax) and its fit with the true speed."""
    w = make_window("driving", 2, width=120, height=90, focal=90.0, duration_s=0.1, max_frames=60)
    return w, fit(w.events, w.K, speed=float(np.linalg.norm(w.twist[:3])), depth_range=(1.0, 20.0))


def _result(v, omega=(0.0, 0.0, 0.0), verdict=Verdict.OK, resolved=False):
    base = street()[1]
    return replace(base, v=np.asarray(v, float), omega=np.asarray(omega, float),
                   quality=Quality(verdict, "constructed", resolved=resolved))


# ----------------------------------------------------------------------------------------------
# The consensus
# ----------------------------------------------------------------------------------------------
def test_the_consensus_is_the_running_median_of_the_window_and_its_confident_neighbours():
    x = np.array([1.0, 0.0, 0.0])
    results = [_result(_rotate_z(x, 10), (0.0, 0.1, 0.0)),
               _result(_rotate_z(x, 20), (0.0, 0.3, 0.0)),
               _result(-x, (0.0, 9.0, 0.0)),                       # the window itself: one vote
               _result(_rotate_z(x, 30), (0.0, 0.2, 0.0)),
               _result(_rotate_z(x, 20), (0.0, 0.3, 0.0), verdict=Verdict.AMBIGUOUS, resolved=True),
               _result(_rotate_z(x, 0), (0.0, 0.0, 0.0))]          # 3 windows away: outside neighbours=2
    direction, omega, count = neighbour_consensus(results, 2, neighbours=2, min_count=2)
    # votes at 10, 20, 180, 30 and 20 deg: the component-wise medians are those of the 20 deg direction
    assert count == 4
    np.testing.assert_allclose(direction, _rotate_z(x, 20), atol=1e-12)
    np.testing.assert_allclose(omega, [0.0, 0.3, 0.0])
    # an unresolved ambiguous neighbour does not vote
    results[4] = _result(_rotate_z(x, 20), (0.0, 0.3, 0.0), verdict=Verdict.AMBIGUOUS)
    assert neighbour_consensus(results, 2, neighbours=2, min_count=2)[2] == 3
    # one deviant neighbour among two moves nothing: the window's own vote breaks the tie
    direction, _, count = neighbour_consensus([_result(x), _result(x), _result(-x)], 0, neighbours=2, min_count=2)
    assert count == 2 and np.allclose(direction, x)
    # too few confident neighbours: no consensus
    assert neighbour_consensus(results, 0, neighbours=1, min_count=2) is None
    assert neighbour_consensus(results, 0, neighbours=1, min_count=1)[2] == 1


@pytest.mark.parametrize("field,value", [("smoothing", 1), ("min_consensus", 0), ("min_consensus", 1.5),
                                         ("smoothing_min_deg", -1.0), ("smoothing_min_deg", float("nan"))])
def test_smoothing_settings_are_checked(field, value):
    with pytest.raises((TypeError, ValueError), match=field):
        QualitySettings(**{field: value})


# ----------------------------------------------------------------------------------------------
# The test against the window's own objective
# ----------------------------------------------------------------------------------------------
def test_the_scorer_tells_a_far_motion_from_a_near_one():
    """On a clear window, the fit's own motion rotated by 1 deg is within noise of the fit (the data
    cannot tell them apart), the direction 60 deg away is not; and the fit against itself gains 0."""
    w, r = street()
    settings = FitSettings(depth_range=(1.0, 20.0), contrast="variance", polarity_split=False)
    window = Window.from_events(w.events, w.K, settings, (24, 32))
    scorer = MotionScorer.build(window, r.v, r.omega, float(np.linalg.norm(r.v)), QualitySettings())
    assert scorer is not None
    itself = scorer.score("itself", r.v, r.omega)
    assert itself.gain == pytest.approx(0.0, abs=1e-9) and itself.within_noise
    near = scorer.score("near", _rotate_z(r.v, 1.0), r.omega)
    far = scorer.score("far", np.linalg.norm(r.v) * np.array([1.0, 0.0, 0.3]) / np.linalg.norm([1.0, 0.0, 0.3]),
                       r.omega)
    assert near.within_noise, near
    assert not far.within_noise and far.gain > 0, far


# ----------------------------------------------------------------------------------------------
# The choice in fit_sequence
# ----------------------------------------------------------------------------------------------
def _constructed_sequence(monkeypatch, prior_within_noise: bool, windows_off=(2,), count: int = 5,
                          quality: QualitySettings | None = None):
    """``count`` windows of a camera moving +x; the own fits of those in ``windows_off`` are 25 deg off. The
    prior's score is constructed (within noise or not); returns the sequence and the poses the re-fits were
    given."""
    speed, truth = 0.5, np.array([0.5, 0.0, 0.0])
    off = _rotate_z(truth, 25.0)
    poses, windows = [], []
    base = street()[1]

    def constructed_fit(events, K, model="se3", *, speed=None, pose=None, omega=None, init=None, quality=None,
                        **options):
        t0, t1 = int(events.t[0]), int(events.t[-1])
        if pose is not None:
            poses.append(np.asarray(pose, float))
            pose = np.asarray(pose, float)
            return replace(base, t0_us=t0, t1_us=t1, v=pose[:3], omega=pose[3:], scale_known=True,
                           quality=Quality(Verdict.OK, "ambiguity not tested: the pose is given"))
        windows.append(t0)
        v = off if len(windows) - 1 in windows_off else truth
        return replace(base, t0_us=t0, t1_us=t1, v=v.copy(), omega=np.zeros(3),
                       quality=Quality(Verdict.OK, "every alternative scores worse beyond noise"))

    def constructed_score(events, K, result, v, omega, settings, fit_options):
        gain = 0.05 if prior_within_noise else 0.5
        return Alternative("neighbours", v, omega, gain, 0.1, gain <= 0.1)

    monkeypatch.setattr(sequence_module, "fit", constructed_fit)
    monkeypatch.setattr(sequence_module, "_score_prior", constructed_score)
    w = street()[0]
    window_us = (int(w.events.t[-1]) - int(w.events.t[0])) // count
    options = {} if quality is None else {"quality": quality}
    return (fit_sequence(w.events, w.K, window_us=window_us, speed=speed, min_events=10, **options), poses, truth,
            off)


def test_a_window_its_data_cannot_tell_from_its_neighbours_takes_their_motion(monkeypatch):
    sequence, poses, truth, off = _constructed_sequence(monkeypatch, prior_within_noise=True)
    middle = sequence.results[2]
    assert len(poses) == 1                                # only the middle window differs from its neighbours
    np.testing.assert_allclose(poses[0], np.r_[truth, np.zeros(3)], atol=1e-12)
    np.testing.assert_allclose(middle.v, truth, atol=1e-12)
    np.testing.assert_allclose(middle.quality.replaced[0], off)         # its own fit, kept
    assert "took it" in middle.quality.resolution and middle.verdict is Verdict.OK
    assert all("smoothing" not in r.quality.resolution for k, r in enumerate(sequence.results) if k != 2)


def test_a_window_whose_data_beats_the_prior_keeps_its_fit(monkeypatch):
    sequence, poses, truth, off = _constructed_sequence(monkeypatch, prior_within_noise=False)
    middle = sequence.results[2]
    assert poses == []
    np.testing.assert_allclose(middle.v, off, atol=1e-12)
    assert "kept the fit" in middle.quality.resolution and middle.quality.replaced is None


@pytest.mark.parametrize("span_s", [0.0, QualitySettings().smoothing_span_s])
def test_a_run_of_windows_with_one_wrong_motion_is_outvoted_by_the_prior_s_span(monkeypatch, span_s):
    """Nine windows moving +x, three in a row fitted 25 deg off (the slider's bias, window after window):
    with two neighbours on each side (span 0) the run is its own majority and nothing moves; with the
    default span (every window here lies within 1.7 s) the six others outvote it and the run takes +x."""
    quality = QualitySettings(smoothing_span_s=span_s)
    sequence, poses, truth, off = _constructed_sequence(monkeypatch, True, windows_off=(3, 4, 5), count=9,
                                                        quality=quality)
    run = sequence.results[3:6]
    if span_s == 0.0:
        assert poses == [] and all(np.allclose(r.v, off) for r in run)
        return
    assert len(poses) == 3
    for r in run:
        np.testing.assert_allclose(r.v, truth, atol=1e-12)
        np.testing.assert_allclose(r.quality.replaced[0], off)
        assert r.quality.resolution.startswith("smoothing: the consensus of 8 neighbour(s) is 25.0 deg away; took it")
    assert all(r.quality.resolution == "" for k, r in enumerate(sequence.results) if k not in (3, 4, 5))


def _unsteady_sequence(monkeypatch, **options):
    """Five windows of a camera moving +x at 0.5 m/s; the middle one's fit is 60 deg off and unsteady (its motion
    changes inside it). Returns the sequence and the poses the re-fits were given."""
    truth, off = np.array([0.5, 0.0, 0.0]), _rotate_z(np.array([0.5, 0.0, 0.0]), 60.0)
    base, poses, windows = street()[1], [], []

    def constructed_fit(events, K, model="se3", *, speed=None, pose=None, omega=None, init=None, **kwargs):
        t0, t1 = int(events.t[0]), int(events.t[-1])
        if pose is not None:
            poses.append(np.asarray(pose, float))
            return replace(base, t0_us=t0, t1_us=t1, v=np.asarray(pose, float)[:3], omega=np.zeros(3),
                           scale_known=True, quality=Quality(Verdict.OK, "ambiguity not tested: the pose is given"))
        windows.append(t0)
        if len(windows) == 3:
            return replace(base, t0_us=t0, t1_us=t1, v=off.copy(), omega=np.zeros(3),
                           quality=Quality(Verdict.AMBIGUOUS, "the event rate changes 15.3x", rate_change=15.3,
                                           unsteady=True))
        return replace(base, t0_us=t0, t1_us=t1, v=truth.copy(), omega=np.zeros(3),
                       quality=Quality(Verdict.OK, "every alternative scores worse beyond noise"))

    monkeypatch.setattr(sequence_module, "fit", constructed_fit)
    monkeypatch.setattr(sequence_module, "_score_prior",
                        lambda *a, **k: Alternative("neighbours", a[3], a[4], 0.5, 0.1, False))  # the fit "wins"
    w = street()[0]
    window_us = (int(w.events.t[-1]) - int(w.events.t[0])) // 5
    return fit_sequence(w.events, w.K, window_us=window_us, speed=0.5, min_events=10, **options), poses, truth, off


def test_an_unsteady_window_takes_its_neighbours_motion_without_its_own_vote(monkeypatch):
    """A window whose motion changes inside it (a stop) is no evidence for its direction, however well its fit
    scores: it takes the consensus of its neighbours (re-fitted with it), counts as resolved, and its own
    direction neither votes in its consensus nor in its neighbours'."""
    sequence, poses, truth, off = _unsteady_sequence(monkeypatch)
    middle = sequence.results[2]
    assert len(poses) == 1
    np.testing.assert_allclose(poses[0], np.r_[truth, np.zeros(3)], atol=1e-12)
    np.testing.assert_allclose(middle.v, truth, atol=1e-12)
    np.testing.assert_allclose(middle.quality.replaced[0], off)
    assert middle.verdict is Verdict.AMBIGUOUS and middle.quality.unsteady and middle.quality.resolved
    assert middle.quality.resolution == ("smoothing: the consensus of 4 neighbour(s) is 60.0 deg away; took it (the "
                                         "motion is not steady over the window: its own fit is no evidence)")
    assert sequence.counts()["resolved"] == 1
    assert all(r.quality.resolution == "" for k, r in enumerate(sequence.results) if k != 2)


def test_an_unsteady_window_stays_unresolved_without_the_prior(monkeypatch):
    sequence, poses, _, off = _unsteady_sequence(monkeypatch, quality=QualitySettings(smoothing=False))
    middle = sequence.results[2]
    assert poses == [] and np.allclose(middle.v, off) and not middle.quality.resolved
    assert middle.quality.resolution == ("unresolved: the motion is not steady over the window and the motion prior "
                                         "(QualitySettings.smoothing) is off")


def test_an_unsteady_window_does_not_vote():
    x = np.array([1.0, 0.0, 0.0])
    results = [_result(x), _result(_rotate_z(x, 40)), _result(_rotate_z(x, 60))]
    # with its vote: the component-wise medians of 0, 40 and 60 deg are those of 40 deg
    np.testing.assert_allclose(neighbour_consensus(results, 0, neighbours=2, min_count=2)[0], _rotate_z(x, 40),
                               atol=1e-12)
    # without it: the medians of 40 and 60 deg alone, (cos 40 + cos 60, sin 40 + sin 60) / 2, at 50 deg
    np.testing.assert_allclose(neighbour_consensus(results, 0, neighbours=2, min_count=2, own_vote=False)[0],
                               _rotate_z(x, 50), atol=1e-12)
    results[1] = replace(results[1], quality=Quality(Verdict.AMBIGUOUS, "unsteady", resolved=True, unsteady=True))
    assert neighbour_consensus(results, 0, neighbours=2, min_count=1)[2] == 1     # an unsteady neighbour: no vote


def test_the_prior_s_neighbours_follow_its_span_in_seconds():
    quality = QualitySettings()
    assert sequence_module.prior_neighbours(quality, 166_500) == 10          # the default window: +-1.7 s
    assert sequence_module.prior_neighbours(quality, 50_000) == 34
    assert sequence_module.prior_neighbours(quality, 2_000_000) == quality.neighbours      # never fewer
    assert sequence_module.prior_neighbours(QualitySettings(smoothing_span_s=0.0), 166_500) == 2
    with pytest.raises(ValueError, match="smoothing_span_s"):
        QualitySettings(smoothing_span_s=-1.0)


def test_without_smoothing_nothing_changes(monkeypatch):
    monkeypatch.setattr(sequence_module, "_score_prior",
                        lambda *a, **k: pytest.fail("scored although smoothing is off"))
    w = street()[0]
    window_us = (int(w.events.t[-1]) - int(w.events.t[0])) // 2
    sequence = fit_sequence(w.events, w.K, window_us=window_us, speed=0.5, min_events=10,
                            quality=QualitySettings(smoothing=False, ambiguity_test=False),
                            depth_range=(1.0, 20.0))
    assert all("smoothing" not in r.quality.resolution for r in sequence.results)
