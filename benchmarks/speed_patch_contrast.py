"""The patch contrasts of the se3 fit: compiled value and gradient against the torch reference.

Every evaluation of the fit's patch-wise objectives (:class:`cmax.contrast.PatchFlowContrast` of the
patch-flow initialiser, :class:`cmax.contrast.PatchMotionContrast` of the refinement and of its
per-patch depth sweep) images each patch's events, blurs the images and takes their variances. On
CPU float32 / float64 tensors that image part runs as one compiled value and gradient
(:mod:`cmax.contrast._patch_kernels`); ``cmax.contrast.patches._COMPILED = False`` restores the torch
operations (the reference). This script times both on real 346x260 ``indoor_flying`` windows, one
torch thread, interleaved, medians:

* the image part alone (:meth:`cmax.contrast.Patches.variances`, value + gradient in the event
  coordinates) on the refinement's and on the patch flows' patches;
* the patch flows' objective (value + gradient) at its coarse level (sigma 3 px, every
  ``coarse_step``-th event) and at its fine level (the window's sigma), 2 px of flow per patch;
* the refinement's objective (value + gradient, the parameters as the solver sees them) at the true
  motion, each patch's depth the median inverse depth of the sweep's candidates;
* the same two objectives through ``fun_and_grad``, what the fit's solves call: on the compiled path
  the kernels' gradients chained in numpy with no autograd at all, on the torch path autograd of the
  torch operations (so its ratio is against the same reference as the rows above);
* the refinement's depth sweep (``sweep_rho``: forward evaluations of every candidate);
* the numba compile time: the first call in a fresh process with an empty numba cache, and with the
  cache that compile left (what every later process pays);
* with ``--fit``, ``cmax.fit`` se3 on seeds 100-103 (``benchmarks.accuracy_cmax.run_se3`` with the
  preset's depth range) on both paths, interleaved: seconds, direction, omega and abs_rel errors. The
  two paths differ by float32 rounding, and the fit's solvers amplify that; a third run, the torch
  path with every imaged coordinate moved by a fixed +-1e-5 px (about float32's spacing at 100 px),
  shows how far rounding alone moves the results (the noise the compiled path is judged against).

Writes ``benchmarks/results/speed_patch_contrast.md``.

Usage::

    python -m benchmarks.speed_patch_contrast [--seeds 100] [--repeats 15] [--fit] [--fit-seeds 100-103]
"""
from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

RESULTS = Path(__file__).resolve().parent / "results"

_COMPILE_PROBE = """
import time, torch
from cmax.contrast._patch_kernels import patch_variances
for dtype in (torch.float32, torch.float64):
    x = torch.tensor([1.5, 2.25], dtype=dtype, requires_grad=True)
    start = time.perf_counter()
    patch_variances(x, x.detach() + 1, torch.tensor([0, 0]), torch.zeros(1, 2), (6, 6), 1.0).sum().backward()
    print(time.perf_counter() - start)
"""


@contextlib.contextmanager
def compiled_flag(module_name: str, flag: bool):
    """Set ``module_name``'s ``_COMPILED`` switch to ``flag`` (the compiled path, or the torch reference) for
    the block."""
    import importlib

    module = importlib.import_module(module_name)
    saved = module._COMPILED
    module._COMPILED = flag
    try:
        yield
    finally:
        module._COMPILED = saved


def compiled(flag: bool):
    """Run the patch contrasts on the compiled path (True) or on the torch reference (False)."""
    return compiled_flag("cmax.contrast.patches", flag)


@contextlib.contextmanager
def nudged(step: float = 1e-5):
    """The torch path with each event's imaged coordinates moved by ``+-step`` px (alternating signs)."""
    from cmax.contrast.patches import Patches

    original = Patches.variances

    def variances(self, x, y, sigma):
        sign = 1.0 - 2.0 * (torch.arange(x.numel()) % 2).to(x.dtype)
        return original(self, x + step * sign, y - step * sign, sigma)

    with compiled(False):
        Patches.variances = variances
        try:
            yield
        finally:
            Patches.variances = original


PATHS = {"compiled": lambda: compiled(True), "torch": lambda: compiled(False),
         "torch, coordinates +-1e-5 px": nudged}


