"""``cmax fit`` on real-recording needs: --size, --t0/--t1, --depth-range, --calib / --distortion, a recording
shorter than the window, a gyro that covers only part of the events, the progress bar and the summary line."""
from __future__ import annotations

import json

import numpy as np
import pytest

from cmax.cli import main
from cmax.cli.recording import calibration_note
from cmax.io import read_calibration
from cmax.events import Events
from cmax.io import write_h5, write_txt
from conftest import MVSEC_LEFT_CAMCHAIN as MVSEC_CAMCHAIN  # MVSEC's left camera, shared with the other tests

cv2 = pytest.importorskip("cv2")

DSEC_YAML = """\
disparity_to_depth:
  cams_03:
  - [1.0, 0.0, 0.0, -335.1]
extrinsics:
  R_rect0:
  - [1.0, 0.0, 0.0]
  - [0.0, 1.0, 0.0]
  - [0.0, 0.0, 1.0]
intrinsics:
  cam0:
    camera_matrix: [553.47, 553.40, 346.65, 216.52]
    camera_model: pinhole
    distortion_coeffs: [-0.0936, 0.1945, 7.6e-05, 0.00196]
    distortion_model: radtan
    resolution: [640, 480]
  camRect0:
    camera_matrix: [569.76, 569.76, 335.10, 221.24]
    camera_model: pinhole
    resolution: [640, 480]
"""


def noise_events(n: int, span_us: int, seed: int) -> Events:
    """``n`` events at random pixels of a 64x48 sensor and random times in ``[0, span_us)`` µs: no motion."""
    rng = np.random.default_rng(seed)
    return Events(rng.integers(0, 64, n), rng.integers(0, 48, n), np.sort(rng.integers(0, span_us, n)),
                  rng.integers(0, 2, n), 64, 48)


#: The layout of DSEC's own cam_to_cam.yaml (and PyYAML's safe_dump): block lists, one ``- value`` line per number,
#: nested block lists for the matrices, a camera's keys in another order than DSEC_YAML's.
DSEC_BLOCK_YAML = """\
intrinsics:
  cam0:
    camera_type: event
    is_rectified: false
    camera_model: pinhole
    distortion_coeffs:
    - -0.0936
    - 0.1945
    - 7.6e-05
    - 0.00196
    distortion_model: radtan
    resolution:
    - 640
    - 480
    camera_matrix:
    - 553.47
    - 553.40
    - 346.65
    - 216.52
  camRect0:
    camera_matrix:
    - 569.76
    - 569.76
    - 335.10
    - 221.24
    resolution:
    - 640
    - 480
  cam1:
    T_cn_cnm1:
    - - 0.99
      - 0.01
    camera_matrix:
    - 1188.2
    - 1187.9
    - 720.6
    - 567.3
extrinsics:
  R_rect0:
  - - 1.0
    - 0.0
    - 0.0
  - - 0.0
    - 1.0
    - 0.0
  - - 0.0
    - 0.0
    - 1.0
"""


def test_dsec_block_lists_are_read(tmp_path):
    """DSEC writes its lists in block style; they were refused as 'no intrinsics/cam0 (cameras found: cam0,
    camRect0, camera_matrix, distortion_coeffs, resolution)': the keys with a block list below them counted as
    cameras."""
    yaml = tmp_path / "cam_to_cam.yaml"
    yaml.write_text(DSEC_BLOCK_YAML)
    K, distortion, size = read_calibration(yaml)[:3]
    assert (K[0, 0], K[1, 1], K[0, 2], K[1, 2]) == (553.47, 553.40, 346.65, 216.52) and size == (640, 480)
    np.testing.assert_array_equal(distortion, [-0.0936, 0.1945, 7.6e-05, 0.00196])
    K, distortion, size = read_calibration(yaml, "camRect0")[:3]
    assert K[0, 0] == 569.76 and K[1, 2] == 221.24 and distortion is None and size == (640, 480)
    K, _, size = read_calibration(yaml, "cam1")[:3]
    assert K[0, 0] == 1188.2 and size is None
    with pytest.raises(ValueError, match=r"no intrinsics/cam9 \(cameras found: cam0, cam1, camRect0\)"):
        read_calibration(yaml, "cam9")


def test_calibration_files(tmp_path):
    ecd = tmp_path / "calib.txt"
    ecd.write_text("199.09 199.09 132.19 110.14 -0.368 0.150 -0.0003 -0.0002 0.0\n")
    K, distortion, size = read_calibration(ecd)[:3]
    assert K[0, 0] == 199.09 and K[1, 2] == 110.14 and size is None
    np.testing.assert_array_equal(distortion, [-0.368, 0.150, -0.0003, -0.0002, 0.0])
    yaml = tmp_path / "cam_to_cam.yaml"
    yaml.write_text(DSEC_YAML)
    K, distortion, size = read_calibration(yaml)[:3]
    assert (K[0, 0], K[1, 1], K[0, 2], K[1, 2]) == (553.47, 553.40, 346.65, 216.52) and size == (640, 480)
    np.testing.assert_array_equal(distortion, [-0.0936, 0.1945, 7.6e-05, 0.00196])
    K, distortion, size = read_calibration(yaml, "camRect0")[:3]
    assert K[0, 0] == 569.76 and distortion is None
    with pytest.raises(ValueError, match=r"no intrinsics/cam9 \(cameras found: cam0, camRect0\)"):
        read_calibration(yaml, "cam9")
    (tmp_path / "bad.txt").write_text("1 2 3\n")
    with pytest.raises(ValueError, match="fx fy cx cy"):
        read_calibration(tmp_path / "bad.txt")
    with pytest.raises(FileNotFoundError):
        read_calibration(tmp_path / "none.txt")


@pytest.fixture(scope="module")
def slider(tmp_path_factory):
    from benchmarks.synthetic_windows import make_window

    w = make_window("slider", 7, width=96, height=72, focal=72.0, duration_s=0.2)
    folder = tmp_path_factory.mktemp("fit_cli")
    return w, write_txt(folder / "slider.txt", w.events), folder


@pytest.mark.slow   # one fit: about 10 s on 2 shared cores
def test_fit_options_short_recording_and_gyro_overlap(slider, tmp_path, capsys):
    """One run: a .txt file (--size W,H), --t0/--t1, an ECD calib.txt, --depth-range, a window longer than
    the (cut) recording and a gyro that starts late: one window over the overlap, with two notes. (The wall lies
    at 3.06 m: a range of 1-3 m put the depth on its far bound, a failed window, exit 1.)"""
    w, path, _ = slider
    first = int(w.events.t[0])
    calib = tmp_path / "calib.txt"
    calib.write_text(f"{w.K[0, 0]} {w.K[1, 1]} {w.K[0, 2]} {w.K[1, 2]} 0 0 0 0 0\n")
    gyro = tmp_path / "gyro.txt"
    times = np.arange(first + 80_000, first + 200_000, 1000)            # starts 30 ms after --t0
    gyro.write_text("".join(f"{t * 1e-6:.6f} 0 0 0\n" for t in times))
    out = tmp_path / "out"
    argv = ["fit", str(path), "--size", "96,72", "--calib", str(calib), "-o", str(out), "--t0", "0.05",
            "--t1", "0.15", "--depth-range", "1,4", "--window-ms", "500", "--gyro", str(gyro),
            "--max-events", "4000", "--depth-grid", "12,16"]
    assert main(argv) == 0
    captured = capsys.readouterr()
    assert "the gyro samples of" in captured.err and " cover " in captured.err and "fitting the overlap" in captured.err
    assert "the span of --t0/--t1 (" in captured.err
    assert "is shorter than the window (500.0 ms): fitting one window over it" in captured.err
    assert "windows: 100%" in captured.err and "1/1" in captured.err           # the progress bar
    assert "1 of 1 windows fitted" in captured.out
    summary = json.loads((out / "summary.json").read_text())
    (window,) = summary["windows"]
    assert window["t0_us"] >= times[0] and window["t1_us"] <= first + 150_000     # the gyro overlap of [t0, t1)
    assert window["t1_us"] - window["t0_us"] > 60_000                              # the whole overlap
    np.testing.assert_allclose(window["omega"], 0.0)                               # held at the gyro's
    # No --speed: v is a direction (a unit vector) and the units say so, as trajectory.txt's header does.
    assert np.linalg.norm(window["v"]) == pytest.approx(1.0, rel=1e-6)
    assert summary["units"]["v"].startswith("unit vector (no --speed")
    assert summary["units"]["depth_range"] == "m at a speed of 1 m/s (no --speed: up to scale)"
    assert summary["depth_range"] == [1.0, 4.0] and summary["calib"] == str(calib)
    assert summary["depth_grid"] == [12, 16]
    depth = np.load(out / "depth_00000.npz")
    assert depth["inverse_depth_grid"].shape == (12, 16)
    inside = depth["depth"][depth["mask"]]
    assert inside.size and inside.min() >= 1.0 - 1e-6 and inside.max() <= 4.0 + 1e-6


def test_a_depth_range_without_speed_is_said_to_be_in_units_of_the_speed(tmp_path, capsys):
    """`--depth-range 0.47,2.4` (the ECD slider's range in metres) without --speed bounded depths that the fit
    measures at 1 m/s: the slider moves at about 0.3 m/s, so its scene lay at 1.6-8 in those units, 44% of the
    depth on the far bound and 4 of 5 windows ambiguous, without a word on the unit. Now a note says so; with
    --speed (metres) there is none."""
    path = write_h5(tmp_path / "few.h5", noise_events(300, 50_000, seed=1))
    base = ["fit", str(path), "--K", "60,60,32,24", "--quiet", "--depth-range", "0.5,2"]
    main([*base, "-o", str(tmp_path / "a")])
    err = capsys.readouterr().err
    assert "note: without --speed the fit's depths are in units of the speed x 1 s" in err, err
    assert "at 0.3 m/s a scene at 0.5-2 m lies at 1.67-6.67 in these units" in err, err        # 0.5 / 0.3, 2 / 0.3
    notes = json.loads((tmp_path / "a" / "summary.json").read_text())["notes"]
    assert any(note.startswith("without --speed the fit's depths") for note in notes)
    main([*base, "--speed", "0.3", "-o", str(tmp_path / "b")])
    assert "without --speed" not in capsys.readouterr().err


def test_no_window_with_enough_events_exits_1(tmp_path, capsys):
    events = noise_events(300, 50_000, seed=1)
    path = write_h5(tmp_path / "few.h5", events)
    assert main(["fit", str(path), "--K", "60,60,32,24", "-o", str(tmp_path / "o"), "--quiet"]) == 1
    captured = capsys.readouterr()
    assert "0 of 1 windows fitted, 1 skipped (fewer than 1,000 events)" in captured.out
    assert "no window was fitted" in captured.err
    notes = json.loads((tmp_path / "o" / "summary.json").read_text())["notes"]
    assert any("no window was fitted" in note for note in notes)
    # A window a hair shorter than the recording leaves an end too short to name: no note (was "note: None").
    window_ms = (int(events.t[-1]) - int(events.t[0]) + 1) / 1000 - 0.05
    assert main(["fit", str(path), "--K", "60,60,32,24", "-o", str(tmp_path / "o2"), "--quiet",
                 "--window-ms", f"{window_ms:.3f}"]) == 1
    assert "None" not in capsys.readouterr().err
    assert "a longer --window-ms or a lower --min-events (at least 10) fits them" in captured.err
    assert "pass a longer window_us or a lower min_events" in captured.err         # fit_sequence's own warning
    assert main(["fit", str(path), "--K", "60,60,32,24", "-o", str(tmp_path / "o"), "--quiet", "--min-events", "9"]) == 2
    assert "--min-events must be at least 10" in capsys.readouterr().err
    status = main(["fit", str(path), "--K", "60,60,32,24", "-o", str(tmp_path / "o"), "--quiet", "--min-events", "300",
                   "--max-events", "300", "--depth-grid", "6,8", "--overwrite"])
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["min_events"] == 300 and len(summary["windows"]) == 1 and summary["skipped_us"] == []
    # Noise: nothing to be sure of. Whether the window fails or is called low parallax turns on the last bits of
    # the solvers (it differs between scipy / numba releases); the exit status follows the verdict either way.
    verdict = summary["windows"][0]["verdict"]
    assert verdict in ("failed", "low parallax", "ambiguous")
    assert status == (1 if verdict == "failed" else 0)


