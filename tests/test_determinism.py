"""Determinism on the CPU: the same inputs and seeds give identical outputs, bit for bit.

Covered: the event simulator with every noise source on (threshold mismatch,
refractory period, shot noise, leak), synthetic scenes (world, textures,
trajectory and their events), ``cmax.fit`` (twice on one window, and the seeded
subsampling of ``FitSettings.seed``), the representations, and the bytes of the
files this library writes (DSEC h5, EVT 2.0/3.0, ECD text): HDF5 files carry no
creation times here, so equal events give byte-identical files.

Each determinism test also shows that it could fail: changing the seed changes
the output (so the seed is really used, and equality is not vacuous).
"""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

import cmax
from cmax import Events
from cmax.io import read_h5, write_evt2, write_evt3, write_h5, write_txt
from cmax.representations import event_frame, time_surface, voxel_grid, voxel_grid_batch
from cmax.sim import EventSimulator, make_scene, simulate_scene
from conftest import random_events

NOISY = dict(cp=0.15, cn=0.25, threshold_sigma=0.03, refractory_us=200,
             shot_noise_rate_hz=2.0, leak_rate_hz=0.5)


def _frames(count: int = 40, size: tuple[int, int] = (48, 64)) -> tuple[np.ndarray, np.ndarray]:
    """A bright bar sweeping across a textured background: grey uint8 (T, H, W), times (T,) µs."""
    rng = np.random.default_rng(11)
    background = rng.integers(40, 120, size).astype(np.float64)
    frames = np.empty((count,) + size, np.uint8)
    columns = np.arange(size[1])
    for k in range(count):
        bar = np.exp(-0.5 * ((columns - 1.5 * k) / 3.0) ** 2) * 120
        frames[k] = np.clip(background + bar[None, :], 0, 255).astype(np.uint8)
    return frames, np.arange(count, dtype=np.int64) * 2_000


def _same_events(a: Events, b: Events) -> bool:
    return a.sensor_size == b.sensor_size and all(np.array_equal(getattr(a, n), getattr(b, n)) for n in "xytp")


# -- the simulator ---------------------------------------------------------------------------
def test_simulator_with_noise_repeats_with_its_seed():
    frames, times = _frames()
    first = EventSimulator(seed=5, **NOISY).simulate(frames, times)
    second = EventSimulator(seed=5, **NOISY).simulate(frames, times)
    assert len(first) > 100
    assert _same_events(first, second)
    # reset() restarts the same random streams.
    simulator = EventSimulator(seed=5, **NOISY)
    simulator.simulate(frames, times)
    simulator.reset()
    assert _same_events(simulator.simulate(frames, times), first)
    # The seed is used: another seed gives other noise and mismatch.
    assert not _same_events(EventSimulator(seed=6, **NOISY).simulate(frames, times), first)


def test_simulator_step_by_step_equals_whole_run():
    frames, times = _frames()
    whole = EventSimulator(seed=2, **NOISY).simulate(frames, times)
    simulator = EventSimulator(seed=2, **NOISY)
    parts = [simulator.step(frame, int(t)) for frame, t in zip(frames, times)]
    assert _same_events(cmax.concatenate(parts), whole)


def test_unseeded_noise_differs_between_simulators():
    """seed=None draws fresh entropy (documented): two runs differ, so a seed is needed to repeat."""
    frames, times = _frames()
    first = EventSimulator(seed=None, **NOISY).simulate(frames, times)
    second = EventSimulator(seed=None, **NOISY).simulate(frames, times)
    assert not _same_events(first, second)


# -- synthetic scenes ------------------------------------------------------------------------
def _sequence(seed: int, simulator_seed: int):
    scene = make_scene("slider", seed=seed, width=64, height=48, duration_s=1.0, texture_size=256)
    simulator = EventSimulator(seed=simulator_seed, threshold_sigma=0.02, shot_noise_rate_hz=1.0)
    return simulate_scene(scene, 0.06, simulator, depth_rate_hz=50.0)


@pytest.fixture(scope="module")
def sequence():
    return _sequence(seed=1, simulator_seed=3)


