"""cmax.contrast: the event batch, the objectives' batching, gradients, metric scale, and the shared loss."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cmax.contrast import (SHARED_OBJECTIVE, AverageTimestamp, CollapseGuard, CrossFit, DepthMotion, EventWindows,
                           GlobalContrast, LocalContrast, PlaneVote, SweepVote, VoteNormaliser, WeightedSum,
                           twist_at_speed)
from benchmarks.synthetic_windows import make_window

OBJECTIVES = {
    "average_timestamp": AverageTimestamp(),
    "average_timestamp_tv": AverageTimestamp(smoothness=0.01),
    "sweep_vote": SweepVote(rho_range=(0.2, 1.0), candidates=6),
    "plane_vote": PlaneVote(rho_range=(0.2, 1.0), planes=6),
    "plane_vote_window_tv": PlaneVote(rho_range=(0.2, 1.0), planes=6, normaliser="window", smoothness=0.01),
    "plane_vote_profile_tv": PlaneVote(rho_range=(0.2, 1.0), planes=6, smoothness=0.01, motion_weight=2.0,
                                       motion_cells=(2, 3)),
    "local_contrast": LocalContrast(cells=(2, 3), margin=3, smoothness=0.01),
    "global_contrast": GlobalContrast(),
    "collapse_guard": CollapseGuard(lattice=(3, 4)),
    "average_timestamp_tv_random": AverageTimestamp(smoothness=0.01, cross_fit=CrossFit("random")),
    "average_timestamp_pixels": AverageTimestamp(cross_fit=CrossFit("pixels")),
    "average_timestamp_multi_reference": AverageTimestamp(smoothness=0.01, references=(1.0, 0.5, 0.0)),
    **{f"{name}_{split}": kind(rho_range=(0.2, 1.0), cross_fit=CrossFit(split), **{size: 6})
       for name, kind, size in (("sweep_vote", SweepVote, "candidates"), ("plane_vote", PlaneVote, "planes"))
       for split in ("random", "pixels", "leave_one_out")},
}


@pytest.fixture(scope="module")
def windows():
    """Two small constant-twist windows (indoor room, sliding wall) with exact twists."""
    return [make_window("indoor_flying", 3, width=64, height=48, focal=48.0, duration_s=0.1, max_frames=30),
            make_window("slider", 2, width=64, height=48, focal=48.0, duration_s=0.1, max_frames=30)]


def _tiny(n: int = 24, seed: int = 0) -> tuple[EventWindows, DepthMotion]:
    """A few events in a 16 x 12 image, a 2 x 3 inverse-depth grid and a twist, float64."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, generator=g, dtype=torch.float64) * 10 + 3
    y = torch.rand(n, generator=g, dtype=torch.float64) * 6 + 3
    t = torch.sort(torch.rand(n, generator=g, dtype=torch.float64) * 0.1).values
    polarity = torch.where(torch.rand(n, generator=g) > 0.5, 1.0, -1.0).to(torch.float64)
    K = torch.tensor([[[12.0, 0, 7.5], [0, 12.0, 5.5], [0, 0, 1]]], dtype=torch.float64)
    batch = EventWindows(x, y, t, polarity, torch.zeros(n, dtype=torch.int64), K,
                         torch.tensor([0.1], dtype=torch.float64), 16, 12)
    rho = (0.3 + 0.4 * torch.rand(1, 1, 2, 3, generator=g, dtype=torch.float64)).requires_grad_(True)
    twist = torch.tensor([[0.8, -0.5, 0.3, 0.4, -0.3, 0.5]], dtype=torch.float64).requires_grad_(True)
    return batch, DepthMotion(rho, twist)


def test_event_windows_rejects_bad_input():
    batch, _ = _tiny()
    with pytest.raises(ValueError, match="one shape"):
        EventWindows(batch.x, batch.y[:-1], batch.t, batch.polarity, batch.window, batch.K, batch.duration_s, 16, 12)
    with pytest.raises(ValueError, match="window indices"):
        EventWindows(batch.x, batch.y, batch.t, batch.polarity, batch.window + 1, batch.K, batch.duration_s, 16, 12)
    with pytest.raises(ValueError, match="duration_s"):
        EventWindows(batch.x, batch.y, batch.t, batch.polarity, batch.window, batch.K, -batch.duration_s, 16, 12)
    with pytest.raises(TypeError, match="int64"):
        EventWindows(batch.x, batch.y, batch.t, batch.polarity, batch.window.int(), batch.K, batch.duration_s, 16, 12)
    # half precision (was: accepted, then "linalg.inv: Low precision dtypes not supported" inside an objective)
    with pytest.raises(TypeError, match=r"x must be a float32 or float64 tensor, got torch.float16"):
        EventWindows(batch.x.half(), batch.y.half(), batch.t.half(), batch.polarity.half(), batch.window, batch.K,
                     batch.duration_s, 16, 12)
    with pytest.raises(ValueError, match="speed"):
        batch.with_speed([-1.0])
    with pytest.raises(ValueError, match="twist"):
        DepthMotion(torch.ones(1, 1, 2, 2), torch.zeros(6))
    with pytest.raises(TypeError, match="EventWindows"):
        SHARED_OBJECTIVE("events", DepthMotion(torch.ones(1, 1, 2, 2), torch.zeros(1, 6)))
    with pytest.raises(ValueError, match="finer"):
        SHARED_OBJECTIVE(batch, DepthMotion(torch.ones(1, 1, 13, 2), torch.zeros(1, 6)))


