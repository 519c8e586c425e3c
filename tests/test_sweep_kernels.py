"""The compiled depth-sweep cost (cmax.contrast._sweep_kernels) against the torch reference of
cmax.contrast.sweep (``_COMPILED = False``): the same node costs on a real simulated window and on edge
cases (events warped off the image, on pixel borders, one polarity, one image, no blur), one score by
hand, and the dispatch rules."""
from __future__ import annotations

import functools
from dataclasses import replace

import numpy as np
import pytest
import torch

import cmax.contrast.sweep as sweep
from benchmarks.synthetic_windows import make_window
from cmax.contrast._sweep_kernels import event_scores_compiled, se3_terms, vote_scale_compiled
from cmax.contrast.sweep import SweepNodeCost, vote_scale
from cmax.warp import MIN_PROJECTED_DEPTH, DepthGrid, WarpEvents, project, warp_se3

TOLERANCE = {torch.float32: 1e-5, torch.float64: 1e-12}


@functools.lru_cache(maxsize=None)
def _window():
    return make_window("indoor_flying", 3, width=120, height=90, focal=90.0, duration_s=0.1, max_frames=60)


def _real_cost(dtype: torch.dtype, **options) -> tuple[SweepNodeCost, int]:
    w = _window()
    ev = WarpEvents.from_events(w.events, w.K, dtype=dtype)
    grid = DepthGrid((3, 4), ev.width, ev.height)
    index, weight = grid.weights(ev.x, ev.y)
    cost = SweepNodeCost(ev.rays, ev.dt((0.5,)), ev.polarity, w.twist[:3], w.twist[3:], ev.K, ev.height, ev.width,
                         (3, 4), index, weight, **options)
    return cost, len(ev)


def _both(cost: SweepNodeCost, rho: torch.Tensor, monkeypatch) -> tuple[torch.Tensor, torch.Tensor]:
    """(compiled, torch reference) node costs; asserts that the compiled path really ran."""
    calls = []
    original = sweep.event_scores_compiled
    monkeypatch.setattr(sweep, "event_scores_compiled", lambda *a: calls.append(1) or original(*a))
    compiled = cost(rho)
    assert calls, "the compiled path did not run"
    monkeypatch.setattr(sweep, "_COMPILED", False)
    reference = cost(rho)
    monkeypatch.setattr(sweep, "_COMPILED", True)
    assert len(calls) == 1
    return compiled, reference


def _assert_same(compiled: torch.Tensor, reference: torch.Tensor, dtype: torch.dtype) -> None:
    assert compiled.dtype == reference.dtype == dtype and compiled.shape == reference.shape
    np.testing.assert_allclose(compiled.numpy(), reference.numpy(), rtol=TOLERANCE[dtype], atol=TOLERANCE[dtype])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("polarity_split", [True, False])
def test_a_real_window_costs_the_same_as_the_torch_reference(dtype, polarity_split, monkeypatch):
    cost, n = _real_cost(dtype, polarity_split=polarity_split, chunk=5)
    rho = torch.linspace(0.0, 2.0, 12, dtype=dtype)[:, None].expand(-1, n)          # the sweep over the range
    compiled, reference = _both(cost, rho, monkeypatch)
    _assert_same(compiled, reference, dtype)
    assert float(reference.std()) > 0.01                                            # not a constant cost
    base = torch.from_numpy(np.random.default_rng(0).uniform(0.2, 1.5, n)).to(dtype)  # a relative sweep
    compiled, reference = _both(cost, base[None] * torch.exp(torch.linspace(-0.3, 0.3, 7, dtype=dtype))[:, None],
                                monkeypatch)
    _assert_same(compiled, reference, dtype)


@pytest.mark.parametrize("polarity", [1.0, -1.0])
def test_one_polarity_only_and_a_skewed_camera(polarity, monkeypatch):
    cost, n = _real_cost(torch.float32)
    skewed = cost.K.clone()
    skewed[0, 1] = 0.4                                                               # K[0, 1] enters the warp
    cost = replace(cost, polarity=torch.full((n,), polarity), K=skewed)
    rho = torch.linspace(0.1, 1.5, 6)[:, None].expand(-1, n)
    _assert_same(*_both(cost, rho, monkeypatch), torch.float32)


