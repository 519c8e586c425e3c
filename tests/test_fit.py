"""cmax.fit: flow and rotation on synthetic windows, objective sanity, solvers, bad inputs, real data."""
from __future__ import annotations

import functools

import cv2
import numpy as np
import pytest

from cmax.events import Events
from cmax import FitResult, fit, fit_sequence
from benchmarks.synthetic_windows import make_window, preset_window

SMALL = dict(width=120, height=90, focal=90.0)
ABS_REL_SMALL = 0.25  # 120x90 (a third of the resolution: a third of the parallax); 0.17 measured
SE3_DIRECTION_SMALL_DEG = 25.0  # 16 deg measured at 120x90 (7.8 deg median at 346x260: see benchmarks/results)


@pytest.fixture(scope="module")
def slider():
    return make_window("slider", 101, duration_s=0.08, **SMALL)


@pytest.fixture(scope="module")
def rotation():
    return make_window("rotation", 102, duration_s=0.15, contrast_threshold=0.1, **SMALL)


def test_flow_fit_recovers_constant_flow(slider):
    r = fit(slider.events, slider.K, model="flow")
    assert isinstance(r, FitResult) and r.depth is None and r.depth_spread is None
    T = (r.t1_us - r.t0_us) * 1e-6
    assert np.linalg.norm((r.flow - slider.flow) * T) < 0.3  # endpoint error over the window [px]
    assert r.objective_after > r.objective_before
    assert r.iwe_after.shape == (90, 120) and r.t0_us <= r.t_ref_us <= r.t1_us


def test_parallax_of_a_slide_along_a_wall(slider):
    """Sliding parallel to a wall at depth Z: every event moves by f |v| T / Z through the translation."""
    r = fit(slider.events, slider.K, pose=slider.twist, depth_grid=(3, 4))
    T = (r.t1_us - r.t0_us) * 1e-6
    expected = slider.K[0, 0] * np.linalg.norm(slider.twist[:3]) * T / float(np.nanmedian(slider.depth))
    assert r.parallax_px == pytest.approx(expected, rel=0.1)
    assert fit(slider.events, slider.K, model="flow").parallax_px is None


def test_rotation_fit_and_casadi_agree(rotation):
    r = fit(rotation.events, rotation.K, model="rotation")
    truth = rotation.twist[3:]
    assert np.linalg.norm(r.omega - truth) < 0.10 * np.linalg.norm(truth)  # 7% measured at 120x90
    c = fit(rotation.events, rotation.K, model="rotation", solver="casadi", iterations=30)
    assert c.objective_after == pytest.approx(r.objective_after, rel=0.01)
    np.testing.assert_allclose(r.T[:3, :3] @ r.T[:3, :3].T, np.eye(3), atol=1e-9)


@functools.lru_cache(maxsize=None)
def _preset(preset: str, width: int, height: int, seed: int = 7):
    return preset_window(preset, seed, width=width, height=height, duration_s=0.1665, texture_size=128)


def _sanity(preset: str, width: int, height: int) -> None:
    """The objective of se3 (normalised multi-reference contrast + deformation guard) at the truth
    (per-event ground-truth inverse depth, the window's twist) beats zoom, a rotation in place of the
    translation (or a translation in place of the rotation), a constant depth and no motion."""
    import torch

    from cmax.fitting import FitSettings
    from cmax.fitting.window import SE3Model, Window

    w = _preset(preset, width, height)
    win = Window.from_events(w.events, w.K, FitSettings(max_events=60000), depth_grid=(6, 8))
    v, omega = w.twist[:3], w.twist[3:]
    speed = float(np.linalg.norm(v))
    se3 = SE3Model(win, max(speed, 1e-6))
    inverse = torch.from_numpy(1.0 / np.nan_to_num(w.depth.astype(np.float64), nan=np.inf))

    def at(x, y):
        return inverse[y.round().long().clamp(0, height - 1), x.round().long().clamp(0, width - 1)].reshape(-1)

    rho, rho_probes = at(win.ev.x, win.ev.y), at(se3.probes[0], se3.probes[1])

    def J(v, omega, r=rho, rp=rho_probes):
        return float(se3.objective(torch.as_tensor(v, dtype=torch.float64),
                                   torch.as_tensor(omega, dtype=torch.float64), r, rp))

    truth = J(v, omega)
    rate = max(np.linalg.norm(omega), np.radians(10))
    median = float(rho[rho > 0].median())
    const = lambda value: (torch.full_like(rho, value), torch.full_like(rho_probes, value))  # noqa: E731
    perturbed = {
        "zoom": J(np.array([0, 0, max(speed, 0.5)]), omega, *const(median)),
        "rotation instead of translation": J(v * 0, omega + np.r_[0, 0.5 * rate, 0]),
        "no motion": J(v * 0, omega * 0),
    }
    if speed > 1e-3:
        perturbed["constant depth"] = J(v, omega, *const(2 * median))
    else:  # pure rotation: depth is unobservable; swap the other way
        perturbed["translation instead of rotation"] = J(np.cross(omega, [0, 0, 1.0]) / median, omega * 0)
    for name, value in perturbed.items():
        assert truth < value, f"{preset}: the truth ({truth:.4f}) does not beat '{name}' ({value:.4f})"


