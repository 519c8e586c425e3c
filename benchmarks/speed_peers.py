"""Section "peers" of ``benchmarks/speed.py``: ours against every available peer and floor, one process.

Run with ``python -m benchmarks.speed --section peers [--peer-events 50000000]``;
writes ``benchmarks/results/speed_peers.md`` and ``.json``. Each group times
the peer or floor first (the baseline) and ours after it, interleaved
(round-robin repeats after one warm-up each, medians), on the same input
with the same event count; the "ratio" column of the summary is the
peer's median time over ours (> 1: ours is faster). Peers are optional
(``pip install evtslowtv[bench]``): a missing one is skipped with a note.

* ESIM: C++ ``esim_py`` of rpg_vid2e when importable; otherwise the figures
  measured with it on this machine before (issue 22), as context only (not
  the same process), and the implementation before issue 22 (``git show``).
* EVT 3.0 / EVT 2.0 read and write: expelliarmus (Rust), evlib (Rust +
  polars, read only, one polars thread); the file is the Gen4 driving sample
  tiled in time to ``--peer-events`` events.
* Event frame: a plain C loop compiled here with ``gcc -O2`` (the floor)
  and tonic's ``to_frame_numpy``.
"""
from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.speed_simulator import DATA, _head_esim, _truck

#: Events/s of the C++ esim_py on this machine (issue 22), when it could still be built.
ESIM_PY_MEV_S = {"truck": {0.2: 1.2, 0.1: 2.6, 0.05: 4.5}, "bikes": {0.2: 6.8, 0.1: 7.6, 0.05: 7.5}}
THRESHOLDS = (0.2, 0.1, 0.05)
#: The commit before the speed work of issue 22: its simulator is timed in this process
#: when esim_py is missing (``git show``; skipped outside a git checkout).
BASELINE_REV = "2e7feb7"
BIKES_FRAMES = 100  # of 250: at C = 0.05 the whole video makes ~70 M events per run


def _import(name: str):
    try:
        return __import__(name)
    except Exception:  # noqa: BLE001 - any failure means "not available"
        return None


# -- ESIM -----------------------------------------------------------------------------------
def _esim_py():
    module = _import("esim_py")
    return None if module is None or not hasattr(module, "EventSimulator") else module


def _esim_py_run(esim_py, paths, times_us, c) -> int:
    """esim_py on the image files (its own PNG decoding), as the committed figures were taken."""
    simulator = esim_py.EventSimulator(c, c, 0.0, 1e-3, True)
    events = simulator.generateFromStampedImageSequence(paths, list(np.asarray(times_us) / 1e6))
    return len(events)


def _bikes_frames(limit: int | None = None):
    import cv2

    capture = cv2.VideoCapture(str(DATA / "videos" / "bikes.mp4"))
    frames, times = [], []
    while limit is None or len(frames) < limit:
        ok, image = capture.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
        times.append(int(round(capture.get(cv2.CAP_PROP_POS_MSEC) * 1000)))
    capture.release()
    times = np.asarray(times, np.int64)
    if np.any(np.diff(times) <= 0):
        times = np.arange(len(frames), dtype=np.int64) * 40_000
    return np.stack(frames), times


