"""What a new user meets first: ``cmax scene``, ``cmax emvs`` and ``cmax demo`` refuse a mistake in one line
that names the option to change, BEFORE the long work (simulating), and do what the README says on the files
``cmax scene`` writes; a warning of the library is one line."""
from __future__ import annotations

import numpy as np
import pytest

from cmax.cli import main as cmax_main
from conftest import one_line_error


# -- cmax scene ------------------------------------------------------------------------------------
@pytest.fixture
def no_simulation(monkeypatch):
    """Make simulating fail: a refusal must come before it (it took minutes before the error)."""
    import cmax.sim.synthetic

    def simulate(*args, **kwargs):
        raise AssertionError("simulated before refusing the output")

    monkeypatch.setattr(cmax.sim.synthetic, "simulate_scene", simulate)


@pytest.mark.parametrize("output, extra, message", [
    ("EXISTING", [], "exists: pass --overwrite to replace it"),
    ("scene.txt", [], "cmax scene writes an HDF5 file: give a name ending in .h5"),
    (".", [], "is a folder: give the file to write"),
    ("missing/scene.h5", [], "the folder missing does not exist"),
    ("scene.h5", ["--depth-rate", "1e9"], "asks for 100,000,001 depth maps of 64x48 over 0.1 s"),
])
def test_scene_refuses_its_output_before_simulating(tmp_path, capsys, monkeypatch, no_simulation, output, extra,
                                                    message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "EXISTING").with_suffix(".h5").write_bytes(b"an earlier result")
    output = "EXISTING.h5" if output == "EXISTING" else output
    status, err = one_line_error(lambda: cmax_main(["scene", "slider", "-o", output, "--duration", "0.1",
                                               "--size", "64x48", *extra]), capsys)
    assert status == 2 and message in err, err
    assert (tmp_path / "EXISTING.h5").read_bytes() == b"an earlier result"


@pytest.mark.parametrize("size", ["10x10", "1x1", "31x24", "346x23"])
def test_scene_refuses_a_sensor_too_small_to_fit_before_simulating(tmp_path, capsys, no_simulation, size):
    """Was: `--size 10x10` wrote a file of 17 events (exit 0, no word); `--size 1x1` failed after building the
    scene with numpy's "Shape of array too small to calculate a numerical gradient"."""
    status, err = one_line_error(lambda: cmax_main(["scene", "slider", "-o", str(tmp_path / "s.h5"), "--size", size]),
                                 capsys)
    assert status == 2 and "argument --size: expected at least 32x24 pixels" in err and repr(size) in err, err
    assert not (tmp_path / "s.h5").exists()


def test_scene_minimum_size_is_what_the_default_fit_needs():
    """`MIN_SIZE` is the smallest sensor `cmax.fit`'s default depth grid (rows, columns) fits."""
    import inspect

    import cmax
    from cmax.cli.scene import MIN_SIZE, scene_size

    rows, cols = inspect.signature(cmax.fit).parameters["depth_grid"].default
    assert MIN_SIZE == (cols, rows)
    assert scene_size(f"{cols}x{rows}") == (cols, rows)


def test_scene_depth_map_budget_is_the_memory_they_take():
    from cmax.cli.scene import MAX_DEPTH_BYTES, check_depth_maps

    maps = MAX_DEPTH_BYTES // (346 * 260 * 4)                # just fits: 11,930 maps of a DAVIS346
    check_depth_maps((maps - 1) / 1000.0, 1000.0, 346, 260)
    with pytest.raises(ValueError, match=f"asks for {maps + 1:,} depth maps of 346x260"):
        check_depth_maps(maps / 1000.0, 1000.0, 346, 260)


@pytest.mark.parametrize("option, value", [("--duration", "nan"), ("--duration", "0"), ("--cp", "-1"),
                                           ("--cn", "inf")])
def test_scene_numbers_are_refused_by_their_option_name(tmp_path, capsys, option, value):
    status, err = one_line_error(lambda: cmax_main(["scene", "slider", "-o", str(tmp_path / "s.h5"), option, value]),
                            capsys)
    assert status == 2 and f"argument {option}: expected a finite number > 0" in err