@pytest.mark.parametrize("preset", ["indoor_flying", "rotation", "slider"])
def test_objective_sanity_small(preset):
    """120x90, 0.1665 s (the paper's window): enough parallax for the truth to win."""
    _sanity(preset, 120, 90)


@pytest.mark.slow
@pytest.mark.parametrize("preset", ["indoor_flying", "driving_day", "driving_night", "hiking", "rotation", "slider"])
def test_objective_sanity_every_preset(preset):
    """Every preset at 173x130, 0.1665 s (driving takes about 2 minutes to simulate)."""
    _sanity(preset, 173, 130)


def test_depth_with_known_pose_indoor_flying():
    w = _preset("indoor_flying", 120, 90)
    r = fit(w.events, w.K, pose=w.T01)
    assert r.depth.shape == (90, 120) and r.scale_known and r.t0_us <= r.t_ref_us <= r.t1_us
    valid = r.mask & np.isfinite(w.depth)
    assert valid.sum() > 0.2 * valid.size and np.all(np.isfinite(r.depth))
    abs_rel = float(np.mean(np.abs(r.depth[valid] - w.depth[valid]) / w.depth[valid]))
    assert abs_rel < ABS_REL_SMALL, abs_rel
    # the depth spread ranks the errors: the half of the mask with the smaller spread is the better half
    assert r.depth_spread.shape == (90, 120) and np.all(r.depth_spread >= 0)
    error = np.abs(r.depth[valid] - w.depth[valid]) / w.depth[valid]
    order = np.argsort(r.depth_spread[valid], kind="stable")
    low, high = error[order[: len(order) // 2]].mean(), error[order[len(order) // 2:]].mean()
    assert low < 0.8 * high, (low, high)


def test_depth_spread_of_a_step_is_its_log_ratio_next_to_it_and_zero_away():
    from cmax.fitting.api import depth_spread
    from cmax.warp import DepthGrid

    grid = DepthGrid((4, 6), 60, 40)                     # nodes at x = 10 j + 4.5, y = 10 i + 4.5
    rho = np.where(np.arange(6) < 3, 0.5, 0.25)[None].repeat(4, 0)      # 2 m | 4 m between columns 2 and 3
    spread = depth_spread(rho, grid)
    assert spread.shape == (40, 60) and spread.dtype == np.float32
    np.testing.assert_allclose(spread[:, :15], 0.0, atol=1e-7)          # up to node column 1: one depth around
    np.testing.assert_allclose(spread[:, 25:35], np.log(2.0), rtol=1e-6)  # between the nodes next to the step
    np.testing.assert_allclose(spread[:, 45:], 0.0, atol=1e-7)
    np.testing.assert_allclose(depth_spread(np.full((4, 6), 0.3), grid), 0.0, atol=1e-7)


def test_event_pixels_rounds_to_the_nearest_pixel_and_leaves_out_points_outside():
    from cmax.fitting.api import event_pixels

    x = np.array([0.4, 2.6, 2.4, -0.6, 4.49, 1.0, 3.0])
    y = np.array([0.0, 1.4, 1.6, 0.0, 2.0, 2.51, -0.51])
    pixels = event_pixels(x, y, 3, 5)
    expected = np.zeros((3, 5), bool)
    expected[0, 0] = expected[1, 3] = expected[2, 2] = expected[2, 4] = True   # (-0.6, 0), (1, 2.51), (3, -0.51): out
    np.testing.assert_array_equal(pixels, expected)


def test_se3_with_known_speed_indoor_flying():
    """Motion and depth together (120x90: a coarse check; the 346x260 figures are in benchmarks/results)."""
    w = _preset("indoor_flying", 120, 90)
    v, omega = w.twist[:3], w.twist[3:]
    r = fit(w.events, w.K, speed=float(np.linalg.norm(v)))
    assert r.scale_known and np.linalg.norm(r.v) == pytest.approx(np.linalg.norm(v))
    assert np.all(np.isfinite(r.depth)) and r.mask.any()
    angle = np.degrees(np.arccos(np.clip(r.v @ v / np.linalg.norm(v) ** 2, -1, 1)))
    assert angle < SE3_DIRECTION_SMALL_DEG, angle
    assert np.degrees(np.sqrt(np.mean((r.omega - omega) ** 2))) < 5.0
    assert r.objective_after > 1.0


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
    (dict(omega=np.zeros(2)), ValueError, "omega must be an angular velocity"),
    (dict(omega=[0.0, np.nan, 0.0]), ValueError, "omega must be finite"),
    (dict(omega="fast"), ValueError, "omega must be 3 numbers"),
    (dict(pose=np.zeros(6), omega=np.zeros(3)), ValueError, "pose or omega"),
    (dict(model="rotation", omega=np.zeros(3)), ValueError, "se3"),
    (dict(bogus=1), TypeError, "bogus"),
    (dict(motion_init="random"), ValueError, "motion_init"),
    (dict(zero_rotation_start="yes"), TypeError, "zero_rotation_start"),
    (dict(polarity_split=1), TypeError, "polarity_split"),
    (dict(K=np.array([[10.0, 0, 60], [0, 10.0, 4], [0, 0, 1]])), ValueError, "principal point"),
    (dict(K=np.array([[20.0, 0, 12], [0, 20.0, 9], [0, 0, 1]])), ValueError, "outside the 12x9 image"),
])
def test_bad_arguments(kwargs, error, match):
    events = Events(np.arange(20) % 10, np.arange(20) % 7, np.arange(20) * 100, np.ones(20), 12, 9)
    args = dict(K=np.array([[10.0, 0, 6], [0, 10.0, 4], [0, 0, 1]]), model="se3")
    args.update(kwargs)
    with pytest.raises(error, match=match):
        fit(events, **args)


