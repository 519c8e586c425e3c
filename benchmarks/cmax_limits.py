"""Where the remaining errors of ``cmax.fit`` come from, written to ``benchmarks/results/cmax_limits.md``.

Section ``depth``: the depth with known motion. On the held-out ``indoor_flying``
windows of :mod:`benchmarks.accuracy_cmax` (0.1665 s, 346x260, known motion
``pose=T01``), four figures per window, all abs_rel on the same pixels
(``FitResult.mask`` with finite ground truth):

``fit``
    ``cmax.fit(events, K, pose=T01)`` as the accuracy table measures it.
``grid floor``
    The best the fit's inverse-depth grid (``FitResult.inverse_depth_grid``,
    24 x 32 by default) can do: the grid fitted to the ground-truth inverse
    depth of those pixels by least squares.
``objective floor``
    Where the contrast itself puts each grid node when every event already
    has its TRUE inverse depth: the relative sweep of
    :func:`cmax.fitting.depth_sweep.relative_sweep_cost` around the per-event
    ground truth (steps ``exp(-0.5 .. 0.5)``), each node's parabolic arg-max,
    interpolated to the pixels and applied to the ground truth. A perfect
    optimiser of the sweep's objective cannot do better than this.
``EMVS``
    :class:`cmax.EMVS` (100 planes over 0.8-8 m) with the same constant-twist
    motion, on its own semi-dense mask (coverage in brackets): the
    field's usual baseline for depth from events with known poses.

Section ``rotation``: the angular velocity of the held-out rotation windows
of :mod:`benchmarks.accuracy_cmax` (0.05 s, ``max_events=30000`` as there):
the relative error of the benchmark's fit (subsample seed 0), its spread
over other random 30k-event subsets of the same window (seeds 1-3), and the
error when all the window's events are used. When the error changes as much
between subsets as it is large, the 30k events, not the optimiser, set it.

Section ``se3``: the depth of ``fit(events, K, speed=|v|)`` on the same
``indoor_flying`` windows, and how much of its error the rotation causes.
Every fit here keeps ``FitSettings``' default depth range (0.5-60 m), where
the ambiguity shows in full: ``se3_default_range`` of ``accuracy_cmax.md``
(the room's range of 1-6.5 m stops part of it).
``fit``, ``true_omega``, ``true_v``: abs_rel of the fit, and of the depth
with a known pose made of the fit's direction and the TRUE angular velocity,
or the TRUE velocity and the fit's angular velocity; ``omega_rms`` the fit's
omega error [deg/s]. Then the rotation-translation ambiguity: motions on the
line from the truth (``t = 0``) to the fit (``t = 1``), ``(v, omega) = truth +
t (fit - truth)`` (``v`` renormalised), ``t`` in ``PROFILE_T``, scored by the
patch-wise contrast of the fit's own motion refinement
(:class:`cmax.fitting.motion.LocalMotionObjective`, 6 x 8 patches) with two
depths: ``peak_t_true_structure`` is the ``t`` of the highest score when
every event has its TRUE inverse depth times one free factor (the best of
``STRUCTURE_SCALES``), ``peak_t_swept`` when the depth is swept for each
motion as ``fit`` does (free per grid node). ``gap_percent`` is how much the
score with swept depth changes between the truth and the fit, in percent.

Section ``se3_slider``: the same measures on the ``slider`` preset windows of
:mod:`benchmarks.accuracy_presets` (objects before a poster wall, the camera
translates sideways on a slider and does not rotate).

Usage::

    python -m benchmarks.cmax_limits [--seeds 100-119] [--cache DIR] [--sections depth,rotation,se3,se3_slider]
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.accuracy_cmax import RESULTS, ROTATION_EVENTS, parse_names, parse_seeds, windows
from benchmarks.accuracy_presets import preset_window
from cmax.camera import Camera
from cmax.emvs import EMVS
from cmax.fitting import FitSettings, fit
from cmax.fitting.depth_sweep import _parabolic_argmax, node_cost_function, relative_sweep_cost
from cmax.fitting.motion import LocalMotionObjective
from cmax.fitting.patch_flow import make_patches
from cmax.fitting.pipeline import DepthSweepStage, Motion
from cmax.fitting.window import Window
from cmax.geometry import se3_exp, se3_log
from cmax.io.atomic import write_text_atomic
from cmax.iwe import sample_bilinear
from cmax.metrics import depth_metrics
from cmax.warp import DepthGrid, WarpEvents, warp_se3

#: Log steps of the relative sweep around the true per-event inverse depth.
STEPS = torch.linspace(-0.5, 0.5, 21)
#: Positions on the line from the true motion (0) to the fitted one (1) where the se3 section scores the motion.
PROFILE_T = (-1.0, -0.5, 0.0, 0.5, 1.0, 1.5)
#: Factors of the true inverse depth tried at each position (the structure is known, its scale is not).
STRUCTURE_SCALES = np.exp(np.linspace(-0.5, 0.5, 11))
#: Nodes with less event weight than this are left out of the objective floor's step statistics.
MIN_NODE_WEIGHT = 100.0


def abs_rel(depth: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    return depth_metrics(depth, truth, mask=mask).abs_rel


def grid_floor(truth: np.ndarray, mask: np.ndarray, grid: DepthGrid) -> np.ndarray:
    """Dense depth (H, W) of the grid fitted to ``1 / truth`` on ``mask`` by (slightly damped) least squares."""
    ys, xs = np.nonzero(mask)
    index, weight = grid.weights(torch.from_numpy(xs.astype(np.float64)), torch.from_numpy(ys.astype(np.float64)))
    G = grid.shape[0] * grid.shape[1]
    A = np.zeros((len(xs), G))
    np.add.at(A, (np.repeat(np.arange(len(xs)), 4), index.numpy().ravel()), weight.numpy().ravel())
    b = 1.0 / truth[ys, xs]
    damping = 1e-3
    A = np.vstack([A, damping * np.eye(G)])
    b = np.r_[b, np.full(G, damping * np.median(b))]
    return 1.0 / grid.upsample(np.linalg.lstsq(A, b, rcond=None)[0])


def true_event_inverse_depth(ev: WarpEvents, truth: np.ndarray, v: torch.Tensor, omega: torch.Tensor,
                             dt: torch.Tensor) -> torch.Tensor:
    """Inverse depth (N,) [1/m] of each event: the ground truth where the event lands at the reference time."""
    return true_inverse_depth(ev.x, ev.y, ev.rays, ev.K, truth, v, omega, dt)


def true_inverse_depth(x: torch.Tensor, y: torch.Tensor, rays: torch.Tensor, K: torch.Tensor, truth: np.ndarray,
                       v: torch.Tensor, omega: torch.Tensor, dt: torch.Tensor) -> torch.Tensor:
    """Inverse depth (N,) [1/m] of events at pixels ``x, y`` (N,) with ``rays`` (N, 3), ``dt`` (1, N) or (N,) [s]:
    the ground truth ``truth`` (H, W) [m] where each lands at the reference time under the motion ``v, omega``."""
    truth_map = torch.as_tensor(np.nan_to_num(1.0 / truth, nan=0.0), dtype=x.dtype)[None]
    rho = sample_bilinear(truth_map, x[None], y[None])[0]
    for _ in range(3):  # fixed point: the landing point depends on the depth
        x1, y1 = warp_se3(rays, dt, v, omega, rho[None] if dt.dim() == 2 else rho, K)
        rho = sample_bilinear(truth_map, x1.reshape(1, -1), y1.reshape(1, -1))[0]
    return rho


def objective_floor(window, grid: DepthGrid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-node arg-max steps (G,) of the sweep around the true depth, node weights (G,), dense step map (H, W)."""
    settings = FitSettings()
    ev = WarpEvents.from_events(window.events, window.K, max_events=settings.max_events, seed=settings.seed)
    xi = se3_log(window.T01) / ev.duration_s
    v, omega = torch.as_tensor(xi[:3], dtype=ev.x.dtype), torch.as_tensor(xi[3:], dtype=ev.x.dtype)
    dt = ev.dt((0.5,))
    index, weight = grid.weights(ev.x, ev.y)
    with torch.no_grad():
        rho = true_event_inverse_depth(ev, window.depth, v, omega, dt)
        cost = node_cost_function(ev.rays, dt, ev.polarity, xi[:3], xi[3:], ev.K, height=ev.height,
                                  width=ev.width, grid_shape=grid.shape, index=index, weight=weight,
                                  sigma=settings.sigma)
        curves = relative_sweep_cost(cost, rho, STEPS.to(ev.x.dtype))
        steps = _parabolic_argmax(curves, STEPS.to(ev.x.dtype)).numpy().astype(np.float64)
    node_weight = np.bincount(index.reshape(-1).numpy(), weights=weight.reshape(-1).numpy(),
                              minlength=steps.size)
    return steps, node_weight, grid.upsample(steps)