# -- cmax emvs ---------------------------------------------------------------------------------------
def test_emvs_uses_the_files_own_poses(slider_file, tmp_path, capsys):
    """Without --poses an h5 file's gt/poses are the trajectory: the depth of cmax.EMVS run on those poses."""
    import h5py

    import cmax
    from cmax.camera import Camera

    with h5py.File(slider_file, "r") as file:
        times, poses, K = file["gt/poses_t"][()], file["gt/poses"][()], file["gt/K"][()]
    events = cmax.io.read(slider_file)
    expected = cmax.EMVS(Camera(K, 64, 48), depth_range=(0.4, 3.0), n_planes=40).run(events, (times, poses))
    assert cmax_main(["emvs", str(slider_file), "--depth-range", "0.4,3", "--planes", "40",
                      "-o", str(tmp_path / "own")]) == 0
    own = np.load(tmp_path / "own" / "depth.npz")
    assert expected.mask.sum() > 0
    np.testing.assert_array_equal(own["mask"], expected.mask)
    np.testing.assert_array_equal(own["depth"], expected.depth)


def test_emvs_without_poses_anywhere_says_how_to_give_them(tmp_path, capsys):
    from cmax.io import write_h5
    from conftest import random_events

    bare = write_h5(tmp_path / "bare.h5", random_events(500, width=64, height=48))
    status, err = one_line_error(lambda: cmax_main(["emvs", str(bare), "--K", "60,60,32,24", "-o", str(tmp_path / "o")]),
                            capsys)
    assert status == 2 and "stores no poses (gt/poses): give them with --poses traj.txt" in err


@pytest.mark.parametrize("argv, message", [
    (["--poses", "FILE"], "is not a text file: expected a TUM trajectory"),      # the h5 given as the poses
    (["-o", "FILE"], "is a file, not a folder: give a folder for depth.npz"),
    (["--t0", "5"], "--t0 5.0 s is past the recording's last event"),
    (["--planes", "1"], "argument --planes: expected a whole number >= 2"),
    (["--depth-range", "3,0.4"], "0 < NEAR < FAR"),
])
def test_emvs_mistakes_name_the_option(slider_file, tmp_path, capsys, argv, message):
    argv = [str(slider_file) if a == "FILE" else a for a in argv]
    output = [] if "-o" in argv else ["-o", str(tmp_path / "o")]
    status, err = one_line_error(lambda: cmax_main(["emvs", str(slider_file), *output, *argv]), capsys)
    assert status == 2 and message in err, err
    assert not (tmp_path / "o").exists()


# -- warnings of the library ---------------------------------------------------------------------------
def test_a_library_warning_is_one_line_and_debug_shows_pythons_format(capsys):
    import argparse
    import warnings

    from cmax._args import ArgumentParser, run_main

    class FarWarning(UserWarning):
        pass

    def command(args: argparse.Namespace) -> int:
        warnings.warn("the scene is\n far away", FarWarning)
        return 0

    assert run_main(ArgumentParser(prog="tool"), command, []) == 0
    assert capsys.readouterr().err == "tool: warning: the scene is far away\n"
    with pytest.warns(FarWarning, match="the scene is"):   # --debug: Python's own warning, left to its handler
        assert run_main(ArgumentParser(prog="tool"), command, ["--debug"]) == 0
    assert "tool: warning" not in capsys.readouterr().err


# -- cmax demo -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("argv, message", [
    (["--window", "2"], "--window-s must be in (0, --duration=0.5], got 2.0"),
    (["--window-ms", "2000"], "--window-s must be in (0, --duration=0.5], got 2.0"),
    (["--duration", "0.05"], "--window-s must be in (0, --duration=0.05], got 0.1665"),
    (["--size", "8x8"], "--size width must be an integer >= 32 (cmax.fit's default depth grid of 24x32 nodes needs a sensor of 32x24 px), got 8"),
    (["-o", "FILE"], "is a file, not a folder: give a folder for the demo's h5 file and report"),
])
def test_demo_refusals_name_the_options(tmp_path, capsys, argv, message):
    (tmp_path / "a.txt").write_text("notes")
    argv = [str(tmp_path / "a.txt") if a == "FILE" else a for a in argv]
    output = [] if "-o" in argv else ["-o", str(tmp_path / "demo")]
    status, err = one_line_error(lambda: cmax_main(["demo", *output, *argv]), capsys)
    assert status == 2 and message in err, err
    assert not (tmp_path / "demo").exists()




