"""``cmax simulate`` of one input: manifest and progress like the folder mode, image folders, empty results;
``cmax manifest merge`` of manifests that list a video twice."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from cmax.cli import main
from cmax.io import read
from cmax.sim.convert import ConvertSettings, convert_video, load_manifest
from cmax.sim.video import ArraySource
from test_sim_convert import write_video

cv2 = pytest.importorskip("cv2")
FAST = ["--no-adaptive"]


def test_one_video_writes_its_manifest_and_shows_progress(tmp_path, capsys):
    write_video(tmp_path / "clip.avi")
    out = tmp_path / "out" / "clip.h5"
    assert main(["simulate", str(tmp_path / "clip.avi"), "-o", str(out), *FAST]) == 0
    captured = capsys.readouterr()
    assert "frame" in captured.err                    # the per-video tqdm bar
    manifest = load_manifest(out.parent / "manifest.json")
    entry = manifest["videos"]["clip"]
    expected = convert_video(tmp_path / "clip.avi", tmp_path / "ref.h5", ConvertSettings(adaptive=False))
    assert entry["status"] == "ok" and entry["events"] == expected.events == len(read(out)) > 0
    assert entry["frames"] == 8 and f"{expected.events:,} events from 8 frames" in captured.out
    # A rerun resumes (the manifest says it is done): the file is left alone.
    mtime = os.stat(out).st_mtime_ns
    assert main(["simulate", str(tmp_path / "clip.avi"), "-o", str(out), *FAST, "--quiet"]) == 0
    assert os.stat(out).st_mtime_ns == mtime
    # --overwrite redoes it.
    assert main(["simulate", str(tmp_path / "clip.avi"), "-o", str(out), *FAST, "--quiet", "--overwrite"]) == 0
    assert os.stat(out).st_mtime_ns != mtime and len(read(out)) == expected.events


def test_a_foreign_file_under_the_output_name_is_not_replaced(tmp_path, capsys):
    write_video(tmp_path / "clip.avi")
    (tmp_path / "clip.h5").write_bytes(b"precious")
    assert main(["simulate", str(tmp_path / "clip.avi"), "-o", str(tmp_path / "clip.h5"), *FAST]) == 2
    assert "pass --overwrite" in capsys.readouterr().err
    assert (tmp_path / "clip.h5").read_bytes() == b"precious"


def test_a_folder_conversion_refuses_files_its_manifest_does_not_list(tmp_path, capsys):
    """A user's own a.h5 (real events beside a.avi) and an unrelated b.h5 in -o (was: both replaced by the
    conversions of a.avi and b.avi without --overwrite, exit 0): refused before any work, naming them, exit 2;
    --overwrite replaces them; the outputs the manifest then lists are resumed or redone without it."""
    videos, out = tmp_path / "videos", tmp_path / "out"
    videos.mkdir()
    out.mkdir()
    for name in "abc":
        write_video(videos / f"{name}.avi")
    (out / "a.h5").write_bytes(b"real events")
    (out / "b.h5").write_bytes(b"user text")
    base = ["simulate", str(videos), "-o", str(out), *FAST, "--quiet"]
    assert main(base) == 2
    err = capsys.readouterr().err
    assert "2 output file(s) already exist" in err and "a.h5, b.h5" in err and "pass --overwrite" in err
    assert len(err.strip().splitlines()) == 1
    assert (out / "a.h5").read_bytes() == b"real events" and (out / "b.h5").read_bytes() == b"user text"
    assert sorted(p.name for p in out.iterdir()) == ["a.h5", "b.h5"]      # no c.h5, no manifest: nothing done
    assert main([*base, "--overwrite"]) == 0
    manifest = load_manifest(out / "manifest.json")
    assert all(manifest["videos"][name]["status"] == "ok" for name in "abc") and len(read(out / "a.h5")) > 0
    # listed outputs keep the resume's behaviour: one damaged in place is redone without --overwrite
    (out / "b.h5").write_bytes(b"damaged")
    assert main(base) == 0
    assert "output not verified" in capsys.readouterr().err and len(read(out / "b.h5")) > 0


def test_a_video_without_events_says_so_and_exits_1(tmp_path, capsys):
    write_video(tmp_path / "still.avi", n_frames=1)
    assert main(["simulate", str(tmp_path / "still.avi"), "-o", str(tmp_path / "still.h5"), *FAST, "--quiet"]) == 1
    captured = capsys.readouterr()
    assert "no events from still: 1 frame(s)" in captured.err
    assert "this run: converted 1 video (0 events), 0 skipped (done before, verified), 0 failed, 1 with no events; " \
        f"{tmp_path / 'manifest.json'} holds 1 video ok" in captured.out
    assert load_manifest(tmp_path / "manifest.json")["videos"]["still"]["events"] == 0


def _frames(n: int = 6, width: int = 40, height: int = 30) -> np.ndarray:
    y, x = np.mgrid[0:height, 0:width]
    return np.stack([(128 + 90 * np.sin(0.3 * (x - 2 * k)) * np.cos(0.2 * y)).astype(np.uint8) for k in range(n)])


def _expected_events(frames: np.ndarray, times_us: np.ndarray, tmp_path) -> int:
    result = convert_video("frames", tmp_path / "expected.h5", ConvertSettings(adaptive=False),
                           frames=ArraySource(frames, times_us, dtype=np.uint8))
    return result.events


@pytest.mark.parametrize("layout", ["ecd", "ecd-file", "ecd-images", "rpg", "rpg-file", "rpg-images",
                                    "vid2e", "vid2e-file"])
def test_image_folders_are_accepted_as_input(tmp_path, capsys, layout):
    """rpg_vid2e's upsampler writes imgs/ + timestamps.txt (was: 'folder seq holds no videos')."""
    frames = _frames()
    times_us = np.arange(len(frames), dtype=np.int64) * 40_000 + 1_000_000
    seq = tmp_path / "seq"
    images = "imgs" if layout.startswith("vid2e") else "images"
    (seq / images).mkdir(parents=True)
    for k, frame in enumerate(frames):
        cv2.imwrite(str(seq / images / f"frame_{k:08d}.png"), frame)
    if layout.startswith("ecd"):   # ECD: images.txt with "t images/frame_XXXXXXXX.png"
        (seq / "images.txt").write_text("".join(f"{t * 1e-6:.6f} images/frame_{k:08d}.png\n"
                                                for k, t in enumerate(times_us)))
        source = {"ecd": seq, "ecd-file": seq / "images.txt", "ecd-images": seq / "images"}[layout]
    else:                          # rpg_vid2e / ESIM: images/ and timestamps.txt (seconds, one per image)
        (seq / "timestamps.txt").write_text("".join(f"{t * 1e-6:.6f}\n" for t in times_us))
        source = {"rpg": seq, "rpg-file": seq / "timestamps.txt", "rpg-images": seq / "images",
                  "vid2e": seq, "vid2e-file": seq / "timestamps.txt"}[layout]
    out = tmp_path / "events" / "seq.h5"
    assert main(["simulate", str(source), "-o", str(out), *FAST, "--quiet"]) == 0
    events = read(out)
    assert len(events) == _expected_events(frames, times_us, tmp_path) > 0
    assert load_manifest(out.parent / "manifest.json")["videos"]["seq"]["frames"] == len(frames)
    assert (events.width, events.height) == (40, 30)


