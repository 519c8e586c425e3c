"""Tests of the ESIM event model (cmax/sim/esim.py)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from cmax.events import Events, concatenate
from cmax.sim.esim import (
    MIN_THRESHOLD_FRACTION,
    EsimSettings,
    EventSimulator,
    log_intensity,
    threshold_crossings,
)
from cmax.sim._cvlog import _cv_log32f, _fma32

cv2 = pytest.importorskip("cv2")


# -- helpers --------------------------------------------------------------------------------
def grey_for_log(log: np.ndarray, eps: float = 1e-3) -> np.ndarray:
    """Float grey values whose log intensity ``log(I/255 + eps)`` is ``log``."""
    return 255.0 * (np.exp(np.asarray(log, np.float64)) - eps)


def smooth_video(n_frames: int = 12, height: int = 16, width: int = 20, seed: int = 0):
    """(T, H, W) uint8 frames of a moving smooth pattern with a brightness change."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width]
    phase = rng.uniform(0, 2 * np.pi, 3)
    frames = []
    for k in range(n_frames):
        wave = np.sin(0.5 * x + 0.4 * k + phase[0]) * np.cos(0.3 * y - 0.2 * k + phase[1])
        value = 120 + 60 * wave
        value = value * (1 + 0.3 * np.sin(0.7 * k + phase[2]))
        frames.append(np.clip(np.round(value), 0, 255).astype(np.uint8))
    return np.stack(frames)


def paired_fraction(ours: Events, x, y, t_us, p_signed, tol_us: float) -> tuple[float, float]:
    """Fraction of reference events paired with ours, and the largest |dt| of pairs.

    The k-th event of each (pixel, polarity) in one stream is paired with the
    k-th of the same (pixel, polarity) in the other; a pair matches when
    ``|dt| <= tol_us``. Vectorised: lexsort by (pixel, polarity, t), rank in group.
    """

    def keyed(px, py, pt, pp):
        group = (np.asarray(py, np.int64) * ours.width + np.asarray(px, np.int64)) * 2 + (
            np.asarray(pp) > 0
        )
        order = np.lexsort((pt, group))
        group, pt = group[order], np.asarray(pt, np.float64)[order]
        starts = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
        rank = np.arange(group.size) - np.repeat(starts, np.diff(np.r_[starts, group.size]))
        return group * (1 << 24) + rank, pt

    key_a, t_a = keyed(ours.x, ours.y, ours.t, ours.p)
    key_b, t_b = keyed(x, y, t_us, p_signed)
    _, ia, ib = np.intersect1d(key_a, key_b, assume_unique=True, return_indices=True)
    dt = np.abs(t_a[ia] - t_b[ib])
    return float(np.count_nonzero(dt <= tol_us)) / key_b.size, float(dt.max(initial=0.0))


# -- parity with the reference C++ ESIM -----------------------------------------------------
@pytest.fixture(scope="module")
def truck_pan(shared_data):
    folder = shared_data / "esim_truck_pan"
    paths = sorted((folder / "images").glob("image_*.png"))
    frames = np.stack([cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) for path in paths])
    reference = np.load(folder / "esim_truck_pan_reference.npz")
    times_s = reference["frame_timestamps_s"]
    assert times_s.size == frames.shape[0] + 1  # frame 0 was fed twice
    frames = np.concatenate([frames[:1], frames])
    return frames, np.round(times_s * 1e6).astype(np.int64), reference


@pytest.mark.parametrize("threshold, key", [(0.2, "C0_2"), (0.1, "C0_1")])
def test_matches_reference_esim(truck_pan, threshold, key):
    frames, times_us, reference = truck_pan
    events = EventSimulator(cp=threshold, cn=threshold).simulate(frames, times_us)
    n_ref = reference[f"t_{key}"].size
    matched, max_dt = paired_fraction(
        events, reference[f"x_{key}"], reference[f"y_{key}"], reference[f"t_{key}"] * 1e6,
        reference[f"p_{key}"], tol_us=2.0,
    )
    count_error = (len(events) - n_ref) / n_ref
    print(
        f"\nESIM parity C={threshold}: {len(events)} events vs {n_ref} reference "
        f"({100 * count_error:+.3f} %), {100 * matched:.4f} % paired within 2 µs, "
        f"largest |dt| of a pair {max_dt:.2f} µs"
    )
    assert abs(count_error) <= 0.005
    assert matched >= 0.99


