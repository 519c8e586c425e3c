"""Frame sources (cmax.sim.video): video files, image folders with timestamps, arrays."""
from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from cmax.sim.video import (
    ArraySource,
    DecodeError,
    FrameSource,
    ImageFolderSource,
    VideoFileSource,
    open_source,
    read_timestamps,
)


@pytest.fixture(scope="module")
def bikes(shared_data) -> Path:
    return shared_data / "videos" / "bikes.mp4"


def write_images(folder: Path, count: int, size=(40, 30)) -> list[np.ndarray]:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (size[1], size[0]), dtype=np.uint8) for _ in range(count)]
    for i, image in enumerate(images):
        cv2.imwrite(str(folder / f"frame_{i}.png"), image)  # natural order: 0, 1, ..., 10
    return images


def write_avi(path: Path, count: int = 30, fps: float = 20.0) -> None:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (64, 48))
    assert writer.isOpened()
    for i in range(count):
        frame = np.zeros((48, 64, 3), np.uint8)
        frame[:, : 2 * i + 2] = (30, 120, 220)
        writer.write(frame)
    writer.release()


def _ebml(ident: bytes, data: bytes) -> bytes:
    """One EBML element: its ID, an 8-byte size, the data."""
    return ident + b"\x01" + len(data).to_bytes(7, "big") + data


