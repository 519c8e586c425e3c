"""The output folder of ``cmax fit``, ``cmax emvs`` and ``cmax depth`` (:mod:`cmax.io.run_folder`): only the files
these commands write count as (and are replaced as) an earlier run's results, one lock per folder for all three,
and ``summary.json`` moved in last so that an interrupted move never looks complete."""
from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from cmax.cli import main as cmax_main
from cmax.io import run_folder
from conftest import one_line_error

#: User files whose names look like results (depth_*.png, window_*.png, depth.*) but are not the commands' own.
USER_FILES = {"notes.txt": b"notes", "depth_groundtruth.png": b"a user's picture", "depth_of_field_study.npz": b"mine",
              "window_seat_photo.png": b"a photo", "depth_0001.npz": b"four digits", "depth.npz.bak": b"backup"}


def _fit(slider_file: Path, out: Path, *extra: str) -> list[str]:
    return ["fit", str(slider_file), "-o", str(out), "--quiet", "--window-ms", "100", "--min-events", "200",
            "--depth-grid", "6,8", *extra]


def _depth(slider_file: Path, out: Path, checkpoint: Path, *extra: str) -> list[str]:
    return ["depth", str(slider_file), "-o", str(out), "--checkpoint", str(checkpoint), "--quiet", *extra]


def _emvs(slider_file: Path, out: Path, *extra: str) -> list[str]:
    return ["emvs", str(slider_file), "-o", str(out), "--planes", "20", *extra]