def test_events_pushed_off_the_image_and_no_blur(monkeypatch):
    """A fast motion and near depths move many events off the sensor for the near candidates, and put some
    behind the camera (z clamped to MIN_PROJECTED_DEPTH)."""
    cost, n = _real_cost(torch.float64, sigma=0.0, border_px=3)
    cost = replace(cost, v=np.array([3.0, -1.0, 5.0]))
    rho = torch.linspace(0.0, 20.0, 8, dtype=torch.float64)[:, None].expand(-1, n)
    x, y = warp_se3(cost.rays, cost.dt, torch.as_tensor(cost.v), torch.as_tensor(cost.omega), rho, cost.K)
    off = ((x < 0) | (x > cost.width - 1) | (y < 0) | (y > cost.height - 1)).double().mean(1)
    assert float(off[0]) < 0.1 and float(off[-1]) > 0.3
    rotated, moved = se3_terms(cost.rays, cost.dt, torch.as_tensor(cost.v), torch.as_tensor(cost.omega))
    assert bool(((rotated + rho[..., None] * moved)[..., 2] < MIN_PROJECTED_DEPTH).any())
    _assert_same(*_both(cost, rho, monkeypatch), torch.float64)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_events_on_pixel_borders_and_the_image_edge(dtype, monkeypatch):
    """Without motion events stay where they are: integer and half-integer positions on and around the
    edge (x = -1.5 ... W - 0.5), where the bilinear votes and reads split exactly or fall off."""
    W, H = 9, 7
    xs = torch.tensor([-1.5, -1.0, -0.5, 0.0, 0.5, 3.0, 4.5, W - 1.5, W - 1.0, W - 0.5, W - 0.25], dtype=dtype)
    ys = torch.tensor([-1.0, -0.5, 0.0, 2.5, 3.0, H - 1.0, H - 0.5], dtype=dtype)
    x, y = (a.reshape(-1) for a in torch.meshgrid(xs, ys, indexing="ij"))
    Kt = torch.tensor([[5.0, 0.0, 4.0], [0.0, 5.0, 3.0], [0.0, 0.0, 1.0]], dtype=dtype)
    rays = torch.stack([x, y, torch.ones_like(x)], -1) @ torch.linalg.inv(Kt).T
    polarity = torch.where(torch.arange(len(x)) % 3 == 0, -1.0, 1.0).to(dtype)
    grid = DepthGrid((2, 2), W, H)
    index, weight = grid.weights(x.clamp(0, W - 1), y.clamp(0, H - 1))
    cost = SweepNodeCost(rays, torch.zeros(1, len(x), dtype=dtype), polarity, np.zeros(3), np.zeros(3), Kt, H, W,
                         (2, 2), index, weight, border_px=0)
    rho = torch.tensor([[0.5], [1.0]], dtype=dtype).expand(-1, len(x))
    _assert_same(*_both(cost, rho, monkeypatch), dtype)


def test_one_event_scores_its_own_bilinear_energy():
    """Unblurred, an event alone at (2.25, 3.5) reads back sum_k w_k^2 of its own four votes:
    2 (0.75 * 0.5)^2 + 2 (0.25 * 0.5)^2 = 0.3125; inside with border 1, not with border 3."""
    rotated = np.array([[2.25, 3.5, 1.0]])
    K = np.eye(3)
    for border, inside_expected in ((1, 1.0), (3, 0.0)):
        score, inside, peak, always = event_scores_compiled(rotated, np.zeros((1, 3)), np.zeros((1, 1)),
                                                            np.zeros(1, np.int64), 2, K, 8, 8, 0.0, border, 4)
        np.testing.assert_allclose(score, [[0.3125]], rtol=1e-15)
        assert inside[0, 0] == inside_expected and bool(always[0]) == bool(inside_expected)
        assert peak[0] == 0.3125 * inside_expected


def test_a_point_behind_the_camera_projects_from_the_clamped_depth():
    """``rotated + rho moved`` = (0.05, 0, -1): z is clamped to MIN_PROJECTED_DEPTH = 0.05, so the event lands on
    x = 5 * 0.05 / 0.05 + 4 = 9, y = 3 (as :func:`cmax.warp.project`), an integer pixel: it reads back its
    whole vote, 1."""
    K = np.array([[5.0, 0.0, 4.0], [0.0, 5.0, 3.0], [0.0, 0.0, 1.0]])
    rotated, moved, rho = np.array([[0.05, 0.0, 1.0]]), np.array([[0.0, 0.0, -2.0]]), np.ones((1, 1))
    x, y = project(torch.from_numpy(rotated + rho[..., None] * moved), torch.from_numpy(K))
    assert (float(x), float(y)) == (9.0, 3.0)
    score, inside, _, _ = event_scores_compiled(rotated, moved, rho, np.zeros(1, np.int64), 1, K, 7, 12, 0.0, 1, 1)
    assert score[0, 0] == 1.0 and inside[0, 0] == 1.0


@pytest.mark.parametrize("omega", [np.array([0.01, -0.02, 0.005]), np.array([1.5, -2.0, 3.0])])
def test_the_depth_independent_terms_rebuild_the_se3_warp_bit_for_bit(omega):
    """Below and above the small-angle switch of the Rodrigues coefficients."""
    cost, n = _real_cost(torch.float32)
    v, w = torch.tensor([0.4, -0.2, 0.3]), torch.as_tensor(omega, dtype=torch.float32)
    rho = torch.linspace(0.0, 3.0, 5)[:, None].expand(-1, n)
    rotated, moved = se3_terms(cost.rays, cost.dt, v, w)
    x, y = project(rotated + rho[..., None] * moved, cost.K)
    x_ref, y_ref = warp_se3(cost.rays, cost.dt, v, w, rho, cost.K)
    assert torch.equal(x, x_ref) and torch.equal(y, y_ref)