# -- closed forms ---------------------------------------------------------------------------
def test_single_pixel_linear_ramp_gives_predicted_events():
    slope, threshold, frame_dt = 0.0731, 0.2, 10_000  # log units per frame, µs per frame
    log = -3.0 + slope * np.arange(40)
    frames = grey_for_log(log)[:, None, None]
    times = frame_dt * np.arange(40, dtype=np.int64)
    events = EventSimulator(cp=threshold, cn=threshold).simulate(frames, times)
    delta = (log_intensity(frames[-1]) - log_intensity(frames[0])).item()
    assert len(events) == math.floor(delta / threshold) == 14
    assert (events.p == 1).all() and (events.x == 0).all() and (events.y == 0).all()
    predicted = np.arange(1, len(events) + 1) * threshold / slope * frame_dt
    np.testing.assert_allclose(events.t, predicted, atol=1.0)


def test_darkening_ramp_and_asymmetric_thresholds():
    up = np.linspace(-4.0, -1.0, 7)  # +3 log units, then back down
    log = np.r_[up, up[::-1][1:]]
    frames = grey_for_log(log)[:, None, None]
    times = 1000 * np.arange(log.size, dtype=np.int64)
    events = EventSimulator(cp=0.1, cn=0.3).simulate(frames, times)
    on, off = np.count_nonzero(events.p == 1), np.count_nonzero(events.p == 0)
    assert on == 29 or on == 30  # floor(3 / 0.1), whatever float32 makes of the last level
    assert off == 9 or off == 10  # floor(~2.9..3 / 0.3)
    assert events.p[:on].all() and not events.p[on:].any()  # all ON first, then OFF


def test_constant_frames_give_no_events():
    rng = np.random.default_rng(3)
    frame = rng.integers(0, 256, (9, 11), dtype=np.uint8)
    events = EventSimulator(cp=0.05, cn=0.05).simulate(np.stack([frame] * 5), np.arange(5) * 100)
    assert len(events) == 0 and events.sensor_size == (11, 9)


def test_signed_event_sum_tracks_log_change():
    frames = smooth_video()
    cp, cn = 0.15, 0.25
    simulator = EventSimulator(cp=cp, cn=cn)
    events = simulator.simulate(frames, 1000 * np.arange(len(frames)))
    pixel = events.y.astype(np.int64) * 20 + events.x
    signed = np.where(events.p == 1, cp, -cn)
    total = np.bincount(pixel, weights=signed, minlength=16 * 20).reshape(16, 20)
    change = log_intensity(frames[-1]).astype(np.float64) - log_intensity(frames[0])
    assert len(events) > 500
    assert (total - change < cn + 1e-5).all() and (change - total < cp + 1e-5).all()
    np.testing.assert_allclose(simulator.reference, log_intensity(frames[0]) + total, atol=1e-4)


def test_threshold_crossings_closed_form():
    ref = np.array([0.0, 0.0, 0.05, -1.0], np.float32)
    log0 = np.array([0.0, 0.0, 0.1, -1.0], np.float32)
    log1 = np.array([0.55, -0.35, 0.1, -0.95], np.float32)
    c = np.float32(0.1)
    crossings = threshold_crossings(ref, log0, log1, c, c)
    assert crossings.pixel.tolist() == [0] * 5 + [1] * 3
    assert crossings.polarity.tolist() == [1] * 5 + [0] * 3
    levels = [0.1, 0.2, 0.3, 0.4, 0.5, -0.1, -0.2, -0.3]
    np.testing.assert_allclose(crossings.level, levels, atol=1e-6)
    np.testing.assert_allclose(crossings.ref, [0.5, -0.3, 0.05, -1.0], atol=1e-6)
    with pytest.raises(ValueError, match="log1"):
        threshold_crossings(ref, log0, log1[:3], c, c)
    with pytest.raises(ValueError, match="c_on"):
        threshold_crossings(ref, log0, log1, np.float32(-0.1), c)


