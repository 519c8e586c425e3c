"""``cmax depth`` / ``python -m learned.predict``: every file format, outputs equal to a direct forward, one-line errors.

The expected outputs are computed here without the command's code: the windows' bounds from the
events' own first time and the window length, the volume with :func:`cmax.representations.voxel_grid`
of the original events, the network rebuilt from the checkpoint's state dict.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import torch

from cmax import viz
from cmax.cli import main as cmax_main
from cmax.cli.recording import tail_note
from cmax.events import Events
from cmax.io import write_evt2, write_evt3, write_h5, write_txt
from cmax.representations import voxel_grid
from conftest import random_events
from learned.checkpoint import rng_state, save_checkpoint
from learned.config import Config, DataConfig
from learned.model import DepthPoseNet, ModelConfig
from learned.predict import window_picture

W, H = 64, 48
WINDOW_US = 50_000
K_TEXT = "60,58,31.5,23.5"
K = np.array([[60.0, 0, 31.5], [0, 58.0, 23.5], [0, 0, 1]])
MVSEC_T0 = 1_504_645_177_000_000   # MVSEC stores seconds since the epoch

#: The reference forward and the command's agree to rounding: both run on one thread (see ``one_thread``).
FORWARD_RTOL = 1e-5


@pytest.fixture(autouse=True)
def one_thread(monkeypatch):
    """One torch thread for the command (``CMAX_TORCH_THREADS``) and for the reference forward: a channels_last
    convolution sums in another order on two threads, which an untrained network amplifies to ~4e-3."""
    monkeypatch.setenv("CMAX_TORCH_THREADS", "1")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    """A tiny network (width 4, 2 levels) with random weights, its pose head too (so that twists vary)."""
    torch.manual_seed(5)
    config = Config(model=ModelConfig(width=4, levels=2), data=DataConfig(window_us=WINDOW_US))
    model = DepthPoseNet(config.model)
    torch.nn.init.normal_(model.pose_out.weight, std=0.5)
    path = tmp_path_factory.mktemp("ckpt") / "tiny.pt"
    save_checkpoint(path, {"model": model.state_dict(), "optimizer": {}, "step": 0, "config": config.to_dict(),
                           "rng": rng_state()})
    return path


@pytest.fixture(scope="module")
def network(checkpoint) -> DepthPoseNet:
    """The checkpoint's network, rebuilt from its state dict (not through learned.evaluate.load_model)."""
    payload = torch.load(checkpoint, weights_only=True)
    model = DepthPoseNet(ModelConfig(width=4, levels=2))
    model.load_state_dict(payload["model"])
    return model.eval()


@pytest.fixture(scope="module")
def events() -> Events:
    """3,000 random events on a 64x48 sensor over 0.2 s (first event near 0)."""
    return random_events(3000, W, H, seed=3, t_span_us=200_000)


