"""Inference speed of the depth-pose network against ``cmax.fit``, per 346x260 window (same run).

Inputs: ``indoor_flying`` preset windows of :func:`benchmarks.synthetic_windows.preset_window`
(held-out seeds 100, 101, ...; 0.1665 s, 346x260), and denser windows made by merging the
events of 2 and 4 of them (time-aligned: one 0.1665 s window with 2x and 4x the events).

* **event volume**: :func:`cmax.representations.voxel_grid` (5 bins, numpy) and the compiled
  :func:`learned.volume.event_volume` (the same volume), ms per window at each event count;
* **network forward**, batch 1, ``torch.inference_mode``, for the original network
  (``ModelConfig()``, in its original NCHW layout and channels_last), width 8 with dense blocks,
  and the fast one (``ModelConfig.fast()``, also without GroupNorm; with ``--compile`` also
  ``torch.compile``d and ``torch.jit.trace`` + ``freeze``d, their preparation times reported),
  with 1 and 2 torch threads; untrained weights (speed does not depend on them), and the shipped student when present;
* **per window**: volume (compiled, on the densest window) + forward, and windows/s;
* ``cmax.fit(events, K, "se3", speed=|v|)`` (known speed, its defaults, 1 thread): seconds per
  window, ``--fits`` runs after one warm-up fit;
* **training step** (``--train-repeats``): teacher loss forward + backward + AdamW step, batch 8 at
  160x120, 2 threads, for the original and the fast network;
* **does it learn** (``--accuracy-train``/``--accuracy-val`` labelled h5 files): each of
  :data:`CANDIDATES` trained as a teacher for ``--accuracy-steps`` steps per seed, its last training
  losses and Abs mean on the held-out files.

Timings are medians and minimums of ``--repeats`` interleaved rounds (every variant once per round)
after a warm-up, so load changes hit all variants alike; the minimum (least disturbed round) is the
idle-machine figure used for the per-window totals, the median what the shared machine gave; the
load average is printed beside them.
Writes ``results/speed_learned.md``.

Usage::

    python -m benchmarks.speed_learned [--windows 4] [--repeats 9] [--fits 1] [--compile] [--train-repeats 5]
        [--accuracy-train A.h5 B.h5 ... --accuracy-val C.h5 ... --accuracy-steps 200 --accuracy-seeds 0 1]
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
import warnings
from dataclasses import fields
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from cmax.io.atomic import write_text_atomic
from learned.model import DepthPoseNet, ModelConfig
from learned import pretrained
from learned.evaluate import load_model

RESULTS = Path(__file__).resolve().parent / "results"
BUDGET_MS = 30.0


#: The networks trained by the accuracy section.
CANDIDATES = {"original": ModelConfig(), "fast": ModelConfig.fast(),
              "width 8, separable": ModelConfig(width=8, block="separable"),
              "space_to_depth, width 16, separable": ModelConfig(space_to_depth=True, block="separable")}


def changed_fields(config: ModelConfig) -> dict[str, object]:
    """The fields of ``config`` that differ from the defaults (the original network)."""
    return {f.name: getattr(config, f.name) for f in fields(ModelConfig)
            if getattr(config, f.name) != getattr(ModelConfig(), f.name)}


def interleaved_ms(functions: dict[str, Callable[[], object]], repeats: int,
                   threads: dict[str, int] | None = None) -> dict[str, tuple[float, float, float]]:
    """(median wall, min wall, median CPU) milliseconds of each function over ``repeats`` interleaved rounds.

    Each round runs every function once, after one warm-up round. The minimum is the least disturbed
    round (the figure of an idle machine); the median is what the shared machine gave. CPU time is the
    process's (all threads). ``threads`` maps a name to the torch thread count set before its call.
    """
    threads = threads or {}
    times: dict[str, list[tuple[float, float]]] = {name: [] for name in functions}
    for round_ in range(repeats + 1):
        for name, function in functions.items():
            if name in threads:
                torch.set_num_threads(threads[name])
            start, cpu = time.perf_counter(), time.process_time()
            function()
            if round_:
                times[name].append(((time.perf_counter() - start) * 1e3, (time.process_time() - cpu) * 1e3))
    return {name: (statistics.median(v[0] for v in values), min(v[0] for v in values),
                   statistics.median(v[1] for v in values)) for name, values in times.items()}


class _Tensors(torch.nn.Module):
    """A network returning (inverse_depth, twist) tensors instead of a NetOutput, for ``torch.jit.trace``."""

    def __init__(self, net: torch.nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, volume: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.net(volume)
        return out.inverse_depth, out.twist


def merged_events(windows: list):
    """The events of several windows of one sensor in one window: each shifted to start at the first's t0."""
    from cmax.events import Events

    t0 = int(windows[0].events.t[0])
    parts = [w.events for w in windows]
    t = np.concatenate([e.t - int(e.t[0]) + t0 for e in parts])
    order = np.argsort(t, kind="stable")
    column = lambda name: np.concatenate([getattr(e, name) for e in parts])[order]
    return Events(column("x"), column("y"), t[order], column("p"), width=parts[0].width, height=parts[0].height)


