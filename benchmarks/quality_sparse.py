"""The quality verdict of ``cmax.fit`` on sparse windows, written to ``benchmarks/results/quality_sparse.md``.

A window fitted on few events per pixel has an image of warped events in which nearly every event lies alone
in its pixel; the ambiguity test (:func:`cmax.fitting.quality.assess`) then passes wrong directions as ``ok``.
This benchmark draws ``N`` events from held-out ``indoor_flying`` windows (346x260, seeds 100-107, the
library's default settings, ``speed=|v|``, with the default depth range and with the room's) at several
``N``, fits each draw with the sparse rule off (``QualitySettings(min_event_density=0)``) and on (the
default), and counts the ``ok`` verdicts and the ``ok`` ones whose direction is more than ``BAD_DEG`` from the
truth.

    python -m benchmarks.quality_sparse [--seeds 100-107] [--counts 3000,6000,10000,20000,40000] [--draws 2]
"""
from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from benchmarks.accuracy_cmax import parse_seeds
from benchmarks.machine import describe
from benchmarks.quality_cmax import BAD_DEG, angle_deg
from benchmarks.synthetic_windows import make_window
from cmax.fitting import QualitySettings, Verdict, fit
from cmax.io.atomic import write_text_atomic


def draws(seeds: list[int], counts: list[int], n_draws: int, depth_range: tuple[float, float] | None) -> list[dict]:
    """One row per (seed, count, draw): the direction error [deg] and the verdicts without and with the rule;
    ``depth_range`` [m] given to the fit (None: the library's default)."""
    rows = []
    for seed in seeds:
        window = make_window("indoor_flying", seed)
        speed = float(np.linalg.norm(window.twist[:3]))
        rng = np.random.default_rng(seed)
        for count in counts:
            for draw in range(n_draws):
                events = window.events[np.sort(rng.choice(len(window.events), min(count, len(window.events)),
                                                          replace=False))]
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    given = {} if depth_range is None else {"depth_range": depth_range}
                    off = fit(events, window.K, speed=speed, quality=QualitySettings(min_event_density=0.0), **given)
                    on = fit(events, window.K, speed=speed, **given)
                rows.append({"seed": seed, "count": len(events), "draw": draw,
                             "density": len(events) / (events.width * events.height),
                             "error_deg": angle_deg(off.v, window.twist[:3]), "same_motion": bool(
                                 np.array_equal(off.v, on.v) and np.array_equal(off.omega, on.omega)),
                             "off": off.verdict, "on": on.verdict, "sparse": bool(on.quality.sparse)})
    return rows


def table(rows: list[dict]) -> list[str]:
    """Per event count: draws, ok verdicts and bad ok verdicts without and with the rule."""
    lines = ["| events | per pixel | draws | median direction error [deg] | ok without the rule (bad: > "
             f"{BAD_DEG:g} deg) | ok with it (bad) | flagged sparse | same motion |",
             "|---|---|---|---|---|---|---|---|"]
    for count in sorted({row["count"] for row in rows}):
        group = [row for row in rows if row["count"] == count]
        counts = []
        for key in ("off", "on"):
            ok = [row for row in group if row[key] is Verdict.OK]
            bad = [row for row in ok if row["error_deg"] > BAD_DEG]
            errors = ", ".join(f"{row['error_deg']:.0f}" for row in ok)
            counts.append(f"{len(ok)} ({len(bad)} bad{': ' + errors + ' deg' if ok else ''})")
        lines.append(f"| {count:,} | {group[0]['density']:.3f} | {len(group)} | "
                     f"{np.median([row['error_deg'] for row in group]):.1f} | {counts[0]} | {counts[1]} | "
                     f"{sum(row['sparse'] for row in group)} | {sum(row['same_motion'] for row in group)} of "
                     f"{len(group)} |")
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="100-107")
    parser.add_argument("--counts", default="3000,6000,10000,20000,40000")
    parser.add_argument("--draws", type=int, default=2)
    parser.add_argument("--output", type=Path, default=Path(__file__).parent / "results" / "quality_sparse.md")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    start = time.perf_counter()
    counts = [int(c) for c in args.counts.split(",")]
    seeds = parse_seeds(parser, args.seeds)
    sections = []
    for title, depth_range in (("The library's default depth range (0.5-60 m)", None),
                               ("The room's depth range given (1-6.5 m, as `benchmarks.quality_cmax`)", (1.0, 6.5))):
        sections += [f"## {title}", "", *table(draws(seeds, counts, args.draws, depth_range)), ""]
    lines = ["# cmax.fit verdicts on sparse windows", "",
             f"`indoor_flying` seeds {args.seeds}, 346x260, {args.draws} random draws of each event count per seed, "
             "fitted with the library's defaults and `speed=|v|`, with the sparse rule off "
             "(`QualitySettings(min_event_density=0)`) and on (the default, "
             f"{QualitySettings().min_event_density:g} events per pixel). Machine: {describe()}, torch threads 1. "
             f"Written by `python -m benchmarks.quality_sparse` in {time.perf_counter() - start:.0f} s.", "",
             *sections]
    write_text_atomic(args.output, "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