def value_and_grad(loss, x: np.ndarray) -> tuple[float, np.ndarray]:
    """``loss`` and its gradient at ``x`` (float64), as the solvers evaluate it."""
    p = torch.from_numpy(np.array(x, dtype=np.float64)).requires_grad_()
    value = loss(p)
    value.backward()
    return float(value.detach()), p.grad.numpy().copy()


def cases(window, seed: int) -> dict:
    """The timed calls of one window: name -> callable (run on whichever path is active)."""
    from benchmarks.accuracy_cmax import _room
    from cmax.contrast.patches import PatchFlowContrast
    from cmax.fitting.motion import LocalMotionObjective
    from cmax.fitting.patch_flow import make_patches
    from cmax.fitting.settings import FitSettings
    from cmax.fitting.window import Window

    settings = FitSettings(**_room())
    w = Window.from_events(window.events, window.K, settings)
    flow, refine = settings.patch_flow, settings.refine
    flow_patches = make_patches(w, grid=flow.grid, min_events=flow.min_events, max_events=flow.max_events,
                                margin=flow.margin, min_margin_px=flow.min_margin_px)
    refine_patches = make_patches(w, grid=refine.grid, min_events=refine.min_events, max_events=refine.max_events,
                                  margin=refine.margin, min_margin_px=refine.min_margin_px)
    q = np.tile([2.0, -1.0], flow_patches.count) * np.sqrt(0.8)   # 2 px of displacement per patch
    v, omega = window.twist[:3], window.twist[3:]
    speed = float(np.linalg.norm(v))
    near, far = settings.depth_range
    candidates = np.exp(np.linspace(np.log(1 / far), np.log(1 / near), refine.rho_candidates))
    info = {"seed": seed, "events": len(window.events), "flow patches": flow_patches.count,
            "flow frame": flow_patches.size, "flow events": int(flow_patches.x.numel()),
            "refine patches": refine_patches.count, "refine frame": refine_patches.size,
            "refine events": int(refine_patches.x.numel())}

    def flow_loss(sigma: float, step: int):
        def run():
            loss = PatchFlowContrast.build(flow_patches.every(step), sigma, w.T)
            return value_and_grad(loss, q)
        return run

    def refine_objective():
        return LocalMotionObjective.build(w, refine_patches, speed, direction_scale=refine.direction_scale)

    def refine_loss():
        objective = refine_objective()
        p = objective.params(v, omega, np.full(refine_patches.count, float(np.median(candidates))))
        return value_and_grad(lambda x: -objective.values(x).sum(), p)

    def refine_fun_and_grad():
        objective = refine_objective()
        return objective.fun_and_grad(objective.params(v, omega, np.full(refine_patches.count,
                                                                         float(np.median(candidates)))))

    def flow_fun_and_grad():
        return PatchFlowContrast.build(flow_patches, settings.sigma, w.T).fun_and_grad(q)

    def sweep():
        return refine_objective().sweep_rho(v, omega, candidates)

    def image_part(patches, sigma: float):
        """Only what the kernel replaces: the patch variances and their gradient in x, y (the events
        displaced by 1 px along x and y over the window, as a warp would)."""
        x0 = (patches.x + patches.dt / w.T).detach()
        y0 = (patches.y - patches.dt / w.T).detach()

        def run():
            x, y = x0.clone().requires_grad_(), y0.clone().requires_grad_()
            values = patches.variances(x, y, sigma)
            values.sum().backward()
            return float(values.detach().sum()), np.concatenate([x.grad.numpy(), y.grad.numpy()])
        return run

    # Each call builds its objective (base variances included), as each solve of the fit does once:
    # the build is one forward evaluation, timed separately below.
    calls = {
        f"image part only: refinement patches (sigma {settings.sigma:g} px)": image_part(refine_patches, settings.sigma),
        f"image part only: patch-flow patches (sigma 3 px, every {flow.coarse_step}-th event)":
            image_part(flow_patches.every(flow.coarse_step), 3.0),
        f"patch flows, coarse (sigma 3 px, every {flow.coarse_step}-th event)": flow_loss(3.0, flow.coarse_step),
        f"patch flows, fine (sigma {settings.sigma:g} px)": flow_loss(settings.sigma, 1),
        "refinement (se3 warp + patch contrast)": refine_loss,
        "patch flows, fine: fun_and_grad (what the solves call; compiled: no autograd)": flow_fun_and_grad,
        "refinement: fun_and_grad (what the solves call; compiled: no autograd)": refine_fun_and_grad,
        f"depth sweep ({refine.rho_candidates} forward evaluations)": sweep,
    }
    builds = {
        "build: patch flows, fine": lambda: PatchFlowContrast.build(flow_patches, settings.sigma, w.T),
        "build: refinement": refine_objective,
    }
    return info, calls, builds


