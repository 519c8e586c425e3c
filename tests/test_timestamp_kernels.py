"""The compiled average-timestamp images (cmax.contrast._timestamp_kernels) against the torch operations of
AverageTimestamp, which stay the reference (objectives._COMPILED = False)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from cmax.contrast import SHARED_OBJECTIVE, AverageTimestamp, DepthMotion, EventWindows
from cmax.contrast import objectives as objectives_module
from cmax.contrast._timestamp_kernels import average_timestamp_images, compiled_images_apply
from benchmarks.synthetic_windows import make_window


@pytest.fixture(scope="module")
def windows():
    return [make_window("indoor_flying", 5, width=96, height=72, focal=70.0, duration_s=0.1, max_frames=30),
            make_window("driving", 6, width=96, height=72, focal=70.0, duration_s=0.1, max_frames=30)]


def _value_and_gradients(objective, batch, rho, twist, compiled: bool, monkeypatch):
    monkeypatch.setattr(objectives_module, "_COMPILED", compiled)
    rho, twist = rho.detach().clone().requires_grad_(True), twist.detach().clone().requires_grad_(True)
    value = objective(batch, DepthMotion(rho, twist))
    value.sum().backward()
    return value.detach(), rho.grad, twist.grad


def _batch(windows, which, dtype=torch.float64):
    pairs = [(windows[i].events, windows[i].K) for i in which]
    speed = [float(np.linalg.norm(windows[i].twist[:3])) for i in which]
    return EventWindows.from_windows(pairs, dtype=dtype, max_events=4000, speed=speed)


def _params(windows, which, grid, seed=0):
    g = torch.Generator().manual_seed(seed)
    rho = torch.rand(len(which), 1, *grid, dtype=torch.float64, generator=g) * 0.6 + 0.2
    twist = torch.as_tensor(np.stack([windows[i].twist for i in which]))
    return rho, twist


@pytest.mark.parametrize("which", [(0,), (1,), (0, 1)])           # one window, two windows
@pytest.mark.parametrize("grid", [(6, 8), (72, 96)])              # a coarse grid, a per-pixel map
@pytest.mark.parametrize("objective", [SHARED_OBJECTIVE, AverageTimestamp(purge=False), AverageTimestamp(eps=0.5)])
def test_equals_the_torch_operations_in_float64(windows, which, grid, objective, monkeypatch):
    batch = _batch(windows, which)
    rho, twist = _params(windows, which, grid)
    compiled = _value_and_gradients(objective, batch, rho, twist, True, monkeypatch)
    reference = _value_and_gradients(objective, batch, rho, twist, False, monkeypatch)
    assert compiled[0].dtype == torch.float64
    assert torch.allclose(compiled[0], reference[0], rtol=1e-12, atol=0)
    for mine, theirs in zip(compiled[1:], reference[1:]):
        assert float((mine - theirs).norm()) <= 1e-10 * float(theirs.norm())


def test_float32_events_agree_with_the_float64_reference(windows, monkeypatch):
    """The compiled images accumulate in float64 whatever the events' dtype: a float32 batch gives the
    float64 reference's value to float32 rounding of the warp."""
    rho, twist = _params(windows, (0, 1), (6, 8))
    reference = _value_and_gradients(SHARED_OBJECTIVE, _batch(windows, (0, 1)), rho, twist, False, monkeypatch)
    single = _value_and_gradients(SHARED_OBJECTIVE, _batch(windows, (0, 1), torch.float32), rho.float(),
                                  twist.float(), True, monkeypatch)
    assert single[0].dtype == torch.float32
    assert torch.allclose(single[0].double(), reference[0], rtol=1e-5)
    assert float((single[1].double() - reference[1]).norm()) <= 0.05 * float(reference[1].norm())


