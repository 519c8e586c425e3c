"""The shared objective (:data:`cmax.contrast.SHARED_OBJECTIVE`): compiled value and gradient against the torch
reference.

:class:`cmax.contrast.AverageTimestamp` images every event at two reference times, per polarity and window,
divides the weighted votes by the votes and sums the squares. On CPU float32 / float64 batches that image part
runs as one compiled value and gradient (:mod:`cmax.contrast._timestamp_kernels`), and a one-window batch is
warped by the compiled se3 warp; ``cmax.contrast.objectives._COMPILED = False`` restores the torch operations
(the reference). This script times both on 346x260 ``indoor_flying`` windows (``benchmarks.accuracy_cmax``'s
held-out seeds), one torch thread, interleaved, medians:

* the fit's polish (:class:`cmax.fitting.polish.SharedPolishStage`): one window, float64, the window's events
  as the fit subsamples them, the 24x32 inverse-depth grid; value + gradient in the grid alone
  (``polish="depth"``) and in the grid and the twist (``"depth_motion"``);
* a training step's loss (:data:`~cmax.contrast.SHARED_OBJECTIVE` as :func:`learned.losses.student_loss`
  calls it): 8 windows, float32, ``learned``'s 20000 events per window, a per-pixel inverse-depth map and the
  twist; and the whole student training step around it (``learned/configs/student.toml``'s network and
  loss terms, an untrained teacher, AdamW);
* the numba compile of the first call in a fresh process (empty cache, then the cache it left);
* with ``--polish``, the whole polish stage (``polish="depth"``, from the default fit's result) on both paths:
  seconds, evaluations and the objective it reached.

Writes ``benchmarks/results/speed_shared_objective.md``.

Usage::

    python -m benchmarks.speed_shared_objective [--seeds 100-101] [--repeats 11] [--polish] [--cache DIR]
"""
from __future__ import annotations

import argparse
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
from cmax.contrast._timestamp_kernels import average_timestamp_images
for dtype in (torch.float32, torch.float64):
    x = torch.tensor([[1.5, 2.25], [1.0, 2.0]], dtype=dtype, requires_grad=True)
    start = time.perf_counter()
    average_timestamp_images(x, x.detach() + 1, torch.tensor([0.2, 0.7], dtype=dtype), torch.tensor([0, 1]), 1,
                             (6, 6), 1e-9, True).sum().backward()
    print(time.perf_counter() - start)
