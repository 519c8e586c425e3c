"""The cmax command line: info and show on files, clear errors on bad input."""
from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np
import pytest

from cmax.cli import main
from cmax.io import write_h5, write_txt
from conftest import random_events


@pytest.fixture
def h5_file(tmp_path):
    ev = random_events(4000, width=64, height=48, t_span_us=200_000, seed=5)
    return write_h5(tmp_path / "ev.h5", ev, source="unit test"), ev


def test_info_reports_counts_rate_and_balance(h5_file, capsys):
    path, ev = h5_file
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    on = int(ev.p.sum())
    assert f"events      {len(ev):,}" in out
    assert "sensor      64 x 48" in out
    assert f"{on:,} ON / {len(ev) - on:,} OFF" in out
    rate = len(ev) / (ev.duration_us / 1e6) / 1e6
    assert f"rate        {rate:.3f} Mev/s" in out
    assert "source = unit test" in out


def test_info_summarises_the_files_after_one_it_cannot_read(h5_file, tmp_path, capsys):
    """`cmax info A BAD C` stopped at BAD: C was never summarised (`cmax info *.raw` over a folder holding one
    truncated recording). Every readable file now gets its block, each bad one a line on stderr, exit status 2."""
    from cmax import Events

    path, ev = h5_file
    later = write_h5(tmp_path / "later.h5", Events([1, 3], [2, 4], [5, 9], [1, 0], width=8, height=8))
    assert main(["info", str(later)]) == 0
    alone = capsys.readouterr().out                       # C summarised on its own: the block expected after BAD
    cut = tmp_path / "cut.h5"
    cut.write_bytes(path.read_bytes()[:3000])             # a copy cut short: not a readable HDF5 file
    missing = tmp_path / "missing.h5"
    assert main(["info", str(path), str(cut), str(missing), str(later)]) == 2
    captured = capsys.readouterr()
    assert captured.out.count("file        ") == 2
    assert captured.out.startswith(f"file        {path}\n") and captured.out.endswith(alone)
    errors = captured.err.splitlines()
    assert len(errors) == 2 and errors[0].startswith("cmax info: error: ") and str(cut) in errors[0]
    assert errors[1].startswith("cmax info: error: ") and str(missing) in errors[1]
    assert main(["info", str(path), str(later)]) == 0     # all readable: exit 0 as before
    with pytest.raises(ValueError, match="cut.h5"):       # --debug: the first error (FormatError), raised
        main(["info", "--debug", str(cut), str(later)])


def test_info_of_one_event_says_the_rate_is_not_available(tmp_path, capsys):
    """Report userC item 7: a file whose events span 0 µs printed `rate        nan Mev/s`."""
    from cmax import Events

    for name, events in (("one.h5", Events([1], [2], [5], [1], width=8, height=8)),
                         ("same_time.h5", Events([1, 3], [2, 4], [5, 5], [1, 0], width=8, height=8))):
        assert main(["info", str(write_h5(tmp_path / name, events))]) == 0
        out = capsys.readouterr().out
        assert "rate        n/a (the events span 0 µs)" in out and "nan" not in out


def test_info_of_a_sparse_recording_gives_its_rate_in_events_per_second(tmp_path, capsys):
    """2,000 events over 40 s printed `rate        0.000 Mev/s`, which reads as a file without events."""
    from cmax import Events

    events = Events(np.arange(2_000) % 8, np.zeros(2_000, int), np.arange(2_000) * 20_000, np.ones(2_000, int),
                    width=8, height=8)                 # 1,999 intervals of 20 ms: 2,000 events / 39.98 s
    assert main(["info", str(write_h5(tmp_path / "sparse.h5", events))]) == 0
    out = capsys.readouterr().out
    assert "rate        50.0 ev/s" in out and "Mev/s" not in out