@pytest.mark.parametrize("name", sorted(OBJECTIVES))
def test_batch_equals_windows_one_by_one(windows, name):
    """A batch of two windows gives each window the value it has alone."""
    objective = OBJECTIVES[name]
    pairs = [(w.events, w.K) for w in windows]
    both = EventWindows.from_windows(pairs, dtype=torch.float64, max_events=3000)
    rho = torch.rand(2, 1, 4, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 0.6 + 0.2
    twist = torch.as_tensor(np.stack([w.twist for w in windows]))
    batched = objective(both, DepthMotion(rho, twist))
    assert batched.shape == (2,)
    for b, pair in enumerate(pairs):
        alone = objective(EventWindows.from_windows([pair], dtype=torch.float64, max_events=3000),
                          DepthMotion(rho[b:b + 1], twist[b:b + 1]))
        assert float(batched[b]) == pytest.approx(float(alone[0]), rel=1e-9, abs=1e-12)


@pytest.mark.parametrize("name", sorted(OBJECTIVES))
def test_gradcheck(name):
    """Analytic gradients in inverse depth and twist match finite differences (float64, tiny input)."""
    batch, params = _tiny()
    objective = OBJECTIVES[name]
    if isinstance(objective, SweepVote):   # its normaliser is a no-gradient sweep: fix it for the check
        objective = objective.with_motion(batch, params.twist.detach())
    assert torch.autograd.gradcheck(lambda r, t: objective(batch, DepthMotion(r, t)),
                                    (params.inverse_depth, params.twist), eps=1e-6, atol=1e-5, rtol=1e-3)


def test_plane_vote_without_motion_is_minus_one_for_any_depth():
    """With a zero twist every plane's image is the unwarped one: each event's value is the same on every
    plane, so each vote is 1 (its own largest value), and the window's mean value over the window's mean
    is 1 too: the loss is -1 whatever the depth map."""
    batch, params = _tiny()
    still = torch.zeros(1, 6, dtype=torch.float64)
    for normaliser in VoteNormaliser:
        objective = PlaneVote(rho_range=(0.2, 1.0), planes=5, normaliser=normaliser)
        for rho in (params.inverse_depth.detach(), torch.full((1, 1, 1, 1), 0.9, dtype=torch.float64)):
            assert float(objective(batch, DepthMotion(rho, still))[0]) == pytest.approx(-1.0, rel=1e-12)


@pytest.mark.parametrize("cross_fit", [None, CrossFit("random"), CrossFit("leave_one_out")],
                         ids=["plain", "halves", "loo"])
def test_plane_vote_with_motion_fixes_the_planes_and_gives_the_same_values(cross_fit):
    batch, params = _tiny()
    objective = PlaneVote(rho_range=(0.2, 1.0), planes=6, smoothness=0.01, cross_fit=cross_fit)
    fixed = objective.with_motion(batch, params.twist)
    assert fixed.values[0].shape == (6, len(batch)) and not fixed.values[0].requires_grad
    torch.testing.assert_close(fixed(batch, params), objective(batch, params))
    with pytest.raises(ValueError, match="events"):
        fixed(EventWindows(batch.x[:-1], batch.y[:-1], batch.t[:-1], batch.polarity[:-1], batch.window[:-1],
                           batch.K, batch.duration_s, 16, 12), params)


def test_plane_vote_motion_term_does_not_depend_on_the_depth_map():
    """motion_weight adds the same number at every depth map of one motion (its cells' best planes), and a
    different one at another motion: it ranks motions and leaves a depth-only descent as it was."""
    batch, params = _tiny(n=200)
    plain = PlaneVote(rho_range=(0.2, 1.0), planes=6)
    profiled = PlaneVote(rho_range=(0.2, 1.0), planes=6, motion_weight=2.0, motion_cells=(2, 3))
    added = [float(profiled(batch, DepthMotion(rho, params.twist)) - plain(batch, DepthMotion(rho, params.twist)))
             for rho in (params.inverse_depth.detach(), torch.full((1, 1, 1, 1), 0.9, dtype=torch.float64))]
    assert added[0] == pytest.approx(added[1], rel=1e-12) and added[0] < 0
    other = params.twist.detach() * torch.tensor([[-1.0, 1, 1, 1, 1, 1]], dtype=torch.float64)
    rho = params.inverse_depth.detach()
    assert float(profiled(batch, DepthMotion(rho, other)) - plain(batch, DepthMotion(rho, other))) != \
        pytest.approx(added[0], rel=1e-6)
    fixed = profiled.with_motion(batch, params.twist.detach())
    torch.testing.assert_close(fixed(batch, params), profiled(batch, params))
    assert fixed.motion_term is not None and plain.with_motion(batch, params.twist.detach()).motion_term is None
    torch.testing.assert_close(fixed.motion_term, profiled.motion_profile(batch, *fixed.values[:2]))


def test_plane_values_equal_the_planes_one_by_one(windows):
    """All planes imaged at once equal each plane warped (warp_windows at a constant inverse depth) and imaged
    on its own, with the same events kept, for a batch of two windows."""
    from cmax.contrast.objectives import _inside, _own_image_values, warp_windows

    batch = EventWindows.from_windows([(w.events, w.K) for w in windows], dtype=torch.float64, max_events=3000)
    twist = torch.as_tensor(np.stack([w.twist for w in windows]))
    objective = PlaneVote(rho_range=(0.2, 1.0), planes=5)
    values, kept, _ = objective.plane_values(batch, twist)
    dt = (batch.t - objective.reference * batch.duration_s.to(torch.float64)[batch.window])[None]
    for c, rho in enumerate(objective.plane_inverse_depths()):
        x, y = warp_windows(batch, DepthMotion(torch.full((2, 1, 1, 1), float(rho), dtype=torch.float64), twist), dt)
        torch.testing.assert_close(values[c], _own_image_values(batch, x[0], y[0], objective.sigma), rtol=1e-12,
                                   atol=1e-12)
        assert not torch.any((kept > 0) & ~_inside(batch, x[0], y[0]))


def test_plane_vote_settings_are_checked():
    with pytest.raises(ValueError, match="rho_range"):
        PlaneVote(rho_range=(0.0, 1.0))
    with pytest.raises(ValueError, match="planes"):
        PlaneVote(planes=1)
    with pytest.raises(ValueError, match="normaliser must be one of"):
        PlaneVote(normaliser="median")
    with pytest.raises(ValueError, match="smoothness"):
        PlaneVote(smoothness=-1.0)
    with pytest.raises(ValueError, match="motion_weight"):
        PlaneVote(motion_weight=float("nan"))
    with pytest.raises(ValueError, match="motion_cells"):
        PlaneVote(motion_cells=(0, 3))
    assert PlaneVote(normaliser="window").normaliser is VoteNormaliser.WINDOW


def test_weighted_sum_is_the_weighted_sum():
    batch, params = _tiny()
    total = WeightedSum(((1.0, GlobalContrast()), (0.25, CollapseGuard())))(batch, params)
    expected = GlobalContrast()(batch, params) + 0.25 * CollapseGuard()(batch, params)
    torch.testing.assert_close(total, expected)


def test_known_speed_fixes_the_scale_of_v():
    """With the speed known, the objective depends on v's direction only; NaN (unknown) leaves v as given."""
    batch, params = _tiny()
    speed = float(params.twist.detach()[0, :3].norm())
    anchored = batch.with_speed([speed])
    longer = params.twist.detach() * torch.tensor([[3.0, 3.0, 3.0, 1, 1, 1]], dtype=torch.float64)
    same = SHARED_OBJECTIVE(anchored, DepthMotion(params.inverse_depth.detach(), longer))
    torch.testing.assert_close(same, SHARED_OBJECTIVE(batch, DepthMotion(params.inverse_depth.detach(),
                                                                         params.twist.detach())))
    assert float(SHARED_OBJECTIVE(batch, DepthMotion(params.inverse_depth.detach(), longer))) != pytest.approx(
        float(same))
    torch.testing.assert_close(twist_at_speed(longer, torch.tensor([float("nan")], dtype=torch.float64)), longer)


def test_average_timestamp_by_hand():
    """Two events of one polarity on one pixel, no motion: each reference's image has one active pixel whose
    average timestamp is the mean of the two weights; the loss is the sum of the two squares."""
    K = torch.eye(3, dtype=torch.float64)[None]
    batch = EventWindows(torch.tensor([2.0, 2.0], dtype=torch.float64), torch.tensor([3.0, 3.0], dtype=torch.float64),
                         torch.tensor([0.0, 0.1], dtype=torch.float64), torch.ones(2, dtype=torch.float64),
                         torch.zeros(2, dtype=torch.int64), K, torch.tensor([0.1], dtype=torch.float64), 6, 5)
    value = AverageTimestamp()(batch, DepthMotion(torch.zeros(1, 1, 1, 1, dtype=torch.float64),
                                                  torch.zeros(1, 6, dtype=torch.float64)))
    # forward weights tau = (0, 1): average 0.5; backward weights 1 - tau = (1, 0): average 0.5
    assert float(value) == pytest.approx(0.25 + 0.25)


def test_learned_loss_is_the_core_objective(windows):
    """learned's self-supervised loss is the shared objective object, to 1e-6, on one window."""
    from learned import losses
    from learned.train import contrast_objective

    assert contrast_objective(0.0) is SHARED_OBJECTIVE
    w = windows[0]
    batch = EventWindows.from_events(w.events, w.K, max_events=3000, speed=float(np.linalg.norm(w.twist[:3])))
    rho = torch.full((1, 1, 48, 64), 0.3)
    twist = torch.as_tensor(w.twist, dtype=torch.float32)[None]
    loss, _ = losses.student_loss(rho, twist, batch, teacher_inverse_depth=None)
    assert float(loss) == pytest.approx(float(SHARED_OBJECTIVE(batch, DepthMotion(rho, twist))[0]), abs=1e-6)


def test_the_identifiability_benchmark_fixes_the_planes_of_every_term_of_a_weighted_sum():
    """benchmarks.objective_identifiability's combined candidate (the shared objective plus a plane vote): its
    depth-only copy images the plane vote's planes once and gives the same values as the sum itself."""
    from benchmarks.objective_identifiability import _with_motion

    batch, params = _tiny()
    combined = WeightedSum(((1.0, AverageTimestamp(smoothness=0.003)),
                            (0.5, PlaneVote(rho_range=(0.2, 1.0), planes=6))))
    fixed = _with_motion(combined, batch, params.twist.detach())
    assert isinstance(fixed, WeightedSum) and fixed.terms[0][1] is combined.terms[0][1]
    assert fixed.terms[1][1].values is not None and fixed.terms[1][0] == 0.5
    torch.testing.assert_close(fixed(batch, params), combined(batch, params))


def _two_tiny() -> tuple[EventWindows, DepthMotion]:
    """Two windows of :func:`_tiny` (seeds 0 and 1) in one batch, their parameters stacked (no gradient)."""
    (a, pa), (b, pb) = _tiny(seed=0), _tiny(seed=1)
    batch = EventWindows(torch.cat([a.x, b.x]), torch.cat([a.y, b.y]), torch.cat([a.t, b.t]),
                         torch.cat([a.polarity, b.polarity]), torch.cat([a.window, b.window + 1]),
                         torch.cat([a.K, b.K]), torch.cat([a.duration_s, b.duration_s]), 16, 12)
    return batch, DepthMotion(torch.cat([pa.inverse_depth, pb.inverse_depth]).detach(),
                              torch.cat([pa.twist, pb.twist]).detach())


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "torch"])
@pytest.mark.parametrize("bad", ["twist_nan", "twist_inf", "depth_nan", "depth_inf"])
@pytest.mark.parametrize("name", sorted(OBJECTIVES))
def test_a_non_finite_parameter_scores_nan_for_its_window_only(name, bad, compiled, monkeypatch):
    """A NaN or infinite twist or inverse-depth node scores NaN for its window (was: 3e-6 from the compiled
    shared objective, near its minimum, or IndexError from the images), and the other window keeps its value."""
    monkeypatch.setattr("cmax.contrast.objectives._COMPILED", compiled)
    objective = OBJECTIVES[name]
    batch, params = _two_tiny()
    clean = objective(batch, params)
    twist, rho = params.twist.clone(), params.inverse_depth.clone()
    value = {"nan": float("nan"), "inf": float("inf")}[bad.split("_")[1]]
    if bad.startswith("twist"):
        twist[1, 3] = value
    else:
        rho[1, 0, 1, 2] = value
    scored = objective(batch, DepthMotion(rho.requires_grad_(True), twist.requires_grad_(True)))
    assert torch.isnan(scored[1])
    assert float(scored[0]) == pytest.approx(float(clean[0]), rel=1e-12, abs=1e-15)
    scored[0].backward()
    assert torch.isfinite(twist.grad).all() and torch.isfinite(rho.grad).all()