def emvs_depth(window) -> tuple[np.ndarray, np.ndarray]:
    """EMVS depth and mask with the window's constant-twist motion."""
    events = window.events
    t0, t1 = int(events.t[0]), int(events.t[-1])
    xi = se3_log(window.T01) / ((t1 - t0) * 1e-6)
    times = np.linspace(t0, t1, 64).round().astype(np.int64)
    poses = np.stack([se3_exp(xi * (t - t0) * 1e-6) for t in times])
    camera = Camera(window.K, events.width, events.height)
    result = EMVS(camera, depth_range=(0.8, 8.0), n_planes=100).run(events, (times, poses))
    return result.depth, result.mask


def measure(window) -> dict:
    truth = window.depth
    result = fit(window.events, window.K, pose=window.T01)
    mask = result.mask & np.isfinite(truth)
    grid = DepthGrid(result.inverse_depth_grid.shape, window.events.width, window.events.height)
    steps, node_weight, step_map = objective_floor(window, grid)
    used = node_weight >= MIN_NODE_WEIGHT
    floor_depth = truth / np.exp(step_map)      # a node's step scales the inverse depth
    emvs, emvs_mask = emvs_depth(window)
    emvs_mask = emvs_mask & np.isfinite(truth)
    return {
        "fit": abs_rel(result.depth, truth, mask),
        "grid_floor": abs_rel(grid_floor(truth, mask, grid), truth, mask),
        "objective_floor": abs_rel(floor_depth, truth, mask),
        "node_step_median": float(np.median(steps[used])),
        "node_step_mean_abs": float(np.mean(np.abs(steps[used]))),
        "emvs": abs_rel(emvs, truth, emvs_mask) if emvs_mask.any() else float("nan"),
        "emvs_coverage": float(emvs_mask.mean()),
        "fit_coverage": float(mask.mean()),
    }


