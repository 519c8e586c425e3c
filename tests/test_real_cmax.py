"""``benchmarks.real_cmax``: the DSEC file as DSEC ships it (fitted by the CLI), the far-wall region of an EMVS
depth map, and the cache of the slider's fit."""
from __future__ import annotations

import json
from types import SimpleNamespace

import h5py
import numpy as np
import pytest

from benchmarks import real_cmax
from benchmarks.real_cmax import FarWall, far_wall_region, write_dsec_original
from cmax.cli import main
from cmax.events import Events
from cmax.io import read, write_h5

pytest.importorskip("cv2")


def test_dsec_original_layout_and_the_cli_fits_it(tmp_path, capsys):
    """uint32 t relative to t_offset, ms_to_idx, no size attributes: read() asks for the size, and
    ``cmax fit FILE --size W,H --K ... --speed ...`` fits it end to end (exit 0, a window in summary.json)."""
    from benchmarks.synthetic_windows import make_window

    w = make_window("slider", 1, width=96, height=72)    # seed 0's fit fails (its depth at the near bound): exit 1
    shifted = Events(w.events.x, w.events.y, w.events.t + 7_000_000_000, w.events.p, 96, 72)  # past 2**32 us
    path = write_dsec_original(tmp_path / "events.h5", shifted)
    with h5py.File(path, "r") as file:
        assert file["events/t"].dtype == np.uint32 and not dict(file.attrs)
        assert int(file["t_offset"][()]) == int(shifted.t[0])
        index = file["ms_to_idx"][:]
        t = file["events/t"][:].astype(np.int64)
    expected = [int(np.sum(t < 1000 * k)) for k in range(len(index))]      # first event with t >= 1000 k
    np.testing.assert_array_equal(index, expected)
    assert len(index) == t[-1] // 1000 + 1
    with pytest.raises(ValueError, match="width= and height="):
        read(path)
    assert read(path, width=96, height=72) == shifted
    K = ",".join(f"{v:g}" for v in (w.K[0, 0], w.K[1, 1], w.K[0, 2], w.K[1, 2]))
    out = tmp_path / "fit"
    speed = float(np.linalg.norm(w.twist[:3]))
    assert main(["fit", str(path), "--size", "96,72", "--K", K, "--speed", f"{speed}", "-o", str(out),
                 "--max-events", "3000", "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["windows"] and summary["windows"][0]["t0_us"] >= shifted.t[0]
    v = np.asarray(summary["windows"][0]["v"])
    np.testing.assert_allclose(np.linalg.norm(v), speed, rtol=1e-6)     # --speed made it metric
    assert "windows fitted" in capsys.readouterr().out


def test_dsec_original_refuses_a_span_that_wraps_uint32(tmp_path):
    events = Events(np.zeros(2, int), np.zeros(2, int), np.array([0, 2 ** 32]), np.zeros(2, int), 4, 4)
    with pytest.raises(ValueError, match="would wrap"):
        write_dsec_original(tmp_path / "x.h5", events)
    assert not (tmp_path / "x.h5").exists()


def test_far_wall_region_is_the_farthest_structure():
    """A table object at 1.0 m and a wall at 2.1 m: the region is exactly the wall's pixels."""
    depth = np.full((40, 60), np.nan, np.float32)
    depth[5:15, 5:25] = 1.0
    depth[20:35, 10:50] = 2.1 + np.linspace(-0.02, 0.02, 40)[None]
    result = SimpleNamespace(depth=depth, mask=np.isfinite(depth), depth_range=(0.47, 2.4))
    region, threshold = far_wall_region(result)
    assert 1.0 < threshold < 2.07
    np.testing.assert_array_equal(region, np.isfinite(depth) & (depth > 2.0))
    assert FarWall(2.0, 2.2, 10, threshold).ratio == pytest.approx(1.1)


def test_slider_fit_is_cached_per_events_file(tmp_path, monkeypatch):
    """The second call reads the pickle; another events file (or a changed one) is fitted again."""
    import cmax.fitting

    calls, seen, cameras = [], [], []

    def fake_fit_sequence(events, K, speed, gyro=None, motion_members=1, zero_rotation_start=False, polish="none",
                          seed=0):
        calls.append(len(events))
        seen.append(events)
        cameras.append(K)
        return SimpleNamespace(n=len(events), speed=speed, gyro=gyro, members=motion_members,
                               zero_rotation_start=zero_rotation_start, polish=polish, seed=seed)

    monkeypatch.setattr(cmax.fitting, "fit_sequence", fake_fit_sequence)
    rng = np.random.default_rng(0)
    paths = []
    for n in (50, 60):
        events = Events(rng.integers(0, 8, n), rng.integers(0, 8, n), np.sort(rng.integers(0, 1000, n)),
                        rng.integers(0, 2, n), 8, 8)
        paths.append(write_h5(tmp_path / f"e{n}.h5", events))
    cache = tmp_path / "cache" / "fit.pkl"
    first, _, origin = real_cmax.slider_sequence(paths[0], cache)
    again, _, again_origin = real_cmax.slider_sequence(paths[0], cache)
    assert calls == [50] and first.n == again.n == 50 and again.speed == real_cmax.ECD_SPEED
    assert "this run" in origin and "cached" in again_origin and "not recorded" not in again_origin
    other, _, _ = real_cmax.slider_sequence(paths[1], cache)
    assert calls == [50, 60] and other.n == 60
    # the same events with the rotation held at zero: another fit (a constant zero gyro over the events)
    held, _, _ = real_cmax.slider_sequence(paths[1], cache, omega=(0.0, 0.0, 0.0))
    assert calls == [50, 60, 60] and held.gyro is not None and np.all(held.gyro[1] == 0)
    # with motion members: another fit, cached apart from the one-member fit
    members, _, _ = real_cmax.slider_sequence(paths[1], cache, members=4)
    assert calls == [50, 60, 60, 60] and members.members == 4 and other.members == 1
    again, _, _ = real_cmax.slider_sequence(paths[1], cache)
    assert calls == [50, 60, 60, 60, 60] and again.members == 1     # the cache held the members' fit last
    # with a second start at zero rotation: another fit too
    zrs, _, _ = real_cmax.slider_sequence(paths[1], cache, zero_rotation_start=True)
    assert calls == [50, 60, 60, 60, 60, 60] and zrs.zero_rotation_start and not again.zero_rotation_start
    # with the shared-objective polish: another fit, the mode passed on
    polished, _, _ = real_cmax.slider_sequence(paths[1], cache, polish="depth_motion")
    assert calls == [50, 60, 60, 60, 60, 60, 60] and polished.polish == "depth_motion"
    # at another fit seed: another fit, the seed passed on
    seeded, _, _ = real_cmax.slider_sequence(paths[1], cache, seed=3)
    assert calls == [50, 60, 60, 60, 60, 60, 60, 60] and seeded.seed == 3 and polished.seed == 0
    # other library code: the cache is not trusted (the first call refits: the cache held the seed-3 fit)
    real_cmax.slider_sequence(paths[1], cache)
    assert len(calls) == 9
    real_cmax.slider_sequence(paths[1], cache)
    assert len(calls) == 9
    monkeypatch.setattr(real_cmax, "library_fingerprint", lambda: "other code")
    real_cmax.slider_sequence(paths[1], cache)
    assert len(calls) == 10
    # with a calibration: another fit, of the recorded events with the file's camera, as cmax fit --calib does
    from cmax import Camera

    calib = tmp_path / "calib.txt"
    calib.write_text("6 6 3.5 3.5 -0.4 0 0 0 0\n")
    calibrated, _, _ = real_cmax.slider_sequence(paths[1], cache, calibration=calib)
    assert len(calls) == 11 and calibrated.n == 60
    camera = cameras[-1]
    assert isinstance(camera, Camera) and camera.width == camera.height == 8
    np.testing.assert_array_equal(camera.K, [[6, 0, 3.5], [0, 6, 3.5], [0, 0, 1.0]])
    np.testing.assert_array_equal(camera.distortion, [-0.4, 0, 0, 0, 0])


def test_window_speeds_of_a_slide_that_stops():
    """x = 0.3 m/s * t for 1 s, then at rest: 0.3 m/s inside the slide, 0 at rest, half over a window
    that straddles the stop, and the ends clamped outside the poses' span."""
    times = np.arange(0, 2_000_001, 10_000)
    T = np.tile(np.eye(4), (len(times), 1, 1))
    T[:, 0, 3] = 0.3 * np.minimum(times, 1_000_000) * 1e-6
    speeds = real_cmax.window_speeds(times, T, [(100_000, 300_000), (1_200_000, 1_500_000),
                                                (900_000, 1_100_000), (1_900_000, 2_100_000)])
    np.testing.assert_allclose(speeds, [0.3, 0.0, 0.15, 0.0], atol=1e-12)


def _rotated_pair(omega_deg_s: np.ndarray, dt_s: float, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A smooth random texture (260 x 346) and the same texture seen by a camera rotated by ``omega dt``
    (``frame1(x1) = frame0(x0)`` with ``x1 ~ K R^T K^-1 x0``, the model :func:`real_cmax.aps_rotation` inverts)."""
    import cv2

    from cmax.geometry import so3_exp

    rng = np.random.default_rng(3)
    frame0 = cv2.GaussianBlur(rng.uniform(0, 255, (260, 346)).astype(np.float32), (0, 0), 3.0)
    R = so3_exp(np.radians(omega_deg_s) * dt_s)
    H = K @ R.T @ np.linalg.inv(K)
    frame1 = cv2.warpPerspective(frame0, H, (346, 260), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return frame0, frame1


def test_aps_registrations_recover_a_known_rotation_and_the_direct_one_holds_on_half_frames():
    """Two frames of a known rotation (about 2 px over 40 ms): the homography's rotation and the direct 3-parameter
    fit both return it; on half frames the direct fit still does (its four halves agree within 0.3 deg/s), where a
    homography trades its rotation against its perspective terms by more than 1 deg/s."""
    K = real_cmax.K_DAVIS346
    omega = np.array([12.0, -8.0, 5.0])                      # deg/s
    frame0, frame1 = _rotated_pair(omega, 0.04, K)
    np.testing.assert_allclose(np.degrees(real_cmax.aps_rotation(frame0, frame1, K, 0.04)), omega, rtol=0.05)
    np.testing.assert_allclose(np.degrees(real_cmax.aps_rotation_direct(frame0, frame1, K, 0.04)), omega, atol=0.15)
    spread = np.degrees(real_cmax.aps_half_spread(frame0, frame1, K, 0.04))
    assert spread.shape == (3,) and np.all(spread >= 0) and spread.max() < 0.3, spread
    left = np.zeros(frame0.shape, np.uint8)
    left[:, :173] = 1
    by_halves = [real_cmax.aps_rotation(frame0, frame1, K, 0.04, mask) for mask in (left, 1 - left)]
    assert np.degrees(np.ptp(np.array(by_halves), axis=0)).max() > 1.0


def test_far_wall_reference_reads_the_events_near_each_windows_reference_time(monkeypatch):
    """The far wall's EMVS reference of a window is run on the events within ``span_us`` of its reference time
    (EMVS knows no occlusion: over the whole recording it draws the wall behind a near object), once per
    reference time for every sequence; ``span_us=None`` reads every event."""
    t = np.arange(0, 1_000_000, 1000)
    events = Events(np.zeros_like(t), np.zeros_like(t), t, np.ones_like(t), 4, 4)
    seen = []

    class Recorder:
        def run(self, events, trajectory, t_ref_us):
            seen.append((t_ref_us, int(events.t[0]), int(events.t[-1])))
            return SimpleNamespace(depth=np.full((4, 4), 2.0), mask=np.ones((4, 4), bool))

    monkeypatch.setattr(real_cmax, "far_wall_region", lambda reference: (np.ones((4, 4), bool), 1.0))
    result = lambda t_ref: SimpleNamespace(t_ref_us=t_ref, mask=np.ones((4, 4), bool),  # noqa: E731
                                           depth=np.full((4, 4), 1.8))
    first = SimpleNamespace(results=(result(300_000), result(700_000)))
    second = SimpleNamespace(results=(result(300_000), result(700_000)))
    (walls, again), references = real_cmax._far_walls_against(Recorder(), events, None, (first, second), 100_000)
    assert seen == [(300_000, 200_000, 400_000), (700_000, 600_000, 800_000)]     # within 100 ms, once each
    assert sorted(references) == [300_000, 700_000]
    assert [w.ratio for w in walls] == [w.ratio for w in again] == [pytest.approx(0.9)] * 2
    seen.clear()
    real_cmax._far_walls_against(Recorder(), events, None, (first,), None)
    assert seen == [(300_000, 0, 999_000), (700_000, 0, 999_000)]