def _ebml_uint(value: int) -> bytes:
    return value.to_bytes(max(1, (value.bit_length() + 7) // 8), "big")


def write_mkv(path: Path, times_ms: list[int], duration_ms: float, size=(64, 48)) -> list[np.ndarray]:
    """A Matroska file of MJPEG frames at the given presentation times (ms), written by hand.

    Matroska stores no frame count: OpenCV estimates it from ``duration_ms`` and the frame rate. The
    frames' times (a variable rate, a first time after 0) are free, which OpenCV's VideoWriter cannot
    write. Returns the grey frames.
    """
    width, height = size
    blocks, greys = [], []
    for i, t in enumerate(times_ms):
        frame = np.full((height, width, 3), 40, np.uint8)
        frame[:, 4 * i: 4 * i + 10] = 220
        greys.append(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
        jpeg = cv2.imencode(".jpg", frame)[1].tobytes()  # track 1, time after the cluster's, key frame
        blocks.append(_ebml(b"\xa3", b"\x81" + struct.pack(">hB", t - times_ms[0], 0x80) + jpeg))
    header = _ebml(b"\x1a\x45\xdf\xa3", _ebml(b"\x42\x82", b"matroska") + _ebml(b"\x42\x87", _ebml_uint(4))
                   + _ebml(b"\x42\x85", _ebml_uint(2)))
    info = _ebml(b"\x15\x49\xa9\x66", _ebml(b"\x2a\xd7\xb1", _ebml_uint(1_000_000))  # ms ticks
                 + _ebml(b"\x44\x89", struct.pack(">d", duration_ms)))
    video = _ebml(b"\xe0", _ebml(b"\xb0", _ebml_uint(width)) + _ebml(b"\xba", _ebml_uint(height)))
    track = _ebml(b"\xae", _ebml(b"\xd7", _ebml_uint(1)) + _ebml(b"\x73\xc5", _ebml_uint(1))
                  + _ebml(b"\x83", _ebml_uint(1)) + _ebml(b"\x86", b"V_MJPEG") + video)
    cluster = _ebml(b"\x1f\x43\xb6\x75", _ebml(b"\xe7", _ebml_uint(times_ms[0])) + b"".join(blocks))
    path.write_bytes(header + _ebml(b"\x18\x53\x80\x67", info + _ebml(b"\x16\x54\xae\x6b", track) + cluster))
    return greys


# -- video files --------------------------------------------------------------------------
def test_bikes_video_frames_and_times(bikes):
    source = VideoFileSource(bikes)
    assert isinstance(source, FrameSource)
    assert (source.width, source.height, source.fps, source.frame_count) == (640, 272, 25.0, 250)
    items = list(source)
    assert len(items) == 250
    frame, _ = items[0]
    assert frame.dtype == np.float32 and frame.shape == (272, 640)
    assert 0 <= frame.min() and frame.max() <= 255
    times = np.array([t for _, t in items])
    assert times[0] == 0 and np.all(np.diff(times) > 0)
    np.testing.assert_allclose(np.diff(times), 40_000, atol=1_000)


def test_bikes_grey_conversion_and_resize(bikes):
    capture = cv2.VideoCapture(str(bikes))
    ok, bgr = capture.read()
    capture.release()
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(np.float32)
    frame, _ = next(iter(VideoFileSource(bikes)))
    np.testing.assert_array_equal(frame, grey)
    small = VideoFileSource(bikes, size=(320, 136))
    assert (small.width, small.height) == (320, 136)
    frame, _ = next(iter(small))
    assert frame.shape == (136, 320) and frame.dtype == np.float32
    np.testing.assert_allclose(frame, cv2.resize(grey, (320, 136), interpolation=cv2.INTER_AREA))


def test_bikes_time_window(bikes):
    source = VideoFileSource(bikes, t0_s=2.0, t1_s=3.0)
    times = [t for _, t in source]
    assert times[0] == 2_000_000 and times[-1] == 2_960_000 and len(times) == 25
    assert source.frame_count is None


def test_written_avi_and_its_truncated_copy(tmp_path):
    path = tmp_path / "clip.avi"
    write_avi(path)
    source = open_source(path)
    assert isinstance(source, VideoFileSource) and source.frame_count == 30
    items = list(source)
    assert len(items) == 30 and [t for _, t in items[:3]] == [0, 50_000, 100_000]
    truncated = tmp_path / "clip_truncated.avi"
    truncated.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(DecodeError, match="clip_truncated.avi"):
        list(VideoFileSource(truncated))


@pytest.mark.parametrize("times_ms, duration_ms", [
    ([0, 10, 50, 60, 200, 210, 500, 510], 520),  # a variable frame rate: OpenCV estimated 10 frames
    ([5000 + 40 * i for i in range(25)], 6000),  # a segment cut at 5 s: OpenCV estimated 150 frames
], ids=["vfr", "starts-at-5s"])
def test_a_matroska_video_whose_estimated_count_is_too_large_is_read_whole(tmp_path, times_ms, duration_ms):
    """Was: `decoding stopped after frame 8 of the 10 the container lists (truncated or corrupt video)`."""
    path = tmp_path / "clip.mkv"
    greys = write_mkv(path, times_ms, duration_ms)
    capture = cv2.VideoCapture(str(path))
    listed = capture.get(cv2.CAP_PROP_FRAME_COUNT)
    capture.release()
    assert listed > len(times_ms) + 1  # the estimate the old check believed
    items = list(VideoFileSource(path, dtype=np.uint8))
    assert [t for _, t in items] == [1000 * (t - times_ms[0]) for t in times_ms]
    for (frame, _), grey in zip(items, greys):
        assert np.abs(frame.astype(int) - grey).max() <= 8  # JPEG
    cut = tmp_path / "cut.mkv"  # the same file cut in half is still refused
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(DecodeError, match="cut.mkv: decoding stopped"):
        list(VideoFileSource(cut))
    whole = tmp_path / "cfr.mkv"  # a constant rate from 0, cut: refused as before
    write_mkv(whole, [40 * i for i in range(25)], 1000)
    assert len(list(VideoFileSource(whole))) == 25
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    with pytest.raises(DecodeError, match="decoding stopped after frame"):
        list(VideoFileSource(cut))


@pytest.mark.parametrize("t0_s, t1_s", [(1.9, None), (2.62, None), (1.4, 2.65), (4.5, None)])
def test_a_time_range_of_a_variable_frame_rate_video_keeps_every_frame_in_it(tmp_path, t0_s, t1_s):
    """OpenCV seeks a variable-rate stream by frame number (time x its estimated rate): asked for 1.9 s it
    landed at 4.5 s, and the frames between were dropped without a word (or, past the end, `no frames`)."""
    times_ms = list(range(0, 2000, 100)) + [2600, 2610, 2620, 2630] + list(range(3000, 5000, 500))
    path = tmp_path / "vfr.mkv"
    write_mkv(path, times_ms, 5000)
    whole = list(VideoFileSource(path, dtype=np.uint8))
    assert [t for _, t in whole] == [1000 * t for t in times_ms]  # the last frame shows for 500 ms: not cut
    upper = np.inf if t1_s is None else 1e6 * t1_s
    expected = [(frame, t) for frame, t in whole if 1e6 * t0_s <= t < upper]
    got = list(VideoFileSource(path, t0_s=t0_s, t1_s=t1_s, dtype=np.uint8))
    assert [t for _, t in got] == [t for _, t in expected] and got
    assert all(np.array_equal(a, b) for (a, _), (b, _) in zip(got, expected))


def test_frames_whose_container_times_do_not_increase_are_counted_in_a_warning(tmp_path):
    """Frames at 0, 40, 40, 40, 80 ms (and 60 after 80) were moved to 40.001, 40.002 ms (80.001) without a
    word: two changes of the picture crammed into 2 µs, a burst of events at the wrong time."""
    import warnings

    path = tmp_path / "dup.mkv"
    write_mkv(path, [0, 40, 40, 40, 80, 120, 160, 200], 240)
    with pytest.warns(UserWarning) as caught:
        times = [t for _, t in VideoFileSource(path, prefetch=0)]
    assert times == [0, 40_000, 40_001, 40_002, 80_000, 120_000, 160_000, 200_000]
    assert [str(w.message) for w in caught] == [
        f"{path}: 2 of its 8 frames have a time not after the frame before (duplicated or reordered timestamps "
        "in the container; the first: frame 2 at 40.000 ms, after 40.000 ms): each was placed 1 µs after the "
        "frame before, so the change to it happens within 1 µs"]
    write_mkv(path, [0, 40, 80, 60, 100, 140], 180)
    with pytest.warns(UserWarning, match=r"1 of its 6 frames has a time .* frame 3 at 60.000 ms, after 80.000 ms"):
        list(VideoFileSource(path))
    write_mkv(path, [0, 40, 80, 120], 160)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert [t for _, t in VideoFileSource(path)] == [0, 40_000, 80_000, 120_000]


def test_random_bytes_are_not_a_video(tmp_path):
    noise = tmp_path / "noise.mp4"
    noise.write_bytes(np.random.default_rng(0).integers(0, 256, 20_000, dtype=np.uint8).tobytes())
    with pytest.raises(DecodeError, match="noise.mp4"):
        VideoFileSource(noise)
    with pytest.raises(DecodeError, match="noise.mp4"):
        open_source(noise)


def test_corrupt_videos_raise(tmp_path, bikes):
    truncated = tmp_path / "bikes_truncated.mp4"
    truncated.write_bytes(bikes.read_bytes()[:250_000])
    with pytest.raises(DecodeError, match="bikes_truncated.mp4"):
        list(open_source(truncated))
    damaged = bytearray(bikes.read_bytes())  # index kept, half the stream zeroed
    damaged[200_000:500_000] = bytes(300_000)
    (tmp_path / "bikes_damaged.mp4").write_bytes(bytes(damaged))
    with pytest.raises(DecodeError, match="bikes_damaged.mp4"):
        list(VideoFileSource(tmp_path / "bikes_damaged.mp4"))


def test_video_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        VideoFileSource(tmp_path / "missing.mp4")
    with pytest.raises(FileNotFoundError):
        open_source(tmp_path / "missing.mp4")
    path = tmp_path / "clip.avi"
    write_avi(path, count=5)
    with pytest.raises(ValueError, match="t1_s"):
        VideoFileSource(path, t0_s=2.0, t1_s=1.0)
    with pytest.raises(ValueError, match="zero frames"):
        list(VideoFileSource(path, t0_s=10.0))
    with pytest.raises(TypeError, match="size"):
        VideoFileSource(path, size=(64.0, 48))


def test_prefetching_gives_the_same_frames_and_errors(tmp_path):
    path = tmp_path / "clip.avi"
    write_avi(path)
    direct = list(VideoFileSource(path, prefetch=0))
    threaded = list(VideoFileSource(path, prefetch=3))
    assert [t for _, t in threaded] == [t for _, t in direct]
    assert all(np.array_equal(a, b) for (a, _), (b, _) in zip(direct, threaded))
    truncated = tmp_path / "cut.avi"
    truncated.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    seen = []
    with pytest.raises(DecodeError, match="cut.avi"):  # raised here, after the decodable frames
        for frame, t in VideoFileSource(truncated, prefetch=2):
            seen.append(t)
    assert 0 < len(seen) < 30 and seen == [t for _, t in direct[: len(seen)]]


def test_stopping_early_stops_the_decoding_thread(tmp_path):
    import threading

    path = tmp_path / "clip.avi"
    write_avi(path)
    before = threading.active_count()
    frames = iter(VideoFileSource(path, prefetch=2))
    next(frames)
    assert threading.active_count() == before + 1
    frames.close()  # what a for loop's break and garbage collection do
    assert threading.active_count() == before


def test_uint8_frames(tmp_path, bikes):
    path = tmp_path / "clip.avi"
    write_avi(path, count=4)
    as_float = [f for f, _ in VideoFileSource(path)]
    as_uint8 = [f for f, _ in VideoFileSource(path, dtype=np.uint8)]
    assert all(f.dtype == np.uint8 for f in as_uint8)
    assert all(np.array_equal(a, b) for a, b in zip(as_float, as_uint8))  # 8-bit values, exactly
    small = next(iter(VideoFileSource(bikes, size=(160, 68), dtype=np.uint8)))[0]
    small_float = next(iter(VideoFileSource(bikes, size=(160, 68))))[0]
    assert small.dtype == np.uint8 and np.abs(small - small_float).max() <= 1.0
    for bad in (np.int16, "float64", None):
        with pytest.raises(ValueError, match="dtype"):
            VideoFileSource(path, dtype=bad)
    with pytest.raises(ValueError, match="prefetch"):
        VideoFileSource(path, prefetch=-1)
    with pytest.raises(TypeError, match="prefetch"):
        VideoFileSource(path, prefetch=1.5)


# -- image folders ------------------------------------------------------------------------
def test_esim_truck_folder(shared_data):
    folder = shared_data / "esim_truck_pan" / "images"
    source = ImageFolderSource(folder)  # finds ../timestamps.txt
    assert (source.width, source.height, source.frame_count) == (240, 180, 161)
    items = list(source)
    times = [t for _, t in items]
    assert times[:2] == [0, 1866] and times[-1] == 298_507 and len(items) == 161
    assert items[0][0].dtype == np.float32 and items[0][0].shape == (180, 240)
    explicit = ImageFolderSource(folder, timestamps=shared_data / "esim_truck_pan" / "timestamps.txt",
                                 size=(120, 90))
    frame, _ = next(iter(explicit))
    assert frame.shape == (90, 120) and (explicit.width, explicit.height) == (120, 90)
    as_uint8 = list(ImageFolderSource(folder, dtype=np.uint8, prefetch=2))
    decoded = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in source.images]
    assert all(f.dtype == np.uint8 and np.array_equal(f, d) for (f, _), d in zip(as_uint8, decoded))
    assert [t for _, t in as_uint8] == times


def test_ecd_images_txt(shared_data):
    source = open_source(shared_data / "ecd_slider_depth" / "images.txt")
    assert isinstance(source, ImageFolderSource) and source.frame_count == 87
    times = [t for _, t in source]
    assert times[:3] == [0, 38_766, 77_531] and np.all(np.diff(times) > 0)
    same = open_source(shared_data / "ecd_slider_depth" / "images")  # images.txt in the parent
    np.testing.assert_array_equal(same.timestamps_us, times)


def test_timestamp_file_formats(tmp_path):
    images = write_images(tmp_path / "imgs", 11)
    (tmp_path / "imgs" / "timestamps.txt").write_text("".join(f"{0.01 * i:.6f}\n" for i in range(11)))
    source = ImageFolderSource(tmp_path / "imgs")
    assert source.timestamps_us.tolist() == [10_000 * i for i in range(11)]
    frames = [f for f, _ in source]
    np.testing.assert_array_equal(frames[10], images[10])  # natural order, not frame_1, frame_10
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("# index time\n0 0.5\n\n2 0.75\n10 1.0\n")
    t_us, paths = read_timestamps(pairs, tmp_path / "imgs")
    assert t_us.tolist() == [500_000, 750_000, 1_000_000]
    assert [p.name for p in paths] == ["frame_0.png", "frame_2.png", "frame_10.png"]
    ecd = tmp_path / "images.txt"
    ecd.write_text("1.5 imgs/frame_3.png\n1.6 imgs/frame_4.png\n")
    source = open_source(ecd)
    assert source.timestamps_us.tolist() == [1_500_000, 1_600_000]
    np.testing.assert_array_equal(next(iter(source))[0], images[3])
    source = ImageFolderSource(tmp_path / "imgs", timestamps=np.arange(11) * 7)
    assert source.timestamps_us[-1] == 70


def test_image_folder_errors(tmp_path):
    write_images(tmp_path / "a", 3)
    with pytest.raises(FileNotFoundError, match="no timestamps"):
        ImageFolderSource(tmp_path / "a")
    with pytest.raises(TypeError, match="integer µs"):
        ImageFolderSource(tmp_path / "a", timestamps=np.array([0.0, 0.1, 0.2]))
    with pytest.raises(ValueError, match="3 images"):
        ImageFolderSource(tmp_path / "a", timestamps=np.array([0, 1]))
    with pytest.raises(ValueError, match="strictly increasing"):
        ImageFolderSource(tmp_path / "a", timestamps=np.array([0, 5, 5]))
    (tmp_path / "a" / "timestamps.txt").write_text("0.0\n0.1\n")
    with pytest.raises(ValueError, match="lists 2 times"):
        ImageFolderSource(tmp_path / "a")
    (tmp_path / "a" / "timestamps.txt").write_text("0.0\n0.2\n0.1\n")
    with pytest.raises(ValueError, match="strictly increasing"):
        ImageFolderSource(tmp_path / "a")
    (tmp_path / "a" / "timestamps.txt").write_text("0.0 x y\n")
    with pytest.raises(ValueError, match="format"):
        ImageFolderSource(tmp_path / "a")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="zero frames"):
        ImageFolderSource(tmp_path / "empty", timestamps=np.array([], dtype=np.int64))
    with pytest.raises(FileNotFoundError):
        ImageFolderSource(tmp_path / "nowhere", timestamps=np.array([0]))


def test_mismatched_and_undecodable_images(tmp_path):
    write_images(tmp_path / "b", 2)
    cv2.imwrite(str(tmp_path / "b" / "frame_2.png"), np.zeros((31, 40), np.uint8))
    source = ImageFolderSource(tmp_path / "b", timestamps=np.array([0, 1, 2]))
    with pytest.raises(ValueError, match="frame_2.png is 40x31"):
        list(source)
    write_images(tmp_path / "c", 2)
    (tmp_path / "c" / "frame_2.png").write_bytes(b"not a png at all")
    with pytest.raises(DecodeError, match="frame_2.png"):
        list(ImageFolderSource(tmp_path / "c", timestamps=np.array([0, 1, 2])))


def test_grey_pngs_are_read_without_opencv(tmp_path, monkeypatch):
    """Grey 8- and 16-bit PNGs go through cmax.sim.png (same values); other images still through cv2."""
    images = write_images(tmp_path / "grey", 3)
    deep = (images[0].astype(np.uint16) * 257 + 1)
    (tmp_path / "deep").mkdir()
    cv2.imwrite(str(tmp_path / "deep" / "0.png"), deep)
    cv2.imwrite(str(tmp_path / "grey" / "frame_3.bmp"), images[1])
    expected = [f for f, _ in ImageFolderSource(tmp_path / "grey", timestamps=np.arange(4))]
    expected_deep = next(iter(ImageFolderSource(tmp_path / "deep", timestamps=np.array([0]))))[0]
    calls = []
    real_imread = cv2.imread
    monkeypatch.setattr(cv2, "imread", lambda *args: calls.append(str(args[0])) or real_imread(*args))
    frames = [f for f, _ in ImageFolderSource(tmp_path / "grey", timestamps=np.arange(4))]
    assert [Path(c).name for c in calls] == ["frame_3.bmp"]  # the PNGs never reached OpenCV
    for frame, image in zip(frames, images + [images[1]]):
        np.testing.assert_array_equal(frame, image.astype(np.float32))
    np.testing.assert_array_equal(frames, expected)
    frame, _ = next(iter(ImageFolderSource(tmp_path / "deep", timestamps=np.array([0]))))
    np.testing.assert_array_equal(frame, deep.astype(np.float32) * np.float32(255 / 65535))
    np.testing.assert_array_equal(frame, expected_deep)


def test_corrupt_png_raises_decode_error_naming_it(tmp_path):
    write_images(tmp_path / "d", 3)
    path = tmp_path / "d" / "frame_1.png"
    path.write_bytes(path.read_bytes()[:-40])  # cut inside the image data
    source = ImageFolderSource(tmp_path / "d", timestamps=np.array([0, 1, 2]), prefetch=2)
    with pytest.raises(DecodeError, match=r"frame_1\.png: truncated PNG"):
        list(source)
    data = bytearray((tmp_path / "d" / "frame_2.png").read_bytes())
    data[60] ^= 0xFF  # inside the IDAT chunk
    path.write_bytes(bytes(data))
    with pytest.raises(DecodeError, match=r"frame_1\.png: corrupt PNG \(CRC mismatch"):
        list(ImageFolderSource(tmp_path / "d", timestamps=np.array([0, 1, 2]), prefetch=0))


def test_colour_images_become_grey(tmp_path):
    folder = tmp_path / "colour"
    folder.mkdir()
    bgr = np.zeros((30, 40, 3), np.uint8)
    bgr[..., 2] = 200
    cv2.imwrite(str(folder / "0.png"), bgr)
    frame, _ = next(iter(ImageFolderSource(folder, timestamps=np.array([0]))))
    np.testing.assert_array_equal(frame, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))