def train_step_seconds(configs: dict[str, ModelConfig], repeats: int,
                       threads: int = 2) -> dict[str, tuple[float, float]]:
    """Median and min milliseconds of one teacher-loss step (forward, backward, AdamW), batch 8 at 160x120, per config."""
    from learned.losses import teacher_loss

    torch.manual_seed(0)
    volume = torch.randn(8, 5, 120, 160)
    depth = torch.rand(8, 1, 120, 160) * 5 + 1
    mask = torch.rand(8, 1, 120, 160) > 0.3
    steps = {}
    for name, config in configs.items():
        net = DepthPoseNet(config)
        optimizer = torch.optim.AdamW(net.parameters(), lr=1e-4)

        def step(net=net, optimizer=optimizer) -> None:
            out = net(volume)
            loss = teacher_loss(tuple(1.0 / d for d in out.inverse_depths), depth, mask)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()

        steps[name] = step
    torch.set_num_threads(threads)
    return {name: ms[:2] for name, ms in interleaved_ms(steps, repeats).items()}


def accuracy_rows(runs: list[tuple[str, ModelConfig, int]], train: list[str], val: list[str], seeds: list[int],
                  out: Path) -> list[tuple[str, int, int, float, float, list[tuple[str, float]]]]:
    """Teacher training of each network ``(name, config, steps)`` on ``train``, once per seed.

    Returns rows (name, seed, steps, seconds, mean loss of the last 10 steps, [(file stem, Abs mean [m])] on
    ``val``). Batch 8, lr 3e-4, 1 thread; the same data order for every network of a seed.
    """
    import json

    from learned.config import load_config
    from learned.evaluate import evaluate_files
    from learned.train import Trainer

    torch.set_num_threads(1)
    rows = []
    for seed in seeds:
        for name, model, steps in runs:
            run = out / f"{name.replace(' ', '_').replace(',', '')}_seed{seed}"
            config = load_config(None, [f"data.files={json.dumps(train)}", f"train.steps={steps}",
                                        "train.batch_size=8", "train.lr=3e-4", f"train.seed={seed}", f"train.out={run}",
                                        f"train.checkpoint_every={steps}", f"train.log_every={steps}",
                                        f"train.image_every={10 * steps}"]
                                 + [f"model.{k}={json.dumps(v)}" for k, v in changed_fields(model).items()],
                                 mode="teacher")
            start = time.perf_counter()
            losses = Trainer(config, progress=False).run()
            seconds = time.perf_counter() - start
            reports = evaluate_files(run / "last.pt", val)
            rows.append((name, seed, steps, seconds, float(np.mean(losses[-10:])),
                         [(r.sequence, r.depth.abs_mean) for r in reports]))
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--windows", type=int, default=4, help="preset windows (>= 4: the densest merges 4)")
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--fits", type=int, default=1, help="cmax.fit runs after the warm-up fit")
    parser.add_argument("--compile", action="store_true", help="also time torch.compile of the fast net")
    parser.add_argument("--train-repeats", type=int, default=5, help="training-step rounds (0: skip)")
    parser.add_argument("--accuracy-train", nargs="*", default=[], metavar="H5",
                        help="labelled files: also train each candidate as a teacher on them (slow)")
    parser.add_argument("--accuracy-val", nargs="*", default=[], metavar="H5", help="held-out labelled files")
    parser.add_argument("--accuracy-steps", type=int, default=200)
    parser.add_argument("--accuracy-fast-steps", type=int, default=0,
                        help="also train the fast net this many steps (about the original's time for --accuracy-steps)")
    parser.add_argument("--accuracy-seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--accuracy-out", type=Path, default=Path("runs/speed_learned_accuracy"))
    parser.add_argument("--sections", nargs="+", choices=("speed", "training"), default=["speed"],
                        help="speed: the timings (-> --output); training: the candidates' teacher runs "
                             "(needs --accuracy-train/--accuracy-val; -> --training-output)")
    parser.add_argument("--output", type=Path, default=RESULTS / "speed_learned.md")
    parser.add_argument("--training-output", type=Path, default=RESULTS / "speed_learned_training.md")
    args = parser.parse_args(argv)
    if (args.windows < 4 or args.repeats < 1 or args.fits < 1 or args.train_repeats < 0 or args.accuracy_steps < 10
            or 0 < args.accuracy_fast_steps < 10):
        parser.error("need --windows >= 4, --repeats >= 1, --fits >= 1, --train-repeats >= 0, --accuracy-steps >= 10, "
                     "--accuracy-fast-steps 0 or >= 10")
    if ("training" in args.sections) != bool(args.accuracy_train) or bool(args.accuracy_train) != bool(args.accuracy_val):
        parser.error("--sections training needs --accuracy-train and --accuracy-val (and they need it)")
    if "training" in args.sections:
        training_report(args)
    if "speed" in args.sections:
        speed_report(args)
    return 0