def esim_groups(report, run_group, repeats: int, summary: list) -> None:
    import cv2

    from cmax.sim.esim import EventSimulator
    from cmax.sim.png import INFLATE_BACKEND
    from cmax.sim.video import ImageFolderSource, _read_image

    cv2.setNumThreads(1)
    esim_py = _esim_py()
    head = _head_esim(BASELINE_REV)
    if esim_py is None:
        report.notes.append(
            "esim_py (C++ ESIM of rpg_vid2e) is not importable here (it is built from source, not on "
            "PyPI): its rows show the figures measured with it on this machine before (issue 22), as "
            f"context, and the implementation before issue 22 (commit {BASELINE_REV}) is timed in "
            "this process instead.")
    folder, paths, times = _truck()
    # the inflate the default install uses (isal where it has wheels, else zlib): named in the rows
    source_label = f"ImageFolderSource (decode threads, {INFLATE_BACKEND} inflate)"
    frames = np.stack([cv2.imread(p, cv2.IMREAD_GRAYSCALE) for p in paths])
    bikes, bikes_t = _bikes_frames(BIKES_FRAMES)

    def run_pngs(cls, c, read=lambda path: cv2.imread(path, cv2.IMREAD_GRAYSCALE)):
        simulator, count = cls(cp=c, cn=c), 0
        for path, t_us in zip(paths, times):
            count += len(simulator.step(read(path), int(t_us)))
        return count

    def read_ours(path):
        """The frame as ImageFolderSource(dtype=np.uint8) reads it (cmax.sim.png, OpenCV for the rest)."""
        return _read_image(Path(path), None, np.uint8)

    def run_source(c):
        simulator, count = EventSimulator(cp=c, cn=c), 0
        for frame, t_us in ImageFolderSource(folder / "images", timestamps=times, dtype=np.uint8):
            count += len(simulator.step(frame, t_us))
        return count

    for c in THRESHOLDS:
        count = len(EventSimulator(cp=c, cn=c).simulate(frames, times))
        methods = []
        if esim_py is not None:
            methods.append(("esim_py (C++), PNG decode + simulate",
                            lambda: _esim_py_run(esim_py, paths, times, c), "peer"))
        elif head is not None:
            methods.append((f"{BASELINE_REV}: PNG decode + step, one thread", lambda: run_pngs(head, c),
                            "before issue 22"))
        methods += [(f"ours: PNG decode (cmax.sim.png, {INFLATE_BACKEND}) + step, one thread",
                     lambda: run_pngs(EventSimulator, c, read_ours), ""),
                    (f"ours: {source_label} + step", lambda: run_source(c),
                     "what cmax simulate runs: frames decoded in threads while the compiled (nogil) simulation "
                     "runs (with the CPU clock the overlap does not show)")]
        group = f"ESIM truck-pan 240x180 incl. PNG decoding, C={c}, {count:,} events"
        run_group(report, group, methods, count, repeats)
        _esim_summary(report, summary, group, "truck", c, count, esim_py is not None, f"{source_label} + step")
    for c in THRESHOLDS:
        count = len(EventSimulator(cp=c, cn=c).simulate(bikes, bikes_t))
        methods = []
        if esim_py is None and head is not None:
            methods.append((f"{BASELINE_REV}: simulate, frames decoded",
                            lambda: head(cp=c, cn=c).simulate(bikes, bikes_t), "before issue 22"))
        methods.append(("ours: simulate, frames decoded",
                        lambda: EventSimulator(cp=c, cn=c).simulate(bikes, bikes_t), ""))
        group = f"ESIM bikes 640x272 frames (dense), {len(bikes)} frames, C={c}, {count:,} events"
        run_group(report, group, methods, count, repeats)
        _esim_summary(report, summary, group, "bikes", c, count, False, "simulate, frames decoded")


def _esim_summary(report, summary, group, scene, c, count, same_process, ours_label) -> None:
    rows = {row.method: row for row in report.rows if row.group == group}
    ours = next(row for name, row in rows.items() if name.startswith("ours") and ours_label in name)
    reference = ESIM_PY_MEV_S[scene][c]
    if same_process:
        peer = next(row for name, row in rows.items() if name.startswith("esim_py"))
        summary.append((f"ESIM {scene}, C = {c}", f"{ours.mev_per_s:.1f} M ev/s",
                        f"esim_py {peer.mev_per_s:.1f} M ev/s", peer.median_s / ours.median_s,
                        "same process, interleaved"))
        return
    head = next((row for name, row in rows.items() if name.startswith(BASELINE_REV)), None)
    how = "esim_py not importable: its figure from issue 22 (another run, context only)"
    if head is not None:
        how += f"; {head.median_s / ours.median_s:.2f}x the code before issue 22 in this process"
    summary.append((f"ESIM {scene}, C = {c} ({ours_label})", f"{ours.mev_per_s:.1f} M ev/s",
                    f"C++ esim_py {reference} M ev/s (issue 22)", ours.mev_per_s / reference, how))


