"""A long ``cmax depth`` / ``python -m learned.predict`` keeps each finished block of windows
(``-o/.depth.windows``) and ``--resume`` continues a killed run, in the same blocks, only after checking that it is
the same run: the resumed results equal an uninterrupted run's bit for bit; a mismatch is refused."""
from __future__ import annotations

import os
import random
import subprocess
import sys

import numpy as np
import pytest

import learned.predict as predict
from conftest import counted_calls, sigkill_after
from cmax.events import Events
from cmax.io import write_h5
from learned.kept_windows import KEPT_FOLDER


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """0.6 s of random events of a 64x48 sensor with gt/K-free intrinsics given by --K: 12 windows of 50 ms."""
    rng = np.random.default_rng(7)
    n = 24_000
    events = Events(rng.integers(0, 64, n), rng.integers(0, 48, n), np.sort(rng.integers(0, 600_000, n)),
                    rng.integers(0, 2, n), 64, 48)
    return write_h5(tmp_path_factory.mktemp("depth_resume") / "ev.h5", events)


def argv(recording, out, checkpoint, *extra):
    return [str(recording), "-o", str(out), "--checkpoint", str(checkpoint), "--K", "60,60,32,24", "--quiet",
            "--batch", "2", *extra]


def outputs(out) -> dict:
    """Every result file's bytes but summary.json's and the pictures' (their bytes hold no extra information)."""
    return {p.name: (dict(np.load(p)) if p.suffix == ".npz" else p.read_bytes())
            for p in sorted(out.iterdir()) if p.suffix in (".npz", ".csv")}


def assert_same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for name in a:
        if name.endswith(".npz"):
            for key in a[name]:
                np.testing.assert_array_equal(a[name][key], b[name][key], err_msg=f"{name}:{key}")
        else:
            assert a[name] == b[name], name


def test_an_interrupted_depth_run_resumes_to_the_results_of_an_uninterrupted_one(recording, tiny_checkpoint,
                                                                                  tmp_path, monkeypatch, capsys):
    """Interrupted in its third forward pass, a run keeps the two blocks it finished (was: nothing: the private
    stage is removed by the next run); without --resume the folder is refused in one line; another option is
    refused naming it; ``--resume`` predicts only the other blocks and every result equals an uninterrupted
    run's, bit for bit; the kept blocks are removed once the results are in."""
    whole = tmp_path / "whole"
    assert predict.main(argv(recording, whole, tiny_checkpoint)) == 0
    expected = outputs(whole)
    assert len([name for name in expected if name.endswith(".npz")]) == 12

    out = tmp_path / "o"
    counted_calls(monkeypatch, predict, "forward", interrupt_at=3)
    capsys.readouterr()
    assert predict.main(argv(recording, out, tiny_checkpoint)) == 130
    kept = out / KEPT_FOLDER
    assert capsys.readouterr().err.strip() == (f"python -m learned.predict: interrupted: 4 finished window(s) kept in "
                                               f"{kept}: the same command with --resume continues the run")
    assert sorted(p.name for p in kept.glob("block_*.json")) == ["block_0.json", "block_2.json"]
    assert not (out / "summary.json").exists()
    capsys.readouterr()
    assert predict.main(argv(recording, out, tiny_checkpoint)) == 2
    err = capsys.readouterr().err
    assert "4 finished window(s) of an interrupted cmax depth" in err and len(err.strip().splitlines()) == 1
    assert predict.main(argv(recording, out, tiny_checkpoint, "--resume", "--window", "0.04")) == 2
    err = capsys.readouterr().err
    *notes, error = err.strip().splitlines()   # the checkpoint's note on the other window length, then the error
    assert "window_us was 50000, now 40000" in error and all(": note: " in line for line in notes)

    calls = counted_calls(monkeypatch, predict, "forward")
    assert predict.main(argv(recording, out, tiny_checkpoint, "--resume")) == 0
    assert len(calls) == 4                       # blocks 4-5, 6-7, 8-9, 10-11
    assert "resumed: 4 of 12 windows taken" in capsys.readouterr().err
    assert_same(outputs(out), expected)
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []


