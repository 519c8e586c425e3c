"""Section "simulator" of ``benchmarks/speed.py``: ESIM throughput and conversion memory.

Run with ``python -m benchmarks.speed --section simulator`` (writes
``benchmarks/results/speed_simulator.md`` and ``.json``). Measures, in one run:

* events/s and frames/s of :class:`cmax.sim.esim.EventSimulator` on the 161
  real frames of ``../shared/data/esim_truck_pan`` **including PNG decoding**
  (as the reference C++ ESIM's 3.6-4.2 M events/s was measured), against the
  simulator of the last commit (``git show HEAD:cmax/sim/esim.py``) timed
  interleaved in the same process, and without decoding;
* ``../shared/data/videos/bikes.mp4`` (640x272, 25 fps): decoding + simulation
  without adaptive sampling, and with adaptive sampling (linear, flow) on its
  first second;
* peak memory of a long conversion: bikes.mp4 looped to 10 minutes of video
  through :func:`cmax.sim.convert.convert_video` in a child process, VmRSS at
  1, 5 and 10 minutes of video.
"""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("EVTSLOWTV_SHARED_DATA", ROOT.parent / "shared" / "data"))


def _head_esim():
    """The EventSimulator of the last commit, or None outside a git checkout."""
    try:
        text = subprocess.run(["git", "show", "HEAD:cmax/sim/esim.py"], cwd=ROOT, check=True,
                              capture_output=True, text=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    path = Path(tempfile.mkdtemp()) / "esim_head.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location("esim_head", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["esim_head"] = module
    spec.loader.exec_module(module)
    return module.EventSimulator


def _truck():
    folder = DATA / "esim_truck_pan"
    paths = [str(p) for p in sorted((folder / "images").glob("image_*.png"))]
    times = np.round(np.loadtxt(folder / "timestamps.txt") * 1e6).astype(np.int64)
    return paths, times


def _run_pngs(simulator_class, paths, times, c):
    simulator, count = simulator_class(cp=c, cn=c), 0
    for path, t_us in zip(paths, times):
        count += len(simulator.step(cv2.imread(path, cv2.IMREAD_GRAYSCALE), int(t_us)))
    return count


def _run_frames(simulator_class, frames, times, c):
    simulator, count = simulator_class(cp=c, cn=c), 0
    for frame, t_us in zip(frames, times):
        count += len(simulator.step(frame, int(t_us)))
    return count


def truck_groups(report, run_group, repeats):
    from cmax.sim.esim import EventSimulator

    paths, times = _truck()
    frames = [cv2.imread(p, cv2.IMREAD_GRAYSCALE) for p in paths]
    head = _head_esim()
    for c in (0.2, 0.1, 0.05):
        count = _run_pngs(EventSimulator, paths, times, c)
        methods = []
        if head is not None:
            methods.append(("HEAD EventSimulator, PNG decode + step", lambda: _run_pngs(head, paths, times, c), ""))
        methods += [
            ("EventSimulator, PNG decode + step", lambda: _run_pngs(EventSimulator, paths, times, c),
             f"{len(paths) / 1:.0f} frames"),
            ("EventSimulator.step, frames decoded", lambda: _run_frames(EventSimulator, frames, times, c), ""),
            ("PNG decode only", lambda: [cv2.imread(p, cv2.IMREAD_GRAYSCALE) for p in paths], ""),
        ]
        run_group(report, f"truck-pan 240x180, C={c}, {count:,} events", methods, count, repeats)
    report.checks["truck-pan frames"] = len(paths)
    if head is not None:
        same = all(_run_pngs(head, paths, times, c) == _run_pngs(EventSimulator, paths, times, c)
                   for c in (0.2, 0.1))
        report.checks["same event counts as HEAD (C=0.2, 0.1)"] = same


def bikes_groups(report, run_group, time_call, add_row):
    from cmax.sim.convert import ConvertSettings, open_frames
    from cmax.sim.esim import EventSimulator
    from cmax.sim.sampling import iter_upsample

    video = DATA / "videos" / "bikes.mp4"

    def plain(t1_s=None):
        simulator, count, n = EventSimulator(), 0, 0
        for frame, t_us in open_frames(video, ConvertSettings(adaptive=False, t1_s=t1_s)):
            count, n = count + len(simulator.step(frame, t_us)), n + 1
        return count, n

    count, n = plain()
    run_group(report, f"bikes.mp4 640x272, {n} frames, C=0.2, no adaptive sampling, {count:,} events",
              [("decode + step", lambda: plain(), f"{n} frames")], count, 3)
    for method in ("linear", "flow"):
        stats = {}

        def adaptive():
            simulator, count, samples = EventSimulator(), 0, 0
            frames = open_frames(video, ConvertSettings(adaptive=False, t1_s=1.0))
            for frame, t_us in iter_upsample(frames, 0.2, lam=0.5, method=method):
                count, samples = count + len(simulator.step(frame, t_us)), samples + 1
            stats.update(events=count, samples=samples)

        times = time_call(adaptive, 1) if method == "linear" else _once(adaptive)
        add_row(report, f"bikes.mp4 first 1 s (26 frames), adaptive {method}", f"decode + iter_upsample({method}) + step",
                times, stats["events"], baseline=True,
                note=f"{stats['samples']} samples, {stats['samples'] / times[0]:.1f} samples/s, "
                     f"{26 / times[0]:.2f} video frames/s")


def _once(function):
    start = time.perf_counter()
    function()
    return [time.perf_counter() - start]


_RSS_CHILD = r"""
import sys, resource, numpy as np
from pathlib import Path
from cmax.sim.convert import ConvertSettings, convert_video, open_frames
video, out, minutes = Path(sys.argv[1]), Path(sys.argv[2]), float(sys.argv[3])
marks, seen = {1: None, 5: None, 10: None}, []
def rss_mb():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024
def looped():
    offset, period = 0, None
    while True:
        last = 0
        for frame, t_us in open_frames(video, ConvertSettings(adaptive=False)):
            t = offset + t_us
            if t > minutes * 60e6:
                return
            for m in marks:
                if marks[m] is None and t >= m * 60e6:
                    marks[m] = rss_mb()
            yield frame, t
            last = t_us
        offset += last + 40_000
r = convert_video(video, out, ConvertSettings(adaptive=False), frames=looped())
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(marks[1], marks[5], marks[10], peak, r.frames, r.events, r.wall_s, out.stat().st_size)
"""


def rss_rows(report, minutes=10.0):
    video = DATA / "videos" / "bikes.mp4"
    with tempfile.TemporaryDirectory() as folder:
        result = subprocess.run([sys.executable, "-c", _RSS_CHILD, str(video), str(Path(folder) / "long.h5"),
                                 str(minutes)], capture_output=True, text=True, check=True)
    at1, at5, at10, peak, frames, events, wall, size = result.stdout.split()
    report.checks["10-minute conversion (bikes.mp4 looped, no adaptive)"] = (
        f"{int(frames):,} frames, {int(events):,} events, {float(wall):.0f} s wall, "
        f"{int(size) / 2**20:.0f} MiB h5")
    report.checks["VmRSS at 1 / 5 / 10 min of video (MiB)"] = (
        " / ".join("-" if v == "None" else f"{float(v):.0f}" for v in (at1, at5, at10))
        + f"; peak (ru_maxrss) {float(peak):.0f}")
