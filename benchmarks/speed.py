"""Speed benchmarks, organised in sections, each timed against baselines in the same run.

Usage::

    python -m benchmarks.speed                        # every section
    python -m benchmarks.speed --section representations --events 10000000 --repeats 5

Each section writes ``benchmarks/results/speed_<section>.md`` (a table with the
machine) and ``.json``. To add a section (simulator, cmax, emvs, ...), write a
function ``(args) -> Report`` decorated with ``@section("name")``: build the
``Report``, time each group of methods with :func:`run_group` (round-robin
repeats after one warm-up each; the first method is the group's baseline, and
speed-ups are median-time ratios against it), and put correctness checks in
``report.checks``. Section-specific options go into :func:`main`'s parser.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import statistics
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from benchmarks.machine import cpu_name
from cmax.io.atomic import write_text_atomic

RESULTS = Path(__file__).resolve().parent / "results"

SECTIONS: dict[str, Callable[[argparse.Namespace], "Report"]] = {}


def section(name: str) -> Callable:
    """Register a benchmark section under ``name`` (for ``--section name``)."""

    def register(function: Callable[[argparse.Namespace], "Report"]) -> Callable:
        SECTIONS[name] = function
        return function

    return register


@dataclass
class Row:
    """One timed method: median seconds over the repeats, throughput, ratio to the group baseline."""

    group: str
    method: str
    median_s: float
    times_s: list[float]
    events: int
    mev_per_s: float = 0.0
    speedup_vs_baseline: float = 1.0
    baseline: str = ""
    note: str = ""


@dataclass
class Report:
    section: str
    title: str
    config: dict
    rows: list[Row] = field(default_factory=list)
    checks: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    summary: list[str] = field(default_factory=list)  # markdown lines shown first (e.g. a table)


def time_call(function: Callable[[], object], repeats: int) -> list[float]:
    """Wall-clock seconds of ``repeats`` calls, after one untimed warm-up call."""
    return time_interleaved({"f": function}, repeats)["f"]


def time_interleaved(
    functions: dict[str, Callable[[], object]], repeats: int
) -> dict[str, list[float]]:
    """Seconds of ``repeats`` calls of each function, taken round-robin after one warm-up each.

    Interleaving puts every method under the same background load, so the
    ratios of one group stay fair on a shared machine.
    """
    for function in functions.values():
        function()
    clock = CLOCKS[CLOCK[0]]
    times: dict[str, list[float]] = {name: [] for name in functions}
    for _ in range(repeats):
        for name, function in functions.items():
            start = clock()
            function()
            times[name].append(clock() - start)
    return times


#: Clocks of :func:`time_interleaved`: wall seconds, or CPU seconds of this process (all its
#: threads; steadier than wall time on a machine that other work keeps busy).
CLOCKS = {"wall": time.perf_counter, "cpu": time.process_time}
CLOCK = ["wall"]


def run_group(report: "Report", group: str, methods: list[tuple[str, Callable[[], object], str]],
              events: int, repeats: int) -> None:
    """Time ``(method, function, note)`` rows interleaved; the first row is the baseline."""
    times = time_interleaved({name: function for name, function, _ in methods}, repeats)
    for i, (name, _, note) in enumerate(methods):
        add_row(report, group, name, times[name], events, baseline=i == 0, note=note)


def fresh_process_outputs(code: str, runs: int = 2, env: dict | None = None) -> list[str]:
    """The standard output of ``python -c code`` run ``runs`` times, one fresh process after another, all
    sharing one new, empty ``NUMBA_CACHE_DIR``: the first compiles the numba kernels, the next ones load
    them from that cache (how long a kernel's first call takes, with and without the cache). ``env``
    adds variables."""
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory() as cache:
        variables = {**os.environ, **(env or {}), "NUMBA_CACHE_DIR": cache}
        return [subprocess.run([sys.executable, "-c", code], env=variables, capture_output=True, text=True,
                               check=True).stdout for _ in range(runs)]


def first_calls_seconds(setup: str, call: str) -> dict[str, tuple[float, float]]:
    """Seconds of the first and the second ``call`` (a Python expression) after ``setup`` (untimed), in a fresh
    process with an empty numba cache and in a second one that loads it (:func:`fresh_process_outputs`):
    ``{"compile (empty numba cache)": (first, second), "cached (numba cache on disk)": (first, second)}``."""
    code = (f"{setup}\nimport time\ntimes = []\nfor _ in range(2):\n"
            f"    start = time.perf_counter(); {call}; times.append(time.perf_counter() - start)\n"
            "print(times[0], times[1])\n")
    labels = ("compile (empty numba cache)", "cached (numba cache on disk)")
    return {label: tuple(float(v) for v in out.split()[-2:]) for label, out in zip(labels, fresh_process_outputs(code))}


def timed_machine(clock: str) -> dict:
    """Time the groups that follow with ``clock`` (a key of :data:`CLOCKS`); returns :func:`machine_info` with
    the clock recorded, for the report's header."""
    CLOCK[0] = clock
    return {**machine_info(), "clock": clock}


def machine_info() -> dict:
    info = {
        "date_utc": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu": cpu_name(),
        "cpu_count": os.cpu_count(),
        "numpy": np.__version__,
        "load_average_1min_at_start": (
            round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None
        ),
    }
    try:
        import torch

        info["torch"] = torch.__version__
        info["torch_threads"] = torch.get_num_threads()
    except ImportError:  # pragma: no cover
        info["torch"] = None
    try:
        import tonic

        info["tonic"] = tonic.__version__
    except ImportError:
        info["tonic"] = None
    return info


def add_row(report: Report, group: str, method: str, times: list[float], events: int,
            *, baseline: bool = False, note: str = "") -> Row:
    """Append a row; the row marked ``baseline`` (first in its group) sets the group's ratios."""
    median = statistics.median(times)
    row = Row(group, method, median, times, events, events / median / 1e6, note=note)
    report.rows.append(row)
    if baseline:
        row.baseline = method
    return row


def finish_ratios(report: Report) -> None:
    for group in dict.fromkeys(row.group for row in report.rows):
        rows = [row for row in report.rows if row.group == group]
        base = next((row for row in rows if row.baseline), rows[0])
        for row in rows:
            row.baseline = base.method
            row.speedup_vs_baseline = base.median_s / row.median_s


def write_report(report: Report, machine: dict) -> tuple[Path, Path]:
    RESULTS.mkdir(parents=True, exist_ok=True)
    stem = RESULTS / f"speed_{report.section}"
    payload = {"machine": machine, **asdict(report)}
    write_text_atomic(stem.with_suffix(".json"), json.dumps(payload, indent=2) + "\n")
    command = report.config.get("command", f"python -m benchmarks.speed --section {report.section}")
    lines = [f"# {report.title}", "", f"Written by `{command}`; median of "
             f"{report.config.get('repeats')} runs after a warm-up.", ""]
    lines += ["| | |", "|---|---|"] + [f"| {key} | {value} |" for key, value in machine.items()]
    lines += [f"| {key} | {value} |" for key, value in report.config.items()]
    if report.summary:
        lines += ["", "## Summary", ""] + report.summary
    for group in dict.fromkeys(row.group for row in report.rows):
        rows = [row for row in report.rows if row.group == group]
        lines += ["", f"## {group}", "",
                  f"| method | median (ms) | Mev/s | speed-up vs {rows[0].baseline} | note |",
                  "|---|---:|---:|---:|---|"]
        lines += [f"| {r.method} | {r.median_s * 1e3:.1f} | {r.mev_per_s:.1f} | "
                  f"{r.speedup_vs_baseline:.2f}x | {r.note} |" for r in rows]
    if report.checks:
        lines += ["", "## Checks (same run)", ""] + [f"- {k}: {v}" for k, v in report.checks.items()]
    if report.notes:
        lines += ["", "## Notes", ""] + [f"- {note}" for note in report.notes]
    write_text_atomic(stem.with_suffix(".md"), "\n".join(lines) + "\n")
    return stem.with_suffix(".md"), stem.with_suffix(".json")


def publish_report(report: Report, machine: dict, *, write: bool = True) -> None:
    """Fill in the ratios, print the report and (``write``) save its markdown and JSON."""
    finish_ratios(report)
    print_report(report)
    if write:
        for path in write_report(report, machine):
            print(f"  wrote {path}")


def print_report(report: Report) -> None:
    print(f"\n== {report.title}")
    for line in report.summary:
        print(f"  {line}")
    for row in report.rows:
        print(f"  {row.group:12s} {row.method:42s} {row.median_s * 1e3:9.1f} ms "
              f"{row.mev_per_s:8.1f} Mev/s  {row.speedup_vs_baseline:6.2f}x vs {row.baseline}")
    for key, value in report.checks.items():
        print(f"  check {key}: {value}")


# -- section: representations ------------------------------------------------------------------
def _random_events(n: int, width: int, height: int, seed: int = 0):
    from cmax import Events

    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, 1_000_000, n)) + 1_700_000_000_000_000  # 1 s at epoch µs
    return Events(
        rng.integers(0, width, n), rng.integers(0, height, n), t, rng.integers(0, 2, n), width, height,
    )


