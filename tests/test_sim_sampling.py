"""Adaptive sampling of videos (cmax.sim.sampling): the lam*C bound, flow interpolation, streaming."""
from __future__ import annotations

import math

import numpy as np
import pytest

from cmax.sim.sampling import (
    LOG_EPS,
    IntervalReport,
    UpsampleResult,
    interpolate_frames,
    iter_upsample,
    upsample,
)
from cmax.sim.video import ArraySource, ImageFolderSource

THRESHOLD, LAM = 0.2, 0.5
BOUND = THRESHOLD * LAM


def texture(size: int = 64, seed: int = 0) -> np.ndarray:
    """Fourier coefficients of a smooth periodic texture (band-limited, values in ~[40, 215])."""
    rng = np.random.default_rng(seed)
    spectrum = np.fft.fft2(rng.standard_normal((size, size)))
    k = np.fft.fftfreq(size)
    ky, kx = np.meshgrid(k, k, indexing="ij")
    spectrum *= np.exp(-(kx**2 + ky**2) / (2 * 0.06**2))
    image = np.fft.ifft2(spectrum).real
    scale = 85 / np.abs(image).max()
    spectrum *= scale
    spectrum[0, 0] = 128 * size * size
    return spectrum


def render(spectrum: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """The texture translated by (dx, dy) pixels, exactly (Fourier shift), float32 (H, W)."""
    size = spectrum.shape[0]
    k = np.fft.fftfreq(size)
    ky, kx = np.meshgrid(k, k, indexing="ij")
    shifted = spectrum * np.exp(-2j * np.pi * (kx * dx + ky * dy))
    return np.fft.ifft2(shifted).real.astype(np.float32)


def max_log_step(frames: np.ndarray) -> np.ndarray:
    """Per consecutive pair, the largest |dL| of any pixel (float64 log)."""
    log = np.log(frames.astype(np.float64) / 255 + LOG_EPS)
    return np.abs(np.diff(log, axis=0)).reshape(len(frames) - 1, -1).max(axis=1)


@pytest.fixture(scope="module")
def moving_texture() -> tuple[np.ndarray, np.ndarray]:
    spectrum = texture()
    frames = np.stack([render(spectrum, 1.5 * i, 0.75 * i) for i in range(4)])
    return frames, np.array([0, 10_000, 20_000, 30_000], dtype=np.int64)


def check_result(result: UpsampleResult, frames: np.ndarray, times: np.ndarray) -> None:
    assert result.frames.dtype == np.float32 and result.frames.shape[1:] == frames.shape[1:]
    assert result.timestamps_us.dtype == np.int64
    assert len(result.frames) == len(frames) + result.inserted == len(result.timestamps_us)
    assert result.inserted == result.inserted_per_interval.sum()
    assert np.all(np.diff(result.timestamps_us) > 0)
    np.testing.assert_array_equal(result.timestamps_us[result.source_index], times)
    np.testing.assert_array_equal(result.frames[result.source_index], frames.astype(np.float32))
    assert np.diff(result.source_index).tolist() == (result.inserted_per_interval + 1).tolist()
    assert result.frames.min() >= 0 and result.frames.max() <= 255


# -- the bound ----------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["flow", "linear"])
def test_bound_on_moving_texture(moving_texture, method):
    frames, times = moving_texture
    result = upsample(frames, times, THRESHOLD, lam=LAM, method=method)
    check_result(result, frames, times)
    assert result.inserted > 0 and np.all(result.inserted_per_interval > 0)
    assert result.bound_met and result.bound == pytest.approx(BOUND)
    steps = max_log_step(result.frames)
    assert steps.max() <= BOUND
    for i, (a, b) in enumerate(zip(result.source_index[:-1], result.source_index[1:])):
        assert steps[a:b].max() == pytest.approx(result.max_dlog_per_interval[i], abs=1e-5)


@pytest.mark.parametrize("method", ["flow", "linear"])
def test_bound_on_real_truck_frames(shared_data, method):
    source = ImageFolderSource(shared_data / "esim_truck_pan" / "images")
    pairs = [item for item, _ in zip(source, range(6))]
    frames = np.stack([f for f, _ in pairs])
    times = np.array([t for _, t in pairs])
    result = upsample(frames, times, THRESHOLD, lam=LAM, method=method)
    check_result(result, frames, times)
    assert result.bound_met and result.inserted > 0
    assert max_log_step(result.frames).max() <= BOUND
    assert max_log_step(frames).max() > BOUND  # the raw frames break it


def test_linear_count_is_tight():
    """Linear blending of uniform frames: eq. 1 step by step gives the fewest samples possible,
    ``ceil(|L1 - L0| / bound)``, each step (but the last) moving L by the bound."""
    frames = np.stack([np.full((8, 8), 50.0), np.full((8, 8), 100.0)]).astype(np.float32)
    result = upsample(frames, np.array([0, 1_000_000]), THRESHOLD, lam=LAM, method="linear")
    total = np.log((100 + 255 * LOG_EPS) / (50 + 255 * LOG_EPS))
    assert result.inserted + 1 == int(np.ceil(total / BOUND)) == 7
    steps = max_log_step(result.frames)
    assert steps.max() <= BOUND and steps[:-1].min() > 0.99 * BOUND
    assert result.max_dlog_per_interval[0] <= BOUND


def test_steps_follow_eq1_near_black():
    """A dark pixel brightening linearly: samples crowd where L changes fast (near black),
    and their count follows the total log change, not the fastest rate."""
    frames = np.stack([np.full((4, 4), 0.0), np.full((4, 4), 30.0)]).astype(np.float32)
    result = upsample(frames, np.array([0, 1_000_000]), THRESHOLD, lam=LAM, method="linear")
    total = np.log((30 + 255 * LOG_EPS) / (255 * LOG_EPS))  # 4.78 nepers
    uniform = np.ceil((30 / (255 * LOG_EPS)) / np.expm1(BOUND))  # uniform steps sized at a = 0
    assert np.ceil(total / BOUND) <= result.inserted + 1 <= np.ceil(total / BOUND) + 2
    assert uniform > 20 * (result.inserted + 1)
    gaps = np.diff(result.timestamps_us)
    assert gaps[0] < gaps[-2] / 50  # dense at the dark start, sparse later
    assert max_log_step(result.frames).max() <= BOUND


# -- interpolation quality -------------------------------------------------------------------
def test_flow_beats_linear_on_translation():
    spectrum = texture(96, seed=1)
    frame0, frame1 = render(spectrum, 0, 0), render(spectrum, 3.3, -1.7)
    inner = (slice(12, -12), slice(12, -12))
    for alpha in (0.25, 0.5, 0.75):
        truth = render(spectrum, 3.3 * alpha, -1.7 * alpha)[inner]
        flow = interpolate_frames(frame0, frame1, [alpha], method="flow")[0][inner]
        linear = interpolate_frames(frame0, frame1, [alpha], method="linear")[0][inner]
        err_flow = np.sqrt(np.mean((flow - truth) ** 2))
        err_linear = np.sqrt(np.mean((linear - truth) ** 2))
        assert err_flow < 0.3 * err_linear, (alpha, err_flow, err_linear)


def test_flow_key_frames_are_flow_frames_at_most_a_pixel_of_motion_apart():
    """Flow sampling renders ceil(motion / 1 px) key frames by flow warping (exactly the frames
    of interpolate_frames) and blends linearly between them."""
    from cmax.sim.interpolation import make_pair

    spectrum = texture(96, seed=1)
    frame0, frame1 = render(spectrum, 0, 0), render(spectrum, 4.6, -2.1)
    span = 1_000_000
    result = upsample(np.stack([frame0, frame1]), np.array([0, span]), THRESHOLD, method="flow")
    motion = make_pair(frame0, frame1, "flow", "medium", {}).motion_px
    keys = math.ceil(motion)
    assert 4.6 < motion < 6.5 and result.bound_met
    times = result.timestamps_us.tolist()
    for k in range(1, keys):
        t = k * span // keys
        assert t in times
        expected = interpolate_frames(frame0, frame1, [t / span], method="flow")[0]
        np.testing.assert_array_equal(result.frames[times.index(t)], expected)
    assert result.inserted > keys - 1  # blended frames between the key frames too


def test_interpolation_end_points_and_shapes():
    spectrum = texture()
    frame0, frame1 = render(spectrum, 0, 0), render(spectrum, 2, 1)
    for method in ("flow", "linear"):
        out = interpolate_frames(frame0, frame1, [0.0, 1.0], method=method)
        assert out.shape == (2, 64, 64) and out.dtype == np.float32
        np.testing.assert_allclose(out[0], frame0, atol=1e-3)
        np.testing.assert_allclose(out[1], frame1, atol=1e-3)
    assert interpolate_frames(frame0, frame1, []).shape == (0, 64, 64)


def test_pure_brightness_change_falls_back_to_linear():
    frame0 = render(texture(), 0, 0)
    frame1 = np.clip(frame0 * 1.25, 0, 255).astype(np.float32)
    alphas = [0.25, 0.5, 0.75]
    flow = interpolate_frames(frame0, frame1, alphas, method="flow")
    linear = interpolate_frames(frame0, frame1, alphas, method="linear")
    assert np.abs(flow - linear).mean() < 0.5
    assert np.abs(flow - linear).max() < 10


# -- counts, caps, streaming ---------------------------------------------------------------
@pytest.mark.parametrize("method", ["flow", "linear"])
def test_identical_frames_insert_nothing(moving_texture, method):
    frame = moving_texture[0][0]
    frames = np.stack([frame, frame, frame])
    result = upsample(frames, np.array([0, 40_000, 80_000]), THRESHOLD, method=method)
    assert result.inserted == 0 and result.inserted_per_interval.tolist() == [0, 0]
    np.testing.assert_array_equal(result.frames, frames)
    assert result.bound_met and np.all(result.max_dlog_per_interval == 0)


def test_max_insert_caps_and_reports():
    frames = np.stack([np.full((8, 8), 0.0), np.full((8, 8), 255.0)]).astype(np.float32)
    result = upsample(frames, np.array([0, 1_000_000]), THRESHOLD, method="linear", max_insert=3)
    assert result.inserted == 3 and result.capped.tolist() == [True]
    assert not result.bound_met and result.max_dlog_per_interval[0] > BOUND
    assert np.all(np.diff(result.timestamps_us) > 0)


def test_short_interval_caps_at_one_sample_per_microsecond():
    frames = np.stack([np.full((8, 8), 10.0), np.full((8, 8), 200.0)]).astype(np.float32)
    result = upsample(frames, np.array([100, 105]), THRESHOLD, method="linear")
    assert result.timestamps_us.tolist() == [100, 101, 102, 103, 104, 105]
    assert result.capped.tolist() == [True]


@pytest.mark.parametrize("method", ["flow", "linear"])
def test_streaming_equals_batch(moving_texture, method):
    frames, times = moving_texture
    batch = upsample(frames, times, THRESHOLD, lam=LAM, method=method)
    reports: list[IntervalReport] = []
    streamed = list(iter_upsample(ArraySource(frames, times), THRESHOLD, lam=LAM, method=method,
                                  report=reports.append))
    assert [t for _, t in streamed] == batch.timestamps_us.tolist()
    np.testing.assert_array_equal(np.stack([f for f, _ in streamed]), batch.frames)
    assert [r.index for r in reports] == [0, 1, 2]
    assert [r.inserted for r in reports] == batch.inserted_per_interval.tolist()
    assert [(r.t0_us, r.t1_us) for r in reports] == list(zip(times[:-1].tolist(), times[1:].tolist()))


def test_streaming_keeps_no_reference_to_frames(moving_texture):
    frames, times = moving_texture
    out = list(iter_upsample(zip(frames, times), THRESHOLD, method="linear"))
    out[0][0][:] = -1  # yielded arrays are independent copies
    assert frames.min() >= 0 and len({id(f) for f, _ in out}) == len(out)


def test_bgr_frames_are_converted_to_grey(moving_texture):
    frames, times = moving_texture
    grey = upsample(frames[:2], times[:2], THRESHOLD, method="linear")
    bgr = np.repeat(frames[:2, ..., None], 3, axis=3)
    colour = upsample(bgr, times[:2], THRESHOLD, method="linear")
    np.testing.assert_allclose(colour.frames, grey.frames, atol=1e-3)


# -- validation ---------------------------------------------------------------------------
def test_rejects_bad_input(moving_texture):
    frames, times = moving_texture
    with pytest.raises(ValueError, match="strictly increasing"):
        upsample(frames, np.array([0, 10, 10, 20]), THRESHOLD)
    with pytest.raises(TypeError, match="integer"):
        upsample(frames, times.astype(float), THRESHOLD)
    with pytest.raises(ValueError, match="shape"):
        upsample(frames, times[:3], THRESHOLD)
    with pytest.raises(ValueError, match="method"):
        upsample(frames, times, THRESHOLD, method="cubic")
    with pytest.raises(ValueError, match="threshold"):
        upsample(frames, times, 0.0)
    with pytest.raises(ValueError, match="lam"):
        upsample(frames, times, THRESHOLD, lam=-1)
    with pytest.raises(ValueError, match="max_insert"):
        upsample(frames, times, THRESHOLD, max_insert=-1)
    with pytest.raises(ValueError, match=r"\[0, 255\]"):
        upsample(frames + 300, times, THRESHOLD)
    with pytest.raises(ValueError, match="at least 32x32"):
        upsample(frames[:, :16, :16], times, THRESHOLD, method="flow")


def test_stream_validates_while_iterating(moving_texture):
    frames, times = moving_texture
    bad_shape = [(frames[0], 0), (frames[1][:32], 10)]
    with pytest.raises(ValueError, match="shape"):
        list(iter_upsample(bad_shape, THRESHOLD, method="linear"))
    backwards = [(frames[0], 10), (frames[1], 10)]
    with pytest.raises(ValueError, match="strictly increasing"):
        list(iter_upsample(backwards, THRESHOLD, method="linear"))
    with pytest.raises(ValueError, match="no frames"):
        list(iter_upsample([], THRESHOLD))
    with pytest.raises(ValueError, match="method"):  # settings are checked at the call
        iter_upsample([], THRESHOLD, method="nearest")