# -- arrays and dispatch -------------------------------------------------------------------
def test_array_source():
    frames = np.arange(2 * 4 * 6, dtype=np.uint8).reshape(2, 4, 6)
    source = ArraySource(frames, np.array([5, 9]))
    assert (source.width, source.height, source.frame_count, len(source)) == (6, 4, 2, 2)
    assert source.fps == pytest.approx(1e6 / 4)
    items = list(source)
    assert [t for _, t in items] == [5, 9] and items[1][0].dtype == np.float32
    np.testing.assert_array_equal(items[1][0], frames[1])
    assert next(iter(ArraySource(frames, np.array([5, 9]), size=(3, 2))))[0].shape == (2, 3)
    with pytest.raises(ValueError, match="strictly increasing"):
        ArraySource(frames, np.array([9, 5]))
    with pytest.raises(TypeError, match="integer"):
        ArraySource(frames, np.array([0.0, 1.0]))
    with pytest.raises(ValueError, match=r"\(T, H, W\)"):
        ArraySource(frames[0], np.array([0]))
    with pytest.raises(ValueError, match=r"\[0, 255\]"):
        ArraySource(frames.astype(float) - 1, np.array([5, 9]))
    as_uint8 = list(ArraySource(frames.astype(np.float64), np.array([5, 9]), dtype=np.uint8))
    assert as_uint8[1][0].dtype == np.uint8 and np.array_equal(as_uint8[1][0], frames[1])
    with pytest.raises(ValueError, match="whole grey values"):
        ArraySource(frames + 0.5, np.array([5, 9]), dtype=np.uint8)


