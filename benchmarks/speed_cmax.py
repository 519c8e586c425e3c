"""Speed of the contrast-maximization core: section ``cmax`` of :mod:`benchmarks.speed`.

Writes ``benchmarks/results/speed_cmax.md`` and ``.json`` (through ``benchmarks.speed``'s report writer).

1. **kernels** — one forward + backward pass of warp + IWE (bilinear votes,
   Gaussian blur sigma 1) + objective for 30k events on 346x260, per warp model
   (se3 with an inverse-depth grid of 12x16 and three reference times, as
   ``cmax.fit`` uses it), float32, one thread. Baseline in the same run,
   interleaved: the *forward pass alone* in plain numpy (``np.add.at`` votes,
   ``scipy.ndimage.gaussian_filter``, variance), i.e. what a numpy
   implementation pays before any gradient.
2. **fit** — ``cmax.fit`` seconds per window for each model on the first
   windows of the accuracy benchmark (held-out seeds 100, 101, ...; see
   ``accuracy_cmax.md`` for all 20), one warm-up fit first. Ratios are against
   the flow fit of the same run.

Usage::

    python -m benchmarks.speed --section cmax [--repeats 5]
    python -m benchmarks.speed_cmax [--repeats 5]        # the same
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import gaussian_filter

from cmax.iwe import accumulate_bilinear, blur
from cmax.objectives import multi_reference_contrast
from cmax.warp import DepthGrid, warp_flow, warp_rotation, warp_se3

H, W, N = 260, 346, 30_000
#: Windows per model of the fit group (held-out seeds 100, 101, ...).
FIT_WINDOWS = 3
FIT_TARGETS_S = {"flow": 0.4, "depth": 2.0, "se3": 5.0}


def numpy_forward(x: np.ndarray, y: np.ndarray) -> float:
    """Baseline: bilinear votes with np.add.at, scipy Gaussian blur, variance (one reference time)."""
    image = np.zeros((H + 2, W + 2))
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    ok = (x0 >= -1) & (x0 <= W - 1) & (y0 >= -1) & (y0 <= H - 1)
    x0, y0, fx, fy = x0[ok] + 1, y0[ok] + 1, fx[ok], fy[ok]
    for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(image, (y0 + dy, x0 + dx), wgt)
    return float(gaussian_filter(image[1:-1, 1:-1], 1.0, mode="constant").var())


def kernel_methods() -> list[tuple[str, object, str]]:
    """``(name, function, note)`` of the kernel group; the numpy forward pass first (the baseline)."""
    rng = np.random.default_rng(0)
    x = torch.from_numpy(rng.uniform(0, W, N).astype(np.float32))
    y = torch.from_numpy(rng.uniform(0, H, N).astype(np.float32))
    t = torch.from_numpy(np.sort(rng.uniform(0, 0.1, N)).astype(np.float32))
    K = torch.tensor([[226.0, 0, 173.0], [0, 226.0, 130.0], [0, 0, 1]])
    rays = torch.stack([x, y, torch.ones_like(x)], -1) @ torch.linalg.inv(K).T
    refs = torch.tensor([0.0, 0.05, 0.1])[:, None]
    dt_mid, dt3 = (t - 0.05)[None], t[None] - refs
    grid = DepthGrid((12, 16), W, H)
    index, weight = grid.weights(x, y)

    def run(model: str) -> None:
        if model == "flow":
            p = torch.tensor([30.0, -20.0], requires_grad=True)
            xw, yw = warp_flow(x, y, dt_mid, p)
        elif model == "rotation":
            p = torch.tensor([0.1, -0.2, 0.3], requires_grad=True)
            xw, yw = warp_rotation(rays, dt_mid, p, K)
        else:
            p = torch.full((12 * 16,), 0.3, requires_grad=True)
            rho = DepthGrid.sample(p, index, weight)
            xw, yw = warp_se3(rays, dt3, torch.tensor([0.3, 0.1, 0.5]), torch.tensor([0.1, -0.2, 0.3]), rho, K)
        (-multi_reference_contrast(xw, yw, height=H, width=W, sigma=1.0)).backward()

    def forward_only() -> None:
        with torch.no_grad():
            blur(accumulate_bilinear(x, y, None, H, W), 1.0).var()

    xn, yn = x.double().numpy(), y.double().numpy()
    return [("numpy forward only (np.add.at, scipy blur)", lambda: numpy_forward(xn, yn), "baseline, float64"),
            ("torch flow fwd+bwd", lambda: run("flow"), "1 reference time"),
            ("torch rotation fwd+bwd", lambda: run("rotation"), "1 reference time"),
            ("torch se3 fwd+bwd", lambda: run("se3"), "3 reference times, 12x16 depth grid"),
            ("torch IWE forward only", forward_only, "votes + blur + variance")]


def fit_seconds(windows: int, cache: Path | None = None) -> dict[str, list[float]]:
    """``cmax.fit`` seconds per window of each model on the accuracy benchmark's first windows."""
    from benchmarks.accuracy_cmax import RUNS
    from benchmarks.accuracy_cmax import windows as make_windows

    seconds = {}
    for model in ("flow", "rotation", "depth", "se3"):
        RUNS[model](make_windows(model, 100, cache), 100)  # warm-up
        seconds[model] = [RUNS[model](make_windows(model, 100 + i, cache), 100 + i)["seconds"]
                          for i in range(windows)]
    return seconds


def cmax_section(args: argparse.Namespace, report, run_group, add_row) -> None:
    """Fill ``report`` (a ``benchmarks.speed.Report``) with the kernel and fit groups."""
    torch.set_num_threads(1)
    load_start = os.getloadavg()[0]
    run_group(report, f"warp+IWE+objective, {N} events, {W}x{H}", kernel_methods(), N, args.repeats)
    windows = getattr(args, "cmax_windows", FIT_WINDOWS)
    seconds = fit_seconds(windows, getattr(args, "cmax_cache", None))
    for i, (model, times) in enumerate(seconds.items()):
        target = FIT_TARGETS_S.get(model)
        add_row(report, "cmax.fit seconds per window", f"fit {model}", times, 0, baseline=i == 0,
                note=f"{len(times)} windows" + (f"; target <= {target} s" if target else ""))
        if target:
            report.checks[f"fit {model} median <= {target} s"] = bool(np.median(times) <= target)
    report.config.update(torch_threads=1, fit_windows=windows)
    report.notes += [
        "Kernel rows: one forward + backward pass (the gradient a solver needs); the numpy baseline is the "
        "forward pass alone, so a speed-up below 1 still means the torch pass with its gradient is cheap.",
        "Fit rows: held-out seeds 100.. of benchmarks/accuracy_cmax.py (depth = fit with pose=, se3 = fit with "
        "speed=, both given the preset's depth range 1-6.5 m; flow = 30k events, rotation = 30k of about 150k "
        "events); the 'Mev/s' column is meaningless there.",
        f"Load average (1 min): {load_start:.2f} at the start, {os.getloadavg()[0]:.2f} at the end (2 shared cores).",
    ]


def main(argv: list[str] | None = None) -> int:
    """Run section ``cmax`` of :mod:`benchmarks.speed` (arguments as ``benchmarks.speed``)."""
    from benchmarks import speed

    return speed.main(["--section", "cmax", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