def _per_event_weights(events, bins: int):
    """Lower bin, left and right signed weights, pixel index and plane size of every event."""
    t = events.t
    t_star = (bins - 1) * (t - t[0]).astype(np.float64) / max(int(t[-1] - t[0]), 1)
    lower = np.minimum(t_star.astype(np.intp), max(bins - 2, 0))
    right = events.signed_polarity(np.float64) * (t_star - lower)
    left = events.signed_polarity(np.float64) - right
    base = events.y.astype(np.intp) * events.width + events.x
    return lower, left, right, base, events.width * events.height


def _voxel_grid_add_at(events, bins: int) -> np.ndarray:
    """The paper's voxel grid written the usual way: per-event weights and ``np.add.at``."""
    lower, left, right, base, plane = _per_event_weights(events, bins)
    grid = np.zeros(bins * plane)
    np.add.at(grid, lower * plane + base, left)
    np.add.at(grid, np.minimum(lower + 1, bins - 1) * plane + base, right)
    return grid.astype(np.float32).reshape(bins, events.height, events.width)


def _voxel_grid_bincount_naive(events, bins: int) -> np.ndarray:
    """As :func:`_voxel_grid_add_at` with ``np.bincount`` (no use of the time order)."""
    lower, left, right, base, plane = _per_event_weights(events, bins)
    index = lower * plane + base
    grid = np.bincount(index, weights=left, minlength=bins * plane)
    grid += np.bincount(np.minimum(index + plane, bins * plane - 1), weights=right,
                        minlength=bins * plane)
    return grid.astype(np.float32).reshape(bins, events.height, events.width)


