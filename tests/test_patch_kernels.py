"""The compiled per-patch variances (cmax.contrast._patch_kernels) against the torch reference
(accumulate_bilinear_indexed -> blur -> variance): values, gradients (gradcheck and the reference's
autograd), events on pixel borders and off the frame, the dispatch of cmax.contrast.patches, and a
real window's patch objectives on both paths."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import cmax.contrast.patches as patches_module
from cmax.contrast._patch_kernels import _PatchVariances, gaussian_taps, patch_variances
from cmax.contrast.patches import PatchFlowContrast, PatchMotionContrast, cut_patches
from cmax.iwe import _gaussian_kernel, accumulate_bilinear_indexed, blur
from cmax.objectives import variance

RTOL = {torch.float32: 1e-5, torch.float64: 1e-10}


def reference(x, y, patch, offset, size, sigma):
    """The torch path: the images of :meth:`cmax.contrast.Patches.images`, then their variances."""
    H, W = size
    ox, oy = offset[patch, 0], offset[patch, 1]
    return variance(blur(accumulate_bilinear_indexed(x - ox, y - oy, None, patch, offset.shape[0], H, W), sigma))


def random_events(n=600, P=3, size=(13, 17), seed=0, dtype=torch.float64, spill=3.0):
    """Events in P frames of ``size`` at random offsets, some ``spill`` px beyond each frame's border."""
    rng = np.random.default_rng(seed)
    H, W = size
    offset = torch.from_numpy(rng.uniform(-5, 40, (P, 2))).to(dtype)
    patch = torch.from_numpy(rng.integers(0, P, n))
    x = offset[patch, 0] + torch.from_numpy(rng.uniform(-spill, W + spill, n)).to(dtype)
    y = offset[patch, 1] + torch.from_numpy(rng.uniform(-spill, H + spill, n)).to(dtype)
    return x, y, patch, offset


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("sigma", [0.0, 0.7, 1.0, 3.0])
def test_values_equal_the_torch_reference(dtype, sigma):
    x, y, patch, offset = random_events(dtype=dtype)
    got = patch_variances(x, y, patch, offset, (13, 17), sigma)
    want = reference(x, y, patch, offset, (13, 17), sigma)
    assert got.dtype == dtype and got.shape == (3,)
    np.testing.assert_allclose(got.numpy(), want.numpy(), rtol=RTOL[dtype])


def test_a_hand_computed_image():
    """Two events at (1.5, 1) and (2, 1) in one 2 x 4 frame, no blur: row 1 is [0, 0.5, 1.5, 0],
    mean 2/8, mean square 2.5/8, variance 0.3125 - 0.0625 (the population variance)."""
    x, y = torch.tensor([1.5, 2.0], dtype=torch.float64), torch.tensor([1.0, 1.0], dtype=torch.float64)
    got = patch_variances(x, y, torch.tensor([0, 0]), torch.zeros(1, 2, dtype=torch.float64), (2, 4), 0.0)
    assert got.tolist() == [0.25]


def test_the_taps_are_the_blur_of_cmax_iwe():
    for sigma in (0.5, 1.0, 3.0):
        for dtype, torch_dtype in ((np.float32, torch.float32), (np.float64, torch.float64)):
            np.testing.assert_array_equal(gaussian_taps(sigma, dtype),
                                          _gaussian_kernel(sigma, torch_dtype, torch.device("cpu")).numpy())
    assert gaussian_taps(0.0, np.float32).tolist() == [1.0]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_events_on_pixel_borders_and_off_the_frame(dtype):
    """Integer coordinates (on pixel borders), the frame's edges -1, 0, W-1, W and beyond, and every
    combination in x and y: the same votes, variances and gradients as the torch path (which drops a
    corner off the frame, and a point whose corners all leave the one-pixel border)."""
    H, W = 5, 6
    xs = torch.tensor([-2.0, -1.5, -1.0, -0.5, 0.0, 0.5, 2.0, 4.5, 5.0, 5.5, 6.0, 6.5, 7.0], dtype=dtype)
    ys = torch.tensor([-1.25, -1.0, 0.0, 2.0, 3.75, 4.0, 4.5, 5.0, 5.25], dtype=dtype)
    x = xs.repeat_interleave(len(ys)) + 10.0
    y = ys.repeat(len(xs)) - 3.0
    patch = torch.zeros(len(x), dtype=torch.long)
    offset = torch.tensor([[10.0, -3.0]], dtype=dtype)
    for sigma in (0.0, 1.0):
        a_x, a_y = x.clone().requires_grad_(), y.clone().requires_grad_()
        got = patch_variances(a_x, a_y, patch, offset, (H, W), sigma)
        got.sum().backward()
        b_x, b_y = x.clone().requires_grad_(), y.clone().requires_grad_()
        want = reference(b_x, b_y, patch, offset, (H, W), sigma)
        want.sum().backward()
        np.testing.assert_allclose(got.detach().numpy(), want.detach().numpy(), rtol=RTOL[dtype])
        scale = float(b_x.grad.abs().max())
        np.testing.assert_allclose(a_x.grad.numpy(), b_x.grad.numpy(), atol=RTOL[dtype] * scale, rtol=0)
        np.testing.assert_allclose(a_y.grad.numpy(), b_y.grad.numpy(), atol=RTOL[dtype] * scale, rtol=0)
        off = ((x - 10.0) < -1) | ((x - 10.0) >= W) | ((y + 3.0) < -1) | ((y + 3.0) >= H)
        assert off.any() and torch.all(a_x.grad[off] == 0) and torch.all(a_y.grad[off] == 0)


