"""``cmax show``: robust contrast, a readable layout of wide sensors, refusals of impossible windows and formats."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from cmax.cli import main
from cmax.events import Events
from cmax.io import write_h5
from cmax.show import SHOW_PERCENTILE, render_events
from conftest import random_events


def test_show_t0_past_the_end_is_an_error(tmp_path, capsys):
    events = random_events(500, width=64, height=48, t_span_us=100_000, seed=1)
    path = write_h5(tmp_path / "ev.h5", events)
    out = tmp_path / "late.png"
    assert main(["show", str(path), "--t0", "0.2", "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    span = f"{(events.t_end - events.t_start) * 1e-6:.6g}"
    assert err == [f"cmax show: error: t0 = 0.2 s is past the end of ev.h5: its events span {span} s"]
    assert not out.exists()
    # the last event's own time is still a window (it holds that event)
    last = (events.t_end - events.t_start) * 1e-6
    assert main(["show", str(path), "--t0", f"{last:.6f}", "--mode", "frame", "-o", str(out)]) == 0


@pytest.mark.parametrize("name, magic", [("w.jpg", b"\xff\xd8\xff"), ("w.png", b"\x89PNG")])
def test_show_writes_the_format_of_the_extension(tmp_path, name, magic):
    path = write_h5(tmp_path / "ev.h5", random_events(500, width=64, height=48, seed=2))
    assert main(["show", str(path), "-o", str(tmp_path / name)]) == 0
    assert (tmp_path / name).read_bytes()[:3] == magic[:3]


def test_show_refuses_an_unknown_extension(tmp_path, capsys):
    path = write_h5(tmp_path / "ev.h5", random_events(500, width=64, height=48, seed=2))
    assert main(["show", str(path), "-o", str(tmp_path / "w.bmp")]) == 2
    assert "must end in .png, .jpg, .jpeg" in capsys.readouterr().err
    assert not (tmp_path / "w.bmp").exists()


def test_show_beside_a_recording_in_a_read_only_folder_names_output_before_any_work(tmp_path, capsys, monkeypatch):
    """``cmax show`` writes FILE.png beside the recording by default; in a read-only data folder it failed after
    drawing, with ``cmax show: error: Permission denied: .../ev.png.lock`` (the lock file), not naming ``-o``. The
    folder is checked first now (a user who can write there anyway, as root can, is unaffected)."""
    import os

    import cmax.show

    data = tmp_path / "data"
    data.mkdir()
    path = write_h5(data / "ev.h5", random_events(500, width=64, height=48, seed=2))
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if os.fspath(p) == str(data) else
                        real_access(p, mode, **kw))
    drawn = []
    monkeypatch.setattr(cmax.show, "render_window", lambda *a, **k: drawn.append(1))
    assert main(["show", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "-o/--output" in err and f"its folder {data} is not writable" in err, err
    assert "beside the recording" in err and not drawn and sorted(p.name for p in data.iterdir()) == ["ev.h5"]
    monkeypatch.undo()
    assert main(["show", str(path), "-o", str(tmp_path / "elsewhere.png")]) == 0


def test_wide_sensor_is_laid_out_in_rows_with_a_large_title():
    rng = np.random.default_rng(0)
    n = 20_000
    events = Events(rng.integers(0, 1280, n), rng.integers(0, 720, n), np.sort(rng.integers(0, 10_000, n)),
                    rng.integers(0, 2, n), width=1280, height=720)
    picture = render_events(events, bins=5, title="gen4: ")
    # not a 6416 px strip: at most about 1800 px wide, the event frame at full size, bins at half size
    assert 1280 <= picture.shape[1] <= 1800
    assert picture.shape[0] > 720 + 3 * 360
    small = render_events(Events(events.x // 4, events.y // 4, events.t, events.p, width=320, height=180), bins=5)
    # the bins of a small sensor stay in one row beside one another, their colour bar beside them
    assert 5 * 320 + 4 * 4 + 4 + 40 < small.shape[1] < 5 * 320 + 4 * 4 + 4 + 200


def test_contrast_follows_the_bulk_of_the_pixels_not_a_few_bright_ones():
    """A flickering lamp (a few pixels, many events) no longer washes out the rest of the picture."""
    x, y, t = [], [], []
    for i in range(300):                        # the scene: 300 pixels with 2 events each
        x += [i % 60, i % 60]
        y += [i // 60, i // 60]
    for i in range(16):                         # the lamp: 16 pixels with 60 events each
        x += [i % 4 + 50] * 60
        y += [i // 4 + 40] * 60
    t = np.arange(len(x))
    events = Events(x, y, t, np.ones(len(x), int), width=64, height=48)
    frame = render_events(events, mode="frame")[-5 * 48::5, ::5]     # drawn 5x enlarged: one sample per pixel
    # the scene's pixels (2 events) are saturated blue: the scale is the 90th percentile of the non-zero pixels
    assert SHOW_PERCENTILE == 90.0
    assert tuple(frame[0, 0]) == (255, 0, 0) and tuple(frame[41, 51]) == (255, 0, 0)


def test_a_small_sensor_is_drawn_enlarged_by_a_whole_factor():
    """64x48 (the size the docs' examples use): each event pixel a 5x5 block, so that the title, the legend and
    the colour bar fit; the five bins side by side at the same zoom."""
    rng = np.random.default_rng(1)
    n = 300
    events = Events(rng.integers(0, 64, n), rng.integers(0, 48, n), np.sort(rng.integers(0, 10_000, n)),
                    rng.integers(0, 2, n), width=64, height=48)
    frame = render_events(events, mode="frame")
    assert frame.shape[1] == 5 * 64 and frame.shape[0] > 5 * 48
    painted = (frame[-5 * 48:] != 255).any(-1)             # the map: a non-white pixel comes in 5x5 blocks
    assert painted.reshape(48, 5, 64, 5).all(axis=(1, 3)).sum() == painted.reshape(48, 5, 64, 5).any(axis=(1, 3)).sum()
    both = render_events(events, bins=5)
    assert both.shape[1] >= 5 * (5 * 64)


def test_the_volume_alone_is_titled_with_the_file_window_and_events(tmp_path):
    """`cmax show --mode voxel` drew the bins and their colour bar without a title (no file, no window, no event
    count; the frame's title carried them in the other modes): several pictures of one recording could not be
    told apart. The picture now starts with the strip `titled` draws for that text, as the frame's does."""
    from cmax.viz import titled

    rng = np.random.default_rng(2)
    n = 400
    events = Events(rng.integers(0, 64, n), rng.integers(0, 48, n), np.sort(rng.integers(0, 40_000, n)),
                    rng.integers(0, 2, n), width=64, height=48)
    path = write_h5(tmp_path / "rec.h5", events)
    out = tmp_path / "v.png"
    assert main(["show", str(path), "--mode", "voxel", "--dt", "0.02", "-o", str(out)]) == 0
    picture = cv2.imread(str(out))
    shown = events.slice_time(int(events.t[0]), int(events.t[0]) + 20_000)
    span = (int(shown.t[-1]) - int(shown.t[0])) * 1e-3
    text = f"rec.h5, 0 s + 20 ms (events over {span:.3g} ms): {len(shown):,} events"
    strip = titled(np.full((1, picture.shape[1], 3), 255, np.uint8), text)[:-1]
    np.testing.assert_array_equal(picture[:len(strip)], strip)
    assert (strip != 255).any()                               # the strip holds the text, not only white


def test_bins_with_the_frame_alone_is_refused_not_ignored(tmp_path, capsys):
    """`cmax show --mode frame --bins 7` drew the frame and dropped --bins without a word (exit 0). Now refused
    before any work; the volume's modes take it, and without it they draw the library's 5 bins."""
    events = random_events(300, width=64, height=48, t_span_us=10_000, seed=3)
    path = write_h5(tmp_path / "rec.h5", events)
    out = tmp_path / "f.png"
    assert main(["show", str(path), "--mode", "frame", "--bins", "7", "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("cmax show: error: --bins applies to the event volume") and err.count("\n") == 1, err
    assert not out.exists()
    assert main(["show", str(path), "--mode", "frame", "-o", str(out)]) == 0
    for bins, name in ((7, "seven.png"), (None, "default.png")):
        argv = ["show", str(path), "--mode", "voxel", "-o", str(tmp_path / name)]
        assert main(argv + ([] if bins is None else ["--bins", str(bins)])) == 0
        expected = render_events(events.slice_time(int(events.t[0]), int(events.t[0]) + 50_000), mode="voxel",
                                 bins=5 if bins is None else bins,
                                 title=f"rec.h5, 0 s + 50 ms (events over {events.duration_us * 1e-3:.3g} ms): ")
        np.testing.assert_array_equal(cv2.imread(str(tmp_path / name)), expected)


def test_the_ground_truth_depth_is_drawn_only_for_a_window_that_holds_its_time(tmp_path):
    """A scene with one depth map a second: a window at 0.45-0.5 s drew the map of t=0 as "ground-truth depth"."""
    from cmax.show import read_window
    from cmax.sim import EventSimulator, make_scene, simulate_scene

    scene = make_scene("slider", seed=0, width=48, height=36, duration_s=1.0, texture_size=64)
    simulate_scene(scene, 0.6, EventSimulator(**scene.recommended_simulator, seed=0),
                   depth_times_s=[0.0, 0.5]).save(tmp_path / "s.h5")
    _, far = read_window(tmp_path / "s.h5", 0.40, 0.05)
    _, holds = read_window(tmp_path / "s.h5", 0.48, 0.05)
    assert far is None and holds is not None and holds.shape == (36, 48)


def test_the_title_gives_the_span_the_events_cover(tmp_path, monkeypatch):
    """A file of 8.8 ms drawn with the default 50 ms window was titled "0 s + 50 ms" alone."""
    import cmax.show as show

    events = Events([1, 2, 3], [0, 1, 2], [0, 4_000, 8_800], [1, 0, 1], 16, 12)
    path = write_h5(tmp_path / "short.h5", events)
    titles = []
    monkeypatch.setattr(show, "render_events", lambda *a, title="", **k: titles.append(title))
    show.render_window(path)
    assert titles == ["short.h5, 0 s + 50 ms (events over 8.8 ms): "]


def test_show_of_a_raw_file_too_long_to_hold_reads_only_its_window(tmp_path, monkeypatch, capsys):
    """``cmax show`` of a Prophesee RAW file over cmax.events.MAX_EVENTS (lowered here under its 400k events, over
    one chunk's): the window is decoded holding only itself (the whole file was decoded and refused with
    EventLimitError), equal to the file cut to the window; a window past the last event is still refused."""
    from cmax.io import write_evt3
    from cmax.show import read_window

    events = random_events(400_000, seed=9, t_span_us=2_000_000)
    path = write_evt3(tmp_path / "long.raw", events)
    monkeypatch.setattr("cmax.events.MAX_EVENTS", 150_000)
    window, depth = read_window(path, 1.0, 0.05)
    start = events.t_start + 1_000_000
    assert window == events.slice_time(start, start + 50_000) and len(window) > 9_000 and depth is None
    assert main(["show", str(path), "--t0", "1", "-o", str(tmp_path / "w.png")]) == 0
    assert main(["show", str(path), "--t0", "2.5", "-o", str(tmp_path / "late.png")]) == 2
    span = f"{(events.t_end - events.t_start) * 1e-6:.6g}"
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"cmax show: error: t0 = 2.5 s is past the end of long.raw: its events span {span} s")


def test_show_of_an_mvsec_file_reads_only_its_window(tmp_path, monkeypatch):
    """``cmax show`` of an MVSEC file read the camera's whole (N, 4) float64 table for one window (refused over
    cmax.events.MAX_EVENTS, lowered here under its 5,000 events): now its first and last rows and the window's."""
    import h5py

    from cmax.io import read
    from cmax.show import read_window

    rng = np.random.default_rng(2)
    n = 5_000
    t = 1504645177.0 + np.sort(rng.uniform(0, 2, n))
    table = np.column_stack([rng.integers(0, 346, n), rng.integers(0, 260, n), t, rng.choice([-1.0, 1.0], n)])
    path = tmp_path / "indoor_flying.hdf5"
    with h5py.File(path, "w") as file:
        file["davis/left/events"] = table
    events = read(path)
    assert events.t.tolist() == np.rint(t * 1e6).astype(np.int64).tolist()   # seconds, rounded to µs
    monkeypatch.setattr("cmax.events.MAX_EVENTS", 1_000)
    window, depth = read_window(path, 1.0, 0.05)
    start = events.t_start + 1_000_000
    assert window == events.slice_time(start, start + 50_000) and 0 < len(window) < 1_000 and depth is None
    with pytest.raises(ValueError, match=r"t0 = 3 s is past the end of indoor_flying.hdf5: its events span 1.99"):
        read_window(path, 3.0, 0.05)


@pytest.mark.parametrize("kind", ["h5", "txt"])
def test_show_of_an_empty_file_or_an_empty_window_is_refused_not_drawn_blank(tmp_path, capsys, kind):
    """An empty file, or a window in a gap of the recording, was drawn as a blank picture with exit 0; cmax fit
    refuses both (exit 2), and so does cmax show now, naming the file or the window; the picture is not written."""
    from cmax.io import write_txt

    write = write_h5 if kind == "h5" else write_txt
    none = np.zeros(0, dtype=np.int64)
    empty = write(tmp_path / f"empty.{kind}", Events(none, none, none, none, 64, 48))
    rng = np.random.default_rng(4)
    t = np.r_[np.sort(rng.integers(0, 10_000, 100)), np.sort(rng.integers(900_000, 1_000_000, 100))]
    gap = write(tmp_path / f"gap.{kind}", Events(rng.integers(0, 64, 200), rng.integers(0, 48, 200), t,
                                                 rng.integers(0, 2, 200), 64, 48))
    size = [] if kind == "h5" else ["--size", "64x48"]
    out = tmp_path / "w.png"
    assert main(["show", str(empty), "-o", str(out), *size]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [f"cmax show: error: empty.{kind} holds no events: "
                                                             "nothing to draw"]
    assert main(["show", str(gap), "--t0", "0.3", "-o", str(out), *size]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"no events in the window [0.3, 0.35) s after the first event of gap.{kind}" in err[0]
    assert not out.exists()
    assert main(["show", str(gap), "--t0", "0.9", "-o", str(out), *size]) == 0 and out.exists()