def test_info_of_an_ecd_folder_points_to_its_events_txt(tmp_path, capsys):
    """Report userC item 7: `cmax info FOLDER` of an ECD sequence advised only `cmax simulate FOLDER`."""
    folder = tmp_path / "slider_depth"
    folder.mkdir()
    (folder / "images.txt").write_text("0.0 images/frame_00000000.png\n")
    write_txt(folder / "events.txt", random_events(20, width=240, height=180))
    assert main(["info", str(folder)]) == 2
    err = capsys.readouterr().err
    assert f"its events are in {folder / 'events.txt'} (give that file)" in err and err.count("\n") == 1
    assert "its frames become events with `cmax simulate FOLDER -o events.h5`" in err
    assert main(["info", str(folder / "events.txt"), "--size", "240x180"]) == 0


def test_polarity_help_states_each_formats_default(tmp_path, capsys):
    """Report userC item 7: the help said "default: 01", but an MVSEC file is read as -1/+1 without the option."""
    import h5py

    with pytest.raises(SystemExit):
        main(["info", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "default: 01;" not in help_text
    assert "(default: the format's own: 01; MVSEC: signed; never guessed)" in help_text
    path = tmp_path / "mvsec.hdf5"
    with h5py.File(path, "w") as file:
        file.create_dataset("davis/left/events", data=np.array([[1, 2, 10.0, -1], [3, 4, 10.5, 1]]))
    assert main(["info", str(path)]) == 0
    assert "1 ON / 1 OFF" in capsys.readouterr().out


def test_info_on_text_needs_size(tmp_path, capsys):
    ev = random_events(100, width=240, height=180)
    path = write_txt(tmp_path / "events.txt", ev)
    assert main(["info", str(path)]) == 2
    assert "width= and height=" in capsys.readouterr().err
    assert main(["info", str(path), "--size", "240x180"]) == 0
    assert "events      100" in capsys.readouterr().out


def test_show_writes_picture_of_the_window(h5_file, tmp_path):
    path, ev = h5_file
    out = tmp_path / "frame.png"
    assert main(["show", str(path), "--t0", "0.05", "--dt", "0.02", "--mode", "frame", "-o", str(out)]) == 0
    image = cv2.imread(str(out))
    assert image.shape[1] == 5 * 64 and image.shape[0] > 5 * 48   # a 64 px sensor drawn 5x (readable_zoom)
    # Pixels with events are coloured, the others white: count them against the window.
    window = ev.slice_time(ev.t_start + 50_000, ev.t_start + 70_000)
    picture = image[-5 * 48::5, ::5]
    coloured = np.count_nonzero((picture != 255).any(axis=2))
    assert coloured == np.unique(window.y.astype(int) * 64 + window.x).size


def test_show_refuses_to_replace_a_picture_without_overwrite(h5_file, tmp_path, capsys):
    """Was: ``cmax show rec.h5`` replaced a user's own ``rec.png`` beside the recording without a word."""
    path, _ = h5_file
    own = path.with_suffix(".png")
    own.write_bytes(b"the user's picture")
    assert main(["show", str(path), "--mode", "frame"]) == 2
    assert f"cmax show: error: {own} exists: --overwrite replaces it" in capsys.readouterr().err
    assert own.read_bytes() == b"the user's picture"
    assert main(["show", str(path), "--mode", "frame", "--overwrite"]) == 0
    assert cv2.imread(str(own)) is not None
    own.unlink()


def test_show_voxel_mode(h5_file, tmp_path):
    path, _ = h5_file
    out = tmp_path / "voxel.png"
    assert main(["show", str(path), "--mode", "voxel", "--bins", "3", "-o", str(out)]) == 0
    width = cv2.imread(str(out)).shape[1]       # three bins side by side, each drawn 5x, then their colour bar
    assert 3 * (5 * 64) + 2 * 4 + 4 + 40 < width < 3 * (5 * 64) + 2 * 4 + 4 + 250


@pytest.mark.parametrize("argv, message", [
    (["show", "MISSING.h5"], "no such event file"),
    (["show", "FILE", "--dt", "0"], "dt must be positive"),
    (["show", "FILE", "--dt", "1e-9"], "dt must be at least 1e-06 s (one microsecond"),  # was: a 0 µs window drawn
    (["show", "FILE", "--t0", "-1"], "t0 must be >= 0"),
    (["info", "BAD"], "cannot tell the event format"),
])
def test_cli_errors_are_one_line(h5_file, tmp_path, capsys, argv, message):
    path, _ = h5_file
    (tmp_path / "bad.bin").write_bytes(b"nonsense")
    argv = [str(path) if a == "FILE" else str(tmp_path / "bad.bin") if a == "BAD" else a for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_console_script_entry_point():
    result = subprocess.run([sys.executable, "-m", "cmax.cli", "--version"], capture_output=True, text=True)
    assert result.returncode == 0 and "evtslowtv" in result.stdout


def test_parser_and_info_start_without_torch(h5_file):
    """Every command's parser is built at start-up; none may load torch (about 1.2 s) to do it."""
    path, ev = h5_file
    code = ("import sys; from cmax.cli import main; main(['info', sys.argv[1]]); "
            "assert 'torch' not in sys.modules, 'torch was imported'")
    result = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert f"{len(ev):,}" in result.stdout


def test_scene_command_writes_events_and_ground_truth(tmp_path, capsys):
    from cmax.sim.synthetic import load_sequence

    out = tmp_path / "slider.h5"
    argv = ["scene", "slider", "-o", str(out), "--duration", "0.1", "--size", "96x72", "--seed", "3", "--depth-rate", "20"]
    assert main(argv) == 0
    sequence = load_sequence(out)
    assert len(sequence.events) > 1000 and sequence.events.sensor_size == (96, 72)
    assert sequence.depth.shape == (3, 72, 96)  # depth maps at 0, 50 and 100 ms
    assert sequence.attrs["simulated_s"] == [0.0, 0.1]     # the file says what was simulated (its scene: 1 s)
    # Slider: pure translation along x, depth within the preset's stated 0.4-3 m.
    valid = np.isfinite(sequence.depth)
    assert 0.4 <= sequence.depth[valid].min() and sequence.depth[valid].max() <= 3.0
    np.testing.assert_allclose(sequence.twists[:, 1:], 0.0, atol=1e-9)
    assert main(argv) == 2 and "overwrite" in capsys.readouterr().err


def test_scene_output_written_by_another_run_meanwhile_is_kept_and_named_in_the_command_s_words(tmp_path, capsys,
                                                                                                  monkeypatch):
    """Two `cmax scene -o S.h5` at once, or a file put at S.h5 while the scene is simulated (was: `S.h5 exists
    (pass overwrite=True to replace it)`, the API's words): one line naming --overwrite; the file kept."""
    import cmax.sim.synthetic as synthetic

    out = tmp_path / "s.h5"
    simulate = synthetic.simulate_scene

    def simulate_then_plant(*args, **kwargs):
        sequence = simulate(*args, **kwargs)
        out.write_bytes(b"the other run's file")
        return sequence

    monkeypatch.setattr(synthetic, "simulate_scene", simulate_then_plant)
    argv = ["scene", "slider", "-o", str(out), "--duration", "0.02", "--size", "32x24", "--depth-rate", "50"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    line = err.rstrip("\n").split("\n")[-1].split("\r")[-1]     # after the progress bar
    assert line.startswith(f"cmax scene: error: {out} was written by another program while this scene was simulated")
    assert "pass --overwrite to replace it" in line and "overwrite=True" not in err and err.count("error") == 1, err
    assert out.read_bytes() == b"the other run's file" and sorted(p.name for p in tmp_path.iterdir()) == ["s.h5"]


def test_fit_writes_depth_trajectory_and_summary(tmp_path):
    """`cmax fit` on two windows of a sliding camera (known speed): per-window depth npz + PNG, a TUM
    trajectory whose path length is speed x time (whatever the fitted directions), and a summary with
    the parallax of each window. (A slide along one wall is the plane ambiguity: the depth is not
    checked against the truth here; benchmarks/accuracy_cmax.py measures it.)"""
    import json

    from benchmarks.synthetic_windows import make_window

    w = make_window("slider", 7, width=120, height=90, focal=90.0, duration_s=0.2)
    path = tmp_path / "slider.h5"
    write_h5(path, w.events)
    K = w.K
    speed = float(np.linalg.norm(w.twist[:3]))
    args = ["fit", str(path), "--K", f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}", "-o", str(tmp_path / "out"),
            "--window-ms", "90", "--speed", str(speed), "--max-events", "15000"]
    assert main(args) == 0
    out = tmp_path / "out"
    depth = np.load(out / "depth_00000.npz")
    assert depth["depth"].shape == depth["depth_spread"].shape == (90, 120) and depth["mask"].any()
    inside = depth["depth"][depth["mask"]]
    assert np.all(np.isfinite(inside)) and inside.min() >= 0.5 * 0.999 and inside.max() <= 60.0 * 1.001
    picture = cv2.imread(str(out / "depth_00000.png"))
    assert picture.shape[1] > 120 + 30 and picture.shape[0] > 90   # the map, its title and its colour bar
    lines = (out / "trajectory.txt").read_text().splitlines()
    assert lines[:2] == ["# t[s] tx ty tz qx qy qz qw (TUM)", "# T_w_c (camera-to-world); translation in metres"]
    rows = [line.split() for line in lines[2:]]
    times = np.array([float(r[0]) for r in rows])
    positions = np.array([[float(v) for v in r[1:4]] for r in rows])
    path_length = np.linalg.norm(np.diff(positions, axis=0), axis=1).sum()
    assert path_length == pytest.approx(speed * (times[-1] - times[0]), rel=0.02)
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["windows"]) == len(rows) - 1 >= 2
    assert all(window["parallax_px"] > 0 and window["scale_known"] for window in summary["windows"])
    assert summary["zero_rotation_start"] is False
    # Every number says its unit: v is the given speed in m/s, depth and the trajectory in metres.
    units = summary["units"]
    assert units["v"].startswith("m/s") and units["omega"].startswith("rad/s")
    assert all(np.linalg.norm(window["v"]) == pytest.approx(speed, rel=1e-6) for window in summary["windows"])
    assert units["depth_range"] == "m" and "z-depth [m]" in units["depth_NNNNN.npz"]


def test_fit_with_members_reaches_the_fit(tmp_path):
    """`cmax fit --members 3`: the motion stages run on three draws of the window (three times the solver
    iterations of those stages, counted in the window's iterations) and the summary records it."""
    import json

    from benchmarks.synthetic_windows import make_window

    w = make_window("slider", 7, width=120, height=90, focal=90.0, duration_s=0.1)
    write_h5(tmp_path / "slider.h5", w.events)
    K = w.K
    args = ["fit", str(tmp_path / "slider.h5"), "--K", f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}",
            "--window-ms", "90", "--max-events", "15000", "--speed", "1", "--quiet"]
    summaries = {}
    for name, flag in (("one", []), ("three", ["--members", "3"])):
        assert main(args + ["-o", str(tmp_path / name)] + flag) == 0
        summaries[name] = json.loads((tmp_path / name / "summary.json").read_text())
    assert (summaries["one"]["members"], summaries["three"]["members"]) == (1, 3)
    assert summaries["three"]["windows"][0]["iterations"] > summaries["one"]["windows"][0]["iterations"]
    with pytest.raises(SystemExit):
        main(args + ["-o", str(tmp_path / "bad"), "--members", "0"])


def test_fit_with_the_polish_reaches_the_fit(tmp_path):
    """`cmax fit --polish depth`: each se3 window ends on the shared objective (the depth grid moves, more
    solver iterations), and the summary records it; without the flag the library's default, none."""
    import json

    from benchmarks.synthetic_windows import make_window

    w = make_window("slider", 7, width=120, height=90, focal=90.0, duration_s=0.1)
    write_h5(tmp_path / "slider.h5", w.events)
    K = w.K
    args = ["fit", str(tmp_path / "slider.h5"), "--K", f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}",
            "--window-ms", "90", "--max-events", "15000", "--speed", "1", "--quiet"]
    summaries, grids = {}, {}
    for name, flag in (("plain", []), ("polished", ["--polish", "depth"])):
        assert main(args + ["-o", str(tmp_path / name)] + flag) == 0
        summaries[name] = json.loads((tmp_path / name / "summary.json").read_text())
        grids[name] = np.load(tmp_path / name / "depth_00000.npz")["inverse_depth_grid"]
    assert (summaries["plain"]["polish"], summaries["polished"]["polish"]) == ("none", "depth")
    assert summaries["polished"]["windows"][0]["iterations"] > summaries["plain"]["windows"][0]["iterations"]
    assert not np.allclose(grids["plain"], grids["polished"])
    with pytest.raises(SystemExit):
        main(args + ["-o", str(tmp_path / "bad"), "--polish", "motion"])


