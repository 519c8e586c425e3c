"""What the warm start of ``cmax.fit(..., init=)`` (as ``fit_sequence`` passes it) does to se3, written to
``benchmarks/results/warm_start_cmax.md``.

For each held-out ``indoor_flying`` seed the window of :mod:`benchmarks.accuracy_cmax` (0.1665 s from
0.5 s) is fitted twice with the known speed and the room's depth range: cold, and warm-started from the
fit of the window just before it (0.1665 s from 0.3335 s), as ``fit_sequence`` does. Reported per
window and as medians: seconds, translation direction error [deg], omega RMS error [deg/s], depth
abs_rel, the patch-wise objective at the end of the refinement (lower is better), and whether the warm
start's refined start won.

Usage::

    python -m benchmarks.warm_start_cmax [--seeds 100-109] [--cache DIR]
"""
from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.accuracy_cmax import abs_rel, cached, parse_seeds, preset_depth_range
from benchmarks.synthetic_windows import preset_window
from cmax.fitting import fit
from cmax.io.atomic import write_text_atomic

RESULTS = Path(__file__).resolve().parent / "results"
PREVIOUS_T0_S = 0.5 - 0.1665


def scores(result, window, depth_range, seconds: float) -> dict:
    v, omega = window.twist[:3], window.twist[3:]
    cos = float(result.v @ v / (np.linalg.norm(result.v) * np.linalg.norm(v)))
    return {"seconds": seconds, "direction_deg": float(np.degrees(np.arccos(np.clip(cos, -1, 1)))),
            "omega_rms_deg_s": float(np.degrees(np.sqrt(np.mean((result.omega - omega) ** 2)))),
            "abs_rel": abs_rel(result, window.depth, depth_range),
            "refine_objective": result.stages[1].objective_after}


def run(seed: int, cache: Path | None) -> dict:
    depth_range = preset_depth_range("indoor_flying")
    window = cached(cache, f"indoor_flying_{seed}", lambda: preset_window("indoor_flying", seed))
    before = cached(cache, f"indoor_flying_prev_{seed}",
                    lambda: preset_window("indoor_flying", seed, t0_s=PREVIOUS_T0_S))
    speed = float(np.linalg.norm(window.twist[:3]))
    previous = fit(before.events, before.K, speed=float(np.linalg.norm(before.twist[:3])), depth_range=depth_range)
    rows = {}
    for name, init in (("cold", None), ("warm", previous)):
        start = time.perf_counter()
        result = fit(window.events, window.K, speed=speed, depth_range=depth_range, init=init)
        rows[name] = scores(result, window, depth_range, time.perf_counter() - start)
    rows["warm"]["warm_start_won"] = float(rows["warm"]["refine_objective"] < rows["cold"]["refine_objective"])
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="100-109")
    parser.add_argument("--cache", type=Path, default=None)
    args = parser.parse_args(argv)
    seeds = parse_seeds(parser, args.seeds)
    torch.set_num_threads(1)
    start = time.perf_counter()
    rows = []
    for seed in seeds:
        rows.append(run(seed, args.cache))
        print(seed, {k: {m: round(v, 3) for m, v in r.items()} for k, r in rows[-1].items()}, flush=True)
    lines = ["# Warm start of se3 (`fit(..., init=previous window)`) on held-out windows", "",
             f"indoor_flying seeds {seeds[0]}-{seeds[-1]}, 346x260, known speed, depth range 1-6.5 m; the warm "
             f"start is the fit of the window before (from {PREVIOUS_T0_S:.4f} s). Machine: "
             f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch threads 1; load average "
             f"(1 min) at the end {os.getloadavg()[0]:.2f}; {time.perf_counter() - start:.0f} s. Written by "
             "`python -m benchmarks.warm_start_cmax`.", "",
             "| figure | cold median | warm median | cold p90 | warm p90 |", "|---|---|---|---|---|"]
    for key in rows[0]["cold"]:
        cold = np.array([r["cold"][key] for r in rows])
        warm = np.array([r["warm"][key] for r in rows])
        lines.append(f"| {key} | {np.median(cold):.3f} | {np.median(warm):.3f} | {np.percentile(cold, 90):.3f} | "
                     f"{np.percentile(warm, 90):.3f} |")
    won = sum(r["warm"]["warm_start_won"] for r in rows)
    lines += ["", f"The warm start's refined start won (a lower patch-wise objective than the cold fit's) on "
              f"{won:.0f} of {len(rows)} windows.", "", "Per window:", ""]
    for seed, r in zip(seeds, rows):
        for name in ("cold", "warm"):
            lines.append(f"- seed {seed} {name}: " + ", ".join(f"{k} {v:.3f}" for k, v in r[name].items()))
    RESULTS.mkdir(exist_ok=True)
    text = "\n".join(lines) + "\n"
    write_text_atomic(RESULTS / "warm_start_cmax.md", text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
