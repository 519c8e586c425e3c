"""``cmax.fit`` and ``fit_sequence`` on scenes the fit was never tuned on, written to
``benchmarks/results/unseen_scenes.md``: for each case, the truth, the estimate, its error and the verdict,
and whether the window is a *confident wrong answer* (verdict ``ok`` with a direction more than ``BAD_DEG`` off,
a depth abs_rel over ``BAD_ABS_REL``, or a rotation error over ``BAD_ROTATION`` of the true rate and over 1 px of
image motion; on a pure rotation any ``ok``: the depth is unobservable).

The scenes are built here (not the presets of :mod:`benchmarks.synthetic_windows` or :mod:`cmax.sim.presets`):
a box room of random size and textures with a few boxes in it, seen by a camera with a constant body twist (so
that the se3 warp is exact), rendered by :class:`cmax.sim.render.PlanarRenderer` and turned into events by
:class:`cmax.sim.esim.EventSimulator`. The cases: ``general`` (a room, translation and rotation, 8-20 px of
motion on 160x120), ``pure_rotation``, ``forward`` (the focus of expansion in the image), ``forward_rotation``,
``slow`` (0.5-2 px over the window), ``fast`` (50-80 px), ``plane`` (one fronto-parallel textured wall),
``few_edges`` (a blank wall with two faint bars), ``noise`` (1-5 Hz per pixel of background activity and 20 hot
pixels), ``near`` (the room scaled to 0.05-0.3 m) and ``far`` (scaled to 200-1000 m), both also fitted with
``speed=|v|`` (``near_metric``, ``far_metric``: the default ``depth_range`` of 0.5-60 m), ``vga`` (640x480) and
``hd`` (1280x720), ``half_texture`` (the right half of the view a blank wall), ``one_polarity`` (the ``general``
window's ON events only). ``slow``, ``fast``, ``noise``, ``near``, ``far``, ``vga``, ``hd`` and ``one_polarity`` change
the ``general`` window of the same seed (the same room and motion direction). Every fit is ``cmax.fit(events, K)`` with the defaults (se3, scale unknown: the depth
is compared after multiplying by the true speed) but for the ``*_metric`` rows; ``fit_sequence`` fits three
consecutive windows of the same motion (not for ``vga`` and ``hd``: their rendering is slow).

    python -m benchmarks.unseen_scenes [--seeds 500-505] [--cases general,plane] [--output FILE]
"""
from __future__ import annotations

import argparse
import math
import time
import warnings
from dataclasses import dataclass

import numpy as np
import torch

from benchmarks.machine import describe
from benchmarks.synthetic_windows import _room
from cmax.camera import Camera
from cmax.events import Events, concatenate
from cmax.fitting import FitSettings, QualitySettings, Verdict, fit, fit_sequence
from cmax.fitting.pipeline import depth_on_bounds
from cmax.fitting.window import Window
from cmax.geometry import se3_exp
from cmax.io.atomic import write_text_atomic
from cmax.sim.esim import EventSimulator
from cmax.sim.render import PlanarRenderer
from cmax.sim.textures import Texture
from cmax.sim.trajectories import look_at_rotation
from cmax.sim.world import WorldBuilder

#: Confident wrong: an ``ok`` window with a direction error over this [deg] ...
BAD_DEG = 30.0
#: ... or a depth abs_rel over this ...
BAD_ABS_REL = 0.5
#: ... or a rotation error over this share of the true rate (and over 1 px of image motion over the window).
BAD_ROTATION = 0.3
#: The verdict's settings before the bas-relief turn test (``bas_relief_turn_deg``; the ``before`` columns).
BEFORE = QualitySettings(bas_relief_turn_deg=0.0)

CASES = ("general", "pure_rotation", "forward", "forward_rotation", "slow", "fast", "plane", "few_edges", "noise",
         "near", "near_metric", "far", "far_metric", "vga", "hd", "half_texture", "one_polarity")
WINDOW_S = 0.1
SEQUENCE_WINDOWS = 3


