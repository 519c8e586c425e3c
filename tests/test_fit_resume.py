"""A long ``cmax fit`` keeps each window it finished (``-o/.fit.windows``) and ``--resume`` continues a killed run
only after checking that it is the same run: the resumed results equal an uninterrupted run's; a mismatch is
refused; a damaged or planted window file is fitted again, never executed; kept results hold no (H, W) maps."""
from __future__ import annotations

import json
import os
import pickle
import random
import subprocess
import sys
import time

import numpy as np
import pytest

import cmax.fitting.sequence as sequence_module
from conftest import counted_calls, hash_held_back, hashing_threads, sigkill_after
from cmax.cli import main
from cmax.events import Events
from cmax.io import write_h5
from cmax.io.window_store import WINDOWS_FOLDER, WindowStore, _sealed

K_OPTION = "60,60,32,24"


def noise_events(n: int, span_us: int, seed: int) -> Events:
    """``n`` events at random pixels of a 64x48 sensor and random times in ``[0, span_us)`` µs."""
    rng = np.random.default_rng(seed)
    return Events(rng.integers(0, 64, n), rng.integers(0, 48, n), np.sort(rng.integers(0, span_us, n)),
                  rng.integers(0, 2, n), 64, 48)


def results_of(out) -> dict:
    """What a run wrote, less the wall-clock seconds and the notes: the trajectory, the windows of the summary,
    every depth file's arrays."""
    summary = json.loads((out / "summary.json").read_text())
    windows = [{key: value for key, value in w.items() if key != "seconds"} for w in summary["windows"]]
    depths = {path.name: {key: value for key, value in np.load(path).items()} for path in sorted(out.glob("*.npz"))}
    return {"trajectory": (out / "trajectory.txt").read_text(), "windows": windows, "depths": depths,
            "warnings": summary["warnings"]}


def assert_same(a: dict, b: dict) -> None:
    assert a["trajectory"] == b["trajectory"] and a["windows"] == b["windows"] and a["warnings"] == b["warnings"]
    assert a["depths"].keys() == b["depths"].keys()
    for name in a["depths"]:
        for key in a["depths"][name]:
            np.testing.assert_array_equal(a["depths"][name][key], b["depths"][name][key], err_msg=f"{name}:{key}")


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    folder = tmp_path_factory.mktemp("resume")
    return write_h5(folder / "ev.h5", noise_events(3000, 50_000, seed=3))


def se3_argv(path, out):
    return ["fit", str(path), "--K", K_OPTION, "-o", str(out), "--quiet", "--min-events", "300", "--depth-grid",
            "6,8", "--window-ms", "12.5"]


def test_an_interrupted_se3_run_resumes_to_the_results_of_an_uninterrupted_one(recording, tmp_path, monkeypatch,
                                                                                capsys):
    """Interrupted (Ctrl-C) in its third window, a run keeps the two it finished (was: nothing); a rerun without
    --resume is refused in one line, ``--resume`` fits only the two others, and every result equals an
    uninterrupted run's; the kept windows are removed once the results are in."""
    whole = tmp_path / "whole"
    status = main(se3_argv(recording, whole))     # 1 when every window failed: noise holds no motion
    expected = results_of(whole)
    assert len(expected["depths"]) == 4 and not (whole / WINDOWS_FOLDER).exists()

    out = tmp_path / "o"
    counted_calls(monkeypatch, sequence_module, "fit", interrupt_at=3)
    capsys.readouterr()
    assert main(se3_argv(recording, out)) == 130
    err = capsys.readouterr().err
    assert err.strip() == (f"cmax fit: interrupted: 2 finished window(s) kept in {out / WINDOWS_FOLDER}: the same "
                           "command with --resume continues the run")
    assert not (out / "summary.json").exists()
    assert sorted(p.name for p in (out / WINDOWS_FOLDER).glob("window_*")) == ["window_00000.pickle",
                                                                               "window_00001.pickle"]
    capsys.readouterr()
    assert main(se3_argv(recording, out)) == 2
    err = capsys.readouterr().err
    assert "2 finished window(s) of an interrupted cmax fit" in err and "--resume" in err
    assert len(err.strip().splitlines()) == 1

    calls = counted_calls(monkeypatch, sequence_module, "fit")
    assert main([*se3_argv(recording, out), "--resume"]) == status
    assert len(calls) == 2                                   # windows 2 and 3 (no re-fit: noise is never resolved)
    assert "resumed: 2 of 4 fitted windows taken" in capsys.readouterr().err
    assert_same(results_of(out), expected)
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []


