"""The batched contrast loss (cmax.loss) against cmax.fit's objective, its batching and its gradient."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from cmax.fitting import FitSettings
from cmax.fitting.window import SE3Model, Window
from cmax.loss import ContrastLoss, EventBatch, contrast_loss
from benchmarks.synthetic_windows import make_window
from cmax.warp import DepthGrid, WarpEvents


@pytest.fixture(scope="module")
def window():
    """A small indoor_flying window with exact twist and depth (constant-twist world)."""
    return make_window("indoor_flying", 3, width=120, height=90, focal=90.0, duration_s=0.1, max_frames=60)


def _fit_objective(ev: WarpEvents, settings: FitSettings, grid_rho: np.ndarray, twist: np.ndarray) -> float:
    """The objective exactly as cmax.fit's se3 stages evaluate it (SE3Model.objective, scale 1)."""
    w = Window(ev, settings, DepthGrid(grid_rho.shape, ev.width, ev.height))
    se3 = SE3Model(w, speed=1.0)
    rho = torch.as_tensor(grid_rho, dtype=ev.x.dtype)
    index, weight = se3.probes[3]
    rho_events = DepthGrid.sample(rho, w.index, w.weight)
    rho_probes = DepthGrid.sample(rho, index, weight)
    v, omega = torch.as_tensor(twist[:3]), torch.as_tensor(twist[3:])
    return float(se3.objective(v, omega, rho_events, rho_probes, 1))


@pytest.fixture(scope="module")
def slider():
    """A wall 2.8 m ahead, the camera slides sideways (constant twist)."""
    return make_window("slider", 1, width=120, height=90, focal=90.0, duration_s=0.1, max_frames=60)


@pytest.mark.parametrize("grid_shape", [(6, 8), (90, 120)])
def test_equals_fit_objective_for_one_window(window, grid_shape):
    settings = FitSettings(contrast="variance")   # se3's contrast in cmax.fit
    ev = WarpEvents.from_events(window.events, window.K, dtype=torch.float64, max_events=20_000)
    rng = np.random.default_rng(0)
    grid_rho = rng.uniform(0.2, 0.8, grid_shape)
    twist = window.twist + rng.normal(0, 0.05, 6)
    expected = _fit_objective(ev, settings, grid_rho, twist)
    got = contrast_loss(EventBatch.from_windows([ev]), torch.as_tensor(grid_rho)[None, None],
                        torch.as_tensor(twist)[None], torch.as_tensor(window.K)[None],
                        references=settings.references, sigma=settings.sigma, kind=settings.contrast,
                        collapse_weight=settings.collapse_weight)
    assert float(got) == pytest.approx(expected, rel=1e-9, abs=1e-12)


def test_batch_equals_windows_one_by_one(window, slider):
    other = slider
    evs = [WarpEvents.from_events(w.events, w.K, dtype=torch.float64, max_events=5000) for w in (window, other)]
    rho = torch.rand(2, 1, 6, 8, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) + 0.2
    twist = torch.as_tensor(np.stack([window.twist, other.twist]))
    K = torch.as_tensor(np.stack([window.K, other.K]))
    batched = contrast_loss(EventBatch.from_windows(evs), rho, twist, K, reduction="none")
    single = [contrast_loss(EventBatch.from_windows([evs[b]]), rho[b:b + 1], twist[b:b + 1], K[b:b + 1])
              for b in range(2)]
    assert batched.shape == (2,)
    np.testing.assert_allclose(batched.numpy(), [float(s) for s in single], rtol=1e-12)
    assert float(contrast_loss(EventBatch.from_windows(evs), rho, twist, K)) == pytest.approx(float(batched.mean()))


def test_from_padded_matches_from_windows(window):
    ev = WarpEvents.from_events(window.events, window.K, max_events=3000)
    n = len(ev)
    pad = lambda a: torch.cat([a, torch.zeros(500, dtype=a.dtype)])[None]  # noqa: E731
    valid = torch.cat([torch.ones(n, dtype=torch.bool), torch.zeros(500, dtype=torch.bool)])[None]
    padded = EventBatch.from_padded(pad(ev.x), pad(ev.y), pad(ev.t), pad(ev.polarity), valid,
                                    torch.tensor([ev.duration_s]), width=ev.width, height=ev.height)
    direct = EventBatch.from_windows([ev])
    args = (torch.full((1, 1, 4, 4), 0.4), torch.as_tensor(window.twist, dtype=torch.float32)[None],
            torch.as_tensor(window.K, dtype=torch.float32)[None])
    assert float(contrast_loss(padded, *args)) == pytest.approx(float(contrast_loss(direct, *args)), rel=1e-6)