"""


def compiled(flag: bool):
    """Run the shared objective on the compiled path (True) or on the torch reference (False)."""
    from benchmarks.speed_patch_contrast import compiled_flag

    return compiled_flag("cmax.contrast.objectives", flag)


def cases(windows: list, speeds: list[float]) -> dict:
    """The timed calls: name -> callable returning (value, gradient) on whichever path is active."""
    from benchmarks.accuracy_cmax import _room
    from cmax.contrast import SHARED_OBJECTIVE, EventWindows
    from cmax.fitting.polish import window_events
    from cmax.fitting.settings import FitSettings
    from cmax.fitting.window import Window
    from learned.config import DataConfig

    calls = {}
    for window, speed in zip(windows[:2], speeds):
        w = Window.from_events(window.events, window.K, FitSettings(**_room()))
        batch = window_events(w, speed)
        rho = torch.full((1, 1, *w.grid.shape), 0.3, dtype=torch.float64)
        twist = torch.as_tensor(window.twist, dtype=torch.float64)[None]
        for motion in (False, True):
            calls[f"polish, {'depth_motion' if motion else 'depth'}: 1 window, {len(batch)} events, float64, "
                  f"grid {w.grid.shape[0]}x{w.grid.shape[1]}"] = _evaluation(SHARED_OBJECTIVE, batch, rho, twist,
                                                                              twist_free=motion)
    events = DataConfig().max_events
    batch = EventWindows.from_windows([(w.events, w.K) for w in windows], max_events=events, dtype=torch.float32,
                                      speed=speeds)
    rho = torch.full((len(windows), 1, batch.height, batch.width), 0.3)
    twist = torch.as_tensor(np.stack([w.twist for w in windows]), dtype=torch.float32)
    calls[f"training loss: {len(windows)} windows, {events} events each, float32, per-pixel map"] = \
        _evaluation(SHARED_OBJECTIVE, batch, rho, twist, twist_free=True)
    calls[f"student training step (learned/configs/student.toml's network and loss, batch {len(windows)}): "
          "forward, teacher, loss, backward, AdamW"] = _student_step(batch)
    return calls


def _student_step(batch):
    """One step of ``python -m learned.train --mode student`` on ``batch``'s events (random volumes: the
    speed does not depend on them; an untrained teacher)."""
    from learned.config import load_config
    from learned.losses import student_loss
    from learned.model import DepthPoseNet

    config = load_config(Path(__file__).resolve().parents[1] / "learned" / "configs" / "student.toml",
                         ["train.val_every=0"], mode="student")
    torch.manual_seed(0)
    net, teacher = DepthPoseNet(config.model), DepthPoseNet(config.model).eval()
    optimizer = torch.optim.AdamW(net.parameters(), lr=1e-5)
    volume = torch.randn(batch.count, config.model.bins, batch.height, batch.width)
    tc = config.train

    def run():
        output = net(volume)
        with torch.no_grad():
            teacher_rho = teacher(volume).inverse_depth
        loss, _ = student_loss(output.inverse_depth, output.twist, batch, teacher_inverse_depth=teacher_rho,
                               lam=tc.lam, speed_weight=tc.speed_weight)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grads = torch.cat([p.grad.reshape(-1) for p in net.parameters() if p.grad is not None])
        optimizer.step()
        return float(loss.detach()), grads.double().numpy()
    return run


def _evaluation(objective, batch, rho, twist, *, twist_free: bool):
    """``run() -> (value, gradient)`` of ``objective`` at ``rho`` and ``twist``: the gradient in the inverse
    depth, and in the twist too when ``twist_free``."""
    from cmax.contrast import DepthMotion

    def run():
        r = rho.clone().requires_grad_()
        t = twist.clone().requires_grad_() if twist_free else twist
        value = objective(batch, DepthMotion(r, t)).sum()
        value.backward()
        grads = [r.grad.reshape(-1)] + ([t.grad.reshape(-1)] if twist_free else [])
        return float(value.detach()), torch.cat(grads).double().numpy()
    return run


def agreement(calls: dict) -> dict[str, tuple[float, float]]:
    """Relative difference of the values and of the gradients (norm of the difference over the norm)."""
    out = {}
    for name, call in calls.items():
        if name.startswith("student training step"):   # its weights move at every step: no pair to compare
            out[name] = (float("nan"), float("nan"))
            continue
        with compiled(True):
            a = call()
        with compiled(False):
            b = call()
        out[name] = (abs(a[0] - b[0]) / abs(b[0]), float(np.linalg.norm(a[1] - b[1]) / np.linalg.norm(b[1])))
    return out


def polish_check(windows: list, speeds: list[float], seeds: list[int]) -> list[dict]:
    """The polish stage (depth) from the default fit's result, on both paths, interleaved."""
    from benchmarks.accuracy_cmax import _room
    from cmax.fitting.pipeline import Motion, run_stages, stages_for
    from cmax.fitting.polish import SharedPolishStage
    from cmax.fitting.settings import FitSettings
    from cmax.fitting.solvers import make_solver
    from cmax.fitting.window import Window

    rows = []
    for seed, window, speed in zip(seeds, windows, speeds):
        w = Window.from_events(window.events, window.K, FitSettings(**_room()))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            start, _ = run_stages(stages_for("se3", w, pose_known=False, hold_omega=False), w,
                                  Motion(speed=speed), make_solver("scipy"))
        for label, flag in (("compiled", True), ("torch", False)):
            with compiled(flag):
                began = time.perf_counter()
                _, log = SharedPolishStage(motion_free=False).run(w, start, make_solver("scipy"))
                rows.append({"seed": seed, "path": label, "seconds": time.perf_counter() - began,
                             "iterations": log.iterations, "evaluations": log.evaluations,
                             "before": log.objective_before, "after": log.objective_after})
    return rows


