"""``cmax.fit`` se3 (or depth) seconds per window of two checkouts of the project, interleaved window by window.

What a change to the fit's code buys in time, measured the way the accuracy benchmark fits (held-out
``indoor_flying`` windows, 346x260, ``speed=|v|`` (``--model depth``: ``pose=`` the true motion) and the
preset's depth range, fit seed 0, one torch thread, verdict included): each checkout runs in a worker process of its own (its own modules and numba
cache), both warmed up by one fit, then every window is fitted by both, the order alternating from
window to window so that both see the same load. Reported: the medians, and the median per-window ratio.
The two sides' fits are not compared here (``benchmarks.se3_variants`` and ``benchmarks.accuracy_cmax``
judge accuracy).

Usage::

    git worktree add /tmp/before <rev>
    python -m benchmarks.speed_fit_ab --before /tmp/before [--after .] [--seeds 100-119] [--cache DIR]
        [--model se3|depth]

Writes ``benchmarks/results/speed_fit_ab.md``.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from benchmarks.accuracy_cmax import RESULTS, parse_seeds
from benchmarks.machine import describe
from cmax.io.atomic import write_text_atomic

#: The worker, run with ``python -c`` in a checkout (so it needs nothing of this file there): reads window
#: seeds on stdin, prints one JSON line per fit; argv: the cache folder (or -), the warm-up seed, the model.
WORKER = """
import json, sys, time, warnings
from pathlib import Path
import numpy as np, torch
torch.set_num_threads(1)
from benchmarks.accuracy_cmax import _room, windows
from cmax import fit
cache = None if sys.argv[1] == "-" else Path(sys.argv[1])
def given(w):
    if sys.argv[3] == "depth":
        return {"pose": w.T01}
    return {"speed": float(np.linalg.norm(w.twist[:3]))}
w = windows("se3", int(sys.argv[2]), cache)
fit(w.events, w.K, **given(w), **_room())
print("ready", flush=True)
for line in sys.stdin:
    w = windows("se3", int(line), cache)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        start, cpu = time.perf_counter(), time.process_time()
        fit(w.events, w.K, **given(w), **_room())
    print(json.dumps({"seconds": time.perf_counter() - start, "cpu_seconds": time.process_time() - cpu}), flush=True)
