"""Does the shared-objective polish (``FitSettings.polish``) help or hurt ``cmax.fit``? -> ``results/shared_polish.md``.

For each held-out window the same fit runs with ``polish="none"``, ``"depth"`` and ``"depth_motion"``
(interleaved, one window at a time, so load changes hit the three alike):

* ``depth``: ``fit(events, K, pose=T01, depth_range=preset's)`` (``depth_motion`` is ``depth`` there: the
  pose holds the motion);
* ``se3``: ``fit(events, K, speed=|v|, depth_range=preset's)``.

Windows: ``indoor_flying`` at 346x260 (the held-out windows of :mod:`benchmarks.accuracy_cmax`, seeds
100-119 or a subset) and other presets of :mod:`cmax.sim.presets` at 160x120 (the windows of
:mod:`benchmarks.objective_identifiability`). Figures: abs_rel on the fit's mask, the translation direction
error [deg], the RMS omega error [deg/s] (as :mod:`benchmarks.accuracy_cmax` scores them), seconds per
window, and the shared objective at the polish's start and end (its own log); medians and p90.

Usage::

    python -m benchmarks.shared_polish [--seeds 100-107] [--presets driving_day,hiking] [--preset-seeds 100-102]
                                       [--cache DIR] [--preset-cache DIR] [--models depth,se3]
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.accuracy_cmax import abs_rel, cached, parse_seeds, preset_depth_range
from benchmarks.synthetic_windows import preset_window
from cmax.fitting import fit
from cmax.io.atomic import write_text_atomic

RESULTS = Path(__file__).resolve().parent / "results"
MODES = {"depth": ("none", "depth"), "se3": ("none", "depth", "depth_motion")}


def run(window, model: str, polish: str, depth_range: tuple[float, float]) -> dict:
    """One fit of ``window`` with ``polish``: its errors, seconds and the polish's objective before/after."""
    v, omega = window.twist[:3], window.twist[3:]
    speed = float(np.linalg.norm(v))
    known = {"pose": window.T01} if model == "depth" else {"speed": speed}
    start = time.perf_counter()
    r = fit(window.events, window.K, depth_range=depth_range, polish=polish, **known)
    row = {"abs_rel": abs_rel(r, window.depth, depth_range), "seconds": time.perf_counter() - start}
    if model == "se3":
        cos = float(r.v @ v / (np.linalg.norm(r.v) * speed))
        row["direction_deg"] = float(np.degrees(np.arccos(np.clip(cos, -1, 1))))
        row["omega_rms_deg_s"] = float(np.degrees(np.sqrt(np.mean((r.omega - omega) ** 2))))
    for log in r.stages:
        if log.stage == "shared_polish":
            row["shared_before"], row["shared_after"] = log.objective_before, log.objective_after
            row["polish_seconds"], row["polish_iterations"] = log.seconds, log.iterations
    return row


def summarise(rows: list[dict], header: str) -> str:
    """The table (median, p90 per group, model, mode, figure) and the per-window lines."""
    groups = sorted({(r["group"], r["model"]) for r in rows}, key=lambda g: (g[0] != "indoor_flying", g))
    lines = [header, "", "| windows | model | polish | figure | median | p90 | n |", "|---|---|---|---|---|---|---|"]
    for group, model in groups:
        for mode in MODES[model]:
            mine = [r for r in rows if (r["group"], r["model"], r["polish"]) == (group, model, mode)]
            for figure in ("abs_rel", "direction_deg", "omega_rms_deg_s", "seconds", "shared_before", "shared_after"):
                values = np.array([r[figure] for r in mine if figure in r], float)
                values = values[np.isfinite(values)]
                if values.size:
                    lines.append(f"| {group} | {model} | {mode} | {figure} | {np.median(values):.4f} | "
                                 f"{np.percentile(values, 90):.4f} | {values.size} |")
    lines += ["", "Per window:", ""]
    for r in rows:
        figures = ", ".join(f"{k} {v:.4f}" for k, v in r.items() if isinstance(v, (int, float)) and k != "seed")
        lines.append(f"- {r['group']} seed {r['seed']} {r['model']} polish={r['polish']}: {figures}")
    return "\n".join(lines) + "\n"


def _header(args: argparse.Namespace, argv: list[str] | None, start: float, done: str) -> str:
    load_avg = f"{os.getloadavg()[0]:.2f}" if hasattr(os, "getloadavg") else "n/a"
    command = " ".join(["python -m benchmarks.shared_polish", *(argv if argv is not None else sys.argv[1:])])
    return (f"# cmax.fit with and without the shared-objective polish\n\nWritten by `{command}` ({done}) in "
            f"{time.perf_counter() - start:.0f} s on {platform.machine()}, torch threads 1; load average (1 min) "
            f"at the end {load_avg}. indoor_flying: 346x260, seeds {args.seeds} (held out); "
            f"{args.presets or 'no other presets'}: 160x120, seeds {args.preset_seeds}. Each fit is given the "
            f"preset's depth range and, for se3, the true speed.")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="100-107", help="indoor_flying 346x260 seeds (held out: 100-119)")
    parser.add_argument("--presets", default="driving_day,hiking", help="other presets at 160x120")
    parser.add_argument("--preset-seeds", default="100-102")
    parser.add_argument("--models", default="depth,se3")
    parser.add_argument("--cache", type=Path, default=None, help="folder of benchmarks.accuracy_cmax's windows")
    parser.add_argument("--preset-cache", type=Path, default=None,
                        help="folder of benchmarks.objective_identifiability's windows")
    parser.add_argument("--out", type=Path, default=RESULTS / "shared_polish.md")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    models = [m for m in args.models.split(",") if m]
    if set(models) - set(MODES):
        parser.error(f"--models: unknown {sorted(set(models) - set(MODES))}")
    jobs = []                                   # the small windows first: every group has figures early
    for preset in [p for p in args.presets.split(",") if p]:
        jobs += [(preset, seed, lambda p=preset, s=seed: cached(args.preset_cache, f"{p}_{s}_160x120",
                                                               lambda: preset_window(p, s, width=160, height=120)))
                 for seed in parse_seeds(parser, args.preset_seeds)]
    jobs += [("indoor_flying", seed, lambda s=seed: cached(args.cache, f"indoor_flying_{s}",
                                                           lambda: preset_window("indoor_flying", s)))
             for seed in parse_seeds(parser, args.seeds)]
    rows, start = [], time.perf_counter()
    for number, (group, seed, load) in enumerate(jobs, 1):
        window = load()
        depth_range = preset_depth_range(group)
        for model in models:
            for mode in MODES[model]:
                row = run(window, model, mode, depth_range)
                rows.append({"group": group, "seed": seed, "model": model, "polish": mode, **row})
                print(f"{group} {seed} {model} polish={mode}: " + ", ".join(
                    f"{k} {v:.4f}" for k, v in row.items()), flush=True)
        write_text_atomic(args.out, summarise(rows, _header(args, argv, start, f"{number} of {len(jobs)} windows")))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