def test_open_source_dispatch(tmp_path):
    frames = np.zeros((2, 4, 6), np.uint8)
    source = open_source(frames, timestamps=np.array([0, 1]))
    assert isinstance(source, ArraySource)
    assert open_source(source) is source
    with pytest.raises(ValueError, match="timestamps"):
        open_source(frames)
    with pytest.raises(ValueError, match="not to an array"):
        open_source(frames, timestamps=np.array([0, 1]), t0_s=1.0)
    with pytest.raises(TypeError):
        open_source(42)  # type: ignore[arg-type]
    write_avi(tmp_path / "v.avi", count=3)
    with pytest.raises(ValueError, match="timestamps"):
        open_source(tmp_path / "v.avi", timestamps=np.array([0, 1, 2]))


def test_t0_t1_count_seconds_after_the_first_frame_for_videos_and_image_folders(tmp_path):
    """One meaning for every source: ``t_first + t0_s <= t < t_first + t1_s``; an image folder on an absolute
    clock (ROS/DSEC exports) is cut as one that starts at 0 (it kept every image for t0_s=0.1)."""
    path = tmp_path / "clip.avi"
    write_avi(path, count=10, fps=20.0)
    everything = [t for _, t in VideoFileSource(path)]
    cut = [t for _, t in VideoFileSource(path, t0_s=0.1, t1_s=0.3)]
    assert cut == [t for t in everything if 100_000 <= t - everything[0] < 300_000] and len(cut) == 4
    with pytest.raises(ValueError, match="from 10.0 s after the first frame to the end"):
        list(VideoFileSource(path, t0_s=10.0))
    for start_us in (0, 1_700_000_000_000_000):
        folder = tmp_path / f"seq{start_us}"
        folder.mkdir()
        for k in range(6):
            cv2.imwrite(str(folder / f"{k}.png"), np.full((4, 4), 40 * k, np.uint8))
        (folder / "timestamps.txt").write_text("".join(f"{(start_us + k * 50_000) * 1e-6:.6f}\n" for k in range(6)))
        source = ImageFolderSource(folder, t0_s=0.1, t1_s=0.2)
        assert (source.timestamps_us - start_us).tolist() == [100_000, 150_000]
        with pytest.raises(ValueError, match=r"images span 0\.250000 s"):
            ImageFolderSource(folder, t0_s=0.3)


