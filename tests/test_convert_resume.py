"""Resuming and stopping a collection (cmax/sim/convert.py): damaged outputs are redone, an interrupt leaves no
temporaries, the manifest names outputs relative to its folder."""
from __future__ import annotations

import json
import os
import signal
import threading
import time

import numpy as np
import pytest

from cmax.io.h5 import read_h5
from cmax.sim.convert import (
    ConvertSettings,
    collect_jobs,
    convert_collection,
    entry_output,
    file_sha256,
    load_manifest,
    output_problem,
)
from test_sim_convert import write_video

cv2 = pytest.importorskip("cv2")
FAST = ConvertSettings(adaptive=False)


def _damage_in_place(path, manifest_entry) -> None:
    """Change one byte of the event data so that size, completion record and event count still pass."""
    data = bytearray(path.read_bytes())
    original = bytes(data)
    for offset in range(len(data) // 2, len(data)):  # a byte the structural checks do not read
        data[offset] ^= 0xFF
        path.write_bytes(bytes(data))
        if output_problem(dict(manifest_entry, sha256=file_sha256(path)), path) is None:
            return
        data[offset] ^= 0xFF
    path.write_bytes(original)
    raise AssertionError("no byte to damage without breaking the file's structure")


def test_a_file_damaged_in_place_is_redone_on_resume(tmp_path):
    write_video(tmp_path / "a.avi")
    jobs, _ = collect_jobs(tmp_path / "a.avi")
    out = tmp_path / "out"
    entry = convert_collection(jobs, out, FAST, progress=False)["videos"]["a"]
    good = (out / "a.h5").read_bytes()
    _damage_in_place(out / "a.h5", entry)
    assert (out / "a.h5").stat().st_size == entry["bytes"] and (out / "a.h5").read_bytes() != good
    assert "SHA-256" in output_problem(entry, out / "a.h5")
    seen = []
    manifest = convert_collection(jobs, out, FAST, progress=False, on_result=lambda r: seen.append(r.name))
    assert seen == ["a"]                                     # not skipped
    assert (out / "a.h5").read_bytes() == good and manifest["videos"]["a"]["status"] == "ok"
    assert manifest["videos"]["a"]["sha256"] == file_sha256(out / "a.h5")
    # An intact file is skipped (its checksum is read, not rewritten).
    seen.clear()
    convert_collection(jobs, out, FAST, progress=False, on_result=lambda r: seen.append(r.name))
    assert seen == []


def test_resume_notes_the_damaged_file(tmp_path, capsys):
    write_video(tmp_path / "a.avi")
    jobs, _ = collect_jobs(tmp_path / "a.avi")
    entry = convert_collection(jobs, tmp_path, FAST, progress=False)["videos"]["a"]
    _damage_in_place(tmp_path / "a.h5", entry)
    capsys.readouterr()
    convert_collection(jobs, tmp_path, FAST, progress=False)
    err = capsys.readouterr().err
    assert "note: a: output not verified" in err and "SHA-256" in err and "converting it again" in err


def test_the_manifest_names_outputs_relative_to_its_folder(tmp_path, monkeypatch):
    write_video(tmp_path / "a.avi")
    monkeypatch.chdir(tmp_path)
    jobs, _ = collect_jobs("a.avi")
    manifest = convert_collection(jobs, "out", FAST, progress=False)
    assert manifest["videos"]["a"]["output"] == "a.h5"
    assert load_manifest(tmp_path / "out" / "manifest.json")["videos"]["a"]["output"] == "a.h5"
    # Old manifests hold the path typed at conversion time: still the file in the manifest's folder.
    for old in ("out/a.h5", str(tmp_path / "out" / "a.h5"), "a.h5"):
        assert entry_output({"output": old}, tmp_path / "moved", relative=False) == tmp_path / "moved" / "a.h5"
        raw = dict(json.loads((tmp_path / "out" / "manifest.json").read_text()))
        raw.pop("output_paths")
        raw["videos"]["a"]["output"] = old                            # as an older version wrote it
        (tmp_path / "moved").mkdir(exist_ok=True)
        (tmp_path / "moved" / "manifest.json").write_text(json.dumps(raw))
        entry = load_manifest(tmp_path / "moved" / "manifest.json")["videos"]["a"]
        assert entry_output(entry, tmp_path / "moved") == tmp_path / "moved" / "a.h5"


def test_an_interrupt_removes_the_temporaries_of_the_workers(tmp_path):
    """Ctrl-C while two workers write: their ``.partial`` and ``.lock`` files are removed (as with one worker)."""
    videos = tmp_path / "videos"
    videos.mkdir()
    for name, shift in (("a", 0), ("b", 3)):   # long enough to be interrupted mid-write
        write_video(videos / f"{name}.avi", n_frames=300, width=160, height=120, shift=shift)
    jobs, _ = collect_jobs(videos)
    out = tmp_path / "out"
    done, sent = threading.Event(), []

    def interrupt_while_writing() -> None:
        deadline = time.monotonic() + 120
        while not done.is_set() and time.monotonic() < deadline:
            if list(out.glob("*.h5.*.partial")):
                time.sleep(0.05)
                if not done.is_set():
                    sent.append(True)
                    os.kill(os.getpid(), signal.SIGINT)
                return
            time.sleep(0.005)

    # a shell that starts the test run in the background leaves SIGINT ignored: Ctrl-C's own handler here
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    watcher = threading.Thread(target=interrupt_while_writing)
    watcher.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            convert_collection(jobs, out, FAST, workers=2, progress=False)
    finally:
        done.set()
        watcher.join()
        signal.signal(signal.SIGINT, previous)
    assert sent
    assert sorted(p.name for p in out.iterdir() if p.suffix in (".partial", ".lock")) == []
    # A resume converts both (nothing was recorded as done) and leaves no temporaries either.
    manifest = convert_collection(jobs, out, FAST, workers=2, progress=False)
    assert manifest["totals"]["ok"] == 2, manifest["videos"]
    assert len(read_h5(out / "a.h5")) == manifest["videos"]["a"]["events"]


def test_an_interrupt_leaves_the_files_of_another_writer_alone(tmp_path, monkeypatch):
    """The clean-up after killed workers takes each output's lock (a live writer's temporaries stay) and is not
    cut short by a second Ctrl-C."""
    from cmax.io.atomic import AtomicOutput
    import cmax.sim.convert as convert

    out = tmp_path / "out"
    out.mkdir()
    other = AtomicOutput(out / "a.h5", overwrite=True)   # another live writer of a.h5
    try:
        calls = []
        real = convert.discard_leftovers

        def discard(path):
            calls.append(os.path.basename(path))
            return real(path)

        monkeypatch.setattr(convert, "discard_leftovers", discard)

        class Process:
            exitcode = None
            pid = None          # gone: a lock still held is another writer's, left at once (no wait)

            def kill(self):
                pass

            def join(self, timeout=None):   # a second Ctrl-C while the workers are stopped
                os.kill(os.getpid(), signal.SIGINT)

        class Receive:
            def close(self):
                pass

        def wait(connections):
            raise KeyboardInterrupt

        monkeypatch.setattr("multiprocessing.connection.wait", wait)

        class Context:
            def Pipe(self, duplex):
                return Receive(), Receive()

            def Process(self, **kwargs):
                process = Process()
                process.start = lambda: None
                return process

        monkeypatch.setattr(convert, "_worker_context", lambda: Context())
        jobs = [convert.VideoJob("a", tmp_path / "a.avi"), convert.VideoJob("b", tmp_path / "b.avi")]
        with pytest.raises(KeyboardInterrupt):
            convert._run_parallel(jobs, out, FAST, 2, False, lambda result: None)
        assert sorted(calls) == [".a.h5.chunks", ".b.h5.chunks", "a.h5", "b.h5"]   # outputs, chunk-folder locks
        assert other.temp.exists() and (out / "a.h5.lock").exists()   # the live writer's files are kept
    finally:
        other.abort()
    assert not list(out.glob("*.partial"))


def test_settings_refuse_an_empty_time_range():
    with pytest.raises(ValueError, match="t1_s must be > 0"):
        ConvertSettings(t1_s=0.0)
    with pytest.raises(ValueError, match="larger than t0_s"):
        ConvertSettings(t0_s=0.2, t1_s=0.1)
    assert ConvertSettings(t1_s=1e-3).t1_s == 1e-3


# -- the source a resume skips is verified too (new-user report item 1) ------------------------------------
def test_a_replaced_source_is_converted_again(tmp_path, capsys):
    write_video(tmp_path / "a.avi", n_frames=8)
    jobs, _ = collect_jobs(tmp_path / "a.avi")
    out = tmp_path / "out"
    old = convert_collection(jobs, out, FAST, progress=False)["videos"]["a"]
    assert old["source_signature"]["bytes"] == (tmp_path / "a.avi").stat().st_size
    write_video(tmp_path / "a.avi", n_frames=14, shift=5)          # the video is replaced, same name
    fresh = convert_collection(collect_jobs(tmp_path / "a.avi")[0], tmp_path / "fresh", FAST, progress=False)
    capsys.readouterr()
    seen = []
    manifest = convert_collection(jobs, out, FAST, progress=False, on_result=lambda r: seen.append(r.name))
    assert seen == ["a"]
    assert "note: a: the source changed since it was converted (a.avi has" in capsys.readouterr().err
    entry = manifest["videos"]["a"]
    assert entry["frames"] == 14 != old["frames"]
    assert entry["events"] == fresh["videos"]["a"]["events"] == len(read_h5(out / "a.h5"))


def test_a_touched_source_and_another_file_of_the_same_name_are_converted_again(tmp_path, capsys):
    (tmp_path / "one").mkdir()
    (tmp_path / "two").mkdir()
    write_video(tmp_path / "one" / "a.avi")
    write_video(tmp_path / "two" / "a.avi", shift=7)
    out = tmp_path / "out"
    convert_collection(collect_jobs(tmp_path / "one" / "a.avi")[0], out, FAST, progress=False)
    seen = []
    stat = (tmp_path / "one" / "a.avi").stat()
    os.utime(tmp_path / "one" / "a.avi", ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))   # re-exported
    capsys.readouterr()
    convert_collection(collect_jobs(tmp_path / "one" / "a.avi")[0], out, FAST, progress=False,
                       on_result=lambda r: seen.append(r.name))
    assert seen == ["a"] and "was modified after it was converted" in capsys.readouterr().err
    manifest = convert_collection(collect_jobs(tmp_path / "two" / "a.avi")[0], out, FAST, progress=False,
                                  on_result=lambda r: seen.append(r.name))
    assert seen == ["a", "a"] and f"it was {tmp_path / 'one' / 'a.avi'}" in capsys.readouterr().err
    assert manifest["videos"]["a"]["source"] == str(tmp_path / "two" / "a.avi")
    # unchanged: skipped
    convert_collection(collect_jobs(tmp_path / "two" / "a.avi")[0], out, FAST, progress=False,
                       on_result=lambda r: seen.append(r.name))
    assert seen == ["a", "a"]


