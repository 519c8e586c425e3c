"""The fit's own objectives in the contrast core (cmax.contrast.patches, cmax.contrast.sweep,
cmax.contrast.cells): what they compute, checked by hand or against an independent formula, and their
gradients (gradcheck)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from cmax.contrast.cells import cell_index, contrast_by_cell
from cmax.contrast.patches import PatchFlowContrast, PatchMotionContrast, cut_patches
from cmax.contrast.sweep import SweepNodeCost, lower_quantile, vote_scale
from cmax.objectives import contrast_of_images, variance
from cmax.warp import DepthGrid


def _events(n: int = 400, width: int = 40, height: int = 30, seed: int = 0):
    """Random events (float64) on a width x height sensor over 0.1 s: x, y, dt (t - t_mid) [s], polarity."""
    rng = np.random.default_rng(seed)
    x = torch.from_numpy(rng.uniform(2, width - 3, n))
    y = torch.from_numpy(rng.uniform(2, height - 3, n))
    dt = torch.from_numpy(rng.uniform(-0.05, 0.05, n))
    polarity = torch.from_numpy(rng.choice([-1.0, 1.0], n))
    return x, y, dt, polarity


K = torch.tensor([[30.0, 0, 20.0], [0, 30.0, 15.0], [0, 0, 1.0]], dtype=torch.float64)


# ----------------------------------------------------------------------------------------------
# Cells
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["variance", "gradient"])
def test_the_cell_shares_sum_to_the_contrast(kind):
    images = torch.rand(3, 17, 23, dtype=torch.float64)
    shares = contrast_by_cell(images, kind, (4, 5))
    assert shares.shape == (3, 20)
    np.testing.assert_allclose(shares.sum(-1).numpy(), contrast_of_images(images, kind).numpy(), rtol=1e-12)


def test_a_cell_holds_the_contrast_of_its_own_pixels():
    """One bright pixel in the top-right cell of a 2 x 2 grid: the gradient's energy is all there, the
    variance's is shared by every pixel (each off the mean) in proportion to its pixels."""
    images = torch.zeros(1, 8, 8, dtype=torch.float64)
    images[0, 1, 6] = 1.0
    gradient = contrast_by_cell(images, "gradient", (2, 2))[0]
    assert gradient[1] > 0 and torch.all(gradient[[0, 2, 3]] == 0)
    variance_shares = contrast_by_cell(images, "variance", (2, 2))[0]
    mean = 1 / 64
    np.testing.assert_allclose(variance_shares.numpy(),
                               [16 * mean ** 2 / 64, (15 * mean ** 2 + (1 - mean) ** 2) / 64,
                                16 * mean ** 2 / 64, 16 * mean ** 2 / 64])
    assert cell_index(8, 8, (2, 2)).reshape(8, 8)[1, 6] == 1


# ----------------------------------------------------------------------------------------------
# Patches
# ----------------------------------------------------------------------------------------------
def test_patches_hold_their_events_and_the_margin():
    x, y, dt, _ = _events()
    patches = cut_patches(x, y, dt, 40, 30, grid=(2, 2), min_events=10, max_events=10_000, margin=0.1,
                          min_margin_px=5)
    assert patches.count == 4 and patches.margin == 5 and patches.size == (15 + 10, 20 + 10)
    top_left = (x < 20) & (y < 15)
    np.testing.assert_allclose(patches.counts[0], float(top_left.sum()))
    np.testing.assert_allclose(patches.centres[0], [float(x[top_left].mean()), float(y[top_left].mean())])
    assert cut_patches(x, y, dt, 40, 30, grid=(2, 2), min_events=10_000, max_events=10_000, margin=0.1) is None


