"""Warp models and torch SE(3): closed forms against numpy geometry, shapes, float64 gradchecks."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from cmax.geometry import se3_exp, so3_exp
from cmax.geometry_torch import se3_exp_torch, se3_transform, so3_exp_torch, so3_rotate
from cmax.warp import DepthGrid, WarpEvents, warp_flow, warp_rotation, warp_se3
from conftest import random_events

K = np.array([[200.0, 0.0, 60.0], [0.0, 190.0, 45.0], [0.0, 0.0, 1.0]])


def test_so3_and_se3_match_numpy_including_tiny_angles():
    rng = np.random.default_rng(0)
    omega = np.vstack([rng.normal(size=(5, 3)), 1e-7 * rng.normal(size=(2, 3)), np.zeros((1, 3))])
    xi = np.column_stack([rng.normal(size=(8, 3)), omega])
    u = rng.normal(size=(8, 3))
    rotated = so3_rotate(torch.from_numpy(omega), torch.from_numpy(u)).numpy()
    np.testing.assert_allclose(rotated, np.einsum("nij,nj->ni", so3_exp(omega), u), atol=1e-12)
    moved = se3_transform(torch.from_numpy(xi), torch.from_numpy(u)).numpy()
    T = se3_exp(xi)
    np.testing.assert_allclose(moved, np.einsum("nij,nj->ni", T[:, :3, :3], u) + T[:, :3, 3], atol=1e-12)
    np.testing.assert_allclose(so3_exp_torch(torch.from_numpy(omega)).numpy(), so3_exp(omega), atol=1e-12)
    np.testing.assert_allclose(se3_exp_torch(torch.from_numpy(xi)).numpy(), T, atol=1e-12)


def test_gradcheck_rotations_at_zero_and_away():
    for scale in (0.0, 1e-3, 0.7):
        omega = (scale * torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)).requires_grad_()
        xi = torch.cat([torch.tensor([0.2, 0.1, -0.3], dtype=torch.float64), omega.detach()]).requires_grad_()
        u = torch.randn(4, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
        assert torch.autograd.gradcheck(lambda w: so3_rotate(w, u), (omega,))
        assert torch.autograd.gradcheck(lambda x: se3_transform(x, u), (xi,))


def _rays(x, y):
    return torch.from_numpy(np.column_stack([x, y, np.ones_like(x)]) @ np.linalg.inv(K).T)


def test_flow_warp_closed_form():
    x, y = warp_flow(torch.tensor([10.0, 0.0]), torch.tensor([5.0, 1.0]), torch.tensor([[0.1, -0.2]]),
                     torch.tensor([20.0, -10.0]))
    assert x.tolist() == [[8.0, 4.0]] and y.tolist() == [[6.0, -1.0]]


def test_rotation_warp_is_the_homography_and_se3_reduces_to_it():
    rng = np.random.default_rng(1)
    x, y = rng.uniform(0, 120, 50), rng.uniform(0, 90, 50)
    dt = torch.from_numpy(rng.uniform(-0.05, 0.05, 50))
    omega = np.array([0.4, -1.1, 0.7])
    xr, yr = warp_rotation(_rays(x, y), dt, torch.from_numpy(omega), torch.from_numpy(K))
    H = K @ so3_exp(omega[None] * dt.numpy()[:, None]) @ np.linalg.inv(K)
    p = np.einsum("nij,nj->ni", H, np.column_stack([x, y, np.ones(50)]))
    np.testing.assert_allclose(xr.numpy(), p[:, 0] / p[:, 2], atol=1e-9)
    np.testing.assert_allclose(yr.numpy(), p[:, 1] / p[:, 2], atol=1e-9)
    xs, ys = warp_se3(_rays(x, y), dt, torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64), torch.from_numpy(omega),
                      torch.zeros(50, dtype=torch.float64), torch.from_numpy(K))
    np.testing.assert_allclose(xs.numpy(), xr.numpy(), atol=1e-12)


def test_se3_warp_matches_rigid_motion_of_points():
    rng = np.random.default_rng(2)
    x, y = rng.uniform(0, 120, 30), rng.uniform(0, 90, 30)
    depth = rng.uniform(1, 5, 30)
    dt = rng.uniform(-0.1, 0.1, 30)
    xi = np.array([0.5, -0.2, 1.0, 0.3, 0.2, -0.4])
    xs, ys = warp_se3(_rays(x, y), torch.from_numpy(dt), torch.from_numpy(xi[:3]), torch.from_numpy(xi[3:]),
                      torch.from_numpy(1 / depth), torch.from_numpy(K))
    points = (np.column_stack([x, y, np.ones(30)]) @ np.linalg.inv(K).T) * depth[:, None]
    T = se3_exp(xi[None] * dt[:, None])  # camera at t_i in the frame of t_ref
    moved = np.einsum("nij,nj->ni", T[:, :3, :3], points) + T[:, :3, 3]
    pixels = moved @ K.T
    np.testing.assert_allclose(xs.numpy(), pixels[:, 0] / pixels[:, 2], atol=1e-9)
    np.testing.assert_allclose(ys.numpy(), pixels[:, 1] / pixels[:, 2], atol=1e-9)


def test_batched_references_shape():
    rays = _rays(np.array([1.0, 2.0, 3.0]), np.array([4.0, 5.0, 6.0]))
    dt = torch.zeros(4, 3, dtype=torch.float64)
    x, y = warp_se3(rays, dt, torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64),
                    torch.ones(3, dtype=torch.float64), torch.from_numpy(K))
    assert x.shape == (4, 3)
    np.testing.assert_allclose(x[2].numpy(), [1.0, 2.0, 3.0], atol=1e-12)


def test_gradcheck_se3_warp_all_inputs():
    rng = np.random.default_rng(3)
    rays = _rays(rng.uniform(0, 120, 12), rng.uniform(0, 90, 12))
    dt = torch.from_numpy(rng.uniform(-0.1, 0.1, (2, 12)))
    v = torch.tensor([0.3, -0.1, 0.8], dtype=torch.float64, requires_grad=True)
    omega = torch.tensor([0.2, 0.4, -0.1], dtype=torch.float64, requires_grad=True)
    rho = torch.from_numpy(rng.uniform(0.2, 1.0, 12)).requires_grad_()
    Kt = torch.from_numpy(K)
    assert torch.autograd.gradcheck(lambda a, b, c: warp_se3(rays, dt, a, b, c, Kt), (v, omega, rho))
    assert torch.autograd.gradcheck(lambda b: warp_rotation(rays, dt, b, Kt), (omega,))


def test_depth_grid_interpolation_closed_form_and_upsample():
    grid = DepthGrid((2, 2), width=4, height=4)  # nodes at x, y = 0.5 and 2.5
    values = torch.tensor([[1.0, 3.0], [5.0, 7.0]], dtype=torch.float64)
    index, weight = grid.weights(torch.tensor([0.5, 1.5, 0.0, 3.0], dtype=torch.float64),
                                 torch.tensor([0.5, 0.5, 1.5, 3.0], dtype=torch.float64))
    np.testing.assert_allclose(DepthGrid.sample(values, index, weight).numpy(), [1.0, 2.0, 3.0, 7.0])
    assert torch.allclose(weight.sum(1), torch.ones(4, dtype=torch.float64))
    dense = grid.upsample(values.numpy())
    import cv2
    np.testing.assert_allclose(dense, cv2.resize(values.numpy(), (4, 4), interpolation=cv2.INTER_LINEAR), atol=1e-12)
    # Resampled at the nodes of a 4 x 4 grid (pixel centres 0..3): x = 0, 1, 2, 3 fall at node
    # coordinates -0.25 (held at node 0), 0.25, 0.75 and 1.25 (held at node 1).
    fine = grid.resample(torch.tensor([[0.0, 1.0], [0.0, 1.0]], dtype=torch.float64), (4, 4))
    np.testing.assert_allclose(fine.numpy().reshape(4, 4), np.tile([0.0, 0.25, 0.75, 1.0], (4, 1)), atol=1e-12)
    assert torch.equal(grid.resample(values, (2, 2)), values.reshape(-1))
    with pytest.raises(ValueError, match="depth_grid"):
        DepthGrid((0, 3), 4, 4)
    with pytest.raises(ValueError, match="finer"):
        DepthGrid((8, 3), 4, 4)


def test_upsample_weighs_the_pixels_once_per_grid_and_image_size(monkeypatch):
    """Was: every upsample computed the interpolation weights (H*W, 4) of all the pixels again (a fit upsamples its
    depth and its depth spread on one grid); now at most once per grid shape and image size, the maps still
    those of cv2.resize's bilinear interpolation, for any values and grid objects of that shape."""
    import cv2
    from conftest import counted_calls

    calls = counted_calls(monkeypatch, DepthGrid, "weights")
    rng = np.random.default_rng(5)
    for _ in range(3):
        values = rng.uniform(0.1, 2.0, (5, 7))
        dense = DepthGrid((5, 7), width=70, height=40).upsample(values)
        np.testing.assert_allclose(dense, cv2.resize(values, (70, 40), interpolation=cv2.INTER_LINEAR), atol=1e-9)
    assert len(calls) <= 1


def test_warp_events_preparation():
    events = random_events(500, seed=4)
    ev = WarpEvents.from_events(events, K, max_events=200, dither=False)
    assert len(ev) == 200 and ev.x.dtype == torch.float32
    assert float(ev.t[0]) >= 0 and np.all(np.diff(ev.t.numpy()) >= 0)
    np.testing.assert_allclose(ev.rays[:, 2].numpy(), 1.0)
    assert set(ev.polarity.unique().tolist()) <= {-1.0, 1.0}
    assert ev.dt((0.0, 1.0)).shape == (2, 200)
    dithered = WarpEvents.from_events(events, K, dither=True)
    offset = dithered.x.numpy() - events.x
    assert offset.min() >= -0.5 and offset.max() < 0.5 and np.abs(offset).mean() > 0.1
