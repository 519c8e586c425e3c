"""Section "simulator" of ``benchmarks/speed.py``: ESIM throughput, adaptive sampling, conversion memory.

Run with ``python -m benchmarks.speed --section simulator`` or, with more
options, ``python -m benchmarks.speed_simulator [--quick] [--full-adaptive]``
(both write ``benchmarks/results/speed_simulator.md`` and ``.json``;
``--truck-only``: only the truck-pan groups at C = 0.2/0.1/0.05, to
``speed_simulator_truck.md`` and ``.json``, or ``speed_simulator_truck_isal``
when the optional ``isal`` inflates the PNGs).
Measures, in one run, against the code of the last commit (``git show
HEAD:cmax/sim/esim.py`` and ``sampling.py``, loaded as modules and timed
interleaved in the same process):

* events/s of :class:`cmax.sim.esim.EventSimulator` on the 161 real frames of
  ``../shared/data/esim_truck_pan`` at several thresholds (the event-density
  curve): PNG decoding + step in one thread (as the reference C++ ESIM's
  3.6-4.2 M events/s was measured), the same with the PNGs decoded by
  :class:`cmax.sim.video.ImageFolderSource` in 1 and in 2 (and, on a machine
  with more cores, its default number of) decoding threads while the
  simulation runs (pipelined; each row's note gives the process's CPU
  seconds per wall second, how much the threads overlapped), step alone on
  decoded frames, and PNG decoding alone (``IMREAD_GRAYSCALE`` as the
  reference, ``IMREAD_UNCHANGED`` as the source did before
  :mod:`cmax.sim.png`); each PNG row twice, with ``cv2.imread`` and with
  :func:`cmax.sim.png.read_png` (the source's reader; "fast PNG decode",
  with each inflate importable: zlib, and isal when installed); the
  events/s against the C++ esim_py figures of issue 22
  (``benchmarks.speed_peers.ESIM_PY_MEV_S``; esim_py itself is not
  importable here);
* ``../shared/data/videos/bikes.mp4`` (640x272, 25 fps): decoding + simulation
  without adaptive sampling, and with adaptive sampling (linear, flow) on its
  first second (``--quick``: 0.4 s), new against HEAD; ``--full-adaptive``
  adds the whole video;
* peak memory of a long conversion: bikes.mp4 looped to 10 minutes of video
  through :func:`cmax.sim.convert.convert_video` in a child process, VmRSS
  sampled every 20 ms (at 1, 5 and 10 minutes of video, the peak and when).
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
THRESHOLDS = (0.2, 0.1, 0.05, 0.03, 0.02)
REFERENCE_MEV_S = (3.6, 4.2)  # the reference C++ ESIM, issue 3


def _head_module(relative: str, name: str, rev: str = "HEAD"):
    """A module of commit ``rev`` (``git show <rev>:<relative>``), or None outside git."""
    try:
        text = subprocess.run(["git", "show", f"{rev}:{relative}"], cwd=ROOT, check=True,
                              capture_output=True, text=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    path = Path(tempfile.mkdtemp()) / f"{name}.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except ImportError:  # the committed module needs siblings this checkout lacks
        return None
    return module


def _head_esim(rev: str = "HEAD"):
    module = _head_module("cmax/sim/esim.py", f"esim_{rev}", rev)
    return None if module is None else module.EventSimulator


def _truck():
    folder = DATA / "esim_truck_pan"
    paths = [str(p) for p in sorted((folder / "images").glob("image_*.png"))]
    times = np.round(np.loadtxt(folder / "timestamps.txt") * 1e6).astype(np.int64)
    return folder, paths, times


def _run_pngs(simulator_class, paths, times, c):
    simulator, count = simulator_class(cp=c, cn=c), 0
    for path, t_us in zip(paths, times):
        count += len(simulator.step(cv2.imread(path, cv2.IMREAD_GRAYSCALE), int(t_us)))
    return count


def _run_fast_pngs(simulator_class, paths, times, c, inflate=None):
    from cmax.sim.png import read_png

    simulator, count = simulator_class(cp=c, cn=c), 0
    for path, t_us in zip(paths, times):
        count += len(simulator.step(read_png(path, inflate=inflate), int(t_us)))
    return count


def _cv2_folder_source(folder, times, decoders):
    """An ImageFolderSource that decodes every image with ``cv2.imread`` (as before ``cmax.sim.png``)."""
    from cmax.sim.video import ImageFolderSource, _to_grey

    class Cv2FolderSource(ImageFolderSource):
        def _decode(self, item):
            path, t = item
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            return _to_grey(image, self._size, str(path), self.dtype), t

    return Cv2FolderSource(folder, timestamps=times, dtype=np.uint8, decoders=decoders)


def _inflates():
    """``{name: inflate}`` of :mod:`cmax.sim.png`: zlib, and isal when importable (the default first)."""
    from cmax.sim import png

    inflates = {"zlib": png.inflate_zlib}
    return {"isal": png.inflate_isal, **inflates} if png.INFLATE_BACKEND == "isal" else inflates


def _run_source(simulator_class, source, c):
    simulator, count = simulator_class(cp=c, cn=c), 0
    for frame, t_us in source:
        count += len(simulator.step(frame, t_us))
    return count


def _source_events(simulator_class, source, c):
    """The events of a pipelined run, concatenated (for the identity check)."""
    from cmax.events import Events

    simulator = simulator_class(cp=c, cn=c)
    return Events.concatenate([simulator.step(frame, t_us) for frame, t_us in source])


def _cpu_seconds(function, repeats: int) -> float:
    """Median CPU seconds of this process over ``repeats`` calls (one thread: its work, less the waits)."""
    times = []
    for _ in range(repeats):
        start = time.process_time()
        function()
        times.append(time.process_time() - start)
    return float(np.median(times))


def parallel_capacity(threads: int = 2, seconds: float = 0.3) -> float:
    """CPU seconds per wall second that ``threads`` GIL-free threads get now (zlib inflating).

    About ``threads`` on a machine with that many idle cores; about 1 when
    the scheduler keeps this process on one core (e.g. another process busy
    on the other core of two): then decoding cannot overlap the simulation.
    """
    import threading
    import zlib

    blob = zlib.compress(np.random.default_rng(0).integers(0, 4, 1 << 22, dtype=np.uint8).tobytes())
    deadline = time.perf_counter() + seconds

    def inflate() -> None:
        while time.perf_counter() < deadline:
            zlib.decompress(blob)

    workers = [threading.Thread(target=inflate) for _ in range(threads)]
    wall, cpu = time.perf_counter(), time.process_time()
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    return (time.process_time() - cpu) / (time.perf_counter() - wall)


def _cpu_per_wall(function) -> float:
    """CPU seconds of this process (all threads) per wall second of one call."""
    wall, cpu = time.perf_counter(), time.process_time()
    function()
    return (time.process_time() - cpu) / (time.perf_counter() - wall)


def _run_frames(simulator_class, frames, times, c):
    simulator, count = simulator_class(cp=c, cn=c), 0
    for frame, t_us in zip(frames, times):
        count += len(simulator.step(frame, int(t_us)))
    return count


def _same_events(a, b) -> bool:
    return len(a) == len(b) and all(np.array_equal(getattr(a, k), getattr(b, k)) for k in "xytp")


def truck_groups(report, run_group, repeats, thresholds=THRESHOLDS):
    """One group per threshold on truck-pan; the density curve goes to ``report.checks``."""
    from cmax.sim.esim import EventSimulator
    from cmax.sim.png import INFLATE_BACKEND, read_png
    from cmax.sim.video import ImageFolderSource

    from benchmarks.speed_peers import ESIM_PY_MEV_S
    from cmax._threads import available_cores
    from cmax.sim.prefetch import MAX_DECODERS, default_decoders

    folder, paths, times = _truck()
    frames = [cv2.imread(p, cv2.IMREAD_GRAYSCALE) for p in paths]
    height, width = frames[0].shape
    counts = sorted({1, 2, default_decoders()})
    sources = {n: ImageFolderSource(folder / "images", timestamps=times, dtype=np.uint8, decoders=n)
               for n in counts}
    labels = {n: f"ImageFolderSource ({n} decoding thread{'s' * (n > 1)}) + step" for n in counts}
    cv2_sources = {n: _cv2_folder_source(folder / "images", times, n) for n in counts}
    cv2_labels = {n: f"ImageFolderSource, cv2.imread ({n} decoding thread{'s' * (n > 1)}) + step"
                  for n in counts}
    inflates = _inflates()
    fast_one = f"fast PNG decode ({INFLATE_BACKEND}) + step, one thread"
    report.checks[f"cmax.sim.png pixels identical to cv2.imread IMREAD_UNCHANGED (all {len(paths)} frames, "
                  f"inflate {', '.join(inflates)})"] = all(
        np.array_equal(read_png(p, inflate=f), cv2.imread(p, cv2.IMREAD_UNCHANGED))
        for p in paths for f in inflates.values())
    head = _head_esim()
    capacity = [parallel_capacity()]
    curve, versus, bounds, identical = [], [], [], True
    for c in thresholds:
        count = _run_frames(EventSimulator, frames, times, c)
        serial = EventSimulator(cp=c, cn=c).simulate(np.stack(frames), times)
        identical &= all(_same_events(_source_events(EventSimulator, source, c), serial)
                         for source in sources.values())
        methods = []
        if head is not None:
            methods.append(("HEAD: PNG decode + step, one thread",
                            lambda: _run_pngs(head, paths, times, c), ""))
        methods.append(("PNG decode + step, one thread", lambda: _run_pngs(EventSimulator, paths, times, c),
                        f"{len(paths)} frames, cv2.imread"))
        methods.append((fast_one, lambda: _run_fast_pngs(EventSimulator, paths, times, c),
                        "cmax.sim.png.read_png"))
        for n in counts:
            for label, source, how in ((cv2_labels[n], cv2_sources[n], "cv2.imread"),
                                       (labels[n], sources[n], f"cmax.sim.png ({INFLATE_BACKEND})")):
                run = (lambda source: lambda: _run_source(EventSimulator, source, c))(source)
                methods.append((label, run, f"pipelined, prefetch 4, {how}; CPU/wall {_cpu_per_wall(run):.2f}"))
        methods.append(("step only, frames decoded", lambda: _run_frames(EventSimulator, frames, times, c), ""))
        if head is not None:
            methods.append(("HEAD: step only, frames decoded",
                            lambda: _run_frames(head, frames, times, c), ""))
        methods += [
            ("PNG decode only, IMREAD_GRAYSCALE", lambda: [cv2.imread(p, cv2.IMREAD_GRAYSCALE) for p in paths],
             "as the reference ESIM"),
            ("PNG decode only, IMREAD_UNCHANGED", lambda: [cv2.imread(p, cv2.IMREAD_UNCHANGED) for p in paths],
             "as ImageFolderSource before cmax.sim.png (grey PNGs: same values)"),
        ]
        methods += [(f"fast PNG decode only, {name}",
                     (lambda f: lambda: [read_png(p, inflate=f) for p in paths])(f),
                     "cmax.sim.png.read_png" + (", as ImageFolderSource" if name == INFLATE_BACKEND else ""))
                    for name, f in inflates.items()]
        density = count / (len(paths) - 1) / (width * height)
        group = f"truck-pan {width}x{height}, C={c}, {count:,} events ({density:.3f} per pixel per frame)"
        run_group(report, group, methods, count, repeats)
        rows = {row.method: row for row in report.rows if row.group == group}
        best = max(counts, key=lambda n: rows[labels[n]].mev_per_s)
        curve.append((c, density, rows[fast_one].mev_per_s,
                      rows[labels[best]].mev_per_s, rows["step only, frames decoded"].mev_per_s))
        decode = _cpu_seconds(lambda: [read_png(p) for p in paths], repeats)
        step = _cpu_seconds(lambda: _run_frames(EventSimulator, frames, times, c), repeats)
        two, many = (decode + step) / 2, max(step, decode / MAX_DECODERS)
        bounds.append(f"C = {c}: decode {decode * 1e3:.0f} ms, step {step * 1e3:.0f} ms of CPU; 2 cores {two * 1e3:.0f} ms ({count / two / 1e6:.1f} M ev/s), "
                      f"{MAX_DECODERS + 1}+ cores {many * 1e3:.0f} ms ({count / many / 1e6:.1f} M ev/s)")
        reference = ESIM_PY_MEV_S["truck"].get(c)
        if reference is not None:
            def ratio(label: str) -> str:
                return f"{rows[label].mev_per_s:.2f} M ev/s = {rows[label].mev_per_s / reference:.2f}x"

            versus.append(
                f"C = {c} (esim_py {reference} M ev/s): one thread, no pool: fast {ratio(fast_one)}, cv2 "
                f"{ratio('PNG decode + step, one thread')}; pipelined, fast: " + ", ".join(
                    f"{n} thread{'s' * (n > 1)} {ratio(labels[n])}" for n in counts)
                + "; pipelined, cv2: " + ", ".join(
                    f"{n} thread{'s' * (n > 1)} {ratio(cv2_labels[n])}" for n in counts))
    capacity.append(parallel_capacity())
    report.checks["truck-pan frames"] = len(paths)
    report.checks["CPU seconds per wall second of 2 GIL-free threads (zlib), before / after the truck-pan "
                  "groups (about 2: two cores for this process; about 1: one, and the decoding threads "
                  "cannot overlap the simulation)"] = " / ".join(f"{v:.2f}" for v in capacity)
    report.checks["cores available / decoding threads by default"] = (
        f"{available_cores()} / {default_decoders()}")
    report.checks[f"pipelined events identical to the serial simulation (x, y, t, p; decoding threads "
                  f"{', '.join(map(str, counts))}; C={', '.join(map(str, thresholds))})"] = identical
    if head is not None:
        same = all(_same_events(head(cp=c, cn=c).simulate(np.stack(frames), times),
                                EventSimulator(cp=c, cn=c).simulate(np.stack(frames), times))
                   for c in thresholds)
        report.checks[f"events identical to HEAD (x, y, t, p; C={', '.join(map(str, thresholds))})"] = same
    if versus:
        report.checks["pipelined against C++ esim_py (issue 22's figures; esim_py is not importable "
                      "here, so not the same process)"] = "; ".join(versus)
    report.checks["bound on a free machine, from the CPU seconds (process time, medians) of decoding "
                  f"(cmax.sim.png, {INFLATE_BACKEND}, one thread) and of the step in this run; an estimate, not a "
                  "measurement: (decode + step) / 2 on 2 cores, max(step, decode / 4) with 4 decoders "
                  "and a core for the simulation"] = "; ".join(bounds)
    target = 2 * REFERENCE_MEV_S[1]
    report.checks["density curve: C / events per pixel per frame / Mev/s one thread (fast decode) / best "
                  "pipelined (fast decode) / step only"] = "; ".join(
        f"{c} / {d:.3f} / {a:.1f} / {b:.1f} / {s:.1f}" for c, d, a, b, s in curve)
    reached = [(c, d) for c, d, _, b, _ in curve if b >= target]
    report.checks[f"2x the reference ({target:.1f} Mev/s) pipelined reached at"] = (
        f"C <= {max(c for c, _ in reached)} (>= {min(d for _, d in reached):.3f} events per pixel per frame)"
        if reached else "no threshold measured")


def _video_frames_cv2(video: Path):
    """Grey uint8 frames and µs times decoded in this thread (as HEAD's convert did)."""
    capture = cv2.VideoCapture(str(video))
    try:
        while True:
            ok, image = capture.read()
            if not ok:
                return
            t_us = int(round(capture.get(cv2.CAP_PROP_POS_MSEC) * 1000))
            yield cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), t_us
    finally:
        capture.release()


