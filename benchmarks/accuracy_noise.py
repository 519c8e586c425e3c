"""How much the held-out accuracy figures of ``cmax.fit`` move with the fit's own arbitrary choices.

``benchmarks.accuracy_cmax`` fits each held-out window once, with ``FitSettings.seed = 0``: the seed of
the fit's uniform subsample (windows above ``max_events``) and of its sub-pixel dither of the event
coordinates. Any other seed is an equally valid fit of the same events, so the spread of a figure over
fit seeds is the noise of that figure: the size of a change that says nothing about the method (float
rounding moves the fits in the same way).

For each model (``se3``, ``depth``: the fits of ``accuracy_cmax``, with the preset's depth range) and
each fit seed, the median and 90th percentile of every figure over the windows; then, per figure, the
range of those medians and p90s over the fit seeds, and where the reference figures (``--reference``, an
``accuracy_cmax`` report, e.g. the one an issue compares against) lie in it.

``--against-tree PATH`` (a checkout of another version, e.g. ``git worktree add /tmp/before REV``) fits
the same windows with the same seeds with that version's ``cmax`` as well, in a second process running
at the same time (one thread each, so the seconds compare on a 2-core machine with nothing else
running), and adds the before/after table: both versions' figures averaged over the seeds, pooled over
all fits, the pooled figure's difference with its 90% interval over the windows (a paired bootstrap
that resamples whole windows, each with all its fit seeds in both versions: the windows are the
independent draws, the seeds of one window are not), and paired fit by fit (same window, same seed).
A difference whose interval holds 0 is within the noise of the held-out set.

The fits run in :mod:`benchmarks.accuracy_noise_worker` processes on exported windows, so the other
version needs nothing of this checkout's ``benchmarks``. Written to ``benchmarks/results/accuracy_noise.md``.

Usage::

    python -m benchmarks.accuracy_noise [--seeds 100-119] [--fit-seeds 0-4] [--models se3,depth] [--cache DIR]
                                        [--reference FILE] [--against-tree PATH]
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.accuracy_cmax import RESULTS, _room, parse_names, parse_seeds, windows
from benchmarks.machine import describe
from cmax.io.atomic import write_text_atomic

ROOT = Path(__file__).resolve().parents[1]
WORKER = Path(__file__).resolve().with_name("accuracy_noise_worker.py")
MODELS = ("se3", "depth")
#: Figures reported (the ones ``accuracy_cmax`` gives a target).
FIGURES = {"se3": ("abs_rel", "direction_deg", "omega_rms_deg_s"), "depth": ("abs_rel",)}


def reference_figures(text: str) -> dict[tuple[str, str], tuple[float, float]]:
    """``{(model, figure): (median, p90)}`` of the rows ``| model | figure | median | p90 | ...`` of an
    ``accuracy_cmax.md`` report (its first table: all windows)."""
    figures = {}
    for model, figure, median, p90 in re.findall(r"^\| (\w+) \| (\w+) \| ([\d.]+) \| ([\d.]+) \|", text, re.M):
        figures.setdefault((model, figure), (float(median), float(p90)))
    return figures


def statistics(results: list[dict], figure: str) -> tuple[float, float]:
    """Median and 90th percentile of ``figure`` over the windows' ``results``."""
    values = np.array([r[figure] for r in results], float)
    return float(np.nanmedian(values)), float(np.nanpercentile(values, 90))


def where(value: float, low: float, high: float) -> str:
    """Where ``value`` lies against the range ``[low, high]`` of the fit seeds' figures."""
    if value < low:
        return "below the range"
    if value > high:
        return "above the range"
    return "within"


def summarise(rows: dict[str, dict[int, list[dict]]], seeds: list[int], fit_seeds: list[int],
              reference: dict[tuple[str, str], tuple[float, float]], reference_name: str, seconds: float) -> str:
    """The markdown report (see the module docstring)."""
    lines = ["# Noise of the held-out accuracy figures over the fit's seed", "",
             f"Held-out windows {seeds[0]}-{seeds[-1]} (346x260, `indoor_flying`, as `benchmarks.accuracy_cmax`), "
             f"each fitted with `FitSettings.seed` = {fit_seeds[0]}-{fit_seeds[-1]} (the seed of the fit's "
             "subsample and sub-pixel dither; `accuracy_cmax` uses 0). Written by `python -m "
             f"benchmarks.accuracy_noise` in {seconds:.0f} s on {describe()}, "
             "torch threads 1. Lower is better for every figure.", "",
             "| model | figure | statistic | " + " | ".join(f"seed {s}" for s in fit_seeds)
             + f" | range over seeds | {reference_name} | where |",
             "|---|---|---|" + "---:|" * len(fit_seeds) + "---|---:|---|"]
    for model, by_seed in rows.items():
        for figure in FIGURES[model]:
            stats = {s: statistics(by_seed[s], figure) for s in fit_seeds}
            for k, name in enumerate(("median", "p90")):
                values = [stats[s][k] for s in fit_seeds]
                low, high = min(values), max(values)
                ref = reference.get((model, figure))
                ref_text = "" if ref is None else f"{ref[k]:.3f}"
                lines.append(f"| {model} | {figure} | {name} | " + " | ".join(f"{v:.3f}" for v in values)
                             + f" | {low:.3f}-{high:.3f} | {ref_text} | "
                             + ("" if ref is None else where(ref[k], low, high)) + " |")
    lines += ["", "Per window, the figure at each fit seed:", ""]
    for model, by_seed in rows.items():
        for figure in FIGURES[model]:
            lines.append(f"- {model} {figure}: " + "; ".join(
                f"{seed}: " + " ".join(f"{by_seed[s][i][figure]:.3g}" for s in fit_seeds)
                for i, seed in enumerate(seeds)))
    return "\n".join(lines) + "\n"


