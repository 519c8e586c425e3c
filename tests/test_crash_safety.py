"""Crash safety of ``cmax simulate``: a conversion killed with SIGKILL mid-video resumes cleanly.

A collection of three small videos (made here with ``cv2.VideoWriter``) is
converted by the real console entry point in a subprocess. As soon as the first
video's final file exists and the second one's ``.partial`` file appears, the
process is killed with SIGKILL (no cleanup handlers run). Then:

* no file has a final name unless it is complete (the interrupted video exists
  only as its private temporary ``b.h5.<hex>.partial``, the unstarted one not at all);
* the manifest on disk is valid JSON and lists exactly the finished video, with
  the event count of its file;
* a rerun skips the finished video (same bytes and mtime), redoes the
  interrupted one and converts the last; the redone file equals an
  uninterrupted conversion, no ``.partial`` file remains, and the manifest's
  counts and totals match the files.

If the conversion outruns the poller (a very fast machine), the videos are made
longer and the attempt is repeated.
"""
from __future__ import annotations

import hashlib
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from cmax.io import read_h5
from cmax.sim.convert import ConvertSettings, convert_video
from cmax.sim.esim import EsimSettings
from conftest import sigterm_once

pytestmark = pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs POSIX SIGKILL")

NAMES = ("a", "b", "c")
SIZE = (64, 48)


def _write_video(path: Path, frames: int, seed: int) -> None:
    """A texture sliding left one pixel per frame (MJPG in AVI, readable by any OpenCV)."""
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur((rng.random((SIZE[1], frames + SIZE[0])) * 255).astype(np.uint8), (5, 5), 1.5)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, SIZE)
    assert writer.isOpened(), "OpenCV cannot write MJPG videos here"
    try:
        for k in range(frames):
            writer.write(cv2.cvtColor(np.ascontiguousarray(texture[:, k: k + SIZE[0]]), cv2.COLOR_GRAY2BGR))
    finally:
        writer.release()


def _command(videos: Path, output: Path) -> list[str]:
    return [sys.executable, "-m", "cmax.cli", "simulate", str(videos), "-o", str(output),
            "--quiet", "--method", "linear"]


def _digest(path: Path) -> tuple[str, int]:
    return hashlib.sha256(path.read_bytes()).hexdigest(), path.stat().st_mtime_ns