def _adaptive_run(upsample_module, simulator_class, video: Path, seconds: float, method: str):
    from cmax.sim.video import VideoFileSource

    simulator, events, samples, reports = simulator_class(), 0, 0, []
    frames = VideoFileSource(video, t1_s=seconds)
    kwargs = {"report": reports.append}
    for frame, t_us in upsample_module.iter_upsample(frames, 0.2, lam=0.5, method=method, **kwargs):
        events, samples = events + len(simulator.step(frame, t_us)), samples + 1
    return {"events": events, "samples": samples, "intervals": len(reports),
            "inserted": sum(r.inserted for r in reports),
            "capped": sum(bool(r.capped) for r in reports),
            "rejected": sum(getattr(r, "rejected", 0) for r in reports)}


def bikes_groups(report, run_group, time_call, add_row, *, seconds: float = 1.0,
                 full_adaptive: bool = False):
    """bikes.mp4: decode + step without sampling; adaptive linear and flow against HEAD."""
    from cmax.sim import sampling
    from cmax.sim.esim import EventSimulator
    from cmax.sim.video import VideoFileSource

    video = DATA / "videos" / "bikes.mp4"
    head = _head_esim()
    source = VideoFileSource(video, dtype=np.uint8)

    def plain(simulator_class, frames):
        simulator, count = simulator_class(), 0
        for frame, t_us in frames():
            count += len(simulator.step(frame, t_us))
        return count

    count = plain(EventSimulator, lambda: source)
    methods = [("HEAD: decode + step, one thread", lambda: plain(head, lambda: _video_frames_cv2(video)), "")
               ] if head is not None else []
    methods += [
        ("decode + step, one thread", lambda: plain(EventSimulator, lambda: _video_frames_cv2(video)),
         f"{source.frame_count} frames"),
        ("VideoFileSource (decode thread) + step", lambda: plain(EventSimulator, lambda: source),
         "pipelined, prefetch 4"),
        ("decode only", lambda: sum(1 for _ in _video_frames_cv2(video)), ""),
    ]
    run_group(report, f"bikes.mp4 640x272, {source.frame_count} frames, C=0.2, no adaptive sampling, "
              f"{count:,} events", methods, count, 3)
    head_sampling = _head_module("cmax/sim/sampling.py", "sampling_head")
    spans = [seconds] + ([source.frame_count / source.fps] if full_adaptive else [])
    for span in spans:
        frames = round(span * source.fps)
        for method in ("linear", "flow"):
            group = f"bikes.mp4 first {span:g} s ({frames} frames), adaptive {method}, C=0.2, lam=0.5"
            with_head = head is not None and head_sampling is not None and span == seconds
            variants = [("HEAD", head_sampling, head)] if with_head else []
            variants.append(("new", sampling, EventSimulator))
            for i, (label, module, simulator_class) in enumerate(variants):
                start = time.perf_counter()
                stats = _adaptive_run(module, simulator_class, video, span, method)
                wall = time.perf_counter() - start
                note = (f"{stats['samples']} samples ({stats['inserted']} inserted, {stats['rejected']} "
                        f"rejected renders, {stats['capped']} capped intervals), "
                        f"{stats['samples'] / wall:.0f} samples/s, {frames / wall:.2f} video frames/s")
                add_row(report, group, f"{label}: decode + iter_upsample({method}) + step", [wall],
                        stats["events"], baseline=i == 0, note=note)
    for span in spans:
        rows = {row.group.split(", adaptive ")[1].split(",")[0]: row for row in report.rows
                if row.group.startswith(f"bikes.mp4 first {span:g} s") and row.method.startswith("new")}
        if {"linear", "flow"} <= rows.keys():
            report.checks[f"adaptive flow / linear wall time, first {span:g} s of bikes.mp4 (new)"] = (
                f"{rows['flow'].median_s / rows['linear'].median_s:.2f}x")