@section("representations")
def bench_representations(args: argparse.Namespace) -> Report:
    import torch

    from cmax.representations import event_frame, voxel_grid

    width, height, bins, n, repeats = 346, 260, args.bins, args.events, args.repeats
    report = Report(
        "representations", "Event representations: throughput",
        {"events": n, "sensor": f"{width}x{height}", "bins": bins, "repeats": repeats,
         "events_distribution": "uniform x, y, p; sorted uniform t over 1 s"},
    )
    events = _random_events(n, width, height)
    tensors = events.to_torch()
    structured = events.to_structured()
    try:
        import tonic
        import tonic.functional as tonic_functional
    except ImportError:
        tonic = None
        report.notes.append("tonic is not installed: its rows are missing")

    threads = f"torch threads: {torch.get_num_threads()}; Events.to_torch() not timed"
    sensor = (width, height, 2)

    # voxel grid
    methods = []
    if tonic is not None:
        transform = tonic.transforms.ToVoxelGrid(sensor_size=sensor, n_time_bins=bins)
        scratch = structured.copy()  # tonic rewrites p in place; after the warm-up it finds -1
        methods += [
            ("tonic ToVoxelGrid", lambda: transform(structured),
             "copies the events, then to_voxel_grid_numpy; normalises time by B, not B-1"),
            ("tonic to_voxel_grid_numpy",
             lambda: tonic_functional.to_voxel_grid_numpy(scratch, sensor, bins),
             "on a scratch copy (it modifies its input)"),
        ]
    methods += [
        ("np.add.at, per-event weights", lambda: _voxel_grid_add_at(events, bins), ""),
        ("np.bincount, per-event weights", lambda: _voxel_grid_bincount_naive(events, bins), ""),
        ("ours, numpy (voxel_grid(Events))", lambda: voxel_grid(events, bins), ""),
        ("ours, torch CPU (voxel_grid(EventTensors))", lambda: voxel_grid(tensors, bins), threads),
    ]
    run_group(report, "voxel grid", methods, n, repeats)
    ours = voxel_grid(events, bins)
    report.checks["voxel grid: max |numpy - torch|"] = float(
        np.abs(ours - voxel_grid(tensors, bins).numpy()).max())
    report.checks["voxel grid: max |numpy - np.add.at formula|"] = float(
        np.abs(ours - _voxel_grid_add_at(events, bins)).max())
    if tonic is not None:
        theirs = transform(structured).reshape(bins, height, width)
        ours_tonic_norm = voxel_grid(events, bins + 1)[:bins]  # tonic's t* = B (t - t0) / span
        report.checks["voxel grid: max |tonic - ours(B+1 bins)[:B]|"] = float(
            np.abs(ours_tonic_norm - theirs).max())

    # short windows, as in per-window fitting and training
    small = min(n, args.window_events)
    window = events[:small]
    window_tensors = type(tensors)(*(column[:small] for column in tensors[:4]), width, height)
    window_structured = structured[:small]
    methods = [("tonic ToVoxelGrid", lambda: transform(window_structured), "")] if tonic else []
    methods += [
        ("np.add.at, per-event weights", lambda: _voxel_grid_add_at(window, bins), ""),
        ("ours, numpy", lambda: voxel_grid(window, bins), ""),
        ("ours, torch CPU", lambda: voxel_grid(window_tensors, bins), ""),
    ]
    run_group(report, f"voxel grid, {small:,} events", methods, small, max(repeats, 20))

    # event frame
    frame_add_at = np.zeros((2, height, width))

    def add_at_frame():
        frame_add_at[:] = 0
        np.add.at(frame_add_at, (events.p, events.y, events.x), 1)
        return frame_add_at

    methods = [] if tonic is None else [(
        "tonic to_frame_numpy (event_count=N)",
        lambda: tonic_functional.to_frame_numpy(structured, sensor, event_count=n),
        "int16 output, np.add.at on (p, y, x)",
    )]
    methods += [
        ("np.add.at on (p, y, x)", add_at_frame, ""),
        ("ours, numpy (event_frame(Events))", lambda: event_frame(events), ""),
        ("ours, torch CPU (event_frame(EventTensors))", lambda: event_frame(tensors), threads),
    ]
    run_group(report, "event frame", methods, n, repeats)
    report.checks["event frame: numpy == torch == np.add.at"] = bool(
        np.array_equal(event_frame(events), event_frame(tensors).numpy())
        and np.array_equal(event_frame(events), add_at_frame()))
    finish_ratios(report)
    report.notes += [
        "Throughput in million events per second (Mev/s); speed-ups are median-time ratios "
        "against the first row of each table, measured in this run.",
        "Methods of a group are timed round-robin (each repeat runs every method once), so "
        "they share the same background load.",
        "Our numpy voxel grid uses the time order of Events: per bin interval, two np.bincount "
        "(signed count and signed time, or, above 4 (B-1) H W events, unweighted and "
        "time-weighted counts over the (polarity, pixel) index with the signs applied to the "
        "sums); the linear weights are applied to the per-pixel sums. Below H W / 2 events it "
        "builds per-event weights and makes one np.bincount (lower fixed cost). Events go "
        "through in chunks of 2**20, so temporaries stay small and are reused.",
        "Fresh large arrays are costly on this machine (page faults in a VM): most of the "
        "per-event-weights baselines' time is their (N,) temporaries, not the accumulation.",
        "numpy (and tonic) run on one core; torch runs with --torch-threads (default 1, "
        "the same footing). With 2 threads on this shared 2-core machine, torch's OpenMP "
        "regions stalled for 100s of ms whenever other work took a core.",
        "With numpy >= 1.25 np.add.at on a 1-D integer index is about as fast as np.bincount; "
        "tonic is slow mostly from its per-event temporaries and masks, not from np.add.at itself.",
    ]
    return report