def test_an_event_that_leaves_the_frame_stops_voting():
    """An event alone beyond the one-pixel border leaves an empty image (variance 0)."""
    x = torch.tensor([6.0, 7.5], dtype=torch.float64)
    y = torch.tensor([2.0, 2.0], dtype=torch.float64)
    got = patch_variances(x, y, torch.tensor([0, 1]), torch.zeros(2, 2, dtype=torch.float64), (5, 6), 1.0)
    assert got[0] == 0 and got[1] == 0


def test_a_non_finite_event_votes_nothing():
    x, y, patch, offset = random_events(n=30)
    bad_x, bad_y = x.clone(), y.clone()
    bad_x[3], bad_y[7], bad_x[9] = float("nan"), float("inf"), -float("inf")
    keep = torch.ones(30, dtype=torch.bool)
    keep[[3, 7, 9]] = False
    np.testing.assert_allclose(patch_variances(bad_x, bad_y, patch, offset, (13, 17), 1.0).numpy(),
                               reference(x[keep], y[keep], patch[keep], offset, (13, 17), 1.0).numpy(), rtol=1e-10)


def test_gradcheck_on_a_small_patch_set():
    x, y, patch, offset = random_events(n=40, P=3, size=(7, 8), seed=3, spill=1.5)
    x.requires_grad_(True)
    y.requires_grad_(True)
    for sigma in (0.0, 1.0):
        assert torch.autograd.gradcheck(lambda a, b: patch_variances(a, b, patch, offset, (7, 8), sigma), (x, y),
                                        eps=1e-6, atol=1e-7, rtol=1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gradients_equal_the_reference_autograd(dtype):
    """Weighted by a non-uniform upstream gradient (each patch's own), against torch's autograd."""
    x, y, patch, offset = random_events(n=2000, P=5, size=(20, 24), seed=1, dtype=dtype)
    weights = torch.linspace(-1.0, 2.0, 5, dtype=dtype)
    grads = []
    for function in (patch_variances, reference):
        a, b = x.clone().requires_grad_(), y.clone().requires_grad_()
        (function(a, b, patch, offset, (20, 24), 1.5) * weights).sum().backward()
        grads.append((a.grad, b.grad))
    for got, want in zip(*grads):
        np.testing.assert_allclose(got.numpy(), want.numpy(), atol=RTOL[dtype] * float(want.abs().max()) * 10, rtol=0)



@pytest.mark.parametrize("sigma", [1.0, 3.0])
def test_gradients_of_events_gathered_in_part_of_their_frames_equal_the_reference_autograd(sigma):
    """The backward blurs ``g * B`` only over the box of the events' votes (the pixels they read), not the whole
    frame: events gathered in a small part of large frames, some on and past the frames' borders, one patch whose
    events all lie off its frame (no votes, zero gradients), against torch's autograd of the whole images (float64,
    to 1e-12 of the largest gradient)."""
    rng = np.random.default_rng(7)
    size, P, n = (40, 50), 4, 3000
    offset = torch.tensor([[0.0, 0.0], [30.0, 5.0], [-4.0, 60.0], [100.0, 100.0]], dtype=torch.float64)
    patch = torch.from_numpy(rng.integers(0, P, n))
    core = {0: ((15, 22), (20, 30)), 1: ((-2, 6), (44, 52)), 2: ((30, 41), (-2, 4)), 3: ((-9, -3), (-9, -3))}
    rows = np.array([rng.uniform(*core[int(p)][0]) for p in patch])
    cols = np.array([rng.uniform(*core[int(p)][1]) for p in patch])
    x = offset[patch, 0] + torch.from_numpy(cols)
    y = offset[patch, 1] + torch.from_numpy(rows)
    weights = torch.tensor([1.0, -0.5, 2.0, 1.0], dtype=torch.float64)
    grads = []
    for function in (patch_variances, reference):
        a, b = x.clone().requires_grad_(), y.clone().requires_grad_()
        (function(a, b, patch, offset, size, sigma) * weights).sum().backward()
        grads.append((a.grad, b.grad))
    for got, want in zip(*grads):
        assert float(want.abs().max()) > 0
        np.testing.assert_allclose(got.numpy(), want.numpy(), atol=1e-12 * float(want.abs().max()), rtol=0)
    assert not grads[0][0][patch == 3].any() and not grads[0][1][patch == 3].any()

def test_only_the_coordinates_that_need_a_gradient_get_one():
    x, y, patch, offset = random_events(n=50)
    a = x.clone().requires_grad_()
    patch_variances(a, y, patch, offset, (13, 17), 1.0).sum().backward()
    assert a.grad is not None and a.grad.abs().sum() > 0 and y.grad is None


def test_the_public_function_refuses_bad_input():
    x, y, patch, offset = random_events(n=10)
    with pytest.raises(TypeError, match="float32 or float64"):
        patch_variances(x.long(), y, patch, offset, (13, 17), 1.0)
    with pytest.raises(ValueError, match="one shape"):
        patch_variances(x, y[:5], patch, offset, (13, 17), 1.0)
    with pytest.raises(ValueError, match="offset"):
        patch_variances(x, y, patch, offset[:, :1], (13, 17), 1.0)
    with pytest.raises(ValueError, match="size"):
        patch_variances(x, y, patch, offset, (0, 17), 1.0)
    with pytest.raises(ValueError, match="patch must lie"):
        patch_variances(x, y, patch + 3, offset, (13, 17), 1.0)


# ----------------------------------------------------------------------------------------------
# cmax.contrast.patches: dispatch and the fit's two objectives on a real window
# ----------------------------------------------------------------------------------------------
def test_cpu_floats_take_the_compiled_path_and_the_switch_restores_torch(monkeypatch):
    x, y, patch, offset = random_events(n=300, P=1, size=(40, 40), spill=0.0)
    patches = cut_patches(x, y, torch.zeros_like(x), 60, 60, grid=(1, 1), min_events=1, max_events=10_000, margin=0.1)
    calls = []
    original = _PatchVariances.apply
    monkeypatch.setattr(_PatchVariances, "apply", lambda *a: calls.append(1) or original(*a))
    compiled = patches.variances(patches.x, patches.y, 1.0)
    assert len(calls) == 1
    monkeypatch.setattr(patches_module, "_COMPILED", False)
    torch_path = patches.variances(patches.x, patches.y, 1.0)
    assert len(calls) == 1
    np.testing.assert_allclose(compiled.numpy(), torch_path.numpy(), rtol=1e-10)
    monkeypatch.setattr(patches_module, "_COMPILED", True)
    patches.variances(patches.x.to(torch.bfloat16), patches.y.to(torch.bfloat16), 0.0)  # not a CPU float: torch
    assert len(calls) == 1


@pytest.fixture(scope="module")
def window():
    from benchmarks.synthetic_windows import make_window
    from cmax.fitting.settings import FitSettings
    from cmax.fitting.window import Window

    w = make_window("indoor_flying", 100, width=160, height=120, focal=115.0)
    return w, Window.from_events(w.events, w.K, FitSettings())


def _both_paths(monkeypatch, make):
    """``make()`` on the compiled path, then on the torch path: a pair of results."""
    monkeypatch.setattr(patches_module, "_COMPILED", True)
    compiled = make()
    monkeypatch.setattr(patches_module, "_COMPILED", False)
    return compiled, make()


def test_the_refinement_objective_on_a_real_window(window, monkeypatch):
    """PatchMotionContrast (float32 events, the se3 warp) at the true motion and per-patch depths from the
    ground truth: values to float32 rounding, gradients in v, omega and rho as the reference's."""
    from cmax.fitting.patch_flow import make_patches

    w, fw = window
    r = fw.settings.refine
    patches = make_patches(fw, grid=r.grid, min_events=r.min_events, max_events=r.max_events, margin=r.margin,
                           min_margin_px=r.min_margin_px)
    assert patches.x.dtype == torch.float32 and patches.count >= 8
    v = torch.tensor(w.twist[:3], dtype=torch.float32)
    omega = torch.tensor(w.twist[3:], dtype=torch.float32)
    rho = torch.full((patches.count,), 0.4, dtype=torch.float32)

    def run():
        objective = PatchMotionContrast.build(patches, fw.ev.K, fw.settings.sigma)
        params = [v.clone().requires_grad_(), omega.clone().requires_grad_(), rho.clone().requires_grad_()]
        values = objective(params[0], params[1], params[2][patches.patch])
        values.sum().backward()
        return objective.base, values.detach(), [p.grad for p in params]

    (base_a, values_a, grads_a), (base_b, values_b, grads_b) = _both_paths(monkeypatch, run)
    np.testing.assert_allclose(base_a.numpy(), base_b.numpy(), rtol=1e-5)
    np.testing.assert_allclose(values_a.numpy(), values_b.numpy(), rtol=1e-5)
    for got, want in zip(grads_a, grads_b):
        np.testing.assert_allclose(got.numpy(), want.numpy(), atol=1e-4 * float(want.abs().max()), rtol=0)


def test_the_patch_flow_objective_on_a_real_window(window, monkeypatch):
    from cmax.fitting.patch_flow import make_patches

    w, fw = window
    f = fw.settings.patch_flow
    patches = make_patches(fw, grid=f.grid, min_events=f.min_events, max_events=f.max_events, margin=f.margin,
                           min_margin_px=f.min_margin_px)
    q0 = torch.from_numpy(np.random.default_rng(0).uniform(-3, 3, 2 * patches.count))

    def run():
        q = q0.clone().requires_grad_()
        value = PatchFlowContrast.build(patches, 3.0, fw.T)(q)
        value.backward()
        return value.detach(), q.grad

    (value_a, grad_a), (value_b, grad_b) = _both_paths(monkeypatch, run)
    np.testing.assert_allclose(float(value_a), float(value_b), rtol=1e-5)
    np.testing.assert_allclose(grad_a.numpy(), grad_b.numpy(), atol=1e-4 * float(grad_b.abs().max()), rtol=0)


# ----------------------------------------------------------------------------------------------
# The objectives' value and gradient without autograd (what the fit's solves call)
# ----------------------------------------------------------------------------------------------
def _autograd(loss, x: np.ndarray) -> tuple[float, np.ndarray]:
    p = torch.tensor(x, dtype=torch.float64, requires_grad=True)
    value = loss(p)
    (grad,) = torch.autograd.grad(value, p)
    return float(value.detach()), grad.numpy()


def _float64_patches():
    """Random float64 events cut into 2 x 3 patches of a 60 x 40 sensor, with times over 0.1 s."""
    rng = np.random.default_rng(4)
    x = torch.from_numpy(rng.uniform(0, 60, 3000))
    y = torch.from_numpy(rng.uniform(0, 40, 3000))
    dt = torch.from_numpy(rng.uniform(-0.05, 0.05, 3000))
    return cut_patches(x, y, dt, 60, 40, grid=(2, 3), min_events=10, max_events=10_000, margin=0.2)


@pytest.mark.parametrize("case", ["float32 window", "float64 events"])
def test_patch_flow_fun_and_grad_equals_autograd(window, case):
    """PatchFlowContrast.fun_and_grad (compiled, no autograd) against autograd through the same kernels
    at random displacements: float32 events to float32 rounding, float64 to 1e-10."""
    from cmax.fitting.patch_flow import make_patches

    if case == "float32 window":
        w, fw = window
        f = fw.settings.patch_flow
        patches = make_patches(fw, grid=f.grid, min_events=f.min_events, max_events=f.max_events, margin=f.margin,
                               min_margin_px=f.min_margin_px)
        T, tol = fw.T, 2e-5
    else:
        patches, T, tol = _float64_patches(), 0.1, 1e-10
    loss = PatchFlowContrast.build(patches, 1.0, T)
    assert patches.compiled
    for seed in range(3):
        q = np.random.default_rng(seed).uniform(-3, 3, 2 * patches.count)
        value, grad = loss.fun_and_grad(q)
        want_value, want_grad = _autograd(loss, q)
        assert value == pytest.approx(want_value, rel=tol)
        np.testing.assert_allclose(grad, want_grad, rtol=0, atol=10 * tol * np.abs(want_grad).max())


@pytest.mark.parametrize("unit_norm", [True, False])
@pytest.mark.parametrize("case", ["float32 window", "float64 events"])
def test_refinement_fun_and_grad_equals_autograd(window, unit_norm, case):
    """LocalMotionObjective.fun_and_grad chains the kernels' gradients through the refinement's parameters
    (direction normalised or not, omega and per-patch inverse depths scaled); it equals autograd of
    ``-sum(values(p))`` at points off the optimum."""
    from cmax.fitting.motion import LocalMotionObjective
    from cmax.fitting.patch_flow import make_patches

    w, fw = window
    if case == "float32 window":
        r = fw.settings.refine
        patches = make_patches(fw, grid=r.grid, min_events=r.min_events, max_events=r.max_events, margin=r.margin,
                               min_margin_px=r.min_margin_px)
        v, omega, tol = w.twist[:3], w.twist[3:], 2e-5
    else:
        patches, tol = _float64_patches(), 1e-10
        v, omega = np.array([0.3, -0.1, 0.4]), np.array([0.2, 0.1, -0.3])
    K = fw.ev.K.to(patches.x.dtype)      # the events' dtype
    speed = float(np.linalg.norm(v))
    objective = LocalMotionObjective(PatchMotionContrast.build(patches, K, fw.settings.sigma), speed,
                                     fw.T * fw.focal, speed * fw.T * fw.focal, unit_norm)
    rng = np.random.default_rng(2)
    for _ in range(3):
        tilted = v + rng.normal(0, 0.1, 3)
        p = objective.params(tilted, omega + rng.normal(0, 0.05, 3), rng.uniform(0.2, 0.8, patches.count))
        if not unit_norm:
            p[:3] *= 1.1     # off the sphere: the constraint's solvers see such points too
        value, grad = objective.fun_and_grad(p)
        want_value, want_grad = _autograd(lambda q: -objective.values(q).sum(), p)
        assert value == pytest.approx(want_value, rel=tol)
        np.testing.assert_allclose(grad, want_grad, rtol=0, atol=10 * tol * np.abs(want_grad).max())


def test_fun_and_grad_take_torch_s_autograd_when_the_kernels_are_off(window, monkeypatch):
    """With ``_COMPILED`` False the same methods differentiate the torch operations (the reference)."""
    from cmax.fitting.motion import LocalMotionObjective
    from cmax.fitting.patch_flow import make_patches

    w, fw = window
    r = fw.settings.refine
    patches = make_patches(fw, grid=r.grid, min_events=r.min_events, max_events=r.max_events, margin=r.margin,
                           min_margin_px=r.min_margin_px)
    objective = LocalMotionObjective.build(fw, patches, float(np.linalg.norm(w.twist[:3])))
    flow = PatchFlowContrast.build(patches, 1.0, fw.T)
    p = objective.params(w.twist[:3], w.twist[3:], np.full(patches.count, 0.4))
    q = np.random.default_rng(0).uniform(-2, 2, 2 * patches.count)
    compiled = objective.fun_and_grad(p), flow.fun_and_grad(q)
    monkeypatch.setattr(patches_module, "_COMPILED", False)
    assert not patches.compiled
    with pytest.raises(ValueError, match="Patches.compiled"):
        objective.contrast.sum_and_gradients(w.twist[:3], w.twist[3:], np.full(len(patches.x), 0.4))
    reference_ = objective.fun_and_grad(p), flow.fun_and_grad(q)
    for (value, grad), (want_value, want_grad) in zip(compiled, reference_):
        assert value == pytest.approx(want_value, rel=1e-5)
        np.testing.assert_allclose(grad, want_grad, rtol=0, atol=1e-3 * np.abs(want_grad).max())
