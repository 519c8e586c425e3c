"""How ``cmax.fit`` (se3) holds up under a sensor's background-activity noise, with its noise filter and without.

Held-out synthetic windows (presets at ``--size``, default 160x120; seeds 100-107) get uniform background
activity added: ``rate`` events per pixel and second (Poisson count, uniform pixels, times and polarities,
seeded per window), the noise a DAVIS or Prophesee sensor makes in the dark (0.1-5 Hz per pixel). Each window
and rate is fitted twice in this process, interleaved: with the default settings (the noise filter,
``FitSettings.min_neighbours`` gated by ``denoise_min_rate_hz``, ``denoise_min_window_us`` and
``max_denoised_share``) and with ``min_neighbours=0`` (every event fitted: the fit before the filter), each with
the pose given (depth only: abs_rel against the ground truth, the preset's depth range) and with the
gyroscope's rotation held and the speed given (direction error, verdict).

Reported per preset and rate: the medians of abs_rel (pose given) and of the direction error (rotation held),
the windows whose verdict is ``ok`` with the direction more than ``BAD_DEG`` off (a confident wrong answer),
the noise share the fit estimates (``Quality.noise_share``) against the share added, and how many windows the
filter applied to (``FitResult.events_used`` below the events given).

    python -m benchmarks.background_noise [--seeds 100-107] [--presets indoor_flying,driving_day,slider]
                                          [--rates 0,0.3,1,3] [--size 160x120] [--cache DIR] [--output FILE]

Written to ``benchmarks/results/background_noise.md``.
"""
from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from benchmarks.accuracy_cmax import RESULTS, abs_rel, cached, parse_seeds, preset_depth_range
from benchmarks.machine import describe
from benchmarks.synthetic_windows import preset_window
from cmax import Events
from cmax._args import sensor_size
from cmax.fitting import fit
from cmax.io.atomic import write_text_atomic

#: A direction error [deg] beyond which an ``ok`` verdict is a confident wrong answer.
BAD_DEG = 30.0


def with_noise(events: Events, rate_hz: float, seed: int) -> tuple[Events, int]:
    """``events`` with uniform background activity of ``rate_hz`` events per pixel and second over their span
    (Poisson count; uniform pixels, times and polarities; ``seed``), and the number of noise events added."""
    rng = np.random.default_rng(seed)
    t0, t1 = int(events.t[0]), int(events.t[-1])
    n = int(rng.poisson(rate_hz * events.width * events.height * (t1 - t0) * 1e-6)) if rate_hz else 0
    x = np.concatenate([events.x, rng.integers(0, events.width, n)])
    y = np.concatenate([events.y, rng.integers(0, events.height, n)])
    t = np.concatenate([events.t, rng.integers(t0, t1 + 1, n)])
    p = np.concatenate([events.p, rng.integers(0, 2, n)])
    order = np.argsort(t, kind="stable")
    return Events(x[order], y[order], t[order], p[order], events.width, events.height), n


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle [deg] between two 3-vectors."""
    cosine = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))


def fit_window(window, events: Events, depth_range: tuple[float, float], **settings) -> dict:
    """One window's figures with ``settings`` (FitSettings fields): pose given and rotation held."""
    v = window.twist[:3]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        posed = fit(events, window.K, pose=window.T01, depth_range=depth_range, **settings)
        held = fit(events, window.K, speed=float(np.linalg.norm(v)), omega=window.twist[3:],
                   depth_range=depth_range, **settings)
    direction = angle_deg(held.v, v)
    return {"abs_rel": abs_rel(posed, window.depth, depth_range), "direction": direction,
            "ok_wrong": held.quality.verdict.value == "ok" and direction > BAD_DEG,
            "estimated": held.quality.noise_share, "filtered": held.events_used < len(events)}