# -- section: simulator ---------------------------------------------------------------------
@section("simulator")
def simulator_section(args: argparse.Namespace) -> Report:
    """ESIM events/s and frames/s (truck-pan PNGs, bikes.mp4), memory of a 10-minute conversion."""
    import cv2

    from benchmarks import speed_simulator as sim

    cv2.setNumThreads(1)  # single-threaded, as the reference C++ ESIM figure
    report = Report("simulator", "Simulator speed (EventSimulator, conversion)",
                    {"repeats": args.repeats, "opencv_threads": 1})
    sim.truck_groups(report, run_group, args.repeats)
    sim.bikes_groups(report, run_group, time_call, add_row)
    if not args.skip_long:
        sim.rss_rows(report, args.long_minutes)
    report.notes += [
        "Reference C++ ESIM (issue 3): 3.6-4.2 M events/s single-threaded on this machine, "
        "240x320 frames including PNG decoding (its threshold is not stated).",
        "Mev/s counts events per wall second; frames/s = frames / median time.",
        f"Load average (1 min) at the end: {os.getloadavg()[0]:.2f} (2 shared cores).",
    ]
    return report


# -- section: cmax ----------------------------------------------------------------------------
@section("cmax")
def cmax_section(args: argparse.Namespace) -> Report:
    """Warp + IWE + objective forward/backward for 30k events; cmax.fit seconds per window per model."""
    from benchmarks import speed_cmax

    report = Report("cmax", "Contrast maximization speed (warp, IWE, objective, cmax.fit)",
                    {"repeats": args.repeats})
    speed_cmax.cmax_section(args, report, run_group, add_row)
    return report