def test_an_old_manifest_without_a_signature_compares_the_source_path(tmp_path, capsys):
    (tmp_path / "other").mkdir()
    write_video(tmp_path / "a.avi")
    write_video(tmp_path / "other" / "a.avi", shift=7)
    out = tmp_path / "out"
    manifest = convert_collection(collect_jobs(tmp_path / "a.avi")[0], out, FAST, progress=False)
    del manifest["videos"]["a"]["source_signature"]                   # as an earlier version wrote it
    (out / "manifest.json").write_text(json.dumps(manifest))
    seen = []
    convert_collection(collect_jobs(tmp_path / "a.avi")[0], out, FAST, progress=False,
                       on_result=lambda r: seen.append(r.name))
    assert seen == []                                                 # the same path: skipped
    capsys.readouterr()
    convert_collection(collect_jobs(tmp_path / "other" / "a.avi")[0], out, FAST, progress=False,
                       on_result=lambda r: seen.append(r.name))
    assert seen == ["a"] and "it was converted from" in capsys.readouterr().err


def test_the_signature_of_an_image_sequence_covers_its_images_and_times(tmp_path):
    from cmax.sim.signature import signature_problem, source_signature

    folder = tmp_path / "seq"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i:03d}.png"), np.full((8, 8), 40 * i, np.uint8))
    (folder / "timestamps.txt").write_text("0.0\n0.04\n0.08\n")
    before = source_signature(folder)
    assert before["files"] == 4 and source_signature(folder / "timestamps.txt")["files"] == 4
    cv2.imwrite(str(folder / "001.png"), np.full((8, 8), 41, np.uint8))   # one image re-exported
    os.utime(folder / "001.png", ns=(0, before["mtime_ns"] + 1))
    assert signature_problem(before, source_signature(folder)) is not None
    cv2.imwrite(str(folder / "003.png"), np.zeros((8, 8), np.uint8))       # one more image and time
    (folder / "timestamps.txt").write_text("0.0\n0.04\n0.08\n0.12\n")
    assert "seq has 5 files, it had 4" in signature_problem(before, source_signature(folder))


