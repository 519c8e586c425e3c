"""The quality verdicts of ``cmax.fit`` on held-out synthetic windows, written to
``benchmarks/results/quality_cmax.md``: how many windows are ok / ambiguous / low parallax / failed,
and whether the bad ones (direction more than ``BAD_DEG`` from the truth) are flagged (not ``ok``).

With the rotation fitted, two more columns ask why a window with a large direction error can be called ok:
the true motion scored against the fit on the fit's own patch-wise objective (the ambiguity test's
``gain`` and ``noise``, :class:`cmax.fitting.quality.MotionScorer`; a negative gain: the truth scores
better than the fit), and the refinement (:func:`cmax.fitting.motion.refine_motion_local`, the fit's
settings) started at the truth: its direction error and its gain against the fit.

Windows: ``indoor_flying`` (346x260, seeds 100-119 held out, as ``benchmarks.accuracy_cmax``), fitted
with ``speed=|v|`` and the preset's depth range, with and without the gyroscope's rotation.

    python -m benchmarks.quality_cmax [--seeds 100-119] [--cache DIR] [--size 160x120 --output FILE]

``--size`` simulates the same scenes at another sensor size (the camera's field of view unchanged).
"""
from __future__ import annotations

import argparse
import math
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from benchmarks.accuracy_cmax import _room, cached
from benchmarks.machine import describe
from benchmarks.synthetic_windows import preset_window
from cmax.fitting import FitSettings, Verdict, fit
from cmax.fitting.api import DEFAULT_CONTRAST, DEFAULT_POLARITY_SPLIT
from cmax.fitting.motion import refine_motion_local
from cmax.fitting.quality import MotionScorer
from cmax.fitting.solvers import make_solver
from cmax.fitting.window import Window
from cmax._args import sensor_size
from cmax.io.atomic import write_text_atomic

#: A window whose fitted direction is farther than this from the truth [deg] is a bad one.
BAD_DEG = 30.0


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two vectors (3,) [deg]."""
    cos = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1))))


def truth_against_fit(window, result) -> dict:
    """The true motion and the refinement started at it, scored against the fit ``result`` on the fit's own
    patch-wise objective (same settings, same events): gains, noise, the refined direction's error."""
    v, omega = window.twist[:3], window.twist[3:]
    speed = float(np.linalg.norm(v))
    settings = FitSettings(**_room(), contrast=DEFAULT_CONTRAST["se3"], polarity_split=DEFAULT_POLARITY_SPLIT["se3"])
    w = Window.from_events(window.events, window.K, settings, result.inverse_depth_grid.shape)
    scorer = MotionScorer.build(w, result.v, result.omega, speed, settings.quality)
    if scorer is None:    # too few patches hold events to score anything (a small sensor): no truth columns
        return {"truth_gain": math.nan, "truth_noise": math.nan, "from_truth_deg": math.nan,
                "from_truth_gain": math.nan}
    truth = scorer.score("truth", v, omega)
    refined = refine_motion_local(w, v, omega, speed, settings.refine, make_solver("scipy"))
    from_truth = scorer.score("from_truth", refined.v, refined.omega)
    return {"truth_gain": truth.gain, "truth_noise": truth.noise, "from_truth_deg": angle_deg(refined.v, v),
            "from_truth_gain": from_truth.gain}


def run(window, gyro: bool) -> dict:
    v = window.twist[:3]
    speed = float(np.linalg.norm(v))
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = fit(window.events, window.K, speed=speed, omega=window.twist[3:] if gyro else None, **_room())
    seconds = time.perf_counter() - start
    return {"direction_deg": angle_deg(r.v, v), "verdict": r.verdict,
            "reason": r.quality.reason, "seconds": seconds, "parallax_px": r.parallax_px,
            "quality_seconds": seconds - sum(log.seconds for log in r.stages),
            **({} if gyro else truth_against_fit(window, r))}