def _avi_without_rate(path: Path, keep_frame_period: bool = False) -> Path:
    """An MJPG AVI of 30 frames written at 20 fps whose video stream header (strh) states rate 0, and whose main
    header (avih) states frame period 0 unless ``keep_frame_period`` (what broken writers leave)."""
    write_avi(path, count=30, fps=20.0)
    data = bytearray(path.read_bytes())
    main, stream = data.find(b"avih"), data.find(b"strh")
    assert struct.unpack_from("<I", data, main + 8) == (50_000,) and data[stream + 8: stream + 12] == b"vids"
    if not keep_frame_period:
        struct.pack_into("<I", data, main + 8, 0)
    struct.pack_into("<I", data, stream + 32, 0)                   # dwRate
    path.write_bytes(bytes(data))
    return path


def test_an_avi_whose_headers_state_no_frame_rate_is_refused_not_timed_at_25_fps(tmp_path):
    """Was: FFmpeg's 25 frames/s taken as the rate without a word: the 1.5 s of this 20 fps clip (30 frames)
    converted as 1.16 s, every interval 40 ms instead of 50 ms."""
    source = _avi_without_rate(tmp_path / "clip.avi")
    with pytest.raises(DecodeError, match=r"clip.avi: its AVI headers state no frame rate .* ffmpeg -r RATE -i"):
        VideoFileSource(source)
    # the main header's frame period alone states the rate: FFmpeg takes it, and so the times are the true ones
    kept = _avi_without_rate(tmp_path / "kept.avi", keep_frame_period=True)
    times = [t for _, t in VideoFileSource(kept, prefetch=0)]
    assert times == [50_000 * k for k in range(30)]