def test_a_changed_window_file_is_predicted_again(recording, tiny_checkpoint, tmp_path, monkeypatch, capsys):
    """A kept window file changed after its block was recorded fails its SHA-256: that block is predicted again,
    and the results equal an uninterrupted run's."""
    whole = tmp_path / "whole"
    assert predict.main(argv(recording, whole, tiny_checkpoint)) == 0
    out = tmp_path / "o"
    counted_calls(monkeypatch, predict, "forward", interrupt_at=2)
    assert predict.main(argv(recording, out, tiny_checkpoint)) == 130
    damaged = out / KEPT_FOLDER / "window_00001.npz"
    data = bytearray(damaged.read_bytes())
    data[-40] ^= 0xFF
    damaged.write_bytes(bytes(data))
    counted_calls(monkeypatch, predict, "forward")       # the real forward pass again
    capsys.readouterr()
    assert predict.main(argv(recording, out, tiny_checkpoint, "--resume")) == 0
    assert "1 block(s) not verified, predicted again" in capsys.readouterr().err
    assert_same(outputs(out), outputs(whole))


def test_a_depth_run_killed_at_a_random_block_resumes_to_the_uninterrupted_results(recording, tiny_checkpoint,
                                                                                    tmp_path):
    """SIGKILL (no clean-up) once a random number of blocks are kept; ``--resume`` ends with the uninterrupted
    run's results, bit for bit."""
    command = [sys.executable, "-m", "learned.predict"]
    whole = tmp_path / "whole"
    subprocess.run([*command, *argv(recording, whole, tiny_checkpoint)], check=True, capture_output=True)
    kill_after = random.Random().randint(1, 4)
    out = tmp_path / "o"
    kept = out / KEPT_FOLDER
    if not sigkill_after([*command, *argv(recording, out, tiny_checkpoint)], kept, "block_*.json", kill_after):
        pytest.skip("the run ended before it could be killed (a very fast machine)")
    assert not (out / "summary.json").exists()
    resumed = subprocess.run([*command, *argv(recording, out, tiny_checkpoint, "--resume")], capture_output=True,
                             text=True)
    assert resumed.returncode == 0, resumed.stderr
    assert "resumed: " in resumed.stderr
    assert_same(outputs(out), outputs(whole))
    assert not kept.exists() and not any(p.name.endswith(".lock") for p in out.iterdir())
    assert os.listdir(out)


def test_resume_refuses_an_event_file_replaced_by_one_of_the_same_size_and_mtime(tiny_checkpoint, tmp_path,
                                                                                  monkeypatch, capsys):
    """The event file re-written with other events of the same count (the same size, uncompressed) and its
    modification time set back after the run was killed: --resume took the kept blocks of the old file (was);
    the run's record holds the file's SHA-256: refused in one line naming it, exit 2, the blocks kept."""
    def noise(seed: int) -> Events:
        rng = np.random.default_rng(seed)
        return Events(rng.integers(0, 64, 6000), rng.integers(0, 48, 6000), np.sort(rng.integers(0, 300_000, 6000)),
                      rng.integers(0, 2, 6000), 64, 48)

    path = write_h5(tmp_path / "ev.h5", noise(1), compression="none")
    out = tmp_path / "o"
    counted_calls(monkeypatch, predict, "forward", interrupt_at=2)
    assert predict.main(argv(path, out, tiny_checkpoint)) == 130
    monkeypatch.undo()
    before = path.stat()
    write_h5(path, noise(2), compression="none", overwrite=True)
    os.utime(path, ns=(before.st_atime_ns, before.st_mtime_ns))
    assert (path.stat().st_size, path.stat().st_mtime_ns) == (before.st_size, before.st_mtime_ns)
    capsys.readouterr()
    assert predict.main(argv(path, out, tiny_checkpoint, "--resume")) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "ev.h5 holds other bytes than it did" in err and "--overwrite" in err
    assert sorted(p.name for p in (out / KEPT_FOLDER).glob("block_*.json")) == ["block_0.json"]


