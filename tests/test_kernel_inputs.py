"""The compiled kernels do no bounds checks: the objectives that feed them refuse arrays of the wrong shape
(before, a short inverse-depth array was read past its end, and short depth rows corrupted the heap)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from cmax.contrast import DepthGrid, EventWindows, PatchFlowContrast, PatchMotionContrast, SweepNodeCost, cut_patches

W, H = 64, 48
K = torch.tensor([[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _patches(n: int = 2000):
    rng = np.random.default_rng(1)
    x, y = torch.tensor(rng.uniform(0, W - 1, n)), torch.tensor(rng.uniform(0, H - 1, n))
    dt = torch.tensor(rng.uniform(-0.05, 0.05, n))
    return cut_patches(x, y, dt, W, H, grid=(2, 2), min_events=10, max_events=5000, margin=0.2)


def test_patch_motion_contrast_refuses_per_event_arrays_of_another_length():
    patches = _patches()
    contrast = PatchMotionContrast.build(patches, K, 1.0)
    m = len(patches.x)
    v, omega = np.array([0.1, 0.0, 0.0]), np.array([0.0, 0.1, 0.0])
    value = contrast.sum_and_gradients(v, omega, np.ones(m))[0]
    assert value == pytest.approx(float(contrast(torch.tensor(v), torch.tensor(omega), torch.ones(m,
                                                                                                dtype=torch.float64)).sum()))
    for bad in (np.ones(m // 10), np.float64(1.0), np.ones(m + 1)):
        with pytest.raises(ValueError, match="rho_events must have shape"):
            contrast.sum_and_gradients(v, omega, bad)
    with pytest.raises(ValueError, match="omega must have shape"):
        contrast.sum_and_gradients(v, np.ones(2), np.ones(m))
    rows = torch.ones(3, m, dtype=torch.float64)
    assert tuple(contrast.at_depths(torch.tensor(v), torch.tensor(omega), rows).shape) == (3, patches.count)
    with pytest.raises(ValueError, match="each row of rho_rows"):
        contrast.at_depths(torch.tensor(v), torch.tensor(omega), torch.ones(3, m // 10, dtype=torch.float64))


def test_patch_flows_and_variances_refuse_the_wrong_length():
    patches = _patches()
    objective = PatchFlowContrast.build(patches, 1.0, 0.1)
    value, grad = objective.fun_and_grad(np.zeros(2 * patches.count))
    assert grad.shape == (2 * patches.count,) and np.isfinite(value)
    with pytest.raises(ValueError, match="q must have shape"):
        objective.fun_and_grad(np.zeros(2 * patches.count - 1))
    with pytest.raises(ValueError, match="x must have shape"):
        patches.variances(patches.x[:10], patches.y[:10], 1.0)


def test_sweep_node_cost_refuses_indices_beyond_its_grid_and_short_weights():
    rng = np.random.default_rng(0)
    n = 500
    x, y = torch.tensor(rng.uniform(0, W - 1, n)), torch.tensor(rng.uniform(0, H - 1, n))
    rays = torch.stack([x, y, torch.ones_like(x)], -1) @ torch.linalg.inv(K).T
    dt = torch.tensor(rng.uniform(-0.05, 0.05, n))[None]
    polarity = torch.tensor(rng.choice([-1.0, 1.0], n), dtype=torch.float64)
    index, weight = DepthGrid((6, 8), W, H).weights(x, y)
    motion = (np.array([0.3, 0.0, 0.0]), np.zeros(3), K, H, W)
    cost = SweepNodeCost(rays, dt, polarity, *motion, (6, 8), index, weight)
    assert tuple(cost(torch.full((3, n), 0.5, dtype=torch.float64)).shape) == (3, 48)
    with pytest.raises(ValueError, match="rho_events must be"):
        cost(torch.full((3, n - 1), 0.5, dtype=torch.float64))
    with pytest.raises(ValueError, match="index must hold nodes"):
        SweepNodeCost(rays, dt, polarity, *motion, (2, 2), index, weight)
    with pytest.raises(ValueError, match=r"index and weight must be \(N, 4\)"):
        SweepNodeCost(rays, dt, polarity, *motion, (6, 8), index[:50], weight[:50])


def test_event_windows_refuse_non_finite_pixels_and_times_outside_their_window():
    n = 100
    rng = np.random.default_rng(0)
    x, y = torch.tensor(rng.uniform(0, W - 1, n)), torch.tensor(rng.uniform(0, H - 1, n))
    t = torch.tensor(np.sort(rng.uniform(0, 0.1, n)))
    rest = (torch.ones(n, dtype=torch.float64), torch.zeros(n, dtype=torch.int64), K[None], torch.tensor([0.1]), W, H)
    assert len(EventWindows(x, y, t, *rest)) == n
    bad_x = x.clone()
    bad_x[3] = float("inf")
    with pytest.raises(ValueError, match="x must be finite"):
        EventWindows(bad_x, y, t, *rest)
    with pytest.raises(ValueError, match="microseconds"):
        EventWindows(x, y, t * 1e6, *rest)
    with pytest.raises(ValueError, match="within"):
        EventWindows(x, y, t - 0.05, *rest)