def test_by_hand_and_gradcheck():
    """Two events of one polarity on one pixel, no motion (as test_contrast_objectives' by-hand case), through
    the kernel directly: averages 0.5 at both references, 0.25 + 0.25; then a finite-difference check of the
    kernel's gradient on a few events away from pixel borders."""
    x = torch.tensor([[2.0, 2.0], [2.0, 2.0]], dtype=torch.float64)
    y = torch.tensor([[3.0, 3.0], [3.0, 3.0]], dtype=torch.float64)
    tau = torch.tensor([0.0, 1.0], dtype=torch.float64)
    base = torch.ones(2, dtype=torch.int64)                         # polarity on, window 0 of 1
    value = average_timestamp_images(x, y, tau, base, 1, (5, 6), 1e-9, True)
    assert float(value) == pytest.approx(0.5)

    g = torch.Generator().manual_seed(3)
    n = 9
    x = (torch.rand(2, n, generator=g, dtype=torch.float64) * 4 + 1).requires_grad_(True)
    y = (torch.rand(2, n, generator=g, dtype=torch.float64) * 3 + 1).requires_grad_(True)
    tau = torch.rand(n, generator=g, dtype=torch.float64)
    base = torch.randint(0, 4, (n,), generator=g)                   # two windows, both polarities
    assert torch.autograd.gradcheck(lambda a, b: average_timestamp_images(a, b, tau, base, 2, (6, 7), 0.1, True),
                                    (x, y), eps=1e-7, atol=1e-6, rtol=1e-4)


def test_purge_drops_events_that_leave_the_image(monkeypatch):
    """An event warped out of the image at one reference is dropped from both; without the purge it still
    votes at the other. Compiled and torch agree in both cases."""
    K = torch.eye(3, dtype=torch.float64)[None]
    x = torch.tensor([1.0, 0.2, 7.8], dtype=torch.float64)          # near the left and the right edge
    batch = EventWindows(x, torch.full((3,), 2.0, dtype=torch.float64), torch.tensor([0.0, 0.05, 0.1],
                         dtype=torch.float64), torch.ones(3, dtype=torch.float64), torch.zeros(3, dtype=torch.int64),
                         K, torch.tensor([0.1], dtype=torch.float64), 9, 5)
    params = DepthMotion(torch.ones(1, 1, 1, 1, dtype=torch.float64),
                         torch.tensor([[5.0, 0, 0, 0, 0, 0]], dtype=torch.float64))   # 0.5 px over the window
    values = {}
    for compiled in (True, False):
        monkeypatch.setattr(objectives_module, "_COMPILED", compiled)
        values[compiled] = [float(AverageTimestamp(purge=p)(batch, params)) for p in (True, False)]
    assert values[True] == pytest.approx(values[False], rel=1e-12)
    assert values[True][0] != pytest.approx(values[True][1])


def test_what_it_takes_and_refuses():
    x = torch.zeros(2, 5)
    assert compiled_images_apply(x, x) and compiled_images_apply(x.double(), x.double())
    assert not compiled_images_apply(x, x.double())                   # mixed dtypes
    assert not compiled_images_apply(x[:1], x[:1])                    # one reference only
    assert not compiled_images_apply(x.half(), x.half())
    with pytest.raises(ValueError, match="needs CPU float32/float64"):
        average_timestamp_images(x[:1], x[:1], torch.zeros(5), torch.zeros(5, dtype=torch.int64), 1, (4, 4), 1e-9,
                                 True)
    tau, base = torch.zeros(5), torch.zeros(5, dtype=torch.int64)
    with pytest.raises(ValueError, match=r"base must lie in \[0, 2\)"):     # an image the kernel does not have
        average_timestamp_images(x, x, tau, base + 2, 1, (4, 4), 1e-9, True)
    with pytest.raises(ValueError, match="tau and base"):
        average_timestamp_images(x, x, tau[:4], base, 1, (4, 4), 1e-9, True)
    with pytest.raises(ValueError, match="positive"):
        average_timestamp_images(x, x, tau, base, 0, (4, 4), 1e-9, True)