@pytest.mark.parametrize("inside_rate", [1.0, 0.9, 0.0])
def test_the_vote_scale_by_selection_equals_the_sorted_one(inside_rate):
    rng = np.random.default_rng(1)
    score = torch.from_numpy(rng.random((6, 501)).astype(np.float32))
    inside = torch.from_numpy((rng.random((6, 501)) < inside_rate).astype(np.float32))
    peak = (score * inside).max(0).values.numpy()
    always = (inside.min(0).values > 0).numpy()
    for q in (0.0, 0.3, 0.5, 1.0):
        expected = vote_scale(score, inside, q)[0].numpy()
        np.testing.assert_array_equal(vote_scale_compiled(peak, always, q), expected)


def test_the_torch_path_keeps_gradients_and_mixed_dtypes(monkeypatch):
    """A cost asked for a gradient, or inverse depths in another dtype than the events, take the torch ops."""
    cost, n = _real_cost(torch.float64)
    called = []
    monkeypatch.setattr(sweep, "event_scores_compiled", lambda *a: called.append(1))
    rho = torch.full((2, n), 0.5, dtype=torch.float64, requires_grad=True)
    cost(rho).sum().backward()
    assert rho.grad is not None and float(rho.grad.abs().sum()) > 0
    cost(torch.full((2, n), 0.5, dtype=torch.float32))
    assert not called


def test_the_chunk_does_not_change_the_compiled_scores():
    cost, n = _real_cost(torch.float32)
    rotated, moved = se3_terms(cost.rays, cost.dt, torch.as_tensor(cost.v, dtype=torch.float32),
                               torch.as_tensor(cost.omega, dtype=torch.float32))
    rho = np.ascontiguousarray(np.broadcast_to(np.linspace(0.1, 1.5, 7, dtype=np.float32)[:, None], (7, n)))
    image_of = (cost.polarity <= 0).to(torch.int64).numpy()
    runs = [event_scores_compiled(rotated.numpy(), moved.numpy(), rho, image_of, 2, cost.K.numpy(), cost.height,
                                  cost.width, 1.0, 1, chunk) for chunk in (1, 3, 7)]
    for other in runs[1:]:
        for a, b in zip(runs[0], other):
            np.testing.assert_array_equal(a, b)


def test_the_kept_warp_terms_follow_changes_of_the_events_and_the_motion(monkeypatch):
    """The depth-independent warp terms are reused between calls; changing the rays in place, or the
    twist, gives the costs of the new input, not those of the kept terms."""
    cost, n = _real_cost(torch.float64)
    rays = cost.rays.clone()
    cost = replace(cost, rays=rays)
    rho = torch.linspace(0.1, 1.5, 5, dtype=torch.float64)[:, None].expand(-1, n)
    before = cost(rho)
    rays[:, 0] += 0.02                                                          # every event moves 1.8 px
    compiled, reference = _both(cost, rho, monkeypatch)
    _assert_same(compiled, reference, torch.float64)
    assert not torch.allclose(compiled, before)
    turned = replace(cost, omega=np.asarray(cost.omega) + np.array([0.0, 0.5, 0.0]))
    _assert_same(*_both(turned, rho, monkeypatch), torch.float64)


def test_the_benchmark_switch_restores_the_compiled_path():
    from benchmarks.speed_sweep import torch_reference

    with pytest.raises(RuntimeError):
        with torch_reference():
            assert sweep._COMPILED is False
            raise RuntimeError("inside")
    assert sweep._COMPILED is True


def test_no_event_stays_inside_for_every_candidate(monkeypatch):
    """A candidate that throws every event off the image leaves no event inside for all candidates: every
    event is then divided by the median of all events' largest values, those taken inside the border only
    (an event in the border band reads a value but counts 0)."""
    cost, _ = _real_cost(torch.float32, border_px=25)
    keep = cost.dt[0].abs() > 0.005                                                  # events that move
    cost = replace(cost, rays=cost.rays[keep], dt=cost.dt[:, keep], polarity=cost.polarity[keep],
                   index=cost.index[keep], weight=cost.weight[keep], v=np.array([20.0, 0.0, 0.0]))
    n = int(keep.sum())
    rho = torch.cat([torch.linspace(0.0, 0.5, 5), torch.tensor([400.0])])[:, None].expand(-1, n)
    x, _ = warp_se3(cost.rays, cost.dt, torch.as_tensor(cost.v, dtype=torch.float32),
                    torch.as_tensor(cost.omega, dtype=torch.float32), rho, cost.K)
    assert bool(((x[-1] < -1) | (x[-1] > cost.width)).all())
    _assert_same(*_both(cost, rho, monkeypatch), torch.float32)