# -- negative numbers as values ------------------------------------------------------------------------------
def test_comma_separated_values_may_start_negative(capsys):
    """``--omega -0.1,0,0`` is a value (argparse took it for an unknown option: 'expected one argument')."""
    from cmax.cli import build_parser

    parser = build_parser()
    base = ["fit", "a.h5", "--K", "60,60,32,24", "-o", "out"]
    assert parser.parse_args([*base, "--omega", "-0.1,0,0"]).omega == (-0.1, 0.0, 0.0)
    assert parser.parse_args([*base, "--omega", "-1e-3,-2,+3"]).omega == (-0.001, -2.0, 3.0)
    status, err = one_line_error(lambda: cmax_main(["emvs", "a.h5", "-o", "o", "--K", "-100,100,60,45"]), capsys)
    assert status == 2 and "K must have positive focal lengths" in err
    status, err = one_line_error(lambda: cmax_main(["emvs", "a.h5", "-o", "o", "--depth-range", "-1,1"]), capsys)
    assert status == 2 and "0 < NEAR < FAR" in err
    status, err = one_line_error(lambda: cmax_main([*base, "-x"]), capsys)   # an option is still an option
    assert status == 2 and "unrecognized arguments: -x" in err


def test_emvs_takes_a_calibration_file_and_a_time_unit(slider_file, tmp_path, capsys):
    """``--calib calib.txt`` (ECD) gives the same depth as ``--K``; a .npy of float seconds needs --time-unit,
    which cmax emvs now has (it had neither: 'unrecognized arguments')."""
    import h5py

    import cmax

    with h5py.File(slider_file, "r") as file:
        K = file["gt/K"][()]
    numbers = [repr(float(v)) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2])]
    (tmp_path / "calib.txt").write_text(" ".join(numbers) + "\n")
    events = cmax.io.read(slider_file)
    table = np.zeros(len(events), dtype=[("t", "<f8"), ("x", "<u2"), ("y", "<u2"), ("p", "i1")])
    table["t"], table["x"], table["y"], table["p"] = events.t * 1e-6, events.x, events.y, events.p
    np.save(tmp_path / "events.npy", table)
    from cmax.cli.fit import tum_lines

    with h5py.File(slider_file, "r") as file:
        (tmp_path / "traj.txt").write_text("\n".join(tum_lines(file["gt/poses_t"][()], file["gt/poses"][()])) + "\n")
    common = ["--depth-range", "0.4,3", "--planes", "40", "--poses", str(tmp_path / "traj.txt")]
    assert cmax_main(["emvs", str(slider_file), "-o", str(tmp_path / "k"), *common]) == 0
    assert cmax_main(["emvs", str(slider_file), "-o", str(tmp_path / "calib"), "--calib", str(tmp_path / "calib.txt"),
                      *common]) == 0
    status, err = one_line_error(lambda: cmax_main(["emvs", str(tmp_path / "events.npy"), "-o", str(tmp_path / "npy"),
                                               "--size", "64x48", *common]), capsys)
    assert status == 2 and "time_unit=" in err   # (cmax.io names the keyword, not --time-unit)
    assert cmax_main(["emvs", str(tmp_path / "events.npy"), "-o", str(tmp_path / "npy"), "--size", "64x48",
                      "--time-unit", "s", "--K", ",".join(numbers),
                      *common]) == 0
    assert "calib.txt lies beside the events but was not read" in capsys.readouterr().err   # --K, calib.txt there
    by_k, by_calib, by_npy = (np.load(tmp_path / name / "depth.npz") for name in ("k", "calib", "npy"))
    assert by_k["mask"].sum() > 0
    for other in (by_calib, by_npy):
        np.testing.assert_array_equal(other["mask"], by_k["mask"])
        np.testing.assert_array_equal(other["depth"], by_k["depth"])
    status, err = one_line_error(lambda: cmax_main(["emvs", str(slider_file), "-o", str(tmp_path / "o"), "--calib",
                                               str(tmp_path / "calib.txt"), "--distortion", "0,0,0,0"]), capsys)
    assert status == 2 and "pass --calib or --K with --distortion, not both" in err