def test_fit_with_the_zero_rotation_start(tmp_path, capsys):
    """`cmax fit --zero-rotation-start` reaches the fit: a second refinement runs (more solver
    iterations than without the flag), and the summary records it."""
    import json

    from benchmarks.synthetic_windows import make_window

    w = make_window("slider", 7, width=120, height=90, focal=90.0, duration_s=0.1)
    write_h5(tmp_path / "slider.h5", w.events)
    K = w.K
    args = ["fit", str(tmp_path / "slider.h5"), "--K", f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}",
            "--window-ms", "90", "--max-events", "15000"]
    summaries = []
    for name, flag in (("plain", []), ("both", ["--zero-rotation-start"])):
        assert main(args + ["-o", str(tmp_path / name)] + flag) == 0
        summaries.append(json.loads((tmp_path / name / "summary.json").read_text()))
    plain, both = summaries
    assert (plain["zero_rotation_start"], both["zero_rotation_start"]) == (False, True)
    assert both["windows"][0]["iterations"] > plain["windows"][0]["iterations"]
    # the printed summary counts the windows with under 1 px of fitted parallax, or that a rotation alone
    # explains (cause rotation_only), among the verdicts: low parallax unless a stage failed (this slow slide's
    # window sits at 1 px: 0.99 or 1.07 with float rounding; test_cli_fit's constructed run prints one of each)
    low = sum((w["parallax_px"] < 1.0 or w["cause"] == "rotation_only") and w["verdict"] != "failed"
              for w in both["windows"])
    assert f", {low} low parallax, " in capsys.readouterr().out.splitlines()[-1]