def naive_crossings(ref, log0, log1, c_on, c_off):
    """Per-pixel Python loop over float32 levels ``L_ref += C``: the definition, one by one."""
    pixel, level, polarity, ref_out = [], [], [], ref.copy()
    for i in range(ref.size):
        up = log1[i] > log0[i]
        c = np.float32(c_on[i] if up else -c_off[i])
        r, first = ref[i], True
        while True:
            candidate = np.float32(r + c)
            beyond_start = candidate > log0[i] if up else candidate < log0[i]
            within = candidate <= log1[i] if up else candidate >= log1[i]
            if not within or (first and not beyond_start):
                break
            pixel.append(i), level.append(candidate), polarity.append(int(up))
            r, first = candidate, False
        ref_out[i] = r
    return np.array(pixel, np.int64), np.array(level, np.float32), np.array(polarity, np.int8), ref_out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_threshold_crossings_equal_the_sequential_definition(seed):
    """Random pixels with 0 to ~60 crossings (beyond the 16 ranks done one pass each), levels
    landing exactly on the next sample, per-pixel thresholds: all equal the one-by-one loop."""
    rng = np.random.default_rng(seed)
    n = 400
    c_on = rng.uniform(0.05, 0.3, n).astype(np.float32)
    c_off = rng.uniform(0.05, 0.3, n).astype(np.float32)
    ref = rng.uniform(-6.0, 0.0, n).astype(np.float32)
    log0 = (ref + rng.uniform(-0.9, 0.9, n) * np.minimum(c_on, c_off)).astype(np.float32)
    log1 = rng.uniform(-6.9, 0.0, n).astype(np.float32)
    exact = rng.random(n) < 0.2  # land exactly on a float32 level: ref + C (+ C ...)
    for i in np.flatnonzero(exact):
        level = ref[i]
        for _ in range(rng.integers(1, 4)):
            level = np.float32(level + (c_on[i] if rng.random() < 0.5 else -c_off[i]))
        log1[i] = level
    expected = naive_crossings(ref, log0, log1, c_on, c_off)
    for thresholds in ((c_on, c_off), (np.float32(0.1), np.float32(0.07))):
        if not np.ndim(thresholds[0]):
            expected = naive_crossings(ref, log0, log1, np.full(n, thresholds[0]), np.full(n, thresholds[1]))
        got = threshold_crossings(ref, log0, log1, *thresholds)
        np.testing.assert_array_equal(got.pixel, expected[0])
        np.testing.assert_array_equal(got.level, expected[1])
        np.testing.assert_array_equal(got.polarity, expected[2])
        np.testing.assert_array_equal(got.ref, expected[3])
    assert np.bincount(expected[0]).max() > 16  # the running-sum tail was exercised


def test_fractional_grey_values_use_the_table_where_whole():
    table = log_intensity(np.arange(256, dtype=np.uint8).reshape(16, 16)).ravel()
    frame = np.array([[0.0, 0.5, 17.0, 17.25, 254.9, 255.0]], np.float32)
    log = log_intensity(frame).ravel()
    assert log[0] == table[0] and log[2] == table[17] and log[5] == table[255]
    np.testing.assert_allclose(log, np.log(frame.ravel().astype(np.float64) / 255 + 1e-3), atol=2e-6)
    assert table[0] < log[1] < table[1] and table[17] < log[3] < table[18]


# -- time stamps and order ------------------------------------------------------------------
def test_events_sorted_by_time_then_pixel():
    frames = smooth_video(n_frames=6)
    events = EventSimulator(cp=0.1, cn=0.1).simulate(frames, 50 * np.arange(6))
    pixel = events.y.astype(np.int64) * 20 + events.x
    same_time = (events.t[1:] == events.t[:-1]) & (events.t[1:] % 50 != 0)  # inside an interval
    assert (np.diff(events.t) >= 0).all()
    assert (pixel[1:][same_time] >= pixel[:-1][same_time]).all()
    assert events.t.min() >= 0 and events.t.max() <= 250


def test_step_equals_simulate_and_first_step_is_empty():
    frames = smooth_video(n_frames=10)
    times = 700 * np.arange(10, dtype=np.int64) + 12_345
    options = dict(cp=0.12, cn=0.18, threshold_sigma=0.1, refractory_us=150, seed=7,
                   shot_noise_rate_hz=50.0, leak_rate_hz=5.0)
    whole = EventSimulator(**options).simulate(frames, times)
    streaming = EventSimulator(**options)
    first = streaming.step(frames[0], times[0])
    assert len(first) == 0 and streaming.initialized and streaming.t_us == times[0]
    parts = [streaming.step(frame, t) for frame, t in zip(frames[1:], times[1:])]
    assert concatenate([first, *parts]) == whole
    streaming.reset()
    assert not streaming.initialized and streaming.simulate(frames, times) == whole


