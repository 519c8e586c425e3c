"""Do the three solvers of ``cmax.fit`` reach the same optimum on the default se3 path? Written to
``benchmarks/results/solver_agreement.md``.

For each held-out ``indoor_flying`` seed the window of :mod:`benchmarks.accuracy_cmax` (346x260, 0.1665 s from
0.5 s) is fitted with the known speed and the room's depth range by ``solver="scipy"`` (L-BFGS-B),
``"casadi"`` (IPOPT, ``|v| = speed`` as an equality constraint) and ``"torch"`` (Adam). Reported per window:
the motion refinement's own (patch-wise) objective at its end (lower is better) and its gap to L-BFGS-B's
[%], the fit's normalised contrast, whether every stage succeeded (a stage fails when its solver ended worse
than its start, so the start was kept, or on a bound), the translation direction error [deg] and the seconds.

Usage::

    python -m benchmarks.solver_agreement [--seeds 100-109] [--cache DIR]
"""
from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.accuracy_cmax import cached, parse_seeds, preset_depth_range
from benchmarks.synthetic_windows import preset_window
from cmax.fitting import fit
from cmax.io.atomic import write_text_atomic

RESULTS = Path(__file__).resolve().parent / "results"
SOLVERS = ("scipy", "casadi", "torch")


def run(seed: int, cache: Path | None) -> dict[str, dict]:
    """Each solver's figures on one held-out window."""
    depth_range = preset_depth_range("indoor_flying")
    window = cached(cache, f"indoor_flying_{seed}", lambda: preset_window("indoor_flying", seed))
    speed = float(np.linalg.norm(window.twist[:3]))
    rows = {}
    for solver in SOLVERS:
        start = time.perf_counter()
        result = fit(window.events, window.K, speed=speed, depth_range=depth_range, solver=solver)
        seconds = time.perf_counter() - start
        cos = float(result.v @ window.twist[:3] / (np.linalg.norm(result.v) * speed))
        rows[solver] = {"refine": result.stages[1].objective_after, "contrast": result.objective_after,
                        "success": result.success, "failed": [s.stage for s in result.stages if not s.success],
                        "direction_deg": float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))), "seconds": seconds}
    for solver in SOLVERS:
        rows[solver]["gap_pct"] = 100.0 * (rows[solver]["refine"] - rows["scipy"]["refine"]) / abs(rows["scipy"]["refine"])
    return rows


def report(per_seed: dict[int, dict], seconds: float, load: float) -> str:
    lines = ["# The three solvers on the default se3 path", "",
             f"`python -m benchmarks.solver_agreement`: held-out `indoor_flying` seeds {min(per_seed)}-{max(per_seed)}, "
             f"346x260, 0.1665 s windows, known speed and depth range; {seconds:.0f} s on one thread "
             f"({platform.machine()}, load average (1 min) at the start {load:.2f}). `refine`: the motion "
             "refinement's patch-wise objective at its end (lower is better), `gap`: against L-BFGS-B's; `contrast`: "
             "the fit's normalised contrast (higher is sharper); `ok`: every stage succeeded.", "",
             "## Summary", "",
             "| solver | largest gap to scipy [%] | median gap [%] | fits with a failed stage | direction error median [deg] "
             "| seconds median |", "|---|---:|---:|---:|---:|---:|"]
    for solver in SOLVERS:
        gaps = np.array([r[solver]["gap_pct"] for r in per_seed.values()])
        lines.append(f"| {solver} | {gaps[np.argmax(np.abs(gaps))]:+.2f} | {np.median(gaps):+.2f} | "
                     f"{sum(not r[solver]['success'] for r in per_seed.values())} of {len(per_seed)} | "
                     f"{np.median([r[solver]['direction_deg'] for r in per_seed.values()]):.1f} | "
                     f"{np.median([r[solver]['seconds'] for r in per_seed.values()]):.2f} |")
    lines += ["", "## Per window", "",
              "| seed | " + " | ".join(f"{s} refine / contrast / ok / dir [deg] / s" for s in SOLVERS) + " | casadi gap [%] "
              "| torch gap [%] |", "|---|" + "---|" * (len(SOLVERS) + 2)]
    for seed, rows in per_seed.items():
        cells = [f"{rows[s]['refine']:.3f} / {rows[s]['contrast']:.4f} / "
                 f"{'yes' if rows[s]['success'] else 'no (' + ', '.join(rows[s]['failed']) + ')'} / "
                 f"{rows[s]['direction_deg']:.1f} / {rows[s]['seconds']:.1f}" for s in SOLVERS]
        lines.append(f"| {seed} | " + " | ".join(cells) + f" | {rows['casadi']['gap_pct']:+.2f} | "
                     f"{rows['torch']['gap_pct']:+.2f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="100-109", help="held-out 100-119")
    parser.add_argument("--cache", type=Path, default=None, help="folder to keep simulated windows between runs")
    parser.add_argument("--out", type=Path, default=RESULTS / "solver_agreement.md")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    load, start = os.getloadavg()[0], time.perf_counter()
    per_seed = {}
    for seed in parse_seeds(parser, args.seeds):
        per_seed[seed] = run(seed, args.cache)
        print(seed, {s: f"{r['gap_pct']:+.2f}% ok={r['success']}" for s, r in per_seed[seed].items()}, flush=True)
    text = report(per_seed, time.perf_counter() - start, load)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.out, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