def test_a_non_finite_init_and_window_lengths_in_other_units_are_refused(slider):
    """A warm start must be a motion (NaN / inf refused before any fit); fit_sequence's lengths are integer
    microseconds (a float of seconds, or True, refused; a float holding whole microseconds is taken)."""
    import dataclasses

    events, K = slider.events, slider.K
    start = fit(events, K, model="flow")
    for field, value in (("flow", np.array([np.nan, 0.0])), ("flow", np.array([np.inf, 0.0]))):
        with pytest.raises(ValueError, match="non-finite motion"):
            fit(events, K, model="flow", init=dataclasses.replace(start, **{field: value}))
    with pytest.raises(ValueError, match="whole microseconds"):
        fit_sequence(events, K, model="flow", window_us=0.09)
    with pytest.raises(TypeError, match="integer microseconds"):
        fit_sequence(events, K, model="flow", window_us=True)
    span = int(events.t[-1] - events.t[0])
    assert len(fit_sequence(events, K, model="flow", window_us=float(span)).results) == 1


def test_depth_pinned_to_an_end_of_depth_range_is_a_bound_failure(slider):
    """The slider window's wall lies at 3.9 m: a range that stops at 0.3 m pins the depth to its far end (the
    sweep reports it, BoundWarning, success False); a range that holds it does not."""
    from cmax.fitting import BoundWarning

    pose = slider.twist
    with pytest.warns(BoundWarning, match="far end"):
        pinned = fit(slider.events, slider.K, pose=pose, depth_range=(0.1, 0.3))
    sweep = [log for log in pinned.stages if log.stage == "depth_sweep"][0]
    assert sweep.at_bound == ("depth_far",) and not sweep.success and not pinned.success
    assert np.median(pinned.depth[pinned.mask]) == pytest.approx(0.3, rel=0.05)
    free = fit(slider.events, slider.K, pose=pose, depth_range=(0.1, 20.0))
    assert free.success and all(not log.at_bound for log in free.stages)


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


