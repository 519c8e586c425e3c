"""cmax.fit: flow and rotation on synthetic windows, objective sanity, solvers, bad inputs, real data."""
from __future__ import annotations

import numpy as np
import pytest

from cmax.events import Events
from cmax.fit import FitResult, fit, fit_sequence
from cmax.synthetic_windows import make_window

SMALL = dict(width=120, height=90, focal=90.0)


@pytest.fixture(scope="module")
def slider():
    return make_window("slider", 101, duration_s=0.08, **SMALL)


@pytest.fixture(scope="module")
def rotation():
    return make_window("rotation", 102, duration_s=0.15, contrast_threshold=0.1, **SMALL)


def test_flow_fit_recovers_constant_flow(slider):
    r = fit(slider.events, slider.K, model="flow")
    assert isinstance(r, FitResult) and r.depth is None
    T = (r.t1_us - r.t0_us) * 1e-6
    assert np.linalg.norm((r.flow - slider.flow) * T) < 0.3  # endpoint error over the window [px]
    assert r.objective_after > r.objective_before
    assert r.iwe_after.shape == (90, 120) and r.t0_us <= r.t_ref_us <= r.t1_us


def test_rotation_fit_and_casadi_agree(rotation):
    r = fit(rotation.events, rotation.K, model="rotation")
    truth = rotation.twist[3:]
    assert np.linalg.norm(r.omega - truth) < 0.10 * np.linalg.norm(truth)  # 7% measured at 120x90
    c = fit(rotation.events, rotation.K, model="rotation", solver="casadi", iterations=30)
    assert c.objective_after == pytest.approx(r.objective_after, rel=0.01)
    np.testing.assert_allclose(r.T[:3, :3] @ r.T[:3, :3].T, np.eye(3), atol=1e-9)


@pytest.mark.xfail(strict=True, reason="known failure: on small 120x90 windows of 60 ms the normalised multi-reference "
                   "contrast + deformation guard does not yet rank the truth above zoom / no-motion "
                   "perturbations; see the report of issue 5")
@pytest.mark.parametrize("preset", ["slider", "rotation", "indoor_flying", "two_planes"])
def test_objective_sanity_truth_beats_perturbations(preset):
    """Normalised multi-reference contrast + guard: ground truth beats zoom, swaps, constant depth."""
    import torch

    from cmax.fit import FitSettings, _SE3, _Window
    from cmax.solvers import ScipySolver
    from cmax.warp import DepthGrid, WarpEvents

    w = make_window(preset, 7, duration_s=0.06, **SMALL)
    ev = WarpEvents.from_events(w.events, w.K, max_events=20000)
    win = _Window(ev, FitSettings(), ScipySolver(), DepthGrid((6, 8), 120, 90))
    speed = max(float(np.linalg.norm(w.twist[:3])), 1e-3)
    se3 = _SE3(win, speed, None)
    depth = np.nan_to_num(w.depth, nan=1e3)
    grid = np.array([[np.median(depth[i * 15:(i + 1) * 15, j * 15:(j + 1) * 15]) for j in range(8)] for i in range(6)])

    def loss(v, omega, inv_depth_grid):
        u = v / speed if np.linalg.norm(v) > 0 else np.array([0.0, 0.0, 1e-9])
        p = torch.tensor(np.r_[u, omega * se3.omega_scale, inv_depth_grid.ravel() * se3.q_scale])
        return float(se3.motion_loss(p))

    v, omega = w.twist[:3], w.twist[3:]
    truth = loss(v, omega, 1 / grid)
    rate = max(np.linalg.norm(omega), 0.2)
    perturbed = {
        "zoom": loss(np.array([0, 0, speed if speed > 1e-3 else 0.5]), omega, 1 / grid * (1 if speed > 1e-3 else 0) + (speed <= 1e-3) * 2.0),
        "rotation instead of translation": loss(v * 1e-6, omega + np.r_[0, 0.5 * rate, 0], 1 / grid),
        "constant depth": loss(v, omega, np.full_like(grid, np.median(1 / grid) * 2.0)),
        "no motion": loss(v * 1e-6, omega * 0, 1 / grid),
    }
    for name, value in perturbed.items():
        assert truth < value, f"{preset}: the truth ({truth:.4f}) does not beat '{name}' ({value:.4f})"


def test_fit_sequence_integrates_windows(slider):
    seq = fit_sequence(slider.events, slider.K, "flow", window_us=20_000, min_events=100)
    assert len(seq.results) >= 3 and seq.poses.shape == (len(seq.times_us), 4, 4)
    assert np.all(np.diff(seq.times_us) == 20_000)


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(model="affine"), ValueError, "model"),
    (dict(solver="newton"), ValueError, "solver"),
    (dict(K=np.zeros((3, 3))), ValueError, "focal"),
    (dict(K=np.eye(2)), ValueError, "3x3"),
    (dict(speed=-1.0), ValueError, "speed"),
    (dict(model="flow", speed=1.0), ValueError, "se3"),
    (dict(pose=np.zeros(5)), ValueError, "pose"),
    (dict(bogus=1), TypeError, "bogus"),
])
def test_bad_arguments(kwargs, error, match):
    events = Events(np.arange(20) % 10, np.arange(20) % 7, np.arange(20) * 100, np.ones(20), 12, 9)
    args = dict(K=np.array([[10.0, 0, 6], [0, 10.0, 4], [0, 0, 1]]), model="se3")
    args.update(kwargs)
    with pytest.raises(error, match=match):
        fit(events, **args)


def test_bad_windows():
    K = np.array([[10.0, 0, 6], [0, 10.0, 4], [0, 0, 1]])
    with pytest.raises(ValueError, match="at least 10"):
        fit(Events([], [], [], [], 12, 9), K)
    same = Events(np.arange(20) % 10, np.arange(20) % 7, np.full(20, 5), np.ones(20), 12, 9)
    with pytest.raises(ValueError, match="same timestamp"):
        fit(same, K)
    with pytest.raises(ValueError, match="no translation"):
        fit(Events(np.arange(20) % 10, np.arange(20) % 7, np.arange(20), np.ones(20), 12, 9), K, pose=np.zeros(6), depth_grid=(2, 2))
    with pytest.raises(TypeError, match="Events"):
        fit(np.zeros((10, 4)), K)


def test_one_polarity_window_is_fine(slider):
    events = slider.events
    keep = np.flatnonzero(events.p == 1)
    only_on = Events(events.x[keep], events.y[keep], events.t[keep], events.p[keep], events.width, events.height)
    r = fit(only_on, slider.K, model="flow")
    assert np.all(np.isfinite(r.flow))


def test_pegboard_rotation_is_slow_and_does_not_blur(shared_data):
    """Real DAVIS346 events: the fitted rotation is slow (the gyro says ~6 deg/s) and the IWE is not worse."""
    from cmax.io import read_aedat4, read_aedat4_imu

    path = shared_data / "davis346_pegboard" / "davis.aedat4"
    events, imu = read_aedat4(path), read_aedat4_imu(path)
    K = np.array([[245.0, 0, 172.5], [0, 245.0, 129.5], [0, 0, 1]])
    r = fit(events, K, model="rotation", max_events=20000)
    assert np.all(np.isfinite(r.omega))
    assert np.degrees(np.linalg.norm(r.omega)) < 2 * np.linalg.norm(imu.gyroscope.mean(0))
    assert r.objective_after >= 1.0