def test_emvs_picture_of_a_small_sensor_is_enlarged(slider_file, tmp_path):
    """depth.png of a 64x48 file was 64x48 maps under wrapped titles; each pixel is now a 5x5 block."""
    import cv2

    import cmax
    from cmax.camera import Camera
    from cmax.cli.emvs import file_trajectory

    assert cmax_main(["emvs", str(slider_file), "-o", str(tmp_path / "o"), "--depth-range", "0.4,3",
                      "--planes", "40"]) == 0
    picture = cv2.imread(str(tmp_path / "o" / "depth.png"))
    assert picture.shape[1] > 2 * 320
    with np.load(tmp_path / "o" / "depth.npz") as saved:
        K = saved["K"]
    result = cmax.EMVS(Camera(K, 64, 48), depth_range=(0.4, 3.0), n_planes=40).run(cmax.io.read(slider_file),
                                                                                     file_trajectory(slider_file))
    assert np.array_equal(picture, result.image(zoom=5))
    assert np.array_equal(picture, result.image())       # the API's default enlarges a small sensor too
    small = result.image(zoom=1)
    assert small.shape[1] < picture.shape[1] / 2 and small.shape[0] < picture.shape[0] / 2
    with pytest.raises(ValueError, match="zoom must be a whole number >= 1"):
        result.image(zoom=0)


def test_emvs_takes_the_depth_range_a_scene_file_records(slider_file, tmp_path, capsys):
    """A cmax scene file records its scene's depth range (slider: 0.4-3 m); EMVS's default 0.5-5 m ignored it."""
    assert cmax_main(["emvs", str(slider_file), "-o", str(tmp_path / "own"), "--planes", "40"]) == 0
    assert "note: planes over 0.4-3 m, the depth range the file records" in capsys.readouterr().err
    assert cmax_main(["emvs", str(slider_file), "-o", str(tmp_path / "given"), "--planes", "40",
                      "--depth-range", "0.4,3"]) == 0
    assert "note:" not in capsys.readouterr().err
    own, given = np.load(tmp_path / "own" / "depth.npz"), np.load(tmp_path / "given" / "depth.npz")
    assert tuple(own["depth_range"]) == (0.4, 3.0)
    np.testing.assert_array_equal(own["depth"], given["depth"])


def test_scene_says_the_intrinsics_and_depth_range_it_stored(tmp_path, capsys):
    """The README's `cmax fit room.h5 --K 78.5,78.3,59.9,46.0` needs K: `cmax scene` now prints it."""
    from cmax.sim.synthetic import load_sequence

    out = tmp_path / "room.h5"
    assert cmax_main(["scene", "indoor_flying", "-o", str(out), "--duration", "0.05", "--size", "64x48"]) == 0
    line = capsys.readouterr().out
    K = load_sequence(out).K
    assert f"--K {K[0, 0]:.6g},{K[1, 1]:.6g},{K[0, 2]:.6g},{K[1, 2]:.6g}, depth 1-6.5 m (both stored in the file)" \
        in line
    fx, fy, cx, cy = (float(v) for v in line.split("--K ")[1].split(",")[:4])
    np.testing.assert_allclose([fx, fy, cx, cy], [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], rtol=1e-5)


def test_an_unknown_option_is_named_by_its_sub_command(capsys):
    """It was 'cmax: error: unrecognized arguments: --bogus x (see cmax --help)', not the sub-command's help."""
    status, err = one_line_error(lambda: cmax_main(["emvs", "a.h5", "-o", "o", "--bogus", "x"]), capsys)
    assert status == 2 and err == "cmax emvs: error: unrecognized arguments: --bogus x (see cmax emvs --help)\n"
    status, err = one_line_error(lambda: cmax_main(["--bogus"]), capsys)
    assert status == 2 and err.startswith("cmax: error: unrecognized arguments: --bogus")


# -- one window option, two units, on every command -------------------------------------------------------
_WINDOW_COMMANDS = {   # command line before the window option; the attribute holding the window; its unit
    "fit": (["fit", "f.h5", "--K", "1,1,1,1", "-o", "out"], "window_ms", 1e-3),
    "depth": (["depth", "f.h5", "-o", "out"], "window", 1.0),
    "demo": (["demo"], "window", 1.0),
    "show": (["show", "f.h5"], "dt", 1.0),
}


