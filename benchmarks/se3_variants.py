"""``cmax.fit`` se3 under variants of its settings on the held-out windows, written to
``benchmarks/results/se3_variants.md``: what a setting buys or costs in accuracy and time.

Windows: ``indoor_flying`` (346x260, seeds 100-119 held out, as ``benchmarks.accuracy_cmax``), fitted with
``speed=|v|`` and the preset's depth range. A variant is a list of ``field=value`` of
:class:`cmax.fitting.FitSettings`, nested fields dotted at any depth (``refine.iterations=150``,
``patch_flow.tolerances.ftol=1e-6``); the default settings run too. The variants run interleaved window
by window (the same load on each), one torch thread.

A single fit per window is not enough to tell two variants apart: the se3 figures move with the fit's seed
(``FitSettings.seed``, its dither) by more than most settings do (``benchmarks/results/accuracy_noise.md``).
``--fit-seeds 0-4`` fits every window at each of those seeds with every variant; the figures are then
pooled over all fits, and each variant is compared with the default fit by fit (same window and seed).

    python -m benchmarks.se3_variants "refine.iterations=150" \\
        "patch_flow.max_events=10000,refine.max_events=10000" [--seeds 100-119] [--fit-seeds 0-4] [--cache DIR]
"""
from __future__ import annotations

import argparse
import ast
import os
import sys
import time
import warnings
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import torch

from benchmarks.accuracy_cmax import RESULTS, _room, abs_rel, parse_seeds, windows
from benchmarks.machine import describe
from cmax.fitting import FitSettings, fit
from cmax.io.atomic import write_text_atomic

FIGURES = ("abs_rel", "direction_deg", "omega_rms_deg_s", "seconds")


def parse_variant(text: str) -> dict[str, object]:
    """``"a.b=1,c=2.5"`` -> ``{"a.b": 1, "c": 2.5}`` (values as Python literals); ValueError otherwise."""
    out = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        name, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"a variant is field=value[,field=value...], got {item!r}")
        try:
            out[name.strip()] = ast.literal_eval(value.strip())
        except (ValueError, SyntaxError):
            raise ValueError(f"{name.strip()}: {value.strip()!r} is not a Python literal") from None
    return out


def settings_of(variant: dict[str, object], base: FitSettings) -> FitSettings:
    """``base`` with the dotted fields of ``variant`` replaced, at any depth (``refine.tolerances.ftol``);
    each level validated by its dataclass."""
    settings = base
    for name, value in variant.items():
        settings = _replaced(settings, name.split("."), value, "FitSettings")
    return settings


def _replaced(obj, path: list[str], value: object, where: str):
    """``obj`` (a dataclass) with the field at ``path`` set to ``value``, every level rebuilt by ``replace``."""
    head = path[0].strip()
    if head not in {f.name for f in fields(obj)}:
        raise ValueError(f"{where} has no field {head!r}")
    if len(path) > 1:
        value = _replaced(getattr(obj, head), path[1:], value, f"{where}.{head}")
    return replace(obj, **{head: value})


def run(window, settings: FitSettings) -> dict:
    v, omega = window.twist[:3], window.twist[3:]
    speed = float(np.linalg.norm(v))
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = fit(window.events, window.K, speed=speed, settings=settings)
    seconds = time.perf_counter() - start
    cos = float(r.v @ v / (np.linalg.norm(r.v) * speed))
    return {"abs_rel": abs_rel(r, window.depth, settings.depth_range),
            "direction_deg": float(np.degrees(np.arccos(np.clip(cos, -1, 1)))),
            "omega_rms_deg_s": float(np.degrees(np.sqrt(np.mean((r.omega - omega) ** 2)))), "seconds": seconds,
            "verdict": r.quality.verdict.value if r.quality is not None else "none"}


def paired(rows: dict[str, list[dict]], figure: str) -> dict[str, str]:
    """Per variant, ``"lower in n of N"``: the fits (same window and fit seed) where its ``figure`` is below the
    default's."""
    base = [r[figure] for r in rows["default"]]
    return {name: f"{sum(r[figure] < b for r, b in zip(results, base, strict=True))} of {len(base)}"
            for name, results in rows.items() if name != "default"}