class _CaptureWithoutTimes:
    """A stand-in for cv2.VideoCapture of a stream that states neither frame times nor a frame rate."""

    def __init__(self, *args) -> None:
        self.read_frames = 0

    def isOpened(self) -> bool:
        return True

    def read(self):
        if self.read_frames == 3:
            return False, None
        self.read_frames += 1
        return True, np.full((48, 64, 3), 40 * self.read_frames, np.uint8)

    def get(self, prop: int) -> float:
        if prop == cv2.CAP_PROP_POS_FRAMES:
            return float(self.read_frames)
        return 0.0 if prop in (cv2.CAP_PROP_FPS, cv2.CAP_PROP_POS_MSEC) else float("nan")

    def set(self, prop: int, value: float) -> bool:
        return False

    def release(self) -> None:
        pass


def test_frames_without_times_in_a_stream_without_a_rate_are_refused_not_timed_at_30_fps(tmp_path, monkeypatch):
    """Was: frame k placed at k / 30 s when the container gave neither a time nor a rate."""
    import cmax.sim.video as video

    source = tmp_path / "clip.mkv"
    source.write_bytes(b"\x1a\x45\xdf\xa3" + bytes(60))               # opened by the stand-in, never decoded
    monkeypatch.setattr(video.cv2, "VideoCapture", _CaptureWithoutTimes)
    frames = VideoFileSource(source, prefetch=0)
    assert frames.fps is None
    with pytest.raises(DecodeError, match="frame 1 has no time in the container, which states no frame rate"):
        list(frames)