@pytest.mark.parametrize("command", sorted(_WINDOW_COMMANDS))
def test_every_command_with_a_window_takes_it_in_ms_or_in_s_and_keeps_its_old_spelling(command):
    """``cmax fit`` took ``--window-ms``, ``cmax depth`` and ``cmax demo`` ``--window`` [s], ``cmax show`` ``--dt``
    [s]: the spelling learned on one command was refused on another. Now each takes ``--window-ms`` and
    ``--window-s``: 150 ms and 0.15 s are the same window, as the old spelling gave it."""
    from cmax.cli import build_parser

    before, attribute, seconds_per_unit = _WINDOW_COMMANDS[command]
    parser = build_parser()

    def window_s(*option: str) -> float:
        return getattr(parser.parse_args([*before, *option]), attribute) * seconds_per_unit

    old = {"fit": ("--window-ms", "150"), "show": ("--dt", "0.15")}.get(command, ("--window", "0.15"))
    assert window_s(*old) == pytest.approx(0.15, rel=1e-12)
    assert window_s("--window-ms", "150") == pytest.approx(0.15, rel=1e-12)
    assert window_s("--window-s", "0.15") == pytest.approx(0.15, rel=1e-12)
    # the same value, not one float's rounding apart: --resume compares the options it records
    assert getattr(parser.parse_args([*before, "--window-ms", "33.3"]), attribute) == \
        getattr(parser.parse_args([*before, "--window-s", "0.0333"]), attribute)


@pytest.mark.parametrize("argv", [["--window", "150"], ["--window-s", "0.1", "--window-ms", "100"],
                                  ["--step", "50"]])
def test_fit_refuses_a_window_without_its_unit_naming_both_spellings(capsys, argv):
    """``cmax fit --window 150`` was read as ``--window-ms 150`` (argparse's abbreviation), ``--window 0.15`` (the
    seconds of ``cmax depth``) as a window of 150 µs, without a word: now refused, naming the options with units."""
    status, err = one_line_error(lambda: cmax_main(["fit", "f.h5", "--K", "1,1,1,1", "-o", "out", *argv]), capsys)
    assert status == 2, err
    stem = argv[0].lstrip("-").split("-")[0]
    assert f"--{stem}-ms" in err and f"--{stem}-s" in err, err


# -- --quiet on every long-running command ----------------------------------------------------------------
def test_scene_quiet_writes_no_progress_bar(tmp_path, capsys):
    """``cmax scene`` drew its progress bar on stderr with no way to turn it off (fit, depth, emvs and simulate
    took ``--quiet``); with ``--quiet`` stderr stays empty and the result line is printed."""
    assert cmax_main(["scene", "slider", "-o", str(tmp_path / "s.h5"), "--duration", "0.1", "--size", "64x48",
                      "--quiet"]) == 0
    out, err = capsys.readouterr()
    assert err == "" and out.startswith(f"wrote {tmp_path / 's.h5'}: "), (out, err)


def test_demo_quiet_prints_only_where_its_report_is(tmp_path, capsys, monkeypatch):
    """``cmax demo`` printed its progress lines with no ``--quiet``; with it only the report's path is printed."""
    import types

    import cmax.demo

    def run_demo(output_dir, *, settings=None, overwrite=False, log=print):
        log("[1/5] rendering ...")
        return types.SimpleNamespace(report_png=output_dir / "report.png")

    monkeypatch.setattr(cmax.demo, "run_demo", run_demo)
    assert cmax_main(["demo", "-o", str(tmp_path)]) == 0
    assert capsys.readouterr().out == f"[1/5] rendering ...\ndemo report: {tmp_path / 'report.png'}\n"
    assert cmax_main(["demo", "-o", str(tmp_path), "--quiet"]) == 0
    assert capsys.readouterr().out == f"demo report: {tmp_path / 'report.png'}\n"


def test_learned_train_takes_quiet_as_the_other_commands_do(monkeypatch):
    """``python -m learned.train`` said ``--no-progress`` where every other command says ``--quiet``: both work."""
    import argparse

    import learned.train

    parsed = []

    def parse_args(self, args=None, namespace=None):
        parsed.append(argparse.ArgumentParser.parse_known_args(self, args, namespace)[0])
        raise SystemExit(0)

    monkeypatch.setattr(learned.train._IntermixedParser, "parse_args", parse_args)
    for option in ("--quiet", "--no-progress"):
        with pytest.raises(SystemExit):
            learned.train.main([option])
    assert [args.no_progress for args in parsed] == [True, True]
