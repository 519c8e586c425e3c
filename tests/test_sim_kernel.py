"""The compiled ESIM interval kernels equal the sequential definition and the numpy path."""
from __future__ import annotations

import numpy as np
import pytest

from cmax.sim.crossings import _interval_crossings, _sorted_by_time, crossing_times
from cmax.sim.esim import EventSimulator

from test_sim_esim import naive_crossings


def _random_interval(seed: int, n: int = 400):
    rng = np.random.default_rng(seed)
    c_on = rng.uniform(0.05, 0.3, n).astype(np.float32)
    c_off = rng.uniform(0.05, 0.3, n).astype(np.float32)
    ref = rng.uniform(-6.0, 0.0, n).astype(np.float32)
    log0 = (ref + rng.uniform(-0.9, 0.9, n) * np.minimum(c_on, c_off)).astype(np.float32)
    log1 = rng.uniform(-6.9, 0.0, n).astype(np.float32)
    for i in np.flatnonzero(rng.random(n) < 0.2):  # land exactly on a float32 level
        level = ref[i]
        for _ in range(rng.integers(1, 4)):
            level = np.float32(level + (c_on[i] if rng.random() < 0.5 else -c_off[i]))
        log1[i] = level
    return ref, log0, log1, c_on, c_off


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("per_pixel", [True, False])
def test_kernel_crossings_equal_the_sequential_definition(seed, per_pixel):
    ref, log0, log1, c_on, c_off = _random_interval(seed)
    if not per_pixel:
        c_on, c_off = np.full_like(c_on, 0.1), np.full_like(c_off, 0.07)
    pixel, level, polarity, ref_after = naive_crossings(ref, log0, log1, c_on, c_off)
    dt = 1866
    thresholds = (c_on, c_off) if per_pixel else (c_on[:1], c_off[:1])
    near = tuple(np.float32(0.9) * c * s for c, s in zip(thresholds, (1, -1)))
    moved = ref.copy()
    got_pixel, got_t, got_p, held, _ = _interval_crossings(moved, log0, log1, *thresholds, *near, dt, 2**62)
    assert held
    np.testing.assert_array_equal(got_pixel, pixel)
    np.testing.assert_array_equal(got_p, polarity)
    np.testing.assert_array_equal(got_t, crossing_times(pixel, level, log0, log1, dt))
    np.testing.assert_array_equal(moved, ref_after)
    assert np.bincount(pixel).max() > 16 or not per_pixel


@pytest.mark.parametrize("dt", [50, 10**7])  # counting sort, and merge sort for long intervals
def test_sorted_by_time_is_a_stable_sort_into_place(dt):
    rng = np.random.default_rng(3)
    m, width = 3000, 37
    pixel = np.sort(rng.integers(0, width * 11, m))
    t_rel = rng.integers(0, min(dt, 60) + 1, m)
    polarity = rng.integers(0, 2, m).astype(np.int8)
    out = (np.zeros(m + 5, np.uint16), np.zeros(m + 5, np.uint16), np.zeros(m + 5, np.int64),
           np.zeros(m + 5, np.int8))
    _sorted_by_time(pixel, t_rel, polarity, dt, width, 1000, *out, 5)
    order = np.argsort(t_rel, kind="stable")
    np.testing.assert_array_equal(out[0][5:], pixel[order] % width)
    np.testing.assert_array_equal(out[1][5:], pixel[order] // width)
    np.testing.assert_array_equal(out[2][5:], 1000 + t_rel[order])
    np.testing.assert_array_equal(out[3][5:], polarity[order])
    assert not out[2][:5].any()  # nothing written before the offset


def test_compiled_and_numpy_paths_give_the_same_events():
    """A 1 µs refractory period sends step() down the numpy path; it drops only a pixel's second
    event within one µs, and there is none here (checked), so both must give the same events."""
    rng = np.random.default_rng(5)
    frames = np.clip(rng.normal(128, 60, (8, 24, 30)).cumsum(0) / 3 + 60, 0, 255).astype(np.uint8)
    times = 1000 * np.arange(8)
    compiled = EventSimulator(cp=0.05, cn=0.07).simulate(frames, times)
    numpy_path = EventSimulator(cp=0.05, cn=0.07, refractory_us=1).simulate(frames, times)
    assert len(compiled) > 1000
    pixel_time = compiled.t * (24 * 30) + compiled.y.astype(np.int64) * 30 + compiled.x
    assert np.unique(pixel_time).size == len(compiled)
    assert compiled == numpy_path