@pytest.mark.parametrize("command", ["info", "show", "scene", "fit", "depth", "emvs", "demo", "simulate"])
def test_every_command_describes_itself_in_plain_text(command, capsys):
    """``cmax fit --help`` showed the module docstring's reST (````cmax fit````), ``cmax info --help`` no
    description at all."""
    with pytest.raises(SystemExit) as stop:
        main([command, "--help"])
    assert stop.value.code == 0
    text = capsys.readouterr().out
    description = text.split("\n\n")[1]
    assert "``" not in text and len(description.split()) >= 5, text[:400]


def _two_camera_mvsec(path, left: int = 5, right: int = 7):
    """An MVSEC-layout file with ``left`` events on davis/left and ``right`` on davis/right (all ON at (1, 2) on the
    left, all OFF at (3, 4) on the right), one per 10 ms from t = 10 s."""
    import h5py

    def table(count, x, y, p):
        return np.array([[x, y, 10.0 + 0.01 * i, p] for i in range(count)])

    with h5py.File(path, "w") as file:
        file.create_dataset("davis/left/events", data=table(left, 1, 2, 1))
        file.create_dataset("davis/right/events", data=table(right, 3, 4, -1))
    return path


def test_info_names_the_mvsec_camera_and_reads_the_right_one(tmp_path, capsys):
    """Was: `cmax info` on an MVSEC file summarised its left camera without saying so, never mentioned the right
    camera, and no command could read the right one (only `cmax.io.read(..., camera='right')`)."""
    path = _two_camera_mvsec(tmp_path / "rig.hdf5")
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "events      5\n" in out and "5 ON / 0 OFF" in out
    assert "camera      left (davis/left/events); the file also holds right (7 events): --camera right" in out
    assert main(["info", str(path), "--camera", "right"]) == 0
    out = capsys.readouterr().out
    assert "events      7\n" in out and "0 ON / 7 OFF" in out
    assert "camera      right (davis/right/events); the file also holds left (5 events)" in out