def test_synthetic_scene_repeats_with_its_seeds(sequence):
    again = _sequence(seed=1, simulator_seed=3)
    assert len(sequence.events) > 50
    assert _same_events(sequence.events, again.events)
    for name in ("depth", "depth_t_us", "poses", "poses_t_us", "twists", "K", "frame_t_us"):
        assert np.array_equal(getattr(sequence, name), getattr(again, name), equal_nan=True), name
    other_world = _sequence(seed=2, simulator_seed=3)
    assert not np.array_equal(other_world.depth, sequence.depth, equal_nan=True)
    other_noise = _sequence(seed=1, simulator_seed=4)
    assert np.array_equal(other_noise.depth, sequence.depth, equal_nan=True)  # same world ...
    assert not _same_events(other_noise.events, sequence.events)              # ... other noise


# -- fitting ---------------------------------------------------------------------------------
_FIELDS = ("flow", "v", "omega", "T", "depth", "mask", "inverse_depth_grid", "objective_before",
           "objective_after", "iterations", "evaluations", "iwe_before", "iwe_after", "events_used",
           "t0_us", "t1_us", "t_ref_us", "message", "success", "scale_known")


def _assert_same_fit(a, b) -> None:
    for name in _FIELDS:
        left, right = getattr(a, name), getattr(b, name)
        if isinstance(left, np.ndarray) or isinstance(right, np.ndarray):
            assert np.array_equal(left, right, equal_nan=True), name
        else:
            assert left == right, name


@pytest.mark.parametrize("model", ["flow", "rotation"])
def test_fit_repeats_on_the_same_window(sequence, model):
    first = cmax.fit(sequence.events, sequence.K, model)
    second = cmax.fit(sequence.events, sequence.K, model)
    assert first.events_used == len(sequence.events)
    _assert_same_fit(first, second)


def test_fit_subsampling_follows_settings_seed(sequence):
    keep = len(sequence.events) // 2
    settings = cmax.FitSettings(max_events=keep, seed=7)
    first = cmax.fit(sequence.events, sequence.K, "flow", settings=settings)
    second = cmax.fit(sequence.events, sequence.K, "flow", settings=settings)
    assert first.events_used == keep
    _assert_same_fit(first, second)
    other = cmax.fit(sequence.events, sequence.K, "flow", settings=cmax.FitSettings(max_events=keep, seed=8))
    assert not np.array_equal(other.iwe_before, first.iwe_before)


@pytest.mark.slow
def test_se3_fit_repeats_on_the_same_window(sequence):
    options = dict(iterations=5, depth_candidates=8, depth_grid=(3, 4), speed=1.0)
    _assert_same_fit(cmax.fit(sequence.events, sequence.K, "se3", **options),
                     cmax.fit(sequence.events, sequence.K, "se3", **options))


# -- representations -------------------------------------------------------------------------
def test_representations_repeat_bit_for_bit():
    events = random_events(20_000, width=64, height=48, seed=9)
    for make in (lambda e: voxel_grid(e, bins=5), event_frame, time_surface):
        assert np.array_equal(make(events), make(events))
        tensors = events.to_torch()
        assert np.array_equal(make(tensors).numpy(), make(tensors).numpy())
    batch = [events[:5000].to_torch(), events[5000:].to_torch()]
    assert np.array_equal(voxel_grid_batch(batch).numpy(), voxel_grid_batch(batch).numpy())


# -- files -----------------------------------------------------------------------------------
def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.parametrize("compression", ["blosc", "gzip", "none"])
def test_h5_files_of_equal_events_are_byte_identical(tmp_path, compression):
    events = random_events(30_000, width=640, height=480, seed=4, t_span_us=3_000_000)
    first = write_h5(tmp_path / "first.h5", events, compression=compression, source="determinism")
    second = write_h5(tmp_path / "second.h5", events, compression=compression, source="determinism")
    assert _sha(first) == _sha(second)
    assert read_h5(first) == events
    changed = Events(events.x, events.y, events.t, 1 - events.p, 640, 480)
    assert _sha(write_h5(tmp_path / "third.h5", changed, compression=compression, source="determinism")) != _sha(first)


def test_simulated_scene_files_are_byte_identical(tmp_path, sequence):
    again = _sequence(seed=1, simulator_seed=3)
    assert _sha(sequence.save(tmp_path / "a.h5")) == _sha(again.save(tmp_path / "b.h5"))


@pytest.mark.parametrize("write", [write_evt3, write_evt2, write_txt], ids=["evt3", "evt2", "txt"])
def test_other_writers_are_byte_identical(tmp_path, write):
    events = random_events(5_000, width=640, height=480, seed=6)
    write(tmp_path / "a.out", events)
    write(tmp_path / "b.out", events)
    assert _sha(tmp_path / "a.out") == _sha(tmp_path / "b.out")