def _edge_points(rng, width, height, points):
    """Pixel positions (points, 2) of the edges of :func:`_approaching_plane` at the window's middle."""
    return rng.uniform([5, 5], [width - 5, height - 5], (points, 2))


def _approaching_plane(depth_ref=2.0, vz=4.0, duration=0.2, width=120, height=90, f=90.0, points=500,
                       per_point=40, seed=0):
    """Events of edges on a fronto-parallel plane the camera flies toward at ``vz`` [m/s], ON only.

    The plane is at ``depth_ref`` at the window's middle, so at ``depth_ref + vz T / 2`` at the first
    event and ``depth_ref - vz T / 2`` at the last; an edge at pixel ``p`` at the middle is at
    ``c + (p - c) Z_ref / Z(t)`` at time ``t`` (closed form of a pure forward motion).
    """
    rng = np.random.default_rng(seed)
    cx, cy = (width - 1) / 2, (height - 1) / 2
    edges = _edge_points(rng, width, height, points)
    t = np.sort(rng.uniform(0, duration, (points, per_point)), axis=1)
    t[0, 0], t[0, -1] = 0.0, duration
    scale = depth_ref / (depth_ref - vz * (t - duration / 2))
    x, y = cx + (edges[:, :1] - cx) * scale, cy + (edges[:, 1:] - cy) * scale
    inside = (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)
    order = np.argsort(t[inside], kind="stable")
    x, y = np.round(x[inside][order]).astype(int), np.round(y[inside][order]).astype(int)
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1]])
    return Events(x, y, np.round(t[inside][order] * 1e6).astype(np.int64), np.ones(len(x), int), width, height), K


