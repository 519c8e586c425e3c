"""Rendering under load: torch threads 1 vs 2 vs the policy of :func:`cmax._threads.torch_threads`.

Renders ``indoor_flying`` at 346x260 (:class:`cmax.sim.render.PlanarRenderer`)
at ``--frames`` poses with torch set to 1 thread, 2 threads and the policy
(:func:`cmax._threads.torch_threads_scope`, as the renderer does), each timed
interleaved, first with the machine as it is ("idle": whatever else runs),
then with ``--busy`` busy-loop processes started by this script ("busy").
Writes ``benchmarks/results/speed_threads.md``. The load average at each
phase is printed and written: on a shared machine "idle" is not idle.

Usage::

    python -m benchmarks.speed_threads [--frames 40] [--repeats 5] [--busy 4]
"""
from __future__ import annotations

import argparse
import multiprocessing
import os
import statistics
import time
from pathlib import Path

import numpy as np

from cmax.io.atomic import write_text_atomic

RESULTS = Path(__file__).resolve().parent / "results"


def _spin(stop) -> None:  # a busy loop, in a child process
    x = 0
    while not stop.is_set():
        for _ in range(100_000):
            x += 1


def _renders(renderer, poses, threads: int | None) -> None:
    from cmax._threads import torch_threads_scope

    if threads is None:  # the renderer's own scope: the policy, per frame
        for T in poses:
            renderer.render(T)
        return
    with torch_threads_scope(threads=threads):  # a fixed count: the renderer's body alone
        for T in poses:
            renderer._render(np.asarray(T, dtype=np.float64))


def measure(renderer, poses, repeats: int) -> dict[str, float]:
    """Frames/s (median over repeats, interleaved) for 1, 2 and policy threads."""
    from cmax._threads import torch_threads

    methods = {"1 thread": 1, "2 threads": 2, "policy": None}
    times: dict[str, list[float]] = {name: [] for name in methods}
    for threads in methods.values():
        _renders(renderer, poses[:3], threads)
    for _ in range(repeats):
        for name, threads in methods.items():
            start = time.perf_counter()
            _renders(renderer, poses, threads)
            times[name].append(time.perf_counter() - start)
    out = {name: len(poses) / statistics.median(t) for name, t in times.items()}
    out["policy picks"] = torch_threads(renderer.camera.width * renderer.camera.height)
    out["load"] = os.getloadavg()[0]
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--busy", type=int, default=4, help="busy-loop processes in the busy phase")
    parser.add_argument("--settle", type=float, default=20.0,
                        help="seconds to let the load average rise after starting the busy loops")
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args(argv)
    from cmax.sim.presets import make_scene

    scene = make_scene("indoor_flying", seed=0, width=346, height=260)
    times = np.linspace(0.0, scene.info.duration_s, args.frames, endpoint=False)
    poses = [scene.pose(float(t)) for t in times]
    phases = {"idle (as found)": measure(scene.renderer, poses, args.repeats)}
    stop = multiprocessing.Event()
    workers = [multiprocessing.Process(target=_spin, args=(stop,), daemon=True) for _ in range(args.busy)]
    for worker in workers:
        worker.start()
    try:
        time.sleep(args.settle)
        phases[f"busy ({args.busy} busy loops)"] = measure(scene.renderer, poses, args.repeats)
    finally:
        stop.set()
        for worker in workers:
            worker.join()
    lines = ["# Rendering under load: torch threads", "",
             "Written by `python -m benchmarks.speed_threads`; `indoor_flying` at 346x260, "
             f"{args.frames} poses, frames/s = poses / median of {args.repeats} interleaved runs. "
             f"cores available: {len(os.sched_getaffinity(0))}.", "",
             "| phase | load (1 min) | 1 thread | 2 threads | policy | policy picks | policy / best fixed |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for phase, r in phases.items():
        best = max(r["1 thread"], r["2 threads"])
        lines.append(f"| {phase} | {r['load']:.1f} | {r['1 thread']:.1f} | {r['2 threads']:.1f} | "
                     f"{r['policy']:.1f} | {r['policy picks']} | {r['policy'] / best:.2f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if not args.no_write:
        write_text_atomic(RESULTS / "speed_threads.md", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
