"""The compiled se3 warp of the patch refinement (cmax.contrast._warp_kernels) against cmax.warp.warp_se3."""
from __future__ import annotations

import pytest
import torch

from cmax.contrast import patches as patches_module
from cmax.contrast._warp_kernels import compiled_warp_applies, warp_se3_compiled
from cmax.warp import warp_se3


def _events(n: int, dtype: torch.dtype, seed: int = 0, *, skew: float = 0.3):
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[200.0, skew, 170.0], [0.0, 210.0, 130.0], [0.0, 0.0, 1.0]], dtype=dtype)
    px, py = torch.rand(n, generator=g, dtype=dtype) * 340, torch.rand(n, generator=g, dtype=dtype) * 260
    rays = torch.stack([px, py, torch.ones_like(px)], -1) @ torch.linalg.inv(K).T
    dt = (torch.rand(n, generator=g, dtype=dtype) - 0.5) * 0.16
    rho = torch.rand(n, generator=g, dtype=dtype) * 2
    return rays, dt, rho, K


def _both(rays, dt, v, omega, rho, K, weights):
    """Positions and the gradients of ``sum(wx x + wy y)`` in (v, omega, rho) from both warps."""
    out = []
    for warp in (warp_se3, warp_se3_compiled):
        params = [t.detach().clone().requires_grad_(True) for t in (v, omega, rho)]
        x, y = warp(rays, dt, *params, K)
        grads = torch.autograd.grad((x * weights[0] + y * weights[1]).sum(), params)
        out.append((x.detach(), y.detach(), grads))
    return out


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
@pytest.mark.parametrize("omega_scale", [0.0, 1e-3, 0.5, 5.0, 20.0])
# zero, the small-angle series, large angles; at 20 some events turn by more than 1 rad: sin and cos
def test_positions_and_gradients_equal_the_torch_warp(dtype, tol, omega_scale):
    rays, dt, rho, K = _events(3000, dtype)
    v = torch.tensor([0.3, -0.2, 1.5], dtype=dtype)
    omega = torch.tensor([0.7, -1.1, 0.4], dtype=dtype) * omega_scale
    g = torch.Generator().manual_seed(1)
    weights = (torch.randn(3000, generator=g, dtype=dtype), torch.randn(3000, generator=g, dtype=dtype))
    (x1, y1, a), (x2, y2, b) = _both(rays, dt, v, omega, rho, K, weights)
    assert x2.dtype == dtype and y2.dtype == dtype
    scale = float(max(x1.abs().max(), y1.abs().max()))
    assert float((x1 - x2).abs().max()) <= tol * scale and float((y1 - y2).abs().max()) <= tol * scale
    for p, q in zip(a, b):
        assert float((p - q).abs().max()) <= 10 * tol * float(p.abs().max())


def test_gradcheck():
    rays, dt, rho, K = _events(12, torch.float64, seed=3)
    for omega in (torch.tensor([1e-3, -2e-3, 5e-4]), torch.tensor([3.0, -2.0, 1.0])):
        params = (torch.tensor([0.3, -0.2, 1.5], dtype=torch.float64, requires_grad=True),
                  omega.to(torch.float64).requires_grad_(True), rho.clone().requires_grad_(True))
        assert torch.autograd.gradcheck(lambda v, w, r: warp_se3_compiled(rays, dt, v, w, r, K), params)


def test_a_point_behind_the_clamp_passes_no_depth_gradient():
    """A point pushed behind the camera is projected at the clamped depth, as the torch warp does."""
    rays, dt, rho, K = _events(50, torch.float64, seed=4)
    dt = dt.abs() + 0.05
    rho = torch.full_like(rho, 5.0)
    v = torch.tensor([0.0, 0.0, -6.0], dtype=torch.float64)    # z = 1 - 30 dt < 0 for dt > 1/30 s
    omega = torch.zeros(3, dtype=torch.float64)
    assert bool(((1.0 + rho * v[2] * dt) < 0.05).all())
    weights = (torch.ones(50, dtype=torch.float64), torch.ones(50, dtype=torch.float64))
    (x1, y1, a), (x2, y2, b) = _both(rays, dt, v, omega, rho, K, weights)
    assert torch.allclose(x1, x2, rtol=1e-12) and torch.allclose(y1, y2, rtol=1e-12)
    for p, q in zip(a, b):
        assert torch.allclose(p, q, rtol=1e-10, atol=1e-12)