def test_colour_float_and_uint8_frames_agree():
    rng = np.random.default_rng(5)
    bgr = rng.integers(0, 256, (4, 6, 8, 3), dtype=np.uint8)
    grey = np.stack([cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) for frame in bgr])
    times = np.array([0, 10, 20, 30])
    reference = EventSimulator().simulate(grey, times)
    assert len(reference) > 0
    assert EventSimulator().simulate(bgr, times) == reference
    assert EventSimulator().simulate(grey.astype(np.float64), times) == reference
    assert EventSimulator().simulate(grey.astype(np.int32), times) == reference


def test_log_intensity_values():
    values = np.arange(256, dtype=np.float32)
    ours = log_intensity(values.reshape(16, 16)).ravel()
    assert ours.dtype == np.float32
    np.testing.assert_allclose(ours, np.log(values / 255.0 + 1e-3), rtol=0, atol=5e-7)
    from_uint8 = log_intensity(values.reshape(16, 16).astype(np.uint8)).ravel()
    np.testing.assert_array_equal(from_uint8, ours)
    x = np.random.default_rng(0).uniform(1e-3, 40.0, 10_000).astype(np.float32)
    np.testing.assert_allclose(_cv_log32f(x), np.log(x.astype(np.float64)), rtol=0, atol=2e-6)


def test_fma32_rounds_once():
    a = np.array([1 + 2**-12, 1 + 2**-12], np.float32)
    result = _fma32(a, a, np.array([2**-80, -2**-80], np.float32))  # exact: half-way +- 2**-80
    assert (result.astype(np.float64) - 1 - 2**-11).tolist() == [2**-23, 0.0]


# -- refractory period, mismatch and noise --------------------------------------------------
def test_refractory_period_drops_events_but_moves_the_reference():
    log = np.linspace(-5.0, 0.0, 6)  # 5 log units in 5 frames: 5 events per pixel per frame
    frames = np.repeat(grey_for_log(log)[:, None, None], 2, axis=2)
    times = 1000 * np.arange(6)
    free = EventSimulator(cp=0.2, cn=0.2)
    blind = EventSimulator(cp=0.2, cn=0.2, refractory_us=500)
    all_events, kept = free.simulate(frames, times), blind.simulate(frames, times)
    assert len(all_events) == 2 * 25 and 0 < len(kept) < len(all_events)
    for x in (0, 1):
        t = kept.t[kept.x == x]
        assert (np.diff(t) >= 500).all()
    np.testing.assert_array_equal(free.reference, blind.reference)


def test_threshold_mismatch_map_is_seeded_and_clipped():
    frames = smooth_video(n_frames=8)
    times = 1000 * np.arange(8)
    a = EventSimulator(threshold_sigma=0.3, seed=1)
    events_a = a.simulate(frames, times)
    assert EventSimulator(threshold_sigma=0.3, seed=1).simulate(frames, times) == events_a
    assert EventSimulator(threshold_sigma=0.3, seed=2).simulate(frames, times) != events_a
    assert EventSimulator().simulate(frames, times) != events_a
    strong = EventSimulator(threshold_sigma=5.0, seed=1)
    strong.simulate(frames[:2], times[:2])
    assert strong._c_on.min() == np.float32(MIN_THRESHOLD_FRACTION * 0.2)


def test_shot_noise_is_seeded_with_the_expected_rate():
    frames = np.full((11, 30, 40), 100, np.uint8)
    times = 100_000 * np.arange(11)  # 1 s
    noisy = EventSimulator(seed=3, shot_noise_rate_hz=2.0).simulate(frames, times)
    expected = 2.0 * 1200 * 1.0
    assert abs(len(noisy) - expected) < 5 * math.sqrt(expected)
    assert 0.4 < noisy.p.mean() < 0.6
    assert EventSimulator(seed=3, shot_noise_rate_hz=2.0).simulate(frames, times) == noisy
    assert EventSimulator(seed=4, shot_noise_rate_hz=2.0).simulate(frames, times) != noisy


