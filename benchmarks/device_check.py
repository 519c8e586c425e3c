"""Does the code give the same numbers on a GPU as on the CPU? Written to ``benchmarks/results/device_check.md``.

One short run for a machine with a GPU (none is lent to this project's CI; ``--device cpu`` runs every part on
the CPU twice, which checks the script itself). Three parts, each compared with the same computation on the
CPU:

* ``objectives``: every objective of :mod:`cmax.contrast` (value and gradient in inverse depth and twist) on two
  small synthetic windows (float64), the batch moved with :meth:`cmax.contrast.EventWindows.to`; largest
  relative difference of the values and of the gradients;
* ``training``: ``learned.train`` in teacher mode for :data:`TRAIN_STEPS` steps with ``train.device`` set, from
  the same seed on a tiny simulated scene; largest relative difference of the step losses;
* ``prediction``: ``cmax depth --device`` with a small random network on the same scene; largest relative
  difference of the depth maps.

A part passes when every difference is under its tolerance (:data:`TOLERANCE`: float64 objectives to 1e-6;
float32 convolutions, whose sums run in another order on a GPU, to 1e-3 over a few steps).

Usage::

    python -m benchmarks.device_check [--device cuda] [--out FILE]
"""
from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.synthetic_windows import tiny_training_file
from cmax.io.atomic import write_text_atomic

RESULTS = Path(__file__).resolve().parent / "results"
TRAIN_STEPS = 3
#: Largest relative difference each part accepts.
TOLERANCE = {"objectives": 1e-6, "training": 1e-3, "prediction": 1e-3}


def relative(a: np.ndarray, b: np.ndarray) -> float:
    """``max |a - b| / max(max |b|, 1e-12)``."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.abs(a - b).max() / max(float(np.abs(b).max()), 1e-12))


def objectives_part(device: torch.device) -> list[tuple[str, float]]:
    """``(objective, largest relative difference of value and gradients)`` of every core objective."""
    from benchmarks.synthetic_windows import make_window
    from cmax.contrast import (AverageTimestamp, CollapseGuard, DepthMotion, EventWindows, GlobalContrast,
                               LocalContrast, PlaneVote, SweepVote)

    windows = [make_window(preset, seed, width=64, height=48, focal=48.0, duration_s=0.1, max_frames=30)
               for preset, seed in (("indoor_flying", 3), ("slider", 2))]
    batch = EventWindows.from_windows([(w.events, w.K) for w in windows], dtype=torch.float64,
                                      max_events=3000).with_speed([0.5, float("nan")])
    rho = torch.rand(2, 1, 4, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 0.6 + 0.2
    twist = torch.as_tensor(np.stack([w.twist for w in windows]))
    candidates = {"AverageTimestamp (shared)": AverageTimestamp(smoothness=0.003),
                  "SweepVote": SweepVote(rho_range=(0.2, 1.0), candidates=6),
                  "PlaneVote": PlaneVote(rho_range=(0.2, 1.0), planes=6, motion_weight=2.0, motion_cells=(2, 3)),
                  "LocalContrast": LocalContrast(cells=(2, 3), margin=3, smoothness=0.01),
                  "GlobalContrast": GlobalContrast(), "CollapseGuard": CollapseGuard(lattice=(3, 4))}
    rows = []
    for name, objective in candidates.items():
        results = []
        for where in (torch.device("cpu"), device):
            r = rho.clone().to(where).requires_grad_(True)
            t = twist.clone().to(where).requires_grad_(True)
            value = objective(batch.to(device=where), DepthMotion(r, t))
            value.sum().backward()
            results.append([x.detach().cpu().numpy() for x in (value, r.grad, t.grad)])
        rows.append((name, max(relative(a, b) for a, b in zip(results[1], results[0]))))
    return rows


def training_part(device: torch.device, scene: Path, folder: Path) -> list[tuple[str, float]]:
    """``("teacher losses over N steps", largest relative difference)``."""
    from learned.config import load_config
    from learned.train import Trainer

    losses = []
    for k, name in enumerate(("cpu", str(device))):
        overrides = [f'data.files=["{scene}"]', "data.max_events=1500", "data.window_us=100000", "model.width=4",
                     "model.levels=2", "train.batch_size=4", "train.lr=3e-3", f"train.out={folder / f'train_{k}'}",
                     f"train.steps={TRAIN_STEPS}", "train.image_every=1000", f"train.device={name}"]
        torch.manual_seed(0)
        losses.append(np.array(Trainer(load_config(None, overrides, mode="teacher"), progress=False).run()))
    return [(f"teacher losses over {TRAIN_STEPS} steps", relative(losses[1], losses[0]))]


def prediction_part(device: torch.device, scene: Path, folder: Path) -> list[tuple[str, float]]:
    """``("depth maps of cmax depth", largest relative difference)`` with a small random network."""
    from learned.checkpoint import rng_state, save_checkpoint
    from learned.config import Config, DataConfig
    from learned.model import DepthPoseNet, ModelConfig
    from learned.predict import run_prediction

    torch.manual_seed(5)
    config = Config(model=ModelConfig(width=4, levels=2), data=DataConfig(window_us=100_000))
    checkpoint = folder / "random.pt"
    save_checkpoint(checkpoint, {"model": DepthPoseNet(config.model).state_dict(), "optimizer": {}, "step": 0,
                                 "config": config.to_dict(), "rng": rng_state()})
    depths = []
    for k, name in enumerate(("cpu", str(device))):
        out = folder / f"depth_{k}"
        run_prediction(scene, out, checkpoint=checkpoint, progress=False, note=lambda text: None, device=name)
        depths.append(np.stack([np.load(path)["depth"] for path in sorted(out.glob("window_*.npz"))]))
    return [("depth maps of cmax depth", relative(depths[1], depths[0]))]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda", help="the device to check against the CPU (default cuda)")
    parser.add_argument("--out", type=Path, default=RESULTS / "device_check.md")
    args = parser.parse_args(argv)
    from learned.device import resolve_device

    try:
        device = resolve_device(args.device)
    except ValueError as error:
        parser.error(str(error))
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        scene = tiny_training_file(folder)
        parts = {"objectives": objectives_part(device), "training": training_part(device, scene, folder),
                 "prediction": prediction_part(device, scene, folder)}
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor() or "CPU"
    lines = ["# The same numbers on another device", "",
             f"`python -m benchmarks.device_check --device {args.device}`: {device} ({name}) against the CPU, "
             f"torch {torch.__version__}, {time.perf_counter() - started:.0f} s. Relative difference = "
             "max |device - cpu| / max |cpu|.", "",
             "| part | what | relative difference | tolerance | |", "|---|---|---|---|---|"]
    failed = 0
    for part, rows in parts.items():
        for what, difference in rows:
            ok = difference <= TOLERANCE[part]
            failed += not ok
            lines.append(f"| {part} | {what} | {difference:.2e} | {TOLERANCE[part]:g} | {'ok' if ok else 'FAILED'} |")
    lines += ["", f"{failed} of {sum(len(rows) for rows in parts.values())} comparisons outside their tolerance."]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