def test_depth_belongs_to_the_reference_time():
    """Flying at 4 m/s toward a wall 2 m away at mid-window: the depth map is the one at ``t_ref_us``
    (2 m), not at the first event (2.4 m) or the last (1.6 m)."""
    events, K = _approaching_plane()
    r = fit(events, K, pose=np.r_[0, 0, 4.0, 0, 0, 0], depth_grid=(6, 8))
    assert r.t_ref_us == (r.t0_us + r.t1_us) // 2 == 100_000
    assert np.all(np.isfinite(r.depth))
    # the mask is the event pixels of the reference view: the edges where they are at t_ref
    edges = _edge_points(np.random.default_rng(0), 120, 90, 500)         # the first draw of _approaching_plane()
    at_ref = np.zeros_like(r.mask)
    at_ref[np.rint(edges[:, 1]).astype(int), np.rint(edges[:, 0]).astype(int)] = True
    near_ref = cv2.dilate(at_ref.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    # on the edges at t_ref (0.90 measured; 0.47 of the pixels the events were recorded at)...
    assert (r.mask & near_ref).sum() > 0.8 * r.mask.sum()
    assert (r.mask & at_ref).sum() > 0.9 * at_ref.sum()          # ...and on nearly all of them (1.0)
    median = float(np.median(r.depth[r.mask]))
    assert median == pytest.approx(2.0, rel=0.06), median  # 2.06 measured
    assert abs(median - 2.0) < 0.3 * min(abs(median - 2.4), abs(median - 1.6))


def test_low_parallax_warns_and_enough_parallax_does_not():
    """A window whose translation moves the events by a fraction of a pixel gets a LowParallaxWarning
    (the depth is poorly constrained); the same scene flown through fast enough does not."""
    import warnings

    from cmax import LowParallaxWarning

    events, K = _approaching_plane(vz=0.1)             # 2 cm over the window: edges move under 0.5 px
    with pytest.warns(LowParallaxWarning, match="the depth is poorly constrained"):
        slow = fit(events, K, pose=np.r_[0, 0, 0.1, 0, 0, 0], depth_grid=(6, 8))
    assert slow.parallax_px < 1.0
    events, K = _approaching_plane()                   # 4 m/s: the edges move by several px
    with warnings.catch_warnings():
        warnings.simplefilter("error", LowParallaxWarning)
        fast = fit(events, K, pose=np.r_[0, 0, 4.0, 0, 0, 0], depth_grid=(6, 8))
    assert fast.parallax_px > 1.0


def test_one_polarity_se3_window_gives_finite_depth():
    """A window of ON events only (the IWE counts events, polarity is not needed): finite depth
    everywhere, the unsupported pixels outside the mask, never NaN."""
    events, K = _approaching_plane(width=80, height=60, f=60.0, points=200, per_point=20)
    r = fit(events, K, speed=4.0, depth_grid=(3, 4))
    assert np.all(np.isfinite(r.depth)) and r.depth.min() > 0 and r.mask.any()
    assert np.all(np.isfinite(r.v)) and np.all(np.isfinite(r.omega))


def test_events_in_one_corner_leave_the_rest_outside_the_mask():
    """Cells without events get a depth borrowed from their neighbours (finite) but are not in the mask."""
    events, K = _approaching_plane()
    corner = np.flatnonzero((events.x < 40) & (events.y < 30))
    sub = Events(events.x[corner], events.y[corner], events.t[corner], events.p[corner], events.width, events.height)
    r = fit(sub, K, pose=np.r_[0, 0, 4.0, 0, 0, 0], depth_grid=(6, 8))
    assert np.all(np.isfinite(r.depth))
    assert r.mask[45:, 60:].sum() == 0 and r.mask[:30, :40].any()


@pytest.mark.parametrize("K, match", [
    (np.zeros((3, 3)), "focal"),
    (np.array([[10.0, 0, 6], [0, 10.0, 4], [0, 0, 0]]), "form"),
    (np.diag([1e-7, 1e-7, 1.0]), "invertible"),
    (np.array([[np.nan, 0, 6], [0, 10.0, 4], [0, 0, 1]]), "finite"),
])
def test_singular_or_bad_K(K, match):
    events = Events(np.arange(20) % 10, np.arange(20) % 7, np.arange(20) * 100, np.ones(20), 12, 9)
    with pytest.raises(ValueError, match=match):
        fit(events, K)


def test_one_polarity_window_is_fine(slider):
    events = slider.events
    keep = np.flatnonzero(events.p == 1)
    only_on = Events(events.x[keep], events.y[keep], events.t[keep], events.p[keep], events.width, events.height)
    r = fit(only_on, slider.K, model="flow")
    assert np.all(np.isfinite(r.flow))
    split = fit(only_on, slider.K, model="flow", polarity_split=True)  # the OFF image is empty
    np.testing.assert_allclose(split.flow, r.flow, rtol=1e-9)


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


def _plane_events(rng, points, depth, events_per_point, f, v):
    """Events of edge points (P, 2) [px at t_ref] at depths (P,) [m] seen by a camera translating at ``v``
    (no rotation): an event at time dt sits where its point is then, ``x - f v dt / Z``. Returns x, y, dt
    (N,) float64 tensors and the per-event inverse depth (N,)."""
    import torch

    dt = rng.uniform(-0.1, 0.1, (len(points), events_per_point))
    xs = points[:, :1] - f * v[0] * dt / depth[:, None]
    ys = points[:, 1:] - f * v[1] * dt / depth[:, None]
    rho = np.repeat(1.0 / depth, events_per_point)
    return (*(torch.from_numpy(a.ravel()) for a in (xs, ys, dt)), torch.from_numpy(rho))


def _sweep_inputs(x, y, f, H, W, grid_shape):
    """K (3, 3) with the principal point at the image centre, the events' rays (N, 3), and their grid nodes and
    bilinear weights (N, 4) on a ``grid_shape`` depth grid."""
    import torch

    from cmax.warp import DepthGrid

    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]], dtype=torch.float64)
    rays = torch.stack([x, y, torch.ones_like(x)], -1) @ torch.linalg.inv(K).T
    index, weight = DepthGrid(grid_shape, W, H).weights(x, y)
    return K, rays, index, weight