def measure_rotation(window, subsets: int = 4) -> dict:
    """Relative omega errors: subsample seed 0, the spread over seeds 0..subsets-1, all events."""
    truth = window.twist[3:]
    error = lambda r: float(np.linalg.norm(r.omega - truth) / np.linalg.norm(truth))  # noqa: E731
    errors = [error(fit(window.events, window.K, model="rotation", max_events=ROTATION_EVENTS, seed=seed))
              for seed in range(subsets)]
    every = fit(window.events, window.K, model="rotation", max_events=len(window.events))
    return {"error_30k": errors[0], "subset_min": min(errors), "subset_max": max(errors),
            "subset_std": float(np.std(errors)), "error_all_events": error(every), "events": float(len(window.events))}


def _patch_score(objective: LocalMotionObjective, v: np.ndarray, omega: np.ndarray,
                 rho_events: torch.Tensor) -> float:
    """Sum over patches of the normalised patch contrast for a motion and per-event inverse depths (M,) [1/m]."""
    dtype = objective.rays.dtype
    with torch.no_grad():
        return float(objective.contrast_at(torch.as_tensor(v, dtype=dtype), torch.as_tensor(omega, dtype=dtype),
                                           rho_events).sum())


def measure_se3(window) -> dict:
    """The se3 fit's depth error, with the true rotation or translation, and the ambiguity profile."""
    truth = window.depth
    v_true, omega_true = window.twist[:3], window.twist[3:]
    speed = float(np.linalg.norm(v_true))
    result = fit(window.events, window.K, speed=speed)
    error = lambda r: abs_rel(r.depth, truth, r.mask & np.isfinite(truth))  # noqa: E731
    row = {
        "fit": error(result),
        "true_omega": error(fit(window.events, window.K, pose=np.r_[result.v, omega_true])),
        "true_v": error(fit(window.events, window.K, pose=np.r_[v_true, result.omega])),
        "omega_rms": float(np.degrees(np.sqrt(np.mean((result.omega - omega_true) ** 2)))),
    }
    settings = FitSettings()
    w = Window.from_events(window.events, window.K, settings)
    r = settings.refine
    patches = make_patches(w, grid=r.grid, min_events=r.min_events, max_events=r.max_events, margin=r.margin)
    objective = LocalMotionObjective.build(w, patches, speed)
    dtype = objective.rays.dtype
    patch_index, patch_weight = w.grid.weights(patches.x, patches.y)
    with torch.no_grad():  # each patch event's true inverse depth, where the true motion takes it
        rho_true = true_inverse_depth(patches.x, patches.y, objective.rays, objective.K, truth,
                                      torch.as_tensor(v_true, dtype=dtype), torch.as_tensor(omega_true, dtype=dtype),
                                      patches.dt)
    structure, swept = [], []
    for t in PROFILE_T:
        v = v_true + t * (result.v - v_true)
        v = speed * v / np.linalg.norm(v)
        omega = omega_true + t * (result.omega - omega_true)
        structure.append(max(_patch_score(objective, v, omega, rho_true * float(k)) for k in STRUCTURE_SCALES))
        swept_motion, _ = DepthSweepStage().run(w, Motion(v=v, omega=omega), None)
        grid = torch.as_tensor(swept_motion.inverse_depth.reshape(-1), dtype=dtype)
        swept.append(_patch_score(objective, v, omega, DepthGrid.sample(grid, patch_index, patch_weight)))
    at = {t: i for i, t in enumerate(PROFILE_T)}
    row.update({
        "peak_t_true_structure": PROFILE_T[int(np.argmax(structure))],
        "peak_t_swept": PROFILE_T[int(np.argmax(swept))],
        "gap_percent": 100.0 * (swept[at[1.0]] - swept[at[0.0]]) / swept[at[0.0]],
        "parallax_px": float(result.parallax_px),
    })
    return row