def test_event_windows_refuses_a_non_finite_or_singular_K():
    batch, _ = _tiny()
    with pytest.raises(ValueError, match="K must be finite"):
        EventWindows(batch.x, batch.y, batch.t, batch.polarity, batch.window, torch.full_like(batch.K, float("nan")),
                     batch.duration_s, 16, 12)
    with pytest.raises(ValueError, match="positive focal lengths"):
        EventWindows(batch.x, batch.y, batch.t, batch.polarity, batch.window, torch.zeros_like(batch.K),
                     batch.duration_s, 16, 12)


def test_shared_objective_differentiates_event_pixels_and_intrinsics_on_the_cpu():
    """The compiled CPU path gives the gradient in the events' pixels and in K that the torch path gives and
    finite differences confirm (was: zero for the pixels, none for K: the compiled warp has no gradient for
    the rays, so a batch whose pixels or K need one takes the torch warp)."""
    import cmax.contrast.objectives as objectives

    batch, params = _tiny(n=40, seed=3)
    params = DepthMotion(params.inverse_depth.detach(), params.twist.detach())

    def loss(x: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
        moved = EventWindows(x, batch.y, batch.t, batch.polarity, batch.window, K, batch.duration_s, 16, 12)
        return SHARED_OBJECTIVE(moved, params).sum()

    grads = {}
    for compiled in (True, False):
        objectives._COMPILED, saved = compiled, objectives._COMPILED
        try:
            x, K = batch.x.clone().requires_grad_(True), batch.K.clone().requires_grad_(True)
            grads[compiled] = torch.autograd.grad(loss(x, K), (x, K))
        finally:
            objectives._COMPILED = saved
    torch.testing.assert_close(grads[True][0], grads[False][0], rtol=1e-6, atol=1e-12)
    torch.testing.assert_close(grads[True][1], grads[False][1], rtol=1e-6, atol=1e-12)
    assert grads[True][0].abs().max() > 1e-4
    eps, step = 1e-6, torch.zeros_like(batch.K)
    step[0, 0, 0] = eps
    numeric = (loss(batch.x, batch.K + step) - loss(batch.x, batch.K - step)) / (2 * eps)
    assert float(grads[True][1][0, 0, 0]) == pytest.approx(float(numeric), rel=1e-4, abs=1e-9)


@pytest.mark.parametrize("make, match", [
    (lambda: AverageTimestamp(eps=0.0), r"AverageTimestamp: eps must be a finite number > 0, got 0.0"),
    (lambda: AverageTimestamp(eps=-1.0), r"eps must be a finite number > 0"),
    (lambda: AverageTimestamp(cross_fit=CrossFit("leave_one_out")),
     r"AverageTimestamp: cross_fit must be None or a CrossFit with split 'random' or 'pixels'"),
    (lambda: AverageTimestamp(cross_fit="random"), r"AverageTimestamp: cross_fit must be None or a CrossFit"),
    (lambda: AverageTimestamp(references=(0.5, 1.5)),
     r"AverageTimestamp: references must be a non-empty tuple of distinct numbers in \[0, 1\]"),
    (lambda: AverageTimestamp(references=()), r"AverageTimestamp: references must be a non-empty tuple"),
    (lambda: SweepVote(sigma=-1.0), r"SweepVote: sigma must be a finite number >= 0, got -1.0"),
    (lambda: SweepVote(reference=float("nan")), r"SweepVote: reference must be a finite number"),
    (lambda: SweepVote(candidates=2.5), r"SweepVote: candidates must be an integer >= 2, got 2.5"),
    (lambda: PlaneVote(planes=2.5), r"PlaneVote: planes must be an integer >= 2, got 2.5"),
    (lambda: PlaneVote(sigma=float("nan")), r"PlaneVote: sigma must be a finite number >= 0"),
    (lambda: SweepVote(cross_fit="random"), r"SweepVote: cross_fit must be None or a CrossFit"),
    (lambda: PlaneVote(cross_fit="pixels"), r"PlaneVote: cross_fit must be None or a CrossFit"),
    (lambda: LocalContrast(cells=(2.5, 3)), r"LocalContrast: cells \(rows, cols\) must be an integer >= 1, got 2.5"),
    (lambda: LocalContrast(margin=2.5), r"LocalContrast: margin must be an integer >= 0, got 2.5"),
    (lambda: LocalContrast(smoothness=float("nan")), r"LocalContrast: smoothness must be a finite number >= 0"),
    (lambda: GlobalContrast(references=(0.0, float("nan"))), r"GlobalContrast: references must be a finite number"),
    (lambda: GlobalContrast(sigma=-1.0), r"GlobalContrast: sigma must be a finite number >= 0"),
    (lambda: CollapseGuard(lattice=(1, 3)), r"CollapseGuard: lattice \(rows, cols\) must be an integer >= 2, got 1"),
    (lambda: CollapseGuard(times=(float("nan"),)), r"CollapseGuard: times must be a finite number"),
], ids=["at-eps-zero", "at-eps-negative", "at-cross-fit-loo", "at-cross-fit-str", "at-references",
        "at-references-empty", "sweep-sigma", "sweep-reference", "sweep-candidates", "plane-planes",
        "plane-sigma", "sweep-cross-fit-str", "plane-cross-fit-str", "local-cells", "local-margin", "local-smoothness", "global-references", "global-sigma",
        "guard-lattice", "guard-times"])
def test_objective_settings_are_refused_by_name(make, match):
    """Settings that gave a ZeroDivisionError (eps 0), an absurd loss (eps -1: 346), NaN (a NaN reference or
    smoothness, one row of collapse probes), IndexError / TypeError deep in torch (2.5 cells, margin 2.5), or
    a silently unblurred image (sigma -1) are refused when the objective is made, naming the setting."""
    with pytest.raises(ValueError, match=match):
        make()


def test_event_windows_take_a_camera_as_fit_does():
    """``EventWindows.from_events`` / ``from_windows`` take a :class:`cmax.Camera` as :func:`cmax.fit` does (was:
    ``TypeError: K must be a 3x3 matrix of numbers, got Camera(...)``). Through a lens they took each event at its
    nearest undistorted pixel and dithered it there; now each event is dithered over its SENSOR pixel with the
    fit's seeded subset and dither and mapped through the lens, unrounded: OpenCV's undistortPoints of the dithered
    sensor pixels, and the very positions the fit's window holds (:func:`cmax.fitting.polish.window_events`)."""
    import cv2

    import cmax
    from conftest import random_events
    from cmax.fitting import FitSettings
    from cmax.fitting.polish import window_events
    from cmax.fitting.window import SensorPixels, Window

    events = random_events(3000, width=64, height=48, seed=5)
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    distortion = np.array([-0.2, 0.05, 0.0, 0.0])
    camera = cmax.Camera(K, 64, 48, distortion=distortion)
    rounded = camera.undistort_events(events)
    kept = camera.undistorted_kept(events)
    assert len(rounded) == len(kept) < len(events)     # the barrel lens moves some corner events out of the image
    seed, n = 3, 1500
    batches = (EventWindows.from_events(events, camera, max_events=n, seed=seed, dtype=torch.float64),
               EventWindows.from_windows([(events, camera)], max_events=n, seed=seed, dtype=torch.float64))
    sensor = np.column_stack([events.x[kept], events.y[kept]]).astype(np.float64)
    keep = np.sort(np.random.default_rng(seed).choice(len(kept), n, replace=False))
    dithered = sensor[keep] + np.random.default_rng([seed, 1]).uniform(-0.5, 0.5, (n, 2))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    expected = cv2.undistortPoints(dithered.reshape(-1, 1, 2), K, distortion, P=camera.pinhole_K,
                                   criteria=criteria).reshape(-1, 2)
    fit_window = Window.from_events(rounded, camera.pinhole_K, FitSettings(max_events=n, seed=seed), (6, 8),
                                    SensorPixels(sensor, camera))
    fitted = window_events(fit_window, 1.0)
    for batch in batches:
        np.testing.assert_allclose(np.column_stack([batch.x.numpy(), batch.y.numpy()]), expected, atol=1e-6)
        torch.testing.assert_close(batch.x.float(), fitted.x.float(), rtol=0, atol=0)   # the fit's float32 ones
        torch.testing.assert_close(batch.y.float(), fitted.y.float(), rtol=0, atol=0)
        torch.testing.assert_close(batch.t.float(), fitted.t.float(), rtol=0, atol=0)
        torch.testing.assert_close(batch.K, torch.as_tensor(camera.pinhole_K)[None])
    old = EventWindows.from_events(rounded, camera.pinhole_K, max_events=n, seed=seed, dtype=torch.float64)
    assert float((batches[0].x - old.x).abs().max()) > 0.3          # no longer the rounded pixel's dither
    with pytest.raises(ValueError, match=r"pixels: not with a cmax.Camera with a lens"):
        EventWindows.from_events(events, camera, pixels=sensor)


def test_event_windows_of_a_pinhole_camera_or_a_K_are_unchanged():
    """A camera without a lens and a plain K give the events as before, bit for bit: the integer pixels with the
    seeded subset and dither of ``WarpEvents.from_events``."""
    import cmax
    from conftest import random_events
    from cmax.warp import WarpEvents

    events = random_events(3000, width=64, height=48, seed=5)
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    before = WarpEvents.from_events(events, K, max_events=1500, seed=3)
    for given in (K, cmax.Camera(K, 64, 48)):
        for batch in (EventWindows.from_events(events, given, max_events=1500, seed=3),
                      EventWindows.from_windows([(events, given)], max_events=1500, seed=3)):
            for name in ("x", "y", "t", "polarity"):
                assert torch.equal(getattr(batch, name), getattr(before, name)), name


@pytest.mark.parametrize("split", ["random", "pixels", "leave_one_out"])
def test_cross_fit_reads_each_event_in_an_image_without_its_fold(windows, split):
    """With a :class:`CrossFit`, each event's value on each plane is its value in the blurred image of the events
    of its window and polarity that are not in its fold (times ``folds / (folds - 1)``), or, leaving one out, of
    all the others: built here event by event with the public image functions."""
    from cmax.contrast import image_of_warped_events, sample_bilinear, warp_windows

    batch = EventWindows.from_windows([(w.events, w.K) for w in windows], dtype=torch.float64, max_events=150)
    twist = torch.as_tensor(np.stack([w.twist for w in windows]))
    cross_fit = CrossFit(split)
    objective = PlaneVote(rho_range=(0.2, 1.0), planes=3, cross_fit=cross_fit)
    values = objective.plane_values(batch, twist).values
    fold = cross_fit.fold(batch)
    if split == "pixels":   # the events of one pixel share their fold
        pixel = batch.y.floor().long() * batch.width + batch.x.floor().long()
        for p in pixel.unique():
            assert fold[pixel == p].unique().numel() == 1
    dt = (batch.t - objective.reference * batch.duration_s.to(torch.float64)[batch.window])[None]
    checked = 0
    for c, rho in enumerate(objective.plane_inverse_depths()):
        x, y = warp_windows(batch, DepthMotion(torch.full((2, 1, 1, 1), float(rho), dtype=torch.float64), twist),
                            dt)
        x, y = x[0], y[0]
        for i in range(0, len(batch), 7):
            same = (batch.window == batch.window[i]) & ((batch.polarity > 0) == (batch.polarity[i] > 0))
            others = same & (torch.arange(len(batch)) != i if fold is None else fold != fold[i])
            image = image_of_warped_events(x[others][None], y[others][None], height=batch.height,
                                           width=batch.width, sigma=objective.sigma)
            expected = float(sample_bilinear(image, x[i:i + 1][None], y[i:i + 1][None])[0, 0])
            if fold is not None:
                expected *= cross_fit.folds / (cross_fit.folds - 1)
            assert float(values[c, i]) == pytest.approx(expected, rel=1e-9, abs=1e-12)
            checked += expected > 0
    assert checked > 10


def test_cross_fit_settings_are_checked():
    with pytest.raises(ValueError, match=r"CrossFit: split must be one of \['random', 'pixels', 'leave_one_out'\]"):
        CrossFit("halves")
    with pytest.raises(ValueError, match=r"CrossFit: folds must be an integer >= 2, got 1"):
        CrossFit(folds=1)
    with pytest.raises(ValueError, match=r"CrossFit: block must be an integer >= 1, got 0"):
        CrossFit("pixels", block=0)


def test_cross_fit_random_deal_is_seeded_and_balanced(windows):
    """The random deal depends on the seed alone (not on the call), and puts about half the events in each fold."""
    batch = EventWindows.from_windows([(w.events, w.K) for w in windows], dtype=torch.float64, max_events=3000)
    first, again = CrossFit(seed=3).fold(batch), CrossFit(seed=3).fold(batch)
    assert torch.equal(first, again)
    assert not torch.equal(first, CrossFit(seed=4).fold(batch))
    for k in range(2):
        share = float(first[batch.window == k].double().mean())
        assert 0.45 < share < 0.55


def test_sweep_vote_with_motion_keeps_its_cross_fit():
    """The sweep vote's fixed normaliser (what the identifiability benchmark's depth-only descent uses) gives the
    cross-fitted objective's own values, not the plain one's."""
    batch, params = _tiny()
    objective = SweepVote(rho_range=(0.2, 1.0), candidates=6, cross_fit=CrossFit("leave_one_out"))
    fixed = objective.with_motion(batch, params.twist)
    torch.testing.assert_close(fixed(batch, params), objective(batch, params))
    plain = SweepVote(rho_range=(0.2, 1.0), candidates=6)
    assert abs(float(fixed(batch, params)[0]) - float(plain(batch, params)[0])) > 1e-3


def _average_timestamp_event_by_event(batch: EventWindows, params: DepthMotion, references: tuple[float, ...],
                                      fold: list[int] | None, folds: int) -> float:
    """The average-timestamp loss of one window built event by event (no smoothness): warped to each reference
    ``r T``, each event weighted by ``1 - |tau - r| / max(r, 1 - r)``, purged when a warp leaves the image, its
    bilinear shares voted pixel by pixel. Plain (``fold`` None): each pixel's average squared, over the pixels
    with a vote. Held out: each event of fold k contributes its share of fold k's votes times its weight times
    fold l's average there, over ordered pairs k != l, divided by their number, over the pixels where two folds
    vote in one polarity. The references' sum times ``2 / len(references)``."""
    from cmax.contrast import warp_windows

    T = float(batch.duration_s[0])
    tau = [float(t) / T for t in batch.t]
    dt = torch.stack([batch.t - r * T for r in references])
    with torch.no_grad():
        x, y = warp_windows(batch, params, dt)
    H, W, n = batch.height, batch.width, len(batch)
    kept = [all(-1e-3 <= float(x[r, i]) <= W - 1 + 1e-3 and -1e-3 <= float(y[r, i]) <= H - 1 + 1e-3
                for r in range(len(references))) for i in range(n)]
    assert 20 < sum(kept) < n                                       # some events purged, most kept
    fold = [0] * n if fold is None else fold
    expected = 0.0
    for r, reference in enumerate(references):
        votes = {}                                                  # (polarity, fold, pixel) -> [(event, vote)]
        for i in range(n):
            if not kept[i]:
                continue
            x0, y0 = math.floor(float(x[r, i])), math.floor(float(y[r, i]))
            fx, fy = float(x[r, i]) - x0, float(y[r, i]) - y0
            for u, v, share in ((x0, y0, (1 - fx) * (1 - fy)), (x0 + 1, y0, fx * (1 - fy)),
                                (x0, y0 + 1, (1 - fx) * fy), (x0 + 1, y0 + 1, fx * fy)):
                if 0 <= u < W and 0 <= v < H:
                    votes.setdefault((float(batch.polarity[i]) > 0, fold[i], (u, v)), []).append((i, share))
        weight = [1 - abs(tau[i] - reference) / max(reference, 1 - reference) for i in range(n)]
        count = {key: sum(s for _, s in vs) for key, vs in votes.items()}
        average = {key: sum(s * weight[i] for i, s in vs) / count[key] for key, vs in votes.items()}
        if folds == 1:
            total = sum(a * a for a in average.values())
            pixels = {pixel for (_, _, pixel) in votes}
        else:
            total = 0.0
            for (on, k, pixel), vs in votes.items():
                for i, share in vs:
                    for m in range(folds):
                        if m != k:
                            total += share / count[(on, k, pixel)] * weight[i] * average.get((on, m, pixel), 0.0)
            total /= folds * (folds - 1)
            pixels = {pixel for (on, k, pixel) in votes if sum((on, m, pixel) in votes for m in range(folds)) >= 2}
        assert len(pixels) > 5
        expected += total / len(pixels)
    return expected * 2 / len(references)


@pytest.mark.parametrize("split, folds, references", [
    ("random", 2, (1.0, 0.0)), ("pixels", 2, (1.0, 0.0)), ("random", 3, (1.0, 0.0)), (None, 1, (1.0, 0.5, 0.0)),
    ("random", 2, (0.25, 1.0, 0.0))])
def test_average_timestamp_cross_fitted_or_multi_reference_equals_an_event_by_event_construction(split, folds,
                                                                                                  references):
    """The held-out average timestamp (one fold's timestamps read against the others' per-pixel averages) and
    the multi-reference one equal :func:`_average_timestamp_event_by_event`."""
    batch, params = _tiny(80, seed=3)
    params = DepthMotion(params.inverse_depth.detach(), params.twist.detach() * 6)   # some events leave
    cross_fit = None if split is None else CrossFit(split, folds=folds)
    value = float(AverageTimestamp(cross_fit=cross_fit, references=references)(batch, params)[0])
    fold = None if cross_fit is None else cross_fit.fold(batch).tolist()
    expected = _average_timestamp_event_by_event(batch, params, references, fold, folds)
    assert value == pytest.approx(expected, rel=1e-7)


def test_multi_reference_average_timestamp_by_hand():
    """Three events of one polarity on one pixel at tau = 0, 0.5, 1, no motion: at the middle reference the
    weights are 0, 1, 0 (average 1/3), at the end 0, 0.5, 1 and at the start 1, 0.5, 0 (average 1/2); the sum over
    references is scaled by 2 / their number."""
    K = torch.eye(3, dtype=torch.float64)[None]
    batch = EventWindows(torch.full((3,), 2.0, dtype=torch.float64), torch.full((3,), 3.0, dtype=torch.float64),
                         torch.tensor([0.0, 0.05, 0.1], dtype=torch.float64), torch.ones(3, dtype=torch.float64),
                         torch.zeros(3, dtype=torch.int64), K, torch.tensor([0.1], dtype=torch.float64), 6, 5)
    params = DepthMotion(torch.zeros(1, 1, 1, 1, dtype=torch.float64), torch.zeros(1, 6, dtype=torch.float64))
    assert float(AverageTimestamp(references=(0.5,))(batch, params)[0]) == pytest.approx(2 / 9)
    assert float(AverageTimestamp(references=(1.0, 0.5, 0.0))(batch, params)[0]) == pytest.approx(
        (0.25 + 1 / 9 + 0.25) * 2 / 3)
    assert float(AverageTimestamp(references=(1.0, 0.0))(batch, params)[0]) == pytest.approx(0.5)


def test_cross_fitted_average_timestamp_by_hand():
    """Two events of one polarity on one pixel, in different folds, no motion: the plain loss squares each
    reference's average (0.5^2 + 0.5^2), the held-out one multiplies the two folds' averages, 0 x 1 and 1 x 0."""
    K = torch.eye(3, dtype=torch.float64)[None]
    batch = EventWindows(torch.tensor([2.0, 2.0], dtype=torch.float64), torch.tensor([3.0, 3.0], dtype=torch.float64),
                         torch.tensor([0.0, 0.1], dtype=torch.float64), torch.ones(2, dtype=torch.float64),
                         torch.zeros(2, dtype=torch.int64), K, torch.tensor([0.1], dtype=torch.float64), 6, 5)
    params = DepthMotion(torch.zeros(1, 1, 1, 1, dtype=torch.float64), torch.zeros(1, 6, dtype=torch.float64))
    cross_fit = next(CrossFit(seed=s) for s in range(20) if len(set(CrossFit(seed=s).fold(batch).tolist())) == 2)
    assert float(AverageTimestamp()(batch, params)[0]) == pytest.approx(0.5)
    assert float(AverageTimestamp(cross_fit=cross_fit)(batch, params)[0]) == pytest.approx(0.0, abs=1e-12)
    # one event alone: the plain loss scores its own weight squared (0^2 + 1^2), the held-out one has no pixel
    one = EventWindows(batch.x[1:], batch.y[1:], batch.t[1:], batch.polarity[1:], batch.window[1:], K,
                       batch.duration_s, 6, 5)
    assert float(AverageTimestamp()(one, params)[0]) == pytest.approx(1.0)
    assert float(AverageTimestamp(cross_fit=cross_fit)(one, params)[0]) == 0.0
