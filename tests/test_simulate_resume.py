"""A long ``cmax simulate`` killed part-way continues from its last kept chunk (cmax/sim/chunks.py) and ends with
the events of an uninterrupted conversion, bit for bit; a chunk that fails its check is simulated again; chunks of
another source or other settings are refused unless the run starts over."""
from __future__ import annotations

import io
import json
import os
import random
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import cmax.sim.chunks as chunks_module
import cmax.sim.convert as convert_module
from cmax.cli import main
from cmax.io.h5 import read_h5, write_h5
from cmax.sim.chunks import KeptChunks, chunk_folder
from cmax.sim.convert import ConvertSettings, collect_jobs, convert_collection, convert_video
from cmax.sim.esim import EsimSettings, EventSimulator
from conftest import counted_calls, one_line_error, sigkill_after

cv2 = pytest.importorskip("cv2")
#: Noise and mismatch on: the generator's state, the thresholds and the refractory times must carry over too.
NOISY = EsimSettings(threshold_sigma=0.05, refractory_us=200, shot_noise_rate_hz=2.0, seed=3)
NOISY_OPTIONS = ["--threshold-sigma", "0.05", "--refractory-us", "200", "--shot-noise", "2", "--seed", "3"]
#: The settings ``cmax simulate --method linear`` converts with (its --seed is 0 by default).
LINEAR = ConvertSettings(method="linear", esim=EsimSettings(seed=0))