def test_an_image_folder_needs_an_h5_output(tmp_path, capsys):
    seq = tmp_path / "seq"
    seq.mkdir()
    cv2.imwrite(str(seq / "a.png"), _frames(1)[0])
    (seq / "timestamps.txt").write_text("0.0\n")
    assert main(["simulate", str(seq), "-o", str(tmp_path / "outdir")]) == 2
    assert "image folder (one sequence)" in capsys.readouterr().err


def test_t0_t1_cut_an_image_folder_as_they_cut_a_video(tmp_path, capsys):
    """--t0/--t1 on an image folder (they failed the conversion: 't0_s/t1_s apply to video files only'): the
    frames with t0 <= t < t1 on the timestamps' clock, the same events as converting those frames alone."""
    frames = _frames(8)
    times_us = np.arange(8, dtype=np.int64) * 40_000                     # 0, 40, ..., 280 ms
    seq = tmp_path / "seq"
    (seq / "images").mkdir(parents=True)
    for k, frame in enumerate(frames):
        cv2.imwrite(str(seq / "images" / f"frame_{k:08d}.png"), frame)
    (seq / "timestamps.txt").write_text("".join(f"{t * 1e-6:.6f}\n" for t in times_us))
    out = tmp_path / "events" / "seq.h5"
    assert main(["simulate", str(seq), "-o", str(out), *FAST, "--t0", "0.07", "--t1", "0.2", "--quiet"]) == 0
    kept = (times_us >= 70_000) & (times_us < 200_000)                    # frames 2, 3, 4
    assert len(read(out)) == _expected_events(frames[kept], times_us[kept], tmp_path) > 0
    assert load_manifest(out.parent / "manifest.json")["videos"]["seq"]["frames"] == 3