def test_resume_refuses_another_run_and_a_changed_file(recording, tmp_path, capsys):
    """``--resume`` of a folder whose windows come from other options, or from an event file changed since, is
    refused in one line naming what differs, and the kept windows stay; with --overwrite they are dropped."""
    path = tmp_path / "ev.h5"
    path.write_bytes(recording.read_bytes())
    out = tmp_path / "o"
    out.mkdir()
    store = WindowStore(out, {"file": None}, resume=False, overwrite=False)
    store.folder.mkdir()
    (store.folder / "window_00000.pickle").write_bytes(b"left by a killed run")
    argv = se3_argv(path, out)
    from cmax.cli.fit import run_record
    from cmax.cli import build_parser

    (store.folder / "run.json").write_text(json.dumps(run_record(build_parser().parse_args([*argv, "--resume"]))))
    capsys.readouterr()
    argv_other = [*argv[:-1], "25", "--resume"]
    assert main(argv_other) == 2
    err = capsys.readouterr().err
    assert "window_ms was 12.5, now 25.0" in err and len(err.strip().splitlines()) == 1
    os.utime(path, ns=(time.time_ns(), time.time_ns() + 10**9))
    assert main([*argv, "--resume"]) == 2
    err = capsys.readouterr().err
    assert "ev.h5 was modified since" in err and len(err.strip().splitlines()) == 1
    record = json.loads((store.folder / "run.json").read_text())
    (store.folder / "run.json").write_text(json.dumps({**record, "code": "0" * 64}))   # windows of other code
    assert main([*argv, "--resume"]) == 2
    assert "the code of cmax (or learned) changed" in capsys.readouterr().err
    assert (store.folder / "window_00000.pickle").exists()
    main([*argv, "--overwrite"])
    assert not (out / WINDOWS_FOLDER).exists() and (out / "summary.json").is_file()


class _Planted:
    """A pickle that would run a command when loaded by a plain unpickler."""

    def __init__(self, marker) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def test_a_damaged_or_planted_window_file_is_fitted_again_never_run(recording, tmp_path, capsys):
    """A window file that is not a window of this run (garbage, or a pickle that would run a command) is fitted
    again, and nothing in it runs; the results equal an uninterrupted run's."""
    whole = tmp_path / "whole"
    status = main(se3_argv(recording, whole))
    out = tmp_path / "o"
    from cmax.cli import build_parser
    from cmax.cli.fit import run_record

    record = run_record(build_parser().parse_args([*se3_argv(recording, out), "--resume"]))
    out.mkdir()
    store = WindowStore(out, record, resume=False, overwrite=False)
    store.folder.mkdir()
    (store.folder / "run.json").write_text(json.dumps(record))
    marker = tmp_path / "ran"
    planted = pickle.dumps({"run": store.digest, "start_us": 0, "result": _Planted(marker), "caught": ()})
    (store.folder / "window_00000.pickle").write_bytes(_sealed(planted))    # its SHA-256 right: the unpickler stops it
    (store.folder / "window_00001.pickle").write_bytes(b"\x80\x05garbage")
    capsys.readouterr()
    assert main([*se3_argv(recording, out), "--resume"]) == status
    assert not marker.exists()
    assert "2 unreadable window file(s) fitted again" in capsys.readouterr().err
    assert_same(results_of(out), results_of(whole))


