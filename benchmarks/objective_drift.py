"""Where does a read-at-event objective's data term move a depth grid started at the truth? The tuning tables of
``docs/contrast_objective.md`` ("Cross-fitting"), printed.

For each window (a preset of :mod:`cmax.sim.presets` as :mod:`benchmarks.objective_identifiability` makes it,
the true motion known): Adam (``STEPS`` steps, log inverse depth) on the 24 x 32 grid from the truth averaged
onto it, for the sweep vote and the plane vote, each plain and cross-fitted (:class:`cmax.contrast.CrossFit`:
``loo``, ``halves``, ``pixels``), data term alone; printed: abs_rel where the descent ends (on the event pixels,
as the identifiability benchmark) and its loss minus the truth's. Then, for the plain plane vote, each 24 x 32
cell's events' summed normalised votes per plane: on how many cells the truth is within 2% of the cell's best
plane, and the span in log depth of the planes within 2% of it (a flat profile: a wide span).

Usage::

    python -m benchmarks.objective_drift [--seeds 1-1] [--size 160x120] [--presets indoor_flying,driving_day,slider]
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from benchmarks.accuracy_cmax import parse_seeds, preset_depth_range, with_truth
from benchmarks.objective_identifiability import CROSS_FITS, GRID, MAX_EVENTS, _with_motion, abs_rel, dense, descend
from benchmarks.objective_identifiability import truth_maps
from benchmarks.synthetic_windows import preset_window
from cmax.contrast import DepthMotion, EventWindows, PlaneVote, SweepVote
from cmax.fitting.api import event_pixels

STEPS = 120


def profile_flatness(objective: PlaneVote, batch: EventWindows, truth_grid: torch.Tensor) -> tuple[float, float]:
    """For ``objective`` with its planes fixed (:meth:`PlaneVote.with_motion`): the share of 24 x 32 cells (with
    >= 20 events) whose true inverse depth ``truth_grid`` (1, 1, 24, 32) [1/m] is within 2% of the cell's best
    summed vote, and the median span [log depth] of the planes within 2% of it."""
    values, kept, scale = objective.values
    rows, cols = GRID
    cell = ((batch.y * rows / batch.height).long().clamp(0, rows - 1) * cols
            + (batch.x * cols / batch.width).long().clamp(0, cols - 1)).numpy()
    votes = (values * kept / scale).numpy()
    profile = np.zeros((votes.shape[0], rows * cols))
    np.add.at(profile.T, cell, votes.T)
    count = np.bincount(cell, minlength=rows * cols)
    planes = objective.plane_inverse_depths().numpy()
    used = count >= 20
    profile = profile[:, used] / count[used]
    peak = profile.max(0)
    at = np.interp(np.log(truth_grid.numpy().reshape(-1)[used]), np.log(planes), np.arange(len(planes)))
    at_truth = np.array([np.interp(a, np.arange(len(planes)), profile[:, i]) for i, a in enumerate(at)])
    span = (profile >= 0.98 * peak).sum(0) * float(np.log(planes[1] / planes[0]))
    return float(np.mean(peak - at_truth <= 0.02 * peak)), float(np.median(span))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1-1", help="tuning seeds FIRST-LAST (within 1-12)")
    parser.add_argument("--size", default="160x120", help="width x height [px]")
    parser.add_argument("--presets", default="indoor_flying,driving_day,slider")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    width, height = (int(v) for v in args.size.split("x"))
    for preset in args.presets.split(","):
        for seed in parse_seeds(parser, args.seeds):
            window = preset_window(preset, seed, width=width, height=height)
            depth_range = preset_depth_range(preset)
            rho_range = tuple(sorted(1.0 / np.array(depth_range)))
            batch = EventWindows.from_events(window.events, window.K, max_events=MAX_EVENTS, dtype=torch.float32,
                                             speed=float(np.linalg.norm(window.twist[:3])))
            pixels = with_truth(event_pixels(window.events.x.astype(float), window.events.y.astype(float),
                                             height, width), window.depth, depth_range)
            twist = torch.tensor(window.twist, dtype=torch.float32)[None]
            _, truth = truth_maps(window, rho_range, torch.float32)
            print(f"{preset} {seed}: truth on grid abs_rel {abs_rel(dense(batch, truth), window.depth, pixels):.3f}")
            for kind in (SweepVote, PlaneVote):
                for split, cross_fit in {"plain": None, **CROSS_FITS}.items():
                    objective = _with_motion(kind(rho_range=rho_range, cross_fit=cross_fit), batch, twist)
                    with torch.no_grad():
                        start = float(objective(batch, DepthMotion(truth, twist))[0])
                    grid, loss = descend(objective, batch, twist, truth, STEPS, rho_range)
                    error = abs_rel(dense(batch, grid), window.depth, pixels)
                    print(f"  {kind.__name__:9s} {split:6s} abs_rel {error:.3f}  loss - truth's {loss - start:+.4f}",
                          flush=True)
            share, span = profile_flatness(_with_motion(PlaneVote(rho_range=rho_range), batch, twist), batch, truth)
            print(f"  PlaneVote cells: truth within 2% of the best plane on {share:.2f}; median span within 2%: "
                  f"{span:.2f} in log depth")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