# -- merged manifests name outputs in sub-folders (new-user report item 3) ----------------------------------
def test_entry_output_honours_sub_paths_and_refuses_paths_out_of_the_folder(tmp_path):
    assert entry_output({"output": "shard0/a.h5"}, tmp_path) == tmp_path / "shard0" / "a.h5"
    for bad in ("../a.h5", "shard0/../../a.h5", str(tmp_path / "a.h5")):
        with pytest.raises(ValueError, match="not a path inside the manifest's folder"):
            entry_output({"output": bad}, tmp_path)


def test_a_resume_into_the_folder_of_merged_shards_converts_nothing_again(tmp_path, capsys):
    from cmax.cli import main

    videos = tmp_path / "slowtv"
    videos.mkdir()
    for name, shift in (("00000", 0), ("00001", 3), ("00003", 6)):
        write_video(videos / f"{name}.avi", shift=shift)
    evt = tmp_path / "evt"
    for i in range(2):
        assert main(["simulate", "--catalogue", "slowtv", str(videos), "-o", str(evt / f"shard{i}"),
                     "--shard", f"{i}/2", "--no-adaptive", "--quiet"]) == 0
    shards = sorted(str(p) for p in evt.glob("shard*/manifest.json"))
    assert main(["manifest", "merge", *shards, "-o", str(evt / "manifest.json")]) == 0
    merged = load_manifest(evt / "manifest.json")
    assert {name: entry["output"] for name, entry in merged["videos"].items()} == {
        "00000": "shard0/00000.h5", "00001": "shard1/00001.h5", "00003": "shard1/00003.h5"}
    capsys.readouterr()
    assert main(["simulate", "--catalogue", "slowtv", str(videos), "-o", str(evt), "--no-adaptive", "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "not verified" not in captured.err and not list(evt.glob("*.h5"))
    assert captured.out.count("already converted") == 3 and f"{evt / 'shard1' / '00003.h5'}: already" in captured.out
    assert load_manifest(evt / "manifest.json")["videos"]["00001"]["output"] == "shard1/00001.h5"
    # A merged manifest written outside the shards' folders is refused (its outputs could not be found from it).
    assert main(["manifest", "merge", *shards, "-o", str(tmp_path / "elsewhere" / "manifest.json")]) == 2
    assert "lie outside" in capsys.readouterr().err


def test_a_moved_source_is_not_converted_again(tmp_path, capsys):
    """A collection moved to another folder or disk (``mv`` keeps sizes and times) keeps its signature: the
    resume verifies and skips it instead of converting hours of video again."""
    (tmp_path / "here").mkdir()
    write_video(tmp_path / "here" / "a.avi")
    out = tmp_path / "out"
    convert_collection(collect_jobs(tmp_path / "here" / "a.avi")[0], out, FAST, progress=False)
    os.rename(tmp_path / "here", tmp_path / "there")
    seen = []
    convert_collection(collect_jobs(tmp_path / "there" / "a.avi")[0], out, FAST, progress=False,
                       on_result=lambda r: seen.append(r.name))
    assert seen == [] and "converting it again" not in capsys.readouterr().err


def test_a_stopped_worker_s_lock_is_waited_for_only_while_the_worker_exists(tmp_path):
    """The clean-up after a stopped worker retries while process ``pid`` still exists (a killed worker can
    still hold its output's lock when ``join`` returns) and gives up at ``wait_s``; once that process is gone,
    a lock still held is another live writer's: left at once, its files kept."""
    import subprocess
    import sys
    import time

    from cmax.io.atomic import AtomicOutput
    import cmax.sim.convert as convert

    out = tmp_path / "a.h5"
    other = AtomicOutput(out, overwrite=True)          # the live writer that holds the lock throughout
    try:
        start = time.monotonic()
        convert._discard_after_stop(out, os.getpid(), wait_s=0.3)     # "the worker" exists: waited for
        waited = time.monotonic() - start
        gone = subprocess.Popen([sys.executable, "-c", "pass"])
        gone.wait()
        start = time.monotonic()
        convert._discard_after_stop(out, gone.pid, wait_s=5.0)         # gone: another writer's lock
        assert 0.3 <= waited < 3.0 and time.monotonic() - start < 0.25
        assert other.temp.exists() and (tmp_path / "a.h5.lock").exists()
    finally:
        other.abort()


def test_a_source_deleted_after_its_conversion_keeps_its_verified_output_ok(tmp_path, capsys):
    """Sources are often deleted once converted (disk space): a rerun of the list marked the intact output
    `failed` (`video not found`), exit 1, and the totals lost its events; the output stays `ok` once verified."""
    write_video(tmp_path / "a.avi")
    write_video(tmp_path / "b.avi", shift=3)
    (tmp_path / "list.txt").write_text("a.avi\nb.avi\n")
    out = tmp_path / "out"
    first = convert_collection(collect_jobs(tmp_path / "list.txt")[0], out, FAST, progress=False)
    (tmp_path / "a.avi").unlink()
    capsys.readouterr()
    again = convert_collection(collect_jobs(tmp_path / "list.txt")[0], out, FAST, progress=False)
    assert again["videos"]["a"] == first["videos"]["a"] and again["totals"] == first["totals"]
    assert "a: its source" in capsys.readouterr().err
    (out / "a.h5").write_bytes(b"damaged")                  # not verified, and nothing to convert it from
    damaged = convert_collection(collect_jobs(tmp_path / "list.txt")[0], out, FAST, progress=False)
    assert damaged["videos"]["a"]["status"] == "failed"


def test_a_source_replaced_by_one_of_the_same_size_and_mtime_is_converted_again(tmp_path, capsys):
    """A converted video replaced by another of the same size, its modification time set back (``cp -p``, a
    re-download keeping the server's time): the manifest entry's signature (files, bytes, mtime) passed, and the
    rerun skipped it as ``ok``: the manifest and the output held the old video's events under the new video's name
    (was). The signature holds the SHA-256 of the source's bytes: the video is converted again, and its output
    equals a fresh conversion of the new video."""
    videos, scratch, out = tmp_path / "videos", tmp_path / "scratch", tmp_path / "out"
    videos.mkdir(), scratch.mkdir()
    write_video(scratch / "old.avi", n_frames=10)
    write_video(scratch / "new.avi", n_frames=10, shift=4)
    old, new = (scratch / "old.avi").read_bytes(), (scratch / "new.avi").read_bytes()
    size = max(len(old), len(new))
    (videos / "v.avi").write_bytes(old + bytes(size - len(old)))      # padded after the end: both of one size
    (scratch / "new.avi").write_bytes(new + bytes(size - len(new)))
    jobs, _ = collect_jobs(videos)
    convert_collection(jobs, out, FAST, progress=False)
    before = (videos / "v.avi").stat()
    (videos / "v.avi").write_bytes((scratch / "new.avi").read_bytes())
    os.utime(videos / "v.avi", ns=(before.st_atime_ns, before.st_mtime_ns))
    assert (videos / "v.avi").stat().st_size == before.st_size
    fresh = convert_collection(*collect_jobs(scratch)[:1], tmp_path / "fresh", FAST, progress=False)
    old_events, new_events = read_h5(tmp_path / "fresh" / "old.h5"), read_h5(tmp_path / "fresh" / "new.h5")
    assert len(old_events) != len(new_events) or not np.array_equal(old_events.x, new_events.x)   # not vacuous
    capsys.readouterr()
    manifest = convert_collection(jobs, out, FAST, progress=False)
    err = capsys.readouterr().err
    assert "v: the source changed since it was converted (v.avi holds other bytes than it did" in err
    np.testing.assert_array_equal(read_h5(out / "v.h5").x, read_h5(tmp_path / "fresh" / "new.h5").x)
    np.testing.assert_array_equal(read_h5(out / "v.h5").t, read_h5(tmp_path / "fresh" / "new.h5").t)
    assert manifest["videos"]["v"]["events"] == fresh["videos"]["new"]["events"]


def test_the_rerun_s_hashing_of_sources_and_outputs_shows_a_progress_bar(tmp_path, monkeypatch):
    """A rerun of a converted folder reads every converted video's source and output to hash them (SHA-256) before
    any video bar appears: a bar [bytes] shows that reading (above HASH_PROGRESS_BYTES, 1 GiB; 0 here); its total
    and what it counted are the bytes of the source and of the output (was: no bar, minutes of silence for a
    catalogue of multi-GB videos)."""
    import tqdm.auto

    import cmax.io.window_store

    write_video(tmp_path / "a.avi")
    jobs, _ = collect_jobs(tmp_path / "a.avi")
    out = tmp_path / "out"
    convert_collection(jobs, out, FAST, progress=False)
    bars = {}

    class Recorded(tqdm.auto.tqdm):
        def close(self):
            bars[id(self)] = (self.desc, self.total, self.n)     # (tqdm may close a bar twice)
            super().close()

    monkeypatch.setattr(tqdm.auto, "tqdm", Recorded)
    monkeypatch.setattr(cmax.io.window_store, "HASH_PROGRESS_BYTES", 0)
    seen = []
    convert_collection(jobs, out, FAST, progress=True, on_result=lambda r: seen.append(r.name))
    assert seen == []                                                       # verified and skipped
    expected = (tmp_path / "a.avi").stat().st_size + (out / "a.h5").stat().st_size
    assert [(total, n) for desc, total, n in bars.values() if desc.startswith("verifying")] == [(expected, expected)]


@pytest.mark.parametrize("which", ["input", "source"])
def test_a_file_that_grows_while_it_is_hashed_is_refused(tmp_path, which):
    """An input of cmax fit / depth (file_signature) or a video of cmax simulate (source_signature) that is still
    being written or copied: bytes appended after the first 4 MiB block was hashed. Refused naming the file (was:
    a signature of the size before and the SHA-256 of more bytes, bytes the file never held whole, recorded for
    --resume and the manifest without a word)."""
    from cmax.io.window_store import file_signature
    from cmax.sim.signature import source_signature

    path = tmp_path / ("rec.h5" if which == "input" else "clip.mp4")
    path.write_bytes(bytes(5 << 20))                                 # two blocks of file_sha256

    def grow(_bytes: int) -> None:
        if path.stat().st_size == 5 << 20:
            with open(path, "ab") as file:
                file.write(b"more events")

    sign = file_signature if which == "input" else source_signature
    with pytest.raises(ValueError, match=f"{path.name} changed while it was read to hash it: it has "
                                         f"{(5 << 20) + 11:,} bytes \\(had {5 << 20:,}\\)"):
        sign(path, grow)
    assert sign(path)["bytes"] == (5 << 20) + 11                      # complete now: hashed as it is


@pytest.mark.parametrize("chunk_frames", [None, 4])
def test_a_file_put_at_a_pending_video_s_output_during_the_run_is_not_replaced(tmp_path, chunk_frames):
    """A file that appears at ``out/b.h5`` after the conversion checked its outputs (a user's copy, another
    program's output, written while ``a`` converts) (was: replaced by b's events without ``overwrite``, the run
    reporting ``ok``): b fails naming the file, which keeps its bytes; the rerun refuses it as any unlisted file;
    with ``overwrite`` it is replaced."""
    videos, out = tmp_path / "videos", tmp_path / "out"
    videos.mkdir()
    write_video(videos / "a.avi")
    write_video(videos / "b.avi", shift=5)
    jobs, _ = collect_jobs(videos)

    def plant(result) -> None:
        if result.name == "a":
            (out / "b.h5").write_bytes(b"the user's own file\n")

    manifest = convert_collection(jobs, out, FAST, progress=False, on_result=plant, chunk_frames=chunk_frames)
    assert manifest["videos"]["a"]["status"] == "ok" and manifest["videos"]["b"]["status"] == "failed"
    assert "out/b.h5 appeared after this conversion checked its outputs" in manifest["videos"]["b"]["error"]
    assert (out / "b.h5").read_bytes() == b"the user's own file\n"
    assert not [p.name for p in out.iterdir() if p.name.endswith((".partial", ".lock"))]
    with pytest.raises(FileExistsError, match="1 output file.s. already exist in .* b.h5"):
        convert_collection(jobs, out, FAST, progress=False, chunk_frames=chunk_frames)
    manifest = convert_collection(jobs, out, FAST, progress=False, overwrite=True, chunk_frames=chunk_frames)
    entry = manifest["videos"]["b"]
    assert entry["status"] == "ok" and len(read_h5(out / "b.h5")) == entry["events"] > 0