def time_interleaved(calls: dict, repeats: int, switch=None) -> dict[str, dict[str, list[float]]]:
    """Seconds of every call on both paths, interleaved, ``repeats`` times (after one warm-up each);
    ``switch(flag)`` is the context manager that selects the compiled (True) or torch (False) path (default:
    the patch contrasts' :func:`compiled`)."""
    switch = compiled if switch is None else switch
    times = {name: {"compiled": [], "torch": []} for name in calls}
    for name, call in calls.items():
        for flag in (True, False):
            with switch(flag):
                call()
    for _ in range(repeats):
        for name, call in calls.items():
            for flag, label in ((True, "compiled"), (False, "torch")):
                with switch(flag):
                    start = time.perf_counter()
                    call()
                    times[name][label].append(time.perf_counter() - start)
    return times


def agreement(calls: dict) -> dict[str, tuple[float, float]]:
    """Largest relative difference of the values and of the gradients, compiled vs torch, of each call."""
    out = {}
    for name, call in calls.items():
        with compiled(True):
            a = call()
        with compiled(False):
            b = call()
        if isinstance(a, tuple):
            value = abs(a[0] - b[0]) / abs(b[0])
            grad = float(np.abs(a[1] - b[1]).max() / np.abs(b[1]).max())
            out[name] = (value, grad)
        elif isinstance(a, np.ndarray):
            out[name] = (float(np.abs(a - b).max()), float("nan"))
    return out


def compile_seconds() -> tuple[list[float], list[float]]:
    """First-call seconds (float32, float64) in a fresh process: with an empty numba cache, then with its result."""
    from benchmarks.speed import fresh_process_outputs

    first, second = ([float(line) for line in out.split()]
                     for out in fresh_process_outputs(_COMPILE_PROBE, env={"OMP_NUM_THREADS": "1"}))
    return first, second


def fit_check(seeds: list[int], repeats: int) -> list[dict]:
    """``run_se3`` on both paths, interleaved: per seed, the median seconds and the (last) errors of each."""
    from benchmarks.accuracy_cmax import _room, run_se3
    from benchmarks.synthetic_windows import preset_window

    rows = []
    for seed in seeds:
        window = preset_window("indoor_flying", seed)
        results: dict[str, list[dict]] = {label: [] for label in PATHS}
        for _ in range(repeats):
            for label, path in PATHS.items():
                with path(), warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    results[label].append(run_se3(window, **_room()))
        for label, runs in results.items():
            same = all(r["direction_deg"] == runs[0]["direction_deg"] for r in runs)
            rows.append({"seed": seed, "path": label, "seconds": statistics.median(r["seconds"] for r in runs),
                         "repeatable": same, **{k: runs[-1][k] for k in ("direction_deg", "omega_rms_deg_s", "abs_rel")}})
    return rows


def _ms(values: list[float]) -> str:
    return f"{1e3 * statistics.median(values):.2f}"