@dataclass(frozen=True, eq=False)
class Case:
    """A simulated recording of ``SEQUENCE_WINDOWS`` windows of one constant body twist and its truth."""

    events: Events
    K: np.ndarray
    twist: np.ndarray            # (6,) v [m/s], omega [rad/s], camera frame
    renderer: PlanarRenderer
    T_w_c0: np.ndarray
    windows: int

    def depth_at(self, t_us: float) -> np.ndarray:
        """z-depth (H, W) [m] at ``t_us`` (NaN: nothing)."""
        _, depth = self.renderer.render(self.T_w_c0 @ se3_exp(self.twist * t_us * 1e-6))
        return depth


def _pose(forward, position) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = look_at_rotation(forward)
    T[:3, 3] = position
    return T


def _unit(rng: np.random.Generator) -> np.ndarray:
    u = rng.normal(size=3)
    return u / np.linalg.norm(u)


def _bars_texture(rng: np.random.Generator, size: int = 256, bars: int = 2) -> Texture:
    """A blank grey texture with ``bars`` faint dark bars near its centre: few edges, few events."""
    values = np.full((size, size), 120.0, np.float32)
    for _ in range(bars):
        x0, y0 = rng.integers(size * 2 // 5, size * 3 // 5, 2)
        values[y0 - size // 16:y0 + size // 16, x0 - size // 64:x0 + size // 64] = 95.0
    return Texture(values, name="bars")


def _world(case: str, rng: np.random.Generator):
    """World, start pose and the twist's direction (before scaling to the case's image motion)."""
    b = WorldBuilder(rng, texture_size=256)
    deg = math.pi / 180
    v, omega = _unit(rng), _unit(rng) * rng.uniform(0.1, 0.4)     # rotation about 0.1-0.4 of the translation's
    if case in ("plane", "few_edges"):
        near = rng.uniform(1.5, 4.0)
        if case == "few_edges":    # the bars' texture once over a wall 2 near wide: they lie in the view
            b.image_quad([-2 * near, near, -2 * near], [4 * near, 0, 0], [0, 0, 4 * near], b.texture(_bars_texture(rng)))
        else:
            b.quad([-30, near, -20], [60, 0, 0], [0, 0, 40], b.texture(str(rng.choice(["wood", "rock", "mat"]))),
                   texels_per_metre=80.0 / near)
        return b.build(), _pose([0, 1, 0], [0, 0, 0]), v, omega * rng.uniform(0, 1) * deg
    half = (rng.uniform(2.5, 4.5), rng.uniform(3.0, 5.0), rng.uniform(1.5, 2.5))
    _room(b, rng, half, ("wood", "rock", "mat", "plaster", "poster"))
    for _ in range(int(rng.integers(2, 5))):
        b.box([rng.uniform(-half[0] + 1, half[0] - 1), rng.uniform(-half[1] + 2.5, half[1] - 1), -half[2] + 0.5],
              [rng.uniform(0.4, 1.2), rng.uniform(0.4, 1.2), rng.uniform(0.6, 1.6)], rng.uniform(0, math.pi),
              b.texture(str(rng.choice(["poster", "wood", "car"]))))
    if case == "half_texture":   # a blank wall across the right half of the view, 1 m ahead
        b.quad([0.0, -half[1] + 1.8, -half[2]], [half[0], 0, 0], [0, 0, 2 * half[2]], b.texture(Texture(
            np.full((64, 64), 110.0, np.float32), name="blank")))
    position = [rng.uniform(-0.5, 0.5), -half[1] + 0.8, rng.uniform(-0.3, 0.3)]
    if case == "pure_rotation":
        v = np.zeros(3)
        omega = _unit(rng)
    elif case in ("forward", "forward_rotation"):
        v = np.array([rng.uniform(-0.15, 0.15), rng.uniform(-0.15, 0.15), 1.0])
        v /= np.linalg.norm(v)
        omega = _unit(rng) * rng.uniform(0.1, 0.3) if case == "forward_rotation" else np.zeros(3)
    return b.build(), _pose([rng.uniform(-0.3, 0.3), 1, rng.uniform(-0.1, 0.1)], position), v, omega


def _scale(case: str) -> float:
    return {"near": 0.05, "near_metric": 0.05, "far": 200.0, "far_metric": 200.0}.get(case, 1.0)


def _scaled(world, factor: float):
    """The world with every point scaled by ``factor`` about the origin (textures unchanged)."""
    from dataclasses import replace
    return replace(world, origins=world.origins * factor, edges_u=world.edges_u * factor,
                   edges_v=world.edges_v * factor)


def _max_px(renderer: PlanarRenderer, T_w_c0: np.ndarray, twist: np.ndarray, duration_s: float) -> float:
    """The largest image motion [px] of a point of the first view over ``duration_s`` (90th percentile)."""
    cam = renderer.camera
    _, depth = renderer.render(T_w_c0)
    ys, xs = np.mgrid[0:cam.height:4, 0:cam.width:4]
    d = depth[ys, xs].ravel()
    keep = np.isfinite(d)
    rays = np.column_stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])[keep] @ np.linalg.inv(cam.K).T
    points = rays * d[keep, None]
    T = np.linalg.inv(se3_exp(twist * duration_s))
    moved = points @ T[:3, :3].T + T[:3, 3]
    front = moved[:, 2] > 1e-6
    px = moved[front] @ cam.K.T
    px = px[:, :2] / px[:, 2:]
    start = np.column_stack([xs.ravel(), ys.ravel()])[keep][front]
    return float(np.percentile(np.linalg.norm(px - start, axis=1), 90)) if len(px) else 0.0