def test_what_it_takes_and_refuses():
    rays, dt, rho, K = _events(10, torch.float32)
    v, omega = torch.zeros(3), torch.zeros(3)
    assert compiled_warp_applies(rays, dt, v, omega, rho)
    assert not compiled_warp_applies(rays, dt[None], v, omega, rho)                 # (B, N) times: torch
    assert not compiled_warp_applies(rays, dt.double(), v, omega, rho)              # mixed dtypes: torch
    assert not compiled_warp_applies(rays.half(), dt.half(), v, omega, rho.half())
    with pytest.raises(ValueError, match="warp_se3_compiled needs"):
        warp_se3_compiled(rays, dt[None], v, omega, rho, K)


def test_the_patch_refinement_takes_it_and_the_switch_turns_it_off(monkeypatch):
    calls = []
    real = patches_module.warp_se3_compiled
    monkeypatch.setattr(patches_module, "warp_se3_compiled", lambda *a: calls.append(1) or real(*a))
    rays, dt, rho, K = _events(400, torch.float32, seed=5)
    xy = rays @ K.T
    patches = patches_module.cut_patches(xy[:, 0], xy[:, 1], dt, 346, 260, grid=(2, 2), min_events=10,
                                         max_events=10_000, margin=0.3)
    contrast = patches_module.PatchMotionContrast.build(patches, K, 1.0)
    rho_events = torch.full((len(patches.x),), 0.5)
    v, omega = torch.tensor([0.3, 0.0, 1.0]), torch.tensor([0.1, -0.2, 0.05])
    compiled = contrast(v, omega, rho_events)
    assert calls
    monkeypatch.setattr(patches_module, "_COMPILED", False)
    reference = contrast(v, omega, rho_events)
    assert len(calls) == 1
    assert torch.allclose(compiled, reference, rtol=1e-4)


