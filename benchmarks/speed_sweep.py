"""The depth sweep's cost on a real 346x260 window: the compiled kernels against the torch reference.

The window is ``indoor_flying`` (:func:`benchmarks.accuracy_cmax.windows`, the accuracy benchmark's se3
windows). One ``cmax.fit(model="se3")`` of it records the arguments its ``depth_sweep`` stage hands to
:func:`cmax.fitting.depth_sweep.sweep_inverse_depth` (the fitted twist, the depth grid, the settings);
then, with one torch, OpenCV and numba thread, timed round-robin (:func:`benchmarks.speed.run_group`):

* the cost of the whole-range sweep (:class:`cmax.contrast.SweepNodeCost` on the coarse grid, all
  candidates in one call): torch reference (``cmax.contrast.sweep._COMPILED = False``) and compiled;
* the whole ``sweep_inverse_depth`` (coarse sweep, semi-global matching, the relative refinements).

The checks compare the two paths' costs and inverse-depth grids, and give the first call in a fresh
process (numba compiling with an empty cache, then loading it) apart from the timed calls. A cProfile
of the compiled ``sweep_inverse_depth`` says where its time goes. With ``--fit-seeds`` the fits themselves
(``cmax.fit`` se3 and ``cmax.fit(pose=)``, the accuracy benchmark's ``run_se3`` / ``run_depth`` with the
room's depth range) run on both paths, interleaved: seconds, the ``depth_sweep`` stage's seconds, and
whether the inverse-depth grids are identical.

Usage::

    python -m benchmarks.speed_sweep [--seed 100] [--repeats 7] [--fit-seeds 100,101,102,103] [--fit-repeats 3]
                                     [--clock wall|cpu]
"""
from __future__ import annotations

import argparse
import contextlib
import cProfile
import os
import pstats
import statistics
import sys
import time

import numpy as np
import torch

import cmax.contrast.sweep as sweep_module
from cmax.fitting import pipeline
from cmax.fitting.depth_sweep import coarse_grid_shape, node_cost_function, sweep_inverse_depth
from cmax.warp import DepthGrid

COMMAND = "python -m benchmarks.speed_sweep"


def fresh_sweep(*args, **kwargs):
    """``sweep_inverse_depth`` as a new window's fit runs it: the kept warp terms of the last call forgotten
    (:func:`cmax.contrast.sweep._warp_terms`), so each timed call computes them once, as a fit does."""
    sweep_module._LAST_TERMS.clear()
    return sweep_inverse_depth(*args, **kwargs)


def fresh_cost(cost, rho):
    """``cost(rho)`` with the kept warp terms forgotten (see :func:`fresh_sweep`)."""
    sweep_module._LAST_TERMS.clear()
    return cost(rho)


@contextlib.contextmanager
def torch_reference(on: bool = True):
    """Run :class:`cmax.contrast.SweepNodeCost` on its torch operations inside the block (``on``)."""
    previous = sweep_module._COMPILED
    sweep_module._COMPILED = not on
    try:
        yield
    finally:
        sweep_module._COMPILED = previous


def recorded_sweep(window) -> tuple[tuple, dict]:
    """``(args, kwargs)`` of the ``sweep_inverse_depth`` call of one se3 fit of ``window``."""
    from benchmarks.accuracy_cmax import _room, run_se3

    calls = []
    original = pipeline.sweep_inverse_depth

    def record(*args, **kwargs):
        calls.append((args, kwargs))
        return original(*args, **kwargs)

    pipeline.sweep_inverse_depth = record
    try:
        run_se3(window, **_room())
    finally:
        pipeline.sweep_inverse_depth = original
    return calls[0]


def coarse_cost(args: tuple, kwargs: dict):
    """The whole-range sweep's cost function and its candidates (C, N) of a recorded call."""
    rays, dt, polarity, v, omega, K = args
    coarse = coarse_grid_shape(kwargs["grid_shape"], kwargs.get("coarsening", 2))
    pixels = rays @ K.to(rays.dtype).T
    index, weight = DepthGrid(coarse, kwargs["width"], kwargs["height"]).weights(pixels[:, 0], pixels[:, 1])
    cost = node_cost_function(rays, dt, polarity, v, omega, K, height=kwargs["height"], width=kwargs["width"],
                              grid_shape=coarse, index=index, weight=weight, sigma=kwargs.get("sigma", 1.0),
                              chunk=kwargs.get("chunk", 8), border_px=kwargs.get("border_px", 1),
                              vote_scale_quantile=kwargs.get("vote_scale_quantile", 0.5))
    lo, hi = kwargs["rho_range"]
    rhos = torch.linspace(float(lo), float(hi), kwargs.get("candidates", 48), dtype=rays.dtype)
    return cost, rhos[:, None].expand(-1, rays.shape[0])