def _descent_agrees(window, offsets) -> list[float]:
    """Cosines between the negative gradient at ``truth + offset`` and the direction back to the truth."""
    ev = WarpEvents.from_events(window.events, window.K, dtype=torch.float64, max_events=20_000)
    batch = EventBatch.from_windows([ev])
    rho = torch.as_tensor(np.nan_to_num(1.0 / window.depth, nan=0.0))[None, None]
    K = torch.as_tensor(window.K)[None]
    truth = torch.as_tensor(window.twist)
    cosines = []
    for offset in offsets:
        start = (truth + torch.as_tensor(offset)).clone().requires_grad_(True)
        (grad,) = torch.autograd.grad(ContrastLoss()(batch, rho, start[None], K), start)
        back = truth - start.detach()
        cosines.append(float(torch.dot(-grad, back) / (grad.norm() * back.norm())))
    return cosines


def test_gradient_wrt_rotation_points_towards_ground_truth(window):
    """With the true depth, the descent direction from a rotation error of 0.1 or 0.3 rad/s leads back."""
    offsets = [s * np.eye(6)[i] for i in (3, 4, 5) for s in (0.1, -0.1, 0.3, -0.3)]
    cosines = _descent_agrees(window, offsets)
    assert min(cosines) > 0.2, cosines
    assert np.median(cosines) > 0.6, cosines


def test_gradient_wrt_translation_points_towards_ground_truth(slider):
    """Sideways translation errors of 0.3 m/s (half the true speed): the descent direction leads back.

    (Smaller translation errors, or errors along the optical axis, change the
    parallax of a 0.1 s window at 120x90 px by well under a pixel; there the
    contrast's gradient is dominated by noise, which is why cmax.fit needs
    several starts.)
    """
    offsets = [s * np.eye(6)[i] for i in (0, 1) for s in (0.3, -0.3)]
    assert min(_descent_agrees(slider, offsets)) > 0.1


def test_true_twist_beats_rotation_errors(window):
    ev = WarpEvents.from_events(window.events, window.K, dtype=torch.float64, max_events=20_000)
    batch = EventBatch.from_windows([ev])
    rho = torch.as_tensor(np.nan_to_num(1.0 / window.depth, nan=0.0))[None, None]
    K, truth = torch.as_tensor(window.K)[None], torch.as_tensor(window.twist)
    at_truth = float(contrast_loss(batch, rho, truth[None], K))
    for i in (3, 4, 5):
        assert at_truth < float(contrast_loss(batch, rho, (truth + 0.1 * torch.as_tensor(np.eye(6)[i]))[None], K))


def test_gradcheck_wrt_depth_and_twist(window):
    ev = WarpEvents.from_events(window.events, window.K, dtype=torch.float64, max_events=300)
    batch = EventBatch.from_windows([ev])
    K = torch.as_tensor(window.K)[None]
    rho = (torch.full((1, 1, 3, 4), 0.4, dtype=torch.float64)).requires_grad_(True)
    twist = torch.as_tensor(window.twist)[None].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda r, t: contrast_loss(batch, r, t, K, sigma=1.0), (rho, twist),
                                    eps=1e-6, atol=1e-4, rtol=1e-3)


def test_bad_input_raises(window):
    ev = WarpEvents.from_events(window.events, window.K, max_events=100)
    batch = EventBatch.from_windows([ev])
    K = torch.as_tensor(window.K, dtype=torch.float32)[None]
    with pytest.raises(ValueError, match="inverse_depth"):
        contrast_loss(batch, torch.ones(1, 4, 4), torch.zeros(1, 6), K)
    with pytest.raises(ValueError, match="twist"):
        contrast_loss(batch, torch.ones(1, 1, 4, 4), torch.zeros(6), K)
    with pytest.raises(ValueError, match="K"):
        contrast_loss(batch, torch.ones(1, 1, 4, 4), torch.zeros(1, 6), K[0])
    with pytest.raises(ValueError, match="reduction"):
        contrast_loss(batch, torch.ones(1, 1, 4, 4), torch.zeros(1, 6), K, reduction="sum")
    with pytest.raises(TypeError, match="events"):
        contrast_loss(ev, torch.ones(1, 1, 4, 4), torch.zeros(1, 6), K)