def test_leak_events_are_on_at_the_leak_rate():
    frames = np.full((11, 30, 40), 100, np.uint8)
    times = 100_000 * np.arange(11)  # 1 s
    leaky = EventSimulator(seed=0, leak_rate_hz=3.0).simulate(frames, times)
    assert (leaky.p == 1).all()
    per_pixel = np.bincount(leaky.y.astype(np.int64) * 40 + leaky.x, minlength=1200)
    assert set(np.unique(per_pixel)) <= {2, 3}  # 3 Hz for 1 s with a random phase
    assert abs(len(leaky) - 3 * 1200) < 0.05 * 3 * 1200


# -- settings and bad input -----------------------------------------------------------------
def test_settings_validation():
    assert EventSimulator(cp=0.3).settings == EsimSettings(cp=0.3)
    assert EventSimulator.from_settings(EsimSettings(cn=0.4)).settings.cn == 0.4
    for name, value in [("cp", 0.0), ("cn", -0.1), ("cp", float("nan")), ("threshold_sigma", -1.0),
                        ("refractory_us", -5), ("log_eps", 0.0), ("shot_noise_rate_hz", -1.0),
                        ("leak_rate_hz", float("inf")), ("seed", -1)]:
        with pytest.raises(ValueError, match=name):
            EventSimulator(**{name: value})
    with pytest.raises(TypeError, match="seed"):
        EventSimulator(seed=1.5)


def test_bad_frames_and_times_raise():
    frames = np.full((3, 4, 5), 100.0)
    times = np.array([0, 10, 20])
    simulator = EventSimulator()
    bad_nan = frames.copy()
    bad_nan[1, 2, 3] = np.nan
    with pytest.raises(ValueError, match=r"frames\[1\]"):
        simulator.simulate(bad_nan, times)
    with pytest.raises(ValueError, match=r"frames\[2\].*\[0, 255\]"):
        simulator.simulate(frames * np.array([1, 1, 2.6])[:, None, None], times)
    with pytest.raises(ValueError, match=r"frames\[0\]"):
        simulator.simulate(frames - 101, times)
    with pytest.raises(ValueError, match="timestamps_us.*increasing"):
        simulator.simulate(frames, np.array([0, 10, 10]))
    with pytest.raises(ValueError, match="timestamps_us"):
        simulator.simulate(frames, np.array([0, 10]))
    with pytest.raises(ValueError, match="timestamps_us"):
        simulator.simulate(frames, np.array([0.0, 10.5, 20.0]))
    with pytest.raises(ValueError, match="frames"):
        simulator.simulate(frames[0], times)
    simulator.step(frames[0], 0)
    with pytest.raises(ValueError, match="frame"):
        simulator.step(np.zeros((4, 6)), 10)
    with pytest.raises(ValueError, match="t_us"):
        simulator.step(frames[1], 0)
    with pytest.raises(ValueError, match="frame"):
        simulator.step(np.zeros((4, 5, 2)), 10)
    with pytest.raises(TypeError, match="frame"):
        simulator.step(np.zeros((4, 5), bool), 10)


def test_single_frame_gives_no_events():
    events = EventSimulator().simulate(np.zeros((1, 3, 4), np.uint8), np.array([5]))
    assert len(events) == 0 and events.sensor_size == (4, 3)


def test_reversing_the_video_flips_polarities():
    rng = np.random.default_rng(3)
    start = rng.uniform(-5.0, -0.5, (6, 7))
    change = rng.uniform(-6.0, -0.1, (6, 7)) - start  # a monotonic ramp per pixel, either way
    log = start + change * np.linspace(0.0, 1.0, 9)[:, None, None]
    frames, times = grey_for_log(log), 1000 * np.arange(9)
    forward = EventSimulator(cp=0.2, cn=0.2).simulate(frames, times)
    backward = EventSimulator(cp=0.2, cn=0.2).simulate(frames[::-1], times)
    assert len(forward) > 100
    for events, sign in ((forward, 1), (backward, -1)):
        pixel = events.y.astype(np.int64) * 7 + events.x
        signed = np.bincount(pixel, 2 * events.p.astype(np.int64) - 1, minlength=42)
        counts = np.bincount(pixel, minlength=42)
        np.testing.assert_array_equal(np.abs(signed), counts)  # one polarity per pixel
        np.testing.assert_array_equal(np.sign(signed) * sign, np.sign(change.ravel()) * (counts > 0))
    np.testing.assert_array_equal(np.bincount(forward.y.astype(int) * 7 + forward.x, minlength=42),
                                  np.bincount(backward.y.astype(int) * 7 + backward.x, minlength=42))