def target_px(case: str, rng: np.random.Generator, width: int) -> float:
    """The case's image motion over one window [px] (90th percentile of the points)."""
    if case == "slow":
        return rng.uniform(0.5, 2.0)
    if case == "fast":
        return rng.uniform(50.0, 80.0)
    return rng.uniform(8.0, 20.0) * width / 160


def size_of(case: str) -> tuple[int, int]:
    return {"vga": (640, 480), "hd": (1280, 720)}.get(case, (160, 120))


def make_case(case: str, seed: int) -> Case:
    """Simulate case ``case`` for ``seed``: ``SEQUENCE_WINDOWS`` windows of ``WINDOW_S`` (one for vga, hd)."""
    base = case if case in ("pure_rotation", "forward", "forward_rotation", "plane", "few_edges",
                            "half_texture") else "general"    # the others: the general window, changed
    rng = np.random.default_rng([seed, CASES.index(base), 77])
    width, height = size_of(case)
    world, T_w_c0, v, omega = _world(base, rng)
    factor = _scale(case)
    world = _scaled(world, factor)
    T_w_c0 = T_w_c0.copy()
    T_w_c0[:3, 3] *= factor
    camera = Camera.from_intrinsics(0.7 * width, 0.7 * width, (width - 1) / 2, (height - 1) / 2, width, height)
    renderer = PlanarRenderer(world, camera, near=0.01 * factor, texture_size=256)
    twist = np.r_[v * factor, omega]
    twist = twist * target_px(case, rng, width) / max(_max_px(renderer, T_w_c0, twist, WINDOW_S), 1e-9)
    windows = 1 if case in ("vga", "hd") else SEQUENCE_WINDOWS
    duration = WINDOW_S * windows
    px = _max_px(renderer, T_w_c0, twist, duration)
    step_px = 0.25 if width <= 160 else 1.0
    frames = int(np.clip(np.ceil(px / step_px), 20 * windows, 400 * windows))
    simulator = EventSimulator(cp=0.2, cn=0.2, threshold_sigma=0.03, seed=seed)
    chunks = [simulator.step(renderer.render(T_w_c0 @ se3_exp(twist * t))[0], int(round(t * 1e6)))
              for t in np.linspace(0.0, duration, frames + 1)]
    events = concatenate(chunks[1:])
    if case == "one_polarity":
        events = events[events.p == 1]
    if case == "noise":
        noise_rng = np.random.default_rng([seed, 991])
        events = _with_noise(events, noise_rng, noise_rng.uniform(1.0, 5.0), hot=20)
    return Case(events, camera.K.copy(), twist, renderer, T_w_c0, windows)