def test_kept_results_hold_no_maps_and_give_them_back(recording, tmp_path):
    """With a store, the results fit_sequence keeps in memory hold none of the (H, W) maps (was: five per window,
    about 5 MB at 640x480, for the whole run); :meth:`WindowStore.maps` gives back the same maps as a run
    without a store."""
    from cmax.fitting import fit_sequence
    from cmax.io import read

    events = read(recording)
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    options = dict(window_us=12_500, min_events=300, depth_grid=(6, 8))
    alone = fit_sequence(events, K, "se3", **options)
    store = WindowStore(tmp_path, {"test": 1}, resume=False, overwrite=False)
    kept = fit_sequence(events, K, "se3", store=store, **options)
    assert len(kept.results) == len(alone.results) == 4
    for i, (a, b) in enumerate(zip(alone.results, kept.results)):
        assert b.depth is None and b.mask is None and b.iwe_before is None and b.iwe_after is None
        full = store.maps(i, b)
        for name in ("depth", "mask", "depth_spread", "iwe_before", "iwe_after"):
            np.testing.assert_array_equal(getattr(full, name), getattr(a, name))
        np.testing.assert_array_equal(b.v, a.v)


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_a_run_killed_at_a_random_window_resumes_to_the_uninterrupted_results(tmp_path, jobs):
    """SIGKILL (no clean-up at all) once a random number of windows are kept: the folder holds no summary.json,
    and ``--resume`` ends with the uninterrupted run's results, its warnings too (with ``--jobs 2`` as well)."""
    path = write_h5(tmp_path / "ev.h5", noise_events(6000, 60_000, seed=5))
    argv = [sys.executable, "-m", "cmax.cli", "fit", str(path), "--K", K_OPTION, "--quiet", "--model", "flow",
            "--window-ms", "7.5", "--min-events", "300", "--jobs", jobs]
    whole = tmp_path / "whole"
    status = subprocess.run([*argv, "-o", str(whole)], capture_output=True).returncode
    assert status in (0, 1)
    n = len(json.loads((whole / "summary.json").read_text())["windows"])
    assert n == 8
    kill_after = random.Random().randint(1, n - 2)
    out = tmp_path / "o"
    kept = out / WINDOWS_FOLDER
    if not sigkill_after([*argv, "-o", str(out)], kept, "window_*.pickle", kill_after):
        pytest.skip("the run ended before it could be killed (a very fast machine)")
    assert not (out / "summary.json").exists()
    done = len(list(kept.glob("window_*.pickle")))
    assert kill_after <= done < n, (kill_after, done)
    resumed = subprocess.run([*argv, "-o", str(out), "--resume"], capture_output=True, text=True)
    assert resumed.returncode == status, resumed.stderr
    assert f"resumed: {done} of {n} fitted windows" in resumed.stderr
    assert_same(results_of(out), results_of(whole))
    assert not kept.exists()


def test_a_full_disk_at_the_first_window_is_one_line_and_leaves_no_kept_folder(tmp_path, monkeypatch, capsys):
    """A window that cannot be written (full disk) stops the run with one line naming the file, exit 2; a kept
    folder without any window (only run.json) is not left behind to be taken for an interrupted run."""
    import errno

    import cmax.io.window_store as window_store

    def full(path, data):
        raise OSError(errno.ENOSPC, f"No space left on device while writing: {path}")

    monkeypatch.setattr(window_store, "write_bytes_atomic", full)
    path = write_h5(tmp_path / "ev.h5", noise_events(3000, 30_000, seed=5))
    out = tmp_path / "o"
    capsys.readouterr()
    assert main(["fit", str(path), "--K", K_OPTION, "-o", str(out), "--quiet", "--model", "flow", "--window-ms",
                 "7.5", "--min-events", "300"]) == 2
    err = capsys.readouterr().err
    assert "No space left on device" in err and "window_00000.pickle" in err and len(err.strip().splitlines()) == 1
    assert not (out / WINDOWS_FOLDER).exists()