def test_an_mp4_whose_frames_last_zero_is_refused_not_timed_at_an_invented_rate(tmp_path):
    """Was: an mp4 whose stts table gives every sample a duration of 0 read at the rate FFmpeg/OpenCV made up:
    this 20 fps clip came out at 0.5 fps (frames 2 s apart instead of 50 ms), without a word."""
    source = tmp_path / "clip.mp4"
    writer = cv2.VideoWriter(str(source), cv2.VideoWriter_fourcc(*"mp4v"), 20.0, (64, 48))
    assert writer.isOpened()
    for i in range(10):
        frame = np.zeros((48, 64, 3), np.uint8)
        frame[:, 4 * i: 4 * i + 8] = 255
        writer.write(frame)
    writer.release()
    assert [t for _, t in VideoFileSource(source, prefetch=0)] == [50_000 * k for k in range(10)]   # intact
    data = bytearray(source.read_bytes())
    table = data.find(b"stts")
    assert struct.unpack_from(">II", data, table + 8) == (1, 10)       # one entry of 10 samples
    struct.pack_into(">I", data, table + 16, 0)                        # their duration: 0
    source.write_bytes(bytes(data))
    with pytest.raises(DecodeError, match=r"clip.mp4: its video track states no frame durations \(each of its 10 "
                                          r"samples lasts 0 in its stts table\)"):
        VideoFileSource(source)