def write_video(path, n_frames: int = 48, width: int = 64, height: int = 48, phase: float = 0.0) -> None:
    """A small MJPG video (25 frames/s) of a pattern that drifts and changes, so that every frame has events."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25, (width, height))
    assert writer.isOpened()
    y, x = np.mgrid[0:height, 0:width]
    for k in range(n_frames):
        value = 128 + 90 * np.sin(0.3 * (x - 2 * k) + phase) * np.cos(0.2 * y + 0.1 * k)
        writer.write(cv2.cvtColor(value.astype(np.uint8), cv2.COLOR_GRAY2BGR))
    writer.release()


def same_events(a, b) -> bool:
    return len(a) == len(b) and a.sensor_size == b.sensor_size and all(
        np.array_equal(getattr(a, name), getattr(b, name)) for name in "xytp")


@pytest.mark.parametrize("kw", [{}, {"threshold_sigma": 0.1, "seed": 3}, {"refractory_us": 100},
                                {"shot_noise_rate_hz": 50.0, "seed": 1, "leak_rate_hz": 5.0}])
def test_a_restored_simulator_continues_with_the_events_of_one_that_ran_on(kw):
    rng = np.random.default_rng(0)
    frames, times = rng.integers(0, 256, (10, 12, 16)).astype(np.uint8), np.arange(10) * 1000
    whole = EventSimulator(**kw).simulate(frames, times)
    first = EventSimulator(**kw)
    parts = [first.step(frame, t) for frame, t in zip(frames[:4], times[:4])]
    buffer = io.BytesIO()
    np.savez(buffer, **first.state())                      # as a chunk keeps it
    buffer.seek(0)
    second = EventSimulator(**kw)
    second.restore(dict(np.load(buffer)))
    parts += [second.step(frame, t) for frame, t in zip(frames[4:], times[4:])]
    from cmax.events import Events

    assert same_events(Events.concatenate(parts), whole)


def test_a_state_of_other_settings_is_refused():
    simulator = EventSimulator(threshold_sigma=0.1, seed=1)
    simulator.step(np.zeros((4, 5), np.uint8), 0)
    with pytest.raises(ValueError, match="does not fit these settings"):
        EventSimulator().restore(simulator.state())
    with pytest.raises(ValueError, match="no state before its first frame"):
        EventSimulator().state()


def test_chunks_of_many_blocks_give_the_events_of_one_pass(tmp_path, monkeypatch):
    """Chunks are written as compressed blocks with time differences: they must read back whole (was: each
    block's times restarted from 0, so the output was refused as out of time order)."""
    monkeypatch.setattr(chunks_module, "BLOCK_EVENTS", 500)
    write_video(tmp_path / "v.avi", 30)
    settings = ConvertSettings(method="linear", esim=NOISY)
    convert_video(tmp_path / "v.avi", tmp_path / "whole.h5", settings)
    result = convert_video(tmp_path / "v.avi", tmp_path / "chunked.h5", settings, chunk_frames=7)
    assert result.events > 5000                            # many blocks per chunk
    assert same_events(read_h5(tmp_path / "chunked.h5"), read_h5(tmp_path / "whole.h5"))
    assert not chunk_folder(tmp_path / "chunked.h5").exists()


def _interrupted(tmp_path, monkeypatch, settings, stop_at: int):
    """Convert ``v.avi`` in chunks of 6 frames and stop it (Ctrl-C) at the ``stop_at``-th chunk; returns the
    output path, the chunk folder and the uninterrupted conversion's events."""
    write_video(tmp_path / "v.avi", 40)
    convert_video(tmp_path / "v.avi", tmp_path / "whole.h5", settings)
    counted_calls(monkeypatch, KeptChunks, "save", interrupt_at=stop_at)
    with pytest.raises(KeyboardInterrupt):
        convert_video(tmp_path / "v.avi", tmp_path / "v.h5", settings, chunk_frames=6)
    monkeypatch.undo()
    assert not (tmp_path / "v.h5").exists()
    return tmp_path / "v.h5", chunk_folder(tmp_path / "v.h5"), read_h5(tmp_path / "whole.h5")


@pytest.mark.parametrize("damaged, kept_frames", [
    ("chunk_000004.events", 24), ("chunk_000004.state.npz", 24), ("chunk_000004.json", 24),   # from chunk 3
    ("chunk_000001.events", None),        # before the kept states: simulated again from the first frame
])
def test_a_damaged_chunk_is_simulated_again_never_trusted(tmp_path, monkeypatch, damaged, kept_frames):
    settings = ConvertSettings(esim=NOISY)                 # adaptive sampling with optical flow
    output, folder, whole = _interrupted(tmp_path, monkeypatch, settings, stop_at=6)
    assert sorted(p.name for p in folder.glob("chunk_*.json")) == [f"chunk_00000{i}.json" for i in range(5)]
    assert sorted(p.name for p in folder.glob("*.state.npz")) == ["chunk_000003.state.npz", "chunk_000004.state.npz"]
    data = bytearray((folder / damaged).read_bytes())
    data[len(data) // 2] ^= 0x01                           # one bit, size unchanged
    (folder / damaged).write_bytes(bytes(data))
    resumed = []
    with pytest.warns(UserWarning, match="kept chunk.s. are simulated again: a chunk failed its check"):
        result = convert_video(tmp_path / "v.avi", output, settings, chunk_frames=6,
                               resumed=lambda frames, events: resumed.append(frames))
    assert resumed == ([] if kept_frames is None else [kept_frames])
    assert same_events(read_h5(output), whole) and result.frames == 40
    assert not folder.exists()


def test_kept_chunks_of_other_settings_or_another_source_are_refused(tmp_path, monkeypatch):
    settings = LINEAR
    output, folder, whole = _interrupted(tmp_path, monkeypatch, settings, stop_at=3)
    other = ConvertSettings(method="linear", esim=EsimSettings(cp=0.3, seed=0))
    with pytest.raises(ValueError, match=r"another run \(esim.cp was 0.2, now 0.3\)"):
        convert_video(tmp_path / "v.avi", output, other, chunk_frames=6)
    os.utime(tmp_path / "v.avi", ns=(1, 1))                # the source touched (re-exported, replaced)
    with pytest.raises(ValueError, match=r"v.avi was modified since"):
        convert_video(tmp_path / "v.avi", output, settings, chunk_frames=6)
    assert len(list(folder.glob("chunk_*.json"))) == 2     # nothing was thrown away
    resumed = []
    convert_video(tmp_path / "v.avi", output, settings, chunk_frames=6, kept="resume_or_restart",
                  resumed=lambda frames, events: resumed.append(frames))
    assert resumed == [] and same_events(read_h5(output), whole)


def test_cmax_simulate_killed_part_way_continues_to_the_events_of_an_uninterrupted_run(tmp_path):
    """SIGKILL (no clean-up at all) once a random number of chunks are kept; the same command continues from
    them (the progress note says how many frames were kept) and ends with the uninterrupted run's events."""
    write_video(tmp_path / "v.avi", 72)
    argv = [sys.executable, "-m", "cmax.cli", "simulate", str(tmp_path / "v.avi"), "--quiet", "--chunk-frames", "6",
            *NOISY_OPTIONS]
    whole = subprocess.run([*argv, "-o", str(tmp_path / "whole" / "v.h5")], capture_output=True, text=True)
    assert whole.returncode == 0, whole.stderr
    out = tmp_path / "o"
    out.mkdir()
    kill_after = random.Random().randint(1, 10)
    folder = chunk_folder(out / "v.h5")
    if not sigkill_after([*argv, "-o", str(out / "v.h5")], folder, "chunk_*.json", kill_after):
        pytest.skip("the run ended before it could be killed (a very fast machine)")
    assert not (out / "v.h5").exists()
    kept = len(list(folder.glob("chunk_*.json")))
    assert kill_after <= kept < 12
    resumed = subprocess.run([*argv, "-o", str(out / "v.h5")], capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    assert f"continuing an interrupted conversion: {6 * kept} frame(s)" in resumed.stderr
    assert same_events(read_h5(out / "v.h5"), read_h5(tmp_path / "whole" / "v.h5"))
    assert sorted(os.listdir(out)) == ["manifest.json", "v.h5"]
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["videos"]["v"]["frames"] == 72 and manifest["videos"]["v"]["status"] == "ok"


def test_cmax_simulate_refuses_kept_chunks_of_a_changed_video_in_one_line(tmp_path, monkeypatch, capsys):
    settings = LINEAR
    output, folder, whole = _interrupted(tmp_path, monkeypatch, settings, stop_at=3)
    os.utime(tmp_path / "v.avi", ns=(1, 1))
    argv = ["simulate", str(tmp_path / "v.avi"), "-o", str(output), "--quiet", "--method", "linear",
            "--chunk-frames", "6"]
    status, err = one_line_error(lambda: main(argv), capsys)
    assert status == 2 and "v.avi was modified since" in err and "--overwrite" in err
    assert len(list(folder.glob("chunk_*.json"))) == 2
    assert main([*argv, "--overwrite"]) == 0               # starts over
    assert same_events(read_h5(output), whole) and not folder.exists()


def test_a_folder_killed_in_its_second_video_continues_that_video_and_verifies_the_first(tmp_path, capsys):
    videos, out = tmp_path / "videos", tmp_path / "out"
    videos.mkdir()
    for number, name in enumerate("abc"):
        write_video(videos / f"{name}.avi", 36, phase=number)
    argv = [sys.executable, "-m", "cmax.cli", "simulate", str(videos), "-o", str(out), "--quiet", "--method",
            "linear", "--chunk-frames", "6"]
    if not sigkill_after(argv, chunk_folder(out / "b.h5"), "chunk_*.json", 2):
        pytest.skip("the run ended before it could be killed (a very fast machine)")
    assert (out / "a.h5").exists() and not (out / "b.h5").exists()
    a_bytes = (out / "a.h5").read_bytes()
    data = bytearray(a_bytes)
    data[len(data) // 2] ^= 0x01                           # a finished file damaged in place
    (out / "a.h5").write_bytes(bytes(data))
    jobs, _ = collect_jobs(videos)
    converted = []
    manifest = convert_collection(jobs, out, LINEAR, progress=False, chunk_frames=6,
                                  on_result=lambda result: converted.append(result.name))
    err = capsys.readouterr().err
    assert converted == ["a", "b", "c"] and "a: output not verified" in err   # its checksum, not its existence
    assert "b: continuing an interrupted conversion" in err
    assert (out / "a.h5").read_bytes() == a_bytes
    for name in "bc":
        clean = convert_video(videos / f"{name}.avi", tmp_path / f"{name}.h5", LINEAR)
        assert same_events(read_h5(out / f"{name}.h5"), read_h5(tmp_path / f"{name}.h5"))
        assert manifest["videos"][name]["events"] == clean.events
    assert sorted(os.listdir(out)) == ["a.h5", "b.h5", "c.h5", "manifest.json"]


def test_an_output_written_from_its_chunks_but_not_recorded_is_written_again_not_refused(tmp_path, capsys):
    """Killed after the output was renamed into place and before the manifest recorded it: the rerun would have
    refused the file as not its own (--overwrite, which starts over); the chunks are still there, so it is
    written again from them."""
    write_video(tmp_path / "v.avi", 20)
    settings = LINEAR
    convert_video(tmp_path / "v.avi", tmp_path / "v.h5", settings, chunk_frames=6, keep_chunks=True)
    first = read_h5(tmp_path / "v.h5")
    argv = ["simulate", str(tmp_path / "v.avi"), "-o", str(tmp_path / "v.h5"), "--quiet", "--method", "linear",
            "--chunk-frames", "6"]
    assert main(argv) == 0, capsys.readouterr().err
    err = capsys.readouterr().err      # every chunk kept: no frame is read again, the video's SHA-256 is the check
    assert "20 frame(s)" in err and "the video's bytes verified by SHA-256" in err and "as they are read again" not in err
    assert same_events(read_h5(tmp_path / "v.h5"), first) and not chunk_folder(tmp_path / "v.h5").exists()


def test_an_interrupted_overwrite_keeps_the_old_file_and_continues_with_overwrite_again(tmp_path):
    """``-o F.h5 --overwrite`` killed part-way: the old F.h5 stays until the new one is complete, and the same
    command again continues the kept chunks (was it to start over, the hours already simulated were lost)."""
    write_video(tmp_path / "v.avi", 72)
    out = tmp_path / "o"
    argv = [sys.executable, "-m", "cmax.cli", "simulate", str(tmp_path / "v.avi"), "-o", str(out / "v.h5"),
            "--quiet", "--chunk-frames", "6", "--method", "linear"]
    assert subprocess.run(argv, capture_output=True).returncode == 0
    old = (out / "v.h5").read_bytes()
    if not sigkill_after([*argv, "--overwrite"], chunk_folder(out / "v.h5"), "chunk_*.json", 3):
        pytest.skip("the run ended before it could be killed (a very fast machine)")
    assert (out / "v.h5").read_bytes() == old
    kept = len(list(chunk_folder(out / "v.h5").glob("chunk_*.json")))
    again = subprocess.run([*argv, "--overwrite"], capture_output=True, text=True)
    assert again.returncode == 0, again.stderr
    assert f"continuing an interrupted conversion: {6 * kept} frame(s)" in again.stderr
    clean = convert_video(tmp_path / "v.avi", tmp_path / "clean.h5", LINEAR)
    assert same_events(read_h5(out / "v.h5"), read_h5(tmp_path / "clean.h5")) and clean.frames == 72


def test_kept_chunks_whose_last_frame_decodes_otherwise_are_not_continued(tmp_path, monkeypatch):
    """The last kept frame is decoded again and checked (another OpenCV could decode it otherwise): refused with
    ``kept="resume"``; with ``"resume_or_restart"`` a warning and the whole video is converted again."""
    output, folder, whole = _interrupted(tmp_path, monkeypatch, LINEAR, stop_at=3)
    record = json.loads((folder / "chunk_000001.json").read_text())
    record["frame_sha256"] = "0" * 64                      # as if the frame had decoded to other pixels
    (folder / "chunk_000001.json").write_text(json.dumps(record))
    with pytest.raises(ValueError, match="decodes differently .* pass --overwrite"):
        convert_video(tmp_path / "v.avi", output, LINEAR, chunk_frames=6)
    with pytest.warns(UserWarning, match="converting it from its first frame"):
        convert_video(tmp_path / "v.avi", output, LINEAR, chunk_frames=6, kept="resume_or_restart")
    assert same_events(read_h5(output), whole) and not folder.exists()


def test_a_second_conversion_into_the_same_output_is_refused_while_one_runs(tmp_path):
    """The chunks are one conversion's: while it runs (its lock held) another one into the same output fails at
    once and changes nothing (without the lock it would have taken the running one's chunks as its own)."""
    from cmax.io.atomic import OutputLockedError, PathLock, lock_path

    write_video(tmp_path / "v.avi", 12)
    with PathLock(lock_path(chunk_folder(tmp_path / "v.h5"))):
        with pytest.raises(OutputLockedError, match="being written by another writer"):
            convert_video(tmp_path / "v.avi", tmp_path / "v.h5", LINEAR, chunk_frames=4)
    assert sorted(os.listdir(tmp_path)) == ["v.avi"]
    convert_video(tmp_path / "v.avi", tmp_path / "v.h5", LINEAR, chunk_frames=4)
    assert sorted(os.listdir(tmp_path)) == ["v.avi", "v.h5"]


def test_chunks_of_a_video_this_run_does_not_convert_are_named(tmp_path, monkeypatch, capsys):
    """Chunks left by an interrupted conversion of another video hold disk space (as much as its output) that no
    run would free: a conversion into the folder names them."""
    output, folder, _ = _interrupted(tmp_path, monkeypatch, LINEAR, stop_at=2)
    write_video(tmp_path / "w.avi", 8)
    jobs, _ = collect_jobs(tmp_path / "w.avi")
    convert_collection(jobs, tmp_path, LINEAR, progress=False)
    err = capsys.readouterr().err
    assert "kept chunks of 1 interrupted conversion(s) of other videos than this run's (.v.h5.chunks)" in err
    assert folder.is_dir()                                 # named, not removed


def test_a_video_replaced_by_one_of_the_same_size_and_mtime_is_not_continued(tmp_path, monkeypatch):
    """The source's signature is its size and mtime: a video replaced in place by another of the same size and
    mtime (a re-download keeping the server's time) passed it, and only the kept chunks' last frame was checked,
    so a change before it went unseen (was: the output held the old video's events up to there and the new one's
    after, without a word). The source's signature now holds the SHA-256 of its bytes, so the kept chunks are
    another run's (was, before that: each chunk's digest of its frames caught it, and still catches frames that
    decode otherwise, another OpenCV or FFmpeg)."""
    output, folder, _ = _interrupted(tmp_path, monkeypatch, LINEAR, stop_at=4)
    assert len(list(folder.glob("chunk_*.json"))) == 3                # frames 0..17 kept
    video = tmp_path / "v.avi"
    stat = video.stat()
    capture = cv2.VideoCapture(str(video))
    frames = [capture.read()[1] for _ in range(40)]
    capture.release()
    frames[2] = np.full_like(frames[2], 128)                          # one early frame differs; the last kept one not
    writer = cv2.VideoWriter(str(tmp_path / "new.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 25, frames[0].shape[1::-1])
    for frame in frames:
        writer.write(frame)
    writer.release()
    data = (tmp_path / "new.avi").read_bytes()
    assert len(data) < stat.st_size                                   # a flat frame compresses better
    video.write_bytes(data + bytes(stat.st_size - len(data)))         # padded to the same size after its end
    os.utime(video, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    (tmp_path / "new.avi").unlink()
    convert_video(video, tmp_path / "fresh.h5", LINEAR)               # the replaced video, converted whole
    with pytest.raises(ValueError, match=r"another run \(v.avi holds other bytes .* --overwrite"):
        convert_video(video, output, LINEAR, chunk_frames=6)
    recorded = json.loads((folder / "run.json").read_text())["source"]   # as if the bytes were the same
    monkeypatch.setattr(convert_module, "source_signature", lambda source, read=None: recorded)
    with pytest.raises(ValueError, match=r"v.avi: frames 0 to 5 decode to other pixels .* pass --overwrite"):
        convert_video(video, output, LINEAR, chunk_frames=6)
    monkeypatch.undo()
    convert_video(video, output, LINEAR, chunk_frames=6, kept="resume_or_restart")
    assert same_events(read_h5(output), read_h5(tmp_path / "fresh.h5")) and not folder.exists()


def replace_with_same_size_and_mtime(video, n_frames: int = 40, flat: int = 2) -> None:
    """Replace ``video`` in place by the same frames with frame ``flat`` made flat grey, padded after its end to the
    old size, and its modification time set back (``cp -p``, ``rsync -t``, a re-download keeping the server's
    time)."""
    stat = video.stat()
    capture = cv2.VideoCapture(str(video))
    frames = [capture.read()[1] for _ in range(n_frames)]
    capture.release()
    frames[flat] = np.full_like(frames[flat], 128)
    other = video.with_name("other_" + video.name)
    writer = cv2.VideoWriter(str(other), cv2.VideoWriter_fourcc(*"MJPG"), 25, frames[0].shape[1::-1])
    for frame in frames:
        writer.write(frame)
    writer.release()
    data = other.read_bytes()
    other.unlink()
    assert len(data) < stat.st_size                                   # a flat frame compresses better
    video.write_bytes(data + bytes(stat.st_size - len(data)))
    os.utime(video, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert (video.stat().st_size, video.stat().st_mtime_ns) == (stat.st_size, stat.st_mtime_ns)


def test_a_video_replaced_after_its_last_chunk_was_kept_is_not_assembled_from_the_old_chunks(tmp_path, monkeypatch):
    """Killed after every chunk was kept (while the output was written from them), then the video replaced by
    another of the same size and mtime: the rerun decoded no frame (the chunks hold the whole video) and wrote the
    old video's events under the new one's name, exit 0 (was). The source's content (SHA-256) is part of what a
    chunked conversion is: refused; starting over gives the new video's events."""
    video, output = tmp_path / "v.avi", tmp_path / "v.h5"
    write_video(video, 40)
    counted_calls(monkeypatch, chunks_module.KeptChunks, "iter_events", interrupt_at=1)   # killed in assembly
    with pytest.raises(KeyboardInterrupt):
        convert_video(video, output, LINEAR, chunk_frames=6)
    monkeypatch.undo()
    folder = chunk_folder(output)
    assert not output.exists() and json.loads((folder / "chunk_000006.json").read_text())["final"] is True
    replace_with_same_size_and_mtime(video)
    convert_video(video, tmp_path / "fresh.h5", LINEAR)               # the new video, converted whole
    with pytest.raises(ValueError, match=r"another run \(v.avi holds other bytes .*--overwrite"):
        convert_video(video, output, LINEAR, chunk_frames=6)
    assert not output.exists() and len(list(folder.glob("chunk_*.json"))) == 7   # nothing thrown away unasked
    convert_video(video, output, LINEAR, chunk_frames=6, kept="resume_or_restart")
    assert same_events(read_h5(output), read_h5(tmp_path / "fresh.h5")) and not folder.exists()


def test_chunks_of_a_moved_video_are_continued_not_simulated_again(tmp_path, monkeypatch):
    """The video and the chunk folder moved together (``mv`` keeps bytes and times, so the SHA-256 is the same):
    the conversion continues from the kept chunks (was: every chunk failed its check, a warning, and the video was
    simulated again from its first frame) and ends with the uninterrupted conversion's events."""
    settings = LINEAR
    output, folder, whole = _interrupted(tmp_path, monkeypatch, settings, stop_at=4)
    kept = len(list(folder.glob("chunk_*.json")))
    moved = tmp_path / "moved"
    moved.mkdir()
    os.rename(tmp_path / "v.avi", moved / "v.avi")
    os.rename(folder, chunk_folder(moved / "v.h5"))
    resumed = []
    with warnings.catch_warnings():
        warnings.simplefilter("error")                      # no "simulated again"
        result = convert_video(moved / "v.avi", moved / "v.h5", settings, chunk_frames=6,
                               resumed=lambda frames, events: resumed.append(frames))
    assert resumed == [6 * kept] and kept >= 2
    assert same_events(read_h5(moved / "v.h5"), whole) and result.frames == 40


def _chunks_beside(tmp_path, video, output) -> None:
    """Leave the chunks of a finished conversion of ``video`` (final chunk included) beside ``output``, as a
    conversion killed after writing its output from them does."""
    convert_video(video, tmp_path / "elsewhere.h5", LINEAR, chunk_frames=6, keep_chunks=True)
    os.rename(chunk_folder(tmp_path / "elsewhere.h5"), chunk_folder(output))


@pytest.mark.parametrize("chunks_of", ["another video", "this video"])
@pytest.mark.parametrize("chunk_frames", ["0", "6"])
def test_a_file_of_the_user_beside_kept_chunks_is_never_replaced(tmp_path, capsys, chunks_of, chunk_frames):
    """A user's own ``v.h5`` that no manifest lists, beside a chunk folder whose chunks include a final one (of
    another video, or of this one: the file is not the one written from them) is refused in one line naming it,
    and stays, with the chunks (was: replaced without --overwrite with --chunk-frames 0, and with the chunks of
    this video at any --chunk-frames); --overwrite replaces it with the conversion of the video."""
    write_video(tmp_path / "v.avi", 20)
    write_video(tmp_path / "other.avi", 20, phase=1.0)
    output = tmp_path / "out" / "v.h5"
    output.parent.mkdir()
    _chunks_beside(tmp_path, tmp_path / ("v.avi" if chunks_of == "this video" else "other.avi"), output)
    users = write_h5(output, read_h5(tmp_path / "elsewhere.h5")).read_bytes()   # a complete h5 file, not this one's
    kept = sorted(os.listdir(chunk_folder(output)))
    argv = ["simulate", str(tmp_path / "v.avi"), "-o", str(output), "--quiet", "--method", "linear",
            "--chunk-frames", chunk_frames]
    status, err = one_line_error(lambda: main(argv), capsys)
    assert status == 2 and "v.h5" in err and "--overwrite" in err
    assert output.read_bytes() == users and sorted(os.listdir(chunk_folder(output))) == kept
    assert main([*argv, "--overwrite"]) == 0
    convert_video(tmp_path / "v.avi", tmp_path / "clean.h5", LINEAR)
    assert same_events(read_h5(output), read_h5(tmp_path / "clean.h5"))


def test_chunks_of_another_video_are_not_removed_by_a_conversion_without_chunks(tmp_path, monkeypatch, capsys):
    """``--chunk-frames 0`` beside the chunks an interrupted conversion of another video kept: refused in one line
    as with chunks (was: converted, then the other video's chunks removed without --overwrite)."""
    _interrupted(tmp_path, monkeypatch, LINEAR, stop_at=3)           # chunks of v.avi beside v.h5
    folder = chunk_folder(tmp_path / "v.h5")
    write_video(tmp_path / "w.avi", 20, phase=1.0)
    (tmp_path / "o").mkdir()
    os.rename(folder, chunk_folder(tmp_path / "o" / "w.h5"))
    argv = ["simulate", str(tmp_path / "w.avi"), "-o", str(tmp_path / "o" / "w.h5"), "--quiet", "--method",
            "linear", "--chunk-frames", "0"]
    status, err = one_line_error(lambda: main(argv), capsys)
    assert status == 2 and "another run" in err and "--overwrite" in err
    assert len(list(chunk_folder(tmp_path / "o" / "w.h5").glob("chunk_*.json"))) == 2
    assert not (tmp_path / "o" / "w.h5").exists()


def test_a_removal_of_kept_chunks_cut_short_is_not_read_as_chunks(tmp_path, monkeypatch, capsys):
    """Ctrl-C while a recorded video's chunks are removed, after ``run.json`` went and before the chunks did (was:
    every later run into the folder refused, ``run.json is missing or unreadable ... pass --overwrite``, which for a
    folder skipped the video and kept the chunks); now the folder is renamed first: the rerun skips the verified
    video and removes what is left."""
    videos, out = tmp_path / "videos", tmp_path / "out"
    videos.mkdir()
    write_video(videos / "a.avi", 20)
    real = chunks_module.shutil.rmtree

    def cut_short(path, ignore_errors=False):
        if not Path(path).exists():
            return real(path, ignore_errors=ignore_errors)
        for leftover in sorted(Path(path).glob("*"), key=lambda p: p.name != "run.json")[:2]:
            leftover.unlink()                           # run.json and one chunk file gone, then Ctrl-C
        raise KeyboardInterrupt

    monkeypatch.setattr(chunks_module.shutil, "rmtree", cut_short)
    with pytest.raises(KeyboardInterrupt):
        convert_collection(collect_jobs(videos)[0], out, LINEAR, progress=False, chunk_frames=6)
    monkeypatch.setattr(chunks_module.shutil, "rmtree", real)
    assert json.loads((out / "manifest.json").read_text())["videos"]["a"]["status"] == "ok"
    argv = ["simulate", str(videos), "-o", str(out), "--quiet", "--method", "linear", "--chunk-frames", "6"]
    assert main(argv) == 0, capsys.readouterr().err
    assert "already converted" in capsys.readouterr().out
    assert sorted(os.listdir(out)) == ["a.h5", "manifest.json"]


def test_a_chunked_resume_reads_the_video_once_to_hash_it(tmp_path, monkeypatch):
    """Continuing a video's kept chunks, cmax simulate hashed the video twice: once to compare it with the chunks
    (before anything is converted), once more as its conversion began (a multi-GB video: seconds each). Now once:
    the conversion takes the signature just taken while the video keeps its size and modification time; the
    events equal an uninterrupted conversion's, and the manifest records the video's SHA-256 (hashlib of its
    bytes). A video touched between the two is hashed again (its new signature is recorded)."""
    import hashlib

    import cmax.sim.signature as signature_module

    output, folder, whole = _interrupted(tmp_path, monkeypatch, LINEAR, stop_at=3)
    video = tmp_path / "v.avi"
    real, hashed = signature_module.file_sha256, []

    def counted(path, read=None):
        if os.path.basename(path) == video.name:
            hashed.append(path)
        return real(path, read)

    monkeypatch.setattr(signature_module, "file_sha256", counted)
    jobs, _ = collect_jobs(video)
    manifest = convert_collection(jobs, tmp_path, LINEAR, progress=False, chunk_frames=6)
    assert len(hashed) == 1                                          # was 2
    assert same_events(read_h5(output), whole) and not folder.exists()
    entry = manifest["videos"]["v"]
    assert entry["status"] == "ok"
    assert entry["source_signature"]["sha256"] == hashlib.sha256(video.read_bytes()).hexdigest()

    check = convert_module._still_signed(entry["source_signature"], video)
    os.utime(video, ns=(video.stat().st_atime_ns, video.stat().st_mtime_ns + 10**9))
    assert check and not convert_module._still_signed(entry["source_signature"], video)


def test_hashing_a_video_shows_a_progress_bar_on_a_first_conversion_and_a_chunked_resume(tmp_path, monkeypatch):
    """A video is read whole to hash it (SHA-256) before its frames: as it is first converted (for the manifest),
    and, when chunks of an interrupted conversion are kept beside its output, before anything is converted (to
    check them). Above HASH_PROGRESS_BYTES (1 GiB; 0 here) a bar [bytes] shows each, its total and count the
    video's bytes (was: no bar, only a frame bar standing at 0 while a multi-GB video was read)."""
    import tqdm.auto

    import cmax.io.window_store

    output, folder, whole = _interrupted(tmp_path, monkeypatch, LINEAR, stop_at=3)
    size = (tmp_path / "v.avi").stat().st_size
    bars = []

    class Recorded(tqdm.auto.tqdm):
        def close(self):
            if not self.disable and not getattr(self, "recorded", False):   # (tqdm may close a bar twice)
                bars.append((self.desc, self.total, self.n))
                self.recorded = True
            super().close()

    monkeypatch.setattr(tqdm.auto, "tqdm", Recorded)
    monkeypatch.setattr(cmax.io.window_store, "HASH_PROGRESS_BYTES", 0)
    jobs, _ = collect_jobs(tmp_path / "v.avi")
    convert_collection(jobs, tmp_path, LINEAR, progress=True, chunk_frames=6)      # continues the kept chunks
    assert [(total, n) for desc, total, n in bars if "hashing" in desc] == [(size, size)]
    assert same_events(read_h5(output), whole) and not folder.exists()
    bars.clear()
    convert_collection(jobs, tmp_path / "fresh", LINEAR, progress=True, chunk_frames=6)    # a first conversion
    assert [(total, n) for desc, total, n in bars if "hashing" in desc] == [(size, size)]
    assert same_events(read_h5(tmp_path / "fresh" / "v.h5"), whole)