def test_depth_only_gradient_equals_the_torch_warp():
    """With the twist held (no gradient asked for it) the compiled backward skips the twist's terms; the
    inverse depths' gradient is the torch warp's."""
    rays, dt, rho, K = _events(500, torch.float64, seed=5)
    v = torch.tensor([0.3, -0.2, 1.5], dtype=torch.float64)
    omega = torch.tensor([0.7, -1.1, 0.4], dtype=torch.float64)
    grads = []
    for warp in (warp_se3, warp_se3_compiled):
        r = rho.clone().requires_grad_(True)
        x, y = warp(rays, dt, v, omega, r, K)
        grads.append(torch.autograd.grad((x - 2 * y).sum(), r)[0])
    assert torch.allclose(grads[0], grads[1], rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_sweep_s_projection_is_cmax_warp_project_bit_for_bit(dtype):
    """project_at_depth (one pass per depth candidate of the patch sweep) computes what
    ``project(rotated + rho * moved, K)`` computes, in the same dtype, to the last bit; a point behind
    the camera is clamped alike."""
    import numpy as np

    from cmax.contrast._warp_kernels import project_at_depth
    from cmax.warp import MIN_PROJECTED_DEPTH, project, se3_parts

    rays, dt, rho, K = _events(3000, dtype)
    v, omega = torch.tensor([0.3, -0.2, 1.4], dtype=dtype), torch.tensor([0.4, -0.3, 0.2], dtype=dtype)
    rotated, moved = se3_parts(rays, dt, v, omega)
    rho = rho.clone()
    rho[:5] = -50.0                                                    # far behind: z clamped
    want_x, want_y = project(rotated + rho[:, None] * moved, K)
    np_dtype = rotated.numpy().dtype
    x, y = np.empty(3000, np_dtype), np.empty(3000, np_dtype)
    project_at_depth(rotated.numpy(), moved.numpy(), rho.numpy(), K.numpy()[[0, 0, 0, 1, 1], [0, 1, 2, 1, 2]],
                     np_dtype.type(MIN_PROJECTED_DEPTH), x, y)
    np.testing.assert_array_equal(x, want_x.numpy())
    np.testing.assert_array_equal(y, want_y.numpy())


def _exact_series(s: float, first: int, derivative: bool) -> float:
    """``sum_j (-1)^j s^j / (2j + first)!`` (or its derivative in ``s``) in exact rational arithmetic, 30 terms
    (the omitted ones below 1e-70 for s <= 1), rounded once to float64."""
    from fractions import Fraction
    from math import factorial

    x, total = Fraction(s), Fraction(0)
    for j in range(30):
        c = Fraction((-1) ** j, factorial(2 * j + first))
        total += c * j * x ** (j - 1) if derivative and j else (0 if derivative else c * x ** j)
    return float(total)


def test_the_series_coefficients_equal_their_definitions():
    """A, B, C and their derivatives by the vectorised kernels' series (s <= 1) against their defining series
    summed exactly, and against sin / cos where those lose no digits to cancellation."""
    import math

    from cmax.contrast._warp_kernels import _SERIES_MAX_SQ, _series

    for s in [0.0, 1e-12, 1e-5, 1e-4, 2e-4, 1e-3, 0.01, 0.1, 0.37, 0.9, _SERIES_MAX_SQ]:
        want = [_exact_series(s, first, derivative) for derivative in (False, True) for first in (1, 2, 3)]
        for g, w in zip(_series(s), want):
            assert abs(g - w) <= 3e-16 * abs(w), (s, g, w)
    t = math.sqrt(0.9)
    A, B, C, dA, _, _ = _series(0.9)
    assert A == pytest.approx(math.sin(t) / t, rel=1e-15) and B == pytest.approx((1 - math.cos(t)) / 0.9, rel=1e-15)
    assert C == pytest.approx((t - math.sin(t)) / (0.9 * t), rel=1e-13)
    assert dA == pytest.approx((t * math.cos(t) - math.sin(t)) / (2 * 0.9 * t), rel=1e-13)


@pytest.mark.parametrize("omega_scale", [1e-3, 0.5, 20.0])
def test_the_rotation_warp_equals_cmax_warp_rotation(omega_scale):
    """warp_rotation_compiled (the rotation fit's warp: the se3 kernel with no translation) gives
    cmax.warp.warp_rotation's positions and omega-gradient for (R, N) and (N,) times; None where the
    kernel does not apply."""
    from cmax.contrast._warp_kernels import warp_rotation_compiled
    from cmax.warp import warp_rotation

    rays, dt, _, K = _events(3000, torch.float64)
    rows = torch.stack([dt, dt - 0.05, dt + 0.05])
    omega = torch.tensor([0.7, -1.1, 0.4], dtype=torch.float64) * omega_scale
    g = torch.Generator().manual_seed(2)
    weights = torch.randn(2, 3, 3000, generator=g, dtype=torch.float64)
    out = []
    for warp in (warp_rotation, warp_rotation_compiled):
        w = omega.clone().requires_grad_(True)
        x, y = warp(rays, rows, w, K)
        (grad,) = torch.autograd.grad((weights[0] * x + weights[1] * y).sum(), w)
        out.append((x.detach(), y.detach(), grad))
    (x1, y1, g1), (x2, y2, g2) = out
    assert x2.shape == (3, 3000)
    torch.testing.assert_close(x2, x1, rtol=0, atol=1e-9)
    torch.testing.assert_close(y2, y1, rtol=0, atol=1e-9)
    torch.testing.assert_close(g2, g1, rtol=1e-9, atol=1e-9 * float(g1.abs().max()))
    single = warp_rotation_compiled(rays, dt, omega, K)
    torch.testing.assert_close(single[0], x1[0], rtol=0, atol=1e-9)
    assert warp_rotation_compiled(rays.float(), dt, omega, K) is None          # dtypes differ: not taken
