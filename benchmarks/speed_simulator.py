"""Speed of the simulator, written to ``benchmarks/results/speed_simulator.md``.

Section "simulator": :class:`cmax.sim.esim.EventSimulator` on the 161 real
frames of ``../shared/data/esim_truck_pan`` (240x180), median of several runs,
in events/s and frames/s, against a naive per-pixel Python loop (the
reference ESIM's algorithm written plainly) on a small crop, measured in the
same run and compared per pixel-frame. The two must give the same events on
the crop.

Usage::

    python benchmarks/speed_simulator.py [--repeats 5] [--data ../shared/data]
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import cv2
import numpy as np

from cmax.events import Events
from cmax.sim.esim import EventSimulator, log_intensity

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = Path(os.environ.get("EVTSLOWTV_SHARED_DATA", ROOT.parent / "shared" / "data"))
RESULTS = ROOT / "benchmarks" / "results" / "speed_simulator.md"


def load_truck_pan(data: Path) -> tuple[np.ndarray, np.ndarray]:
    """(T, H, W) uint8 frames and (T,) int64 µs times of ``esim_truck_pan``."""
    folder = data / "esim_truck_pan"
    paths = sorted((folder / "images").glob("image_*.png"))
    if not paths:
        raise SystemExit(f"no frames found in {folder / 'images'} (pass --data)")
    frames = np.stack([cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) for path in paths])
    times = np.round(np.loadtxt(folder / "timestamps.txt") * 1e6).astype(np.int64)
    return frames, times


def naive_simulate(frames: np.ndarray, times_us: np.ndarray, c: float) -> Events:
    """The baseline: ESIM with a Python loop over pixels and crossings (float32 levels)."""
    height, width = frames.shape[1:]
    log_prev = log_intensity(frames[0])
    ref = log_prev.copy()
    c32 = np.float32(c)
    events = []
    for k in range(1, len(frames)):
        log = log_intensity(frames[k])
        t0, dt = int(times_us[k - 1]), int(times_us[k] - times_us[k - 1])
        interval = []
        for y in range(height):
            for x in range(width):
                it, itdt = log_prev[y, x], log[y, x]
                if it == itdt:
                    continue
                up = itdt > it
                level = ref[y, x]
                while True:
                    level = np.float32(level + c32) if up else np.float32(level - c32)
                    if not ((it < level <= itdt) if up else (itdt <= level < it)):
                        break
                    tau = float(level - it) * dt / float(itdt - it)
                    interval.append((t0 + int(np.floor(tau + 0.5)), y * width + x, int(up)))
                    ref[y, x] = level
        interval.sort(key=lambda event: event[0])  # stable: ties keep the pixel order
        events.extend(interval)
        log_prev = log
    t, pixel, p = np.array(events, np.int64).reshape(-1, 3).T
    return Events(pixel % width, pixel // width, t, p, width, height)


def _median_seconds(run, repeats: int) -> float:
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        seconds.append(time.perf_counter() - start)
    return statistics.median(seconds)


def bench_simulator(frames: np.ndarray, times: np.ndarray, repeats: int) -> list[str]:
    """Markdown lines of the section "simulator"."""
    n_frames, height, width = frames.shape
    lines = [
        "## simulator",
        "",
        f"`EventSimulator.simulate` on esim_truck_pan: {n_frames} frames of {width}x{height}, "
        f"median of {repeats} runs.",
        "",
        "| threshold | events | seconds | events/s | frames/s |",
        "|---|---|---|---|---|",
    ]
    for c in (0.2, 0.1):
        simulator = EventSimulator(cp=c, cn=c)
        n_events = len(simulator.simulate(frames, times))
        seconds = _median_seconds(lambda: simulator.simulate(frames, times), repeats)
        lines.append(
            f"| {c} | {n_events} | {seconds:.3f} | {n_events / seconds:,.0f} | "
            f"{(n_frames - 1) / seconds:,.1f} |"
        )
    crop = np.ascontiguousarray(frames[:, 80:98, 110:134])  # 24x18, where the truck passes
    c = 0.1
    fast = EventSimulator(cp=c, cn=c).simulate(crop, times)
    naive = naive_simulate(crop, times, c)
    same = fast == naive
    fast_s = _median_seconds(lambda: EventSimulator(cp=c, cn=c).simulate(crop, times), repeats)
    naive_s = _median_seconds(lambda: naive_simulate(crop, times, c), max(1, repeats // 2))
    full_s = _median_seconds(lambda: EventSimulator(cp=c, cn=c).simulate(frames, times), repeats)
    rate = lambda pixels, seconds: (n_frames - 1) * pixels / seconds  # noqa: E731
    crop_pixels, full_pixels = crop.shape[1] * crop.shape[2], width * height
    lines += [
        "",
        f"Against a naive per-pixel Python loop, C = {c}, on a {crop.shape[2]}x{crop.shape[1]} "
        f"crop ({len(naive)} events; identical events: {'yes' if same else 'NO'}); the ratio "
        "compares pixel-frames per second:",
        "",
        "| implementation | input | seconds | pixel-frames/s | ratio |",
        "|---|---|---|---|---|",
        f"| naive loop | crop | {naive_s:.3f} | {rate(crop_pixels, naive_s):,.0f} | 1.0 |",
        f"| EventSimulator | crop | {fast_s:.4f} | {rate(crop_pixels, fast_s):,.0f} | "
        f"{naive_s / fast_s:,.0f} |",
        f"| EventSimulator | full frame | {full_s:.3f} | {rate(full_pixels, full_s):,.0f} | "
        f"{rate(full_pixels, full_s) / rate(crop_pixels, naive_s):,.0f} |",
        "",
    ]
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    frames, times = load_truck_pan(args.data)
    header = [
        "# Simulator speed",
        "",
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, Python "
        f"{platform.python_version()}, numpy {np.__version__}; written by "
        "`benchmarks/speed_simulator.py`.",
        "",
    ]
    text = "\n".join(header + bench_simulator(frames, times, args.repeats))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
