"""Tests for cmax.representations: voxel grid, event frame, time surface."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cmax import Events, EventTensors
from cmax.representations import (
    EventFrame,
    TimeSurface,
    VoxelGrid,
    event_frame,
    time_surface,
    voxel_grid,
    voxel_grid_batch,
)
from cmax.representations.voxel import _voxel_grid_numpy
from conftest import random_events


def _np(value) -> np.ndarray:
    return value.cpu().numpy() if isinstance(value, torch.Tensor) else value


def _hand_events() -> Events:
    # width 3, height 2; times 0..100 µs so that with B = 3, t* = t / 50
    return Events(
        x=[0, 1, 1, 0, 2], y=[0, 0, 0, 1, 1], t=[0, 25, 50, 75, 100], p=[1, 0, 1, 0, 1],
        width=3, height=2,
    )


def _slow_voxel_grid(x, y, t, p, width, height, bins, t0=None, t1=None, scale=None) -> np.ndarray:
    """The paper's formula, event by event: E(x,y,b) = sum p_i max(0, 1 - |b - t*_i|).

    ``scale`` replaces the paper's (B - 1) in t* (tonic uses B).
    """
    t0 = int(t.min()) if t0 is None else t0
    t1 = int(t.max()) if t1 is None else t1
    scale = bins - 1 if scale is None else scale
    grid = np.zeros((bins, height, width))
    for xi, yi, ti, pi in zip(x.tolist(), y.tolist(), t.tolist(), p.tolist()):
        t_star = scale * (ti - t0) / (t1 - t0) if t1 > t0 else 0.0
        sign = 1.0 if pi > 0 else -1.0
        for b in range(bins):
            grid[b, yi, xi] += sign * max(0.0, 1.0 - abs(b - t_star))
    return grid


# -- voxel grid ------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_voxel_grid_by_hand(backend):
    ev = _hand_events()
    # t* = 0, 0.5, 1, 1.5, 2 for events (0,0,+), (1,0,-), (1,0,+), (0,1,-), (2,1,+)
    expected = np.zeros((3, 2, 3), np.float32)
    expected[0, 0, 0] = 1.0            # t* = 0: all in bin 0
    expected[0, 0, 1] = -0.5           # t* = 0.5, OFF: half in bin 0 ...
    expected[1, 0, 1] = -0.5 + 1.0     # ... half in bin 1, plus the ON event at t* = 1
    expected[1, 1, 0] = -0.5           # t* = 1.5, OFF: half in bin 1 ...
    expected[2, 1, 0] = -0.5           # ... half in bin 2
    expected[2, 1, 2] = 1.0            # t* = 2: all in the last bin
    out = voxel_grid(ev if backend == "numpy" else ev.to_torch(), bins=3)
    assert out.shape == (3, 2, 3) and out.dtype in (np.float32, torch.float32)
    np.testing.assert_array_equal(_np(out), expected)


def test_voxel_grid_window_bounds_by_hand():
    ev = _hand_events()
    # window [0, 200] µs with B = 3: t* = t / 100 = 0, 0.25, 0.5, 0.75, 1
    out = voxel_grid(ev, bins=3, t0_us=0, t1_us=200)
    expected = np.zeros((3, 2, 3), np.float32)
    expected[0, 0, 0] = 1.0
    expected[0, 0, 1], expected[1, 0, 1] = -0.75 + 0.5, -0.25 + 0.5
    expected[0, 1, 0], expected[1, 1, 0] = -0.25, -0.75
    expected[1, 1, 2] = 1.0
    np.testing.assert_allclose(out, expected, atol=1e-7)
    on_torch = voxel_grid(ev.to_torch(), bins=3, t0_us=0, t1_us=200)
    np.testing.assert_allclose(_np(on_torch), expected, atol=1e-7)


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_voxel_grid_degenerate_windows(backend):
    def run(ev, **kw):
        return _np(voxel_grid(ev if backend == "numpy" else ev.to_torch(), **kw))

    single = Events([2], [1], [12345], [0], width=4, height=3)
    out = run(single, bins=5)
    assert out[0, 1, 2] == -1.0 and np.count_nonzero(out) == 1  # one event: bin 0
    same_time = Events([0, 1, 1], [0, 0, 0], [7, 7, 7], [1, 1, 0], width=2, height=1)
    np.testing.assert_array_equal(run(same_time, bins=4)[:, 0], [[1, 0], [0, 0], [0, 0], [0, 0]])
    np.testing.assert_array_equal(run(same_time, bins=2, t0_us=7, t1_us=7)[0, 0], [1, 0])
    ev = random_events(300)
    np.testing.assert_allclose(  # bins = 1 is the signed event frame
        run(ev, bins=1)[0], _np(event_frame(ev, signed=True)), atol=1e-6
    )
    empty = Events.empty(5, 4)
    assert run(empty, bins=3).shape == (3, 4, 5) and not run(empty, bins=3).any()


@pytest.mark.parametrize("bins", [1, 2, 3, 5, 9])
def test_voxel_grid_conserves_signed_polarity(bins):
    ev = random_events(5000, seed=bins)
    signed = np.zeros((ev.height, ev.width))
    np.add.at(signed, (ev.y, ev.x), ev.signed_polarity(np.float64))  # a slow, obvious reference
    span = int(ev.t[-1] - ev.t[0])
    for out in (
        voxel_grid(ev, bins=bins),
        voxel_grid(ev.to_torch(), bins=bins),
        *(_voxel_grid_numpy(ev, bins, int(ev.t[0]), span, method=method)
          for method in ("weights", "signed", "split")),
    ):
        out = _np(out)
        np.testing.assert_allclose(out.sum(axis=0), signed, atol=1e-4)
        assert out.sum() == pytest.approx(ev.signed_polarity(np.float64).sum(), abs=1e-2)


@pytest.mark.parametrize("bins", [1, 2, 5, 7])
@pytest.mark.parametrize("window", [None, (-1000, 150_000)])
def test_voxel_grid_matches_slow_formula(bins, window):
    ev = random_events(200, width=9, height=7, seed=3)
    ev = Events(ev.x, ev.y, ev.t + 1_700_000_000_000_000, ev.p, 9, 7)  # absolute epoch times
    t0, t1 = (None, None) if window is None else (ev.t[0] + window[0], ev.t[0] + window[1])
    expected = _slow_voxel_grid(ev.x, ev.y, ev.t, ev.p, 9, 7, bins, t0, t1)
    kw = {} if window is None else {"t0_us": int(t0), "t1_us": int(t1)}
    np.testing.assert_allclose(voxel_grid(ev, bins, **kw), expected, atol=1e-5)
    np.testing.assert_allclose(_np(voxel_grid(ev.to_torch(), bins, **kw)), expected, atol=1e-5)
    t0, t1 = (int(ev.t[0]), int(ev.t[-1])) if window is None else (int(t0), int(t1))
    for method in ("weights", "signed", "split"):  # all numpy methods, whichever the size picks
        out = _voxel_grid_numpy(ev, bins, t0, t1 - t0, method=method)
        np.testing.assert_allclose(out, expected, atol=1e-5, err_msg=method)


@pytest.mark.parametrize("signed_polarity", [False, True])
def test_voxel_grid_numpy_and_torch_agree(signed_polarity):
    ev = random_events(20_000, width=40, height=30, seed=7)
    tensors = ev.to_torch(signed_polarity=signed_polarity)
    np.testing.assert_allclose(_np(voxel_grid(tensors, 5)), voxel_grid(ev, 5), atol=1e-4)
    # torch inputs need not be sorted
    order = torch.randperm(len(ev), generator=torch.Generator().manual_seed(0))
    shuffled = EventTensors(*(column[order] for column in tensors[:4]), ev.width, ev.height)
    np.testing.assert_allclose(_np(voxel_grid(shuffled, 5)), voxel_grid(ev, 5), atol=1e-4)


def test_voxel_grid_batch_equals_stacked_singles():
    parts = [random_events(n, seed=n) for n in (500, 1, 0, 3000)]
    parts.append(Events([1, 2], [3, 3], [50, 50], [1, 0], 64, 48))  # zero time span
    batch = voxel_grid_batch([part.to_torch() for part in parts], bins=4)
    assert batch.shape == (5, 4, 48, 64) and batch.dtype == torch.float32
    for i, part in enumerate(parts):
        np.testing.assert_allclose(batch[i].numpy(), voxel_grid(part, 4), atol=1e-5)
    one_bin = voxel_grid_batch([part.to_torch() for part in parts], bins=1)
    np.testing.assert_allclose(one_bin[3].numpy(), voxel_grid(parts[3], 1), atol=1e-5)


def test_voxel_grid_agrees_with_tonic_after_its_normalisation():
    functional = pytest.importorskip("tonic.functional")
    ev = random_events(3000, width=20, height=10, seed=11)
    bins = 5
    # tonic rewrites the polarity of the array it is given (0 -> -1) in place: give it a copy
    theirs = functional.to_voxel_grid_numpy(ev.to_structured(), (20, 10, 2), bins)
    theirs = theirs.reshape(bins, 10, 20)
    # tonic: t* = B (t - t0) / (tN - t0) with bins 0..B-1 kept (the last event's weight is
    # dropped), where the paper uses B - 1. Same formula with scale B, truncated:
    expected = _slow_voxel_grid(ev.x, ev.y, ev.t, ev.p, 20, 10, bins, scale=bins)
    np.testing.assert_allclose(theirs, expected, atol=1e-9)
    # ... which is ours with B + 1 bins (so that B+1 - 1 = B) without the last bin
    np.testing.assert_allclose(voxel_grid(ev, bins + 1)[:bins], theirs, atol=1e-5)
    assert not np.allclose(voxel_grid(ev, bins), theirs, atol=1e-3)  # the normalisations differ


def test_frames_and_time_surfaces_agree_with_tonic_as_docs_formats_maps_them():
    """The table "Event tensors, for tonic users" of docs/formats.md, row by row, against tonic itself."""
    functional = pytest.importorskip("tonic.functional")
    ev = random_events(3000, width=20, height=10, seed=12)
    sensor, t0, dt = (20, 10, 2), ev.t_start, (ev.t_end - ev.t_start) // 3 + 1
    theirs = functional.to_frame_numpy(ev.to_structured(), sensor, event_count=len(ev))
    assert theirs.shape == (1, 2, 10, 20)
    np.testing.assert_array_equal(event_frame(ev), theirs[0])
    theirs = functional.to_frame_numpy(ev.to_structured(), sensor, time_window=dt, include_incomplete=True)
    ours = np.stack([event_frame(w) for w in ev.windows(duration_us=dt)])
    np.testing.assert_array_equal(ours, theirs)
    theirs = functional.to_timesurface_numpy(ev.to_structured(), sensor, dt=dt, tau=2000.0)
    for k, surface in enumerate(theirs):
        end = t0 + (k + 1) * dt
        np.testing.assert_allclose(time_surface(ev.slice_time(t0, end), tau_us=2000.0, t_ref_us=end), surface,
                                   atol=1e-6)


# -- event frame -----------------------------------------------------------------------------
@pytest.mark.parametrize("signed_polarity", [False, True])
def test_event_frame_counts(signed_polarity):
    ev = random_events(4000, seed=5)
    n_on = int(ev.p.sum())
    for out in (event_frame(ev), event_frame(ev.to_torch(signed_polarity=signed_polarity))):
        out = _np(out)
        assert out.shape == (2, ev.height, ev.width) and out.dtype == np.float32
        assert out[1].sum() == n_on and out[0].sum() == len(ev) - n_on
        assert out[1, ev.y[0], ev.x[0]] >= 1
    expected = np.zeros((2, ev.height, ev.width))
    np.add.at(expected, (ev.p, ev.y, ev.x), 1)
    np.testing.assert_array_equal(event_frame(ev), expected)
    for out in (event_frame(ev, signed=True), event_frame(ev.to_torch(), signed=True)):
        assert out.shape == (ev.height, ev.width)
        np.testing.assert_array_equal(_np(out), expected[1] - expected[0])


# -- time surface ----------------------------------------------------------------------------
@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_time_surface_closed_form(backend):
    # two ON events at pixel (x=1, y=0), one OFF event at (x=0, y=1)
    ev = Events([1, 0, 1], [0, 1, 0], [100, 250, 400], [1, 0, 1], width=2, height=2)
    data = ev if backend == "numpy" else ev.to_torch()
    out = _np(time_surface(data, tau_us=1000.0, t_ref_us=1000))
    expected = np.zeros((2, 2, 2), np.float32)
    expected[1, 0, 1] = math.exp(-(1000 - 400) / 1000)  # the latest event counts, not t=100
    expected[0, 1, 0] = math.exp(-(1000 - 250) / 1000)
    np.testing.assert_allclose(out, expected, rtol=1e-6)
    default_ref = _np(time_surface(data, tau_us=300.0))  # t_ref = last event
    assert default_ref[1, 0, 1] == 1.0 and default_ref[0, 1, 0] == pytest.approx(math.exp(-0.5))


def test_time_surface_numpy_torch_agree_and_unsorted_torch():
    ev = random_events(5000, seed=9)
    ev = Events(ev.x, ev.y, ev.t + 1_700_000_000_000_000, ev.p, ev.width, ev.height)
    ref = int(ev.t[-1]) + 5000
    expected = time_surface(ev, tau_us=20_000.0, t_ref_us=ref)
    tensors = ev.to_torch()
    order = torch.randperm(len(ev), generator=torch.Generator().manual_seed(1))
    shuffled = EventTensors(*(column[order] for column in tensors[:4]), ev.width, ev.height)
    for data in (tensors, shuffled):
        out = time_surface(data, tau_us=20_000.0, t_ref_us=ref)
        np.testing.assert_allclose(_np(out), expected, rtol=1e-6)
    seen = event_frame(ev) > 0
    assert ((expected > 0) == seen).all() and expected.max() <= 1.0
    assert not time_surface(Events.empty(3, 2), tau_us=1.0).any()


# -- inputs, validation, wrappers --------------------------------------------------------------
@pytest.mark.parametrize("polarity", ["int8", "signed", "bool", "int64"])
def test_inputs_are_not_modified(polarity):
    ev = random_events(1000, seed=2)
    columns = {name: getattr(ev, name).copy() for name in "xytp"}
    tensors = ev.to_torch(signed_polarity=polarity == "signed")
    if polarity in ("bool", "int64"):
        p = tensors.p.bool() if polarity == "bool" else tensors.p.long()
        tensors = EventTensors(tensors.x, tensors.y, tensors.t, p, ev.width, ev.height)
    tensor_copies = [column.clone() for column in tensors[:4]]
    for data in (ev, tensors):
        voxel_grid(data, 4), voxel_grid(data, 1), event_frame(data), event_frame(data, signed=True)
        time_surface(data, tau_us=1e4)
    voxel_grid_batch([tensors, tensors], 3)
    np.testing.assert_allclose(_np(voxel_grid(tensors, 4)), voxel_grid(ev, 4), atol=1e-5)
    for name in "xytp":
        np.testing.assert_array_equal(getattr(ev, name), columns[name])
    for column, copy in zip(tensors[:4], tensor_copies):
        assert torch.equal(column, copy)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_numpy():
    ev = random_events(50_000, seed=12)
    tensors = ev.to_torch("cuda")
    out = voxel_grid(tensors, 5)
    assert out.device.type == "cuda" and out.dtype == torch.float32
    np.testing.assert_allclose(_np(out), voxel_grid(ev, 5), atol=1e-4)
    batch = voxel_grid_batch([tensors, ev[:100].to_torch("cuda")], 5)
    np.testing.assert_allclose(_np(batch[1]), voxel_grid(ev[:100], 5), atol=1e-5)
    np.testing.assert_array_equal(_np(event_frame(tensors)), event_frame(ev))
    np.testing.assert_allclose(
        _np(time_surface(tensors, tau_us=1e4)), time_surface(ev, tau_us=1e4), rtol=1e-6
    )


def test_validation_errors_name_the_argument():
    ev = random_events(50)
    tensors = ev.to_torch()
    with pytest.raises(ValueError, match="bins"):
        voxel_grid(ev, 0)
    for bad in (2.5, True, "5"):
        with pytest.raises(TypeError, match="bins"):
            voxel_grid(ev, bad)
    with pytest.raises(TypeError, match=r"events .* got ndarray of shape \(10, 4\): cmax\.Events\.from_array\(array, "
                                        r"width, height, order='xytp'\) names its columns"):
        voxel_grid(np.zeros((10, 4)), 5)
    with pytest.raises(TypeError, match=r"events .* \(a structured array with fields \['x', 'y', 't', 'p'\]\): "
                                        r"cmax\.Events\.from_structured\(array, width, height\)"):
        event_frame(ev.to_structured())
    with pytest.raises(ValueError, match="t0_us"):
        voxel_grid(ev, 5, t0_us=int(ev.t[1]))
    with pytest.raises(ValueError, match="t1_us"):
        voxel_grid(tensors, 5, t1_us=int(ev.t[-1]) - 1)
    with pytest.raises(ValueError, match="t1_us"):
        voxel_grid(ev, 5, t0_us=10, t1_us=5)
    with pytest.raises(TypeError, match="t0_us"):
        voxel_grid(ev, 5, t0_us=0.5)
    for bad, error in ((0, ValueError), (-3.0, ValueError), (math.nan, ValueError), ("1", TypeError)):
        with pytest.raises(error, match="tau_us"):
            time_surface(ev, tau_us=bad)
    with pytest.raises(ValueError, match="t_ref_us"):
        time_surface(ev, tau_us=1.0, t_ref_us=int(ev.t[-1]) - 1)
    with pytest.raises(TypeError, match="signed"):
        event_frame(ev, signed="yes")
    out_of_bounds = EventTensors(tensors.x + ev.width, *tensors[1:4], ev.width, ev.height)
    with pytest.raises(ValueError, match="events.x"):
        voxel_grid(out_of_bounds)
    float_x = EventTensors(tensors.x.float(), *tensors[1:4], ev.width, ev.height)
    with pytest.raises(TypeError, match="events.x"):
        event_frame(float_x)
    short_t = EventTensors(tensors.x, tensors.y, tensors.t[:-1], tensors.p, ev.width, ev.height)
    with pytest.raises(ValueError, match="same length"):
        time_surface(short_t, tau_us=1.0)
    other = random_events(10, width=32).to_torch()
    with pytest.raises(ValueError, match="samples\\[1\\]"):
        voxel_grid_batch([tensors, other])
    with pytest.raises(TypeError, match="samples"):
        voxel_grid_batch(tensors)
    with pytest.raises(ValueError, match="bins"):
        VoxelGrid(bins=0)
    with pytest.raises(ValueError, match="tau_us"):
        TimeSurface(tau_us=0)


@pytest.mark.parametrize("p", [[2, 0, 1], [0.3, 0.0, 1.0], [-1, 0, 1], [-1, 0, 0]], ids=["2", "0.3", "-1,0,1", "-1,0"])
def test_torch_polarity_outside_both_encodings_is_refused_as_numpy_refuses_it(p):
    """Torch polarities were mapped by their sign (2 -> ON, 0.3 -> ON, -3 -> OFF) where Events refuses them."""
    x, y, t = torch.tensor([0, 1, 2]), torch.tensor([0, 0, 0]), torch.tensor([0, 10, 20])
    tensors = EventTensors(x, y, t, torch.tensor(p), 3, 1)
    with pytest.raises(ValueError, match=r"p must hold (polarities|whole numbers)"):
        Events(x.numpy(), y.numpy(), t.numpy(), np.array(p), 3, 1)
    for call in (lambda: voxel_grid(tensors, 2), lambda: event_frame(tensors), lambda: time_surface(tensors),
                 lambda: voxel_grid_batch([tensors])):
        with pytest.raises(ValueError, match=r"p must hold polarities as \{0, 1\}, \{-1, \+1\} or bool; got"):
            call()
    # uint8 255 (a signed -1 cast to uint8) is not -1: refused, not counted as ON
    cast = EventTensors(x, y, t, torch.tensor([255, 1, 0], dtype=torch.uint8), 3, 1)
    with pytest.raises(ValueError, match=r"got the values \[0, 1, 255\]"):
        event_frame(cast)


def test_torch_times_in_nanoseconds_since_1970_are_refused_as_numpy_refuses_them():
    """tonic's int64 times in ns since 1970 (1.7e18) handed over as torch tensors were read as µs: the voxel grid of a
    2 ms recording was built over 2 s of made-up time without a word, where ``Events`` refuses the same numbers. The
    same times in µs (t // 1000) give the grid of ``Events``."""
    x, y = torch.tensor([0, 1, 2, 1]), torch.tensor([0, 0, 1, 1])
    t_ns = torch.tensor([1_700_000_000_000_000_000 + k * 500_000 for k in range(4)])    # 0, 0.5, 1, 1.5 ms
    p = torch.tensor([1, 0, 1, 1], dtype=torch.int8)
    with pytest.raises(ValueError, match="look like nanoseconds"):
        Events(x.numpy(), y.numpy(), t_ns.numpy(), p.numpy(), 3, 2)
    tensors = EventTensors(x, y, t_ns, p, 3, 2)
    for call in (lambda: voxel_grid(tensors, 2), lambda: event_frame(tensors), lambda: time_surface(tensors),
                 lambda: voxel_grid_batch([tensors])):
        with pytest.raises(ValueError, match=r"^events\.t: the time 1700000000001500000, .*look like nanoseconds"):
            call()
    in_us = tensors._replace(t=t_ns // 1000)
    expected = Events(x.numpy(), y.numpy(), (t_ns // 1000).numpy(), p.numpy(), 3, 2)
    np.testing.assert_allclose(voxel_grid(in_us, 3).numpy(), voxel_grid(expected, 3), atol=1e-6)


def test_torch_events_of_a_sensor_given_as_height_width_are_named_as_swapped():
    """``EventTensors(..., 480, 640)`` of a 640x480 sensor's events (an image's shape passed as width, height) was
    refused as "events.x must lie in [0, 480), got values in [0, 639]" only, where ``Events`` names the swap; events
    outside both orders get no such hint."""
    x, y = torch.tensor([0, 639, 300]), torch.tensor([0, 479, 200])
    p, t = torch.tensor([1, 0, 1], dtype=torch.int8), torch.tensor([0, 10, 20])
    with pytest.raises(ValueError, match=r"width and height swapped\? \(Events takes width=640, height=480"):
        Events(x.numpy(), y.numpy(), t.numpy(), p.numpy(), 480, 640)
    with pytest.raises(ValueError, match=r"^events\.x must lie in \[0, 480\), got values in \[0, 639\]; every event "
                                         r"lies inside a 640x480 sensor: width and height swapped\? \(EventTensors "
                                         r"takes width=640, height=480"):
        event_frame(EventTensors(x, y, t, p, 480, 640))
    assert event_frame(EventTensors(x, y, t, p, 640, 480)).shape == (2, 480, 640)
    with pytest.raises(ValueError, match=r"^events\.x must lie in \[0, 480\), got values in \[0, 700\]$"):
        event_frame(EventTensors(torch.tensor([0, 700, 300]), y, t, p, 480, 640))


def test_voxel_grid_batch_reads_each_samples_own_polarity_encoding():
    """A bool sample first made a signed sample's -1.0 True (ON) once cast to its dtype: the batch's second grid
    held only ON weights where voxel_grid of that sample has OFF ones."""
    ev = Events([0, 1, 0, 1], [0, 0, 0, 0], [0, 10, 20, 30], [1, 0, 0, 1], 2, 1)
    as_bool = ev.to_torch()._replace(p=ev.to_torch().p.bool())
    signed = ev.to_torch(signed_polarity=True)
    expected = voxel_grid(ev, 2)      # t* = 0, 1/3, 2/3, 1: bin 0 = [1 - 1/3, -2/3], bin 1 = [-2/3, -1/3 + 1]
    np.testing.assert_allclose(expected[:, 0], [[2 / 3, -2 / 3], [-2 / 3, 2 / 3]], atol=1e-6)
    for samples in ([as_bool, signed], [signed, as_bool], [ev.to_torch(), signed]):
        batch = voxel_grid_batch(samples, bins=2)
        for grid in batch:
            np.testing.assert_allclose(grid.numpy(), expected, atol=1e-6)


def test_settings_objects_call_the_functions():
    ev = random_events(300)
    np.testing.assert_array_equal(VoxelGrid(bins=3)(ev), voxel_grid(ev, 3))
    np.testing.assert_array_equal(EventFrame(signed=True)(ev), event_frame(ev, signed=True))
    np.testing.assert_array_equal(TimeSurface(tau_us=1e3)(ev), time_surface(ev, tau_us=1e3))


def test_chunked_passes_give_the_same_results(monkeypatch):
    import cmax.representations._common as representations

    ev = random_events(3000, width=16, height=12, seed=4)
    tensors = ev.to_torch()
    batch_input = [tensors, random_events(500, width=16, height=12, seed=5).to_torch()]
    span = int(ev.t[-1] - ev.t[0])

    def compute():
        return [
            *(_voxel_grid_numpy(ev, 5, int(ev.t[0]), span, method=method)
              for method in ("weights", "signed", "split")),
            voxel_grid(ev, 1), event_frame(ev), time_surface(ev, tau_us=1e4),
            _np(voxel_grid(tensors, 5)), _np(voxel_grid_batch(batch_input, 3)),
        ]

    whole = compute()
    monkeypatch.setattr(representations, "_CHUNK", 97)  # many chunks, runs split across them
    for one, chunked in zip(whole, compute()):
        np.testing.assert_allclose(chunked, one, atol=1e-5)


# -- voxel grid of sub-pixel positions ------------------------------------------------------
def _slow_bilinear_voxel_grid(xy, t, p, width, height, bins) -> np.ndarray:
    """Event by event: the paper's time weights times the bilinear weights of the 4 pixels around ``xy``."""
    t0, t1 = int(t.min()), int(t.max())
    grid = np.zeros((bins, height, width))
    for (xf, yf), ti, pi in zip(xy.tolist(), t.tolist(), p.tolist()):
        if not (math.isfinite(xf) and math.isfinite(yf)):
            continue
        t_star = (bins - 1) * (ti - t0) / (t1 - t0) if t1 > t0 else 0.0
        sign = 1.0 if pi > 0 else -1.0
        for col in (math.floor(xf), math.floor(xf) + 1):
            for row in (math.floor(yf), math.floor(yf) + 1):
                w = max(0.0, 1 - abs(xf - col)) * max(0.0, 1 - abs(yf - row))
                if 0 <= col < width and 0 <= row < height:
                    for b in range(bins):
                        grid[b, row, col] += sign * w * max(0.0, 1.0 - abs(b - t_star))
    return grid


@pytest.mark.parametrize("bins", [1, 2, 5])
def test_voxel_grid_of_sub_pixel_positions_matches_the_slow_formula(bins):
    ev = random_events(300, width=9, height=7, seed=4)
    rng = np.random.default_rng(4)
    xy = np.column_stack([rng.uniform(-1.5, 9.5, 300), rng.uniform(-1.5, 7.5, 300)])   # some beyond the border
    xy[::37] = np.nan                                                                    # no position: left out
    expected = _slow_bilinear_voxel_grid(xy, ev.t, ev.p, 9, 7, bins)
    np.testing.assert_allclose(voxel_grid(ev, bins, pixels=xy), expected, atol=1e-5)
    tonic = _slow_bilinear_voxel_grid(xy, ev.t, ev.p, 9, 7, bins + 1)[:bins]
    np.testing.assert_allclose(voxel_grid(ev, bins, pixels=xy, normalization="tonic"), tonic, atol=1e-5)


@pytest.mark.parametrize("bins", [1, 2, 5])
def test_voxel_grid_of_events_without_any_position_is_empty(bins, monkeypatch):
    """Events none of which has a position (every one beyond a strong lens's reach: NaN, or inf) give an empty
    volume, also when that is so only for one run of ``_CHUNK`` events (was: IndexError from the empty run)."""
    from cmax.representations import _common

    ev = random_events(300, width=9, height=7, seed=5)
    for value in (np.nan, np.inf):
        xy = np.full((300, 2), value)
        np.testing.assert_array_equal(voxel_grid(ev, bins, pixels=xy), np.zeros((bins, 7, 9), np.float32))
    rng = np.random.default_rng(5)
    xy = np.column_stack([rng.uniform(0, 9, 300), rng.uniform(0, 7, 300)])
    xy[100:200] = np.nan                                           # the second run of 100 has no position
    monkeypatch.setattr(_common, "_CHUNK", 100)
    np.testing.assert_allclose(voxel_grid(ev, bins, pixels=xy),
                               _slow_bilinear_voxel_grid(xy, ev.t, ev.p, 9, 7, bins), atol=1e-5)


def test_voxel_grid_of_integer_positions_is_the_voxel_grid():
    ev = random_events(5000, seed=8)
    np.testing.assert_allclose(voxel_grid(ev, 5, pixels=np.column_stack([ev.x, ev.y])), voxel_grid(ev, 5),
                               atol=1e-5)


def test_voxel_grid_of_sub_pixel_positions_conserves_signed_polarity():
    ev = random_events(5000, seed=9)
    rng = np.random.default_rng(9)
    xy = np.column_stack([rng.uniform(0, ev.width - 1, len(ev)), rng.uniform(0, ev.height - 1, len(ev))])
    for bins in (1, 5):
        grid = voxel_grid(ev, bins, pixels=xy)
        assert grid.sum() == pytest.approx(ev.signed_polarity(np.float64).sum(), abs=1e-2)


def test_a_rectified_fisheye_volume_has_no_holes_with_sub_pixel_positions():
    """One event on every pixel of MVSEC's 346x260 DAVIS, rectified through its camchain (fisheye lens, R_rect,
    P_rect): at their nearest pixels a regular pattern of the rectified image holds no event (measured: 22 % of
    the pixels whose ray reaches the sensor) while others hold two; spread bilinearly from their exact
    positions, none is empty but along the border (0.03 %)."""
    from cmax.camera import Camera

    K = np.array([[226.38018519795807, 0.0, 173.6470807871759], [0.0, 226.15002947047415, 133.73271487507847],
                  [0.0, 0.0, 1.0]])
    D = np.array([-0.048031442223833355, 0.011330957517194437, -0.055378166304281135, 0.021500973881459395])
    R = np.array([[0.999877311526236, 0.015019439766575743, -0.004447282784398257],
                  [-0.014996983873604017, 0.9998748347535599, 0.005040367172759556],
                  [0.004522429630305261, -0.004973052949604937, 0.9999774079320989]])
    P = np.array([[199.6530123165822, 0.0, 177.43276376280926], [0.0, 199.6530123165822, 126.81215684365904],
                  [0.0, 0.0, 1.0]])
    camera = Camera(K, 346, 260, D, "equidistant", R, P)
    ys, xs = np.mgrid[0:260, 0:346]
    ev = Events(xs.ravel(), ys.ravel(), np.arange(xs.size) * 10, np.ones(xs.size, int), 346, 260)
    rounded, kept = camera.undistort_events(ev), camera.undistorted_kept(ev)
    pixels = camera.undistorted_pixels(ev)[kept]
    sensor = camera.distort_points(np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float64))
    seen = (np.isfinite(sensor).all(axis=1) & (sensor[:, 0] >= 1) & (sensor[:, 0] <= 344) & (sensor[:, 1] >= 1)
            & (sensor[:, 1] <= 258)).reshape(260, 346)       # rectified pixels whose ray reaches the sensor
    empty_rounded = 1 - (np.abs(voxel_grid(rounded, 5)).sum(axis=0) > 0)[seen].mean()
    empty_bilinear = 1 - (np.abs(voxel_grid(rounded, 5, pixels=pixels)).sum(axis=0) > 0)[seen].mean()
    assert empty_rounded > 0.1 and empty_bilinear < 0.005, (empty_rounded, empty_bilinear)


def test_voxel_grid_refuses_pixels_it_cannot_use():
    ev = random_events(10, seed=1)
    with pytest.raises(ValueError, match=r"pixels must have shape \(10, 2\)"):
        voxel_grid(ev, 3, pixels=np.zeros((9, 2)))
    with pytest.raises(TypeError, match="pixels= takes numpy cmax.Events"):
        voxel_grid(ev.to_torch(), 3, pixels=np.zeros((10, 2)))
