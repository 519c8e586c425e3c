"""Rendering speed of the synthetic scenes, written to ``benchmarks/results/speed_scenes.md``.

Each preset of :func:`cmax.sim.presets.make_scene` is rendered at 346x260
(intensity and depth) at ``--frames`` times spread over its trajectory;
frames/s is the median over ``--repeats`` runs (after a warm-up). The
baseline, timed in the same run on a few frames, is plain numpy ray casting of
all parallelograms against all pixels (float32, depth only: no textures), the
method the tiled torch renderer replaces. The target is at least 200 frames/s
for ``indoor_flying`` on a 2-core machine.

Usage::

    python benchmarks/speed_scenes.py [--repeats 5] [--frames 200] [--threads N]
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from cmax.io.atomic import write_text_atomic
from cmax.sim.presets import PRESETS, make_scene

RESULTS = Path(__file__).resolve().parent / "results"


def numpy_depth(scene, T_w_c: np.ndarray) -> np.ndarray:
    """Baseline: every parallelogram against every pixel in numpy (float32), nearest hit wins."""
    camera, world = scene.camera, scene.world
    v, u = np.mgrid[0: camera.height, 0: camera.width]
    rays = (np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3) @ np.linalg.inv(camera.K).T)
    rays_w = (rays @ T_w_c[:3, :3].T).astype(np.float32)  # (P, 3)
    centre = T_w_c[:3, 3]
    n = np.cross(world.edges_u, world.edges_v)
    nn = (n * n).sum(1)
    u_dual = np.cross(world.edges_v, n) / nn[:, None]
    v_dual = np.cross(n, world.edges_u) / nn[:, None]
    offset = world.origins - centre
    with np.errstate(divide="ignore", invalid="ignore"):
        z = ((n * offset).sum(1)).astype(np.float32) / (rays_w @ n.T.astype(np.float32))  # (P, R)
        s = z * (rays_w @ u_dual.T.astype(np.float32)) - (u_dual * offset).sum(1).astype(np.float32)
        t = z * (rays_w @ v_dual.T.astype(np.float32)) - (v_dual * offset).sum(1).astype(np.float32)
        hit = (z > 0) & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)
        depth = np.where(hit, z, np.inf).min(axis=1)
    return np.where(np.isfinite(depth), depth, np.nan).reshape(camera.height, camera.width)


def time_renders(scene, times: np.ndarray, repeats: int) -> tuple[float, float]:
    """Median frames/s over the repeats and median milliseconds per frame."""
    scene.render(float(times[0]))
    fps, per_frame = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        for t in times:
            t0 = time.perf_counter()
            scene.render(float(t))
            per_frame.append(time.perf_counter() - t0)
        fps.append(len(times) / (time.perf_counter() - start))
    return statistics.median(fps), 1e3 * statistics.median(per_frame)


def time_sequence(duration_s: float) -> tuple[float, int, int]:
    """Seconds to make and save ``duration_s`` of indoor_flying with events and ground truth."""
    import tempfile

    from cmax.sim import EventSimulator, simulate_scene

    start = time.perf_counter()
    scene = make_scene("indoor_flying", seed=0, width=346, height=260)
    sequence = simulate_scene(scene, duration_s, EventSimulator(**{**scene.recommended_simulator, "seed": 0}))
    with tempfile.TemporaryDirectory() as folder:
        sequence.save(Path(folder) / "sequence.h5")
    seconds = time.perf_counter() - start
    print(f"{duration_s:g} s of indoor_flying with ground truth: {seconds:.1f} s")
    return seconds, len(sequence.frame_t_us), len(sequence.events)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    parser.add_argument("--presets", nargs="*", default=list(PRESETS))
    parser.add_argument("--output", type=Path, default=RESULTS / "speed_scenes.md")
    parser.add_argument("--sequence-seconds", type=float, default=2.0,
                        help="length of the indoor_flying sequence timed end to end (0 to skip)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    load_before = os.getloadavg()
    rows = []
    for name in args.presets:
        build = time.perf_counter()
        scene = make_scene(name, seed=0, width=346, height=260)
        build = time.perf_counter() - build
        times = np.linspace(0.0, scene.info.duration_s, args.frames, endpoint=False)
        fps, ms = time_renders(scene, times, args.repeats)
        base_times = times[:: max(1, len(times) // 3)][:3]
        start = time.perf_counter()
        for t in base_times:
            numpy_depth(scene, scene.pose(float(t)))
        base_fps = len(base_times) / (time.perf_counter() - start)
        rows.append((name, len(scene.world), build, fps, ms, base_fps))
        print(f"{name:14s} {len(scene.world):5d} parallelograms  {fps:7.1f} frames/s  "
              f"({ms:.2f} ms median)  numpy baseline {base_fps:6.2f} frames/s  x{fps / base_fps:.0f}")
    single = None
    if "indoor_flying" in args.presets and torch.get_num_threads() > 1:  # robust to other processes
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        scene = make_scene("indoor_flying", seed=0, width=346, height=260)
        times = np.linspace(0.0, scene.info.duration_s, args.frames, endpoint=False)
        single = time_renders(scene, times, args.repeats)
        torch.set_num_threads(threads)
        print(f"indoor_flying with 1 torch thread: {single[0]:.1f} frames/s ({single[1]:.2f} ms median)")
    sequence = time_sequence(args.sequence_seconds) if args.sequence_seconds > 0 else None
    load_after = os.getloadavg()
    lines = [
        "# Rendering speed of the synthetic scenes",
        "",
        "`python benchmarks/speed_scenes.py` -- intensity and depth at 346x260, textures 512 texels,",
        f"{args.frames} frames spread over each 10 s trajectory, median of {args.repeats} repeats after a warm-up.",
        "Baseline (same run, 3 frames): numpy ray casting of all parallelograms against all pixels,",
        "float32, depth only (no textures).",
        "",
        f"Machine: {platform.platform()}, {os.cpu_count()} CPUs, torch {torch.__version__} with "
        f"{torch.get_num_threads()} threads; load average before/after: "
        f"{load_before[0]:.2f} / {load_after[0]:.2f} (other processes slow the timings down).",
        "",
        "| preset | parallelograms | build [s] | frames/s | ms/frame (median) | numpy baseline frames/s | speed-up |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, count, build, fps, ms, base_fps in rows:
        lines.append(f"| {name} | {count} | {build:.2f} | {fps:.0f} | {ms:.2f} | {base_fps:.2f} | {fps / base_fps:.0f}x |")
    if single is not None:
        lines += ["", f"`indoor_flying` with 1 torch thread (other processes hurt it less): {single[0]:.0f} frames/s "
                      f"({single[1]:.2f} ms median)."]
    lines += ["", "Target: at least 200 frames/s for `indoor_flying` on 2 cores."]
    if sequence is not None:
        seconds, frames, events = sequence
        lines += ["", "## A whole sequence", "",
                  f"`simulate_scene` + `save` of {args.sequence_seconds:g} s of `indoor_flying` (seed 0, 346x260, "
                  f"adaptive sampling lam=0.5, ESIM C=0.2, depth maps at 20 Hz): **{seconds:.1f} s** for "
                  f"{frames} rendered frames and {events:,} events (target: under 60 s for 2 s)."]
    args.output.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.output, "\n".join(lines) + "\n")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
