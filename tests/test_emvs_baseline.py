"""EMVS without camera translation gives no depth, not a confident map at the near plane (issue 20)."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from cmax import Camera, Events
from cmax.emvs import EMVS, NoBaselineWarning
from cmax.geometry import se3_exp

W, H, F = 96, 72, 120.0


def _random_events(n=20_000, seed=0):
    rng = np.random.default_rng(seed)
    return Events(rng.integers(0, W, n), rng.integers(0, H, n), np.sort(rng.integers(0, 300_000, n)),
                  rng.integers(0, 2, n), W, H)


def _camera():
    return Camera.from_intrinsics(F, F, (W - 1) / 2, (H - 1) / 2, W, H)


def _trajectory(translation_m: float, rotation_rad: float):
    """Poses over 0.3 s: a slide along x of ``translation_m`` and a turn about y of ``rotation_rad``."""
    times = np.linspace(0, 300_000, 31).round().astype(np.int64)
    s = np.linspace(-0.5, 0.5, len(times))
    poses = np.stack([se3_exp(np.array([translation_m * a, 0, 0, 0, rotation_rad * a, 0])) for a in s])
    return times, poses


@pytest.mark.parametrize("translation, rotation", [(0.0, 0.0), (0.0, 0.3), (1e-4, 0.0)],
                         ids=["static", "pure-rotation", "0.1-mm"])
def test_no_translation_gives_no_depth_and_a_warning(translation, rotation):
    emvs = EMVS(_camera(), depth_range=(1.0, 4.0), n_planes=32)
    events = _random_events()
    with pytest.warns(NoBaselineWarning, match=r"depth cannot be resolved without camera motion"):
        result = emvs.run(events, _trajectory(translation, rotation))
    assert not result.mask.any() and np.isnan(result.depth).all() and result.points.shape == (0, 3)
    dsi = emvs.dsi(events, _trajectory(translation, rotation))
    # closed form: f * |t_x| * (1/near - 1/far), |t_x| at most half the slide
    assert dsi.parallax_px <= F * translation / 2 * (1.0 - 1.0 / 4.0) + 1e-9


def test_a_sliding_camera_has_the_parallax_of_its_baseline_and_no_warning():
    emvs = EMVS(_camera(), depth_range=(1.0, 4.0), n_planes=32)
    events = _random_events()
    trajectory = _trajectory(0.2, 0.0)
    dsi = emvs.dsi(events, trajectory)
    expected = F * 0.1 * (1.0 - 1.0 / 4.0)  # the packets farthest from the reference are ~0.1 m away
    assert dsi.parallax_px == pytest.approx(expected, rel=0.02)
    with warnings.catch_warnings():
        warnings.simplefilter("error", NoBaselineWarning)
        result = emvs.run(events, trajectory)
    assert result.mask.any()