def _expected(model: DepthPoseNet, events: Events, window_us: int = WINDOW_US, start: int | None = None,
              end: int | None = None, pixels: np.ndarray | None = None) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """``(t0_us, depth (H, W), twist (6,))`` of each window [t0, t0 + window_us) inside [start, end] (inclusive),
    or ending at most 1% of a window after ``end`` (:data:`cmax.events.WINDOW_END_TOLERANCE`); ``pixels`` (N, 2):
    the events' sub-pixel positions, spread bilinearly in the volume."""
    start = int(events.t[0]) if start is None else start
    end = int(events.t[-1]) if end is None else end
    results = []
    for k in range((end - start + 1 + window_us // 100) // window_us):
        t0 = start + k * window_us
        window = events.slice_time(t0, t0 + window_us)
        a, b = np.searchsorted(events.t, [t0, t0 + window_us])
        volume = voxel_grid(window, 5, pixels=None if pixels is None else pixels[a:b])
        with torch.no_grad():
            out = model(torch.from_numpy(volume)[None])
        results.append((t0, out.depth[0, 0].numpy(), out.twist[0].numpy()))
    return results


def _check_outputs(out: Path, expected: list[tuple[int, np.ndarray, np.ndarray]], window_us: int = WINDOW_US,
                   K_expected: np.ndarray = K, origin_us: int | None = None) -> None:
    """``origin_us``: the file's first event [µs], the origin of the pictures' times (default: the first window's
    start, which is that event without --t0)."""
    assert len(expected) >= 3
    assert not np.allclose(expected[0][1], expected[1][1]) and np.abs(expected[0][2]).min() > 0   # not trivial
    assert sorted(p.name for p in out.glob("window_*.npz")) == [f"window_{k:05d}.npz" for k in range(len(expected))]
    rows = (out / "twists.csv").read_text().splitlines()
    assert rows[0] == "window,t0_us,t1_us,events,vx,vy,vz,wx,wy,wz" and len(rows) == len(expected) + 1
    for k, (t0, depth, twist) in enumerate(expected):
        saved = np.load(out / f"window_{k:05d}.npz")
        assert saved["depth"].dtype == np.float32 and saved["depth"].shape == depth.shape
        np.testing.assert_allclose(saved["depth"], depth, rtol=FORWARD_RTOL)
        np.testing.assert_allclose(saved["inverse_depth"], 1.0 / depth, rtol=FORWARD_RTOL)
        np.testing.assert_allclose(saved["twist"], twist, rtol=FORWARD_RTOL, atol=1e-7)
        assert (int(saved["t0_us"]), int(saved["t1_us"])) == (t0, t0 + window_us)
        np.testing.assert_array_equal(saved["K"], K_expected)
        row = rows[k + 1].split(",")
        assert [int(v) for v in row[:3]] == [k, t0, t0 + window_us]
        np.testing.assert_allclose([float(v) for v in row[4:]], twist, rtol=FORWARD_RTOL, atol=1e-6)
    # one colour scale per run (summary.json's depth_range_m): the 1st-99th percentiles of every window's depths
    # pooled (a large map evenly subsampled: within 2 % of all its pixels'), the window's time in the title
    exact = viz.DepthScale.from_depths([np.load(out / f"window_{k:05d}.npz")["depth"] for k in range(len(expected))])
    scale = viz.DepthScale(*json.loads((out / "summary.json").read_text())["depth_range_m"])
    np.testing.assert_allclose([scale.near, scale.far], [exact.near, exact.far], rtol=0.02)
    first = expected[0][0] if origin_us is None else origin_us   # the titles' origin, as cmax fit's and --t0's
    for k, (t0, _, _) in enumerate(expected):
        panel = window_picture(np.load(out / f"window_{k:05d}.npz")["depth"], scale,
                               f"window {k}, {(t0 - first) * 1e-6:.3f}-{(t0 - first + window_us) * 1e-6:.3f} s, "
                               "depth [m]")
        assert np.array_equal(cv2.imread(str(out / f"window_{k:05d}.png")), panel)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["windows"] == len(expected) and summary["size"][0] in (W, 346)
    # twists.csv's header gives no units (was: nowhere in the run's files): summary.json names them, as cmax fit's
    units = summary["units"]
    assert units["twists.csv vx, vy, vz"].startswith("m/s") and units["twists.csv wx, wy, wz"].startswith("rad/s")
    assert set(rows[0].split(",")[4:]) == {"vx", "vy", "vz", "wx", "wy", "wz"}


# -- writers of each format ------------------------------------------------------------------
def _h5(path: Path, ev: Events) -> list[str]:
    write_h5(path, ev)
    return ["--K", K_TEXT]


def _h5_with_K(path: Path, ev: Events) -> list[str]:
    write_h5(path, ev)
    with h5py.File(path, "a") as file:
        file["gt/K"] = K
    return []   # the file's own intrinsics


def _h5_without_size(path: Path, ev: Events) -> list[str]:
    write_h5(path, ev)
    with h5py.File(path, "a") as file:
        del file.attrs["width"], file.attrs["height"]
    return ["--K", K_TEXT, "--size", f"{W}x{H}"]


def _evt2(path: Path, ev: Events) -> list[str]:
    write_evt2(path, ev)
    return ["--K", K_TEXT]


def _evt3(path: Path, ev: Events) -> list[str]:
    write_evt3(path, ev)
    return ["--K", K_TEXT]


def _text(path: Path, ev: Events) -> list[str]:
    write_txt(path, ev)
    calib = path.with_name("calib.txt")
    calib.write_text("60 58 31.5 23.5\n")   # ECD calib.txt without distortion
    return ["--calib", str(calib), "--size", f"{W},{H}"]


def _npy(path: Path, ev: Events) -> list[str]:
    np.save(path, ev.to_structured())
    return ["--K", K_TEXT, "--size", f"{W}x{H}"]


def _npy_float_seconds(path: Path, ev: Events) -> list[str]:
    table = np.zeros(len(ev), dtype=[("x", "<u2"), ("y", "<u2"), ("t", "<f8"), ("p", "<i1")])
    table["x"], table["y"], table["t"], table["p"] = ev.x, ev.y, ev.t * 1e-6, ev.p
    np.save(path, table)
    return ["--K", K_TEXT, "--size", f"{W}x{H}", "--time-unit", "s"]


def _signed_h5(path: Path, ev: Events) -> list[str]:
    """A DSEC-layout file storing -1/+1 polarities (needs --polarity signed)."""
    write_h5(path, ev)
    with h5py.File(path, "a") as file:
        p = file["events/p"][:].astype(np.int8) * 2 - 1
        del file["events/p"]
        file["events/p"] = p
    return ["--K", K_TEXT, "--polarity", "signed"]


def _aedat4(path: Path, ev: Events) -> list[str]:
    from test_io_aedat4 import _aedat4 as aedat4_bytes, _event_packet

    half = len(ev) // 2
    packets = [(0, _event_packet(ev.t[s], ev.x[s], ev.y[s], ev.p[s])) for s in (slice(0, half), slice(half, None))]
    path.write_bytes(aedat4_bytes([(0, "EVTS", "events", (W, H))], packets, compression=0))
    return ["--K", K_TEXT]


def _mvsec(path: Path, ev: Events) -> list[str]:
    with h5py.File(path, "w") as file:
        file["davis/left/events"] = np.column_stack([ev.x, ev.y, (ev.t + MVSEC_T0) / 1e6,
                                                     ev.signed_polarity(np.float64)])
    return ["--K", K_TEXT]


FORMATS = {"h5": (_h5, "e.h5"), "h5 gt/K": (_h5_with_K, "e.h5"), "h5 no size": (_h5_without_size, "e.h5"),
           "h5 signed": (_signed_h5, "e.h5"), "evt2": (_evt2, "e.raw"), "evt3": (_evt3, "e.raw"),
           "ecd text": (_text, "events.txt"), "npy": (_npy, "e.npy"), "npy float s": (_npy_float_seconds, "e.npy"),
           "aedat4": (_aedat4, "e.aedat4"), "mvsec": (_mvsec, "e_data.hdf5")}


@pytest.mark.parametrize("name", FORMATS)
def test_cmax_depth_on_each_format_equals_a_direct_forward(name, checkpoint, network, events, tmp_path, capsys):
    write, filename = FORMATS[name]
    path = tmp_path / filename
    options = write(path, events)
    out = tmp_path / "out"
    assert cmax_main(["depth", str(path), "-o", str(out), "--checkpoint", str(checkpoint), "--quiet", *options]) == 0
    captured = capsys.readouterr()
    expected_events = events
    if name == "mvsec":   # the same events, on MVSEC's clock and 346x260 sensor
        expected_events = Events(events.x, events.y, events.t + MVSEC_T0, events.p, 346, 260)
    expected = _expected(network, expected_events)
    _check_outputs(out, expected)
    # the camera read: an MVSEC file's (left without --camera), none for a file of one camera
    assert json.loads((out / "summary.json").read_text())["camera"] == ("left" if name == "mvsec" else None)
    assert re.fullmatch(rf"{len(expected)} windows of 50 ms predicted in [\d.]+ s \([\d.]+ windows/s\); "
                        rf"results in {re.escape(str(out))}\n", captured.out), captured.out
    # the events end 194 µs (0.4% of a window) before the fourth window's end: that window is whole, no note
    first, last = int(events.t[0]), int(events.t[-1])
    assert first + 4 * 50_000 - (last + 1) == 194 and len(expected) == 4
    assert tail_note(first, last, 50_000, 50_000, option="--window", unit_us=1_000_000) is None
    tail = ""
    if name == "mvsec":   # this K (a small sensor's) on MVSEC's 346x260 sensor: its principal point is in a corner
        assert re.fullmatch(r"cmax depth: note: K \(.*\) is unlike a camera's for a 346x260 sensor: .*\n" + tail,
                            captured.err), captured.err
    else:
        assert re.fullmatch(tail, captured.err), captured.err


DISTORTION = np.array([-0.12, 0.03, 0.002, -0.001])


def _undistorted(events: Events) -> tuple[Events, np.ndarray]:
    """The events at their undistorted pixel by OpenCV directly (nearest integer, those outside dropped), and
    their exact undistorted positions (N, 2) [px]."""
    pixels = np.column_stack([events.x, events.y]).astype(np.float64).reshape(-1, 1, 2)
    exact = cv2.undistortPoints(pixels, K, DISTORTION, P=K, criteria=(
        cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-9)).reshape(-1, 2)
    xy = np.rint(exact).astype(np.int64)
    inside = (xy[:, 0] >= 0) & (xy[:, 0] < W) & (xy[:, 1] >= 0) & (xy[:, 1] < H)
    return Events(xy[inside, 0], xy[inside, 1], events.t[inside], events.p[inside], W, H), exact[inside]


@pytest.mark.parametrize("calibration", ["calib.txt", "cam_to_cam.yaml", "--distortion"])
def test_a_calibration_with_distortion_undistorts_the_events(calibration, checkpoint, network, events, tmp_path,
                                                            capsys):
    """ECD calib.txt (with --size), a DSEC cam_to_cam.yaml whose resolution stands for the missing size
    attributes, or --K with --distortion: the same undistorted events, each spread bilinearly in the volume from
    its exact undistorted position (the volume was that of the events rounded to their nearest pixels)."""
    path = tmp_path / "e.h5"
    _h5_without_size(path, events)
    calib = tmp_path / calibration
    if calibration == "calib.txt":
        calib.write_text("60 58 31.5 23.5 " + " ".join(map(str, DISTORTION)) + " 0\n")
        options = ["--calib", str(calib), "--size", f"{W}x{H}"]
    elif calibration == "cam_to_cam.yaml":
        calib.write_text("intrinsics:\n  cam0:\n    camera_matrix: [60, 58, 31.5, 23.5]\n"
                         f"    distortion_coeffs: [{', '.join(map(str, DISTORTION))}]\n"
                         "    distortion_model: radtan\n    resolution: [64, 48]\n")
        options = ["--calib", str(calib)]
    else:
        options = ["--K", "60,58,31.5,23.5", "--distortion", ",".join(map(str, DISTORTION)), "--size", f"{W}x{H}"]
    out = tmp_path / "out"
    assert cmax_main(["depth", str(path), "-o", str(out), "--checkpoint", str(checkpoint), "--quiet",
                      *options]) == 0
    undistorted, exact = _undistorted(events)
    assert len(undistorted) < len(events) or not np.array_equal(undistorted.x, events.x)   # it moved events
    first = int(events.t[0])
    _check_outputs(out, _expected(network, undistorted, start=first, end=int(events.t[-1]), pixels=exact))
    assert json.loads((out / "summary.json").read_text())["distortion"] == pytest.approx(
        list(DISTORTION) + ([0.0] if calibration == "calib.txt" else []))


def test_distortion_needs_the_K_it_belongs_to(checkpoint, events, tmp_path, capsys):
    write_h5(tmp_path / "e.h5", events)
    status = cmax_main(["depth", str(tmp_path / "e.h5"), "-o", str(tmp_path / "out"), "--checkpoint",
                        str(checkpoint), "--distortion", "0.1,0,0,0", "--quiet"])
    err = capsys.readouterr().err
    assert status == 2 and "--distortion applies to --K: give both" in err and err.count("\n") == 1, err


def test_python_m_learned_predict_is_the_same_command(checkpoint, events, tmp_path, capsys):
    from learned.predict import main

    write_h5(tmp_path / "e.h5", events)
    base = [str(tmp_path / "e.h5"), "--checkpoint", str(checkpoint), "--K", K_TEXT, "--quiet", "--batch"]
    assert main([*base, "3", "-o", str(tmp_path / "a")]) == 0
    assert cmax_main(["depth", *base, "1", "-o", str(tmp_path / "b")]) == 0
    for name in ("window_00000.npz", "window_00002.npz"):
        a, b = np.load(tmp_path / "a" / name), np.load(tmp_path / "b" / name)
        for key in ("depth", "twist", "t0_us", "t1_us", "K"):
            np.testing.assert_allclose(a[key], b[key], rtol=1e-5, atol=1e-7)
    assert (tmp_path / "a" / "twists.csv").read_text().count("\n") == (tmp_path / "b" / "twists.csv").read_text().count("\n")


def test_t0_t1_window_and_depth_range(checkpoint, network, events, tmp_path, capsys):
    write_h5(tmp_path / "e.h5", events)
    out = tmp_path / "out"
    first = int(events.t[0])
    assert cmax_main(["depth", str(tmp_path / "e.h5"), "-o", str(out), "--checkpoint", str(checkpoint), "--K", K_TEXT,
                      "--t0", "0.02", "--t1", "0.19", "--window", "0.04", "--depth-range", "1,10", "--quiet"]) == 0
    expected = _expected(network, events, 40_000, first + 20_000, first + 190_000 - 1)
    assert len(expected) == 4   # 0.17 s hold four windows of 0.04 s
    assert sorted(p.name for p in out.glob("*.npz")) == [f"window_{k:05d}.npz" for k in range(4)]
    for k, (t0, depth, _) in enumerate(expected):
        saved = np.load(out / f"window_{k:05d}.npz")
        assert int(saved["t0_us"]) == t0
        np.testing.assert_allclose(saved["depth"], depth, rtol=FORWARD_RTOL)
    panel = window_picture(depth, viz.DepthScale(1.0, 10.0),   # s after the file's first event, as --t0
                           f"window 3, {(t0 - first) * 1e-6:.3f}-{(t0 - first + 40_000) * 1e-6:.3f} s, depth [m]")
    assert np.array_equal(cv2.imread(str(out / "window_00003.png")), panel)


def test_a_recording_shorter_than_the_window_gives_one_window(checkpoint, network, tmp_path, capsys):
    short = random_events(500, W, H, seed=4, t_span_us=30_000)
    write_h5(tmp_path / "short.h5", short)
    out = tmp_path / "out"
    assert cmax_main(["depth", str(tmp_path / "short.h5"), "-o", str(out), "--checkpoint", str(checkpoint),
                      "--K", K_TEXT, "--quiet"]) == 0
    err = capsys.readouterr().err
    assert err.startswith("cmax depth: note: the recording (") and "one window over the whole recording" in err
    span = int(short.t[-1]) - int(short.t[0]) + 1
    (t0, depth, twist), = _expected(network, short, span)
    saved = np.load(out / "window_00000.npz")
    assert (int(saved["t0_us"]), int(saved["t1_us"])) == (t0, t0 + span)
    np.testing.assert_allclose(saved["depth"], depth, rtol=FORWARD_RTOL)
    assert not (out / "window_00001.npz").exists()


def test_windows_with_too_few_events_are_skipped_and_counted(checkpoint, tmp_path, capsys):
    ev = random_events(2000, W, H, seed=6, t_span_us=50_000)
    late = Events(ev.x[:5], ev.y[:5], np.arange(5) + 170_000, ev.p[:5], W, H)   # 5 events in the last window
    write_h5(tmp_path / "gap.h5", Events.concatenate([ev, late]))
    out = tmp_path / "out"
    assert cmax_main(["depth", str(tmp_path / "gap.h5"), "-o", str(out), "--checkpoint", str(checkpoint),
                      "--K", K_TEXT, "--quiet"]) == 0
    assert "1 window of 50 ms predicted, 2 skipped (fewer than 10 events)" in capsys.readouterr().out
    assert [p.name for p in out.glob("*.npz")] == ["window_00000.npz"]


def test_camera_unlike_the_trained_one_is_noted_once(checkpoint, events, tmp_path, capsys):
    import shutil

    card_ckpt = tmp_path / "student.pt"
    shutil.copy(checkpoint, card_ckpt)
    card_ckpt.with_suffix(".json").write_text(json.dumps({"size": [346, 260], "K": [120.0, 120.0, 173.0, 130.0]}))
    write_h5(tmp_path / "e.h5", events)
    assert cmax_main(["depth", str(tmp_path / "e.h5"), "-o", str(tmp_path / "out"), "--checkpoint", str(card_ckpt),
                      "--K", K_TEXT, "--quiet"]) == 0
    notes = capsys.readouterr().err.splitlines()
    assert len(notes) == 2 and all(line.startswith("cmax depth: note: ") for line in notes)
    assert "trained on a 346x260 sensor, this file is 64x48" in notes[0]
    assert "predicted x 0.5" in notes[1]   # 60 px here, 120 px in training


def test_the_shipped_model_is_the_default(checkpoint, events, tmp_path, monkeypatch, capsys):
    import shutil

    from learned import pretrained

    write_h5(tmp_path / "e.h5", events)
    argv = ["depth", str(tmp_path / "e.h5"), "-o", str(tmp_path / "out"), "--K", K_TEXT, "--quiet"]
    monkeypatch.setattr(pretrained, "CHECKPOINT", tmp_path / "pretrained" / "student.pt")
    assert cmax_main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("cmax depth: error: no trained model ships with this installation") and \
        "python -m learned.train" in err and err.count("\n") == 1
    (tmp_path / "pretrained").mkdir()
    shutil.copy(checkpoint, tmp_path / "pretrained" / "student.pt")
    assert cmax_main(argv) == 0
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["checkpoint"].endswith("student.pt")


# -- mistakes: one line, exit 2 ------------------------------------------------------------
def _bad_files(tmp: Path, events: Events) -> dict[str, Path]:
    write_h5(tmp / "e.h5", events)
    (tmp / "x.bin").write_bytes(b"\x00\x01garbage")
    _npy_float_seconds(tmp / "float.npy", events)
    write_txt(tmp / "e.txt", events)
    (tmp / "notes.pt").write_text("not a checkpoint\n")
    (tmp / "calib.txt").write_text(K_TEXT.replace(",", " ") + "\n")
    return {"FILE": tmp / "e.h5", "BIN": tmp / "x.bin", "FLOAT": tmp / "float.npy", "TEXT": tmp / "e.txt",
            "BADCKPT": tmp / "notes.pt", "MISSING": tmp / "missing.h5", "CALIB": tmp / "calib.txt"}


MISTAKES = [
    (["MISSING", "--K", K_TEXT], "no such event file"),
    (["BIN", "--K", K_TEXT], "cannot tell the event format"),
    (["FLOAT", "--K", K_TEXT, "--size", "64x48"], "state their unit with time_unit="),
    (["TEXT", "--K", K_TEXT], "stores no sensor size"),
    (["FILE"], "stores no intrinsics (gt/K): give them with --K fx,fy,cx,cy or --calib FILE"),
    (["FILE", "--K", K_TEXT, "--checkpoint", "BADCKPT"], "is not a learned checkpoint"),
    (["FILE", "--K", K_TEXT, "--checkpoint", "MISSING"], "no checkpoint at"),
    (["FILE", "--K", K_TEXT, "--window", "0.5"], "--window 0.5 s is longer than the events to predict"),
    (["FILE", "--K", K_TEXT, "--t0", "5"], "--t0 5.0 s is past the recording's last event"),
    (["FILE", "--K", K_TEXT, "--t0", "0.1", "--t1", "0.05"], "--t1 must be after --t0"),
    (["FILE", "--K", K_TEXT, "--calib", "TEXT"], "argument --calib: not allowed with argument --K"),
    (["FILE", "--calib", "TEXT"], "expected one line 'fx fy cx cy"),
    (["FILE", "--K", "1,2,3"], "argument --K: --K must be fx,fy,cx,cy"),
    (["FILE", "--K", K_TEXT, "--batch", "0"], "argument --batch: expected a whole number >= 1"),
    (["FILE", "--K", K_TEXT, "--polarity", "signed"], "the stated encoding is -1 (OFF) / +1 (ON)"),  # 0/1 stored
    # --calib-camera where it chooses nothing (was: taken and ignored, depth maps written with the one K there is):
    (["FILE", "--K", K_TEXT, "--calib-camera", "cam1"], "--calib-camera cam1 chooses a camera of a --calib file"),
    (["FILE", "--calib", "CALIB", "--calib-camera", "camRect0"], "calibrates one camera (ECD calib.txt)"),
]


@pytest.mark.parametrize("argv, message", MISTAKES, ids=[" ".join(a[1:]) or a[0] for a, _ in MISTAKES])
def test_every_mistake_is_one_line_and_exit_2(argv, message, checkpoint, events, tmp_path, capsys):
    files = _bad_files(tmp_path, events)
    argv = [str(files.get(a, a)) for a in argv]
    if "--checkpoint" not in argv:
        argv += ["--checkpoint", str(checkpoint)]
    try:
        status = cmax_main(["depth", *argv, "-o", str(tmp_path / "out"), "--quiet"])
    except SystemExit as exit_:   # argparse's own errors
        status = exit_.code
    err = capsys.readouterr().err
    assert status == 2, err
    assert err.startswith("cmax depth: error: ") and err.count("\n") == 1 and "Traceback" not in err, err
    assert message in err, err


def test_the_shipped_model_when_present_loads_safely_and_runs(events, tmp_path, capsys):
    """The model in learned/pretrained (the lead adds it): weights_only loading, and cmax depth runs on it."""
    from learned import pretrained
    from learned.evaluate import load_model

    if not pretrained.CHECKPOINT.is_file():
        pytest.skip(f"no shipped model at {pretrained.CHECKPOINT} yet")
    model, config = load_model(pretrained.shipped_checkpoint())   # learned.checkpoint: torch.load(weights_only=True)
    card = pretrained.checkpoint_card(pretrained.CHECKPOINT)
    assert card is not None, "the shipped model needs its card student.json"
    write_h5(tmp_path / "e.h5", events)
    assert cmax_main(["depth", str(tmp_path / "e.h5"), "-o", str(tmp_path / "out"), "--K", K_TEXT, "--quiet"]) == 0
    depth = np.load(next((tmp_path / "out").glob("window_*.npz")))["depth"]
    lo, hi = model.config.min_depth, model.config.max_depth
    assert np.isfinite(depth).all() and lo * (1 - 1e-5) <= depth.min() <= depth.max() <= hi * (1 + 1e-5)


def test_a_file_without_a_window_of_enough_events_is_one_line(checkpoint, tmp_path, capsys):
    sparse = Events([1, 2, 3, 4, 5, 6], [1, 1, 1, 1, 1, 1], [0, 40_000, 80_000, 120_000, 160_000, 199_000],
                    [1, 0, 1, 0, 1, 0], W, H)
    write_h5(tmp_path / "sparse.h5", sparse)
    assert cmax_main(["depth", str(tmp_path / "sparse.h5"), "-o", str(tmp_path / "out"), "--checkpoint",
                      str(checkpoint), "--K", K_TEXT, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "none of its 3 windows of 50 ms holds 10 events or more" in err, err
    assert not (tmp_path / "out" / "twists.csv").exists()


def test_the_shipped_model_reproduces_the_scores_on_its_card():
    """The card of learned/pretrained/student.pt stores the model's Abs mean and twist on one held-out window
    (tests/data/learned_window.npz, events and true depth); the shipped weights give them again."""
    from cmax.metrics import depth_metrics
    from learned import pretrained
    from learned.evaluate import load_model

    if not pretrained.CHECKPOINT.is_file():
        pytest.skip(f"no shipped model at {pretrained.CHECKPOINT} yet")
    card = pretrained.checkpoint_card(pretrained.CHECKPOINT)
    fixture = Path(__file__).resolve().parents[1] / card["fixture"]["file"]
    data = np.load(fixture)
    window = Events(data["x"].astype(np.int64), data["y"].astype(np.int64),
                    data["t_us"].astype(np.int64) + int(data["t0_us"]), data["p"].astype(np.int64),
                    int(data["width"]), int(data["height"]))
    model, _ = load_model(pretrained.shipped_checkpoint())
    with torch.no_grad():
        out = model(torch.from_numpy(voxel_grid(window, model.config.bins))[None])
    metrics = depth_metrics(out.depth[0, 0].double().numpy(), data["depth"].astype(np.float64),
                            max_depth=float(data["far_m"]))
    assert metrics.abs_mean == pytest.approx(card["fixture"]["abs_mean_m"], rel=1e-3)
    np.testing.assert_allclose(out.twist[0].numpy(), card["fixture"]["twist"], rtol=1e-3, atol=1e-4)
    assert list(card["size"]) == [int(data["width"]), int(data["height"])]


def test_the_device_option_runs_the_network_where_asked_and_refuses_a_missing_gpu(checkpoint, events, tmp_path,
                                                                                   capsys, monkeypatch):
    """``--device auto`` without a GPU is the CPU (the same windows as the default, and summary.json says where
    it ran); ``--device cuda`` where torch sees none is one line and exit 2, and writes nothing."""
    write_h5(tmp_path / "e.h5", events)
    base = [str(tmp_path / "e.h5"), "--checkpoint", str(checkpoint), "--K", K_TEXT, "--quiet"]
    assert cmax_main(["depth", *base, "-o", str(tmp_path / "cpu")]) == 0
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert cmax_main(["depth", *base, "-o", str(tmp_path / "auto"), "--device", "auto"]) == 0
    for name in ("window_00000.npz", "window_00002.npz"):
        a, b = np.load(tmp_path / "cpu" / name), np.load(tmp_path / "auto" / name)
        for key in ("depth", "twist"):
            np.testing.assert_array_equal(a[key], b[key])
    assert json.loads((tmp_path / "auto" / "summary.json").read_text())["device"] == "cpu"
    capsys.readouterr()
    assert cmax_main(["depth", *base, "-o", str(tmp_path / "gpu"), "--device", "cuda"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sees no CUDA device" in err[0], err
    assert not (tmp_path / "gpu").exists()


def test_the_window_plan_and_the_note_on_the_end_its_windows_leave_out():
    """2.5 s of events in 1 s windows: two windows and a note on the last 0.5 s with a --window [s] whose three
    windows cover the recording; with that window, three windows and no note."""
    from learned.predict import window_plan

    window_us, starts, short = window_plan(0, 2_499_999, 1_000_000, explicit=True)
    assert window_us == 1_000_000 and starts.tolist() == [0, 1_000_000] and short is None
    note = tail_note(0, 2_499_999, window_us, window_us, option="--window", unit_us=1_000_000)
    assert note is not None and "the last 500.0 ms of the recording (after 2.000 s)" in note
    suggested = float(note.split("--window ")[1].split()[0])
    assert note.endswith("covers it in 3 windows") and 0.8 < suggested < 1.0
    window_us, starts, _ = window_plan(0, 2_499_999, int(round(suggested * 1e6)), explicit=True)
    assert len(starts) == 3 and starts[-1] + window_us >= 2_499_999
    assert tail_note(0, 2_499_999, window_us, window_us) is None


def test_t0_t1_of_a_raw_file_too_long_to_hold_read_only_that_span(checkpoint, network, tmp_path, monkeypatch):
    """A Prophesee RAW file over cmax.events.MAX_EVENTS (lowered here under its 400k events, over one chunk's):
    --t0 0.2 --t1 0.4 decode only that span (the file was decoded whole and refused) and predict its windows
    as a direct forward does."""
    events = random_events(400_000, W, H, seed=6, t_span_us=1_000_000)
    path = tmp_path / "long.raw"
    write_evt3(path, events)
    monkeypatch.setattr("cmax.events.MAX_EVENTS", 150_000)
    base = ["depth", str(path), "--checkpoint", str(checkpoint), "--K", K_TEXT, "--quiet"]
    out = tmp_path / "part"
    assert cmax_main([*base, "-o", str(out), "--t0", "0.2", "--t1", "0.4"]) == 0
    first = int(events.t[0])
    expected = _expected(network, events, start=first + 200_000, end=first + 400_000 - 1)
    _check_outputs(out, expected, origin_us=first)


def test_a_whole_raw_file_too_long_to_hold_is_predicted_window_after_window(checkpoint, network, tmp_path,
                                                                           monkeypatch):
    """The same RAW file without --t0 / --t1 (it was refused): decoded window after window
    (cmax.io.prophesee.RawWindows), every window equal to a direct forward."""
    events = random_events(400_000, W, H, seed=6, t_span_us=1_000_000)
    path = tmp_path / "long.raw"
    write_evt3(path, events)
    monkeypatch.setattr("cmax.events.MAX_EVENTS", 150_000)
    out = tmp_path / "all"
    assert cmax_main(["depth", str(path), "--checkpoint", str(checkpoint), "--K", K_TEXT, "--quiet", "-o", str(out)]) == 0
    _check_outputs(out, _expected(network, events))


def test_raw_windows_equal_the_whole_file_cut_and_read_forward(tmp_path):
    from cmax.io.prophesee import RawWindows

    events = random_events(50_000, W, H, seed=7, t_span_us=1_000_000)
    path = tmp_path / "r.raw"
    write_evt3(path, events)
    windows = RawWindows(path, chunk_bytes=2048)
    assert (windows.first_us, windows.last_us, windows.count) == (int(events.t[0]), int(events.t[-1]), len(events))
    starts = np.sort(np.random.default_rng(1).integers(-10_000, 1_100_000, 40))
    for t0, length in zip(starts, np.random.default_rng(2).integers(1, 300_000, 40)):   # overlapping, gaps, empty
        assert windows.window(t0, t0 + length) == events.slice_time(int(t0), int(t0 + length))
    with pytest.raises(ValueError, match="reads forward"):
        windows.window(int(starts[-1]) - 1, int(starts[-1]) + 10)


def test_the_limits_on_a_checkpoints_card_are_said_and_recorded(checkpoint, events, tmp_path, capsys):
    """Was: ``cmax depth`` wrote the shipped student's twists without a word, though its translation pointed
    130-155 deg off on held-out scenes (the model before the odd twist). A card's ``limits`` are printed as notes
    and kept in summary.json; the shipped card states where its translation can be used; a malformed ``limits``
    is one line."""
    import shutil

    from learned import pretrained

    shipped = pretrained.card_limits(pretrained.checkpoint_card(pretrained.CARD))
    assert any("translation direction is usable on drives only" in text for text in shipped)
    # each is printed alone as a note: it cannot point at the card's other fields as 'above' (was: 'test_scores_dense
    # above'), it names the file they are in
    assert not any(" above" in text for text in shipped) and all(
        "student.json" in text for text in shipped if "test_scores_dense" in text)
    card_ckpt = tmp_path / "model.pt"
    shutil.copy(checkpoint, card_ckpt)
    card_ckpt.with_suffix(".json").write_text(json.dumps({"limits": ["its twist points backwards"]}))
    write_h5(tmp_path / "e.h5", events)
    argv = ["depth", str(tmp_path / "e.h5"), "--checkpoint", str(card_ckpt), "--K", K_TEXT, "--quiet"]
    assert cmax_main([*argv, "-o", str(tmp_path / "out")]) == 0
    assert "cmax depth: note: model.pt: its twist points backwards" in capsys.readouterr().err.splitlines()
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert "model.pt: its twist points backwards" in summary["notes"]
    card_ckpt.with_suffix(".json").write_text(json.dumps({"limits": "backwards"}))
    assert cmax_main([*argv, "-o", str(tmp_path / "out2")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "'limits' must be a list of sentences" in err and not (tmp_path / "out2").exists()


def test_depth_range_help_says_it_is_the_colour_scale_only(capsys):
    """`--depth-range` bounds the searched depth in `cmax fit` and `cmax emvs`; in `cmax depth` it colours the
    pictures only (the npz depth is the network's, `test_t0_t1_window_and_depth_range`): the help must say so,
    not leave a user to expect a clamp."""
    with pytest.raises(SystemExit):
        cmax_main(["depth", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "neither clamped nor conditioned by it" in help_text


def test_a_fisheye_camchain_with_a_rectification_maps_the_events_into_the_rectified_frame(checkpoint, network, events,
                                                                                      tmp_path, capsys):
    """A Kalibr camchain of an equidistant (fisheye) camera with rectification_matrix / projection_matrix (MVSEC's
    layout) was refused; the network now sees the events at their rectified positions, as
    cv2.fisheye.undistortPoints(R, P) puts them (spread bilinearly in the volume), and every depth map records
    P's K."""
    R = cv2.Rodrigues(np.array([0.01, -0.02, 0.015]))[0]
    P = np.array([[55.0, 0, 32.0], [0, 55.0, 24.0], [0, 0, 1]])
    D = np.array([-0.05, 0.01, 0.0, 0.0])
    path = tmp_path / "e.h5"
    write_h5(path, events)
    calib = tmp_path / "camchain.yaml"
    calib.write_text("cam0:\n  camera_model: pinhole\n  distortion_model: equidistant\n"
                     f"  distortion_coeffs: [{', '.join(map(str, D))}]\n  intrinsics: [60, 58, 31.5, 23.5]\n"
                     "  resolution: [64, 48]\n  projection_matrix:\n"
                     + "".join(f"  - [{', '.join(map(str, row))}, 0.0]\n" for row in P)
                     + "  rectification_matrix:\n" + "".join(f"  - [{', '.join(map(repr, row.tolist()))}]\n" for row in R))
    out = tmp_path / "out"
    assert cmax_main(["depth", str(path), "-o", str(out), "--checkpoint", str(checkpoint), "--quiet",
                      "--calib", str(calib)]) == 0
    assert "an equidistant (fisheye) lens; the events are undistorted and rectified" in capsys.readouterr().err
    pixels = np.column_stack([events.x, events.y]).astype(np.float64).reshape(-1, 1, 2)
    exact = cv2.fisheye.undistortPoints(pixels, K, D, R=R, P=P, criteria=(
        cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)).reshape(-1, 2)
    xy = np.rint(exact).astype(np.int64)
    inside = (xy[:, 0] >= 0) & (xy[:, 0] < W) & (xy[:, 1] >= 0) & (xy[:, 1] < H)
    rectified = Events(xy[inside, 0], xy[inside, 1], events.t[inside], events.p[inside], W, H)
    assert not np.array_equal(rectified.x, events.x[inside])                               # it moved events
    _check_outputs(out, _expected(network, rectified, start=int(events.t[0]), end=int(events.t[-1]),
                                  pixels=exact[inside]), K_expected=P)   # spread from the exact positions
    summary = json.loads((out / "summary.json").read_text())
    assert summary["distortion_model"] == "equidistant" and summary["rectified"] is True
    np.testing.assert_array_equal(summary["K"], P)
    # the twists are the rectified camera's too (the network saw its pixels), as cmax fit's units say of v, omega
    assert "in which the twists and depth maps are too" in summary["units"]["K"]


def test_raw_dsec_events_are_rectified_into_camrect0_as_dsec_does(checkpoint, network, events, tmp_path):
    """DSEC's layout (events/left/events.h5 without size attributes beside rectify_map.h5, calibration/
    cam_to_cam.yaml): --calib (cam0) maps each event through R_rect0 into camRect0's frame, as DSEC's rectify_map
    (OpenCV's undistortPoints with R=R_rect0, P=K_rect0) does, and the network sees them bilinearly at those
    positions with camRect0's K; --K alone is refused (test_learned_dsec_raw)."""
    from benchmarks.real_cmax import write_dsec_original

    R = cv2.Rodrigues(np.array([0.004, -0.012, 0.009]))[0]
    K_rect = np.array([[62.0, 0, 30.8], [0, 62.0, 24.1], [0, 0, 1]])
    rows = "\n".join(f"  - [{', '.join(repr(float(v)) for v in row)}]" for row in R)
    left, calibration = tmp_path / "seq" / "events" / "left", tmp_path / "seq" / "calibration"
    left.mkdir(parents=True), calibration.mkdir()
    (calibration / "cam_to_cam.yaml").write_text(
        f"extrinsics:\n  R_rect0:\n{rows}\nintrinsics:\n  cam0:\n    camera_matrix: [60, 58, 31.5, 23.5]\n"
        f"    distortion_coeffs: [{', '.join(repr(float(v)) for v in DISTORTION)}]\n    distortion_model: radtan\n"
        f"    resolution: [{W}, {H}]\n  camRect0:\n    camera_matrix: [62.0, 62.0, 30.8, 24.1]\n"
        f"    resolution: [{W}, {H}]\n")
    path = write_dsec_original(left / "events.h5", events)
    (left / "rectify_map.h5").touch()
    out = tmp_path / "out"
    assert cmax_main(["depth", str(path), "-o", str(out), "--checkpoint", str(checkpoint), "--quiet", "--calib",
                      str(calibration / "cam_to_cam.yaml")]) == 0
    exact = cv2.undistortPoints(np.column_stack([events.x, events.y]).astype(np.float64).reshape(-1, 1, 2), K,
                                DISTORTION, R=R, P=K_rect, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                                                                     40, 1e-9)).reshape(-1, 2)
    xy = np.rint(exact).astype(np.int64)
    inside = (xy[:, 0] >= 0) & (xy[:, 0] < W) & (xy[:, 1] >= 0) & (xy[:, 1] < H)
    rectified = Events(xy[inside, 0], xy[inside, 1], events.t[inside], events.p[inside], W, H)
    _check_outputs(out, _expected(network, rectified, start=int(events.t[0]), end=int(events.t[-1]),
                                  pixels=exact[inside]), K_expected=K_rect)
