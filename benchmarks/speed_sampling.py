"""How adaptive sampling's cost grows with the frame size, and why (issue 22, item 7).

Runs :func:`cmax.sim.sampling.iter_upsample` (``method="flow"``, C = 0.2,
lam = 0.5) on the first ``--seconds`` of ``bikes.mp4`` resized to 320, 640
and 1280 pixels wide (aspect kept), decoding and the DIS flow included,
and counts the samples it yields and the key frames it renders. Writes
``benchmarks/results/speed_sampling.md``: seconds (CPU time of this
process), samples, and seconds per (sample x pixel). The method bounds each
point's motion between key frames to one *pixel*, so the number of key
frames grows with the width (the motion in pixels doubles when the width
does); a cost per sample and pixel that stays flat means the work per
sample is linear in the pixel count and the growth beyond that is the
number of samples the method asks for.

Usage::

    python -m benchmarks.speed_sampling [--seconds 0.4] [--widths 320,640,1280]
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import cv2

from benchmarks.speed_simulator import DATA
from cmax.io.atomic import write_text_atomic

RESULTS = Path(__file__).resolve().parent / "results"


def run(width: int, seconds: float) -> dict:
    from cmax.sim.sampling import iter_upsample
    from cmax.sim.video import VideoFileSource

    height = int(round(272 * width / 640 / 2)) * 2
    source = VideoFileSource(DATA / "videos" / "bikes.mp4", size=(width, height), t1_s=seconds,
                             prefetch=0)
    reports: list = []
    start_cpu, start_wall = time.process_time(), time.perf_counter()
    samples = sum(1 for _ in iter_upsample(source, 0.2, lam=0.5, method="flow", report=reports.append))
    cpu, wall = time.process_time() - start_cpu, time.perf_counter() - start_wall
    return {"width": width, "height": height, "pixels": width * height, "samples": samples,
            "inserted": sum(r.inserted for r in reports), "intervals": len(reports),
            "cpu_s": cpu, "wall_s": wall}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=0.4)
    parser.add_argument("--widths", default="320,640,1280")
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)
    rows = [run(int(w), args.seconds) for w in args.widths.split(",")]
    lines = ["# Adaptive sampling (flow) against the frame size", "",
             f"Written by `python -m benchmarks.speed_sampling`: bikes.mp4, first {args.seconds:g} s, "
             "C = 0.2, lam = 0.5, method flow, OpenCV on one thread; CPU seconds of this process "
             f"(load average {os.getloadavg()[0]:.1f} on {len(os.sched_getaffinity(0))} shared cores).", "",
             "| width x height | CPU s | x previous | samples | x previous | µs per sample and kilopixel |"
             " x previous |", "|---|---:|---:|---:|---:|---:|---:|"]
    previous = None
    for r in rows:
        unit = 1e6 * r["cpu_s"] / r["samples"] / (r["pixels"] / 1e3)
        ratio = lambda key, value: "" if previous is None else f"{value / previous[key]:.2f}"  # noqa: E731
        lines.append(f"| {r['width']}x{r['height']} | {r['cpu_s']:.2f} | {ratio('cpu_s', r['cpu_s'])} | "
                     f"{r['samples']} | {ratio('samples', r['samples'])} | {unit:.3f} | "
                     f"{ratio('unit', unit)} |")
        previous = {**r, "unit": unit}
    lines += ["", "Each doubling of the width is 4x the pixels. The key frames bound every point's motion "
              "to one pixel, so their number follows the motion in pixels (2x per doubling); the cost per "
              "sample and pixel staying near flat says the work per sample is linear in the pixels and the "
              "rest is the number of samples the method asks for."]
    text = "\n".join(lines) + "\n"
    print(text)
    if not args.no_write:
        write_text_atomic(RESULTS / "speed_sampling.md", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
