"""``voxel_grid(normalization=...)``: the paper's B-1 time normalization and tonic's B, against closed forms."""
from __future__ import annotations

import numpy as np
import pytest

from cmax.events import Events
from cmax.representations import VoxelGrid, voxel_grid


def _closed_form(events: Events, bins: int, scale: int) -> np.ndarray:
    """Per event: t* = scale (t - t0) / (tN - t0); weight p (1 - frac) in floor(t*), p frac in floor(t*) + 1,
    each kept only inside [0, bins) (tonic's rule; for scale = B-1 nothing falls outside except t* = B-1 exactly,
    whose right weight is 0)."""
    grid = np.zeros((bins, events.height, events.width))
    t = events.t.astype(float)
    t_star = scale * (t - t[0]) / (t[-1] - t[0])
    for x, y, ts, p in zip(events.x, events.y, t_star, events.p):
        sign = 1.0 if p else -1.0
        low = int(np.floor(ts))
        frac = ts - low
        if low < bins:
            grid[low, y, x] += sign * (1 - frac)
        if low + 1 < bins:
            grid[low + 1, y, x] += sign * frac
    return grid


@pytest.fixture
def events() -> Events:
    rng = np.random.default_rng(4)
    n = 300
    return Events(rng.integers(0, 7, n), rng.integers(0, 5, n), np.sort(rng.integers(0, 10_000, n)),
                  rng.integers(0, 2, n), width=7, height=5)


@pytest.mark.parametrize("bins", [1, 2, 5])
def test_paper_normalization_is_b_minus_1(events, bins):
    expected = _closed_form(events, bins, max(bins - 1, 0)) if bins > 1 else None
    got = voxel_grid(events, bins)
    if bins == 1:  # t* = 0: the signed event frame
        signed = np.zeros((1, 5, 7))
        np.add.at(signed[0], (events.y, events.x), np.where(events.p == 1, 1.0, -1.0))
        expected = signed
    np.testing.assert_allclose(got, expected, atol=1e-5)
    # every event's weight is kept: the bins sum to the signed count
    assert got.sum() == pytest.approx(float(np.where(events.p == 1, 1, -1).sum()), abs=1e-3)


@pytest.mark.parametrize("bins", [1, 2, 5])
def test_tonic_normalization_is_b_and_drops_the_weight_past_the_last_bin(events, bins):
    got = voxel_grid(events, bins, normalization="tonic")
    np.testing.assert_allclose(got, _closed_form(events, bins, bins), atol=1e-5)
    # the same as the paper's volume with B+1 bins, cut to B: the last event (t* = B) is lost
    np.testing.assert_allclose(got, voxel_grid(events, bins + 1)[:bins], atol=1e-6)
    assert not got[:, events.y[-1], events.x[-1]].any() or len(np.flatnonzero(
        (events.x == events.x[-1]) & (events.y == events.y[-1]))) > 1


def test_tonic_normalization_on_torch_and_the_stored_settings(events):
    torch_grid = voxel_grid(events.to_torch(), 4, normalization="tonic")
    np.testing.assert_allclose(torch_grid.numpy(), voxel_grid(events, 4, normalization="tonic"), atol=1e-5)
    np.testing.assert_array_equal(VoxelGrid(4, "tonic")(events), voxel_grid(events, 4, normalization="tonic"))


def test_tonic_toVoxelGrid_when_installed(events):
    tonic = pytest.importorskip("tonic")
    structured = np.zeros(len(events), dtype=[("x", "<i8"), ("y", "<i8"), ("t", "<i8"), ("p", "<i8")])
    for name in "xytp":
        structured[name] = getattr(events, name)
    expected = tonic.transforms.ToVoxelGrid(sensor_size=(7, 5, 2), n_time_bins=5)(structured)[:, 0]
    np.testing.assert_allclose(voxel_grid(events, 5, normalization="tonic"), expected, atol=1e-5)


@pytest.mark.parametrize("value", ["B", None, "Tonic"])
def test_unknown_normalization_is_refused(events, value):
    with pytest.raises(ValueError, match="normalization must be one of"):
        voxel_grid(events, 5, normalization=value)
    with pytest.raises(ValueError, match="normalization must be one of"):
        VoxelGrid(5, value)