def _with_noise(events: Events, rng: np.random.Generator, rate_hz: float, hot: int) -> Events:
    """``events`` with uniform background activity of ``rate_hz`` per pixel and ``hot`` pixels at 200-1000 Hz."""
    W, H = events.width, events.height
    t0, t1 = int(events.t[0]), int(events.t[-1])
    n = rng.poisson(rate_hz * W * H * (t1 - t0) * 1e-6)
    x, y, t = rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(t0, t1 + 1, n)
    hx, hy = rng.integers(0, W, hot), rng.integers(0, H, hot)
    counts = rng.poisson(rng.uniform(200, 1000, hot) * (t1 - t0) * 1e-6)
    x = np.concatenate([events.x, x, np.repeat(hx, counts)])
    y = np.concatenate([events.y, y, np.repeat(hy, counts)])
    t = np.concatenate([events.t, t, rng.integers(t0, t1 + 1, counts.sum())])
    p = np.concatenate([events.p, rng.integers(0, 2, len(x) - len(events))])
    return Events(x, y, t, p, W, H, sort=True)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two vectors (3,) [deg] (NaN when either is zero)."""
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return math.nan
    return float(np.degrees(np.arccos(np.clip(a @ b / (na * nb), -1, 1))))


def score(result, case: Case, metric: bool) -> dict:
    """Errors of one fit against the truth: direction [deg], rotation (relative and px over the window), depth
    abs_rel on the fit's mask (the depth times the true speed when the scale is unknown)."""
    v, omega = case.twist[:3], case.twist[3:]
    speed = float(np.linalg.norm(v))
    duration = (result.t1_us - result.t0_us) * 1e-6
    d_omega = float(np.linalg.norm(result.omega - omega))
    rot_px = d_omega * duration * case.K[0, 0]
    rate = float(np.linalg.norm(omega))
    rot_rel = d_omega / rate if rate > 0 else math.nan
    abs_rel = math.nan
    if speed > 0 and result.depth is not None:
        gt = case.depth_at(result.t_ref_us)
        pred = result.depth * (1.0 if metric else speed)
        keep = result.mask & np.isfinite(gt) & np.isfinite(pred) & (pred > 0)
        if keep.any():
            abs_rel = float(np.mean(np.abs(pred[keep] - gt[keep]) / gt[keep]))
    direction = angle_deg(result.v, v)
    wrong = (speed == 0 or direction > BAD_DEG or abs_rel > BAD_ABS_REL
             or (rot_px > 1.0 and not rot_rel <= BAD_ROTATION))
    return {"direction_deg": direction, "rot_rel": rot_rel, "rot_px": rot_px, "abs_rel": abs_rel,
            "confident_wrong": bool(wrong and result.verdict is Verdict.OK), "wrong": bool(wrong)}


def bound_share(result, events: Events, K: np.ndarray) -> float:
    """The larger share of the events' fitted depth on an end of the default ``depth_range``
    (:func:`cmax.fitting.pipeline.depth_on_bounds`, what ``QualitySettings.max_bound_share`` judges); NaN
    without a depth grid."""
    if result.inverse_depth_grid is None:
        return math.nan
    settings = FitSettings()
    w = Window.from_events(events, K, settings, result.inverse_depth_grid.shape)
    near, far = settings.depth_range
    shares = depth_on_bounds(result.inverse_depth_grid.reshape(-1), w.index, w.weight, (1.0 / far, 1.0 / near),
                             settings.depth_candidates)
    return max(shares.values())