_RSS_CHILD = r"""
import resource, sys, threading, time
from pathlib import Path
def rss_mb():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024
at_start = rss_mb()
from cmax.sim.convert import ConvertSettings, convert_video, open_frames
video, out, minutes = Path(sys.argv[1]), Path(sys.argv[2]), float(sys.argv[3])
marks, state = {1: None, 5: None, 10: None}, {"t": 0.0, "peak": 0.0, "peak_t": 0.0}
def sample():
    while True:
        value = rss_mb()
        if value > state["peak"]:
            state["peak"], state["peak_t"] = value, state["t"]
        time.sleep(0.02)
threading.Thread(target=sample, daemon=True).start()
def looped():
    offset = 0
    while True:
        last = 0
        for frame, t_us in open_frames(video, ConvertSettings(adaptive=False)):
            t = offset + t_us
            if t > minutes * 60e6:
                return
            state["t"] = t / 60e6
            for m in marks:
                if marks[m] is None and t >= m * 60e6:
                    marks[m] = rss_mb()
            yield frame, t
            last = t_us
        offset += last + 40_000
r = convert_video(video, out, ConvertSettings(adaptive=False), frames=looped())
state["t"] = minutes + 1  # closed
time.sleep(0.05)
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(marks[1], marks[5], marks[10], peak, r.frames, r.events, r.wall_s, out.stat().st_size,
      at_start, state["peak"], state["peak_t"])
"""