def _sweep(x, y, dt, v, f, H, W, grid_shape, **options):
    import torch

    from cmax.fitting.depth_sweep import sweep_inverse_depth

    K, rays, index, weight = _sweep_inputs(x, y, f, H, W, grid_shape)
    return sweep_inverse_depth(rays, dt[None], torch.ones_like(x), v, np.zeros(3), K, height=H, width=W,
                               grid_shape=grid_shape, index=index, weight=weight, sigma=0.7, **options)


def test_sweep_finds_the_depth_of_a_fronto_parallel_plane():
    """Events of a textured plane at 2 m seen by a sliding camera: every node's sweep peaks near 0.5 1/m."""
    rng = np.random.default_rng(0)
    H, W, f, depth, v = 60, 80, 60.0, 2.0, np.array([0.6, 0.2, 0.0])
    points = rng.uniform([5, 5], [W - 5, H - 5], (400, 2))   # edges at random positions at t_ref
    x, y, dt, _ = _plane_events(rng, points, np.full(400, depth), 30, f, v)
    result = _sweep(x, y, dt, v, f, H, W, (3, 4), rho_range=(0.05, 2.0))
    np.testing.assert_allclose(result.inverse_depth, 1 / depth, rtol=0.06)
    assert result.coarse_shape == (2, 2) and np.all(result.confidence > 0)
    assert result.cost.shape == (len(result.candidates), 4) and len(result.candidates) >= 48


def test_sweep_reaches_a_far_plane_over_a_wide_range():
    """A plane at 60 m over the range 0.5-200 m, 12 px of parallax over the window: 48 candidates uniform in
    inverse depth jump from 200 m to 21.5 m, and the relative refinement (35% either way) reaches 148 m or 29 m
    from them; the old sweep put the plane at 148 m. The far-end candidates let the sweep reach it."""
    from cmax.fitting.depth_sweep import sweep_candidates

    rng = np.random.default_rng(1)
    H, W, f, depth, v = 60, 80, 60.0, 60.0, np.array([60.0, 0.0, 0.0])      # 60 px/s of flow: 12 px over 0.2 s
    points = rng.uniform([5, 5], [W - 5, H - 5], (400, 2))
    x, y, dt, _ = _plane_events(rng, points, np.full(400, depth), 30, f, v)
    result = _sweep(x, y, dt, v, f, H, W, (3, 4), rho_range=(1 / 200, 1 / 0.5))
    np.testing.assert_allclose(1 / result.inverse_depth, depth, rtol=0.05)
    uniform = np.linspace(1 / 200, 1 / 0.5, 48)
    assert uniform[0] * np.exp(0.3) < 1 / depth < uniform[1] / np.exp(0.3)          # out of the refinement's reach
    candidates = sweep_candidates((1 / 200, 1 / 0.5), 48, 0.3)
    assert np.array_equal(result.candidates, candidates) and np.all(np.diff(candidates) > 0)
    far = candidates[candidates < uniform[1]]
    np.testing.assert_allclose(far[1:] / far[:-1], np.exp(0.3), rtol=1e-12)          # a factor the refinement reaches


def test_every_event_has_one_vote_in_the_sweep():
    """One node holds two planes: 40 points at 1.5 m with 30 events each (1200 events that pile up 30
    deep when in focus) and 300 points at 4 m with 8 events each (2400 events). The node takes the
    depth of the plane most events belong to (4 m), not of the one whose focused events pile up highest."""
    rng = np.random.default_rng(5)
    H, W, f, v = 60, 80, 60.0, np.array([2.0, 0.5, 0.0])
    near = _plane_events(rng, rng.uniform([8, 8], [W - 8, H - 8], (40, 2)), np.full(40, 1.5), 30, f, v)
    far = _plane_events(rng, rng.uniform([8, 8], [W - 8, H - 8], (300, 2)), np.full(300, 4.0), 8, f, v)
    import torch

    x, y, dt = (torch.cat([a, b]) for a, b in zip(near[:3], far[:3]))
    result = _sweep(x, y, dt, v, f, H, W, (1, 1), rho_range=(0.05, 1.0), coarsening=1, refinements=())
    np.testing.assert_allclose(result.inverse_depth, 1 / 4.0, rtol=0.08)


