"""se3 motion members (``FitSettings.motion_members``): the motion stages on several draws of the window,
and their consensus."""
from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from benchmarks.synthetic_windows import make_window
from cmax.fitting import FitSettings, fit
from cmax.fitting.settings import BASE_MAX_EVENTS
from cmax.fitting.pipeline import Motion, MotionMembersStage, consensus, member_seed
from cmax.fitting.window import Window
from cmax.warp import WarpEvents

DURATION_S = 0.1


@functools.lru_cache(maxsize=None)
def small_se3():
    """A constant-twist indoor_flying window at 120 x 90."""
    return make_window("indoor_flying", 3, width=120, height=90, focal=90.0, duration_s=DURATION_S, max_frames=60)


def _turned(angle_deg: float, speed: float = 2.0) -> np.ndarray:
    """``speed`` times the unit vector at ``angle_deg`` from +x towards +y."""
    a = math.radians(angle_deg)
    return speed * np.array([math.cos(a), math.sin(a), 0.0])


def test_consensus_is_the_mean_of_the_members_near_their_medoid_and_drops_the_mirrored_one():
    omegas = [np.array([0.1, 0.0, 0.0]), np.array([0.3, 0.0, 0.0]), np.array([0.2, 0.0, 0.3]),
              np.array([5.0, 5.0, 5.0])]
    motions = [Motion(v=_turned(a), omega=o, speed=2.0) for a, o in zip((-6.0, 6.0, 0.0, 180.0), omegas)]
    agreed, kept = consensus(motions, agree_deg=30.0, duration_s=DURATION_S)
    np.testing.assert_array_equal(kept, [True, True, True, False])
    # the three kept directions are symmetric about +x: their mean is +x, at the members' speed
    np.testing.assert_allclose(agreed.v, [2.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(agreed.omega, [0.2, 0.0, 0.1], atol=1e-12)
    assert agreed.alternatives == ()


def test_consensus_distance_counts_the_rotation_over_the_window():
    """Same direction, but one member rotates 10 rad/s more: 10 rad/s x 0.1 s = 57 deg away, dropped."""
    motions = [Motion(v=_turned(0.0), omega=np.zeros(3), speed=2.0),
               Motion(v=_turned(2.0), omega=np.zeros(3), speed=2.0),
               Motion(v=_turned(0.0), omega=np.array([0.0, 10.0, 0.0]), speed=2.0)]
    _, kept = consensus(motions, agree_deg=30.0, duration_s=DURATION_S)
    np.testing.assert_array_equal(kept, [True, True, False])
    _, kept = consensus(motions, agree_deg=60.0, duration_s=DURATION_S)
    assert kept.all()


def test_member_seeds_are_the_fit_seed_first_then_distinct_and_reproducible():
    assert member_seed(7, 0) == 7
    seeds = [member_seed(7, k) for k in range(1, 6)]
    assert len(set(seeds + [7])) == 6 and seeds == [member_seed(7, k) for k in range(1, 6)]
    assert member_seed(8, 1) != member_seed(7, 1)


def test_a_window_drawn_again_keeps_its_events_and_changes_only_the_dither():
    w = small_se3()
    window = Window.from_events(w.events, w.K, FitSettings(), (6, 8))
    again = window.with_seed(5)
    assert again.source is w.events and len(again.ev) == len(window.ev)
    np.testing.assert_array_equal(again.ev.t.numpy(), window.ev.t.numpy())
    shift = (again.ev.x - window.ev.x).numpy()
    assert np.abs(shift).max() < 1.0 and np.abs(shift).max() > 0.1      # both within their pixel, drawn apart
    assert len(w.events) <= BASE_MAX_EVENTS                           # no subsample: event k is event k
    assert np.abs(again.ev.x.numpy() - w.events.x).max() <= 0.5
    assert np.abs(again.ev.y.numpy() - w.events.y).max() <= 0.5
    prepared = Window(WarpEvents.from_events(w.events, w.K), FitSettings(), window.grid)
    with pytest.raises(ValueError, match="keeps no source events"):
        prepared.with_seed(1)


def test_one_member_is_the_plain_fit_and_member_zero_is_the_window_itself():
    w = small_se3()
    speed = float(np.linalg.norm(w.twist[:3]))
    plain = fit(w.events, w.K, speed=speed)
    one = fit(w.events, w.K, speed=speed, motion_members=1)
    assert [s.stage for s in one.stages] == [s.stage for s in plain.stages] and "motion_members" not in [
        s.stage for s in plain.stages]
    np.testing.assert_array_equal(one.v, plain.v)
    np.testing.assert_array_equal(one.omega, plain.omega)
    two = fit(w.events, w.K, speed=speed, motion_members=2)
    names = [s.stage for s in two.stages]
    assert names[:5] == ["patch_flow [member 0]", "local_refine [member 0]", "patch_flow [member 1]",
                         "local_refine [member 1]", "motion_members"]
    # member 0 solved exactly what the plain fit solved
    refine_plain = next(s for s in plain.stages if s.stage == "local_refine")
    refine_zero = two.stages[1]
    assert (refine_zero.objective_before, refine_zero.objective_after, refine_zero.iterations) == (
        refine_plain.objective_before, refine_plain.objective_after, refine_plain.iterations)
    assert "of 2 members within 30 deg" in two.stages[4].message
    assert np.linalg.norm(two.v) == pytest.approx(speed, rel=1e-9)


def test_the_members_consensus_is_the_fits_motion_before_the_sweep(monkeypatch):
    """The motion the fit returns is the consensus of what the members' stages returned."""
    w = small_se3()
    speed = float(np.linalg.norm(w.twist[:3]))
    ends = []
    original = MotionMembersStage.run

    def spy(self, window, motion, solver):
        import cmax.fitting.pipeline as pipeline

        inner = pipeline.run_stages

        def recording(stages, drawn, start, solver_):
            end, logs = inner(stages, drawn, start, solver_)
            ends.append(end)
            return end, logs

        monkeypatch.setattr(pipeline, "run_stages", recording)
        try:
            return original(self, window, motion, solver)
        finally:
            monkeypatch.setattr(pipeline, "run_stages", inner)

    monkeypatch.setattr(MotionMembersStage, "run", spy)
    r = fit(w.events, w.K, speed=speed, motion_members=3)
    assert len(ends) == 3
    agreed, _ = consensus(ends, 30.0, (r.t1_us - r.t0_us) * 1e-6)
    np.testing.assert_allclose(r.v, agreed.v, rtol=1e-12)
    np.testing.assert_allclose(r.omega, agreed.omega, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("field, value", [("motion_members", 0), ("motion_members", 2.5),
                                          ("members_agree_deg", 0.0), ("members_agree_deg", float("nan"))])
def test_members_settings_are_checked(field, value):
    with pytest.raises(ValueError, match=field):
        FitSettings(**{field: value})
