"""Inference speed of the depth-pose network against ``cmax.fit``, per window, at 346x260 (same run).

For each window (``indoor_flying`` preset windows of :func:`benchmarks.synthetic_windows.preset_window`,
held-out seeds 100, 101, ...; 0.1665 s):

* the network (default :class:`learned.model.ModelConfig`, untrained weights: speed does not
  depend on them): milliseconds per window, batch 1, ``torch.no_grad``, forward only and
  event volume + forward; median of ``--repeats`` after a warm-up;
* ``cmax.fit(events, K, "se3", speed=|v|)`` (known speed, the scipy solver, 1 thread as its
  default): seconds per window, one run each after one warm-up fit.

The amortization factor is fit seconds / network seconds. Writes ``results/speed_learned.md``.

Usage::

    python -m benchmarks.speed_learned [--windows 3] [--repeats 7] [--threads 1]
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

RESULTS = Path(__file__).resolve().parent / "results"


def _median_ms(function, repeats: int) -> float:
    function()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> int:
    import cmax
    from cmax.representations import voxel_grid
    from benchmarks.synthetic_windows import preset_window
    from learned.model import DepthPoseNet, ModelConfig

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--windows", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=1, help="torch threads of the network (fit uses 1)")
    parser.add_argument("--output", type=Path, default=RESULTS / "speed_learned.md")
    args = parser.parse_args(argv)
    load_before = os.getloadavg()[0]
    torch.set_num_threads(args.threads)
    model = DepthPoseNet(ModelConfig()).eval()
    parameters = sum(p.numel() for p in model.parameters())
    windows = [preset_window("indoor_flying", 100 + k, texture_size=256) for k in range(args.windows)]
    rows = []
    warm = windows[0]
    cmax.fit(warm.events, warm.K, "se3", speed=float(np.linalg.norm(warm.twist[:3])))
    for w in windows:
        volume = torch.from_numpy(voxel_grid(w.events, 5))[None]
        with torch.no_grad():
            forward_ms = _median_ms(lambda: model(volume), args.repeats)
            full_ms = _median_ms(lambda: model(torch.from_numpy(voxel_grid(w.events, 5))[None]), args.repeats)
        start = time.perf_counter()
        cmax.fit(w.events, w.K, "se3", speed=float(np.linalg.norm(w.twist[:3])))
        fit_s = time.perf_counter() - start
        rows.append((w.seed, len(w.events), forward_ms, full_ms, fit_s))
    load_after = os.getloadavg()[0]
    lines = [
        "# Inference speed of the depth-pose network versus cmax.fit",
        "",
        f"`python -m benchmarks.speed_learned --windows {args.windows} --repeats {args.repeats} --threads {args.threads}`"
        f" -- 346x260 `indoor_flying` preset windows of 0.1665 s (seeds 100-{99 + args.windows}); network: default "
        f"`ModelConfig` ({parameters:,} parameters), batch 1, CPU, {args.threads} torch thread(s), median of "
        f"{args.repeats} after a warm-up; `cmax.fit(..., 'se3', speed=|v|)`: one run per window after a warm-up fit, "
        "1 thread (its default).",
        "",
        f"Machine: {platform.platform()}, {os.cpu_count()} CPUs, torch {torch.__version__}; 1-minute load average "
        f"before/after: {load_before:.2f} / {load_after:.2f} (other processes share the cores; compare the ratios).",
        "",
        "| window (seed) | events | network forward [ms] | volume + forward [ms] | cmax.fit se3 [s] | amortization (fit / volume+forward) |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for seed, n, forward_ms, full_ms, fit_s in rows:
        lines.append(f"| {seed} | {n:,} | {forward_ms:.1f} | {full_ms:.1f} | {fit_s:.2f} | {fit_s * 1e3 / full_ms:.0f}x |")
    med = [statistics.median(c) for c in zip(*[r[2:] for r in rows])]
    lines += [f"| median | | {med[0]:.1f} | {med[1]:.1f} | {med[2]:.2f} | {med[2] * 1e3 / med[1]:.0f}x |", ""]
    write_text_atomic(args.output, "\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