def test_patch_flow_contrast_is_minus_the_summed_normalised_variances():
    x, y, dt, _ = _events()
    patches = cut_patches(x, y, dt, 40, 30, grid=(2, 2), min_events=10, max_events=10_000, margin=0.3)
    objective = PatchFlowContrast.build(patches, 1.0, 0.1)
    assert float(objective(torch.zeros(8, dtype=torch.float64))) == pytest.approx(-4.0)
    q = torch.tensor([1.0, -2.0, 0.5, 0.0, 0.0, 3.0, -1.0, -1.0], dtype=torch.float64)
    flow = q.reshape(4, 2) / 0.1                                                     # px/s
    moved = patches.images(patches.x - flow[patches.patch, 0] * patches.dt,
                           patches.y - flow[patches.patch, 1] * patches.dt, 1.0)
    expected = -(variance(moved) / variance(patches.images(patches.x, patches.y, 1.0))).sum()
    np.testing.assert_allclose(float(objective(q)), float(expected), rtol=1e-12)


def test_patch_motion_contrast_is_one_without_motion():
    x, y, dt, _ = _events()
    patches = cut_patches(x, y, dt, 40, 30, grid=(2, 3), min_events=10, max_events=10_000, margin=0.3)
    objective = PatchMotionContrast.build(patches, K, 1.0)
    zero = torch.zeros(3, dtype=torch.float64)
    values = objective(zero, zero, torch.ones(len(patches.x), dtype=torch.float64))
    np.testing.assert_allclose(values.numpy(), np.ones(patches.count), rtol=1e-12)


def test_gradcheck_of_the_patch_objectives():
    x, y, dt, _ = _events(n=120)
    patches = cut_patches(x, y, dt, 40, 30, grid=(2, 2), min_events=5, max_events=10_000, margin=0.3)
    flow = PatchFlowContrast.build(patches, 1.0, 0.1)
    q = torch.tensor([0.3, -0.2, 0.1, 0.4, -0.3, 0.2, 0.1, -0.1], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(flow, (q,), eps=1e-6, atol=1e-5)
    motion = PatchMotionContrast.build(patches, K, 1.0)
    v = torch.tensor([0.2, -0.1, 0.3], dtype=torch.float64, requires_grad=True)
    omega = torch.tensor([0.1, 0.2, -0.1], dtype=torch.float64, requires_grad=True)
    rho = torch.full((len(patches.x),), 0.5, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b, c: motion(a, b, c).sum(), (v, omega, rho), eps=1e-6, atol=1e-5)


# ----------------------------------------------------------------------------------------------
# The sweep's cost
# ----------------------------------------------------------------------------------------------
def test_lower_quantile_is_torch_median_at_one_half():
    for n in (1, 2, 5, 8):
        values = torch.rand(n, dtype=torch.float64)
        assert lower_quantile(values, 0.5) == values.median()
    np.testing.assert_allclose(float(lower_quantile(torch.tensor([4.0, 1.0, 3.0, 2.0]), 1.0)), 4.0)


def test_every_event_votes_once_and_the_border_is_outside():
    """Each event's normalised values over the candidates of one call peak at 1 (its own largest value);
    with a border of 0 the votes of events next to the edge count, with a border of 5 they do not."""
    x, y, dt, polarity = _events(n=300)
    rays = torch.stack([x, y, torch.ones_like(x)], -1) @ torch.linalg.inv(K).T
    grid = DepthGrid((3, 4), 40, 30)
    index, weight = grid.weights(x, y)
    common = dict(rays=rays, dt=dt[None], polarity=polarity, v=np.array([0.3, 0.0, 0.0]), omega=np.zeros(3), K=K,
                  height=30, width=40, grid_shape=(3, 4), index=index, weight=weight)
    rho = torch.linspace(0.1, 2.0, 6, dtype=torch.float64)[:, None].expand(-1, len(x))
    cost = SweepNodeCost(**common, border_px=0)(rho)
    assert cost.shape == (6, 12) and float(cost.max()) <= 1.0 + 1e-12 and float(cost.min()) >= 0
    wide = SweepNodeCost(**common, border_px=5)(rho)
    assert not torch.allclose(cost, wide)
    score = torch.tensor([[1.0, 2.0], [3.0, 1.0]])
    np.testing.assert_allclose((score / vote_scale(score, torch.ones_like(score))).max(0).values.numpy(), [1.0, 1.0])