def run_case(case_name: str, seed: int, *, sequence: bool = True) -> dict:
    """Simulate and fit one case; the middle window by ``fit`` and all windows by ``fit_sequence``."""
    start = time.perf_counter()
    case = make_case(case_name, seed)
    sim_s = time.perf_counter() - start
    metric = case_name.endswith("_metric")
    speed = float(np.linalg.norm(case.twist[:3])) if metric else None
    t0 = int(case.events.t[0])
    w_us = int(WINDOW_S * 1e6)
    k = case.windows // 2
    window = case.events.slice_time(t0 + k * w_us, t0 + (k + 1) * w_us)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        start = time.perf_counter()
        r = fit(window, case.K, speed=speed)
        seconds = time.perf_counter() - start
    row = {"case": case_name, "seed": seed, "events": len(window), "sim_s": sim_s, "seconds": seconds,
           "verdict": r.verdict, "reason": r.quality.reason, "parallax_px": r.parallax_px,
           "warnings": sorted({type(w.message).__name__ for w in caught}),
           "speed": float(np.linalg.norm(case.twist[:3])), "omega_deg": float(np.degrees(np.linalg.norm(case.twist[3:]))),
           "image_px": _max_px(case.renderer, case.T_w_c0, case.twist, WINDOW_S),
           "median_depth": float(np.nanmedian(case.depth_at(r.t_ref_us))),
           "on_bound": bound_share(r, window, case.K), "v": r.v, "omega": r.omega, "truth": case.twist,
           **score(r, case, metric)}
    row["verdict_before"] = row["verdict"]
    if r.quality.turned:          # the same fit (the rule changes the verdict only) judged by the rule before
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            row["verdict_before"] = fit(window, case.K, speed=speed, quality=BEFORE).verdict
    row["confident_wrong_before"] = row["wrong"] and row["verdict_before"] is Verdict.OK
    if sequence and case.windows > 1:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            start = time.perf_counter()
            seq = fit_sequence(case.events, case.K, window_us=w_us, speed=speed)
            row["sequence_seconds"] = time.perf_counter() - start
            before = seq
            if any(res.quality is not None and res.quality.turned for res in seq.results):
                before = fit_sequence(case.events, case.K, window_us=w_us, speed=speed, quality=BEFORE)
        scores = [score(res, case, metric) for res in seq.results]
        row["sequence"] = [(res.verdict.value, s) for res, s in zip(seq.results, scores)]
        row["sequence_before"] = [res.verdict.value for res in before.results]
        row["sequence_confident_wrong"] = sum(s["confident_wrong"] for s in scores)
        row["sequence_confident_wrong_before"] = sum(s["wrong"] and res.verdict is Verdict.OK
                                                     for res, s in zip(before.results, scores))
    return row


def _f(x: float, fmt: str = ".1f") -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