def table(rows: list[dict], title: str) -> list[str]:
    truth = "truth_gain" in rows[0]
    bad = [row for row in rows if row["direction_deg"] > BAD_DEG]
    flagged_bad = [row for row in bad if row["verdict"] is not Verdict.OK]
    good = [row for row in rows if row["direction_deg"] <= BAD_DEG]
    flagged_good = [row for row in good if row["verdict"] is not Verdict.OK]
    counts = ", ".join(f"{sum(row['verdict'] is v for row in rows)} {v.value}" for v in Verdict)
    lines = [f"## {title}", "", f"Verdicts: {counts}. Bad windows (direction > {BAD_DEG:g} deg): {len(bad)}, "
             f"flagged (not ok): {len(flagged_bad)}. Good windows flagged anyway: {len(flagged_good)} of {len(good)}. "
             f"Median seconds per fit {np.median([r['seconds'] for r in rows]):.2f}, of which the ambiguity test "
             f"and the result {np.median([r['quality_seconds'] for r in rows]):.2f}.", "",
             "| seed | direction error [deg] | parallax [px] | verdict | reason |" + TRUTH_HEADER * truth,
             "|---|---|---|---|---|" + "---|" * 3 * truth]
    for row in rows:
        lines.append(f"| {row['seed']} | {row['direction_deg']:.1f} | {row['parallax_px']:.1f} "
                     f"| {row['verdict'].value} | {row['reason']} |" + (truth_cells(row) if truth else ""))
    if truth:
        within = [row for row in rows if row["truth_gain"] <= row["truth_noise"]]
        better = [row for row in rows if row["from_truth_gain"] < 0]
        lines += ["", f"The true motion scores within noise of the fit on {len(within)} of {len(rows)} windows "
                  f"(better than the fit on {sum(row['truth_gain'] < 0 for row in rows)}); the refinement started "
                  f"at the truth ends better than the fit on {len(better)}, with a median direction error of "
                  f"{np.nanmedian([row['from_truth_deg'] for row in rows]):.1f} deg (the fit's: "
                  f"{np.median([row['direction_deg'] for row in rows]):.1f})."]
    return lines + [""]


TRUTH_HEADER = " truth: gain / noise | from the truth: direction [deg] | from the truth: gain |"


def truth_cells(row: dict) -> str:
    return (f" {row['truth_gain']:.3g} / {row['truth_noise']:.3g} | {row['from_truth_deg']:.1f} | "
            f"{row['from_truth_gain']:.3g} |")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="100-119")
    parser.add_argument("--cache", type=Path, default=None)
    parser.add_argument("--size", type=sensor_size, default=(346, 260), metavar="WxH",
                        help="sensor size of the simulated windows (default 346x260)")
    parser.add_argument("--output", type=Path, default=Path(__file__).parent / "results" / "quality_cmax.md")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    first, last = (int(s) for s in args.seeds.split("-"))
    seeds = list(range(first, last + 1))
    start = time.perf_counter()
    sections = []
    for gyro in (False, True):
        rows = []
        for seed in seeds:
            width, height = args.size
            key = f"indoor_flying_{seed}" + ("" if args.size == (346, 260) else f"_{width}x{height}")
            window = cached(args.cache, key, lambda s=seed: preset_window("indoor_flying", s, width=width,
                                                                        height=height))
            rows.append({"seed": seed, **run(window, gyro)})
            print(seed, gyro, f"{rows[-1]['direction_deg']:.1f}", rows[-1]["verdict"].value, flush=True)
        sections.append(table(rows, "se3 with the gyroscope's rotation held" if gyro else "se3, rotation fitted"))
    head = ["# cmax.fit quality verdicts on held-out synthetic windows", "",
            f"`indoor_flying` seeds {seeds[0]}-{seeds[-1]}, {args.size[0]}x{args.size[1]}, `speed=|v|`, depth range 1-6.5 m, default "
            f"`QualitySettings`. Machine: {describe()}, "
            f"torch threads 1. Written by `python -m benchmarks.quality_cmax"
            f"{'' if args.size == (346, 260) else f' --size {args.size[0]}x{args.size[1]}'}` in "
            f"{time.perf_counter() - start:.0f} s.", ""]
    write_text_atomic(args.output, "\n".join(head + [line for section in sections for line in section]))


if __name__ == "__main__":
    main()