def test_camera_option_reaches_show_and_is_refused_for_other_formats(h5_file, tmp_path, capsys):
    path = _two_camera_mvsec(tmp_path / "rig.hdf5", left=3, right=40)
    out = tmp_path / "right.png"
    assert main(["show", str(path), "--camera", "right", "--dt", "1", "--mode", "frame", "-o", str(out)]) == 0
    assert cv2.imread(str(out)) is not None
    capsys.readouterr()
    dsec, _ = h5_file
    assert main(["info", str(dsec), "--camera", "right"]) == 2
    err = capsys.readouterr().err
    assert "--camera applies to MVSEC files" in err and err.count("\n") == 1


def test_camera_option_reaches_the_reader_of_fit_and_depth(tmp_path):
    """`cmax fit` / `cmax emvs` read through `read_calibrated`, `cmax depth` through `learned.predict`'s
    `open_recording`: both must give the right camera's events when asked."""
    import argparse

    from cmax.cli.recording import read_calibrated
    from learned.predict import open_recording

    path = _two_camera_mvsec(tmp_path / "rig.hdf5", left=3, right=40)
    args = argparse.Namespace(file=path, size=None, time_unit=None, polarity=None, sort=False, camera="right",
                              t0=None, t1=None)
    events, _ = read_calibrated(args, None)
    assert len(events) == 40 and set(events.x.tolist()) == {3}
    recording = open_recording(path, camera="right")
    try:
        assert recording.last_us - recording.first_us == 390_000
    finally:
        recording.close()
    dsec = write_h5(tmp_path / "one.h5", random_events(50))
    with pytest.raises(ValueError, match="applies to MVSEC files"):
        open_recording(dsec, camera="right")