def test_an_event_pushed_out_of_the_image_gets_the_typical_vote_scale():
    """Events always inside are scaled by their own largest value; an event that one candidate pushes
    out of the image by the median largest value of the others (not by its largest over the candidates
    that keep it inside)."""
    import torch

    from cmax.contrast.sweep import vote_scale

    score = torch.tensor([[1.0, 4.0, 2.0, 0.0], [3.0, 2.0, 6.0, 5.0], [2.0, 1.0, 1.0, 1.0]])
    inside = torch.tensor([[1.0, 1.0, 1.0, 0.0], [1.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0]])
    np.testing.assert_allclose(vote_scale(score, inside).numpy(), [[3.0, 4.0, 6.0, 4.0]])
    # the quantile of the always-inside events' largest values (3, 4, 6): the lowest, the lower median, the top
    for quantile, typical in ((0.0, 3.0), (0.5, 4.0), (1.0, 6.0)):
        np.testing.assert_allclose(vote_scale(score, inside, quantile).numpy(), [[3.0, 4.0, 6.0, typical]])


def test_semi_global_matching_fills_a_flat_node_and_keeps_a_depth_step():
    """Cost curves on a 3 x 6 grid peaking at candidate 8 on the left half and 30 on the right; one left
    node has a flat curve (no information) and one right node no events. Semi-global matching gives the
    flat and the empty node their side's value and keeps the step between the halves (no blend)."""
    import torch

    from cmax.fitting.depth_sweep import _regularised_argmax

    C, gh, gw = 40, 3, 6
    candidates = torch.arange(C, dtype=torch.float64)
    peak = torch.tensor([8.0 if j < 3 else 30.0 for i in range(gh) for j in range(gw)], dtype=torch.float64)
    S = 1.0 + 1.0 / (1.0 + (candidates[:, None] - peak[None]) ** 2)              # (C, G), symmetric peaks
    S[:, 1 * gw + 1] = 1.0                                                       # flat curve
    events = torch.full((gh * gw,), 100.0, dtype=torch.float64)
    events[2 * gw + 4] = 0.0                                                     # a node without events
    value, confidence = _regularised_argmax(S, candidates, events, (gh, gw), (0.1, 1.0))
    np.testing.assert_allclose(value.numpy(), peak.numpy(), atol=0.05)
    assert confidence[1 * gw + 1] == 0 and confidence[2 * gw + 4] == 0 and confidence[0] > 0


def test_coarse_to_fine_sweep_keeps_two_planes_apart():
    """Left half at 1.5 m, right half at 4 m: swept on a 2 x 4 grid and refined on a 4 x 8 one, the
    nodes away from the step (not in the two columns next to it) are within 5% of their plane's
    inverse depth."""
    rng = np.random.default_rng(3)
    H, W, f, v = 60, 80, 60.0, np.array([1.0, 0.2, 0.0])
    points = rng.uniform([4, 4], [W - 4, H - 4], (900, 2))
    depth = np.where(points[:, 0] < W / 2, 1.5, 4.0)
    x, y, dt, _ = _plane_events(rng, points, depth, 20, f, v)
    result = _sweep(x, y, dt, v, f, H, W, (4, 8), rho_range=(0.05, 2.0), coarsening=2, refinements=(0.3, 0.1))
    assert result.coarse_shape == (2, 4)
    rho = result.inverse_depth.reshape(4, 8)
    np.testing.assert_allclose(rho[:, :3], 1 / 1.5, rtol=0.05)
    np.testing.assert_allclose(rho[:, 5:], 1 / 4.0, rtol=0.05)