@pytest.mark.parametrize("extra, message", [
    (["--calib", "CALIB", "--distortion", "0,0,0,0"], "pass --calib or --K with --distortion, not both"),
    (["--calib", "YAML"], "calibrates a 640x480 camera (cam0), the events come from a 64x48 sensor"),
    (["--calib", "YAML", "--calib-camera", "left"], "no intrinsics/left"),
    # --calib-camera where it chooses nothing (was: taken and ignored, the fit ran on the only camera there is):
    (["--calib", "CALIB", "--calib-camera", "camRect0"], "calibrates one camera (ECD calib.txt): camera 'camRect0'"),
    (["--K", "60,60,32,24", "--calib-camera", "cam1"], "--calib-camera cam1 chooses a camera of a --calib file"),
    (["--K", "60,60,32,24", "--gyro", "GYRO"], "do not overlap the events"),
    (["--K", "60,60,32,24", "--t0", "1", "--t1", "0.5"], "--t1 must be after --t0"),
    (["--K", "60,60,32,24", "--t1", "0"], "--t1 must be after --t0, got 0.0 (the first event, --t0 left out) and 0.0"),
    (["--K", "60,60,32,24", "--t0", "0.2"], "--t0 0.2 s is past the recording's last event ("),
    (["--K", "60,60,32,24", "-o", "CALIB"], "is a file, not a folder"),
    (["--K", "60,60,32,24", "--depth-range", "3,nan"], "argument --depth-range"),
    (["--K", "60,60,32,24", "--depth-range", "5,1"], "--depth-range must satisfy 0 < near < far"),  # before the bar
    (["--K", "60,60,32,24", "--depth-grid", "24,0"], "argument --depth-grid"),
    (["--K", "60,60,32,24", "--depth-grid", "49,32"], "finer than the image 48x64 (rows x columns; cmax fit: "
                                                      "--depth-grid ROWS,COLS)"),
    (["--K", "60,60,32,24", "--distortion", "1,2"], "argument --distortion"),
    (["--K", "60,60,32,24", "--size", "64;48"], "argument --size"),
    (["--K", "60,60,32,24", "--omega", "0,0,0", "--gyro", "GYRO"], "pass one of them"),
    (["--K", "60,60,32,24", "--omega", "0,0"], "argument --omega"),
    (["--K", "60,60,32,24", "--omega", "0,0,0", "--model", "flow"], "--omega applies to --model se3"),
    ([], "stores no intrinsics (gt/K): give them with --K fx,fy,cx,cy or --calib"),
])
def test_fit_option_errors_are_one_line(tmp_path, capsys, extra, message):
    events = noise_events(300, 50_000, seed=1)
    path = write_h5(tmp_path / "ev.h5", events)
    (tmp_path / "calib.txt").write_text("60 60 32 24\n")
    (tmp_path / "cam_to_cam.yaml").write_text(DSEC_YAML)
    (tmp_path / "gyro.txt").write_text("10.0 0 0 0\n10.1 0 0 0\n")
    names = {"CALIB": "calib.txt", "YAML": "cam_to_cam.yaml", "GYRO": "gyro.txt"}
    extra = [str(tmp_path / names[a]) if a in names else a for a in extra]
    try:
        status = main(["fit", str(path), "-o", str(tmp_path / "o"), *extra])
    except SystemExit as exit_:
        status = exit_.code
    err = capsys.readouterr().err
    assert status == 2 and message in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.parametrize("layout", ["ecd", "dsec"])