def test_an_mvsec_file_of_the_right_camera_alone_names_it(tmp_path, capsys):
    """Was: `davis/left/events` missing read as "not an MVSEC data file?", though the file held the right camera."""
    import h5py

    path = tmp_path / "right.hdf5"
    with h5py.File(path, "w") as file:
        file.create_dataset("davis/right/events", data=np.array([[1, 2, 10.0, -1], [3, 4, 10.5, 1]]))
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err
    assert "it holds the events of the right camera: read them with camera='right' (cmax: --camera right)" in err
    assert main(["info", str(path), "--camera", "right"]) == 0
    assert "events      2\n" in capsys.readouterr().out


def test_info_reads_an_mvsec_camera_a_chunk_at_a_time(tmp_path, monkeypatch):
    """`cmax info` promised bounded memory but read an MVSEC camera whole (32 bytes a row on disk, several GB for
    a long recording; past MAX_EVENTS an EventLimitError). Chunk by chunk it gives what the whole read gives, and a
    time going back across a chunk boundary is still refused."""
    import h5py

    import cmax.events
    import cmax.io.info
    from cmax.io import FormatError, read
    from cmax.io.info import events_info, file_info

    rng = np.random.default_rng(2)
    n = 50
    table = np.stack([rng.integers(0, 346, n), rng.integers(0, 260, n), 20.0 + np.sort(rng.random(n)),
                      rng.choice([-1.0, 1.0], n)], axis=1)
    path = tmp_path / "rig.hdf5"
    with h5py.File(path, "w") as file:
        file.create_dataset("davis/left/events", data=table)
    whole = events_info(read(path), path=str(path), format="mvsec")
    monkeypatch.setattr(cmax.io.info, "_CHUNK", 7)
    monkeypatch.setattr(cmax.events, "MAX_EVENTS", 10)         # the camera does not fit; a chunk does
    summary = file_info(path)
    assert whole.count == n
    assert (summary.count, summary.t_start_us, summary.t_end_us, summary.on_count) == \
           (whole.count, whole.t_start_us, whole.t_end_us, whole.on_count)
    np.testing.assert_array_equal(summary.pixel_counts, whole.pixel_counts)
    table[7, 2], table[6, 2] = table[6, 2], table[7, 2] + 0.5    # row 7 (a chunk's first) before row 6
    with h5py.File(path, "w") as file:
        file.create_dataset("davis/left/events", data=table)
    with pytest.raises(FormatError, match="corrupt events at row 7"):
        file_info(path)