def report(times, agree, compile_times, polish, args, loads, seeds) -> str:
    lines = ["# The shared objective: compiled value + gradient vs the torch reference", "",
             f"Written by `python -m benchmarks.speed_shared_objective {' '.join(args)}`. torch threads 1, numba "
             f"serial; `indoor_flying` 346x260, seeds {', '.join(map(str, seeds))}. Load average (1 min) before / "
             f"after: {loads[0]:.2f} / {loads[1]:.2f} on {os.cpu_count()} cores (a shared machine: the ratios, "
             "measured interleaved, are steadier than the absolute times).", "",
             "Value and gradient (one backward), milliseconds, medians over the repeats:", "",
             "| call | compiled [ms] | torch [ms] | speed-up | value: rel diff | gradient: rel diff (norm) |",
             "|---|---|---|---|---|---|"]
    for name, t in times.items():
        c, r = statistics.median(t["compiled"]), statistics.median(t["torch"])
        value, gradient = (f"{d:.1e}" if np.isfinite(d) else "–" for d in agree[name])
        lines.append(f"| {name} | {1e3 * c:.1f} | {1e3 * r:.1f} | {r / c:.1f}x | {value} | {gradient} |")
    lines += ["", "The float32 rows' differences are the torch path's float32 accumulation: the compiled images "
              "accumulate in float64 (`tests/test_timestamp_kernels.py` checks both paths against the float64 "
              "reference). The training step's network moves at every step, so its two paths are not compared "
              "value for value; its time is mostly the network's (the loss row above is its contrast term).", "",
              f"numba compile of the first call (float32, float64 kernels; a fresh process): with an empty cache "
              f"{compile_times[0][0]:.1f} s + {compile_times[0][1]:.1f} s; loading the on-disk cache "
              f"{compile_times[1][0]:.2f} s + {compile_times[1][1]:.2f} s."]
    if polish:
        lines += ["", "## The polish stage (`polish=\"depth\"`) from the default fit's result", "",
                  "| seed | path | seconds | iterations | evaluations | objective before | after |",
                  "|---|---|---|---|---|---|---|"]
        for row in polish:
            lines.append(f"| {row['seed']} | {row['path']} | {row['seconds']:.2f} | {row['iterations']} | "
                         f"{row['evaluations']} | {row['before']:.5f} | {row['after']:.5f} |")
        lines += ["", "The two paths' evaluations differ in the last digits; the objective is piecewise smooth "
                  "(docs/fitting.md), so L-BFGS-B's path and its number of evaluations can differ too."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    from benchmarks.accuracy_cmax import parse_seeds, windows as load_windows
    from benchmarks.speed import fresh_process_outputs
    from benchmarks.speed_patch_contrast import time_interleaved
    from cmax.io.atomic import write_text_atomic

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="100-107", help="held-out indoor_flying seeds (8 make the training batch)")
    parser.add_argument("--repeats", type=int, default=11)
    parser.add_argument("--polish", action="store_true", help="also run the whole polish stage on both paths")
    parser.add_argument("--cache", type=Path, default=None, help="cache of simulated windows (pickles)")
    parser.add_argument("--output", type=Path, default=RESULTS / "speed_shared_objective.md")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    seeds = parse_seeds(parser, args.seeds)
    loads = [os.getloadavg()[0]]
    windows = [load_windows("se3", seed, args.cache) for seed in seeds]
    speeds = [float(np.linalg.norm(w.twist[:3])) for w in windows]
    calls = cases(windows, speeds)
    times = time_interleaved(calls, args.repeats, compiled)
    agree = agreement(calls)
    compile_times = [[float(v) for v in out.split()]
                     for out in fresh_process_outputs(_COMPILE_PROBE, env={"OMP_NUM_THREADS": "1"})]
    polish = polish_check(windows[:2], speeds[:2], seeds[:2]) if args.polish else []
    loads.append(os.getloadavg()[0])
    text = report(times, agree, compile_times, polish, sys.argv[1:] if argv is None else argv, loads, seeds)
    write_text_atomic(args.output, text)
    print(text)


if __name__ == "__main__":
    main()
