"""Speed of the contrast-maximization core, written to ``benchmarks/results/speed_cmax.md``.

1. One forward + backward pass of warp + IWE (bilinear votes, Gaussian blur
   sigma 1) + objective for 30k events on 346x260, per warp model (se3 with an
   inverse-depth grid of 12x16 and three reference times, as ``cmax.fit`` uses
   it), float32, one thread. Baseline in the same process: the *forward pass
   alone* in plain numpy (``np.add.at`` votes, ``scipy.ndimage.gaussian_filter``,
   variance), i.e. what a numpy implementation pays before any gradient.
2. ``cmax.fit`` seconds per window for each model on a few synthetic windows
   (the accuracy benchmark's windows; see ``accuracy_cmax.md`` for all 20).

Usage::

    python benchmarks/speed_cmax.py [--repeats 20] [--windows 3] [--cache DIR]
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import gaussian_filter

from cmax.iwe import accumulate_bilinear, blur
from cmax.objectives import multi_reference_contrast
from cmax.warp import DepthGrid, warp_flow, warp_rotation, warp_se3

RESULTS = Path(__file__).resolve().parent / "results"
H, W, N = 260, 346, 30_000


def _timed(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


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


def kernel_rows(repeats: int) -> list[tuple[str, float, float]]:
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
        value = -multi_reference_contrast(xw, yw, height=H, width=W, sigma=1.0)
        value.backward()

    xn, yn = x.double().numpy(), y.double().numpy()
    baseline = _timed(lambda: numpy_forward(xn, yn), repeats)
    rows = []
    for model in ("flow", "rotation", "se3"):
        seconds = _timed(lambda m=model: run(m), repeats)
        rows.append((model, seconds, baseline))
    with torch.no_grad():
        forward_only = _timed(lambda: blur(accumulate_bilinear(x, y, None, H, W), 1.0).var(), repeats)
    rows.append(("IWE forward only (torch)", forward_only, baseline))
    return rows


def fit_rows(windows: int, cache: Path | None) -> list[tuple[str, float, float, int]]:
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from benchmarks.accuracy_cmax import RUNS
    from benchmarks.accuracy_cmax import windows as make_windows

    rows = []
    for model in ("flow", "rotation", "depth", "se3"):
        RUNS[model](make_windows(model, 100, cache))  # warm-up
        seconds = [RUNS[model](make_windows(model, 100 + i, cache))["seconds"] for i in range(windows)]
        rows.append((model, statistics.median(seconds), max(seconds), windows))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--windows", type=int, default=3)
    parser.add_argument("--cache", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    kernels = kernel_rows(args.repeats)
    fits = fit_rows(args.windows, args.cache)
    lines = ["# cmax speed", "",
             f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores (shared), torch "
             f"{torch.__version__}, one thread. Written by `benchmarks/speed_cmax.py`.", "",
             f"## Forward + backward of warp + IWE + objective, {N} events, {W}x{H}, sigma 1", "",
             "| model | ms (median) | numpy forward-only baseline ms | speed-up |", "|---|---|---|---|"]
    for name, seconds, baseline in kernels:
        lines.append(f"| {name} | {seconds * 1e3:.1f} | {baseline * 1e3:.1f} | {baseline / seconds:.1f}x |")
    lines += ["", "flow and rotation warp to one reference time, se3 to three (as `cmax.fit`).", "",
              "## `cmax.fit` seconds per window", "",
              "| model | median s | max s | windows | target |", "|---|---|---|---|---|"]
    targets = {"flow": "<= 0.4 s (30k events)", "depth": "<= 2 s", "se3": "<= 5 s", "rotation": ""}
    for model, med, worst, count in fits:
        lines.append(f"| {model} | {med:.2f} | {worst:.2f} | {count} | {targets[model]} |")
    RESULTS.mkdir(exist_ok=True)
    text = "\n".join(lines) + "\n"
    (RESULTS / "speed_cmax.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