def first_call_seconds(seed: int) -> dict:
    """Seconds of the first and second compiled sweep in fresh processes sharing a fresh numba cache
    (first process: compiling; second: loading the cache). The fit that records the call is not timed."""
    from benchmarks.speed import first_calls_seconds

    setup = ("import torch; torch.set_num_threads(1)\n"
             "from benchmarks.accuracy_cmax import windows\n"
             "from benchmarks.speed_sweep import fresh_sweep, recorded_sweep, torch_reference\n"
             f"w = windows('se3', {seed}, None)\n"
             "with torch_reference():\n"
             "    a, k = recorded_sweep(w)")
    return first_calls_seconds(setup, "fresh_sweep(*a, **k)")


def profile_lines(args: tuple, kwargs: dict, repeats: int = 3, top: int = 10) -> list[str]:
    """Markdown: the compiled sweep's time in its cost calls and elsewhere, and the functions with the most
    own time, over ``repeats`` compiled sweeps (cProfile)."""
    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(repeats):
        fresh_sweep(*args, **kwargs)
    profiler.disable()
    stats = pstats.Stats(profiler).stats
    total = sum(entry[2] for entry in stats.values())

    def cumulative(file: str, name: str) -> float:
        return sum(entry[3] for (path, _, function), entry in stats.items()
                   if path.endswith(file) and function == name)

    whole, cost = cumulative("speed_sweep.py", "fresh_sweep"), cumulative("contrast/sweep.py", "__call__")
    lines = [f"Per compiled sweep (profiled, so slower than the timed rows): {whole / repeats * 1e3:.0f} ms, of which "
             f"{cost / repeats * 1e3:.0f} ms in the cost (`SweepNodeCost.__call__`) and "
             f"{(whole - cost) / repeats * 1e3:.0f} ms in the rest of `sweep_inverse_depth` (grid weights, "
             "semi-global matching, resampling).", "",
             "| function | own ms per sweep | share | calls per sweep |", "|---|---:|---:|---:|"]
    rows = sorted(stats.items(), key=lambda item: -item[1][2])[:top]
    for (path, line, name), (_, calls, own, _, _) in rows:
        where = f"{os.path.basename(path)}:{line} {name}" if path != "~" else name
        lines.append(f"| `{where}` | {own / repeats * 1e3:.1f} | {own / total:.0%} | {calls / repeats:g} |")
    return lines


def fit_table(seeds: list[int], repeats: int) -> tuple[list[str], dict]:
    """Markdown rows and checks: both fits per seed on both paths, interleaved (torch, compiled, ...)."""
    from benchmarks.accuracy_cmax import _room
    from benchmarks.accuracy_cmax import windows as make_windows
    from cmax import fit

    lines = ["| fit | seed | torch reference (s) | compiled (s) | ratio | depth_sweep stage: torch / compiled (s) "
             "| inverse-depth grids | abs_rel torch / compiled |", "|---|---:|---:|---:|---:|---:|---|---|"]
    checks = {}
    for seed in seeds:
        w = make_windows("se3", seed, None)
        speed = float(np.linalg.norm(w.twist[:3]))
        runs = {"se3": lambda: fit(w.events, w.K, speed=speed, **_room()),
                "depth": lambda: fit(w.events, w.K, pose=w.T01, **_room())}
        for model, run in runs.items():
            seconds = {True: [], False: []}
            stage = {True: [], False: []}
            results = {}
            for _ in range(repeats):
                for reference in (True, False):
                    with torch_reference(reference):
                        start = time.perf_counter()
                        result = run()
                        seconds[reference].append(time.perf_counter() - start)
                    stage[reference] += [s.seconds for s in result.stages if s.stage == "depth_sweep"]
                    results.setdefault(reference, result)
            a, b = results[True].inverse_depth_grid, results[False].inverse_depth_grid
            same = "identical" if np.array_equal(a, b) else f"max rel diff {np.max(np.abs(a - b) / np.abs(a)):.1e}"
            errors = [_abs_rel(results[r], w) for r in (True, False)]
            med = {r: statistics.median(seconds[r]) for r in (True, False)}
            lines.append(f"| {model} | {seed} | {med[True]:.2f} | {med[False]:.2f} | {med[True] / med[False]:.2f}x | "
                         f"{statistics.median(stage[True]):.3f} / {statistics.median(stage[False]):.3f} | {same} | "
                         f"{errors[0]:.4f} / {errors[1]:.4f} |")
            checks[f"fit {model} seed {seed}: inverse-depth grids of both paths identical"] = same == "identical"
    return lines, checks


def _abs_rel(result, window) -> float:
    from benchmarks.accuracy_cmax import _room, abs_rel

    return abs_rel(result, window.depth, _room()["depth_range"])