def test_info_counts_events_that_repeat_an_earlier_one_exactly(tmp_path, capsys):
    """Was: a file whose every event was written twice summarised as a clean recording of twice the rate."""
    from cmax.events import Events

    events = random_events(500, 64, 48, seed=4)
    twice = Events(*(np.repeat(column, 2) for column in (events.x, events.y, events.t, events.p)), 64, 48)
    path = write_h5(tmp_path / "twice.h5", twice)
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    expected = len(twice) - len(set(zip(twice.x.tolist(), twice.y.tolist(), twice.t.tolist(), twice.p.tolist())))
    assert expected >= 500 and f"duplicates  {expected:,} events (" in out, out
    assert main(["info", str(write_h5(tmp_path / "once.h5", events))]) == 0
    assert "duplicates" not in capsys.readouterr().out       # random events on distinct µs: none


def test_duplicates_split_between_chunks_are_counted_once(tmp_path, monkeypatch):
    """The summary reads a file in chunks; rows of one time stamp on both sides of a chunk's end are compared."""
    import cmax.io.info
    from cmax.events import Events
    from cmax.io.info import file_info

    rng = np.random.default_rng(5)
    n = 400
    t = np.sort(rng.integers(0, 40, n))                     # ~10 events a µs, on 3 pixels, both polarities
    x, y, p = rng.integers(0, 3, n), np.zeros(n, np.int64), rng.integers(0, 2, n)
    path = write_h5(tmp_path / "dense.h5", Events(x, y, t, p, 4, 2))
    expected = n - len(set(zip(x.tolist(), y.tolist(), t.tolist(), p.tolist())))
    monkeypatch.setattr(cmax.io.info, "_CHUNK", 7)
    assert expected > 100 and file_info(path).duplicates == expected


def test_info_says_a_raw_sensor_size_is_only_inferred_from_the_camera_name(tmp_path, capsys):
    """Was: `sensor      640 x 480` for a Gen4 (1280x720) recording whose events lie in its top-left 640x480 (an
    ROI) saved by expelliarmus, whose header names `hal_plugin_gen3_fx3` for every file: a guess shown as a fact."""
    from cmax.events import Events
    from cmax.io import write_evt2

    events = Events([100, 5], [200, 3], [10, 20], [1, 0], width=1280, height=720)
    data = write_evt2(tmp_path / "gen4.raw", events).read_bytes().split(b"% end\n", 1)[1]
    path = tmp_path / "saved_by_expelliarmus.raw"
    path.write_bytes(b"% evt 2.0\n% plugin_name hal_plugin_gen3_fx3\n" + data)
    assert main(["info", str(path)]) == 0
    assert ("sensor      640 x 480 (not stated by the file: inferred from its 'plugin_name hal_plugin_gen3_fx3' "
            "line; --size WxH gives the sensor's)\n") in capsys.readouterr().out
    assert main(["info", str(path), "--size", "1280x720"]) == 0
    assert "sensor      1280 x 720\n" in capsys.readouterr().out


def test_mvsec_times_in_microseconds_name_the_unit_that_reads_them(tmp_path, capsys):
    """Was: `... = 1500000000000099.0 s does not fit into int64 microseconds`, without saying that the column holds
    microseconds since 1970 (a converted MVSEC file), nor which option reads it."""
    import h5py

    t_us = 1_500_000_000_000_000 + np.arange(100, dtype=np.int64)
    table = np.stack([np.full(100, 3), np.full(100, 4), t_us, np.ones(100)], axis=1).astype(np.float64)
    path = tmp_path / "us.hdf5"
    with h5py.File(path, "w") as file:
        file.create_dataset("davis/left/events", data=table)
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "does not fit into int64 microseconds; as us it is 1500000000.000099 s since " \
        "1970: state the unit with time_unit='us' (cmax: --time-unit us)" in err, err
    assert main(["info", str(path), "--time-unit", "us"]) == 0
    assert "time        1500000000000000 .. 1500000000000099 µs" in capsys.readouterr().out