def _kill_during_second_video(videos: Path, output: Path, timeout_s: float = 120.0) -> bool:
    """Run the conversion; SIGKILL it once a.h5 is final and b's temporary file exists.

    Returns False when the process finished (or the moment was missed) before the kill.
    """
    process = subprocess.Popen(_command(videos, output), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline:
            if (output / "a.h5").exists() and list(output.glob("b.h5.*.partial")):
                process.send_signal(signal.SIGKILL)
                process.wait(timeout=30)
                return True
            if process.poll() is not None:
                return False
            time.sleep(0.002)
        raise AssertionError(f"the conversion did not reach the second video in {timeout_s} s")
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(timeout=30)


def _manifest(output: Path) -> dict:
    return json.loads((output / "manifest.json").read_text("utf-8"))


def _check_manifest_matches_files(manifest: dict, output: Path) -> None:
    ok = {name: entry for name, entry in manifest["videos"].items() if entry["status"] == "ok"}
    for name, entry in ok.items():
        assert len(read_h5(output / f"{name}.h5")) == entry["events"]
    totals = manifest["totals"]
    assert totals["ok"] == len(ok) and totals["videos"] == len(manifest["videos"])
    assert totals["events"] == sum(entry["events"] for entry in ok.values())
    assert totals["frames"] == sum(entry["frames"] for entry in ok.values())


def test_killed_conversion_resumes_without_damage(tmp_path):
    videos = tmp_path / "videos"
    videos.mkdir()
    frames = 300
    for attempt in range(3):
        for seed, name in enumerate(NAMES):
            _write_video(videos / f"{name}.avi", frames, seed)
        output = tmp_path / f"events{attempt}"
        if _kill_during_second_video(videos, output):
            break
        frames *= 3  # too fast to catch: longer videos
    else:
        pytest.fail("could not kill the conversion during the second video in 3 attempts")

    # After the kill: only complete files carry final names; the manifest lists a alone.
    names = sorted(path.name for path in output.iterdir())
    assert "a.h5" in names and len(list(output.glob("b.h5.*.partial"))) == 1
    assert "b.h5" not in names and "c.h5" not in names and not list(output.glob("c.h5*"))
    manifest = _manifest(output)
    assert list(manifest["videos"]) == ["a"] and manifest["videos"]["a"]["status"] == "ok"
    _check_manifest_matches_files(manifest, output)
    finished = _digest(output / "a.h5")
    assert manifest["videos"]["a"]["frames"] == frames

    # Rerun to the end: a is skipped, b redone, c converted.
    time.sleep(0.01)  # a rewrite of a.h5 would get a later mtime
    done = subprocess.run(_command(videos, output), capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert _digest(output / "a.h5") == finished
    assert sorted(path.name for path in output.iterdir()) == ["a.h5", "b.h5", "c.h5", "manifest.json"]
    manifest = _manifest(output)
    assert sorted(manifest["videos"]) == list(NAMES)
    assert all(entry["status"] == "ok" and entry["frames"] == frames for entry in manifest["videos"].values())
    _check_manifest_matches_files(manifest, output)

    # The redone video equals a conversion that was never interrupted.
    recorded = manifest["settings"]
    settings = ConvertSettings(EsimSettings(**recorded["esim"]),
                               **{key: value for key, value in recorded.items() if key not in ("esim", "size")})
    clean = convert_video(videos / "b.avi", tmp_path / "clean_b.h5", settings)
    assert read_h5(output / "b.h5") == read_h5(tmp_path / "clean_b.h5")
    assert clean.events == manifest["videos"]["b"]["events"]


@pytest.mark.parametrize("workers", [1, 2])
def test_sigterm_cleans_up_like_ctrl_c(tmp_path, workers):
    """SIGTERM (timeout, a SLURM time limit) left .partial and .lock files (handled like SIGKILL); it now runs the
    clean-up of Ctrl-C: exit 143, one line, only finished files and the manifest left, and a rerun finishes."""
    videos = tmp_path / "videos"
    videos.mkdir()
    for seed, name in enumerate(NAMES):
        _write_video(videos / f"{name}.avi", 600, seed)
    output = tmp_path / "events"
    status, err = sigterm_once([*_command(videos, output), "--workers", str(workers)], output, "*.h5.*.partial",
                               "a video was being written")
    assert status == 143, err
    assert "cmax simulate: terminated (SIGTERM)" in err and "Traceback" not in err
    left = sorted(path.name for path in output.iterdir())
    assert not [name for name in left if name.endswith((".partial", ".lock"))], left
    manifest = _manifest(output)
    _check_manifest_matches_files(manifest, output)
    kept = {name for name in left if name.endswith(".h5.chunks")}   # the chunks of the videos stopped part-way
    assert kept <= {f".{name}.h5.chunks" for name in NAMES if name not in manifest["videos"]}, kept
    assert set(left) - kept == {"manifest.json", *(f"{name}.h5" for name in manifest["videos"])}
    done = subprocess.run([*_command(videos, output), "--workers", str(workers)], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    assert sorted(path.name for path in output.iterdir()) == ["a.h5", "b.h5", "c.h5", "manifest.json"]


def test_sigterm_to_the_process_group_leaves_no_temporaries_and_one_line(tmp_path):
    """`timeout -s TERM` (and batch systems) signal the whole process group: the workers and their forkserver too.
    Was: the forkserver's death made `join` return while the killed workers still held their output's lock, so
    the clean-up left `b.h5.<hex>.partial` and `b.h5.lock`; and stderr had two lines (the command's own and
    `cmax simulate: terminated (SIGTERM)` again from `run_main`)."""
    videos = tmp_path / "videos"
    videos.mkdir()
    for seed, name in enumerate(NAMES):
        _write_video(videos / f"{name}.avi", 600, seed)
    output = tmp_path / "events"
    status, err = sigterm_once([*_command(videos, output), "--workers", "2"], output, "*.h5.*.partial",
                               "a video was being written", group=True)
    assert status == 143, err
    assert err.count("\n") == 1 and err.startswith("cmax simulate: terminated (SIGTERM)"), err
    left = sorted(path.name for path in output.iterdir())
    assert not [name for name in left if name.endswith((".partial", ".lock"))], left


def test_a_sigterm_held_back_by_sigterm_deferred_stops_the_run_at_the_blocks_end():
    """A SIGTERM while a worker starts (`cmax.sim.convert._run_parallel`) must not land between `Process.start` and
    the worker's record (a started worker nobody stops or cleans up after); one that makes the block fail (the
    forkserver dying under `start`: EOFError, a traceback) stops the run as SIGTERM."""
    import os

    from cmax._signals import Terminated, sigterm_as_interrupt, sigterm_deferred

    steps = []
    with pytest.raises(Terminated):
        with sigterm_as_interrupt():
            with sigterm_deferred():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)       # the handler has run by now: held back, not raised
                steps.append("recorded")
            steps.append("after the block")
    assert steps == ["recorded"]
    with pytest.raises(Terminated):
        with sigterm_as_interrupt():
            with sigterm_deferred():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)
                raise EOFError("unexpected EOF")
    with sigterm_as_interrupt():                     # no signal: the block runs as written
        with sigterm_deferred():
            steps.append("quiet")
    assert steps == ["recorded", "quiet"]


def test_a_command_that_reports_its_own_sigterm_prints_one_line(capsys):
    """`cmax simulate` catches Terminated, says what it kept and returns 143; `run_main` then raised it again
    from the remembered signal and printed a second line."""
    import argparse
    import os

    from cmax._args import ArgumentParser, run_main
    from cmax._signals import TERMINATED_STATUS, Terminated

    def command(args: argparse.Namespace) -> int:
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)
        except Terminated:
            print("demo: terminated (SIGTERM): kept what was finished", file=sys.stderr)
            return TERMINATED_STATUS
        return 0

    assert run_main(ArgumentParser(prog="demo"), command, []) == TERMINATED_STATUS
    assert capsys.readouterr().err == "demo: terminated (SIGTERM): kept what was finished\n"