@pytest.mark.parametrize("start_s", [0.0, 1_700_000_000.0])
def test_t0_t1_count_from_the_first_image_whatever_the_clock(tmp_path, capsys, start_s):
    """--t0/--t1 are seconds after the first frame (the help's "seconds into each video"), for timestamps on an
    absolute clock too (ROS/DSEC exports: --t0 0.1 kept every image, and --t1 found none)."""
    frames = _frames(8)
    times_us = np.arange(8, dtype=np.int64) * 40_000 + int(start_s * 1e6)
    seq = tmp_path / "seq"
    seq.mkdir()
    for k, frame in enumerate(frames):
        cv2.imwrite(str(seq / f"{k:03d}.png"), frame)
    (seq / "timestamps.txt").write_text("".join(f"{t * 1e-6:.6f}\n" for t in times_us))
    out = tmp_path / "events" / "seq.h5"
    assert main(["simulate", str(seq), "-o", str(out), *FAST, "--t0", "0.1", "--quiet"]) == 0
    kept = times_us - times_us[0] >= 100_000                              # frames 3..7
    assert load_manifest(out.parent / "manifest.json")["videos"]["seq"]["frames"] == 5
    assert len(read(out)) == _expected_events(frames[kept], times_us[kept], tmp_path) > 0
    capsys.readouterr()
    assert main(["simulate", str(seq), "-o", str(tmp_path / "none.h5"), *FAST, "--t0", "2", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "no images from 2.0 s after the first frame to the end (zero frames)" in err and "span 0.280000 s" in err
    assert ("they start at 1700000000.000000 s" in err) == bool(start_s)


def test_an_image_folder_without_times_says_how_to_write_them(tmp_path, capsys):
    """Frames extracted by ffmpeg (no timestamp file): one line that says so (it said 'holds no videos') and
    gives a command whose timestamps.txt the conversion then reads, at 25 frames/s."""
    import subprocess
    import sys

    from conftest import one_line_error

    seq = tmp_path / "frames"
    seq.mkdir()
    frames = _frames(6)
    for k, frame in enumerate(frames):
        cv2.imwrite(str(seq / f"{k:04d}.png"), frame)
    out = tmp_path / "events" / "frames.h5"
    status, err = one_line_error(lambda: main(["simulate", str(seq), "-o", str(out), *FAST, "--quiet"]), capsys)
    assert status == 2 and "holds 6 images but no times for them: write timestamps.txt beside them" in err
    command = err.split("25 frames/s: ")[1].strip()           # run by a shell, as the user would
    assert command.startswith("python -c ") and command.endswith(f"> {seq / 'timestamps.txt'}")
    subprocess.run(command.replace("python", f'"{sys.executable}"', 1), shell=True, check=True)
    assert main(["simulate", str(seq), "-o", str(out), *FAST, "--quiet"]) == 0
    times_us = np.arange(6, dtype=np.int64) * 40_000
    assert len(read(out)) == _expected_events(frames, times_us, tmp_path) > 0


def _manifest(tmp_path, name: str, videos: dict) -> str:
    base = {"format": "evtslowtv-manifest/1", "simulator": "cmax 1", "settings": {"s": 1}, "catalogue": None,
            "missing": [], "videos": videos}
    (tmp_path / name).write_text(json.dumps(base))
    return str(tmp_path / name)


def _entry(status: str, events: int = 0, output: str = "a.h5") -> dict:
    return {"name": "a", "status": status, "events": events, "frames": 2, "duration_s": 0.1, "output": output,
            "wall_s": 1.0, "error": None if status == "ok" else "boom"}


def test_merge_reports_a_video_listed_twice_and_keeps_its_ok_entry(tmp_path, capsys):
    one = _manifest(tmp_path, "one.json", {"a": _entry("failed")})
    two = _manifest(tmp_path, "two.json", {"a": _entry("ok", 10), "b": _entry("ok", 5, "b.h5")})
    assert main(["manifest", "merge", one, two, "-o", str(tmp_path / "all.json")]) == 0
    captured = capsys.readouterr()
    assert "listed more than once: a: failed in" in captured.err and "kept the entry of" in captured.err
    assert "1 listed more than once" in captured.out
    merged = json.loads((tmp_path / "all.json").read_text())
    assert merged["videos"]["a"]["status"] == "ok" and merged["totals"]["events"] == 15


def test_merge_refuses_two_different_conversions_of_one_video(tmp_path, capsys):
    one = _manifest(tmp_path, "one.json", {"a": _entry("ok", 10)})
    two = _manifest(tmp_path, "two.json", {"a": _entry("ok", 11)})
    assert main(["manifest", "merge", one, two, "-o", str(tmp_path / "all.json")]) == 2
    err = capsys.readouterr().err
    assert "converted differently in several manifests: a (ok in" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "all.json").exists()
    # The same manifest twice (same entries) is not a conflict.
    assert main(["manifest", "merge", one, one, "-o", str(tmp_path / "all.json")]) == 0


def test_merge_refuses_an_existing_output_and_a_folder_being_converted(tmp_path, capsys):
    """merge -o onto an existing manifest (was: replaced without --overwrite, its videos' records gone) is refused
    unless --overwrite; a merge into a folder whose conversion lock is held (was: written meanwhile, then lost or
    erasing the conversion's records) is refused at once; both change nothing."""
    from cmax.io.atomic import PathLock

    one = _manifest(tmp_path, "one.json", {"a": _entry("ok", 10)})
    two = _manifest(tmp_path, "two.json", {"b": _entry("ok", 5, "b.h5")})
    out = tmp_path / "manifest.json"
    assert main(["manifest", "merge", one, "-o", str(out)]) == 0
    before = out.read_bytes()
    assert main(["manifest", "merge", two, "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "manifest.json exists: pass --overwrite" in err and len(err.strip().splitlines()) == 1
    assert out.read_bytes() == before
    with PathLock(tmp_path / ".conversion.lock", tmp_path):    # what convert_collection holds on its folder
        assert main(["manifest", "merge", str(out), two, "-o", str(out), "--overwrite"]) == 2
        assert "being written by another writer (lock .conversion.lock held)" in capsys.readouterr().err
        assert main(["manifest", "merge", two, "-o", str(tmp_path / "other.json")]) == 2
    assert out.read_bytes() == before and not (tmp_path / "other.json").exists()
    assert main(["manifest", "merge", str(out), two, "-o", str(out), "--overwrite"]) == 0
    assert sorted(json.loads(out.read_text())["videos"]) == ["a", "b"]


def test_overwrite_keeps_the_old_file_when_the_new_conversion_fails(tmp_path, capsys):
    write_video(tmp_path / "clip.avi")
    out = tmp_path / "clip.h5"
    assert main(["simulate", str(tmp_path / "clip.avi"), "-o", str(out), *FAST, "--quiet"]) == 0
    before = out.read_bytes()
    (tmp_path / "clip.avi").write_bytes(b"not a video any more")
    assert main(["simulate", str(tmp_path / "clip.avi"), "-o", str(out), *FAST, "--quiet", "--overwrite"]) == 1
    assert "failed clip:" in capsys.readouterr().err
    assert out.read_bytes() == before and not list(tmp_path.glob("*.partial"))
    assert load_manifest(tmp_path / "manifest.json")["videos"]["clip"]["status"] == "failed"


def test_an_earlier_failure_in_the_same_folder_does_not_fail_the_next_video(tmp_path, capsys):
    """Single-file conversions into one folder share its manifest: a video that failed before is reported in
    one line, but the status is this run's (0 for a good video, 1 again for the failed one)."""
    (tmp_path / "broken.avi").write_bytes(b"not a video")
    assert main(["simulate", str(tmp_path / "broken.avi"), "-o", str(tmp_path / "broken.h5"), *FAST, "--quiet"]) == 1
    capsys.readouterr()
    write_video(tmp_path / "clip.avi")
    assert main(["simulate", str(tmp_path / "clip.avi"), "-o", str(tmp_path / "clip.h5"), *FAST, "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "failed broken:" not in err and "1 other video(s) of manifest.json failed in earlier runs: broken" in err
    assert main(["simulate", str(tmp_path / "broken.avi"), "-o", str(tmp_path / "broken.h5"), *FAST, "--quiet"]) == 1


def test_a_refused_overwrite_keeps_the_manifest_entry(tmp_path, capsys):
    """--overwrite refused (other settings, or the folder locked by another writer) changes nothing: the plain
    rerun still resumes the finished file."""
    from cmax.io.atomic import PathLock

    write_video(tmp_path / "clip.avi")
    out = tmp_path / "out" / "clip.h5"
    base = ["simulate", str(tmp_path / "clip.avi"), "-o", str(out), *FAST, "--quiet"]
    assert main(base) == 0
    before = (out.parent / "manifest.json").read_bytes()
    assert main([*base, "--overwrite", "--cp", "0.3"]) == 2
    assert "other settings" in capsys.readouterr().err
    assert (out.parent / "manifest.json").read_bytes() == before
    with PathLock(out.parent / ".conversion.lock", out.parent):
        assert main([*base, "--overwrite"]) == 2
        assert "nothing was changed" in capsys.readouterr().err
    assert (out.parent / "manifest.json").read_bytes() == before
    mtime = os.stat(out).st_mtime_ns
    assert main(base) == 0 and os.stat(out).st_mtime_ns == mtime      # resumed, not refused
    assert main([*base, "--overwrite"]) == 0 and os.stat(out).st_mtime_ns != mtime


def test_outputs_are_printed_relative_to_the_output_folder(tmp_path, monkeypatch, capsys):
    """The manifest stores the output's name; a rerun from another folder, or of a moved folder, prints where
    the file is now (old manifests holding the typed path are still read)."""
    write_video(tmp_path / "clip.avi")
    video = str(tmp_path / "clip.avi")
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", video, "-o", "out/clip.h5", *FAST, "--quiet"]) == 0
    assert "  out/clip.h5: " in capsys.readouterr().out
    assert load_manifest(tmp_path / "out" / "manifest.json")["videos"]["clip"]["output"] == "clip.h5"
    monkeypatch.chdir(tmp_path / "out")
    assert main(["simulate", video, "-o", "clip.h5", *FAST, "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "\n  clip.h5: " in printed and "out/clip.h5" not in printed
    monkeypatch.chdir(tmp_path)
    (tmp_path / "out").rename(tmp_path / "moved")
    manifest_path = tmp_path / "moved" / "manifest.json"
    old = json.loads(manifest_path.read_text())
    old["videos"]["clip"]["output"] = "out/clip.h5"          # as written before: the path typed then
    old.pop("output_paths")                                  # (older manifests lack these)
    old["videos"]["clip"].pop("source_signature")
    manifest_path.write_text(json.dumps(old))
    mtime = os.stat(tmp_path / "moved" / "clip.h5").st_mtime_ns
    assert main(["simulate", video, "-o", "moved/clip.h5", *FAST, "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "  moved/clip.h5: " in printed and "out/clip.h5" not in printed
    assert os.stat(tmp_path / "moved" / "clip.h5").st_mtime_ns == mtime


@pytest.mark.parametrize("extra, message", [
    (["--t1", "0"], "argument --t1: expected a finite number > 0, got '0'"),
    (["--t1", "-0.5"], "argument --t1: expected a finite number > 0"),
    (["--t1", "inf"], "argument --t1: expected a finite number > 0"),
    (["--t0", "-1"], "t0_s must be a non-negative number of seconds"),
    (["--t0", "0.2", "--t1", "0.1"], "t1_s (0.1) must be larger than t0_s (0.2)"),
    (["--t0", "0.2", "--t1", "0.2"], "must be larger than t0_s"),
])
def test_an_empty_time_range_is_refused_before_converting(tmp_path, capsys, extra, message):
    from conftest import one_line_error

    write_video(tmp_path / "clip.avi")
    status, err = one_line_error(lambda: main(["simulate", str(tmp_path / "clip.avi"), "-o",
                                               str(tmp_path / "out" / "clip.h5"), *FAST, *extra]), capsys)
    assert status == 2 and message in err, err
    assert not (tmp_path / "out").exists()


def test_a_rerun_says_the_video_was_already_converted_and_redoes_a_replaced_one(tmp_path, capsys):
    write_video(tmp_path / "in.avi", n_frames=8)
    out = tmp_path / "out" / "in.h5"
    args = ["simulate", str(tmp_path / "in.avi"), "-o", str(out), *FAST, "--quiet"]
    assert main(args) == 0
    first = capsys.readouterr().out
    assert "already converted" not in first and "events from 8 frames" in first
    assert main(args) == 0
    assert f"in.h5: already converted from {tmp_path / 'in.avi'} (verified), " in capsys.readouterr().out
    write_video(tmp_path / "in.avi", n_frames=12, shift=4)           # the video is replaced
    assert main(args) == 0
    captured = capsys.readouterr()
    assert "the source changed since it was converted" in captured.err
    assert "already converted" not in captured.out and "events from 12 frames" in captured.out
    assert load_manifest(out.parent / "manifest.json")["videos"]["in"]["frames"] == 12


def test_the_summary_line_says_what_this_run_did_apart_from_what_the_folder_holds(tmp_path, capsys):
    """A second single-video conversion into a folder holding another printed "manifest.json: 2 videos ok, 0
    failed, <both videos' events> events" after converting one (was): the manifest's totals read as this run's.
    The line now says what this run did (converted, skipped, failed, its events), then what the folder holds."""
    write_video(tmp_path / "a.avi", n_frames=8)
    write_video(tmp_path / "b.avi", n_frames=10, shift=3)
    out = tmp_path / "out"
    assert main(["simulate", str(tmp_path / "a.avi"), "-o", str(out / "a.h5"), *FAST, "--quiet"]) == 0
    capsys.readouterr()
    args = ["simulate", str(tmp_path / "b.avi"), "-o", str(out / "b.h5"), *FAST, "--quiet"]
    assert main(args) == 0
    line = capsys.readouterr().out.splitlines()[0]
    n_a, n_b = len(read(out / "a.h5")), len(read(out / "b.h5"))
    assert line == (f"this run: converted 1 video ({n_b:,} events), 0 skipped (done before, verified), 0 failed; "
                    f"{out / 'manifest.json'} holds 2 videos ok, 0 failed, {n_a + n_b:,} events"), line
    assert main(args) == 0     # again: nothing converted, one skipped
    line = capsys.readouterr().out.splitlines()[0]
    assert line.startswith("this run: converted 0 videos (0 events), 1 skipped (done before, verified), 0 failed; ")
    assert line.endswith(f"holds 2 videos ok, 0 failed, {n_a + n_b:,} events"), line


def test_a_catalogue_conversion_that_finds_no_video_exits_1(tmp_path, capsys):
    """A wrong folder or naming (``0.mp4`` for ``00000.mp4``) found none of the catalogue's videos and exited 0
    ('0 videos ok, 0 failed'): in a SLURM array a silent success. Now exit 1, one line, nothing written."""
    folder = tmp_path / "badcat"
    folder.mkdir()
    write_video(folder / "0.avi")
    out = tmp_path / "out"
    assert main(["simulate", "--catalogue", "slowtv", str(folder), "-o", str(out), *FAST, "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "no video to convert: none of the 40 entries of the slowtv catalogue has a video" in err
    assert "holds 1 other video(s): 0.avi" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
    assert main(["simulate", "--catalogue", "slowtv", str(folder), "-o", str(out), "--shard", "3/8", *FAST]) == 1
    assert "none of the 5 entries of the slowtv catalogue (shard 3/8)" in capsys.readouterr().err


@pytest.mark.parametrize("first, step, unit", [(1600000000123456789, 50_000_000, "nanoseconds"),
                                               (1600000000123456, 50_000, "microseconds"),
                                               (1e300, 1e299, "another unit")])
def test_timestamps_too_large_for_seconds_are_refused_naming_the_unit(tmp_path, capsys, first, step, unit):
    """ns (or DSEC-style µs) in timestamps.txt overflowed int64 (numpy 'invalid value encountered in cast', then
    'time 1 (-9223372036854775808 µs) follows time 0'); now refused when read, naming the likely unit."""
    seq = tmp_path / "ns_like"
    seq.mkdir()
    for k, frame in enumerate(_frames(4)):
        cv2.imwrite(str(seq / f"{k:03d}.png"), frame)
    (seq / "timestamps.txt").write_text("".join(f"{first + k * step}\n" for k in range(4)))
    assert main(["simulate", str(seq), "-o", str(tmp_path / "out" / "a.h5"), *FAST, "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "is too large for seconds" in err and f"these look like {unit}" in err
    assert "cast" not in err and "9223372036854775808" not in err
    assert not list((tmp_path / "out").glob("*.h5"))


def test_whole_number_frame_times_far_apart_are_named_as_another_unit(tmp_path, capsys):
    """timestamps.txt of milliseconds since the start (0 33 67 ...) was read as seconds without a word: a video
    of 0.17 s converted as one of 167 s (event times 1000x), exit 0."""
    import warnings

    from cmax.sim.video import read_timestamps

    seq = tmp_path / "dump"
    seq.mkdir()
    for k, frame in enumerate(_frames(6)):
        cv2.imwrite(str(seq / f"{k:03d}.png"), frame)
    (seq / "timestamps.txt").write_text("".join(f"{round(k * 1000 / 30)}\n" for k in range(6)))
    assert main(["simulate", str(seq), "-o", str(tmp_path / "out" / "a.h5"), *FAST, "--quiet"]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert len(lines) == 1 and "timestamps.txt: every time is a whole number, 33 apart" in lines[0]
    assert "the 6 frames span 167 s; if they are milliseconds (0.167 s)" in lines[0]
    with warnings.catch_warnings():  # seconds with decimals, and whole seconds of a 1 fps time-lapse: silent
        warnings.simplefilter("error")
        for text in ("".join(f"{k / 30:.6f}\n" for k in range(6)), "0\n1\n2\n3\n4\n5\n"):
            (seq / "timestamps.txt").write_text(text)
            assert len(read_timestamps(seq / "timestamps.txt")[0]) == 6


def test_a_warning_in_a_worker_process_reaches_the_caller_naming_its_video(tmp_path, capsys):
    """With --workers 2 a worker's warning was printed by the worker in Python's own format (two lines:
    `/.../video.py:511: UserWarning: ...` and the source line), out of reach of the caller's filters."""
    import warnings

    from cmax.sim.convert import collect_jobs, convert_collection

    seq = tmp_path / "dump" / "images"
    seq.mkdir(parents=True)
    for k, frame in enumerate(_frames(4)):
        cv2.imwrite(str(seq / f"{k:03d}.png"), frame)
    (seq / "timestamps.txt").write_text("0\n33\n67\n100\n")
    write_video(tmp_path / "clip.avi")
    (tmp_path / "list.txt").write_text("dump/images\nclip.avi\n")
    jobs, _ = collect_jobs(tmp_path / "list.txt")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        manifest = convert_collection(jobs, tmp_path / "api", ConvertSettings(adaptive=False), workers=2,
                                      progress=False)
    assert [v["status"] for v in manifest["videos"].values()] == ["ok", "ok"]
    messages = [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    assert len(messages) == 1 and messages[0].startswith("images: ") and "whole number, 33 apart" in messages[0]
    capsys.readouterr()
    assert main(["simulate", str(tmp_path / "list.txt"), "-o", str(tmp_path / "cli"), *FAST, "--quiet",
                 "--workers", "2"]) == 0
    err = capsys.readouterr().err.splitlines()
    assert [line for line in err if "warning" in line.lower()] == [
        line for line in err if line.startswith("cmax simulate: warning: images: ")]
    assert len([line for line in err if "warning" in line.lower()]) == 1
    assert not any("UserWarning" in line or "read_timestamps(" in line for line in err)


def test_a_size_of_another_aspect_ratio_is_named_as_a_stretch(tmp_path, capsys):
    """--size 24x32 on a 48x32 video halved the picture across and kept it down, without a word (the
    intrinsics a fit is later given are then anisotropic)."""
    write_video(tmp_path / "clip.avi")  # 48x32
    assert main(["simulate", str(tmp_path / "clip.avi"), "-o", str(tmp_path / "a" / "a.h5"), *FAST, "--quiet",
                 "--size", "24x32"]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert lines == [f"cmax simulate: warning: {tmp_path / 'clip.avi'}: its 48x32 frames are resized to 24x32, by "
                     "0.5 across and 1 down: the picture is stretched (pixels are no longer square: fx scales by 0.5, "
                     "fy by 1); 24x16 (--size) keeps its shape"]
    assert main(["simulate", str(tmp_path / "clip.avi"), "-o", str(tmp_path / "b" / "b.h5"), *FAST, "--quiet",
                 "--size", "24x16"]) == 0
    assert "warning" not in capsys.readouterr().err


def test_non_finite_timestamps_are_refused(tmp_path):
    from cmax.sim.video import read_timestamps

    (tmp_path / "a.png").write_bytes(cv2.imencode(".png", _frames(1)[0])[1].tobytes())
    (tmp_path / "b.png").write_bytes(cv2.imencode(".png", _frames(1)[0])[1].tobytes())
    (tmp_path / "timestamps.txt").write_text("0.0\nnan\n")
    with pytest.raises(ValueError, match=r"time 1 is nan \(times must be finite seconds\)"):
        read_timestamps(tmp_path / "timestamps.txt")


@pytest.mark.parametrize("name", ["clip.hdf5", "CLIP.H5", "clip.HDF5"])
def test_an_hdf5_suffix_other_than_h5_is_refused_not_made_a_folder(tmp_path, capsys, name):
    """-o clip.hdf5 / CLIP.H5 made a FOLDER of that name (the file mode was chosen by the exact suffix .h5)."""
    write_video(tmp_path / "clip.avi")
    for source in (tmp_path / "clip.avi", tmp_path):                  # one video, a folder of videos
        assert main(["simulate", str(source), "-o", str(tmp_path / "o" / name), *FAST, "--quiet"]) == 2
        err = capsys.readouterr().err
        assert "cmax simulate writes .h5 files (manifest entries are NAME.h5): give -o " in err
        assert err.strip().endswith(str(tmp_path / "o" / name[:-len(name.split(".")[-1])]) + "h5")
    assert not (tmp_path / "o").exists()


def test_an_existing_file_as_the_output_folder_is_named_as_such(tmp_path, capsys):
    """`cmax simulate clip.avi -o notes.txt` with notes.txt a file: `cmax simulate: error: File exists: notes.txt`,
    from the folder's mkdir, which reads as a refusal to replace notes.txt rather than a file given for a folder."""
    write_video(tmp_path / "clip.avi")
    (tmp_path / "notes.txt").write_text("mine\n")
    for source in (tmp_path / "clip.avi", tmp_path):                  # one video, a folder of videos
        assert main(["simulate", str(source), "-o", str(tmp_path / "notes.txt"), *FAST, "--quiet"]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"cmax simulate: error: -o {tmp_path / 'notes.txt'} is a file, not a folder: ")
        assert "-o NAME.h5 for one video" in err and err.count("\n") == 1, err
    assert (tmp_path / "notes.txt").read_text() == "mine\n"
    assert not (tmp_path / "manifest.json").exists()


def test_a_folder_at_a_video_s_output_name_is_refused_before_converting_with_or_without_overwrite(tmp_path, capsys):
    """A folder at -o clip.h5 (or at out/a.h5 of a folder run) (was: `exists and is not a finished conversion ...;
    pass --overwrite to replace it`, then with --overwrite the whole video converted, `failed: IsADirectoryError:
    output is a folder`, exit 1, the chunk folder and a failed manifest entry left): refused in one line before
    anything is converted or written, with or without --overwrite; the folder and its content untouched."""
    write_video(tmp_path / "clip.avi")
    videos = tmp_path / "videos"
    videos.mkdir()
    write_video(videos / "a.avi")
    write_video(videos / "b.avi")
    for source, out, folder in ((tmp_path / "clip.avi", tmp_path / "o" / "clip.h5", tmp_path / "o" / "clip.h5"),
                                (videos, tmp_path / "out", tmp_path / "out" / "a.h5")):
        folder.mkdir(parents=True)
        (folder / "mine.txt").write_text("kept\n")
        for extra in ([], ["--overwrite"]):
            assert main(["simulate", str(source), "-o", str(out), *FAST, "--quiet", *extra]) == 2
            err = capsys.readouterr().err
            assert err.startswith("cmax simulate: error: 1 output(s) of this conversion are folders in ")
            assert f": {folder.name}; nothing was converted" in err and err.count("\n") == 1, err
            assert sorted(p.name for p in folder.parent.iterdir()) == [folder.name]   # no manifest, chunks, lock
            assert [p.name for p in folder.iterdir()] == ["mine.txt"]


def test_flow_on_frames_under_32_pixels_is_explained_in_the_commands_words(tmp_path, capsys):
    """'needs frames of at least 32x32 pixels, got (16, 24); use method='linear'' gave (H, W) and the API's
    words, once per video; with --size it is refused before any video is decoded."""
    write_video(tmp_path / "tiny.avi", width=24, height=16)
    assert main(["simulate", str(tmp_path / "tiny.avi"), "-o", str(tmp_path / "t.h5"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "got 24x16 (width x height)" in err and "(cmax simulate: --method linear)" in err
    assert main(["simulate", str(tmp_path), "-o", str(tmp_path / "out"), "--size", "20x20", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == ("cmax simulate: error: --size 20x20 is smaller than the 32x32 pixels that --method flow "
                           "(the default) needs: pass --method linear (or --no-adaptive)")
    assert not (tmp_path / "out").exists()
    assert main(["simulate", str(tmp_path), "-o", str(tmp_path / "out"), "--size", "20x20", "--method", "linear",
                 "--quiet"]) == 0


@pytest.mark.parametrize("workers", ["1", "2"])
def test_a_video_whose_name_is_not_utf8_fails_alone_instead_of_crashing(tmp_path, workers):
    """A video named cl\\xffip.avi (was: OpenCV's VideoCapture segfaulted on the surrogate-escaped name: exit 139
    with --workers 1, the videos after it never converted, no manifest record) fails alone, recorded in the
    manifest with its name's bytes and "rename it"; the others are converted. In a subprocess: a crash must
    fail this test, not end the test run."""
    import subprocess
    import sys

    videos = tmp_path / "videos"
    videos.mkdir()
    write_video(videos / "d.avi")
    bad = os.path.join(os.fsencode(videos), b"cl\xffip.avi")           # sorted before d and e
    try:
        os.rename(os.fsencode(videos / "d.avi"), bad)
    except (OSError, UnicodeError):
        pytest.skip("this file system refuses names that are not UTF-8")
    write_video(videos / "d.avi")
    write_video(videos / "e.avi")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).resolve().parents[1]),
                                                       os.environ.get("PYTHONPATH", "")]))
    done = subprocess.run([sys.executable, "-m", "cmax.cli", "simulate", str(videos), "-o", str(tmp_path / "out"),
                           *FAST, "--quiet", "--workers", workers], capture_output=True, text=True, env=env,
                          timeout=300)
    assert done.returncode == 1, done.stderr
    manifest = load_manifest(tmp_path / "out" / "manifest.json")
    assert {name: entry["status"] for name, entry in manifest["videos"].items()} == {
        "d": "ok", "e": "ok", os.fsdecode(b"cl\xffip"): "failed"}
    error = manifest["videos"][os.fsdecode(b"cl\xffip")]["error"]
    assert "cl\\xffip.avi' has a name that is not valid UTF-8" in error and "rename it" in error
    assert len(read(tmp_path / "out" / "e.h5")) > 0


_NOT_UTF8_SCRIPT = """
import os, sys
from pathlib import Path
from cmax.sim.video import VideoFileSource, _imread
for read in (VideoFileSource, _imread):
    try:
        read(Path(os.fsdecode(sys.argv[1])))
    except ValueError as error:
        print(error)
"""


def test_opencv_is_never_given_a_path_that_is_not_utf8(tmp_path):
    """The video source and the image reader refuse such a path in one line naming its bytes (in a
    subprocess: the old code crashed there)."""
    import subprocess
    import sys

    bad = os.path.join(os.fsencode(tmp_path), b"cl\xffip.jpg")
    try:
        with open(bad, "wb") as file:
            file.write(b"not an image")
    except (OSError, UnicodeError):
        pytest.skip("this file system refuses names that are not UTF-8")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).resolve().parents[1]),
                                                       os.environ.get("PYTHONPATH", "")]))
    done = subprocess.run([sys.executable, "-c", _NOT_UTF8_SCRIPT, bad], capture_output=True, text=True, env=env,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert [line.split(" b'")[0] for line in lines] == ["the video", "the image"]
    assert all("cl\\xffip.jpg' has a name that is not valid UTF-8" in line and line.endswith("rename it")
               for line in lines)


def test_a_conversion_at_another_size_says_how_a_calibration_of_its_frames_scales(tmp_path, capsys):
    """A video converted at --size half its frames': the h5 records the frames' size (source_size), and fit, emvs
    and depth, given no K, say how a K of those frames scales to its pixels (was: only 'give --K', with nothing
    recording that the pixels are not the frames')."""
    import h5py

    write_video(tmp_path / "clip.avi", width=48, height=32)
    out = tmp_path / "out" / "clip.h5"
    assert main(["simulate", str(tmp_path / "clip.avi"), "-o", str(out), *FAST, "--quiet", "--size", "24x16"]) == 0
    with h5py.File(out, "r") as file:
        assert json.loads(file.attrs["source_size"]) == [48, 32]
    (tmp_path / "traj.txt").write_text("0 0 0 0 0 0 0 1\n10 0.1 0 0 0 0 0 1\n")   # TUM, covering the events
    capsys.readouterr()
    scale = "simulated from 48x32 frames resized to 24x16 (--size): a K of those frames scales to fx*0.5, fy*0.5"
    for command in (["fit", str(out), "-o", str(tmp_path / "fit")],
                    ["emvs", str(out), "--poses", str(tmp_path / "traj.txt"), "-o", str(tmp_path / "emvs")],
                    ["depth", str(out), "-o", str(tmp_path / "depth")]):
        assert main(command) == 2
        err = capsys.readouterr().err
        assert "stores no intrinsics (gt/K)" in err and scale in err and err.count("\n") == 1, (command, err)
    # the frames' K, unscaled: its principal point (36, 24) lies off the 24x16 sensor; the same scale is named
    for command in (["fit", str(out), "-o", str(tmp_path / "fit")],
                    ["emvs", str(out), "--poses", str(tmp_path / "traj.txt"), "-o", str(tmp_path / "emvs")],
                    ["depth", str(out), "-o", str(tmp_path / "depth")]):
        assert main([*command, "--K", "60,60,36,24"]) == 2
        err = capsys.readouterr().err
        assert "principal point (36, 24) lies outside the 24x16 image" in err and scale in err, (command, err)
    # at the frames' own size: no scale, but the origin of such a file said
    same = tmp_path / "same" / "clip.h5"
    assert main(["simulate", str(tmp_path / "clip.avi"), "-o", str(same), *FAST, "--quiet"]) == 0
    capsys.readouterr()
    assert main(["fit", str(same), "-o", str(tmp_path / "fit2")]) == 2
    err = capsys.readouterr().err
    assert "a conversion of frames by cmax simulate" in err and "resized" not in err


def _ecd_folder(tmp_path, calib: str):
    """An ECD-layout folder ``tmp_path/seq`` of :func:`_frames` (six 40x30 frames, 25 frames/s) with ``calib`` as its calib.txt."""
    frames = _frames()
    seq = tmp_path / "seq"
    (seq / "images").mkdir(parents=True)
    for k, frame in enumerate(frames):
        cv2.imwrite(str(seq / "images" / f"frame_{k:08d}.png"), frame)
    (seq / "images.txt").write_text("".join(f"{k * 0.04:.6f} images/frame_{k:08d}.png\n" for k in range(len(frames))))
    (seq / "calib.txt").write_text(calib + "\n")
    return seq


def test_a_calibration_beside_the_simulated_frames_is_named_when_no_k_is_given(tmp_path, capsys):
    """An ECD folder's calib.txt beside images.txt: fit without K names it (was: only 'give --K or --calib')."""
    seq = _ecd_folder(tmp_path, "50 50 19.5 14.5 0 0 0 0 0")
    out = tmp_path / "events" / "seq.h5"
    assert main(["simulate", str(seq), "-o", str(out), *FAST, "--quiet"]) == 0
    capsys.readouterr()
    assert main(["fit", str(out), "-o", str(tmp_path / "fit")]) == 2
    err = capsys.readouterr().err
    assert f"{seq / 'calib.txt'} lies beside the frames it was simulated from: --calib {seq / 'calib.txt'}" in err, err


def _bare_mjpeg(path: Path, frames: int = 12) -> Path:
    """JPEG images one after another, no container (what IP cameras and `ffmpeg -f mjpeg` write)."""
    with open(path, "wb") as file:
        for k in range(frames):
            image = np.zeros((48, 64), np.uint8)
            cv2.circle(image, (10 + 3 * k, 24), 8, 255, -1)
            file.write(cv2.imencode(".jpg", image)[1].tobytes())
    return path


@pytest.mark.parametrize("name", ["clip.mjpeg", "clip.avi"])
def test_a_bare_mjpeg_stream_is_refused_rather_than_timed_at_25_fps(tmp_path, capsys, name):
    """Was: a bare MJPEG stream (named .avi; .mjpeg was refused as "not a video") converted with FFmpeg's invented
    25 frames/s: 12 frames became 0.44 s of events whatever the camera's rate, without a word."""
    from cmax.sim.video import DecodeError, VideoFileSource

    source = _bare_mjpeg(tmp_path / name)
    out = tmp_path / "out" / "clip.h5"
    status = main(["simulate", str(source), "-o", str(out), *FAST, "--quiet"])
    err = capsys.readouterr().err
    assert status in (1, 2) and "a bare MJPEG stream" in err and "ffmpeg -framerate RATE" in err, err
    assert not out.exists()
    with pytest.raises(DecodeError, match="its frame rate would be guessed"):
        VideoFileSource(source)


def test_the_no_intrinsics_message_opens_the_file_once(tmp_path, monkeypatch):
    """`no_intrinsics_message` opened the h5 three times on its error path (simulated_sizes, source_calibration,
    resized_note's own simulated_sizes); the message is the same from one opening."""
    import h5py

    from cmax.cli import recording

    seq = tmp_path / "seq"
    (seq / "images").mkdir(parents=True)
    (seq / "calib.txt").write_text("50 50 23.5 15.5 0 0 0 0 0\n")
    path = tmp_path / "conv.h5"
    with h5py.File(path, "w") as file:       # the attributes of a conversion of 48x32 frames at --size 24x16
        file.attrs.update(width=24, height=16, source_size="[48, 32]", source=str(seq / "images.txt"))
    opened = []
    real = h5py.File
    monkeypatch.setattr(h5py, "File", lambda *args, **kwargs: opened.append(args[0]) or real(*args, **kwargs))
    message = recording.no_intrinsics_message(path, "--calib")
    assert opened == [path]
    assert message == (f"{path} stores no intrinsics (gt/K): give them with --K fx,fy,cx,cy or --calib; "
                       f"{seq / 'calib.txt'} lies beside the frames it was simulated from; {path} was simulated "
                       "from 48x32 frames resized to 24x16 (--size): a K of those frames scales to fx*0.5, fy*0.5, "
                       "(cx+0.5)*0.5-0.5, (cy+0.5)*0.5-0.5")


def test_the_calibration_of_frames_that_size_resized_is_refused_with_the_scaled_k(tmp_path, capsys):
    """An ECD folder (calib.txt beside images.txt) simulated at --size 20x15, half its 40x30 frames; `--calib
    calib.txt` then gave the frames' K to the half-size pixels as it was (focal lengths and principal point twice
    too large), without a word: an ECD calib.txt states no resolution, so nothing refused it."""
    seq = _ecd_folder(tmp_path, "50 52 19.5 14.5 -0.1 0.02 0 0 0")
    out = tmp_path / "events" / "seq.h5"
    assert main(["simulate", str(seq), "-o", str(out), *FAST, "--quiet", "--size", "20x15"]) == 0
    (tmp_path / "traj.txt").write_text("0 0 0 0 0 0 0 1\n10 0.1 0 0 0 0 0 1\n")
    capsys.readouterr()
    # half size: fx 25, fy 26, cx (19.5 + 0.5) / 2 - 0.5 = 9.5, cy (14.5 + 0.5) / 2 - 0.5 = 7
    scaled = "give them scaled: --K 25,26,9.5,7 --distortion -0.1,0.02,0,0,0"
    for command in (["fit", str(out), "-o", str(tmp_path / "fit")],
                    ["emvs", str(out), "--poses", str(tmp_path / "traj.txt"), "-o", str(tmp_path / "emvs")],
                    ["depth", str(out), "-o", str(tmp_path / "depth")]):
        assert main([*command, "--calib", str(seq / "calib.txt")]) == 2
        err = capsys.readouterr().err
        assert f"calibrates the 40x30 frames that {out} was simulated from, but --size resized them to 20x15" in err
        assert scaled in err and err.count("\n") == 1, (command, err)
    # at the frames' own size the same calibration is taken as it is (no refusal from this check)
    same = tmp_path / "same" / "seq.h5"
    assert main(["simulate", str(seq), "-o", str(same), *FAST, "--quiet"]) == 0
    import argparse

    from cmax.cli.recording import calibration_of

    args = argparse.Namespace(calib=seq / "calib.txt", calib_camera="cam0", distortion=None, K=None, file=same)
    K, distortion, _ = calibration_of(args)[:3]
    assert (K[0, 0], K[1, 1], K[0, 2], K[1, 2]) == (50, 52, 19.5, 14.5)


def test_an_avi_whose_headers_state_no_frame_rate_is_one_line_exit_2(tmp_path, capsys):
    """Was: `cmax simulate` converted it at FFmpeg's invented 25 frames/s, exit 0 (a 20 fps clip 20% short)."""
    from test_sim_video import _avi_without_rate

    source = _avi_without_rate(tmp_path / "clip.avi")
    out = tmp_path / "out" / "clip.h5"
    assert main(["simulate", str(source), "-o", str(out), *FAST, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "its AVI headers state no frame rate" in err and "ffmpeg -r RATE" in err, err
    assert not out.exists()


def test_simulate_stores_the_frames_k_scaled_to_its_pixels_for_fit(tmp_path, capsys):
    """Was: `cmax simulate` had no --K / --calib and wrote no gt/K, so every `cmax fit` of the file needed --K again
    (and the K of frames that --size resized, scaled by hand)."""
    import h5py

    source = tmp_path / "clip.avi"
    write_video(source, n_frames=12, width=48, height=32)
    out = tmp_path / "k" / "clip.h5"
    assert main(["simulate", str(source), "-o", str(out), *FAST, "--quiet", "--K", "60,62,23.5,15.5",
                 "--size", "24x16"]) == 0
    with h5py.File(out, "r") as file:
        K = file["gt/K"][()]
    # cv2.resize's pixel centres: x' + 0.5 = s (x + 0.5), s = 0.5 on both axes: cx = 24 * 0.5 - 0.5
    np.testing.assert_allclose(K, [[30.0, 0, 11.5], [0, 31.0, 7.5], [0, 0, 1]], rtol=0, atol=1e-12)
    capsys.readouterr()
    status = main(["fit", str(out), "-o", str(tmp_path / "fit"), "--quiet", "--min-events", "10", "--depth-grid", "4,6"])
    assert status in (0, 1), capsys.readouterr().err                # fitted without --K (no "stores no intrinsics")
    np.testing.assert_allclose(json.loads((tmp_path / "fit" / "summary.json").read_text())["K"], K)
    assert "K" not in ConvertSettings().to_dict()                   # settings without K read as before


def test_simulate_calib_is_read_and_a_lens_distortion_refused(tmp_path, capsys):
    import h5py

    source = tmp_path / "clip.avi"
    write_video(source, n_frames=6, width=48, height=32)
    (tmp_path / "pinhole.txt").write_text("60 62 23.5 15.5 0 0 0 0 0\n")
    (tmp_path / "lens.txt").write_text("60 62 23.5 15.5 -0.1 0.02 0 0 0\n")
    out = tmp_path / "a" / "clip.h5"
    assert main(["simulate", str(source), "-o", str(out), *FAST, "--quiet", "--calib",
                 str(tmp_path / "pinhole.txt")]) == 0
    with h5py.File(out, "r") as file:
        np.testing.assert_array_equal(file["gt/K"][()], [[60.0, 0, 23.5], [0, 62.0, 15.5], [0, 0, 1]])
    capsys.readouterr()
    lens = tmp_path / "b" / "clip.h5"
    assert main(["simulate", str(source), "-o", str(lens), *FAST, "--quiet", "--calib",
                 str(tmp_path / "lens.txt")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "states a lens distortion (-0.1, 0.02, 0, 0, 0)" in err and \
        f"give --calib {tmp_path / 'lens.txt'} to cmax fit" in err, err
    assert not lens.exists()
    off = tmp_path / "c" / "clip.h5"                                  # another sensor's K: that video fails
    assert main(["simulate", str(source), "-o", str(off), *FAST, "--quiet", "--K", "600,600,320,240"]) == 1
    assert "K's principal point (320, 240) lies outside the 48x32 image" in capsys.readouterr().err
    assert not off.exists()


def test_a_k_given_over_the_file_s_own_gt_k_is_named_in_a_note(tmp_path, capsys):
    """Was: `cmax fit --K` on a file storing another gt/K (cmax simulate --K, cmax scene) used the given K without a
    word; the file's was never looked at."""
    source = tmp_path / "clip.avi"
    write_video(source, n_frames=12, width=48, height=32)
    out = tmp_path / "k" / "clip.h5"
    assert main(["simulate", str(source), "-o", str(out), *FAST, "--quiet", "--K", "60,62,23.5,15.5"]) == 0
    capsys.readouterr()
    fit = ["fit", str(out), "--quiet", "--min-events", "10", "--depth-grid", "4,6"]
    assert main([*fit, "-o", str(tmp_path / "other"), "--K", "80,80,23.5,15.5"]) in (0, 1)
    note = (f"note: {out} stores gt/K (fx 60, fy 62, cx 23.5, cy 15.5) unlike the K given (fx 80, fy 80, cx 23.5, "
            "cy 15.5): the given one is used")
    assert note in capsys.readouterr().err
    summary = json.loads((tmp_path / "other" / "summary.json").read_text())
    assert summary["K"][0][0] == 80.0 and any("unlike the K given" in text for text in summary["notes"])
    assert main([*fit, "-o", str(tmp_path / "same"), "--K", "60,62,23.5,15.5"]) in (0, 1)
    assert "unlike the K given" not in capsys.readouterr().err


def test_a_fisheye_or_rectified_calibration_is_refused_for_the_output_s_pinhole_k(tmp_path):
    """A Kalibr camchain of MVSEC's fisheye (equidistant) camera with its rectification: gt/K (a pinhole) cannot
    hold it, as it cannot hold a radtan distortion; refused naming both (was: refused as an unsupported model)."""
    import argparse

    from cmax.cli.simulate import _frames_intrinsics

    calib = tmp_path / "camchain.yaml"
    calib.write_text("cam0:\n  camera_model: pinhole\n  distortion_coeffs: [-0.048, 0.0113, -0.0554, 0.0215]\n"
                     "  distortion_model: equidistant\n  intrinsics: [226.38, 226.15, 173.65, 133.73]\n"
                     "  resolution: [346, 260]\n  rectification_matrix:\n  - [0, -1, 0]\n  - [1, 0, 0]\n  - [0, 0, 1]\n")
    with pytest.raises(ValueError, match=r"\(cam0\) states an equidistant \(fisheye\) lens and a rectification, which "
                                         r"the output's gt/K"):
        _frames_intrinsics(argparse.Namespace(calib=calib, calib_camera="cam0"))


def test_resume_is_refused_naming_that_simulate_resumes_by_itself(tmp_path, capsys):
    """``cmax simulate ... --resume`` (the flag of cmax fit / depth and learned.*): was `unrecognized arguments:
    --resume` alone, leaving the user to guess that a rerun continues; now the same exit 2 and one line that says
    so. Another unknown option is refused as before, without the hint."""
    with pytest.raises(SystemExit) as stop:
        main(["simulate", str(tmp_path / "a.avi"), "-o", str(tmp_path / "out"), "--resume"])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and err.count("\n") == 1
    assert "unrecognized arguments: --resume; cmax simulate resumes by itself: run the same command again" in err
    with pytest.raises(SystemExit) as stop:
        main(["simulate", str(tmp_path / "a.avi"), "-o", str(tmp_path / "out"), "--bogus"])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "--bogus (see cmax simulate --help)" in err and "by itself" not in err
    assert not (tmp_path / "out").exists()