def table(rows: list[dict]) -> list[str]:
    wrong = [r for r in rows if r["confident_wrong"]]
    wrong_before = [r for r in rows if r["confident_wrong_before"]]
    seq_wrong = sum(r.get("sequence_confident_wrong", 0) for r in rows)
    seq_wrong_before = sum(r.get("sequence_confident_wrong_before", 0) for r in rows)
    seq_total = sum(len(r.get("sequence", [])) for r in rows)
    changed = [r for r in rows if r["verdict"] is not r["verdict_before"]]
    seq_changed = sum(a != b for r in rows for (a, _), b in zip(r.get("sequence", []), r.get("sequence_before", [])))
    lines = [f"Confident wrong answers (`ok` and wrong): {len(wrong)} of {len(rows)} fits "
             f"({len(wrong_before)} without the bas-relief turn test before); `fit_sequence` {seq_wrong} of "
             f"{seq_total} windows ({seq_wrong_before} before). Verdicts changed by the test: {len(changed)} "
             f"fits, {seq_changed} `fit_sequence` windows.", "",
             "| case | seed | events | truth: speed / rotation [deg/s] / image motion [px] / median depth | "
             "direction error [deg] | rotation error (rel / px) | depth abs_rel | parallax [px] | depth on a bound [%] | "
             "verdict (before -> after) | "
             "warnings | seconds | fit_sequence verdicts (wrong marked !) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        seq = " ".join((b + "->" if b != v else "") + v + ("!" if s["wrong"] else "")
                       for (v, s), b in zip(r.get("sequence", []), r.get("sequence_before", []))) or "-"
        mark = " **confident wrong**" if r["confident_wrong"] else " (confident wrong before)" if \
            r["confident_wrong_before"] else ""
        verdict = (f"{r['verdict_before'].value} -> " if r["verdict_before"] is not r["verdict"] else "") + \
            r["verdict"].value
        lines.append(
            f"| {r['case']} | {r['seed']} | {r['events']} | {r['speed']:.3g} / {r['omega_deg']:.1f} / "
            f"{r['image_px']:.1f} / {r['median_depth']:.3g} | {_f(r['direction_deg'])} | {_f(r['rot_rel'], '.2f')} / "
            f"{_f(r['rot_px'])} | {_f(r['abs_rel'], '.2f')} | {_f(r['parallax_px'], '.2f')} | "
            f"{100 * r['on_bound']:.0f} | {verdict}{mark} | {', '.join(r['warnings']) or '-'} | {r['seconds']:.1f} | {seq} |")
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="500-505", help="held-out seeds, first-last (default 500-505)")
    parser.add_argument("--cases", default=",".join(CASES), help="comma-separated cases (default: all)")
    parser.add_argument("--no-sequence", action="store_true", help="skip fit_sequence (default: run it)")
    parser.add_argument("--output", default="benchmarks/results/unseen_scenes.md")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    first, last = (int(s) for s in args.seeds.split("-"))
    cases = [c for c in args.cases.split(",") if c]
    unknown = sorted(set(cases) - set(CASES))
    if unknown:
        parser.error(f"--cases: unknown {unknown}; expected some of {', '.join(CASES)}")
    start = time.perf_counter()
    rows = []
    for name in cases:
        for seed in range(first, last + 1):
            row = run_case(name, seed, sequence=not args.no_sequence)
            rows.append(row)
            print(f"{name} {seed} ev={row['events']} dir={_f(row['direction_deg'])} rot={_f(row['rot_rel'], '.2f')} "
                  f"absrel={_f(row['abs_rel'], '.2f')} bound={100 * row['on_bound']:.0f}% par={_f(row['parallax_px'], '.2f')} "
                  f"{row['verdict_before'].value}->{row['verdict'].value}"
                  f"{' CONFIDENT-WRONG' if row['confident_wrong'] else ''} {row['warnings']} {row['seconds']:.1f}s "
                  f"seq={[v for v, _ in row.get('sequence', [])]} | {row['reason'][:160]}", flush=True)
    head = ["# cmax.fit on scenes it was never tuned on", "",
            f"Seeds {first}-{last}, cases {', '.join(cases)} (`benchmarks/unseen_scenes.py` says what each is). "
            f"`cmax.fit(events, K)` with the defaults on the middle {WINDOW_S * 1e3:.0f} ms window (`*_metric`: "
            f"`speed=|v|`); `fit_sequence` on {SEQUENCE_WINDOWS} such windows. Confident wrong: `ok` with a direction "
            f"over {BAD_DEG:g} deg off, a depth abs_rel over {BAD_ABS_REL:g}, a rotation error over "
            f"{BAD_ROTATION:g} of the true rate (and over 1 px), or any `ok` on a pure rotation. Verdicts `before -> after`: "
            f"the same fit judged with `bas_relief_turn_deg` {BEFORE.bas_relief_turn_deg:g} (the rule before) and with the "
            f"defaults (shown once when they agree). "
            f"Machine: {describe()}, torch threads 1. Written by `python -m benchmarks.unseen_scenes --seeds "
            f"{first}-{last}` in {time.perf_counter() - start:.0f} s.", ""]
    write_text_atomic(args.output, "\n".join(head + table(rows)) + "\n")


if __name__ == "__main__":
    main()