MEASURES = {"depth": ("depth", measure), "rotation": ("rotation", measure_rotation), "se3": ("se3", measure_se3),
            "se3_slider": ("preset:slider", measure_se3)}


def section_window(kind: str, seed: int, cache: Path | None):
    """The window a section measures: ``preset:NAME`` windows of :mod:`benchmarks.accuracy_presets`, or the
    windows of :func:`benchmarks.accuracy_cmax.windows` for the model ``kind``."""
    if kind.startswith("preset:"):
        return preset_window(kind.split(":", 1)[1], seed, cache)
    return windows(kind, seed, cache)


TITLES = {
    "depth": "Depth with known motion (`pose=`): the fit against its floors",
    "rotation": "Rotation: the error of 30k-event subsets against all events",
    "se3": "se3 with known speed: the depth error the rotation causes, and the ambiguity behind it",
    "se3_slider": "se3 on the `slider` preset (a pure translation): the same measures",
}
NOTES = {
    "depth": "`node_step_*`: log factor between the inverse depth a node's contrast peaks at and the truth "
             "(positive: the contrast prefers nearer depths).",
    "rotation": "Relative omega errors `|omega - truth| / |truth|`; `subset_*` over 4 random 30k-event subsets "
                "(seeds 0-3) of the same window.",
    "se3": "abs_rel of the fit, with the true omega, with the true v; `peak_t_*`: where on the line truth (0) -> "
           "fit (1) the patch-wise contrast peaks, with the true depth structure (one free scale) or with the "
           "depth swept per motion; `gap_percent`: score(fit) - score(truth) with swept depth, in percent.",
    "se3_slider": "As for se3. The slider's camera does not rotate (true omega = 0): every deg/s of `omega_rms` "
                  "is a rotation the fit invented, and the per-node depth absorbed.",
}


def summarise(section: str, rows: list[dict], seeds: list[int]) -> str:
    keys = list(rows[0])
    table = np.array([[r[k] for k in keys] for r in rows])
    lines = [
        f"## {TITLES[section]}", "",
        "| figure | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys),
        "| median | " + " | ".join(f"{v:.3f}" for v in np.nanmedian(table, 0)) + " |",
        "| p90 | " + " | ".join(f"{v:.3f}" for v in np.nanpercentile(table, 90, axis=0)) + " |", "",
        NOTES[section], "", "Per window:", "",
    ]
    for seed, row in zip(seeds, rows):
        lines.append(f"- seed {seed}: " + ", ".join(f"{k} {v:.3f}" for k, v in row.items()))
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="100-119", help="first-last (default 100-119, the held-out seeds)")
    parser.add_argument("--cache", type=Path, default=None,
                        help="folder of simulated windows (benchmarks.accuracy_cmax)")
    parser.add_argument("--sections", default="depth,rotation,se3,se3_slider")
    args = parser.parse_args(argv)
    seeds = parse_seeds(parser, args.seeds)
    sections = parse_names(parser, "--sections", args.sections, MEASURES)
    torch.set_num_threads(1)
    start = time.perf_counter()
    parts = []
    for section in sections:
        kind, measure_window = MEASURES[section]
        rows = []
        for seed in seeds:
            rows.append(measure_window(section_window(kind, seed, args.cache)))
            print(section, seed, {k: round(v, 3) for k, v in rows[-1].items()}, flush=True)
        parts.append(summarise(section, rows, seeds))
    header = ("# Where the remaining errors of cmax.fit come from\n\n"
              f"Held-out windows, seeds {seeds[0]}-{seeds[-1]}, written by `python -m benchmarks.cmax_limits` in "
              f"{time.perf_counter() - start:.0f} s (load average at the end {os.getloadavg()[0]:.2f}); the module "
              "docstring defines every column.\n\n")
    text = header + "\n".join(parts)
    RESULTS.mkdir(exist_ok=True)
    write_text_atomic(RESULTS / "cmax_limits.md", text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