def _user_files(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name, data in USER_FILES.items():
        (out / name).write_bytes(data)


def _kept(out: Path) -> bool:
    return all((out / name).read_bytes() == data for name, data in USER_FILES.items())


# -- 1. only the commands' own file names are results --------------------------------------------------------------
def test_run_results_match_only_the_names_the_commands_write(tmp_path):
    _user_files(tmp_path)
    assert run_folder.run_results(tmp_path) == []
    for name in ("depth_00000.npz", "depth_00012.png", "depth_123456.npz", "trajectory.txt", "summary.json",
                 "window_00003.npz", "window_00003.png", "twists.csv", "depth.npz", "depth.png", "points.ply"):
        (tmp_path / name).write_bytes(b"result")
    by = {command: [path.name for path in run_folder.run_results(tmp_path, (command,))]
          for command in run_folder.RESULT_NAMES}
    assert by["fit"] == ["depth_00000.npz", "depth_00012.png", "depth_123456.npz", "summary.json", "trajectory.txt"]
    assert by["depth"] == ["summary.json", "twists.csv", "window_00003.npz", "window_00003.png"]
    assert by["emvs"] == ["depth.npz", "depth.png", "points.ply", "summary.json"]


def test_fit_neither_counts_nor_removes_a_users_depth_files(slider_file, tmp_path, capsys):
    """Was: a folder of user files (``depth_groundtruth.png``, ``depth_of_field_study.npz``) refused as "an earlier
    run's results", and ``--overwrite`` deleted them."""
    out = tmp_path / "fitu"
    _user_files(out)
    assert cmax_main(_fit(slider_file, out)) in (0, 1)   # not refused: no earlier run's files
    assert _kept(out) and (out / "summary.json").is_file() and (out / "depth_00000.npz").is_file()
    capsys.readouterr()
    assert cmax_main(_fit(slider_file, out, "--overwrite")) in (0, 1)
    assert _kept(out)


def test_depth_neither_counts_nor_removes_a_users_window_files(slider_file, tiny_checkpoint, tmp_path, capsys):
    """Was: ``window_seat_photo.png`` refused as an earlier run's result, and deleted by ``--overwrite``."""
    out = tmp_path / "dep"
    _user_files(out)
    assert cmax_main(_depth(slider_file, out, tiny_checkpoint)) == 0
    assert _kept(out) and (out / "window_00000.npz").is_file()
    assert cmax_main(_depth(slider_file, out, tiny_checkpoint, "--overwrite", "--window", "0.1")) == 0
    assert _kept(out)
    assert sorted(p.name for p in out.glob("window_0*.npz")) == ["window_00000.npz", "window_00001.npz"]


# -- 3. an interrupted publish never looks complete ----------------------------------------------------------------
def _earlier_and_stage(tmp_path: Path) -> tuple[Path, Path, list[Path]]:
    out = tmp_path / "out"
    out.mkdir()
    for name in ("depth_00000.npz", "depth_00001.npz", "depth_00002.npz"):
        (out / name).write_text("old")
    (out / "summary.json").write_text('{"run": "old"}')
    earlier = sorted(out.iterdir())
    stage = run_folder.new_stage(out, "fit")
    for name in ("depth_00000.npz", "depth_00001.npz"):
        (stage / name).write_text("new")
    (stage / "summary.json").write_text('{"run": "new"}')
    return out, stage, earlier


@pytest.mark.parametrize("moves", [0, 1, 2])
def test_a_publish_killed_part_way_leaves_no_summary(tmp_path, monkeypatch, moves):
    """Was: the new files renamed one by one under the earlier run's summary.json, which was replaced last: a kill
    after the first rename left new and old windows under the old summary, a folder that looked complete."""
    out, stage, earlier = _earlier_and_stage(tmp_path)
    done = []
    real_replace = os.replace

    def replace(source, target):
        if len(done) == moves:
            raise KeyboardInterrupt("killed")      # the process dies between two renames
        done.append(target)
        real_replace(source, target)

    monkeypatch.setattr(run_folder.os, "replace", replace)
    with pytest.raises(KeyboardInterrupt):
        run_folder.publish(stage, out, earlier)
    assert not (out / "summary.json").exists()                # no record of completion: not a complete run
    assert not (out / "depth_00002.npz").exists()             # the earlier run's window the new one does not have
    assert sorted(p.name for p in out.glob("depth_*.npz") if p.read_text() == "new") == \
        sorted(Path(target).name for target in done)


def test_a_whole_publish_moves_the_summary_last_and_removes_the_earlier_files(tmp_path, monkeypatch):
    out, stage, earlier = _earlier_and_stage(tmp_path)
    order = []
    real_replace = os.replace
    monkeypatch.setattr(run_folder.os, "replace", lambda s, t: (order.append(Path(t).name), real_replace(s, t)))
    run_folder.publish(stage, out, earlier)
    assert order == ["depth_00000.npz", "depth_00001.npz", "summary.json"]
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == \
        ["depth_00000.npz", "depth_00001.npz", "summary.json"]
    assert json.loads((out / "summary.json").read_text()) == {"run": "new"}


def test_emvs_writes_a_summary_as_its_record_of_completion(slider_file, tmp_path, capsys):
    """Was: no summary.json, nothing to tell a complete emvs folder from one killed while its files moved in."""
    out = tmp_path / "e"
    assert cmax_main(_emvs(slider_file, out)) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["command"] == "emvs" and summary["file"] == str(slider_file) and summary["n_planes"] == 20
    assert summary["camera"] is None                   # a file of one camera (an MVSEC file's: "left" / "right")
    assert summary["files"] == ["depth.npz", "depth.png", "points.ply", "summary.json"]
    assert sorted(p.name for p in out.iterdir()) == sorted(summary["files"])


def test_emvs_resume_leaves_a_complete_run_and_makes_a_missing_file_again(slider_file, tmp_path, capsys):
    """Was: ``cmax emvs --resume``: ``unrecognized arguments: --resume``, exit 2 (a requeued EMVS job over a long
    recording could only redo everything with --overwrite). Now as its siblings: the same run's complete results
    are left as they are (one line, exit 0); with ``points.ply`` deleted and ``depth.png`` truncated the run is
    made again (a note names them) and the folder ends as the first run left it; another option is refused."""
    import numpy as np

    out = tmp_path / "e"
    assert cmax_main([*_emvs(slider_file, out), "--resume"]) == 0     # a first run may pass --resume too
    stamps = {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in out.iterdir()}
    ply, depth = (out / "points.ply").read_bytes(), dict(np.load(out / "depth.npz"))
    capsys.readouterr()
    assert cmax_main([*_emvs(slider_file, out), "--resume"]) == 0
    assert capsys.readouterr().out.strip().splitlines() == [
        f"the results in {out} are already complete: cmax emvs --resume of the same input files and options has "
        "nothing to do (nothing changed)"]
    assert {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in out.iterdir()} == stamps
    (out / "points.ply").unlink()
    (out / "depth.png").write_bytes((out / "depth.png").read_bytes()[:100])
    assert cmax_main([*_emvs(slider_file, out), "--resume"]) == 0
    captured = capsys.readouterr()
    assert "points.ply is missing" in captured.err and "depth.png has 100 bytes" in captured.err, captured
    assert (out / "points.ply").read_bytes() == ply and (out / "depth.png").stat().st_size > 100
    for key, value in np.load(out / "depth.npz").items():
        np.testing.assert_array_equal(value, depth[key], err_msg=key)
    status, err = one_line_error(lambda: cmax_main([*_emvs(slider_file, out), "--resume", "--planes", "21"]), capsys)
    assert status == 2 and "holds the complete results of another run (planes was 20, now 21)" in err, err


# -- 4. one lock per folder for fit, emvs and depth; another command's results are an earlier run's ------------------
def test_emvs_and_depth_into_a_folder_fit_is_writing_are_refused(slider_file, tiny_checkpoint, tmp_path, capsys,
                                                                 monkeypatch):
    """Was: each command took its own lock (.fit.lock, .emvs.lock, .depth.lock): all three ran into one folder at
    once, exit 0, and fit's summary.json was replaced by depth's."""
    import cmax.cli.fit as fit

    out = tmp_path / "cc"
    others = {}
    real_fit_into = fit._fit_into

    def fit_into(stage, out_, *args, **kwargs):   # while fit holds the folder: the other two commands into it
        for name, argv in (("emvs", _emvs(slider_file, out)), ("depth", _depth(slider_file, out, tiny_checkpoint))):
            others[name] = one_line_error(lambda: cmax_main(argv), capsys)
        return real_fit_into(stage, out_, *args, **kwargs)

    monkeypatch.setattr(fit, "_fit_into", fit_into)
    assert cmax_main(_fit(slider_file, out)) in (0, 1)
    for name, (status, err) in others.items():
        assert status == 2 and "is being written by another writer" in err and ".results.lock" in err, (name, err)
    assert "windows" in json.loads((out / "summary.json").read_text())             # fit's summary, whole
    assert not list(out.glob("window_*")) and not (out / "points.ply").exists()


def test_another_commands_results_are_an_earlier_run(slider_file, tiny_checkpoint, tmp_path, capsys):
    """Was: ``cmax emvs`` into a folder holding ``cmax fit``'s results ran without ``--overwrite`` (it counted only
    depth.npz, depth.png, points.ply), and ``cmax fit`` into an emvs folder likewise."""
    out = tmp_path / "mixed"
    assert cmax_main(_fit(slider_file, out)) in (0, 1)
    _user_files(out)
    capsys.readouterr()
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    for argv in (_emvs(slider_file, out), _depth(slider_file, out, tiny_checkpoint)):
        status, err = one_line_error(lambda: cmax_main(argv), capsys)
        assert status == 2 and "holds the results of an earlier run" in err and "--overwrite" in err, err
        assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert cmax_main(_emvs(slider_file, out, "--overwrite")) == 0   # fit's results replaced, the user's kept
    assert _kept(out) and not list(out.glob("depth_0000*")) and not (out / "trajectory.txt").exists()
    assert json.loads((out / "summary.json").read_text())["command"] == "emvs"
    capsys.readouterr()
    status, err = one_line_error(lambda: cmax_main(_fit(slider_file, out)), capsys)
    assert status == 2 and "depth.npz" in err, err                 # the files named as they are


def test_a_write_error_in_the_stage_names_the_output_folder(tmp_path):
    """A full disk under ``cmax fit -o F`` named the private ``F/.fit.<hex>.partial/depth_00002.npz``; the error
    names ``F/depth_00002.npz`` and says ``F`` is as it was."""
    import errno

    from cmax.io import run_folder
    from cmax.io.atomic import write_error

    out = tmp_path / "F"
    out.mkdir()
    with pytest.raises(OSError) as caught:
        with run_folder.staged_run(out, "fit", lambda folder: [], overwrite=False, what="depth_*.npz") as stage:
            raise write_error(OSError(errno.ENOSPC, "No space left on device"), stage / "depth_00002.npz")
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(out / "depth_00002.npz")
    assert f"{out} is as it was" in str(caught.value) and ".partial" not in str(caught.value)
    assert [p.name for p in out.iterdir()] == []


# -- 5. SIGTERM cleans up as Ctrl-C does ---------------------------------------------------------------------------
@pytest.mark.skipif(not hasattr(__import__("signal"), "SIGKILL"), reason="needs POSIX signals")
def test_sigterm_of_a_fit_leaves_the_folder_as_it_was(slider_file, tmp_path, capsys):
    """Was: ``timeout``/``kill`` of ``cmax fit -o F`` (default SIGTERM) left ``F/.results.lock`` and the private
    ``F/.fit.<hex>.partial`` folder behind, and exited without a word. SIGTERM now runs the clean-up of Ctrl-C: exit
    143 with one line, ``F`` exactly as the earlier complete run left it, no lock file, no stage."""
    import sys

    from conftest import sigterm_once

    out = tmp_path / "F"
    assert cmax_main(_fit(slider_file, out)) == 0
    before = {path.name: path.read_bytes() for path in out.iterdir()}
    assert "summary.json" in before
    status, err = sigterm_once([sys.executable, "-m", "cmax.cli", *_fit(slider_file, out, "--overwrite")], out,
                               ".fit.*.partial", "its stage folder was seen")
    assert status == 143, err
    assert "cmax fit: terminated (SIGTERM)" in err and "Traceback" not in err
    assert {path.name: path.read_bytes() for path in out.iterdir()} == before