def test_the_no_intrinsics_error_names_the_calibration_beside_the_events(tmp_path, capsys, layout):
    """A data set's events given without --K / --calib: the one-line error names the calibration file that lies
    beside them, as the note of a run with --K does (was: only 'give them with --K fx,fy,cx,cy or --calib',
    though ECD's calib.txt lay in the same folder and DSEC's cam_to_cam.yaml in <sequence>/calibration/)."""
    events = noise_events(300, 50_000, seed=1)
    if layout == "ecd":
        path = write_txt(tmp_path / "events.txt", events)
        calib = tmp_path / "calib.txt"
        calib.write_text("60 60 32 24 0 0 0 0 0\n")
        size = ["--size", "64x48"]
    else:
        (tmp_path / "events" / "left").mkdir(parents=True)
        (tmp_path / "calibration").mkdir()
        path = write_h5(tmp_path / "events" / "left" / "events.h5", events)
        calib = tmp_path / "calibration" / "cam_to_cam.yaml"
        calib.write_text(DSEC_YAML)
        size = []
    assert main(["fit", str(path), *size, "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert f"{calib.resolve()} lies beside the events: --calib {calib.resolve()}" in err, err
    assert ("--calib-camera cam0" in err) == (layout == "dsec"), err


def test_a_text_file_takes_its_size_from_the_dsec_calibration(tmp_path, capsys):
    """ECD .txt stores no sensor size: cam_to_cam.yaml's resolution (640x480) is used, so the file reads (no
    'pass width= and height=' error); its 300 events are too few to fit, which the command says (exit 1)."""
    rng = np.random.default_rng(2)
    events = Events(rng.integers(0, 640, 300), rng.integers(0, 480, 300), np.sort(rng.integers(0, 50_000, 300)),
                    rng.integers(0, 2, 300), 640, 480)
    path = write_txt(tmp_path / "ev.txt", events)
    (tmp_path / "cam_to_cam.yaml").write_text(DSEC_YAML)
    assert main(["fit", str(path), "--calib", str(tmp_path / "cam_to_cam.yaml"), "--calib-camera", "camRect0",
                 "-o", str(tmp_path / "o"), "--quiet"]) == 1
    assert "0 of 1 windows fitted" in capsys.readouterr().out
    assert main(["fit", str(path), "--K", "500,500,320,240", "-o", str(tmp_path / "o2")]) == 2
    assert "width= and height=" in capsys.readouterr().err


@pytest.mark.slow   # two real fits and their ambiguity tests: about 10 s on 2 shared cores
def test_fit_prints_each_verdict_and_counts_them(tmp_path, capsys):
    """Each window's verdict on a line of its own and in summary.json; the summary line counts them."""
    from benchmarks.synthetic_windows import make_window

    w = make_window("driving", 2, width=120, height=90, focal=90.0, duration_s=0.1, max_frames=60)
    path = write_h5(tmp_path / "drive.h5", w.events)
    K = ",".join(f"{v:g}" for v in (w.K[0, 0], w.K[1, 1], w.K[0, 2], w.K[1, 2]))
    out = tmp_path / "out"
    speed = float(np.linalg.norm(w.twist[:3]))
    assert main(["fit", str(path), "--K", K, "-o", str(out), "--window-ms", "45", "--speed", f"{speed}",
                 "--depth-range", "1,20", "--max-events", "4000"]) == 0
    printed = capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    verdicts = [window["verdict"] for window in summary["windows"]]
    assert len(verdicts) == 2 and set(verdicts) <= {"ok", "ambiguous", "low_parallax", "failed"}
    for i, window in enumerate(summary["windows"]):
        line = next(line for line in printed.splitlines() if line.startswith(f"window {i} ("))
        assert f": {window['verdict'].replace('_', ' ')}: {window['reason']}" in line
    counts = {name: verdicts.count(name) for name in ("ok", "ambiguous", "low_parallax", "failed")}
    assert {k: summary["verdicts"][k] for k in counts} == counts
    assert (f"2 of 2 windows fitted: {counts['ok']} ok, {counts['ambiguous']} ambiguous"
            in printed), printed
    assert f"{counts['low_parallax']} low parallax, {counts['failed']} failed; results in" in printed


def test_the_summary_counts_each_verdict(tmp_path, capsys, monkeypatch):
    """Five windows (the first with too few events, skipped), the fits of the others constructed with the
    verdicts ambiguous (no ok neighbour within reach, so unresolved), failed, low parallax and ok: one
    line each, the JSON and the summary line agree."""
    from dataclasses import replace

    from benchmarks.synthetic_windows import make_window
    from cmax.fitting import QualitySettings, Verdict, fit
    from cmax.fitting import sequence as sequence_module
    from cmax.fitting.quality import Alternative, Quality

    w = make_window("driving", 2, width=120, height=90, focal=90.0, duration_s=0.1, max_frames=60)
    base = fit(w.events, w.K, speed=8.0, depth_range=(1.0, 20.0), max_events=1000,
               quality=QualitySettings(ambiguity_test=False))
    mirrored = Alternative("mirrored", -base.v, base.omega, 0.01, 0.1, True)
    qualities = [Quality(Verdict.AMBIGUOUS, "mirrored within noise", (mirrored,)),
                 Quality(Verdict.FAILED, "stage(s) failed: local_refine"),
                 Quality(Verdict.LOW_PARALLAX, "parallax 0.40 px, under LOW_PARALLAX_PX=1"),
                 Quality(Verdict.OK, "every alternative scores worse beyond noise")]

    def constructed_fit(events, K, model="se3", **options):
        return replace(base, t0_us=int(events.t[0]), t1_us=int(events.t[-1]), quality=qualities.pop(0))

    monkeypatch.setattr(sequence_module, "fit", constructed_fit)
    path = write_h5(tmp_path / "drive.h5", w.events)
    K = ",".join(f"{v:g}" for v in (w.K[0, 0], w.K[1, 1], w.K[0, 2], w.K[1, 2]))
    out = tmp_path / "out"
    assert main(["fit", str(path), "--K", K, "-o", str(out), "--window-ms", "19", "--quiet"]) == 0
    printed = capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert [window["verdict"] for window in summary["windows"]] == ["ambiguous", "failed", "low_parallax", "ok"]
    assert summary["verdicts"] == {"ok": 1, "ambiguous": 1, "low_parallax": 1, "failed": 1, "resolved": 0}
    assert summary["skipped_us"] == [int(w.events.t[0])]                     # the first window: too few events
    assert summary["windows"][0]["resolution"] == "unresolved: no confident (ok) neighbour window"
    assert "window 0 (" in printed and ": ambiguous: mirrored within noise; unresolved: no confident" in printed
    assert ("4 of 5 windows fitted, 1 skipped (fewer than 1,000 events): 1 ok, 1 ambiguous (0 resolved), "
            "1 low parallax, 1 failed; results in"
            in printed), printed


def test_a_run_whose_every_window_failed_exits_1_and_the_summary_records_what_was_said(tmp_path, capsys, monkeypatch):
    """Every fitted window failed: exit 1 (it was 0) with a note; the same warning of each window is printed once
    with its count and recorded in summary.json (it was printed per window, recorded nowhere); the summary's notes
    hold every note printed (the late ones were missing) and depth_range the range used (it was null)."""
    import warnings
    from dataclasses import replace

    from benchmarks.synthetic_windows import make_window
    from cmax.fitting import FitSettings, LowParallaxWarning, QualitySettings, Verdict, fit
    from cmax.fitting import sequence as sequence_module
    from cmax.fitting.quality import Quality

    w = make_window("driving", 2, width=120, height=90, focal=90.0, duration_s=0.1, max_frames=60)
    base = fit(w.events, w.K, speed=8.0, depth_range=(1.0, 20.0), max_events=1000,
               quality=QualitySettings(ambiguity_test=False))
    parallax = iter([0.25, 0.5, 0.75, 1.0])

    def failing_fit(events, K, model="se3", **options):
        warnings.warn(f"parallax {next(parallax)} px", LowParallaxWarning)
        return replace(base, t0_us=int(events.t[0]), t1_us=int(events.t[-1]),
                       quality=Quality(Verdict.FAILED, "stage(s) failed: local_refine"))

    monkeypatch.setattr(sequence_module, "fit", failing_fit)
    path = write_h5(tmp_path / "drive.h5", w.events)
    K = ",".join(f"{v:g}" for v in (w.K[0, 0], w.K[1, 1], w.K[0, 2], w.K[1, 2]))
    out = tmp_path / "out"
    assert main(["fit", str(path), "--K", K, "-o", str(out), "--window-ms", "24", "--min-events", "10",
                 "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.count("LowParallaxWarning") == 1
    assert "cmax fit: warning: LowParallaxWarning (4 times, windows 0-3; the first): window 0: parallax 0.25 px" in err
    assert "cmax fit: note: every fitted window failed (4)" in err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["verdicts"]["failed"] == 4 and len(summary["windows"]) == 4
    # each window names itself, its depth file and whether its fit succeeded (an audit: neither was recorded)
    assert [(w["index"], w["depth_file"], w["success"]) for w in summary["windows"]] == \
        [(i, f"depth_{i:05d}.npz", base.success) for i in range(4)]
    assert all((out / w["depth_file"]).is_file() for w in summary["windows"])
    assert summary["warnings"] == [{"category": "LowParallaxWarning", "count": 4, "windows": [0, 1, 2, 3],
                                    "message": "window 0: parallax 0.25 px"}]
    printed_notes = [line.removeprefix("cmax fit: note: ") for line in err.splitlines() if "cmax fit: note: " in line]
    assert summary["notes"] == printed_notes and len(printed_notes) >= 2          # the tail note and the failure
    assert summary["depth_range"] == list(FitSettings().depth_range)


def test_jobs_fit_the_windows_in_parallel_from_cold_starts(slider, tmp_path, capsys):
    """``--jobs 2``: two flow windows fitted by worker processes; each equals ``cmax.fit`` of that window alone
    (no warm start), bit for bit, and the summary says how they were fitted."""
    from cmax.fitting import fit

    w, path, _ = slider
    out = tmp_path / "out"
    argv = ["fit", str(path), "--size", "96,72", "--K", "72,72,48,36", "-o", str(out), "--model", "flow",
            "--window-ms", "90", "--jobs", "2", "--quiet"]
    assert main(argv) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["jobs"] == 2 and summary["warm_start"] is False and len(summary["windows"]) == 2
    first = int(w.events.t[0])
    for k, window in enumerate(summary["windows"]):
        t0 = first + k * 90_000
        alone = fit(w.events.slice_time(t0, t0 + 90_000), np.array([[72.0, 0, 48], [0, 72.0, 36], [0, 0, 1]]),
                    "flow")
        assert window["flow"] == alone.flow.tolist()
    try:
        status = main([*argv[:-3], "--jobs", "0"])
    except SystemExit as exit_:
        status = exit_.code
    assert status == 2 and "--jobs" in capsys.readouterr().err


def test_omega_holds_a_known_rotation_in_every_window(slider, tmp_path):
    """``--omega 0.1,0,0``: every window's rotation is the given one (held, as a gyroscope's), said in the summary."""
    w, path, _ = slider
    out = tmp_path / "out"
    argv = ["fit", str(path), "--size", "96,72", "--K", "72,72,48,36", "-o", str(out), "--speed", "0.5",
            "--window-ms", "90", "--omega", "0.1,0,0", "--max-events", "4000", "--quiet"]
    assert main(argv) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["omega"] == [0.1, 0.0, 0.0] and len(summary["windows"]) == 2
    for window in summary["windows"]:
        np.testing.assert_allclose(window["omega"], [0.1, 0.0, 0.0], atol=1e-12)


def test_an_h5_file_with_its_own_intrinsics_needs_no_K(tmp_path, capsys):
    """A file written by ``cmax scene`` stores ``gt/K``: ``cmax fit`` uses it when no --K or --calib is given."""
    import h5py

    scene = tmp_path / "scene.h5"
    assert main(["scene", "slider", "-o", str(scene), "--duration", "0.25", "--size", "96x72", "--seed", "3"]) == 0
    with h5py.File(scene, "r") as file:
        K = np.asarray(file["gt/K"][()])
    out = tmp_path / "out"
    assert main(["fit", str(scene), "-o", str(out), "--model", "flow", "--window-ms", "200", "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    np.testing.assert_array_equal(summary["K"], K)


def test_se3_takes_the_depth_range_the_file_records_for_its_scene(slider_file, tmp_path, capsys):
    """``cmax emvs`` took the depth range a ``cmax scene`` file records, ``cmax fit`` the library's 0.5-60 m (an
    audit: abs_rel 0.290 against 0.211 with the room's range). Both take it now, with a note; --depth-range wins."""
    import h5py

    with h5py.File(slider_file, "r") as file:
        recorded = json.loads(file.attrs["scene"])["depth_range_m"]
    argv = ["fit", str(slider_file), "--speed", "0.3", "--window-ms", "150", "--quiet"]
    assert main([*argv, "-o", str(tmp_path / "a")]) in (0, 1)
    err = capsys.readouterr().err
    assert f"note: depth over {recorded[0]:g}-{recorded[1]:g} m, the depth range the file records" in err, err
    summary = json.loads((tmp_path / "a" / "summary.json").read_text())
    assert summary["depth_range"] == recorded and any("the file records" in n for n in summary["notes"])
    assert main([*argv, "-o", str(tmp_path / "b"), "--depth-range", "0.5,9"]) in (0, 1)
    assert "the file records" not in capsys.readouterr().err
    assert json.loads((tmp_path / "b" / "summary.json").read_text())["depth_range"] == [0.5, 9.0]


def test_the_help_of_depth_range_says_a_scene_file_brings_its_own():
    """``cmax fit --help`` said ``--depth-range ... (default: 0.5,60)`` alone, while a file that records its scene's
    range (every ``cmax scene`` file) is fitted over that range (the test above): the help names both, as
    ``cmax emvs --help`` does."""
    import argparse

    from cmax.cli import build_parser
    from cmax.fitting.settings import FitSettings

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices["fit"]
    text = " ".join(sub.format_help().split())
    near, far = FitSettings().depth_range
    assert (f"the range the file records for its scene (cmax scene), else (default: {near:g},{far:g})"
            in text), text


def test_the_help_of_fit_says_what_it_writes():
    """``cmax fit --help`` opened with "The cmax fit command: fit a recording window by window ..." (its module's
    docstring); it says what the command does and the files it writes, as the other commands' help does."""
    import argparse

    from cmax.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices["fit"]
    assert not sub.description.startswith("The ")
    for name in ("depth_00000.npz and .png per window", "trajectory.txt", "summary.json", "verdict", "up to scale"):
        assert name in sub.description, (name, sub.description)


def test_the_advice_names_what_helps_when_half_the_windows_are_unmeasured():
    from cmax.cli.fit import advice

    counts = {"ok": 2, "ambiguous": 0, "resolved": 0, "low_parallax": 2, "failed": 0}
    (line,) = advice(counts, "se3")
    assert line.startswith("2 of 4 windows have too little parallax") and "--model rotation" in line
    (line,) = advice(counts, "rotation")
    assert "too little motion" in line and "--model rotation" not in line
    assert advice({**counts, "low_parallax": 1}, "se3") == []            # 1 of 3: the windows mostly measure
    ambiguous = {"ok": 1, "ambiguous": 3, "resolved": 1, "low_parallax": 0, "failed": 0}
    (line,) = advice(ambiguous, "se3")                                    # 2 unresolved of 4
    assert line.startswith("2 of 4 windows stay ambiguous") and "--omega 0,0,0" in line
    (line,) = advice(ambiguous, "se3", rotation_known=True)
    assert "--gyro" not in line and "longer --window-ms" in line
    assert advice({**ambiguous, "resolved": 3}, "se3") == []               # all resolved by their neighbours
    # windows where the camera starts or stops: a shorter window, not a longer one
    first, second = advice({"ok": 1, "ambiguous": 3, "resolved": 0, "low_parallax": 0, "failed": 0}, "se3",
                           unsteady=1)
    assert first.startswith("2 of 4 windows stay ambiguous (an alternative motion") and "longer" in first
    assert second.startswith("1 of 4 windows stay ambiguous because the camera starts or stops")
    assert "shorter --window-ms" in second
    (line,) = advice({"ok": 1, "ambiguous": 3, "resolved": 0, "low_parallax": 0, "failed": 0}, "se3", unsteady=3)
    assert "starts or stops" in line
    # a flow that sharpens only parts of the image: too little motion, or parts that move differently
    (line,) = advice(counts, "flow", cell_noise=2)
    assert line.startswith("2 of 4 windows have a fitted flow that sharpens only parts of the image")
    assert "longer --window-ms" in line and "--model se3 or a shorter --window-ms" in line
    first, second = advice({**counts, "low_parallax": 3, "ok": 1}, "flow", cell_noise=1)
    assert first.startswith("2 of 4 windows have too little motion") and second.startswith("1 of 4 windows have")


def test_a_recording_without_motion_is_called_so(tmp_path, capsys):
    """Sensor noise (uniform events, no motion): every window low parallax by the permutation test, and the
    advice says that a longer window is no cure."""
    rng = np.random.default_rng(0)
    n = 30_000
    events = Events(rng.integers(0, 160, n), rng.integers(0, 120, n), np.sort(rng.integers(0, 400_000, n)),
                    rng.integers(0, 2, n), 160, 120)
    path = write_h5(tmp_path / "noise.h5", events)
    assert main(["fit", str(path), "--K", "100,100,80,60", "-o", str(tmp_path / "o"), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "2 of 2 windows fitted: 0 ok, 0 ambiguous, 2 low parallax" in captured.out
    assert "2 of them show no motion at all" in captured.err and "check the recording" in captured.err
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert [w["cause"] for w in summary["windows"]] == ["no_motion", "no_motion"]


def test_a_window_where_the_camera_stops_is_called_unsteady_and_a_shorter_window_advised(tmp_path, capsys):
    """A street window whose second half keeps one event in ten (the camera slowing to a near stop), alone in
    its recording: ambiguous and unsteady, no neighbour to resolve it from, and the advice says that a shorter
    window, not a longer one, helps; summary.json carries the rate change."""
    from benchmarks.synthetic_windows import make_window

    w = make_window("driving", 2, width=120, height=90, focal=90.0, duration_s=0.1, max_frames=60)
    t = w.events.t
    keep = (t < t[0] + (t[-1] - t[0]) / 2) | (np.arange(len(t)) % 10 == 0)
    keep[-1] = True
    path = write_h5(tmp_path / "stop.h5", w.events[np.flatnonzero(keep)])
    K = ",".join(f"{v:g}" for v in (w.K[0, 0], w.K[1, 1], w.K[0, 2], w.K[1, 2]))
    speed = f"{float(np.linalg.norm(w.twist[:3])):.6g}"
    assert main(["fit", str(path), "--K", K, "--speed", speed, "--depth-range", "1,20", "--window-ms", "100",
                 "-o", str(tmp_path / "o"), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "1 of 1 windows fitted: 0 ok, 1 ambiguous (0 resolved)" in captured.out
    assert "1 of 1 windows stay ambiguous because the camera starts or stops" in captured.err
    assert "a longer --window-ms tells them apart" not in captured.err
    (window,) = json.loads((tmp_path / "o" / "summary.json").read_text())["windows"]
    assert window["unsteady"] and window["rate_change"] > 6 and window["verdict"] == "ambiguous"
    assert window["resolution"].startswith("unresolved: the motion is not steady over the window and fewer than")


def test_a_calibration_file_beside_the_events_is_named_not_read(tmp_path, capsys):
    """An ECD folder ships calib.txt beside its events: `cmax fit --K` (a pinhole) says it is there and how to
    use it, and does not read it; with --calib the note goes."""
    events = noise_events(3000, 100_000, seed=3)
    path = write_h5(tmp_path / "ev.h5", events)
    calib = tmp_path / "calib.txt"
    calib.write_text("60 60 32 24 -0.1 0.05 0 0 0\n")
    # Random events: the one window fails or is low parallax (which of the two turns on the solvers' last bits and
    # differs between scipy / numba releases), never ok; the exit status follows the verdict; the note is the point.
    for out, option in (("a", ["--K", "60,60,32,24"]), ("b", ["--calib", str(calib)])):
        status = main(["fit", str(path), *option, "-o", str(tmp_path / out), "--quiet"])
        err = capsys.readouterr().err
        summary = json.loads((tmp_path / out / "summary.json").read_text())
        assert summary["verdicts"]["ok"] == 0 and status == (1 if summary["verdicts"]["failed"] == 1 else 0)
        if out == "a":
            assert f"{calib} lies beside the events but was not read: pass --calib {calib}" in err
            assert summary["distortion"] is None and summary["calib"] is None
        else:
            assert "lies beside the events" not in err and summary["calib"] is not None


def test_the_end_that_no_whole_window_covers_is_named_with_a_window_that_tiles(tmp_path, capsys, monkeypatch):
    """40 ms windows on a 100 ms recording leave its last 20 ms out: a note says how long, from when, how many
    events, and which --window-ms covers it; summary.json records the span; that window leaves nothing out."""
    import re
    from dataclasses import replace

    from benchmarks.synthetic_windows import make_window
    from cmax.fitting import QualitySettings, fit
    from cmax.fitting import sequence as sequence_module

    w = make_window("driving", 2, width=120, height=90, focal=90.0, duration_s=0.1, max_frames=60)
    base = fit(w.events, w.K, speed=8.0, depth_range=(1.0, 20.0), max_events=1000,
               quality=QualitySettings(ambiguity_test=False))
    monkeypatch.setattr(sequence_module, "fit", lambda events, K, model="se3", **options: replace(
        base, t0_us=int(events.t[0]), t1_us=int(events.t[-1])))
    path = write_h5(tmp_path / "drive.h5", w.events)
    K = ",".join(f"{v:g}" for v in (w.K[0, 0], w.K[1, 1], w.K[0, 2], w.K[1, 2]))
    first, last = int(w.events.t[0]), int(w.events.t[-1])
    assert 95_000 < last - first < 100_000
    out = tmp_path / "out"
    assert main(["fit", str(path), "--K", K, "-o", str(out), "--window-ms", "40", "--quiet"]) == 0
    err = capsys.readouterr().err
    left = int(np.sum(w.events.t >= first + 80_000))
    match = re.search(r"note: the last ([\d.]+) ms of the recording \(after 0\.080 s, ([\d,]+) events\) are shorter "
                      r"than a window \(40\.0 ms\) and are left out: --window-ms ([\d.]+) covers it in 3 windows", err)
    assert match, err
    assert float(match[1]) == pytest.approx((last + 1 - first - 80_000) * 1e-3, abs=0.05)
    assert int(match[2].replace(",", "")) == left > 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["uncovered_us"] == [first + 80_000, last + 1] and summary["windows_total"] == 2
    assert any("are left out" in note for note in summary["notes"])
    again = tmp_path / "again"
    assert main(["fit", str(path), "--K", K, "-o", str(again), "--window-ms", match[3], "--quiet"]) == 0
    assert "left out" not in capsys.readouterr().err
    summary = json.loads((again / "summary.json").read_text())
    assert summary["windows_total"] == 3
    # windows of whole µs cannot always divide the recording: they leave out at most its last 2 µs
    assert summary["uncovered_us"] is None or summary["uncovered_us"][1] - summary["uncovered_us"][0] < 3


def test_t0_t1_spanning_whole_windows_fit_them_all(tmp_path, capsys, monkeypatch):
    """--t0 0.6 --t1 0.8 --window-ms 100: the events inside end a few µs before 0.8 s and start a few after 0.6,
    so the second window ended after the last event and was left out (1 window and a note to use 99.993 ms).
    A window that ends within 1% of its length after the last event is whole."""
    from dataclasses import replace

    from benchmarks.synthetic_windows import make_window
    from cmax.fitting import QualitySettings, fit
    from cmax.fitting import sequence as sequence_module

    w = make_window("driving", 2, width=120, height=90, focal=90.0, duration_s=0.1, max_frames=60)
    base = fit(w.events, w.K, speed=8.0, depth_range=(1.0, 20.0), max_events=1000,
               quality=QualitySettings(ambiguity_test=False))
    monkeypatch.setattr(sequence_module, "fit", lambda events, K, model="se3", **options: replace(
        base, t0_us=int(events.t[0]), t1_us=int(events.t[-1])))
    rng = np.random.default_rng(5)
    t = np.sort(rng.choice(np.arange(3, 1_000_000), 200_000, replace=False))   # first event at >= 3 µs
    events = Events(rng.integers(0, 120, t.size), rng.integers(0, 90, t.size), t, rng.integers(0, 2, t.size), 120, 90)
    inside = events.slice_time(int(t[0]) + 600_000, int(t[0]) + 800_000).t
    assert inside[0] > t[0] + 600_000 and inside[-1] < t[0] + 800_000 - 1          # a gap at both ends
    path = write_h5(tmp_path / "long.h5", events)
    out = tmp_path / "out"
    assert main(["fit", str(path), "--K", "90,90,60,45", "-o", str(out), "--t0", "0.6", "--t1", "0.8",
                 "--window-ms", "100", "--quiet"]) == 0
    assert "left out" not in capsys.readouterr().err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["windows_total"] == 2 and summary["uncovered_us"] is None


@pytest.mark.parametrize("suffix", [".h5", ".raw"])
def test_a_part_of_a_recording_too_long_to_hold_is_read_alone(tmp_path, capsys, monkeypatch, suffix):
    """A DSEC-layout h5 or a Prophesee RAW file holding more events than fit in memory (cmax.events.MAX_EVENTS,
    lowered here under the file's 400k events, over one RAW chunk's): the whole file is refused with one line,
    as before; --t0 / --t1 read only their span (they read the whole file first and were refused the same),
    and the window fitted is that span's."""
    from conftest import one_line_error, random_events

    from cmax.io import read, write_evt3

    events = random_events(400_000, width=120, height=90, seed=4, t_span_us=1_000_000)
    path = tmp_path / f"recording{suffix}"
    write_h5(path, events) if suffix == ".h5" else write_evt3(path, events)
    span = events.slice_time(400_000, 500_000)
    monkeypatch.setattr("cmax.events.MAX_EVENTS", 150_000)
    if suffix == ".raw":   # (an h5 file is fitted window by window: the next test)
        status, err = one_line_error(lambda: main(["fit", str(path), "--K", "90,90,59.5,44.5", "-o",
                                                   str(tmp_path / "all"), "--quiet"]), capsys)
        assert status == 2 and "more than cmax.events.MAX_EVENTS" in err and "--t0 / --t1 read a part of it" in err
    out = tmp_path / "part"
    assert main(["fit", str(path), "--K", "90,90,59.5,44.5", "-o", str(out), "--model", "flow", "--t0", "0.4",
                 "--t1", "0.5", "--max-events", "5000", "--quiet"]) == 0
    (window,) = json.loads((out / "summary.json").read_text())["windows"]
    assert "window 0 (0.400-0.500 s):" in capsys.readouterr().out      # times from the file's first event
    # the window spans the part (its ends: the first and last of the fit's 5000-event subsample)
    assert int(span.t[0]) <= window["t0_us"] < 400_100 and 499_900 < window["t1_us"] <= int(span.t[-1])
    monkeypatch.setattr("cmax.events.MAX_EVENTS", 1 << 28)
    assert read(path, t0_us=400_000, t1_us=500_000) == span                      # the same events


@pytest.mark.parametrize("jobs", [1, 2])
def test_a_whole_h5_file_too_long_to_hold_is_fitted_window_by_window(tmp_path, capsys, monkeypatch, jobs):
    """A DSEC-layout h5 file over cmax.events.MAX_EVENTS (lowered here) without --t0/--t1 (it was refused): read
    window by window from the file, with a note, every window's fit equal to that of the same file held in
    memory; undistortion (--distortion) applies to each window."""
    from conftest import random_events

    events = random_events(400_000, width=120, height=90, seed=4, t_span_us=1_000_000)
    path = write_h5(tmp_path / "recording.h5", events)
    argv = ["fit", str(path), "--K", "90,90,59.5,44.5", "--model", "flow", "--max-events", "3000",
            "--distortion", "-0.1,0.02,0,0", "--quiet", "--jobs", str(jobs)]
    assert main([*argv, "-o", str(tmp_path / "held")]) == 0     # --distortion: its summary crashed (a tuple)
    assert json.loads((tmp_path / "held" / "summary.json").read_text())["distortion"] == [-0.1, 0.02, 0.0, 0.0]
    capsys.readouterr()
    monkeypatch.setattr("cmax.events.MAX_EVENTS", 150_000)
    assert main([*argv, "-o", str(tmp_path / "streamed")]) == 0
    err = capsys.readouterr().err
    assert "more than cmax.events.MAX_EVENTS=150,000: fitting it window by window from the file" in err
    held, streamed = (json.loads((tmp_path / name / "summary.json").read_text())["windows"]
                      for name in ("held", "streamed"))
    assert len(held) == len(streamed) == 6
    for a, b in zip(held, streamed):
        assert (a["t0_us"], a["t1_us"], a["flow"]) == (b["t0_us"], b["t1_us"], b["flow"])


@pytest.mark.parametrize("streamed", [False, True])
def test_fit_through_a_lens_warps_each_event_from_its_sub_pixel_position(tmp_path, monkeypatch, streamed):
    """``cmax fit --distortion`` (or a --calib with a lens) fitted each event at its nearest undistorted pixel,
    dithered there. Now every window's fit (held in memory or read window by window) warps each event dithered
    over its sensor pixel and mapped through the lens, as OpenCV's undistortPoints maps that position."""
    from conftest import random_events

    from cmax.camera import Camera
    from cmax.fitting import api

    events = random_events(60_000, width=120, height=90, seed=6, t_span_us=300_000)
    path = write_h5(tmp_path / "recording.h5", events)
    K, distortion = np.array([[90.0, 0, 59.5], [0, 90.0, 44.5], [0, 0, 1]]), np.array([-0.1, 0.02, 0.0, 0.0])
    built = []
    real = api.Window.from_events.__func__
    monkeypatch.setattr(api.Window, "from_events",
                        classmethod(lambda cls, *a, **k: built.append(real(cls, *a, **k)) or built[-1]))
    if streamed:
        monkeypatch.setattr("cmax.events.MAX_EVENTS", 30_000)
    assert main(["fit", str(path), "--K", "90,90,59.5,44.5", "--model", "flow", "--max-events", "3000",
                 "--distortion", "-0.1,0.02,0,0", "--quiet", "--window-ms", "100", "-o", str(tmp_path / "out")]) == 0
    assert len(built) >= 3 and all(w.sensor is not None for w in built)
    camera = Camera(K, 120, 90, distortion)
    for w in built[:2]:
        pixels = w.sensor.pixels
        np.testing.assert_array_equal(np.rint(camera.undistortion_map[pixels[:, 1], pixels[:, 0]]),
                                      np.column_stack([w.source.x, w.source.y]))
        seed, n = w.settings.seed, len(w.source)
        keep = np.sort(np.random.default_rng(seed).choice(n, 3000, replace=False))
        dithered = pixels[keep] + np.random.default_rng([seed, 1]).uniform(-0.5, 0.5, (3000, 2))
        expected = cv2.undistortPoints(dithered.reshape(-1, 1, 2), K, distortion, P=K, criteria=(
            cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)).reshape(-1, 2)
        np.testing.assert_allclose(np.column_stack([w.ev.x.numpy(), w.ev.y.numpy()]), expected, atol=1e-4)


@pytest.mark.parametrize("options, message", [
    (["--model", "flow", "--speed", "1.5"], "--speed applies to --model se3, not flow"),
    (["--model", "rotation", "--zero-rotation-start"], "--zero-rotation-start applies to --model se3, not rotation"),
    # se3's options beside another model were taken and did nothing (the fit ran, exit 0):
    (["--model", "flow", "--members", "3"], "--members applies to --model se3, not flow"),
    (["--model", "rotation", "--depth-grid", "4,4"], "--depth-grid applies to --model se3, not rotation"),
    (["--model", "rotation", "--polish", "depth"], "--polish applies to --model se3, not rotation"),
    (["--model", "rotation", "--depth-range", "1,2"], "--depth-range applies to --model se3, not rotation"),
    (["--model", "flow", "--max-omega", "1"], "--max-omega applies to --model se3 and rotation, not flow"),
    (["--omega", "0,0,0", "--gyro", "g.txt"], "--omega is a constant rotation, --gyro a measured one"),
    (["--depth-range", "3,1"], "--depth-range must satisfy 0 < near < far (metres), got (3.0, 1.0)"),
    (["--max-events", "5"], "--max-events must be >= 10 (an int) or None (by the sensor), got 5"),
    (["--gyro-axes=-x,y,-z"], "--gyro-axes turns the readings of --gyro: pass --gyro too"),
    (["--gyro", "g.txt", "--gyro-axes", "x,x,z"], "--gyro-axes: gyro axes must name each IMU axis once"),
])
def test_options_are_checked_before_the_file_is_read_in_the_options_words(tmp_path, capsys, options, message):
    """A contradicting or bad option is named at once, as the option (was: after reading the file, as the library's
    keyword, e.g. "speed, pose and omega apply to model='se3'", "depth_range must satisfy"): the file here does
    not even exist."""
    argv = ["fit", str(tmp_path / "missing.h5"), "--K", "60,60,32,24", "-o", str(tmp_path / "o"), *options]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "missing.h5" not in err, err


def test_max_omega_bounds_the_fitted_rotation_and_the_warning_names_the_option(tmp_path, capsys):
    """A rotation window at about 0.8 rad/s: with ``--max-omega`` at 30% of it the fit ends on the bound, the
    window fails and the warning says to raise ``--max-omega`` (the option, not the Python setting); with the
    default bound the same window is fitted beyond that clip, without failing."""
    from benchmarks.synthetic_windows import make_window

    w = make_window("rotation", 1, width=120, height=90, focal=90.0, duration_s=0.05, max_frames=60)
    rate = float(np.linalg.norm(w.twist[3:]))
    path = write_h5(tmp_path / "turn.h5", w.events)
    K = ",".join(f"{v:g}" for v in (w.K[0, 0], w.K[1, 1], w.K[0, 2], w.K[1, 2]))
    base = ["fit", str(path), "--K", K, "--model", "rotation", "--window-ms", "50", "--quiet"]
    assert main([*base, "-o", str(tmp_path / "clipped"), "--max-omega", f"{0.3 * rate:.6f}"]) == 1
    err = capsys.readouterr().err
    assert "ended on its bound" in err and "raise --max-omega" in err and "FitSettings" not in err, err
    assert "max_flow_px" not in err, err            # a rotation has no flow bound to raise
    clipped = json.loads((tmp_path / "clipped" / "summary.json").read_text())["windows"][0]
    assert clipped["verdict"] == "failed"
    assert main([*base, "-o", str(tmp_path / "free")]) == 0
    free = json.loads((tmp_path / "free" / "summary.json").read_text())["windows"][0]
    assert free["verdict"] != "failed" and np.max(np.abs(free["omega"])) > 0.3 * rate, (free, rate)


def test_a_second_run_into_the_same_folder_never_mixes_with_the_first(tmp_path, capsys):
    """A folder holding an earlier run's results is refused (exit 2, its files untouched); ``--overwrite`` replaces
    them, and the earlier run's windows that the new run does not have are removed (was: windows 0-1 overwritten,
    2-3 of the earlier run left beside them, summary.json listing 2); a run into a folder another run holds is
    refused; no private folder or lock is left behind."""
    from cmax.io import run_folder
    from cmax.io.atomic import PathLock

    events = noise_events(2400, 50_000, seed=3)
    path = write_h5(tmp_path / "ev.h5", events)
    out = tmp_path / "o"
    base = ["fit", str(path), "--K", "60,60,32,24", "-o", str(out), "--quiet", "--min-events", "300",
            "--depth-grid", "6,8"]
    main([*base, "--window-ms", "12.5"])
    first = sorted(p.name for p in out.glob("depth_*.npz"))
    assert first == [f"depth_{i:05d}.npz" for i in range(4)]
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    capsys.readouterr()
    assert main([*base, "--window-ms", "25"]) == 2
    err = capsys.readouterr().err
    assert "holds the results of an earlier run" in err and "--overwrite" in err and len(err.strip().splitlines()) == 1
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    main([*base, "--window-ms", "25", "--overwrite"])
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["windows"]) == 2 and summary["window_ms"] == 25
    assert sorted(p.name for p in out.glob("depth_*.npz")) == ["depth_00000.npz", "depth_00001.npz"]
    assert sorted(p.name for p in out.glob("depth_*.png")) == ["depth_00000.png", "depth_00001.png"]
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []
    with PathLock(out / run_folder.FOLDER_LOCK, out):   # the lock of cmax fit, emvs and depth
        capsys.readouterr()
        assert main([*base, "--window-ms", "25", "--overwrite"]) == 2
        assert "being written by another writer" in capsys.readouterr().err


def test_a_signed_polarity_file_is_fitted_with_polarity_signed(tmp_path, capsys):
    """The reader's error advised ``--polarity signed``, which ``cmax fit`` did not have (unrecognized arguments)."""
    events = noise_events(600, 50_000, seed=4)
    table = np.zeros(len(events), [("x", "<u2"), ("y", "<u2"), ("t", "<i8"), ("p", "<i1")])
    table["x"], table["y"], table["t"], table["p"] = events.x, events.y, events.t, 2 * events.p.astype(np.int8) - 1
    np.save(tmp_path / "signed.npy", table)
    base = ["fit", str(tmp_path / "signed.npy"), "--size", "64x48", "--K", "60,60,32,24", "--quiet",
            "--min-events", "300", "--depth-grid", "6,8"]
    assert main([*base, "-o", str(tmp_path / "a")]) == 2
    assert "--polarity signed" in capsys.readouterr().err
    main([*base, "-o", str(tmp_path / "b"), "--polarity", "signed"])
    assert json.loads((tmp_path / "b" / "summary.json").read_text())["windows"]


@pytest.mark.parametrize("speed", [None, 8.0])
def test_an_up_to_scale_trajectory_says_so_and_emvs_does_not_call_its_depths_metres(tmp_path, capsys, monkeypatch,
                                                                                     speed):
    """Without --speed each window's v is a unit vector (1 m/s): trajectory.txt was written as if in metres, with
    no word, and ``cmax emvs --poses trajectory.txt`` printed 'median depth 0.651 m' (on a 0.29 m/s slider). Its
    '#' header now states the frame and the unit; emvs reads it and says the depths are up to scale."""
    from dataclasses import replace

    from benchmarks.synthetic_windows import make_window
    from cmax.emvs import read_tum_trajectory
    from cmax.fitting import QualitySettings, fit
    from cmax.fitting import sequence as sequence_module

    w = make_window("driving", 2, width=120, height=90, focal=90.0, duration_s=0.1, max_frames=60)
    base = fit(w.events, w.K, speed=8.0, depth_range=(1.0, 20.0), max_events=1000,
               quality=QualitySettings(ambiguity_test=False))
    monkeypatch.setattr(sequence_module, "fit", lambda events, K, model="se3", **options: replace(
        base, t0_us=int(events.t[0]), t1_us=int(events.t[-1]), scale_known=options.get("speed") is not None))
    path = write_h5(tmp_path / "drive.h5", w.events)
    K = ",".join(f"{v:g}" for v in (w.K[0, 0], w.K[1, 1], w.K[0, 2], w.K[1, 2]))
    out = tmp_path / "out"
    assert main(["fit", str(path), "--K", K, "-o", str(out), "--window-ms", "25", "--min-events", "10", "--quiet",
                 *([] if speed is None else ["--speed", str(speed)])]) == 0
    header = [line for line in (out / "trajectory.txt").read_text().splitlines() if line.startswith("#")]
    assert header[0] == "# t[s] tx ty tz qx qy qz qw (TUM)"
    assert ("translation up to scale" in header[1]) == (speed is None)
    assert ("translation in metres" in header[1]) == (speed is not None)
    times, poses = read_tum_trajectory(out / "trajectory.txt")          # the header is skipped, as evo skips it
    assert len(times) == 4 and np.allclose(poses[0], np.eye(4))
    capsys.readouterr()
    from cmax import viz

    bars, titles, titled = [], [], viz.titled
    monkeypatch.setattr(viz, "depth_colour_bar", lambda *a, unit="m", **k: bars.append(unit) or np.zeros((40, 8, 3),
                                                                                                        np.uint8))
    monkeypatch.setattr(viz, "titled", lambda image, title, **k: titles.append(title) or titled(image, title, **k))
    assert main(["emvs", str(path), "--K", K, "-o", str(tmp_path / "emvs"), "--poses", str(out / "trajectory.txt"),
                 "--depth-range", "1,20", "--planes", "20"]) == 0
    captured = capsys.readouterr()
    summary = json.loads((tmp_path / "emvs" / "summary.json").read_text())
    assert summary["scale_known"] == (speed is not None)
    # its units, as cmax fit's summary names them (was: none): metres only with a speed
    assert (summary["units"]["depth_range, median_depth_m"] == "m") == (speed is not None)
    assert summary["units"]["t_ref_us"].startswith("µs on the file's clock")
    assert ("are up to scale (its header says so" in captured.err) == (speed is None)
    assert ("(up to scale)" in captured.out) == (speed is None)
    # depth.png: was a colour bar in m over depths the note calls 'not metres'; now bare, titled up to scale
    assert bars == (["m"] if speed is not None else [""])
    assert any("semi-dense depth" in t for t in titles)
    assert any("up to scale" in t for t in titles) == (speed is None)


def test_calibration_yaml_in_block_style_and_kalibr_camchains_are_read(tmp_path):
    """A cam_to_cam.yaml whose lists are written as '- value' lines (PyYAML's default block style) was refused
    with 'no intrinsics/cam0 (cameras found: cam0, camRect0, camera_matrix, distortion_coeffs, resolution)';
    a Kalibr camchain (cam0: intrinsics: [...], as MVSEC and DAVIS rigs ship) with 'cameras found: none',
    even for its fisheye model. Both now read to the numbers written, or refuse naming the model."""
    flow_K, flow_distortion, flow_size = read_calibration(_write(tmp_path / "flow.yaml", DSEC_YAML))[:3]
    block = tmp_path / "block.yaml"
    block.write_text("disparity_to_depth:\n  cams_03:\n  - - 1.0\n    - 0.0\nintrinsics:\n  cam0:\n    camera_matrix:\n"
                     "    - 553.47\n    - 553.40\n    - 346.65\n    - 216.52\n    camera_model: pinhole\n"
                     "    distortion_coeffs:\n    - -0.0936\n    - 0.1945\n    - 7.6e-05\n    - 0.00196\n"
                     "    distortion_model: radtan\n    resolution:\n    - 640\n    - 480\n  camRect0:\n"
                     "    camera_matrix:\n    - 569.76\n    - 569.76\n    - 335.10\n    - 221.24\n")
    K, distortion, size = read_calibration(block)[:3]
    np.testing.assert_array_equal(K, flow_K)
    np.testing.assert_array_equal(distortion, flow_distortion)
    assert size == flow_size == (640, 480)
    assert read_calibration(block, "camRect0")[0][0, 2] == 335.10
    with pytest.raises(ValueError, match=r"cameras found: cam0, camRect0\)"):
        read_calibration(block, "cam9")
    camchain = ("cam0:\n  T_cam_imu:\n  - [1, 0, 0, 0]\n  - [0, 1, 0, 0]\n  camera_model: pinhole\n"
                "  distortion_coeffs: [-0.0484, 0.0094, 0.001, 0.002]\n  distortion_model: radtan\n"
                "  intrinsics: [226.38, 226.15, 173.64, 133.73]\n  resolution: [346, 260]\n"
                "cam1:\n  camera_model: pinhole\n  distortion_coeffs: [0.1, 0.2, 0.3, 0.4]\n"
                "  distortion_model: equidistant\n  intrinsics: [226.0, 226.0, 173.0, 133.0]\n")
    path = _write(tmp_path / "camchain.yaml", camchain)
    K, distortion, size = read_calibration(path)[:3]
    assert (K[0, 0], K[1, 1], K[0, 2], K[1, 2]) == (226.38, 226.15, 173.64, 133.73) and size == (346, 260)
    np.testing.assert_array_equal(distortion, [-0.0484, 0.0094, 0.001, 0.002])
    fisheye = read_calibration(path, "cam1")     # was refused: "distortion_model 'equidistant' is not supported"
    assert fisheye.model == "equidistant" and fisheye.distortion.tolist() == [0.1, 0.2, 0.3, 0.4]
    assert fisheye.rectification is None and fisheye.rectified_K is None and fisheye.size is None
    with pytest.raises(ValueError, match=r"cameras found: cam0, cam1\)"):
        read_calibration(path, "cam2")


def _write(path, text):
    path.write_text(text)
    return path


def test_a_long_h5_file_under_the_event_limit_is_fitted_from_the_file_too(tmp_path, capsys, monkeypatch):
    """cmax fit read a whole h5 file into memory unless it held more than MAX_EVENTS (2**28): 1.49 GB for 60 M
    events, growing with the recording. Past STREAM_ABOVE_EVENTS (lowered here) it reads one window at a time
    (read_calibrated, the whole read, is never called), and every window's fit is the one of the held file."""
    import cmax.cli.fit as fit
    from conftest import random_events

    events = random_events(200_000, width=120, height=90, seed=5, t_span_us=600_000)
    path = write_h5(tmp_path / "recording.h5", events)
    argv = ["fit", str(path), "--K", "90,90,59.5,44.5", "--model", "flow", "--max-events", "3000", "--quiet"]
    assert main([*argv, "-o", str(tmp_path / "held")]) == 0
    capsys.readouterr()
    monkeypatch.setattr(fit, "STREAM_ABOVE_EVENTS", 100_000)
    monkeypatch.setattr(fit, "read_calibrated", lambda *a, **k: pytest.fail("the whole file was read"))
    assert main([*argv, "-o", str(tmp_path / "streamed")]) == 0
    assert "holds 200,000 events: fitting it window by window from the file" in capsys.readouterr().err
    held, streamed = (json.loads((tmp_path / name / "summary.json").read_text())["windows"]
                      for name in ("held", "streamed"))
    assert len(held) == len(streamed) >= 3
    for a, b in zip(held, streamed):
        assert (a["t0_us"], a["t1_us"], a["flow"]) == (b["t0_us"], b["t1_us"], b["flow"])


def test_a_streamed_fit_through_a_rectifying_calib_names_the_pixels_whose_events_are_dropped(tmp_path, capsys,
                                                                                             monkeypatch):
    """A DSEC recording (more events than STREAM_ABOVE_EVENTS: DSEC's are) is fitted window by window; with
    --calib cam0 the events that rectify to outside camRect0's image were dropped without a word there (an
    in-memory fit counts them). Now a note names the sensor's pixels whose events are dropped, as many as
    cv2.undistortPoints(R=R_rect0, P=K_rect0) maps outside the image."""
    import cmax.cli.fit as fit
    from conftest import random_events

    events = random_events(20_000, width=640, height=480, seed=6, t_span_us=300_000)
    path = write_h5(tmp_path / "events.h5", events)
    yaml = _write(tmp_path / "cam_to_cam.yaml", DSEC_RECTIFIED_YAML)
    monkeypatch.setattr(fit, "STREAM_ABOVE_EVENTS", 10_000)
    main(["fit", str(path), "--calib", str(yaml), "--model", "flow", "-o", str(tmp_path / "o"), "--quiet"])
    err = capsys.readouterr().err
    assert "fitting it window by window from the file" in err, err
    R = np.array([[0.99991301, -0.00860511, 0.00999626], [0.00859561, 0.99996256, 0.00099302],
                  [-0.01000443, -0.00090701, 0.99994954]])
    ys, xs = np.mgrid[0:480, 0:640]
    pixels = np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float64).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    mapped = np.rint(cv2.undistortPoints(pixels, np.array([[553.47, 0, 346.65], [0, 553.40, 216.52], [0, 0, 1]]),
                                         np.array([-0.0936, 0.1945, 7.6e-05, 0.00196]), R=R,
                                         P=np.array([[569.76, 0, 335.10], [0, 569.76, 221.24], [0, 0, 1]]),
                                         criteria=criteria).reshape(-1, 2))
    outside = int(((mapped[:, 0] < 0) | (mapped[:, 0] >= 640) | (mapped[:, 1] < 0) | (mapped[:, 1] >= 480)).sum())
    assert outside > 1000                       # camRect0's K (569.76) is longer than cam0's: the border is cut
    import re

    note = re.search(r"([\d,]+) of the sensor's 307,200 pixels fall outside the image once undistorted, or lie "
                     r"beyond the radius the distortion model reaches: their events are dropped", err)
    assert note is not None, err
    assert abs(int(note.group(1).replace(",", "")) - outside) <= 0.01 * outside   # a pixel on a rounding edge


@pytest.mark.parametrize("camera", [None, "right"])
def test_the_summary_of_an_mvsec_fit_names_the_camera_fitted(tmp_path, capsys, camera):
    """Was: summary.json of `cmax fit rig.hdf5 --camera right` did not say which camera was fitted: the left and
    the right run of one file gave records that could not be told apart."""
    from test_cli import _two_camera_mvsec

    path = _two_camera_mvsec(tmp_path / "rig.hdf5", left=20, right=30)
    chosen = [] if camera is None else ["--camera", camera]
    assert main(["fit", str(path), "--K", "200,200,173,130", "-o", str(tmp_path / "o"), "--quiet", *chosen]) == 1
    capsys.readouterr()                                # no window has 1,000 events: the summary alone is written
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["camera"] == (camera or "left")
    dsec = write_h5(tmp_path / "one.h5", noise_events(300, 50_000, seed=1))
    assert main(["fit", str(dsec), "--K", "60,60,32,24", "-o", str(tmp_path / "d"), "--quiet"]) == 1
    assert json.loads((tmp_path / "d" / "summary.json").read_text())["camera"] is None


def test_fit_notes_events_that_repeat_an_earlier_one_exactly(tmp_path, capsys):
    """Was: a recording whose every event was written twice fitted without a word (each copy counted)."""
    events = noise_events(300, 50_000, seed=1)
    twice = Events(*(np.repeat(column, 2) for column in (events.x, events.y, events.t, events.p)), 64, 48)
    expected = len(twice) - len(set(zip(twice.x.tolist(), twice.y.tolist(), twice.t.tolist(), twice.p.tolist())))
    path = write_h5(tmp_path / "twice.h5", twice)
    assert main(["fit", str(path), "--K", "60,60,32,24", "-o", str(tmp_path / "o"), "--quiet"]) == 1
    note = f"{expected:,} of the 600 events repeat an earlier event exactly"
    assert expected >= 300 and note in capsys.readouterr().err
    assert any(note in text for text in json.loads((tmp_path / "o" / "summary.json").read_text())["notes"])
    assert main(["fit", str(write_h5(tmp_path / "once.h5", events)), "--K", "60,60,32,24", "-o",
                 str(tmp_path / "p"), "--quiet"]) == 1
    assert "repeat an earlier event" not in capsys.readouterr().err




def test_fit_with_mvsec_s_fisheye_camchain_fits_in_the_rectified_frame(tmp_path, capsys):
    """`cmax fit --calib camchain-imucam-indoor_flying.yaml` was refused ("distortion_model 'equidistant' is not
    supported"). Now the events are undistorted and rectified, the fit's K is P_rect's and a note says so."""
    rng = np.random.default_rng(3)
    events = Events(rng.integers(0, 346, 300), rng.integers(0, 260, 300), np.sort(rng.integers(0, 50_000, 300)),
                    rng.integers(0, 2, 300), 346, 260)
    path = write_txt(tmp_path / "ev.txt", events)
    calib = _write(tmp_path / "camchain-imucam-indoor_flying.yaml", MVSEC_CAMCHAIN)
    status = main(["fit", str(path), "--calib", str(calib), "-o", str(tmp_path / "o"), "--quiet"])
    err = capsys.readouterr().err
    assert status in (0, 1), err           # 300 random events: too few to fit, but read, mapped and run
    assert f"{calib} (cam0): an equidistant (fisheye) lens; the events are undistorted and rectified" in err
    assert "K = fx 199.653, fy 199.653, cx 177.433, cy 126.812" in err
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    np.testing.assert_allclose(summary["K"], [[199.6530123165822, 0, 177.43276376280926],
                                              [0, 199.6530123165822, 126.81215684365904], [0, 0, 1]])
    assert summary["distortion_model"] == "equidistant" and summary["rectified"] is True
    # trajectory.txt in the lens's own frame (what MVSEC's poses and cmax emvs --calib take): its first pose, the
    # rectified frame's identity, is T_w_c = [R_rect | 0]
    lines = (tmp_path / "o" / "trajectory.txt").read_text().splitlines()
    assert any(line.startswith("# the camera's own frame") for line in lines)
    qx, qy, qz, qw = map(float, next(line for line in lines if not line.startswith("#")).split()[4:])
    R = np.array(_numbers_of(MVSEC_CAMCHAIN.split("rectification_matrix:")[1])).reshape(3, 3)
    w, x, y, z = qw, qx, qy, qz
    quaternion_R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                             [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                             [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    np.testing.assert_allclose(quaternion_R, R, atol=1e-6)
    bad = _write(tmp_path / "bad.yaml", MVSEC_CAMCHAIN.replace("0.021500973881459395]", "0.0215, 0.0]"))
    assert main(["fit", str(path), "--calib", str(bad), "-o", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err
    assert "equidistant (fisheye) distortion of cam0 must be 4 finite numbers" in err and err.count("\n") == 1
    flipped = _write(tmp_path / "flip.yaml", MVSEC_CAMCHAIN.replace("0.9999774079320989]", "-0.9999774079320989]"))
    assert main(["fit", str(path), "--calib", str(flipped), "-o", str(tmp_path / "o3")]) == 2
    err = capsys.readouterr().err
    assert "cam0's rectification_matrix must be a rotation" in err and err.count("\n") == 1


def _numbers_of(text):
    return [float(v) for v in text.replace("[", " ").replace("]", " ").replace(",", " ").replace("- ", " ").split()]


def test_the_camchain_camera_must_be_the_mvsec_camera_read(tmp_path, capsys):
    """`cmax fit rig.hdf5 --camera right --calib camchain.yaml` (--calib-camera left at cam0) undistorted and
    rectified the right camera's events with the left camera's lens, exit 0, without a word. The camchain's
    rostopic (/davis/left/image_raw) says which camera each entry is: a mismatch is one line, exit 2."""
    import argparse

    import h5py

    from cmax.cli.recording import calibration_of

    rng = np.random.default_rng(4)
    t = np.sort(rng.uniform(10.0, 10.1, 500))
    with h5py.File(tmp_path / "rig_data.hdf5", "w") as f:
        for side in ("left", "right"):
            f[f"davis/{side}/events"] = np.column_stack([rng.integers(0, 346, 500), rng.integers(0, 260, 500), t,
                                                         rng.choice([-1.0, 1.0], 500)])
    chain = MVSEC_CAMCHAIN + MVSEC_CAMCHAIN.replace("cam0:", "cam1:").replace("/davis/left/", "/davis/right/")
    calib = _write(tmp_path / "camchain.yaml", chain)
    rig = tmp_path / "rig_data.hdf5"
    for options, message in (
            (["--camera", "right"], "cam0 is the left camera (rostopic /davis/left/image_raw), but the events of "
                                    f"{rig} are the right camera's (--camera right): choose the camchain's right camera "
                                    "with --calib-camera"),
            (["--calib-camera", "cam1"], "cam1 is the right camera (rostopic /davis/right/image_raw), but the events of "
                                         f"{rig} are the left camera's (--camera left, the default)")):
        assert main(["fit", str(rig), "--calib", str(calib), "-o", str(tmp_path / "o"), *options]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
    for camera, calib_camera in ((None, "cam0"), ("right", "cam1"), ("left", "cam0")):
        args = argparse.Namespace(calib=calib, calib_camera=calib_camera, distortion=None, K=None, file=rig,
                                  camera=camera)
        assert calibration_of(args).topic == f"/davis/{camera or 'left'}/image_raw"


def test_a_ros_camera_info_yaml_is_read(tmp_path):
    """ROS camera_info YAML (camera_calibration's and rpg_dvs_ros's format: matrices as `data: [...]`) was refused
    as 'no intrinsics/cam0 (cameras found: none)'. Read now, a fisheye model and a rectification included; a
    monocular file's R = I, P = [K | 0] moves nothing and is dropped."""
    fisheye = ("image_width: 346\nimage_height: 260\ncamera_name: davis_left\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
               "  data: [226.38, 0, 173.65, 0, 226.15, 133.73, 0, 0, 1]\ndistortion_model: equidistant\n"
               "distortion_coefficients:\n  rows: 1\n  cols: 4\n  data: [-0.048, 0.0113, -0.0554, 0.0215]\n"
               "rectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n"
               "projection_matrix:\n  rows: 3\n  cols: 4\n  data: [199.65, 0, 177.43, 0, 0, 199.65, 126.81, 0, 0, 0, 1, 0]\n")
    calibration = read_calibration(_write(tmp_path / "davis.yaml", fisheye))
    np.testing.assert_array_equal(calibration.K, [[226.38, 0, 173.65], [0, 226.15, 133.73], [0, 0, 1]])
    assert calibration.model == "equidistant" and calibration.size == (346, 260)
    np.testing.assert_array_equal(calibration.distortion, [-0.048, 0.0113, -0.0554, 0.0215])
    np.testing.assert_array_equal(calibration.rectified_K, [[199.65, 0, 177.43], [0, 199.65, 126.81], [0, 0, 1]])
    assert calibration.rectification is None                               # the identity: nothing to turn
    mono = (fisheye.replace("equidistant", "plumb_bob").replace("[-0.048, 0.0113, -0.0554, 0.0215]", "[-0.1, 0.02, 0, 0, 0]")
            .replace("199.65, 0, 177.43, 0, 0, 199.65, 126.81", "226.38, 0, 173.65, 0, 0, 226.15, 133.73"))
    calibration = read_calibration(_write(tmp_path / "mono.yaml", mono))
    assert calibration.model == "radtan" and calibration.rectification is None and calibration.rectified_K is None
    from cmax.cli.recording import calibration_note

    assert calibration_note(calibration, "mono.yaml", "cam0") is None         # a radtan pinhole: nothing to say
    radtan_rectified = read_calibration(_write(tmp_path / "stereo.yaml", fisheye.replace("equidistant", "plumb_bob")))
    assert calibration_note(radtan_rectified, "stereo.yaml", "cam0").startswith(
        "stereo.yaml (cam0): a radtan lens; the events are undistorted and rectified")
    with pytest.raises(ValueError, match=r"calibrates one camera \(ROS camera_info\): camera 'cam1'"):
        read_calibration(tmp_path / "mono.yaml", "cam1")
    with pytest.raises(ValueError, match=r"camera_matrix data must be the 9 numbers"):
        read_calibration(_write(tmp_path / "skew.yaml", mono.replace("data: [226.38, 0, 173.65", "data: [226.38, 2, 173.65")))


def test_quoted_values_wrapped_lists_and_opencv_matrices_are_read(tmp_path):
    """Three spellings of valid calibration YAML were refused with a wrong reason: a quoted scalar
    (`distortion_model: "plumb_bob"`: "'\"plumb_bob\"' is not supported"), a flow list PyYAML wrapped over two
    lines at 80 columns (only the first line's numbers read: "needs camera_matrix: [fx, fy, cx, cy]"), and
    OpenCV FileStorage's `camera_matrix: !!opencv-matrix` ("cameras found: none"). Each is read now, with the
    numbers the file writes."""
    K = [[226.38, 0, 173.64], [0, 226.15, 133.73], [0, 0, 1]]
    quoted = ("image_width: 346\nimage_height: 260\ncamera_name: 'davis'\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
              "  data: [226.38, 0, 173.64, 0, 226.15, 133.73, 0, 0, 1]\ndistortion_model: \"plumb_bob\"\n"
              "distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [-0.1, 0.05, 0.001, -0.002, 0.0]\n")
    calibration = read_calibration(_write(tmp_path / "quoted.yaml", quoted))
    assert calibration.model == "radtan" and calibration.size == (346, 260)
    np.testing.assert_array_equal(calibration.K, K)
    np.testing.assert_array_equal(calibration.distortion, [-0.1, 0.05, 0.001, -0.002, 0.0])
    chain = MVSEC_CAMCHAIN.replace("camera_model: pinhole", "camera_model: 'pinhole'").replace(
        "distortion_model: equidistant", 'distortion_model: "equidistant"')
    assert read_calibration(_write(tmp_path / "chain.yaml", chain)).model == "equidistant"
    wrapped = ("intrinsics:\n  cam0:\n    camera_matrix: [553.4686750102932, 553.3994078799127, 346.65339162053317,\n"
               "      216.28132394742444]\n    distortion_coeffs: [-0.09356476362537607, 0.19445779814646236,\n"
               "      7.642434242733646e-05, 0.0019563864604273664]\n    resolution: [640, 480]\n")
    calibration = read_calibration(_write(tmp_path / "wrapped.yaml", wrapped))
    np.testing.assert_allclose(calibration.K, [[553.4686750102932, 0, 346.65339162053317],
                                               [0, 553.3994078799127, 216.28132394742444], [0, 0, 1]], rtol=1e-15)
    np.testing.assert_array_equal(calibration.distortion, [-0.09356476362537607, 0.19445779814646236,
                                                           7.642434242733646e-05, 0.0019563864604273664])
    opencv = ("%YAML:1.0\n---\nimage_width: 346\nimage_height: 260\ncamera_matrix: !!opencv-matrix\n   rows: 3\n"
              "   cols: 3\n   dt: d\n   data: [ 2.2638e+02, 0., 1.7364e+02, 0., 2.2615e+02, 1.3373e+02, 0.,\n"
              "       0., 1. ]\ndistortion_coefficients: !!opencv-matrix\n   rows: 5\n   cols: 1\n   dt: d\n"
              "   data: [ -0.1, 0.05, 1.e-03, -2.e-03, 0. ]\n")
    calibration = read_calibration(_write(tmp_path / "opencv.yml", opencv))
    np.testing.assert_array_equal(calibration.K, K)
    np.testing.assert_array_equal(calibration.distortion, [-0.1, 0.05, 0.001, -0.002, 0.0])
    assert calibration.size == (346, 260)


def test_ros_rational_polynomial_empty_d_and_echoed_camera_info_are_read(tmp_path):
    """ROS's camera_info names OpenCV's model plumb_bob or rational_polynomial (8 coefficients) and hands D to
    OpenCV as it is: rational_polynomial was refused ("not supported"), plumb_bob with 8 or with an empty D (no
    distortion) too ("must be 4 or 5 finite numbers"), and a CameraInfo as `rostopic echo` / `ros2 topic echo`
    print it (K, D, R, P / k, d, r, p) as "cameras found: none". Read now; the 8 coefficients undistort as
    cv2.undistortPoints does with them."""
    D = [-0.3, 0.12, 0.001, -0.002, 0.01, 0.05, 0.02, 0.003]
    info = ("image_width: 346\nimage_height: 260\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
            "  data: [226.38, 0, 173.64, 0, 226.15, 133.73, 0, 0, 1]\ndistortion_model: rational_polynomial\n"
            f"distortion_coefficients:\n  rows: 1\n  cols: 8\n  data: {D}\n"
            "projection_matrix:\n  rows: 3\n  cols: 4\n  data: [200.5, 0, 175.2, 0, 0, 201.3, 130.1, 0, 0, 0, 1, 0]\n")
    calibration = read_calibration(_write(tmp_path / "rational.yaml", info))
    np.testing.assert_array_equal(calibration.distortion, D)
    camera = calibration.camera(346, 260)
    ys, xs = np.mgrid[0:260:13, 0:346:17]
    pixels = np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float64)
    K = np.array([[226.38, 0, 173.64], [0, 226.15, 133.73], [0, 0, 1]])
    P = np.array([[200.5, 0, 175.2], [0, 201.3, 130.1], [0, 0, 1]])
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    expected = cv2.undistortPoints(pixels.reshape(-1, 1, 2), K, np.array(D), P=P, criteria=criteria).reshape(-1, 2)
    np.testing.assert_allclose(camera.undistort_points(pixels), expected, atol=1e-3)
    plumb8 = read_calibration(_write(tmp_path / "plumb8.yaml", info.replace("rational_polynomial", "plumb_bob")))
    np.testing.assert_array_equal(plumb8.distortion, D)
    empty = info.replace("rational_polynomial", "plumb_bob").replace(f"cols: 8\n  data: {D}", "cols: 0\n  data: []")
    assert read_calibration(_write(tmp_path / "empty.yaml", empty)).distortion is None
    with pytest.raises(ValueError, match=r"or 8 \(k1 k2 p1 p2 k3 k4 k5 k6: ROS's rational_polynomial\); got 6"):
        read_calibration(_write(tmp_path / "six.yaml", info.replace(f"data: {D}", f"data: {D[:6]}")))
    echoed = ("header:\n  seq: 0\n  frame_id: ''\nheight: 260\nwidth: 346\ndistortion_model: \"plumb_bob\"\n"
              "D: [-0.1, 0.05, 0.001, -0.002, 0.0]\nK: [226.38, 0.0, 173.64, 0.0, 226.15, 133.73, 0.0, 0.0, 1.0]\n"
              "R: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]\n"
              "P: [226.38, 0.0, 173.64, 0.0, 0.0, 226.15, 133.73, 0.0, 0.0, 0.0, 1.0, 0.0]\nbinning_x: 0\n"
              "roi:\n  x_offset: 0\n  height: 0\n  width: 0\n  do_rectify: False\n---\n")
    ros2 = ("height: 260\nwidth: 346\ndistortion_model: plumb_bob\nd:\n" + "".join(
        f"- {v}\n" for v in [-0.1, 0.05, 0.001, -0.002, 0.0]) + "k:\n" + "".join(
        f"- {v}\n" for v in [226.38, 0.0, 173.64, 0.0, 226.15, 133.73, 0.0, 0.0, 1.0]) + "p:\n" + "".join(
        f"- {v}\n" for v in [226.38, 0.0, 173.64, 0.0, 0.0, 226.15, 133.73, 0.0, 0.0, 0.0, 1.0, 0.0]))
    for name, text in (("echo.yaml", echoed), ("echo2.yaml", ros2)):
        calibration = read_calibration(_write(tmp_path / name, text))
        np.testing.assert_array_equal(calibration.K, K)
        np.testing.assert_array_equal(calibration.distortion, [-0.1, 0.05, 0.001, -0.002, 0.0])
        assert calibration.size == (346, 260) and calibration.rectified_K is None, name


def test_an_mvsec_file_without_calib_names_the_camchain_to_pass(tmp_path):
    """`cmax fit/emvs indoor_flying1_data.hdf5 --K ...` fitted MVSEC's fisheye events as a pinhole's without a
    word; a camchain-imucam-*.yaml beside the file was not named either (only calib.txt / cam_to_cam.yaml were)."""
    import argparse

    import h5py

    from cmax.cli.recording import calibration_hint

    rng = np.random.default_rng(8)
    with h5py.File(tmp_path / "indoor_flying1_data.hdf5", "w") as f:
        f["davis/left/events"] = np.column_stack([rng.integers(0, 346, 50), rng.integers(0, 260, 50),
                                                  np.sort(rng.uniform(1.0, 1.1, 50)), rng.choice([-1.0, 1.0], 50)])
    args = argparse.Namespace(file=tmp_path / "indoor_flying1_data.hdf5", calib=None, distortion=None)
    hint = calibration_hint(args)
    assert "MVSEC's DAVIS cameras look through fisheye lenses" in hint and "camchain-imucam-<sequence>.yaml" in hint
    chain = _write(tmp_path / "camchain-imucam-indoor_flying.yaml", MVSEC_CAMCHAIN)
    assert calibration_hint(args).startswith(f"{chain} lies beside the events but was not read: pass --calib {chain}")
    assert calibration_hint(argparse.Namespace(file=args.file, calib=chain, distortion=None)) is None
    events = Events(rng.integers(0, 346, 50), rng.integers(0, 260, 50), np.arange(50), rng.integers(0, 2, 50), 346, 260)
    other = tmp_path / "x" / "y"      # two levels down: the camchain is not beside it
    other.mkdir(parents=True)
    assert calibration_hint(argparse.Namespace(file=write_txt(other / "ev.txt", events), calib=None,
                                               distortion=None)) is None        # not MVSEC: nothing to say


def test_a_known_rotation_is_turned_into_the_rectified_frame(slider, tmp_path):
    """--omega / --gyro are in the camera's axes; with a rectifying --calib the fit's frame is the rectified one,
    so the held rotation must be R_rect omega (was: held as given, in the wrong axes)."""
    w, path, _ = slider
    R = cv2.Rodrigues(np.array([0.0, 0.0, np.deg2rad(5.0)]))[0]
    fx, fy, cx, cy = w.K[0, 0], w.K[1, 1], w.K[0, 2], w.K[1, 2]
    calib = _write(tmp_path / "camchain.yaml",
                   "cam0:\n  camera_model: pinhole\n  distortion_model: radtan\n  distortion_coeffs: [0, 0, 0, 0]\n"
                   f"  intrinsics: [{fx}, {fy}, {cx}, {cy}]\n  resolution: [96, 72]\n  rectification_matrix:\n"
                   + "".join(f"  - [{', '.join(map(repr, row.tolist()))}]\n" for row in R))
    omega = np.array([0.0, 0.5, 0.0])
    out = tmp_path / "out"
    main(["fit", str(path), "--size", "96,72", "--calib", str(calib), "-o", str(out), "--window-ms", "500",
          "--omega", ",".join(map(str, omega)), "--max-events", "3000", "--depth-grid", "8,10", "--quiet"])
    (window,) = json.loads((out / "summary.json").read_text())["windows"]
    np.testing.assert_allclose(window["omega"], R @ omega, atol=1e-9)


#: A DSEC cam_to_cam.yaml of a rig whose rectification turns cam0 by about 1 degree (DSEC's own are of that size).
DSEC_RECTIFIED_YAML = """\
extrinsics:
  R_rect0:
  - [0.99991301, -0.00860511, 0.00999626]
  - [0.00859561, 0.99996256, 0.00099302]
  - [-0.01000443, -0.00090701, 0.99994954]
intrinsics:
  cam0:
    camera_matrix: [553.47, 553.40, 346.65, 216.52]
    distortion_coeffs: [-0.0936, 0.1945, 7.6e-05, 0.00196]
    distortion_model: radtan
    resolution: [640, 480]
  camRect0:
    camera_matrix: [569.76, 569.76, 335.10, 221.24]
    resolution: [640, 480]
"""


def test_dsec_raw_camera_is_rectified_into_camrect_frame_as_opencv_does(tmp_path):
    """DSEC ships its events raw; its disparity maps (and rectify_map.h5) are in camRect0's frame, made with
    cv2.undistortPoints(..., R=R_rect0, P=K_rect0). --calib-camera cam0 was undistorted onto cam0's own pinhole
    (K 553.47, not rotated): a frame 1 degree and 16 px of focal length away from the ground truth's."""
    yaml = _write(tmp_path / "cam_to_cam.yaml", DSEC_RECTIFIED_YAML)
    calibration = read_calibration(yaml, "cam0")
    R = np.array([[0.99991301, -0.00860511, 0.00999626], [0.00859561, 0.99996256, 0.00099302],
                  [-0.01000443, -0.00090701, 0.99994954]])
    K_rect = np.array([[569.76, 0, 335.10], [0, 569.76, 221.24], [0, 0, 1]])
    K = np.array([[553.47, 0, 346.65], [0, 553.40, 216.52], [0, 0, 1]])
    distortion = np.array([-0.0936, 0.1945, 7.6e-05, 0.00196])
    camera = calibration.camera(640, 480)
    np.testing.assert_array_equal(camera.pinhole_K, K_rect)
    ys, xs = np.mgrid[0:480:37, 0:640:41]
    pixels = np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float64)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    expected = cv2.undistortPoints(pixels.reshape(-1, 1, 2), K, distortion, R=R, P=K_rect,
                                   criteria=criteria).reshape(-1, 2)
    np.testing.assert_allclose(camera.undistort_points(pixels), expected, atol=1e-3)
    note = calibration_note(calibration, yaml, "cam0", "events.h5")
    assert "extrinsics/R_rect0 and intrinsics/camRect0" in note and "fx 569.76" in note
    # camRect0 stays a pinhole without distortion (events already rectified), and says what it assumes
    rectified = read_calibration(yaml, "camRect0")
    assert rectified.distortion is None and rectified.rectification is None
    assert "taken as already undistorted and rectified" in calibration_note(rectified, yaml, "camRect0", "ev.h5")
    # a malformed R_rect0 is refused naming it, not read as no rectification
    bad = _write(tmp_path / "bad.yaml", DSEC_RECTIFIED_YAML.replace("  - [-0.01000443, -0.00090701, 0.99994954]\n",
                                                                     ""))
    with pytest.raises(ValueError, match=r"extrinsics/R_rect0 \(the rectification of cam0\) must be a 3x3"):
        read_calibration(bad, "cam0")


def test_camrect_on_raw_dsec_events_with_rectify_map_beside_is_refused(tmp_path, capsys):
    """DSEC's events/left/events.h5 lies beside rectify_map.h5 and is raw: camRect0 fitted it as rectified without
    a word. Now exit 2 naming cam0; without the map, a note says what camRect0 assumes."""
    rng = np.random.default_rng(3)
    events = Events(rng.integers(0, 640, 300), rng.integers(0, 480, 300), np.sort(rng.integers(0, 50_000, 300)),
                    rng.integers(0, 2, 300), 640, 480)
    path = write_h5(tmp_path / "events.h5", events)
    yaml = _write(tmp_path / "cam_to_cam.yaml", DSEC_RECTIFIED_YAML)
    (tmp_path / "rectify_map.h5").write_bytes(b"")
    args = ["fit", str(path), "--calib", str(yaml), "--calib-camera", "camRect0", "-o", str(tmp_path / "o")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "camRect0 is the rectified camera" in err and "--calib-camera cam0" in err
    assert len(err.strip().splitlines()) == 1, err
    (tmp_path / "rectify_map.h5").unlink()
    main(args + ["--quiet"])
    assert "taken as already undistorted and rectified" in capsys.readouterr().err


def test_dsec_calibration_folder_two_levels_above_the_events_is_named(tmp_path):
    """DSEC ships <sequence>/events/left/events.h5 and <sequence>/calibration/cam_to_cam.yaml: the note that names a
    calibration beside the events looked one folder up only, so a DSEC user fitting with --K heard nothing."""
    import argparse

    from cmax.cli.recording import calibration_hint

    left = tmp_path / "zurich_city_04_a" / "events" / "left"
    left.mkdir(parents=True)
    path = write_h5(left / "events.h5", noise_events(300, 50_000, seed=4))
    args = argparse.Namespace(file=path, calib=None, distortion=None)
    assert calibration_hint(args) is None
    (tmp_path / "zurich_city_04_a" / "calibration").mkdir()
    yaml = _write(tmp_path / "zurich_city_04_a" / "calibration" / "cam_to_cam.yaml", DSEC_RECTIFIED_YAML)
    hint = calibration_hint(args)
    assert hint.startswith(f"{yaml.resolve()} lies beside the events but was not read: pass --calib {yaml.resolve()} "
                           "(DSEC: --calib-camera cam0"), hint


@pytest.mark.parametrize("command", ["fit", "emvs", "depth"])
def test_an_ecd_calib_txt_of_another_sensor_is_refused_by_the_frames_of_its_sequence(tmp_path, capsys, command):
    """An ECD ``calib.txt`` states no sensor size, but the sequence it lies in lists its frames (``images.txt``):
    their PNG size is the sensor it calibrates. A calib.txt beside 240x180 frames (ECD's DAVIS240C) applied to
    events of a 64x48 sensor is refused in one line naming both sizes (was: applied without a word); beside
    frames of the events' size it is used."""
    import cv2

    events = noise_events(300, 50_000, seed=1)
    path = write_h5(tmp_path / "ev.h5", events)
    sequence = tmp_path / "slider_depth"
    (sequence / "images").mkdir(parents=True)
    (sequence / "calib.txt").write_text("60 60 32 24 -0.37 0.15 0 0 0\n")
    (sequence / "images.txt").write_text("0.000000000 images/frame_00000000.png\n0.038766001 "
                                         "images/frame_00000001.png\n")
    for width, height, refused in ((240, 180, True), (64, 48, False)):
        assert cv2.imwrite(str(sequence / "images" / "frame_00000000.png"), np.zeros((height, width), np.uint8))
        status = main([command, str(path), "--calib", str(sequence / "calib.txt"), "-o", str(tmp_path / f"o{width}"),
                       "--quiet"])
        err = capsys.readouterr().err
        said = (f"calib.txt states no sensor size, but the frames of its sequence ({sequence / 'images'} "
                f"/ frame_00000000.png".replace(" / ", "/") + ", listed in images.txt beside it) are 240x180: it "
                "calibrates a 240x180 sensor, the events of")
        if refused:
            assert status == 2 and said in err and "come from a 64x48 one" in err and err.count("\n") == 1, err
        else:
            assert "states no sensor size" not in err, err


def test_the_sparse_advice_does_not_ask_for_more_events_than_the_window_holds(tmp_path, monkeypatch):
    """The Prophesee Gen4 sample (1280x720, one window of 219,517 events after its hot pixels) was told 'a larger
    --max-events (at least 230,400 on this sensor ...) gives them more': no --max-events reaches 0.25 events per
    pixel there. The advice now compares the density's need with the most events a window holds, which the command
    counts (here against a count window by window)."""
    from dataclasses import replace

    from benchmarks.synthetic_windows import make_window
    from cmax.cli import fit as fit_cli
    from cmax.fitting import QualitySettings, fit
    from cmax.fitting import sequence as sequence_module

    counts = {"ok": 0, "ambiguous": 1, "resolved": 0, "low_parallax": 0, "failed": 0}
    short = fit_cli.advice(counts, "se3", sparse=1, sparse_needs=230_400, densest=219_517, single_window=True)
    assert "--max-events (at least" not in short[0] and "219,517 events, fewer than the 230,400" in short[0]
    many = fit_cli.advice(counts, "se3", sparse=1, sparse_needs=230_400, densest=400_000)
    assert "a larger --max-events (at least 230,400 on this sensor" in many[0]   # reachable: as before
    sparse_windows = fit_cli.advice(counts, "se3", sparse=1, sparse_needs=230_400, densest=100_000)
    assert "a longer --window-ms with --max-events of at least 230,400 gives more" in sparse_windows[0]
    # the command passes the most events a window holds
    w = make_window("driving", 2, width=120, height=90, focal=90.0, duration_s=0.1, max_frames=60)
    base = fit(w.events, w.K, speed=8.0, depth_range=(1.0, 20.0), max_events=1000,
               quality=QualitySettings(ambiguity_test=False))
    monkeypatch.setattr(sequence_module, "fit", lambda events, K, model="se3", **options: replace(
        base, t0_us=int(events.t[0]), t1_us=int(events.t[-1])))
    seen = []
    original = fit_cli.advice
    monkeypatch.setattr(fit_cli, "advice", lambda *a, **k: seen.append(k.get("densest")) or original(*a, **k))
    path = write_h5(tmp_path / "drive.h5", w.events)
    K = ",".join(f"{v:g}" for v in (w.K[0, 0], w.K[1, 1], w.K[0, 2], w.K[1, 2]))
    assert main(["fit", str(path), "--K", K, "-o", str(tmp_path / "out"), "--window-ms", "25", "--min-events", "10",
                 "--quiet", "--speed", "8"]) == 0
    t = w.events.t
    starts = range(int(t[0]), int(t[-1]) + 1 - 25_000 + 1, 25_000)
    assert seen == [max(int(np.sum((t >= s) & (t < s + 25_000))) for s in starts)]