def report(infos, times, agree, compile_times, fits, args, loads) -> str:
    lines = ["# Patch contrasts of the se3 fit: compiled value + gradient vs the torch reference", "",
             f"Written by `python -m benchmarks.speed_patch_contrast {' '.join(args)}`. torch threads 1, numba serial. "
             f"Load average (1 min) before / after: {loads[0]:.2f} / {loads[1]:.2f} on {os.cpu_count()} cores "
             "(a shared machine: the ratios, measured interleaved, are steadier than the absolute times).", ""]
    for info in infos:
        lines.append(f"- window `indoor_flying` seed {info['seed']}, 346x260, {info['events']} events: "
                     f"patch flows {info['flow patches']} patches of {info['flow frame'][0]}x{info['flow frame'][1]} px, "
                     f"{info['flow events']} events; refinement {info['refine patches']} patches of "
                     f"{info['refine frame'][0]}x{info['refine frame'][1]} px, {info['refine events']} events")
    lines += ["", "'Image part only' times what the kernel replaces (the patch variances, value and gradient in the "
              "event coordinates); the other calls build their objective (one forward evaluation for the unwarped "
              "variances) and evaluate it, as one solve does per level (the warp, in torch, included). "
              "Milliseconds, medians over all windows and repeats:", "",
              "| call | compiled [ms] | torch [ms] | speed-up | values: max rel diff | gradients: max diff / max |",
              "|---|---|---|---|---|---|"]
    for name, t in times.items():
        a, b = statistics.median(t["compiled"]), statistics.median(t["torch"])
        value, grad = agree.get(name, (float("nan"), float("nan")))
        lines.append(f"| {name} | {_ms(t['compiled'])} | {_ms(t['torch'])} | {b / a:.1f}x | {value:.1e} | {grad:.1e} |")
    lines += ["", "The depth sweep's row compares the chosen inverse depths (max abs difference [1/m]).", "",
              f"numba compile of the first call (float32, float64 kernels; a fresh process): with an empty cache "
              f"{compile_times[0][0]:.1f} s + {compile_times[0][1]:.1f} s; loading the on-disk cache "
              f"{compile_times[1][0]:.2f} s + {compile_times[1][1]:.2f} s.", ""]
    if fits:
        lines += ["## `cmax.fit` se3 on both paths", "",
                  "`benchmarks.accuracy_cmax.run_se3` with the preset's depth range; the paths interleaved per "
                  "window; seconds are medians of the repeats; 'same' says whether every repeat of a path gave "
                  "the same direction (the fit is deterministic on one thread).", "",
                  "| seed | path | seconds | direction [deg] | omega rms [deg/s] | abs_rel | same |",
                  "|---|---|---|---|---|---|---|"]
        for r in fits:
            lines.append(f"| {r['seed']} | {r['path']} | {r['seconds']:.2f} | {r['direction_deg']:.3f} | "
                         f"{r['omega_rms_deg_s']:.3f} | {r['abs_rel']:.4f} | {'yes' if r['repeatable'] else 'no'} |")
        lines.append("")
        for label in PATHS:
            mine = [r for r in fits if r["path"] == label]
            lines.append(f"- {label}: median {statistics.median(r['seconds'] for r in mine):.2f} s per window; "
                         f"median direction {statistics.median(r['direction_deg'] for r in mine):.2f} deg, omega "
                         f"{statistics.median(r['omega_rms_deg_s'] for r in mine):.3f} deg/s, abs_rel "
                         f"{statistics.median(r['abs_rel'] for r in mine):.4f}")
    return "\n".join(lines) + "\n"


def _seeds(text: str) -> list[int]:
    if "-" in text:
        lo, hi = text.split("-")
        return list(range(int(lo), int(hi) + 1))
    return [int(s) for s in text.split(",")]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="100", help="windows of the per-call timings, e.g. 100 or 100-101")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--fit", action="store_true", help="also run cmax.fit se3 on both paths")
    parser.add_argument("--fit-seeds", default="100-103")
    parser.add_argument("--fit-repeats", type=int, default=2)
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args(argv)
    from benchmarks.synthetic_windows import preset_window
    from cmax.io.atomic import write_text_atomic

    torch.set_num_threads(1)
    loads = [os.getloadavg()[0]]
    compile_times = compile_seconds()
    infos, times, agree = [], {}, {}
    for seed in _seeds(args.seeds):
        info, calls, builds = cases(preset_window("indoor_flying", seed), seed)
        infos.append(info)
        calls = {**calls, **builds}
        for name, t in time_interleaved(calls, args.repeats).items():
            times.setdefault(name, {"compiled": [], "torch": []})
            for label in t:
                times[name][label] += t[label]
        for name, (value, grad) in agreement(calls).items():
            old = agree.get(name, (0.0, 0.0))
            agree[name] = (max(old[0], value), max(old[1], grad))
    fits = fit_check(_seeds(args.fit_seeds), args.fit_repeats) if args.fit else []
    loads.append(os.getloadavg()[0])
    text = report(infos, times, agree, compile_times, fits, sys.argv[1:] if argv is None else argv, loads)
    print(text)
    if not args.no_write:
        RESULTS.mkdir(exist_ok=True)
        write_text_atomic(RESULTS / "speed_patch_contrast.md", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