# -- section: emvs ----------------------------------------------------------------------------
@section("emvs")
def emvs_section(args: argparse.Namespace) -> Report:
    """EMVS events/s at 240x180 with 100 planes (slider scene): numpy port, exact splat, default gather."""
    from benchmarks import speed_emvs

    return speed_emvs.emvs_report(args)


# -- section: peers ---------------------------------------------------------------------------
@section("peers")
def peers_section(args: argparse.Namespace) -> Report:
    """Ours against every available peer (esim_py, expelliarmus, evlib, tonic) and C floors."""
    from benchmarks import speed_peers

    report = Report("peers", "Speed against the peers and the floors (one process)",
                    {"repeats": args.repeats, "peer_events": args.peer_events,
                     "frame_events": args.events, "groups": ",".join(args.peer_groups),
                     "torch_threads": args.torch_threads})
    speed_peers.peers_report(args, report, run_group)
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.speed", description=__doc__.split("\n")[0])
    parser.add_argument("--section", action="append", choices=sorted(SECTIONS),
                        help="section to run (repeatable); default all")
    parser.add_argument("--events", type=int, default=10_000_000,
                        help="number of events (default 10M)")
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats per method (default 5)")
    parser.add_argument("--bins", type=int, default=5, help="voxel grid bins (default 5)")
    parser.add_argument("--window-events", type=int, default=100_000,
                        help="events of the short-window voxel grid rows (default 100k)")
    parser.add_argument("--torch-threads", type=int, default=1,
                        help="torch intra-op threads (default 1, like numpy; 0 keeps torch's own)")
    parser.add_argument("--peer-events", type=int, default=5_000_000,
                        help="peers: events of the EVT read/write files (default 5M)")
    parser.add_argument("--peer-groups", default="esim,evt,frame",
                        type=lambda text: text.split(","),
                        help="peers: comma-separated groups among esim, evt, frame (default all)")
    parser.add_argument("--clock", choices=sorted(CLOCKS), default="wall",
                        help="wall seconds (default) or CPU seconds of this process (all threads)")
    parser.add_argument("--no-write", action="store_true", help="print only, write no results")
    parser.add_argument("--skip-long", action="store_true", help="simulator: skip the 10-minute run")
    parser.add_argument("--long-minutes", type=float, default=10.0,
                        help="simulator: minutes of looped video in the memory run (default 10)")
    parser.add_argument("--cmax-cache", type=Path, default=None,
                        help="cmax: folder of the accuracy benchmark's simulated windows (reused between runs)")
    args = parser.parse_args(argv)
    if args.events < 2 or args.repeats < 1:
        parser.error("--events must be >= 2 and --repeats >= 1")
    if args.torch_threads > 0:
        import torch

        torch.set_num_threads(args.torch_threads)
    machine = timed_machine(args.clock)
    for name in args.section or sorted(SECTIONS):
        publish_report(SECTIONS[name](args), machine, write=not args.no_write)
    return 0


if __name__ == "__main__":
    sys.exit(main())