def speed_report(args: argparse.Namespace) -> None:
    """Time the volume, the networks, cmax.fit and the training step; write ``args.output``."""
    import cmax
    from benchmarks.synthetic_windows import preset_window
    from cmax.representations import voxel_grid
    from learned.volume import event_volume

    loads = [os.getloadavg()[0]]
    windows = [preset_window("indoor_flying", 100 + k, texture_size=256) for k in range(args.windows)]
    inputs = {f"seed {windows[0].seed}": windows[0].events, "2 merged": merged_events(windows[:2]),
              "4 merged": merged_events(windows[:4])}

    # -- event volume --------------------------------------------------------------------------
    torch.set_num_threads(1)
    for events in inputs.values():
        np.testing.assert_allclose(event_volume(events, 5), voxel_grid(events, 5), atol=1e-5)
    volume_ms = {}
    for label, events in inputs.items():
        volume_ms[label] = interleaved_ms({"voxel_grid": lambda e=events: voxel_grid(e, 5),
                                           "event_volume": lambda e=events: event_volume(e, 5)}, args.repeats)
    loads.append(os.getloadavg()[0])

    # -- network forward -----------------------------------------------------------------------
    volume = torch.from_numpy(voxel_grid(inputs["4 merged"], 5))[None]
    nets = {"original, NCHW (as before)": DepthPoseNet(ModelConfig(), channels_last=False).eval(),
            "original, channels_last": DepthPoseNet(ModelConfig()).eval(),
            "width 8, dense, channels_last": DepthPoseNet(ModelConfig(width=8)).eval(),
            "width 8, separable, channels_last": DepthPoseNet(ModelConfig(width=8, block="separable")).eval(),
            "space_to_depth, width 16, separable": DepthPoseNet(ModelConfig(space_to_depth=True,
                                                                            block="separable")).eval(),
            "fast, no GroupNorm": DepthPoseNet(ModelConfig.fast(norm="none")).eval(),
            "fast": DepthPoseNet(ModelConfig.fast()).eval()}
    if pretrained.CHECKPOINT.is_file():   # the network that ships (learned/pretrained/student.pt), trained weights
        nets["shipped student (learned/pretrained)"] = load_model(pretrained.CHECKPOINT)[0]
    compile_s = trace_s = None
    if args.compile:
        torch.set_num_threads(2)
        compiled = torch.compile(DepthPoseNet(ModelConfig.fast()).eval())
        start = time.perf_counter()
        with torch.inference_mode():
            compiled(volume)
        compile_s = time.perf_counter() - start
        nets["fast, torch.compile"] = compiled
        start = time.perf_counter()
        with torch.inference_mode(), warnings.catch_warnings():
            warnings.simplefilter("ignore", torch.jit.TracerWarning)   # constants of one input shape: intended
            traced = torch.jit.freeze(torch.jit.trace(_Tensors(nets["fast"]).eval(), volume))
            traced(volume)
        trace_s = time.perf_counter() - start
        nets["fast, jit.trace + freeze"] = traced
    fast_parameters = sum(p.numel() for p in nets["fast"].parameters())
    parameters = {name: sum(p.numel() for p in net.parameters()) if "trace" not in name else fast_parameters
                  for name, net in nets.items()}   # a frozen trace holds its weights as constants
    calls, threads = {}, {}
    for name, net in nets.items():
        for n in (1, 2):
            calls[(name, n)] = lambda net=net: net(volume)
            threads[(name, n)] = n
    densest_events = inputs["4 merged"]
    fast_name = "fast, torch.compile" if args.compile else "fast"
    end_to_end = {n: lambda n=n: nets[fast_name](torch.from_numpy(event_volume(densest_events, 5))[None])
                  for n in (1, 2)}
    calls.update({("end-to-end", n): f for n, f in end_to_end.items()})
    threads.update({("end-to-end", n): n for n in end_to_end})
    with torch.inference_mode():
        forward_ms = interleaved_ms(calls, args.repeats, threads)
    whole = {n: forward_ms.pop(("end-to-end", n)) for n in end_to_end}
    loads.append(os.getloadavg()[0])

    # -- cmax.fit ------------------------------------------------------------------------------
    torch.set_num_threads(1)
    fit = lambda w: cmax.fit(w.events, w.K, "se3", speed=float(np.linalg.norm(w.twist[:3])))
    fit(windows[-1])
    fit_s, fit_cpu = [], []
    for w in windows[: args.fits]:
        start, cpu = time.perf_counter(), time.process_time()
        fit(w)
        fit_s.append(time.perf_counter() - start)
        fit_cpu.append(time.process_time() - cpu)
    fit_best = min(fit_s)
    loads.append(os.getloadavg()[0])

    train_s = {}
    if args.train_repeats:
        train_s = train_step_seconds({"original": ModelConfig(), "fast": ModelConfig.fast()}, args.train_repeats)
        loads.append(os.getloadavg()[0])

    # -- report --------------------------------------------------------------------------------
    counts = {label: len(events) for label, events in inputs.items()}
    densest = volume_ms["4 merged"]["event_volume"][1]   # its least disturbed round
    lines = [
        "# Inference speed of the depth-pose network versus cmax.fit",
        "",
        f"`python -m benchmarks.speed_learned --windows {args.windows} --repeats {args.repeats} --fits {args.fits}"
        f"{' --compile' if args.compile else ''} --train-repeats {args.train_repeats}` -- 346x260 `indoor_flying` "
        f"preset windows of 0.1665 s (seeds 100-{99 + args.windows}); median and min of {args.repeats} interleaved "
        "rounds after a warm-up, batch 1, CPU, `torch.inference_mode`, untrained weights except the shipped student's (learned/pretrained).",
        "",
        f"Machine: {platform.platform()}, {os.cpu_count()} CPUs, torch {torch.__version__}; 1-minute load average "
        f"at each stage: {' / '.join(f'{v:.2f}' for v in loads)} (the 2 cores are shared with other jobs: "
        "a load above 2 slows every row; compare the rows, which were interleaved).",
        "",
        "## Event volume (5 bins), 1 thread",
        "",
        "Wall ms, median / min of the rounds.",
        "",
        "| input | events | `voxel_grid` [ms] | `learned.volume.event_volume` [ms] | speed-up (min) |",
        "|---|---:|---:|---:|---:|",
    ]
    for label, ms in volume_ms.items():
        (grid, grid_min, _), (fast, fast_min, _) = ms["voxel_grid"], ms["event_volume"]
        lines.append(f"| {label} | {counts[label]:,} | {grid:.1f} / {grid_min:.1f} | {fast:.1f} / {fast_min:.1f} | "
                     f"{grid_min / fast_min:.1f}x |")
    lines += ["", "## Network forward and the whole window (346x260, batch 1)", "",
              f"fast = `ModelConfig.fast()` = `ModelConfig({_fields_text(ModelConfig.fast())})`; every network runs channels_last unless marked NCHW.", "",
              f"Per window = the least disturbed forward + `event_volume` on the densest input "
              f"({counts['4 merged']:,} events, {densest:.1f} ms); target <= {BUDGET_MS:.0f} ms with 2 threads. "
              "The median column is what the shared machine gave (with 2 threads a busy core stalls every "
              "parallel step, so it suffers most).", "",
              "| network | parameters | threads | forward, median [ms] | forward, min [ms] | per window [ms] | "
              "windows/s | vs cmax.fit se3 |",
              "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for (name, n), (ms, least, _) in forward_ms.items():
        total = least + densest
        lines.append(f"| {name} | {parameters[name]:,} | {n} | {ms:.1f} | {least:.1f} | {total:.1f} | "
                     f"{1e3 / total:.1f} | {fit_best * 1e3 / total:.0f}x |")
    lines += ["", f"Measured in one call (`event_volume` on the densest input, then the {fast_name} net), "
              "median / min: " + ", ".join(f"{whole[n][0]:.1f} / {whole[n][1]:.1f} ms with {n} thread"
                                          f"{'s' if n > 1 else ''}" for n in whole) + "."]
    lines += ["", f"`cmax.fit(events, K, 'se3', speed=|v|)`: {', '.join(f'{s:.2f}' for s in fit_s)} s per window "
              f"(CPU {', '.join(f'{s:.2f}' for s in fit_cpu)} s; min {fit_best:.2f} s, {1 / fit_best:.2f} windows/s, the "
              "last column's reference; 1 thread, after a warm-up fit).", ""]
    if compile_s is not None:
        lines += [f"`torch.compile` of the fast net: {compile_s:.1f} s to compile (first call, 2 threads); "
                  f"`torch.jit.trace` + `freeze`: {trace_s:.1f} s.", ""]
    if train_s:
        lines += ["## Training step (teacher loss, forward + backward + AdamW, batch 8 at 160x120, 2 threads)", "",
                  "| network | seconds per step, median | min |", "|---|---:|---:|"]
        lines += [f"| {name} | {ms / 1e3:.3f} | {least / 1e3:.3f} |" for name, (ms, least) in train_s.items()]
        lines.append("")
    write_text_atomic(args.output, "\n".join(lines))
    print("\n".join(lines))


def training_report(args: argparse.Namespace) -> None:
    """Train each of :data:`CANDIDATES` as a teacher; write ``args.training_output``."""
    load = os.getloadavg()[0]
    runs = [(name, config, args.accuracy_steps) for name, config in CANDIDATES.items()]
    if args.accuracy_fast_steps:
        runs.append((f"fast, {args.accuracy_fast_steps} steps", ModelConfig.fast(), args.accuracy_fast_steps))
    accuracy = accuracy_rows(runs, args.accuracy_train, args.accuracy_val, args.accuracy_seeds, args.accuracy_out)
    stems = [stem for stem, _ in accuracy[0][5]]
    fast_steps = f" --accuracy-fast-steps {args.accuracy_fast_steps}" if args.accuracy_fast_steps else ""
    lines = [f"# Does the fast net learn? Teacher training of each candidate, {args.accuracy_steps} steps per run", "",
             f"`python -m benchmarks.speed_learned --sections training --accuracy-steps {args.accuracy_steps}{fast_steps} "
             f"--accuracy-seeds {' '.join(map(str, args.accuracy_seeds))} --accuracy-train ... --accuracy-val ...`: "
             f"batch 8, lr 3e-4, 1 thread, the same data order for every network of a seed; trained on "
             f"{', '.join(Path(f).stem for f in args.accuracy_train)}; Abs mean [m] on the held-out "
             f"{', '.join(stems)} (short runs: the held-out scores are noisy, the training loss is the steadier "
             f"figure). Networks: {', '.join(f'{k} = `ModelConfig({_fields_text(v)})`' for k, v in CANDIDATES.items())}.",
             "", "| network | seed | steps | seconds | loss, mean of the last 10 steps | "
             + " | ".join(f"Abs mean {s} [m]" for s in stems) + " |", "|---|---:|---:|---:|---:|" + "---:|" * len(stems)]
    for name, seed, steps, seconds, loss, scores in accuracy:
        lines.append(f"| {name} | {seed} | {steps} | {seconds:.0f} | {loss:.3f} | "
                     + " | ".join(f"{v:.2f}" for _, v in scores) + " |")
    lines += ["", f"Machine: {os.cpu_count()} CPUs shared with other jobs; 1-minute load average {load:.2f} at the "
              f"start, {os.getloadavg()[0]:.2f} at the end (the seconds column depends on it).", ""]
    write_text_atomic(args.training_output, "\n".join(lines))
    print("\n".join(lines))


def _fields_text(config: ModelConfig) -> str:
    return ", ".join(f"{k}={v!r}" for k, v in changed_fields(config).items())


if __name__ == "__main__":
    raise SystemExit(main())