def export_windows(folder: Path, seeds: list[int], cache: Path | None) -> None:
    """One ``window_<seed>.npz`` per held-out window in ``folder`` (the worker's input): the ``indoor_flying``
    window that ``accuracy_cmax`` fits as both ``se3`` and ``depth``."""
    depth_range = np.asarray(_room()["depth_range"], float)
    for seed in seeds:
        w = windows("se3", seed, cache)
        e = w.events
        np.savez(folder / f"window_{seed}.npz", x=e.x, y=e.y, t=e.t, p=e.p, width=e.width, height=e.height,
                 K=w.K, twist=w.twist, T01=w.T01, depth=w.depth, depth_range=depth_range)


def run_workers(folder: Path, models: list[str], fit_seeds: list[int], trees: dict[str, Path]
                ) -> dict[str, list[dict]]:
    """Fit every exported window as each of ``models`` at every fit seed with each tree's ``cmax`` (a worker
    process per tree, all at once, one thread each); ``{tree name: rows}``, printing the progress."""
    total = len(list(folder.glob("window_*.npz"))) * len(models) * len(fit_seeds)
    outputs, processes = {}, {}
    for name, tree in trees.items():
        outputs[name] = folder / f"{name}.jsonl"
        env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1"}
        with open(outputs[name], "w") as out:
            processes[name] = subprocess.Popen([sys.executable, str(WORKER), str(folder), ",".join(map(str, fit_seeds)),
                                                ",".join(models)], stdout=out, env=env, cwd=folder)
    while any(p.poll() is None for p in processes.values()):
        time.sleep(5)
        done = {name: len(path.read_text().splitlines()) for name, path in outputs.items()}
        print(" | ".join(f"{name}: {n}/{total} fits" for name, n in done.items()), flush=True)
    for name, process in processes.items():
        if process.returncode != 0:
            raise SystemExit(f"the {name} worker ({trees[name]}) failed with exit status {process.returncode}")
    return {name: [json.loads(line) for line in path.read_text().splitlines()] for name, path in outputs.items()}


def by_model_and_seed(rows: list[dict], fit_seeds: list[int]) -> dict[str, dict[int, list[dict]]]:
    """The worker's rows grouped ``{model: {fit seed: rows in window order}}``."""
    grouped: dict[str, dict[int, list[dict]]] = {}
    for row in sorted(rows, key=lambda r: r["window"]):
        grouped.setdefault(row["model"], {s: [] for s in fit_seeds})[row["fit_seed"]].append(row)
    return grouped


#: Bootstrap draws of the paired difference's interval, and the generator's seed (the report is reproducible).
BOOTSTRAP_DRAWS = 2000
BOOTSTRAP_SEED = 0


def pooled_difference_interval(before: np.ndarray, after: np.ndarray, k: int, draws: int = BOOTSTRAP_DRAWS,
                               seed: int = BOOTSTRAP_SEED) -> tuple[float, float, float]:
    """The pooled statistic's difference ``after - before`` (``k`` 0: median, 1: 90th percentile over all
    fits) and its 90% interval over the windows: ``before`` and ``after`` (windows, fit seeds) are resampled
    together by whole windows (rows), ``draws`` times. Returns ``(difference, low, high)``."""
    stat = (np.nanmedian, lambda v: np.nanpercentile(v, 90))[k]
    difference = float(stat(after.ravel()) - stat(before.ravel()))
    rows = np.random.default_rng(seed).integers(0, before.shape[0], size=(draws, before.shape[0]))
    spread = np.array([stat(after[r].ravel()) - stat(before[r].ravel()) for r in rows])
    low, high = np.percentile(spread, [5, 95])
    return difference, float(low), float(high)


def _verdict(low: float, high: float) -> str:
    """Lower is better: where a difference's interval lies against 0."""
    return "better" if high < 0 else "worse" if low > 0 else "within noise"