def sweep_report(args: argparse.Namespace):
    """The report: sweep cost and sweep groups, checks, profile, optional fit table."""
    import cv2

    from benchmarks.accuracy_cmax import windows as make_windows
    from benchmarks.speed import Report, run_group

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    load_start = os.getloadavg()[0]
    window = make_windows("se3", args.seed, None)
    with torch_reference():
        call_args, call_kwargs = recorded_sweep(window)
    n = call_args[0].shape[0]
    cost, rho = coarse_cost(call_args, call_kwargs)
    candidates = rho.shape[0]
    report = Report("sweep", "The depth sweep's cost: compiled kernels against the torch reference",
                    {"command": getattr(args, "command", COMMAND), "repeats": args.repeats,
                     "window": f"indoor_flying seed {args.seed}", "events": n, "sensor": f"{call_kwargs['width']}x{call_kwargs['height']}",
                     "dtype": str(call_args[0].dtype), "grid": call_kwargs["grid_shape"],
                     "coarse grid": cost.grid_shape, "candidates": candidates,
                     "refinements": call_kwargs.get("refinements"),
                     "refine candidates": call_kwargs.get("refine_candidates"),
                     "threads": "1 torch, 1 OpenCV, numba kernels single-threaded"})

    def reference_cost():
        with torch_reference():
            return cost(rho)

    def reference_sweep():
        with torch_reference():
            return sweep_inverse_depth(*call_args, **call_kwargs)

    run_group(report, f"SweepNodeCost, {candidates} candidates x {n} events, coarse grid {cost.grid_shape}", [
        ("torch reference", reference_cost, "warp_se3, polarity_images, sample_bilinear, index_add_"),
        ("compiled", lambda: fresh_cost(cost, rho), "cmax.contrast._sweep_kernels"),
    ], n * candidates, args.repeats)
    run_group(report, "sweep_inverse_depth (the fit's depth_sweep stage)", [
        ("torch reference", reference_sweep, "the cost on torch ops"),
        ("compiled", lambda: fresh_sweep(*call_args, **call_kwargs), "the cost compiled"),
    ], n, args.repeats)
    compiled_cost, torch_cost = cost(rho), reference_cost()
    report.checks["coarse costs identical (torch.equal)"] = bool(torch.equal(compiled_cost, torch_cost))
    report.checks["coarse costs: max |difference| / max |cost|"] = float(
        (compiled_cost - torch_cost).abs().max() / torch_cost.abs().max())
    grids = sweep_inverse_depth(*call_args, **call_kwargs).inverse_depth, reference_sweep().inverse_depth
    report.checks["sweep inverse-depth grids identical"] = bool(np.array_equal(*grids))
    report.summary += ["Where the compiled sweep's time goes (cProfile, 3 sweeps):", ""]
    report.summary += profile_lines(call_args, call_kwargs)
    load_mid = os.getloadavg()[0]
    if args.fit_seeds:
        lines, checks = fit_table(args.fit_seeds, args.fit_repeats)
        report.summary += ["", f"The fits on both paths (median of {args.fit_repeats}, interleaved; torch threads as "
                               "the fit chooses them):", ""] + lines
        report.checks.update(checks)
    for label, (first, second) in first_call_seconds(args.seed).items():
        report.checks[f"first compiled sweep in a fresh process, {label} [s]"] = (
            f"{first:.2f} (second call {second:.3f})")
    report.notes += [
        f"Load average (1 min): {load_start:.2f} at the start, {load_mid:.2f} after the sweep groups, "
        f"{os.getloadavg()[0]:.2f} at the end (2 cores shared with other work: absolute times vary, ratios hold).",
        "Mev/s of the SweepNodeCost group: event-candidate pairs per microsecond; of the sweep group: events of "
        "the window per microsecond.",
        "Every method is called once before the timed calls, so numba compiling (or loading its cache) is "
        "not timed; the first-call checks give that cost.",
    ]
    return report


def main(argv: list[str] | None = None) -> int:
    from benchmarks.speed import CLOCKS, publish_report, timed_machine

    parser = argparse.ArgumentParser(prog=COMMAND, description=__doc__.split("\n")[0])
    parser.add_argument("--seed", type=int, default=100, help="indoor_flying window (default 100)")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--fit-seeds", type=lambda s: [int(v) for v in s.split(",") if v], default=[],
                        help="comma-separated windows whose fits run on both paths (default: none)")
    parser.add_argument("--fit-repeats", type=int, default=3)
    parser.add_argument("--clock", choices=sorted(CLOCKS), default="wall",
                        help="wall seconds, or CPU seconds of this process (steadier on a busy machine), for the "
                             "timed groups; the fits are timed in wall seconds")
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args(argv)
    args.command = " ".join([COMMAND, *(sys.argv[1:] if argv is None else argv)])
    machine = timed_machine(args.clock)   # first: the groups of the report are timed on its clock
    publish_report(sweep_report(args), machine, write=not args.no_write)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
