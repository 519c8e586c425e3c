"""The contrast core runs where its batch lives: every objective on an :class:`EventWindows` on torch's ``meta``
device (tensors with shapes and no values, where any tensor made on the CPU by the objective meets the batch's and
fails, as it would on a GPU) gives its (B,) value and gradients there; the batch moves with ``to(device=)``."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from cmax.contrast import DepthMotion, EventWindows, SweepVote, WeightedSum
from benchmarks.synthetic_windows import make_window
from tests.test_contrast_objectives import OBJECTIVES

OBJECTIVES_AND_SUMS = {**OBJECTIVES, "weighted_sum": WeightedSum(((1.0, OBJECTIVES["global_contrast"]),
                                                                   (0.1, OBJECTIVES["collapse_guard"])))}


@pytest.fixture(scope="module")
def batch():
    """Two small windows, float64, on the CPU."""
    pairs = [(w.events, w.K) for w in (
        make_window("indoor_flying", 3, width=64, height=48, focal=48.0, duration_s=0.1, max_frames=30),
        make_window("slider", 2, width=64, height=48, focal=48.0, duration_s=0.1, max_frames=30))]
    return EventWindows.from_windows(pairs, dtype=torch.float64, max_events=2000).with_speed([0.5, np.nan])


@pytest.mark.parametrize("name", sorted(OBJECTIVES_AND_SUMS))
def test_every_objective_runs_on_the_batch_s_device(batch, name):
    meta = batch.to(device="meta")
    assert meta.device.type == "meta" and meta.window.device.type == "meta" and meta.speed.device.type == "meta"
    objective = OBJECTIVES_AND_SUMS[name]
    if isinstance(objective, SweepVote):   # its sweep picks each window's median under a mask: values, not shapes
        objective = dataclasses.replace(objective, scale=torch.ones(len(meta), dtype=torch.float64, device="meta"))
    rho = torch.full((2, 1, 4, 6), 0.5, dtype=torch.float64, device="meta", requires_grad=True)
    twist = torch.zeros(2, 6, dtype=torch.float64, device="meta", requires_grad=True)
    value = objective(meta, DepthMotion(rho, twist))
    assert value.shape == (2,) and value.device.type == "meta"
    value.sum().backward()
    assert rho.grad is not None and rho.grad.device.type == "meta"


def test_to_moves_and_casts_and_a_batch_split_over_devices_is_refused(batch):
    same = batch.to(device="cpu")
    assert torch.equal(same.x, batch.x) and torch.equal(same.window, batch.window) and same.dtype == torch.float64
    single = batch.to(torch.float32)
    assert single.dtype == torch.float32 and single.device == batch.device and single.window.dtype == torch.int64
    with pytest.raises(ValueError, match="one device"):
        EventWindows(batch.x.to("meta"), batch.y, batch.t, batch.polarity, batch.window, batch.K, batch.duration_s,
                     batch.width, batch.height)
