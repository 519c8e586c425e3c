"""How unevenly steady windows fill their time: the evidence behind ``QualitySettings.max_rate_change``.

``cmax.fitting.quality.rate_change`` (the events of a window's busier half over those of its other half) flags a
se3 window as ``unsteady`` over ``max_rate_change``: its camera started or stopped inside it. This script measures
the ratio over windows whose camera moves steadily, where the test must stay silent, and over the ECD slider's
windows, whose last one holds the stage's stop:

* the 20 held-out ``indoor_flying`` windows of :mod:`benchmarks.accuracy_cmax` (346x260, seeds 100-119);
* ``make_window`` windows of four presets of :mod:`benchmarks.synthetic_windows` (160x120, seeds 100-109);
* the real recordings of ``../shared/data``: the DAVIS346 pegboard's windows of :mod:`benchmarks.real_cmax`, the
  Prophesee Gen4 drive (one 8.8 ms window), and with ``--slider-events`` the ECD slider's 20 default windows.

Writes ``benchmarks/results/rate_change.md``.

Usage::

    python -m benchmarks.rate_change [--data ../shared/data] [--slider-events slider.h5]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from cmax.fitting import QualitySettings
from cmax.fitting.quality import rate_change
from cmax.io.atomic import write_text_atomic

RESULTS = Path(__file__).resolve().parent / "results"
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
PRESETS = ("indoor_flying", "driving", "slider", "rotation")


def summary_row(name: str, rates: list[float], threshold: float) -> str:
    """One markdown row: the set, its windows, median / p99 / largest ratio and how many exceed ``threshold``."""
    values = np.asarray(rates, float)
    return (f"| {name} | {values.size} | {np.median(values):.2f} | {np.percentile(values, 99):.2f} | "
            f"{values.max():.2f} | {int(np.sum(values > threshold))} |")


def synthetic_rates() -> dict[str, list[float]]:
    """The ratio of every synthetic window (held-out ``accuracy_cmax`` windows, then each preset's)."""
    from benchmarks import accuracy_cmax
    from benchmarks.synthetic_windows import make_window

    out = {"accuracy_cmax se3 windows (indoor_flying, 346x260, seeds 100-119)":
           [rate_change(accuracy_cmax.windows("se3", seed, None).events.t) for seed in range(100, 120)]}
    for preset in PRESETS:
        out[f"{preset} (160x120, seeds 100-109)"] = [
            rate_change(make_window(preset, seed, width=160, height=120).events.t) for seed in range(100, 110)]
    return out


def real_rates(data: Path, slider_events: Path | None) -> dict[str, list[float]]:
    """The ratio of the real recordings' windows (as :mod:`benchmarks.real_cmax` cuts them)."""
    from benchmarks.real_cmax import PEGBOARD_WINDOWS_MS
    from cmax.events import window_starts
    from cmax.io import read

    pegboard = read(data / "davis346_pegboard" / "davis.aedat4")
    first = int(pegboard.t[0])
    out = {"DAVIS346 pegboard (the 7 windows of real_cmax)": [
        rate_change(pegboard.slice_time(first + a * 1000, first + b * 1000).t) for a, b in PEGBOARD_WINDOWS_MS],
        "Prophesee Gen4 drive (8.8 ms)": [rate_change(read(data / "prophesee_gen4_driving" / "evt3_sample.raw").t)]}
    if slider_events is not None:
        slider = read(slider_events)
        window = 166_500
        starts = window_starts(int(slider.t[0]), int(slider.t[-1]), window, window)
        out["ECD slider, default windows (the last: the stage stops)"] = [
            rate_change(slider.slice_time(int(t0), int(t0) + window).t) for t0 in starts]
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=DATA, help="the shared data folder")
    parser.add_argument("--slider-events", type=Path, default=None,
                        help="events simulated from ../shared/data/ecd_slider_depth (cmax simulate ... -o slider.h5)")
    args = parser.parse_args(argv)
    if not args.data.is_dir():
        parser.error(f"--data: no folder {args.data}")
    threshold = QualitySettings().max_rate_change
    sets = {**synthetic_rates(), **real_rates(args.data, args.slider_events)}
    lines = ["# Event-rate change inside a window (`cmax.fitting.quality.rate_change`)", "",
             "Written by `python -m benchmarks.rate_change`: the events of each window's busier half over those of "
             f"its other half; over `QualitySettings.max_rate_change` = {threshold:g} a se3 fit is `unsteady` "
             "(ambiguous; `fit_sequence` gives it its neighbours' motion).", "",
             "| windows | count | median | p99 | largest | over the threshold |", "|---|---|---|---|---|---|"]
    lines += [summary_row(name, rates, threshold) for name, rates in sets.items()]
    if args.slider_events is not None:
        slider = sets["ECD slider, default windows (the last: the stage stops)"]
        lines += ["", "ECD slider per window: " + ", ".join(f"{r:.2f}" for r in slider) + "."]
    text = "\n".join(lines) + "\n"
    RESULTS.mkdir(exist_ok=True)
    write_text_atomic(RESULTS / "rate_change.md", text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