def rss_rows(report, minutes=10.0):
    video = DATA / "videos" / "bikes.mp4"
    with tempfile.TemporaryDirectory() as folder:
        result = subprocess.run([sys.executable, "-c", _RSS_CHILD, str(video), str(Path(folder) / "long.h5"),
                                 str(minutes)], capture_output=True, text=True, check=True, cwd=ROOT)
    at1, at5, at10, peak, frames, events, wall, size, start, sampled, when = result.stdout.split()
    report.checks[f"{minutes:g}-minute conversion (bikes.mp4 looped, no adaptive)"] = (
        f"{int(frames):,} frames, {int(events):,} events, {float(wall):.0f} s wall, "
        f"{int(size) / 2**20:.0f} MiB h5")
    report.checks["VmRSS at 1 / 5 / 10 min of video (MiB)"] = (
        " / ".join("-" if v == "None" else f"{float(v):.0f}" for v in (at1, at5, at10))
        + f"; peak (ru_maxrss) {float(peak):.0f}; sampled peak {float(sampled):.0f} at "
        f"{float(when):.1f} min of video; {float(start):.0f} at start, before imports")


def main(argv: list[str] | None = None) -> int:
    """Run this section alone, with the options ``benchmarks/speed.py`` does not have."""
    import argparse

    from benchmarks import speed

    parser = argparse.ArgumentParser(prog="python -m benchmarks.speed_simulator",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true",
                        help="3 repeats, thresholds 0.2/0.05, 0.4 s of adaptive sampling, no 10-minute run")
    parser.add_argument("--full-adaptive", action="store_true",
                        help="also sample the whole bikes.mp4 adaptively (minutes)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--long-minutes", type=float, default=10.0)
    parser.add_argument("--no-write", action="store_true")
    parser.add_argument("--clock", choices=sorted(speed.CLOCKS), default="wall",
                        help="time wall seconds (default) or CPU seconds of the process (all its threads: "
                             "the one-thread rows' work on a busy machine; pipelined rows then add up "
                             "their threads' CPU time)")
    parser.add_argument("--truck-only", action="store_true",
                        help="only the truck-pan groups at C = 0.2/0.1/0.05, written to "
                             "benchmarks/results/speed_simulator_truck.md and .json")
    args = parser.parse_args(argv)
    speed.CLOCK[0] = args.clock
    load_at_start = os.getloadavg()[0]
    cv2.setNumThreads(1)  # single-threaded, as the reference C++ ESIM figure
    machine = speed.machine_info()
    repeats = 3 if args.quick else args.repeats
    report = speed.Report("simulator", "Simulator speed (EventSimulator, adaptive sampling, conversion)",
                          {"repeats": repeats, "opencv_threads": 1, "quick": args.quick})
    if args.truck_only:
        from cmax.sim.png import INFLATE_BACKEND

        # with the optional isal installed, a second file: the default install's figures stay apart
        suffix = "" if INFLATE_BACKEND == "zlib" else f"_{INFLATE_BACKEND}"
        report = speed.Report(f"simulator_truck{suffix}", "Simulator speed on truck-pan incl. PNG decoding",
                              {"repeats": repeats, "opencv_threads": 1, "png_inflate": INFLATE_BACKEND,
                               "clock": args.clock,
                               "command": "python -m benchmarks.speed_simulator --truck-only"
                               + (" --clock cpu" if args.clock == "cpu" else "")})
        truck_groups(report, speed.run_group, repeats, (0.2, 0.1, 0.05))
        if INFLATE_BACKEND != "zlib":
            from importlib.metadata import version

            report.notes.append(f"PNG frames inflated by {INFLATE_BACKEND} {version(INFLATE_BACKEND)} "
                                "(the optional extra evtslowtv[fast]); without it the same command "
                                "writes speed_simulator_truck.md (zlib).")
        report.notes += [
            f"Mev/s counts events per {args.clock} second; rows of one group are timed interleaved.",
            f"Load average (1 min) at the start / end: {load_at_start:.2f} / {os.getloadavg()[0]:.2f} "
            "(2 shared cores).",
        ]
        speed.publish_report(report, machine, write=not args.no_write)
        return 0
    truck_groups(report, speed.run_group, repeats, (0.2, 0.05) if args.quick else THRESHOLDS)
    bikes_groups(report, speed.run_group, speed.time_call, speed.add_row,
                 seconds=0.4 if args.quick else 1.0, full_adaptive=args.full_adaptive)
    if not args.quick:
        rss_rows(report, args.long_minutes)
    report.notes += [
        "Reference C++ ESIM (issue 3): 3.6-4.2 M events/s single-threaded on this machine, "
        "240x320 frames including PNG decoding (its threshold is not stated); truck-pan is 240x180.",
        "Mev/s counts events per wall second; rows of one group are timed interleaved.",
        f"Load average (1 min) at the end: {os.getloadavg()[0]:.2f} (2 shared cores).",
    ]
    speed.publish_report(report, machine, write=not args.no_write)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