def report(rows: dict[str, list[dict]], seeds: list[int], seconds: float, fit_seeds: list[int] = (0,),
           command: str = "python -m benchmarks.se3_variants") -> str:
    """The markdown report; ``rows[variant]`` holds one result per window and fit seed (windows outer)."""
    lines = ["# cmax.fit se3 under settings variants", "",
             f"`indoor_flying` seeds {seeds[0]}-{seeds[-1]} (held out), 346x260, `speed=|v|`, depth range 1-6.5 m; "
             f"fit seeds {', '.join(map(str, fit_seeds))} ({len(seeds) * len(fit_seeds)} fits per variant); "
             "the variants interleaved window by window. Machine: "
             f"{describe()}, torch threads 1; load average "
             f"(1 min) at the end {os.getloadavg()[0]:.2f}. Written by `{command}` in "
             f"{seconds:.0f} s. Medians / p90 over all fits, then over the fits each variant called `ok`.", "",
             "| variant | " + " | ".join(FIGURES) + " | ok windows | "
             + " | ".join(f"{f} (ok)" for f in FIGURES) + " |",
             "|---|" + "---|" * (2 * len(FIGURES) + 1)]
    for name, results in rows.items():
        ok = [r for r in results if r["verdict"] == "ok"]

        def cells(subset):
            if not subset:
                return ["-"] * len(FIGURES)
            return [f"{np.median([r[f] for r in subset]):.3f} / {np.percentile([r[f] for r in subset], 90):.3f}"
                    for f in FIGURES]
        lines.append(f"| {name} | " + " | ".join(cells(results)) + f" | {len(ok)} of {len(results)} | "
                     + " | ".join(cells(ok)) + " |")
    if len(rows) > 1:
        lines += ["", "Fit by fit against the default (same window and fit seed): the fits where the variant is lower "
                  "(better).", "", "| variant | " + " | ".join(FIGURES[:3]) + " |", "|---|" + "---|" * 3]
        lower = {f: paired(rows, f) for f in FIGURES[:3]}
        for name in rows:
            if name != "default":
                lines.append(f"| {name} | " + " | ".join(lower[f][name] for f in FIGURES[:3]) + " |")
    labels = [f"{s}" if len(fit_seeds) == 1 else f"{s}/{k}" for s in seeds for k in fit_seeds]
    lines += ["", "Per fit (window" + ("" if len(fit_seeds) == 1 else "/fit seed")
              + ": abs_rel, direction [deg], verdict):", ""]
    for name, results in rows.items():
        lines.append(f"- {name}: " + "; ".join(f"{label} {r['abs_rel']:.3f} {r['direction_deg']:.1f} {r['verdict']}"
                                              for label, r in zip(labels, results)))
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("variants", nargs="+", help='field=value[,field=value...], e.g. "refine.iterations=150"')
    parser.add_argument("--seeds", default="100-119")
    parser.add_argument("--fit-seeds", default="0-0", help="FitSettings.seed values, first-last (default 0-0)")
    parser.add_argument("--cache", type=Path, default=None, help="folder to keep simulated windows between runs")
    parser.add_argument("--output", type=Path, default=RESULTS / "se3_variants.md")
    args = parser.parse_args(argv)
    seeds = parse_seeds(parser, args.seeds)
    fit_seeds = parse_seeds(parser, args.fit_seeds)
    base = FitSettings(**_room())
    try:
        variants = {"default": base, **{text: settings_of(parse_variant(text), base) for text in args.variants}}
    except (ValueError, TypeError) as error:
        parser.error(str(error))
    torch.set_num_threads(1)
    start = time.perf_counter()
    rows: dict[str, list[dict]] = {name: [] for name in variants}
    first = windows("se3", seeds[0], args.cache)
    for settings in variants.values():
        run(first, settings)   # warm-up (compilation, torch's first calls), not counted
    for seed in seeds:
        window = windows("se3", seed, args.cache)
        for fit_seed in fit_seeds:
            for name, settings in variants.items():
                rows[name].append(run(window, replace(settings, seed=fit_seed)))
                r = rows[name][-1]
                print(seed, fit_seed, name, f"{r['abs_rel']:.3f} {r['direction_deg']:.1f} {r['seconds']:.2f} "
                      f"{r['verdict']}", flush=True)
    arguments = " ".join(f'"{a}"' if "," in a or " " in a else a for a in (sys.argv[1:] if argv is None else argv))
    text = report(rows, seeds, time.perf_counter() - start, fit_seeds, f"python -m benchmarks.se3_variants {arguments}")
    write_text_atomic(args.output, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