def test_event_windows_keep_rays_and_grid_weights(windows):
    """The batch keeps its rays and depth-grid weights (they depend on nothing the objectives optimise), and
    recomputes them when its pixels carry a gradient."""
    from cmax.warp import DepthGrid

    batch = _batch(windows, (0, 1))
    assert batch.rays() is batch.rays()
    index, weight = batch.grid_weights((6, 8))
    assert batch.grid_weights((6, 8))[0] is index
    own_index, own_weight = DepthGrid((6, 8), batch.width, batch.height).weights(batch.x, batch.y)
    assert torch.equal(index, own_index + batch.window[:, None] * 48) and torch.equal(weight, own_weight)
    moving = EventWindows(batch.x.clone().requires_grad_(True), batch.y, batch.t, batch.polarity, batch.window,
                          batch.K, batch.duration_s, batch.width, batch.height)
    assert moving.rays() is not moving.rays()
    moving.rays()[:, 0].sum().backward()
    assert moving.x.grad is not None


def test_window_bounds():
    """Contiguous runs in window order give their bounds (an empty window too); any other order gives None."""
    K = torch.eye(3)[None].repeat(3, 1, 1)
    def batch(window):
        n = len(window)
        return EventWindows(torch.zeros(n), torch.zeros(n), torch.zeros(n), torch.ones(n),
                            torch.tensor(window, dtype=torch.int64), K, torch.ones(3), 4, 4)
    assert batch([0, 0, 2, 2, 2]).window_bounds() == ((0, 2), (2, 2), (2, 5))
    assert batch([0, 2, 0]).window_bounds() is None


def test_an_unordered_batch_takes_the_torch_warp_and_gives_the_same_loss(windows, monkeypatch):
    """Events of two windows interleaved (not contiguous runs) are warped by torch; the loss is the same."""
    batch = _batch(windows, (0, 1))
    order = torch.randperm(len(batch), generator=torch.Generator().manual_seed(2))
    mixed = EventWindows(batch.x[order], batch.y[order], batch.t[order], batch.polarity[order], batch.window[order],
                         batch.K, batch.duration_s, batch.width, batch.height, batch.speed)
    assert mixed.window_bounds() is None
    rho, twist = _params(windows, (0, 1), (6, 8))
    a = _value_and_gradients(SHARED_OBJECTIVE, batch, rho, twist, True, monkeypatch)
    b = _value_and_gradients(SHARED_OBJECTIVE, mixed, rho, twist, True, monkeypatch)
    assert torch.allclose(a[0], b[0], rtol=1e-12)
    assert float((a[1] - b[1]).norm()) <= 1e-10 * float(a[1].norm())


def test_float32_events_on_the_last_pixel_are_not_purged_by_rounding():
    """With no motion, the float32 round trip K (K^-1 p) puts an event of the last column at x = W - 1 + 2e-6:
    it stays inside (EDGE_TOLERANCE_PX), in the compiled kernels and in the torch operations alike (before: the
    whole window purged, loss 1e-5 against 0.5 in float64)."""
    from cmax.contrast import SHARED_OBJECTIVE, DepthMotion, EventWindows
    from cmax.contrast import objectives as objectives_module

    W, H, n = 32, 24, 400
    rng = np.random.default_rng(0)
    t, p = np.sort(rng.uniform(0, 0.1, n)), rng.choice([-1.0, 1.0], n)
    K = torch.tensor([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])[None]
    x = np.where(np.arange(n) % 2 == 0, W - 1.0, 5.0)            # half on the last column, half well inside
    losses = []
    for compiled in (True, False):
        objectives_module._COMPILED = compiled
        try:
            batch = EventWindows(torch.tensor(x, dtype=torch.float32), torch.full((n,), H - 1.0),
                                 torch.tensor(t, dtype=torch.float32), torch.tensor(p, dtype=torch.float32),
                                 torch.zeros(n, dtype=torch.int64), K, torch.tensor([0.1]), W, H)
            params = DepthMotion(torch.full((1, 1, 3, 4), 0.5), torch.zeros(1, 6))
            losses.append(float(SHARED_OBJECTIVE(batch, params)))
        finally:
            objectives_module._COMPILED = True
    assert losses[0] == pytest.approx(losses[1], rel=1e-5)
    assert abs(losses[0]) > 0.1        # the events count: a purged window scores about 0