@pytest.mark.parametrize("refractory_us", [0, 10])  # the compiled kernel, and the numpy path
def test_an_interval_with_more_crossings_than_memory_holds_is_refused_before_allocating(monkeypatch, refractory_us):
    """A 640x480 frame flashing from black to white at cp = cn = 0.001 crosses 6,908 levels a pixel, 2.1e9
    events: was an allocation of 36 GB (MemoryError under a limit, else the OOM killer), and intervals of more
    than MAX_EVENTS events became an Events past the limit the rest of the package refuses."""
    import cmax.events
    from cmax.events import EventLimitError

    black, white = np.zeros((48, 64), np.uint8), np.full((48, 64), 255, np.uint8)
    per_pixel = math.floor((math.log(1 + 1e-3) - math.log(1e-3)) / 0.01)  # closed form: levels crossed
    assert per_pixel == 690
    monkeypatch.setattr(cmax.events, "MAX_EVENTS", 64 * 48 * per_pixel)  # the events fit, the bound does not
    sim = EventSimulator(cp=0.01, cn=0.01, refractory_us=refractory_us)
    sim.step(black, 0)
    before = sim.reference
    with pytest.raises(EventLimitError, match=r"the frame at 1000 µs changes so much since the one at 0 µs that "
                       r"its interval may hold up to 2,125,824 events over the 64x48 sensor, more than "
                       r"cmax.events.MAX_EVENTS=2,119,680 .*\(adaptive sampling"):
        sim.step(white, 1000)
    np.testing.assert_array_equal(sim.reference, before)  # nothing moved: the simulator goes on
    assert sim.t_us == 0
    monkeypatch.setattr(cmax.events, "MAX_EVENTS", 64 * 48 * (per_pixel + 2))
    events = sim.step(white, 1000)
    fresh = EventSimulator(cp=0.01, cn=0.01, refractory_us=refractory_us).simulate(
        np.stack([black, white]), np.array([0, 1000]))
    assert all(np.array_equal(getattr(events, k), getattr(fresh, k)) for k in "xytp")
    assert len(events) == 64 * 48 * per_pixel or refractory_us  # the refractory period drops some


def test_shot_noise_over_a_long_interval_is_refused_before_it_is_drawn(monkeypatch):
    """Frames 10^4 s apart (times in ms read as seconds) with 1 Hz of shot noise on a 640x480 sensor: was a
    draw of 3e9 noise events (24 GB of pixel indices alone)."""
    import cmax.events
    from cmax.events import EventLimitError

    monkeypatch.setattr(cmax.events, "MAX_EVENTS", 10_000)
    frame = np.full((30, 40), 100, np.uint8)
    sim = EventSimulator(shot_noise_rate_hz=10.0, seed=0)
    sim.step(frame, 0)
    with pytest.raises(EventLimitError, match=r"is 100 s long: shot noise of 10 Hz per pixel over the 40x30 sensor "
                       r"add about 1,200,000 events to it, more than cmax.events.MAX_EVENTS=10,000 .*check the "
                       r"frame times"):
        sim.step(frame, 100_000_000)
    events = sim.step(frame, 500_000)  # the generator was not drawn from: as a fresh simulator's
    fresh = EventSimulator(shot_noise_rate_hz=10.0, seed=0).simulate(np.stack([frame, frame]),
                                                                       np.array([0, 500_000]))
    assert len(events) == len(fresh) > 0
    assert all(np.array_equal(getattr(events, k), getattr(fresh, k)) for k in "xytp")


def test_leak_events_over_a_long_interval_are_refused_naming_the_leak(monkeypatch):
    """A still video with a leak rate too high for its frame interval: the refusal named the frames
    ('changes so much since ...: insert frames') though nothing in them changed."""
    import cmax.events
    from cmax.events import EventLimitError

    monkeypatch.setattr(cmax.events, "MAX_EVENTS", 10_000)
    frame = np.full((30, 40), 100, np.uint8)
    for kwargs in ({}, {"refractory_us": 5}):
        sim = EventSimulator(leak_rate_hz=1000.0, seed=0, **kwargs)
        sim.step(frame, 0)
        with pytest.raises(EventLimitError, match=r"is 0.1 s long: leak events of 1000 Hz per pixel over the 40x30 "
                           r"sensor add about 120,000 events to it, more than cmax.events.MAX_EVENTS=10,000"):
            sim.step(frame, 100_000)