"""


def _revision(root: Path) -> str:
    out = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no", "--", "cmax"],
                           capture_output=True, text=True).stdout.strip()
    return (out.stdout.strip() or "unknown") + (" + uncommitted changes to cmax/" if dirty else "")


def _worker(root: Path, cache: Path | None, warm_seed: int, model: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(root), OMP_NUM_THREADS="1")
    process = subprocess.Popen([sys.executable, "-c", WORKER, str(cache) if cache else "-", str(warm_seed), model],
                               cwd=root, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    line = process.stdout.readline().strip()
    if line != "ready":
        process.kill()
        raise RuntimeError(f"the worker in {root} did not start (got {line!r}); see its stderr above")
    return process


def _fit(process: subprocess.Popen, seed: int) -> tuple[float, float]:
    process.stdin.write(f"{seed}\n")
    process.stdin.flush()
    line = json.loads(process.stdout.readline())
    return float(line["seconds"]), float(line.get("cpu_seconds", float("nan")))


def run(roots: dict[str, Path], seeds: list[int], cache: Path | None, model: str = "se3",
        cpu: dict[str, list[float]] | None = None) -> dict[str, list[float]]:
    """Wall seconds per window of each checkout fitting ``model`` (``se3`` with the speed, ``depth`` with the
    pose), the order of the two alternating from window to window; each fit's CPU seconds of the worker process
    (``time.process_time``) appended to ``cpu`` (per checkout) when given."""
    workers = {name: _worker(root, cache, seeds[0], model) for name, root in roots.items()}
    seconds: dict[str, list[float]] = {name: [] for name in roots}
    try:
        for i, seed in enumerate(seeds):
            for name in (list(workers) if i % 2 == 0 else list(workers)[::-1]):
                wall, used = _fit(workers[name], seed)
                seconds[name].append(wall)
                if cpu is not None:
                    cpu.setdefault(name, []).append(used)
            print(seed, {name: round(values[-1], 2) for name, values in seconds.items()}, flush=True)
    finally:
        for process in workers.values():
            process.stdin.close()
            process.wait(timeout=60)
    return seconds


def report(roots: dict[str, Path], seconds: dict[str, list[float]], seeds: list[int], loads: tuple[float, float],
           command: str, model: str = "se3", cpu: dict[str, list[float]] | None = None) -> str:
    before, after = seconds["before"], seconds["after"]
    ratios = [b / a for b, a in zip(before, after)]
    lines = [f"# `cmax.fit` {model} seconds per window: two checkouts, interleaved", "",
             f"Written by `{command}`: `indoor_flying` seeds {seeds[0]}-{seeds[-1]} (held out), 346x260, "
             f"{'`pose=` the true motion' if model == 'depth' else '`speed=|v|`'}, the preset's depth range, fit seed 0, one torch thread, verdict included; each checkout "
             "in a worker process of its own, warmed up by one fit, the two fitting each window in turn (the order "
             f"alternating). Machine: {describe()}; load "
             f"average (1 min) {loads[0]:.2f} before, {loads[1]:.2f} after.", "",
             "| checkout | revision | median [s] | p90 [s] |", "|---|---|---:|---:|"]
    for name, root in roots.items():
        values = sorted(seconds[name])
        lines.append(f"| {name} | {_revision(root)} | {statistics.median(values):.3f} | "
                     f"{values[max(0, int(round(0.9 * len(values))) - 1)]:.3f} |")
    lines += ["", f"Per-window ratio before / after: median {statistics.median(ratios):.2f}, range "
              f"{min(ratios):.2f}-{max(ratios):.2f}.", "",
              "Per window [s] (seed: before, after): "
              + "; ".join(f"{s}: {b:.2f}, {a:.2f}" for s, b, a in zip(seeds, before, after)), ""]
    if cpu is not None and all(cpu.get(name) for name in ("before", "after")):
        cpu_ratios = [b / a for b, a in zip(cpu["before"], cpu["after"])]
        lines += [f"CPU seconds of each worker process per window (`time.process_time`: less moved by other "
                  f"processes' load than the wall clock): median {statistics.median(cpu['before']):.3f} before, "
                  f"{statistics.median(cpu['after']):.3f} after; per-window ratio before / after: median "
                  f"{statistics.median(cpu_ratios):.2f}, range {min(cpu_ratios):.2f}-{max(cpu_ratios):.2f}.", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", type=Path, required=True, help="checkout of the earlier revision")
    parser.add_argument("--after", type=Path, default=Path(__file__).resolve().parents[1],
                        help="checkout of the later revision (default: this one)")
    parser.add_argument("--seeds", default="100-119")
    parser.add_argument("--cache", type=Path, default=None, help="folder of simulated windows (shared by both)")
    parser.add_argument("--output", type=Path, default=RESULTS / "speed_fit_ab.md")
    parser.add_argument("--model", choices=("se3", "depth"), default="se3",
                        help="se3: fit with the speed (default); depth: with the pose (the true motion)")
    args = parser.parse_args(argv)
    seeds = parse_seeds(parser, args.seeds)
    roots = {"before": args.before.resolve(), "after": args.after.resolve()}
    for name, root in roots.items():
        if not (root / "cmax" / "__init__.py").is_file():
            parser.error(f"--{name} {root} is not a checkout of this project (no cmax/__init__.py)")
    load_before = os.getloadavg()[0]
    cpu: dict[str, list[float]] = {}
    seconds = run(roots, seeds, args.cache, args.model, cpu)
    command = "python -m benchmarks.speed_fit_ab " + " ".join(sys.argv[1:] if argv is None else argv)
    text = report(roots, seconds, seeds, (load_before, os.getloadavg()[0]), command, args.model, cpu)
    write_text_atomic(args.output, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
