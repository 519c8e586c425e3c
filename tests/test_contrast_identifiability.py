"""The shared objective identifies depth and motion on small synthetic windows with exact ground truth.

The full measurement (every preset, two resolutions, held-out seeds, every
candidate objective) is ``benchmarks/objective_identifiability.py``; these are
its checks in small, on tuning seeds.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from benchmarks.objective_identifiability import descend as _descend
from cmax.contrast import SHARED_OBJECTIVE, DepthMotion, EventWindows, GlobalContrast, PlaneVote, SweepVote
from cmax.metrics import depth_metrics
from benchmarks.synthetic_windows import preset_window
from cmax.warp import DepthGrid

DTYPE = torch.float32


def _setup(preset: str, seed: int, width: int, height: int, near_far: tuple[float, float]):
    w = preset_window(preset, seed, width=width, height=height)
    batch = EventWindows.from_events(w.events, w.K, max_events=4000, dtype=DTYPE,
                                     speed=float(np.linalg.norm(w.twist[:3])))
    rho_range = (1.0 / near_far[1], 1.0 / near_far[0])
    finite = np.isfinite(w.depth)
    inverse = np.clip(np.where(finite, 1.0 / np.where(finite, w.depth, 1.0), 0.0), *rho_range)
    pixels = np.zeros((height, width), bool)
    pixels[np.rint(w.events.y).astype(int).clip(0, height - 1), np.rint(w.events.x).astype(int).clip(0, width - 1)] = True
    pixels &= finite & (w.depth >= near_far[0]) & (w.depth <= near_far[1])
    return w, batch, torch.tensor(inverse, dtype=DTYPE)[None, None], rho_range, pixels


@pytest.fixture(scope="module")
def slider():
    """A camera sliding before a poster wall and objects, 0.4-3 m (the preset's stated range)."""
    return _setup("slider", 3, 160, 120, (0.4, 3.0))


@pytest.fixture(scope="module")
def room():
    """An indoor_flying window (translation and rotation), 1-6.5 m."""
    return _setup("indoor_flying", 3, 96, 72, (1.0, 6.5))


def _constant(rho: float) -> torch.Tensor:
    return torch.full((1, 1, 1, 1), float(rho), dtype=DTYPE)


def _abs_rel(grid: torch.Tensor, w, pixels) -> float:
    h, g = grid.shape[-2:]
    dense = DepthGrid((h, g), w.depth.shape[1], w.depth.shape[0]).upsample(grid.reshape(h, g).double().numpy())
    return depth_metrics(1.0 / dense, w.depth, mask=pixels).abs_rel


def test_true_depth_beats_every_constant(slider):
    w, batch, truth, rho_range, _ = slider
    twist = torch.as_tensor(w.twist, dtype=DTYPE)[None]
    at_truth = float(SHARED_OBJECTIVE(batch, DepthMotion(truth, twist))[0])
    constants = [float(SHARED_OBJECTIVE(batch, DepthMotion(_constant(r), twist))[0])
                 for r in np.linspace(*rho_range, 12)]
    assert at_truth < min(constants)


def test_descent_from_the_truth_does_not_collapse(slider):
    """Gradient descent on a free 6 x 8 grid started at the true depth stays near it under the shared
    objective; the global contrast, from the same start, runs off to a much worse depth (the failure the
    shared objective replaces: the check can fail)."""
    w, batch, truth, rho_range, pixels = slider
    twist = torch.as_tensor(w.twist, dtype=DTYPE)[None]
    start = torch.nn.functional.adaptive_avg_pool2d(truth, (6, 8))
    before = _abs_rel(start, w, pixels)
    shared, _ = _descend(SHARED_OBJECTIVE, batch, twist, start, 20, rho_range)
    contrast, _ = _descend(GlobalContrast(), batch, twist, start, 20, rho_range)
    after, global_after = _abs_rel(shared, w, pixels), _abs_rel(contrast, w, pixels)
    assert after <= before + 0.08
    assert global_after > 2 * after


def _profiled(rho_range):
    """The plane vote with its depth-free motion term (``plane_vote_profile_tv`` of the benchmark)."""
    return PlaneVote(rho_range=rho_range, smoothness=0.003, motion_weight=2.0)


def _motion_losses(objective, fixture_values) -> dict[str, float]:
    """The objective's loss at the true motion and its alternatives, depth free (best constant, then a short
    descent on a 3 x 4 grid): the mirror v -> -v and, where the window rotates, omega -> -omega and
    omega_x <-> omega_y."""
    w, batch, _, rho_range, _ = fixture_values
    alternatives = {"true": w.twist, "mirror": np.r_[-w.twist[:3], w.twist[3:]]}
    if np.linalg.norm(w.twist[3:]) > 1e-3:
        alternatives |= {"omega_neg": np.r_[w.twist[:3], -w.twist[3:]],
                         "omega_swap": np.r_[w.twist[:3], w.twist[[4, 3, 5]]]}
    losses = {}
    for name, twist in alternatives.items():
        twist = torch.as_tensor(twist, dtype=DTYPE)[None]
        start = min(np.linspace(*rho_range, 12),
                    key=lambda r: float(objective(batch, DepthMotion(_constant(r), twist))[0]))
        losses[name] = _descend(objective, batch, twist, torch.full((1, 1, 3, 4), start, dtype=DTYPE),
                                12, rho_range)[1]
    return losses


@pytest.mark.parametrize("fixture", ["slider", "room"])
def test_true_motion_beats_mirror_and_rotation_swaps(fixture, request):
    """Under the shared objective, with depth free, the true motion scores below its mirror and, where the
    window rotates, below its rotation swaps."""
    losses = _motion_losses(SHARED_OBJECTIVE, request.getfixturevalue(fixture))
    assert min(losses, key=losses.get) == "true", losses


@pytest.mark.parametrize("fixture", ["slider", "room"])
def test_the_plane_vote_motion_term_sees_the_mirror(fixture, request):
    """The plane vote divides each event by its own peak, so its depth term cannot tell a motion from its
    mirror; with its depth-free motion term (motion_weight), depth free, the true motion beats the mirror
    v -> -v by a clear margin. The rotation swaps are near ties on the room window (measured: omega_swap
    0.05% below the truth), so they are not asserted (docs/contrast_objective.md)."""
    values = request.getfixturevalue(fixture)
    losses = _motion_losses(_profiled(values[3]), values)
    assert losses["true"] < losses["mirror"] - 0.05 * abs(losses["true"]), losses


def test_plane_vote_descent_from_the_truth_does_not_collapse(slider):
    """The plane vote reads each event in images that do not depend on the depth map: descent on a free
    per-pixel map from the true depth stays near it (measured 0.085 abs_rel), where the sweep's vote, read
    in the current depth map's own image (:class:`SweepVote`), runs off from the same start (0.54)."""
    w, batch, truth, rho_range, pixels = slider
    twist = torch.as_tensor(w.twist, dtype=DTYPE)[None]
    planes = PlaneVote(rho_range=rho_range, smoothness=0.003).with_motion(batch, twist)
    sweep = SweepVote(rho_range=rho_range).with_motion(batch, twist)
    plane_after = _abs_rel(_descend(planes, batch, twist, truth.clone(), 20, rho_range)[0], w, pixels)
    sweep_after = _abs_rel(_descend(sweep, batch, twist, truth.clone(), 20, rho_range)[0], w, pixels)
    assert plane_after <= 0.12, plane_after
    assert sweep_after > 3 * plane_after, (sweep_after, plane_after)


def test_plane_vote_truth_beats_every_constant_and_the_window_normaliser_sees_the_mirror(slider):
    """The true depth scores better than every constant depth (both normalisers); at the true depth the
    mirrored motion v -> -v scores worse with the window's normaliser, which keeps the images' contrast,
    and not with the per-event peak, which divides it away (what ``docs/contrast_objective.md`` reports)."""
    w, batch, truth, rho_range, _ = slider
    twist = torch.as_tensor(w.twist, dtype=DTYPE)[None]
    mirror = torch.as_tensor(np.r_[-w.twist[:3], w.twist[3:]], dtype=DTYPE)[None]
    for normaliser in ("event_peak", "window"):
        objective = PlaneVote(rho_range=rho_range, normaliser=normaliser).with_motion(batch, twist)
        at_truth = float(objective(batch, DepthMotion(truth, twist))[0])
        assert at_truth < min(float(objective(batch, DepthMotion(_constant(r), twist))[0])
                              for r in np.linspace(*rho_range, 12))
    window = PlaneVote(rho_range=rho_range, normaliser="window")
    assert float(window(batch, DepthMotion(truth, twist))[0]) < float(window(batch, DepthMotion(truth, mirror))[0])
