"""``cmax.fit``, ``fit_sequence`` and ``fit_windows`` given a ``cmax.Camera``: its distortion is undone first."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

import cmax
from cmax import Camera, Events
from cmax.metrics import depth_metrics

#: Barrel distortion of the test camera (k1, k2, p1, p2): up to 11 px at the corners of 120x90, f = 78.5 px.
DISTORTION = np.array([-0.25, 0.06, 0.0, 0.0])


@pytest.fixture(scope="module")
def window():
    from benchmarks.synthetic_windows import preset_window

    return preset_window("indoor_flying", 7, width=120, height=90, duration_s=0.1665, texture_size=128)


def _distorted(events: Events, K: np.ndarray, distortion: np.ndarray) -> Events:
    """The events of an ideal pinhole camera as a camera with ``distortion`` records them (OpenCV's model,
    nearest pixel; those that leave the image dropped)."""
    rays = np.column_stack([events.x, events.y, np.ones(len(events))]) @ np.linalg.inv(K).T
    pixels, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, distortion)
    xy = np.rint(pixels.reshape(-1, 2)).astype(np.int64)
    inside = (xy[:, 0] >= 0) & (xy[:, 0] < events.width) & (xy[:, 1] >= 0) & (xy[:, 1] < events.height)
    return Events(xy[inside, 0], xy[inside, 1], events.t[inside], events.p[inside], events.width, events.height)


def _abs_rel(result, truth: np.ndarray) -> float:
    return depth_metrics(np.where(result.mask, result.depth, np.nan), truth).abs_rel


def test_a_distorted_camera_is_undone_before_the_fit(window):
    """Events recorded through a barrel lens, fitted with their camera: the depth (a map of the undistorted
    image, against the ideal camera's truth) is nearly that of the ideal camera's events, where the same
    events fitted with K alone are far off (measured: 0.141 ideal, 0.156 with the camera, 0.392 with K)."""
    distorted = _distorted(window.events, window.K, DISTORTION)
    camera = Camera(window.K, window.events.width, window.events.height, DISTORTION)
    ideal = _abs_rel(cmax.fit(window.events, window.K, pose=window.T01), window.depth)
    with_camera = _abs_rel(cmax.fit(distorted, camera, pose=window.T01), window.depth)
    with_K = _abs_rel(cmax.fit(distorted, window.K, pose=window.T01), window.depth)
    assert with_camera < ideal + 0.05, (with_camera, ideal)
    assert with_K > 2 * with_camera, (with_K, with_camera)


_TIGHT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)


def test_the_camera_fit_warps_each_event_from_its_dithered_sensor_pixel_through_the_lens(window, monkeypatch):
    """The fit took each event at its nearest undistorted pixel and dithered it there (two quantisations).
    Now each event is dithered over its SENSOR pixel and mapped through the lens, unrounded (OpenCV's
    undistortPoints of the dithered position), and the motion members redraw the dither the same way; the pixel
    tests keep the nearest undistorted pixel of the same event (aligned through the hot-pixel and the
    isolated-event filters)."""
    from cmax.fitting import api

    distorted = _distorted(window.events, window.K, DISTORTION)
    rng = np.random.default_rng(0)
    n_noise, n_hot = 3000, 400                    # background noise (the isolated-event filter) and a hot pixel
    t = np.concatenate([distorted.t, rng.integers(distorted.t[0], distorted.t[-1], n_noise),
                        np.linspace(distorted.t[0], distorted.t[-1], n_hot).astype(np.int64)])
    x = np.concatenate([distorted.x, rng.integers(0, 120, n_noise), np.full(n_hot, 70)])
    y = np.concatenate([distorted.y, rng.integers(0, 90, n_noise), np.full(n_hot, 40)])
    order = np.argsort(t, kind="stable")
    p = np.concatenate([distorted.p, rng.integers(0, 2, n_noise + n_hot)])
    events = Events(x[order], y[order], t[order], p[order], 120, 90)
    camera = Camera(window.K, 120, 90, DISTORTION)
    built = []
    real = api.Window.from_events.__func__

    def capture(cls, *args, **kwargs):
        built.append(real(cls, *args, **kwargs))
        return built[-1]

    monkeypatch.setattr(api.Window, "from_events", classmethod(capture))
    result = cmax.fit(events, camera, pose=window.T01, max_events=20_000)
    assert np.isfinite(result.depth[result.mask]).all()
    w = built[0]
    rounded = camera.undistort_events(events)
    assert w.sensor is not None and len(w.source) < len(rounded) - n_hot   # hot pixel and noise filtered out
    sensor = w.sensor.pixels.astype(np.float64)
    np.testing.assert_array_equal(np.rint(camera.undistortion_map[w.sensor.pixels[:, 1], w.sensor.pixels[:, 0]]),
                                  np.column_stack([w.source.x, w.source.y]))   # the same events, aligned
    for drawn in (w, w.with_seed(5)):
        seed, n = drawn.settings.seed, len(w.source)
        keep = np.sort(np.random.default_rng(seed).choice(n, 20_000, replace=False))
        dithered = sensor[keep] + np.random.default_rng([seed, 1]).uniform(-0.5, 0.5, (20_000, 2))
        expected = cv2.undistortPoints(dithered.reshape(-1, 1, 2), window.K, DISTORTION, P=window.K,
                                       criteria=_TIGHT).reshape(-1, 2)
        np.testing.assert_allclose(np.column_stack([drawn.ev.x.numpy(), drawn.ev.y.numpy()]), expected, atol=1e-4)
    assert np.abs(w.ev.x.numpy() - np.rint(w.ev.x.numpy())).max() > 0.4


def test_the_camera_fit_differs_from_the_fit_of_rounded_events_and_a_pinhole_camera_is_its_K(window):
    """A camera with a lens no longer fits the events rounded to their nearest undistorted pixels (what
    ``Camera.undistort_events`` gives); a camera without distortion is its K, bit for bit."""
    distorted = _distorted(window.events, window.K, DISTORTION)
    camera = Camera(window.K, 120, 90, DISTORTION)
    a = cmax.fit(distorted, camera, model="rotation")
    b = cmax.fit(camera.undistort_events(distorted), window.K, model="rotation")
    assert not np.array_equal(a.omega, b.omega) and np.allclose(a.omega, b.omega, atol=0.25 * np.abs(b.omega).max())
    pinhole = Camera(window.K, 120, 90)
    assert pinhole.undistort_events(window.events) is window.events
    np.testing.assert_array_equal(cmax.fit(window.events, pinhole, model="flow").flow,
                                  cmax.fit(window.events, window.K, model="flow").flow)


@pytest.mark.filterwarnings("ignore::cmax.LowMotionWarning")       # 50 ms windows of a slow turn
def test_sequences_and_batches_take_the_camera(window):
    distorted = _distorted(window.events, window.K, DISTORTION)
    camera = Camera(window.K, 120, 90, DISTORTION)
    undistorted = camera.undistort_events(distorted)
    kwargs = dict(window_us=50_000, model="rotation", progress=False)
    a = cmax.fit_sequence(distorted, camera, warm_start=False, **kwargs)
    b = cmax.fit_sequence(undistorted, window.K, warm_start=False, **kwargs)
    assert len(a.results) == len(b.results) == 3
    # each window fitted as cmax.fit fits it through the camera (sub-pixel), no longer as its rounded events
    t0 = int(distorted.t[0])
    alone = [cmax.fit(distorted.slice_time(t0 + k * 50_000, t0 + (k + 1) * 50_000), camera, model="rotation")
             for k in range(3)]
    np.testing.assert_array_equal(np.stack([r.omega for r in a.results]), np.stack([r.omega for r in alone]))
    assert not np.array_equal(np.stack([r.omega for r in a.results]), np.stack([r.omega for r in b.results]))
    halves = [distorted.slice_time(distorted.t[0], distorted.t[0] + 80_000),
              distorted.slice_time(distorted.t[0] + 80_000, distorted.t[-1] + 1)]
    batch = cmax.fit_windows(halves, camera, model="rotation", jobs=1, progress=False)
    for events, result in zip(halves, batch):
        np.testing.assert_array_equal(result.omega, cmax.fit(events, camera, model="rotation").omega)


def test_a_camera_of_another_sensor_is_refused(window):
    camera = Camera(window.K, 121, 90, DISTORTION)
    with pytest.raises(ValueError, match="events come from a 120x90 sensor, the camera is 121x90"):
        cmax.fit(window.events, camera)
    with pytest.raises(ValueError, match=r"windows\[0\]: events come from a 120x90 sensor"):
        cmax.fit_windows([window.events], camera, jobs=1, progress=False)
    with pytest.raises(ValueError, match="events come from a 120x90 sensor"):
        cmax.fit_sequence(window.events, camera, window_us=50_000, progress=False)