def test_relative_sweep_peaks_at_the_true_depth_of_each_plane():
    """Left half at 1.5 m, right half at 4 m: scaling every event's true inverse depth by exp(step), each
    node's curve peaks at step 0 (within half of the 0.05 spacing), and a 30% too near base peaks at
    the step that undoes it (log 1/1.3 = -0.26)."""
    import torch

    from cmax.fitting.depth_sweep import _parabolic_argmax, node_cost_function, relative_sweep_cost

    rng = np.random.default_rng(3)
    H, W, f, v = 60, 80, 60.0, np.array([0.5, 0.1, 0.0])
    points = rng.uniform([6, 6], [W - 6, H - 6], (600, 2))
    x, y, dt, rho_true = _plane_events(rng, points, np.where(points[:, 0] < W / 2, 1.5, 4.0), 25, f, v)
    K, rays, index, weight = _sweep_inputs(x, y, f, H, W, (2, 2))
    cost = node_cost_function(rays, dt[None], torch.ones_like(x), v, np.zeros(3), K, height=H, width=W,
                              grid_shape=(2, 2), index=index, weight=weight, sigma=0.7)
    steps = torch.linspace(-0.5, 0.5, 21, dtype=torch.float64)
    at_truth = _parabolic_argmax(relative_sweep_cost(cost, rho_true, steps), steps)
    np.testing.assert_allclose(at_truth.numpy(), 0.0, atol=0.025)
    too_near = _parabolic_argmax(relative_sweep_cost(cost, rho_true * 1.3, steps), steps)
    np.testing.assert_allclose(too_near.numpy(), -np.log(1.3), atol=0.025)


def test_pegboard_rotation_agrees_with_the_aps_frames(shared_data):
    """Real DAVIS346 events between the first and last APS exposure (3-83 ms): the fitted rotation agrees
    per axis within 1.5 deg/s with the rotation between the APS frames (ECC homography, R = (K^-1 H K)^T),
    while the gyro's ~5 deg/s (its uncalibrated zero-rate offset) blurs the IWE."""
    import cv2

    from cmax.geometry import so3_log
    from cmax.io import read_aedat4
    from cmax.io.aedat4 import read_aedat4_frames

    path = shared_data / "davis346_pegboard" / "davis.aedat4"
    events, frames = read_aedat4(path), read_aedat4_frames(path)
    K = np.array([[226.38, 0, 173.64], [0, 226.15, 133.73], [0, 0, 1]])  # MVSEC's DAVIS346 (assumed)
    mid = (frames.t_exposure_start + frames.t_exposure_end) // 2
    H = np.eye(3, dtype=np.float32)
    _, H = cv2.findTransformECC(frames.images[0].astype(np.float32), frames.images[2].astype(np.float32), H,
                                cv2.MOTION_HOMOGRAPHY, (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 300, 1e-7),
                                None, 5)
    U, _, Vt = np.linalg.svd((np.linalg.inv(K) @ H.astype(float) @ K).T)
    aps = np.degrees(so3_log(U @ Vt) / ((mid[2] - mid[0]) * 1e-6))
    r = fit(events.slice_time(int(mid[0]), int(mid[2]) + 1), K, model="rotation")
    np.testing.assert_allclose(np.degrees(r.omega), aps, atol=1.5)  # 0.14, 0.2, 0.76 deg/s measured
    assert r.objective_after >= 1.0


@pytest.mark.slow
def test_prophesee_drive_points_forward_with_the_zero_rotation_start(shared_data):
    """The Gen4 drive (8.8 ms, K assumed as in benchmarks/real_cmax.py): the second start of the local
    refinement finds forward motion; the default fit alone ends at a pitching plane (benchmarks/results/
    real_cmax.md)."""
    from benchmarks.real_cmax import K_GEN4
    from cmax.io import read

    full = read(shared_data / "prophesee_gen4_driving" / "evt3_sample.raw")
    events = Events(full.x // 2, full.y // 2, full.t, full.p, full.width // 2, full.height // 2)
    K = K_GEN4 * np.array([[0.5], [0.5], [1.0]])
    K[:2, 2] = (K_GEN4[:2, 2] + 0.5) / 2 - 0.5
    r = fit(events, K, depth_range=(0.05, 50.0), max_events=30_000, zero_rotation_start=True)
    direction = r.v / np.linalg.norm(r.v)
    assert np.degrees(np.arccos(direction[2])) < 10.0