def summarise(rows: list[dict], args, seconds: float) -> str:
    """The markdown report of the ``rows`` (one per preset, seed, rate and setting)."""
    lines = [
        "# se3 fits under background-activity noise, with the noise filter and without",
        "",
        f"`python -m benchmarks.background_noise --seeds {args.seeds} --presets {args.presets} --rates {args.rates} "
        f"--size {args.size}`: {describe()}; {seconds:.0f} s. Uniform background activity added to held-out "
        "windows; each window fitted with the default settings (`filter`) and with `min_neighbours=0` (`off`, "
        "every event fitted) in this process. abs_rel: pose given (median over the seeds); direction: the "
        f"gyroscope's rotation held and the speed given (median, deg); ok > {BAD_DEG:g} deg: windows whose verdict "
        "is `ok` with the direction that far off; share: the noise added / the share the fit estimates (medians); "
        "filtered: windows the filter applied to.",
        "",
        "| preset | rate [Hz/px] | abs_rel off -> filter | direction off -> filter [deg] | ok > 30 deg off -> filter "
        "| share added / estimated | filtered |",
        "|---|---|---|---|---|---|---|",
    ]
    keys = sorted({(r["preset"], r["rate"]) for r in rows}, key=lambda k: (args.presets.split(",").index(k[0]), k[1]))
    for preset, rate in keys:
        off = [r for r in rows if (r["preset"], r["rate"], r["setting"]) == (preset, rate, "off")]
        on = [r for r in rows if (r["preset"], r["rate"], r["setting"]) == (preset, rate, "filter")]
        med = lambda rs, k: float(np.median([r[k] for r in rs]))          # noqa: E731
        lines.append(
            f"| {preset} | {rate:g} | {med(off, 'abs_rel'):.3f} -> {med(on, 'abs_rel'):.3f} | "
            f"{med(off, 'direction'):.1f} -> {med(on, 'direction'):.1f} | {sum(r['ok_wrong'] for r in off)} -> "
            f"{sum(r['ok_wrong'] for r in on)} | {med(on, 'added'):.2f} / {med(on, 'estimated'):.2f} | "
            f"{sum(r['filtered'] for r in on)} of {len(on)} |")
    worse = [(r_on["preset"], r_on["seed"], r_on["rate"], r_off["abs_rel"], r_on["abs_rel"])
             for r_on in rows if r_on["setting"] == "filter"
             for r_off in rows if r_off["setting"] == "off" and
             (r_off["preset"], r_off["seed"], r_off["rate"]) == (r_on["preset"], r_on["seed"], r_on["rate"])
             and r_on["abs_rel"] > r_off["abs_rel"] + 0.02]
    lines += ["", f"Windows whose pose-given abs_rel the filter made worse by more than 0.02: {len(worse)} of "
              f"{sum(r['setting'] == 'filter' for r in rows)}" + (": " + "; ".join(
                  f"{p} {s} at {r:g} Hz {a:.3f} -> {b:.3f}" for p, s, r, a, b in worse) if worse else "."), ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="100-107", help="held-out scene seeds (default 100-107)")
    parser.add_argument("--presets", default="indoor_flying,driving_day,slider", help="comma-separated presets")
    parser.add_argument("--rates", default="0,0.3,1,3", help="background activity [events per pixel and second]")
    parser.add_argument("--size", default="160x120", help="sensor size WxH [px] (default 160x120)")
    parser.add_argument("--cache", type=Path, default=None, help="folder caching the simulated windows")
    parser.add_argument("--output", type=Path, default=RESULTS / "background_noise.md", help="report file")
    args = parser.parse_args(argv)
    seeds = parse_seeds(parser, args.seeds)
    rates = [float(r) for r in args.rates.split(",")]
    width, height = sensor_size(args.size)
    torch.set_num_threads(1)
    rows, start = [], time.perf_counter()
    for preset in args.presets.split(","):
        depth_range = preset_depth_range(preset)
        for seed in seeds:
            window = cached(args.cache, f"{preset}_{seed}_{width}x{height}",
                            lambda: preset_window(preset, seed, width=width, height=height))
            for rate in rates:
                events, added = with_noise(window.events, rate, 1000 + seed)
                for setting, options in (("off", {"min_neighbours": 0}), ("filter", {})):
                    row = fit_window(window, events, depth_range, **options)
                    rows.append(dict(row, preset=preset, seed=seed, rate=rate, setting=setting,
                                     added=added / len(events)))
                print(f"{preset} {seed} {rate:g} Hz: abs_rel {rows[-2]['abs_rel']:.3f} -> {rows[-1]['abs_rel']:.3f}, "
                      f"direction {rows[-2]['direction']:.1f} -> {rows[-1]['direction']:.1f} deg", flush=True)
    write_text_atomic(args.output, summarise(rows, args, time.perf_counter() - start))
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