def test_an_interrupted_overwrite_resumes_over_the_earlier_complete_run(tmp_path, monkeypatch, capsys):
    """``--overwrite`` of a folder with a complete run, interrupted: the earlier results stay as they were, beside
    the kept windows; ``--resume`` alone is refused (the earlier results), ``--resume --overwrite`` continues the
    interrupted run (fitting only the windows it had not finished) and replaces them."""
    path = write_h5(tmp_path / "ev.h5", noise_events(4000, 40_000, seed=9))
    out = tmp_path / "o"
    argv = ["fit", str(path), "--K", K_OPTION, "-o", str(out), "--quiet", "--model", "flow", "--min-events", "300"]
    status = main([*argv, "--window-ms", "10"])
    earlier = (out / "summary.json").read_bytes()
    counted_calls(monkeypatch, sequence_module, "fit", interrupt_at=3)
    assert main([*argv, "--window-ms", "5", "--overwrite"]) == 130
    assert (out / "summary.json").read_bytes() == earlier and len(list((out / WINDOWS_FOLDER).glob("*.pickle"))) == 2
    capsys.readouterr()
    assert main([*argv, "--window-ms", "5", "--resume"]) == 2    # the complete run's options are another run's
    err = capsys.readouterr().err
    assert "holds the complete results of another run" in err and "window_ms was 10.0, now 5.0" in err, err
    calls = counted_calls(monkeypatch, sequence_module, "fit")
    assert main([*argv, "--window-ms", "5", "--resume", "--overwrite"]) in (0, 1)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["window_ms"] == 5 and len(summary["windows"]) == 8 and len(calls) == 6
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []
    assert status in (0, 1)


def test_resume_refuses_an_event_file_replaced_by_one_of_the_same_size_and_mtime(tmp_path, monkeypatch, capsys):
    """Interrupted after two windows, then the event file re-written (``write_h5`` of another scene with as many
    events: the same size) and its modification time set back (``cp -p``, ``rsync -t``, ``touch -r``): the file's
    size and mtime passed the check, and the run mixed the old file's two windows with the new file's others, exit
    as if nothing happened (was). The signature holds the SHA-256 of the file's bytes: refused in one line naming
    the file, the windows kept; ``--overwrite`` starts over and gives the new file's uninterrupted results."""
    path = write_h5(tmp_path / "ev.h5", noise_events(3000, 50_000, seed=3), compression="none")
    out = tmp_path / "o"
    counted_calls(monkeypatch, sequence_module, "fit", interrupt_at=3)
    assert main(se3_argv(path, out)) == 130
    monkeypatch.undo()
    before = path.stat()
    write_h5(path, noise_events(3000, 50_000, seed=4), compression="none", overwrite=True)
    os.utime(path, ns=(before.st_atime_ns, before.st_mtime_ns))
    assert (path.stat().st_size, path.stat().st_mtime_ns) == (before.st_size, before.st_mtime_ns)
    capsys.readouterr()
    assert main([*se3_argv(path, out), "--resume"]) == 2
    err = capsys.readouterr().err
    assert "ev.h5 holds other bytes than it did" in err and "--overwrite" in err and len(err.strip().splitlines()) == 1
    assert len(list((out / WINDOWS_FOLDER).glob("window_*.pickle"))) == 2
    main([*se3_argv(path, tmp_path / "whole")])
    main([*se3_argv(path, out), "--overwrite"])
    assert_same(results_of(out), results_of(tmp_path / "whole"))


def test_resume_refuses_windows_kept_without_a_sha256_of_the_file(recording, tmp_path, capsys):
    """A ``run.json`` written before signatures held a SHA-256 (size and mtime only) cannot say whether the file
    changed since: refused, naming the file (it would be refused for its other code as well, named too), not
    upgraded on trust; ``--overwrite`` starts over."""
    from cmax.cli import build_parser
    from cmax.cli.fit import run_record

    out = tmp_path / "o"
    (out / WINDOWS_FOLDER).mkdir(parents=True)
    (out / WINDOWS_FOLDER / "window_00000.pickle").write_bytes(b"left by a killed run")
    argv = se3_argv(recording, out)
    record = run_record(build_parser().parse_args([*argv, "--resume"]))
    old_signature = {key: value for key, value in record["file"].items() if key != "sha256"}
    (out / WINDOWS_FOLDER / "run.json").write_text(json.dumps({**record, "file": old_signature}))
    capsys.readouterr()
    assert main([*argv, "--resume"]) == 2
    err = capsys.readouterr().err
    assert "ev.h5: the kept run recorded no SHA-256 of its bytes" in err and len(err.strip().splitlines()) == 1
    (out / WINDOWS_FOLDER / "run.json").write_text(json.dumps({**record, "file": old_signature, "code": "0" * 64}))
    assert main([*argv, "--resume"]) == 2
    err = capsys.readouterr().err
    assert "recorded no SHA-256" in err and "the code of cmax (or learned) changed" in err
    assert main([*argv, "--overwrite"]) in (0, 1) and not (out / WINDOWS_FOLDER).exists()