def test_a_moved_event_file_and_folder_resume_their_kept_windows(recording, tiny_checkpoint, tmp_path, monkeypatch,
                                                                  capsys):
    """The event file and the output folder moved (the same bytes and times): ``--resume`` takes the kept blocks
    (was: each block's record named the old path's run, so every window was predicted again without a word)."""
    path = tmp_path / "ev.h5"
    path.write_bytes(recording.read_bytes())
    whole = tmp_path / "whole"
    assert predict.main(argv(path, whole, tiny_checkpoint)) == 0
    out = tmp_path / "o"
    counted_calls(monkeypatch, predict, "forward", interrupt_at=3)
    assert predict.main(argv(path, out, tiny_checkpoint)) == 130
    moved = tmp_path / "moved"
    moved.mkdir()
    os.rename(path, moved / "ev.h5")
    os.rename(out, moved / "o")
    calls = counted_calls(monkeypatch, predict, "forward")
    capsys.readouterr()
    assert predict.main(argv(moved / "ev.h5", moved / "o", tiny_checkpoint, "--resume")) == 0
    assert len(calls) == 4 and "resumed: 4 of 12 windows taken" in capsys.readouterr().err
    assert_same(outputs(moved / "o"), outputs(whole))


def test_resume_refuses_a_calibration_file_changed_under_the_same_path(recording, tiny_checkpoint, tmp_path,
                                                                      monkeypatch, capsys):
    """The kept blocks of learned.predict / cmax depth --calib record the calibration file by the SHA-256 of its bytes
    (cmax.io.window_store.file_signatures), not its path: a cam_to_cam.yaml edited after the run was killed
    (camRect0's cx moved 0.3 px, the file's size and modification time kept) is refused in one line naming it, the
    blocks kept (coverage of existing behaviour)."""
    from test_learned_dsec_raw import K_RECT, _cam_to_cam

    yaml = tmp_path / "cam_to_cam.yaml"
    yaml.write_text(_cam_to_cam())
    out = tmp_path / "o"
    run = [str(recording), "-o", str(out), "--checkpoint", str(tiny_checkpoint), "--calib", str(yaml), "--quiet",
           "--batch", "2"]
    counted_calls(monkeypatch, predict, "forward", interrupt_at=2)
    assert predict.main(run) == 130
    monkeypatch.undo()
    before = yaml.stat()
    yaml.write_text(_cam_to_cam().replace(f"{K_RECT[0, 2]}, {K_RECT[1, 2]}", f"31.9, {K_RECT[1, 2]}"))   # as long
    os.utime(yaml, ns=(before.st_atime_ns, before.st_mtime_ns))     # its size and modification time as they were
    capsys.readouterr()
    assert predict.main([*run, "--resume"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "cam_to_cam.yaml holds other bytes than it did" in err and "--overwrite" in err, err
    assert sorted(p.name for p in (out / KEPT_FOLDER).glob("block_*.json")) == ["block_0.json"]
    yaml.write_text(_cam_to_cam())                  # restored (the same bytes and modification time): resumes
    os.utime(yaml, ns=(before.st_atime_ns, before.st_mtime_ns))
    assert predict.main([*run, "--resume"]) == 0


def test_a_fresh_run_predicts_while_its_inputs_are_hashed(recording, tiny_checkpoint, tmp_path, monkeypatch):
    """A fresh ``cmax depth`` hashes its inputs (cmax.io.window_store.PendingSignatures) while the network runs:
    the event file's hash is held back until the first forward pass has begun, and the run ends (was: the inputs
    were hashed whole before anything else: this hash waited 60 s for a pass that never came). The kept blocks'
    run.json records the SHA-256 of the file's bytes (hashlib of its bytes); no hashing thread outlives the run."""
    import hashlib
    import json

    from conftest import hash_held_back, hashing_threads

    order = hash_held_back(monkeypatch, recording.name, predict, "forward", interrupt_at=3)
    out = tmp_path / "o"
    assert predict.main(argv(recording, out, tiny_checkpoint)) == 130     # two blocks kept
    assert order[:2] == ["forward", "hashed"], order
    record = json.loads((out / KEPT_FOLDER / "run.json").read_text())
    assert record["file"]["sha256"] == hashlib.sha256(recording.read_bytes()).hexdigest()
    assert not hashing_threads()


def test_resume_of_a_finished_run_says_it_is_complete_and_touches_nothing(tiny_checkpoint, tmp_path, monkeypatch,
                                                                         capsys):
    """A requeued job that always passes --resume, after its run had finished: exit 2, "holds the results of an
    earlier run" (was), while learned.train --resume of a finished run exits 0. summary.json now records the run
    (input files' signatures, options, code): the same run exits 0 with one line and rewrites nothing, no forward
    pass; other bytes under the same size and mtime, another option, or a summary.json that records no run (an
    earlier version) are refused in one line, the results kept."""
    import json

    rng = np.random.default_rng(3)
    events = Events(rng.integers(0, 64, 6000), rng.integers(0, 48, 6000), np.sort(rng.integers(0, 300_000, 6000)),
                    rng.integers(0, 2, 6000), 64, 48)
    path = write_h5(tmp_path / "ev.h5", events, compression="none")
    out = tmp_path / "o"
    assert predict.main(argv(path, out, tiny_checkpoint, "--resume")) == 0   # a first run may pass --resume too
    files = sorted(p for p in out.iterdir() if p.is_file())
    assert len([p for p in files if p.suffix == ".npz"]) == 6

    def stamps() -> dict:
        return {p.name: (p.stat().st_mtime_ns, p.stat().st_ino, p.read_bytes()) for p in sorted(out.iterdir())}

    before = stamps()
    capsys.readouterr()
    calls = counted_calls(monkeypatch, predict, "forward")
    assert predict.main(argv(path, out, tiny_checkpoint, "--resume")) == 0
    captured = capsys.readouterr()
    assert captured.out.strip().splitlines() == [f"the results in {out} are already complete: cmax depth --resume of "
                                                 "the same input files and options has nothing to do (nothing "
                                                 "changed)"], captured
    assert calls == [] and stamps() == before
    # another option: refused, naming it
    assert predict.main(argv(path, out, tiny_checkpoint, "--resume", "--depth-range", "1,5")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds the complete results of another run" in err[0], err
    assert "depth_range was None, now [1.0, 5.0]" in err[0] and stamps() == before
    # other events of the same count, with the old size and modification time
    stat = path.stat()
    rng = np.random.default_rng(4)
    write_h5(path, Events(rng.integers(0, 64, 6000), rng.integers(0, 48, 6000),
                          np.sort(rng.integers(0, 300_000, 6000)), rng.integers(0, 2, 6000), 64, 48),
             compression="none", overwrite=True)
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert (path.stat().st_size, path.stat().st_mtime_ns) == (stat.st_size, stat.st_mtime_ns)
    assert predict.main(argv(path, out, tiny_checkpoint, "--resume")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "ev.h5 holds other bytes than it did" in err[0] and stamps() == before, err
    assert calls == []
    # results of an earlier version: no run recorded, so not verifiable
    summary = json.loads((out / "summary.json").read_text())
    del summary["run"]
    (out / "summary.json").write_text(json.dumps(summary))
    before = stamps()
    assert predict.main(argv(path, out, tiny_checkpoint, "--resume")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "records no run identity" in err[0] and "cannot be checked" in err[0], err
    assert stamps() == before and calls == []


def test_resume_of_a_finished_run_with_a_file_deleted_or_changed_predicts_again(recording, tiny_checkpoint, tmp_path,
                                                                               monkeypatch, capsys):
    """Was: a finished run whose ``window_00003.npz`` was deleted and ``twists.csv`` changed in place was "already
    complete" for ``--resume`` (only summary.json was looked at). Its recorded sizes and SHA-256 now tell: the run
    is predicted again, and the folder ends as the first run left it."""
    import json

    out = tmp_path / "o"
    assert predict.main(argv(recording, out, tiny_checkpoint)) == 0
    expected = outputs(out)
    (out / "window_00003.npz").unlink()
    twists = (out / "twists.csv").read_bytes()
    (out / "twists.csv").write_bytes(twists[:-2] + (b"0" if twists[-2:-1] != b"0" else b"1") + twists[-1:])
    capsys.readouterr()
    calls = counted_calls(monkeypatch, predict, "forward")
    assert predict.main(argv(recording, out, tiny_checkpoint, "--resume")) == 0
    captured = capsys.readouterr()
    assert "already complete" not in captured.out and calls, captured
    assert "window_00003.npz is missing" in captured.err and "twists.csv holds other bytes" in captured.err
    assert_same(outputs(out), expected)
    recorded = json.loads((out / "summary.json").read_text())["outputs"]
    assert sorted(recorded) == sorted(p.name for p in out.iterdir() if p.name != "summary.json")


def test_resume_of_a_finished_run_with_one_window_file_damaged_predicts_only_its_block(recording, tiny_checkpoint,
                                                                                      tmp_path, monkeypatch, capsys):
    """Was: a finished run (12 windows, blocks of 2) whose ``window_00003.npz`` was deleted, or changed in one
    byte, was predicted again in full on ``--resume``: 6 forward passes for one lost file (hours on a long
    recording). The windows whose files summary.json's SHA-256 still verify are now taken as they are: one
    forward pass (the block of windows 2-3), and the folder ends as the first run left it."""
    out = tmp_path / "o"
    assert predict.main(argv(recording, out, tiny_checkpoint)) == 0
    expected = outputs(out)
    calls = counted_calls(monkeypatch, predict, "forward")
    for damage in ("delete", "change"):
        target = out / "window_00003.npz"
        if damage == "delete":
            target.unlink()
        else:
            data = bytearray(target.read_bytes())
            data[len(data) // 2] ^= 1
            target.write_bytes(bytes(data))
        capsys.readouterr()
        calls.clear()
        assert predict.main(argv(recording, out, tiny_checkpoint, "--resume")) == 0
        err = capsys.readouterr().err
        assert len(calls) == 1, (damage, len(calls), err)                 # the block of windows 2 and 3 alone
        assert "resumed: 10 of 12 windows taken from the complete results" in err, err   # not 2 and 3
        assert_same(outputs(out), expected)
        assert not (out / KEPT_FOLDER).exists()
    calls.clear()
    assert predict.main(argv(recording, out, tiny_checkpoint, "--resume")) == 0 and calls == []   # complete now


def test_a_run_killed_while_drawing_its_pictures_draws_only_the_others_on_resume(recording, tiny_checkpoint, tmp_path,
                                                                                monkeypatch, capsys):
    """Was: the pictures were drawn into the private stage only after every window, and not kept: a run killed
    while drawing them (0.1 s each at 640x480: minutes on a long recording) drew every one of them again on
    ``--resume``. Each block's pictures are now kept with their record as they are drawn: stopped at the 4th
    picture (batch 2: the first block's two kept), the resume draws 13 of the 15 and every picture equals an
    uninterrupted run's."""
    whole = tmp_path / "whole"
    assert predict.main(argv(recording, whole, tiny_checkpoint, "--window", "0.04")) == 0
    pictures = {p.name: p.read_bytes() for p in whole.glob("window_*.png")}
    assert len(pictures) == 15
    out = tmp_path / "o"
    counted_calls(monkeypatch, predict, "draw_window", interrupt_at=4)
    assert predict.main(argv(recording, out, tiny_checkpoint, "--window", "0.04")) == 130
    calls = counted_calls(monkeypatch, predict, "draw_window")
    assert predict.main(argv(recording, out, tiny_checkpoint, "--window", "0.04", "--resume")) == 0
    assert len(calls) == 13
    assert {p.name: p.read_bytes() for p in out.glob("window_*.png")} == pictures
    assert_same(outputs(out), outputs(whole))
    assert not (out / KEPT_FOLDER).exists()