def compare(before: dict[str, dict[int, list[dict]]], after: dict[str, dict[int, list[dict]]],
            fit_seeds: list[int], names: tuple[str, str]) -> list[str]:
    """The before/after table (see the module docstring): per figure and statistic the mean over the fit
    seeds, the pooled figure over all fits with the difference's interval over the windows, and the fits
    where ``after`` is lower (better) than ``before``."""
    lines = [f"| model | figure | statistic | {names[0]}: mean over seeds | {names[1]}: mean over seeds | "
             f"{names[0]}: all fits pooled | {names[1]}: all fits pooled | pooled difference (90% interval "
             "over windows) | |", "|---|---|---|---:|---:|---:|---:|---:|---|"]
    paired = []
    for model in after:
        for figure in (*FIGURES[model], "seconds"):
            grids = [np.array([[r[figure] for r in side[model][s]] for s in fit_seeds], float).T
                     for side in (before, after)]                                # (windows, fit seeds)
            for k, name in enumerate(("median", "p90")):
                means = [np.mean([statistics(side[model][s], figure)[k] for s in fit_seeds])
                         for side in (before, after)]
                pooled = [statistics([r for s in fit_seeds for r in side[model][s]], figure)[k]
                          for side in (before, after)]
                difference, low, high = pooled_difference_interval(*grids, k)
                lines.append(f"| {model} | {figure} | {name} | {means[0]:.3f} | {means[1]:.3f} | {pooled[0]:.3f} | "
                             f"{pooled[1]:.3f} | {difference:+.3f} ({low:+.3f} to {high:+.3f}) | "
                             f"{_verdict(low, high)} |")
            matched = [(b, a) for s in fit_seeds for b, a in zip(before[model][s], after[model][s], strict=True)]
            if any(b["window"] != a["window"] for b, a in matched):
                raise ValueError(f"{model}: the two versions' fits are not of the same windows")
            pairs = [(b[figure], a[figure]) for b, a in matched]
            diff = np.array([a - b for b, a in pairs])
            paired.append(f"- {model} {figure}: {names[1]} lower in {int(np.sum(diff < 0))} of {diff.size} fits, "
                          f"higher in {int(np.sum(diff > 0))}; median difference {np.median(diff):+.4g}")
    return lines + ["", f"Fit by fit (same window, same seed), {names[1]} against {names[0]}:", "", *paired]


def main(argv: list[str] | None = None) -> int:
    """Fit every window with every fit seed (and with the other tree's ``cmax``), write the report; returns 0."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="100-119", help="held-out windows, first-last")
    parser.add_argument("--fit-seeds", default="0-4", help="FitSettings.seed values, first-last")
    parser.add_argument("--models", default=",".join(MODELS))
    parser.add_argument("--cache", type=Path, default=None, help="folder to keep simulated windows between runs")
    parser.add_argument("--reference", type=Path, default=RESULTS / "accuracy_cmax.md",
                        help="an accuracy_cmax report whose figures are placed in the ranges")
    parser.add_argument("--reference-name", default=None, help="the reference's column title (default: its path)")
    parser.add_argument("--against-tree", type=Path, default=None,
                        help="a checkout of another version whose cmax fits the same windows (before/after table)")
    parser.add_argument("--against-name", default=None, help="that version's name in the report (default: its path)")
    parser.add_argument("-o", "--output", type=Path, default=RESULTS / "accuracy_noise.md")
    args = parser.parse_args(argv)
    seeds = parse_seeds(parser, args.seeds)
    fit_seeds = parse_seeds(parser, args.fit_seeds)
    models = parse_names(parser, "--models", args.models, MODELS)
    if not args.reference.is_file():
        parser.error(f"--reference {args.reference} is not a file")
    if args.against_tree is not None and not (args.against_tree / "cmax" / "__init__.py").is_file():
        parser.error(f"--against-tree {args.against_tree} holds no cmax package")
    reference = reference_figures(args.reference.read_text())
    trees = {"this": ROOT, **({"against": args.against_tree.resolve()} if args.against_tree else {})}
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as folder:
        export_windows(Path(folder), seeds, args.cache)
        fitted = run_workers(Path(folder), models, fit_seeds, trees)
        rows = {name: by_model_and_seed(r, fit_seeds) for name, r in fitted.items()}
    text = summarise(rows["this"], seeds, fit_seeds, reference, args.reference_name or str(args.reference),
                     time.perf_counter() - start)
    if args.against_tree is not None:
        names = (args.against_name or str(args.against_tree), "this checkout")
        text += "\n".join(["", f"## Against {names[0]}", "",
                           f"The same windows and fit seeds fitted by {names[0]}'s `cmax` in a second "
                           "process at the same time (one thread each). Lower is better.", "",
                           *compare(rows["against"], rows["this"], fit_seeds, names)]) + "\n"
    args.output.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.output, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