# -- EVT files ------------------------------------------------------------------------------
def _tiled_events(n: int):
    """The Gen4 driving sample tiled in time to ``n`` events (1280x720)."""
    from cmax.events import Events
    from cmax.io.prophesee import read_evt3

    base = read_evt3(DATA / "prophesee_gen4_driving" / "evt3_sample.raw")
    reps = -(-n // len(base))
    span = int(base.t[-1] - base.t[0]) + 1
    t = ((base.t - base.t[0])[None, :] + span * np.arange(reps)[:, None]).ravel()[:n]
    tile = lambda column: np.tile(column, reps)[:n]  # noqa: E731
    return Events(tile(base.x), tile(base.y), t, tile(base.p), base.width, base.height)


def evt_groups(report, run_group, repeats: int, n: int, summary: list) -> None:
    from cmax.io.prophesee import read_evt2, read_evt3, write_evt2, write_evt3

    expelliarmus = _import("expelliarmus")
    evlib = _import("evlib")
    for name, module in (("expelliarmus", expelliarmus), ("evlib", evlib)):
        if module is None:
            report.notes.append(f"{name} is not installed (pip install {name}): its rows are missing")
    events = _tiled_events(n)
    structured = np.empty(n, [("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1")])
    structured["t"], structured["x"], structured["y"], structured["p"] = (
        events.t, events.x, events.y, events.p)
    folder = Path(tempfile.mkdtemp(prefix="peers_evt_"))
    try:
        for codec, read, write in (("evt3", read_evt3, write_evt3), ("evt2", read_evt2, write_evt2)):
            path = folder / f"ours.{codec}.raw"
            write(path, events)
            ok = read(path) == events
            report.checks[f"{codec}: write then read gives the events back"] = ok
            methods = []
            if expelliarmus is not None:
                wizard = expelliarmus.Wizard(encoding=codec)
                theirs = wizard.read(path)
                report.checks[f"{codec}: expelliarmus reads our file: same count, x, y, p"] = bool(
                    len(theirs) == n and np.array_equal(theirs["x"], events.x)
                    and np.array_equal(theirs["y"], events.y) and np.array_equal(theirs["p"], events.p))
                methods.append(("expelliarmus Wizard.read", lambda w=wizard, p=path: w.read(p), "peer"))
            if evlib is not None:
                methods.append(("evlib load_events(sort=False).collect()",
                                lambda p=path: evlib.load_events(str(p), sort=False).collect(),
                                "peer; POLARS_MAX_THREADS=1 when set before the run"))
            methods.append((f"ours read_{codec}", lambda r=read, p=path: r(p), ""))
            group = f"{codec.upper()} read, {n:,} events ({path.stat().st_size / 1e6:.0f} MB)"
            run_group(report, group, methods, n, repeats)
            _io_summary(report, summary, group, f"{codec.upper()} read, {n / 1e6:g} M events")
            methods = []
            if expelliarmus is not None:
                wizard = expelliarmus.Wizard(encoding=codec)
                methods.append(("expelliarmus Wizard.save", lambda w=wizard: w.save(folder / "x.raw", structured),
                                "peer, from its structured array"))
            methods.append((f"ours write_{codec}", lambda w=write: w(folder / "y.raw", events), ""))
            group = f"{codec.upper()} write, {n:,} events"
            run_group(report, group, methods, n, repeats)
            _io_summary(report, summary, group, f"{codec.upper()} write, {n / 1e6:g} M events")
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _io_summary(report, summary, group, what) -> None:
    rows = [row for row in report.rows if row.group == group]
    ours = rows[-1]
    for peer in rows[:-1]:
        summary.append((what, f"{ours.median_s * 1e3:.0f} ms", f"{peer.method.split()[0]} "
                        f"{peer.median_s * 1e3:.0f} ms", peer.median_s / ours.median_s,
                        "same process, interleaved, medians"))
    if len(rows) == 1:
        summary.append((what, f"{ours.median_s * 1e3:.0f} ms", "no peer installed", float("nan"), ""))


# -- event frame against a C loop -----------------------------------------------------------
_C_FRAME = r"""
#include <stdint.h>
void event_frame(const uint16_t *x, const uint16_t *y, const int8_t *p, int64_t n,
                 int64_t width, int64_t height, float *frame) {
    for (int64_t i = 0; i < n; ++i)
        frame[((int64_t)p[i] * height + y[i]) * width + x[i]] += 1.0f;
}
"""


def _compile_c(source: str, folder: Path):
    """The shared library of ``source`` compiled with gcc -O2 into ``folder``, or None without gcc."""
    gcc = shutil.which("gcc") or shutil.which("cc")
    if gcc is None:
        return None
    c_file, so_file = folder / "floor.c", folder / "floor.so"
    c_file.write_text(source)
    subprocess.run([gcc, "-O2", "-shared", "-fPIC", str(c_file), "-o", str(so_file)], check=True)
    return ctypes.CDLL(str(so_file))


def frame_groups(report, run_group, repeats: int, n: int, summary: list) -> None:
    from benchmarks.speed import _random_events
    from cmax.representations import event_frame

    width, height = 346, 260
    events = _random_events(n, width, height)
    folder = Path(tempfile.mkdtemp(prefix="peers_c_"))
    try:
        library = _compile_c(_C_FRAME, folder)
        methods = []
        if library is None:
            report.notes.append("no C compiler: the event frame floor is missing")
        else:
            pointer = lambda a: a.ctypes.data_as(ctypes.c_void_p)  # noqa: E731
            library.event_frame.argtypes = [ctypes.c_void_p] * 3 + [ctypes.c_int64] * 3 + [ctypes.c_void_p]

            def c_frame():
                frame = np.zeros((2, height, width), np.float32)
                library.event_frame(pointer(events.x), pointer(events.y), pointer(events.p), n,
                                    width, height, pointer(frame))
                return frame

            report.checks["event frame: ours == C loop"] = bool(np.array_equal(c_frame(), event_frame(events)))
            methods.append(("plain C loop (gcc -O2), float32 frame", c_frame, "floor"))
        tonic = _import("tonic")
        if tonic is not None:
            import tonic.functional as functional

            structured = events.to_structured()
            methods.append(("tonic to_frame_numpy", lambda: functional.to_frame_numpy(
                structured, (width, height, 2), event_count=n), "peer"))
        methods.append(("ours event_frame(Events)", lambda: event_frame(events), ""))
        group = f"event frame {width}x{height}, {n:,} events"
        run_group(report, group, methods, n, repeats)
        rows = [row for row in report.rows if row.group == group]
        ours = rows[-1]
        for peer in rows[:-1]:
            summary.append((f"event frame, {n / 1e6:g} M events", f"{ours.median_s * 1e3:.1f} ms",
                            f"{peer.method} {peer.median_s * 1e3:.1f} ms",
                            peer.median_s / ours.median_s, "same process, interleaved, medians"))
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def peers_report(args, report, run_group) -> None:
    """Fill ``report`` with every group and the issue's summary table (``report.summary``)."""
    summary: list = []
    if "esim" in args.peer_groups:
        esim_groups(report, run_group, args.repeats, summary)
    if "evt" in args.peer_groups:
        evt_groups(report, run_group, args.repeats, args.peer_events, summary)
    if "frame" in args.peer_groups:
        frame_groups(report, run_group, args.repeats, args.events, summary)
    report.summary = [
        "| what | ours | peer or floor | ratio (> 1: ours faster) | how measured |",
        "|---|---|---|---:|---|",
    ] + [f"| {what} | {ours} | {peer} | {ratio:.2f} | {how} |" for what, ours, peer, ratio, how in summary]
    report.notes += [
        "Ratio: the peer's (or floor's) median time over ours on the same input and event count, "
        "timed round-robin in this process; ESIM rows without esim_py compare events/s with the "
        "figure measured with it before (not the same process: context only).",
        "h5 reading (the readers' benchmarks/speed_h5.py) and cmax.fit (benchmarks/speed_cmax.py) "
        "have their own sections.",
        f"Load average (1 min) at the end: {os.getloadavg()[0]:.2f} on "
        f"{len(os.sched_getaffinity(0))} cores shared with other work.",
        f"Wall-clock timings: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.",
    ]