def test_a_window_file_changed_in_its_numbers_is_fitted_again(recording, tmp_path, monkeypatch, capsys):
    """One byte of a kept window's depth map changed on disk (a bad sector, a stray write): the file still
    unpickled to a window of this run, and its wrong depths went into the results (was). Each window file now
    holds the SHA-256 of its pickle, checked before it is read: the window is fitted again and the results equal an
    uninterrupted run's."""
    import io

    from cmax.io.window_store import _ResultUnpickler

    status = main(se3_argv(recording, tmp_path / "whole"))
    out = tmp_path / "o"
    counted_calls(monkeypatch, sequence_module, "fit", interrupt_at=3)
    assert main(se3_argv(recording, out)) == 130
    monkeypatch.undo()
    path = out / WINDOWS_FOLDER / "window_00000.pickle"
    data = bytearray(path.read_bytes())
    depth = _ResultUnpickler(io.BytesIO(bytes(data[data.index(b"\x80"):]))).load()["result"].depth
    where = bytes(data).find(depth.tobytes())
    assert where > 0 and np.isfinite(depth).all()
    data[where + depth.nbytes // 2 + 2] ^= 0x40             # one depth, a bit of its exponent
    path.write_bytes(bytes(data))
    capsys.readouterr()
    assert main([*se3_argv(recording, out), "--resume"]) == status
    assert "1 unreadable window file(s) fitted again" in capsys.readouterr().err
    assert_same(results_of(out), results_of(tmp_path / "whole"))


def test_resume_continues_a_moved_event_file_and_folder(recording, tmp_path, monkeypatch, capsys):
    """The event file and the output folder moved (the same bytes and times: the same SHA-256): ``--resume`` takes
    the kept windows (was: refused in one line, ``file was '.../ev.h5', now '.../moved/ev.h5'``; given by the same
    relative path, every kept window was fitted again without a word) and the results equal an uninterrupted run's."""
    path = tmp_path / "ev.h5"
    path.write_bytes(recording.read_bytes())
    whole = tmp_path / "whole"
    status = main(se3_argv(path, whole))
    out = tmp_path / "o"
    counted_calls(monkeypatch, sequence_module, "fit", interrupt_at=3)
    assert main(se3_argv(path, out)) == 130
    moved = tmp_path / "moved"
    moved.mkdir()
    os.rename(path, moved / "ev.h5")
    os.rename(out, moved / "o")
    calls = counted_calls(monkeypatch, sequence_module, "fit")
    capsys.readouterr()
    assert main([*se3_argv(moved / "ev.h5", moved / "o"), "--resume"]) == status
    assert len(calls) == 2 and "resumed: 2 of 4 fitted windows taken" in capsys.readouterr().err
    assert_same(results_of(moved / "o"), results_of(whole))


def test_a_fresh_run_fits_its_first_window_while_its_inputs_are_hashed(recording, tmp_path, monkeypatch):
    """A fresh ``cmax fit`` hashes its inputs (cmax.io.window_store.PendingSignatures) while it fits: the event
    file's hash is held back until the first window's fit has begun, and the run goes on (was: every run hashed its
    inputs whole before anything else, 13.5 s for 3 GB from disk: this hash waited for a fit that never came, 60 s).
    The window kept with the first window records the SHA-256 of the file's bytes (hashlib of its bytes), and no
    hashing thread outlives the run."""
    import hashlib

    order = hash_held_back(monkeypatch, recording.name, sequence_module, "fit", interrupt_at=3)
    out = tmp_path / "o"
    assert main(se3_argv(recording, out)) == 130          # interrupted in the third window: two kept
    assert order[:2] == ["fit", "hashed"], order
    record = json.loads((out / WINDOWS_FOLDER / "run.json").read_text())
    assert record["file"]["sha256"] == hashlib.sha256(recording.read_bytes()).hexdigest()
    assert record["file"]["bytes"] == recording.stat().st_size
    assert not hashing_threads()


def test_an_input_modified_while_it_is_hashed_beside_the_fit_is_refused(recording, tmp_path, monkeypatch, capsys):
    """The event file touched while it is hashed (in the background now, beside the fit): refused in one line
    naming it (cmax.io.atomic.check_unchanged), exit 2; no result and no kept window is left that looks like a
    run of it."""
    import cmax.io.window_store as window_store

    path = tmp_path / "ev.h5"
    path.write_bytes(recording.read_bytes())
    real = window_store.file_sha256

    def touched(file, read=None):
        digest = real(file, read)
        if os.path.basename(file) == path.name:
            stat = os.stat(file)
            os.utime(file, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
        return digest

    monkeypatch.setattr(window_store, "file_sha256", touched)
    out = tmp_path / "o"
    capsys.readouterr()
    assert main(se3_argv(path, out)) == 2
    err = capsys.readouterr().err
    assert f"{path} changed while it was read to hash it: it was modified" in err and len(err.strip().splitlines()) == 1
    assert not (out / "summary.json").exists() and not (out / WINDOWS_FOLDER).exists()
    assert not out.exists() or not any(out.iterdir())     # the run's own folder, removed with its stage
    assert not hashing_threads()


def test_ctrl_c_while_the_inputs_are_hashed_stops_the_hashing_and_exits_130(recording, tmp_path, monkeypatch,
                                                                             capsys):
    """Ctrl-C in the first window while the event file is still being hashed (a hash that would take 60 s): exit
    130 at once, one line, no result, and the hashing thread is stopped, not left running."""
    import cmax.io.window_store as window_store

    real, stopped = window_store.file_sha256, []

    def slow(path, read=None):
        deadline = time.monotonic() + 60
        try:
            while os.path.basename(path) == recording.name and time.monotonic() < deadline:
                if read is not None:
                    read(0)             # where the hashing is stopped: between blocks
                time.sleep(0.01)
        except BaseException:
            stopped.append(path)
            raise
        return real(path, read)

    monkeypatch.setattr(window_store, "file_sha256", slow)
    counted_calls(monkeypatch, sequence_module, "fit", interrupt_at=1)
    out = tmp_path / "o"
    capsys.readouterr()
    started = time.monotonic()
    assert main(se3_argv(recording, out)) == 130
    assert time.monotonic() - started < 30
    assert capsys.readouterr().err.strip() == "cmax fit: interrupted"
    assert stopped and not hashing_threads()
    assert not (out / "summary.json").exists() and not (out / WINDOWS_FOLDER).exists()


def test_resume_of_a_finished_fit_says_it_is_complete_and_touches_nothing(tmp_path, monkeypatch, capsys):
    """A requeued job that always passes --resume, after its run had finished: exit 2, "holds the results of an
    earlier run" (was). summary.json now records the run: the same run exits with the finished run's status and
    one line, fits nothing and rewrites nothing; other bytes under the same size and mtime, or another option,
    are refused in one line, the results kept."""
    path = write_h5(tmp_path / "ev.h5", noise_events(3000, 50_000, seed=3), compression="none")
    out = tmp_path / "o"
    argv = ["fit", str(path), "--K", K_OPTION, "-o", str(out), "--quiet", "--model", "flow", "--min-events", "300",
            "--window-ms", "12.5"]
    status = main(argv)
    assert status in (0, 1) and len(json.loads((out / "summary.json").read_text())["windows"]) == 4

    def stamps() -> dict:
        return {p.name: (p.stat().st_mtime_ns, p.stat().st_ino, p.read_bytes()) for p in sorted(out.iterdir())}

    before = stamps()
    capsys.readouterr()
    calls = counted_calls(monkeypatch, sequence_module, "fit")
    assert main([*argv, "--resume"]) == status
    captured = capsys.readouterr()
    assert captured.out.strip().splitlines() == [f"the results in {out} are already complete: cmax fit --resume of "
                                                 "the same input files and options has nothing to do (nothing "
                                                 "changed)"], captured
    assert calls == [] and stamps() == before
    assert main([*argv, "--resume", "--min-events", "400"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds the complete results of another run" in err[0], err
    assert "min_events was 300, now 400" in err[0] and stamps() == before and calls == []
    stat = path.stat()
    write_h5(path, noise_events(3000, 50_000, seed=4), compression="none", overwrite=True)
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert (path.stat().st_size, path.stat().st_mtime_ns) == (stat.st_size, stat.st_mtime_ns)
    assert main([*argv, "--resume"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "ev.h5 holds other bytes than it did" in err[0] and stamps() == before, err
    assert calls == []


def _finished_flow_fit(tmp_path):
    """A finished ``cmax fit`` (flow, 4 windows of noise) into ``tmp_path/o``: its argv, folder, exit status and
    results."""
    path = write_h5(tmp_path / "ev.h5", noise_events(3000, 50_000, seed=3), compression="none")
    out = tmp_path / "o"
    argv = ["fit", str(path), "--K", K_OPTION, "-o", str(out), "--quiet", "--model", "flow", "--min-events", "300",
            "--window-ms", "12.5"]
    status = main(argv)
    return argv, out, status, results_of(out)


def _resume_fits_again(argv, out, status, first, monkeypatch, capsys, why):
    """``--resume`` of that run fits its 4 windows again with one "not complete" note saying ``why`` and ends with
    the ``first`` results; returns the recorded fit calls."""
    capsys.readouterr()
    calls = counted_calls(monkeypatch, sequence_module, "fit")
    assert main([*argv, "--resume"]) == status
    captured = capsys.readouterr()
    assert "already complete" not in captured.out and len(calls) == 4, captured
    note = [line for line in captured.err.splitlines() if "not complete" in line]
    assert len(note) == 1 and why in note[0], captured.err
    assert_same(results_of(out), first)
    return calls


def test_resume_of_a_finished_fit_with_a_result_emptied_fits_again(tmp_path, monkeypatch, capsys):
    """Was: ``--resume`` judged the run complete by its summary.json alone: with ``trajectory.txt`` emptied (or a
    depth file deleted), "the results in o are already complete", the folder left damaged. summary.json now
    records each result's size and SHA-256 ("outputs"): the same run fits again, says why on one note line, and
    ends with the first run's results (tests/test_depth_resume.py and tests/test_run_folder.py: deleted and
    changed files)."""
    argv, out, status, first = _finished_flow_fit(tmp_path)
    outputs = json.loads((out / "summary.json").read_text())["outputs"]
    assert sorted(outputs) == ["trajectory.txt"] and outputs["trajectory.txt"]["bytes"] > 0
    (out / "trajectory.txt").write_text("")
    calls = _resume_fits_again(argv, out, status, first, monkeypatch, capsys, "trajectory.txt has 0 bytes")
    assert json.loads((out / "summary.json").read_text())["outputs"] == outputs
    calls.clear()
    assert main([*argv, "--resume"]) == status and calls == []      # now complete: nothing to do
    assert "already complete" in capsys.readouterr().out


def test_resume_of_a_finished_fit_whose_summary_lists_no_outputs_is_not_taken_on_trust(tmp_path, monkeypatch,
                                                                                          capsys):
    """Was: a ``summary.json`` without ``"outputs"`` (as summaries written before they were recorded) was "not
    checked": ``--resume`` of the same run said "already complete" with ``trajectory.txt`` emptied, the damaged
    folder kept. Now results that cannot be verified are not taken on trust: the same run fits again (one note
    naming why) and ends with the first run's results; a summary of another version of the code is refused as
    another run."""
    argv, out, status, first = _finished_flow_fit(tmp_path)
    summary = json.loads((out / "summary.json").read_text())
    (out / "summary.json").write_text(json.dumps({key: value for key, value in summary.items() if key != "outputs"}))
    (out / "trajectory.txt").write_text("")
    _resume_fits_again(argv, out, status, first, monkeypatch, capsys, "cannot be verified")
    assert json.loads((out / "summary.json").read_text())["outputs"] == summary["outputs"]
    old = json.loads((out / "summary.json").read_text())         # another version's summary: refused, kept as it is
    old.pop("outputs")
    old["run"]["code"] = "0" * 64
    (out / "summary.json").write_text(json.dumps(old))
    assert main([*argv, "--resume"]) == 2
    assert "the code of cmax (or learned) changed" in capsys.readouterr().err
