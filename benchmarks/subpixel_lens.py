"""Fitting through a lens with sub-pixel undistortion against rounding to the nearest undistorted pixel.

Each synthetic window (``preset_window``) is recorded through a barrel lens the way ``tests/test_fit_camera.py``
does it (``cv2.projectPoints`` of each ideal event's ray, rounded to the sensor pixel), then fitted with its
:class:`cmax.Camera` in two ways: ``rounded`` fits ``camera.undistort_events(events)`` with the pinhole K (each event
at its nearest undistorted pixel, dithered there: what ``cmax.fit(events, camera)`` did before), ``sub-pixel`` fits
``cmax.fit(events, camera)`` (each event dithered over its sensor pixel and mapped through the lens); ``ideal``
fits the ideal pinhole's own events (the ceiling). Printed: the
depth abs_rel with the true pose, and the translation-direction error [deg] with the true speed, per seed and their
medians.

    python -m benchmarks.subpixel_lens --seeds 100 101 102 --presets slider indoor_flying [--output FILE]
"""
from __future__ import annotations

import argparse
import warnings

import cv2
import numpy as np

import cmax
from benchmarks.synthetic_windows import preset_window
from cmax.metrics import depth_metrics

#: The barrel lens of tests/test_fit_camera.py (k1, k2, p1, p2): up to 11 px at the corners of 120x90.
DISTORTION = np.array([-0.25, 0.06, 0.0, 0.0])


def distorted(events: cmax.Events, K: np.ndarray, distortion: np.ndarray) -> cmax.Events:
    """The ideal pinhole's events as the lens records them: each ray through ``cv2.projectPoints``, rounded to the
    sensor pixel (those that leave the sensor dropped)."""
    rays = np.column_stack([events.x, events.y, np.ones(len(events))]) @ np.linalg.inv(K).T
    pixels, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, distortion)
    xy = np.rint(pixels.reshape(-1, 2)).astype(np.int64)
    inside = (xy[:, 0] >= 0) & (xy[:, 0] < events.width) & (xy[:, 1] >= 0) & (xy[:, 1] < events.height)
    return cmax.Events(xy[inside, 0], xy[inside, 1], events.t[inside], events.p[inside], events.width,
                       events.height)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle [deg] between vectors ``a`` and ``b`` (3,)."""
    cosine = np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))


def run(seed: int, preset: str) -> dict[str, float]:
    """abs_rel (pose given) and direction error [deg] (speed given) of each way on window ``seed``."""
    window = preset_window(preset, seed, width=120, height=90, duration_s=0.1665, texture_size=128)
    events = distorted(window.events, window.K, DISTORTION)
    camera = cmax.Camera(window.K, 120, 90, DISTORTION)
    rounded = camera.undistort_events(events)
    twist = window.twist                                   # (v [m/s], omega [rad/s])
    speed = float(np.linalg.norm(twist[:3]))
    out = {}
    ways = {"ideal": (window.events, window.K), "rounded": (rounded, window.K), "sub-pixel": (events, camera)}
    for name, (ev, K) in ways.items():
        depth = cmax.fit(ev, K, pose=window.T01)
        out[f"{name} abs_rel"] = depth_metrics(np.where(depth.mask, depth.depth, np.nan), window.depth).abs_rel
        motion = cmax.fit(ev, K, speed=speed)
        out[f"{name} dir_deg"] = angle_deg(motion.v, twist[:3])
    return out


def markdown(preset: str, seeds: list[int], rows: list[dict[str, float]]) -> list[str]:
    """Markdown lines of one preset's table: per way, the medians over ``seeds`` and on how many windows the
    sub-pixel fit does better than the rounded one."""
    lines = [f"### {preset} (seeds {seeds[0]}-{seeds[-1]}, {len(seeds)} windows, 120x90)", "",
             "| way | depth abs_rel median (pose given) | direction error median [deg] (speed given) |",
             "|---|---|---|"]
    for way in ("ideal", "rounded", "sub-pixel"):
        lines.append(f"| {way} | {np.median([r[f'{way} abs_rel'] for r in rows]):.3f} | "
                     f"{np.median([r[f'{way} dir_deg'] for r in rows]):.1f} |")
    better = sum(r["sub-pixel abs_rel"] < r["rounded abs_rel"] for r in rows)
    paired = np.median([r["sub-pixel abs_rel"] - r["rounded abs_rel"] for r in rows])
    closer = sum(r["sub-pixel dir_deg"] < r["rounded dir_deg"] for r in rows)
    lines += ["", f"Sub-pixel against rounded: depth better on {better} of {len(rows)} windows (paired median "
              f"difference {paired:+.4f}), direction closer on {closer} of {len(rows)}.", ""]
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5], help="window seeds")
    parser.add_argument("--presets", nargs="+", default=["indoor_flying"],
                        help="preset scenes (benchmarks.synthetic_windows)")
    parser.add_argument("--output", default=None, help="markdown results file (default: print only)")
    args = parser.parse_args(argv)
    warnings.simplefilter("ignore")
    lines = ["# Fitting through a lens: sub-pixel undistortion against rounding", "",
             f"`python -m benchmarks.subpixel_lens --seeds {' '.join(map(str, args.seeds))} --presets "
             f"{' '.join(args.presets)}`. Each window recorded through a barrel lens (k1 = {DISTORTION[0]}, "
             f"k2 = {DISTORTION[1]}; `cv2.projectPoints`, rounded to the sensor pixel) and fitted three ways in one "
             "process: `ideal`, the ideal pinhole's own events (the ceiling); `rounded`, each event at its nearest "
             "undistorted pixel (what `cmax.fit(events, camera)` did until 2026-12-05); `sub-pixel`, "
             "`cmax.fit(events, camera)` (each event dithered over its sensor pixel and mapped through the lens).", ""]
    for preset in args.presets:
        rows = []
        for seed in args.seeds:
            row = run(seed, preset)
            rows.append(row)
            print(f"{preset} seed {seed}: " + ", ".join(f"{k} {v:.4f}" for k, v in row.items()), flush=True)
        lines += markdown(preset, args.seeds, rows)
        print("\n".join(markdown(preset, args.seeds, rows)), flush=True)
    if args.output:
        from cmax.io.atomic import write_text_atomic
        write_text_atomic(args.output, "\n".join(lines))


if __name__ == "__main__":
    main()
