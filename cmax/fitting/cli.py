"""The ``cmax fit`` command: fit a recording window by window and write depth, trajectory and summary.

Register with ``add_fit_command(subparsers)`` in :mod:`cmax.cli`.

Outputs in ``-o outdir/``: ``depth_XXXXX.npz`` (``depth``, ``mask``,
``depth_spread``, ``inverse_depth_grid``, ``t_ref_us``, ``K``) and ``depth_XXXXX.png`` per
window (se3), ``trajectory.txt`` in TUM format (``t[s] tx ty tz qx qy qz qw``,
camera-to-world, the first window's start as the origin) and
``summary.json`` (settings, per-window twist, objective, parallax, seconds).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from cmax._args import api_default, positive_float, positive_int
from cmax.camera import check_intrinsics
from cmax.io.atomic import save_npz_atomic, write_text_atomic

__all__ = ["add_fit_command", "run_fit", "tum_lines", "intrinsics_argument"]


def intrinsics_argument(text: str) -> np.ndarray:
    """``argparse`` type of ``--K fx,fy,cx,cy`` [px]: the validated (3, 3) matrix (``cmax fit``, ``cmax emvs``,
    ``python -m learned.predict``)."""
    try:
        fx, fy, cx, cy = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--K must be fx,fy,cx,cy (four numbers), got {text!r}") from None
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    try:
        return check_intrinsics(K)
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"--K: {error}") from None


def add_fit_command(subparsers) -> argparse.ArgumentParser:
    """Add ``fit`` to an ``argparse`` sub-parser collection; returns the new parser."""
    parser = subparsers.add_parser("fit", help="depth and motion per window by contrast maximization",
                                   description=__doc__.split("\n\n")[0])
    parser.add_argument("file", type=Path, help="event file (any format cmax.io.read reads)")
    parser.add_argument("--K", required=True, type=intrinsics_argument, help="intrinsics fx,fy,cx,cy [px]")
    parser.add_argument("-o", "--output", required=True, type=Path, help="output folder")
    api_default(parser.add_argument("--model", choices=("se3", "rotation", "flow"), default=None,
                                    help="motion model"), _sequence_default("model"))
    api_default(parser.add_argument("--window-ms", type=positive_float, default=None, help="window length [ms]"),
                lambda: _sequence_default("window_us")() / 1000)
    parser.add_argument("--step-ms", type=positive_float, default=None,
                        help="step between window starts [ms] (default: the window length)")
    parser.add_argument("--speed", type=positive_float, default=None,
                        help="known speed [m/s] (metric depth; default: unknown, depth up to scale)")
    parser.add_argument("--gyro", type=Path, default=None,
                        help="gyroscope samples (se3): an .aedat4 file (its IMU stream) or a text file of "
                             "'t wx wy wz' lines [s, rad/s], camera axes, the events' clock; each window's "
                             "rotation is held at their mean, only direction and depth are fitted")
    parser.add_argument("--zero-rotation-start", action="store_true",
                        help="se3: also start the motion refinement from the flows explained without rotation "
                             "and keep the better (vehicles: on a forward drive it found forward motion where the "
                             "default ended at a pitching plane; about 1 s more per window)")
    api_default(parser.add_argument("--solver", choices=("scipy", "casadi", "torch"), default=None,
                                    help="optimisation back end"), _fit_default("solver"))
    api_default(parser.add_argument("--max-events", type=positive_int, default=None,
                                    help="windows with more events are subsampled to this many "
                                         "(cmax.FitSettings.max_events)"), _settings_default("max_events"))
    parser.set_defaults(run=run_fit)
    return parser


def _sequence_default(name: str):
    def default():
        import inspect

        from cmax.fitting.sequence import fit_sequence

        return inspect.signature(fit_sequence).parameters[name].default
    return default


def _fit_default(name: str):
    def default():
        import inspect

        from cmax.fitting.window import fit

        return inspect.signature(fit).parameters[name].default
    return default


def _settings_default(name: str):
    def default():
        from cmax.fitting.window import FitSettings

        return getattr(FitSettings(), name)
    return default


def tum_lines(times_us: np.ndarray, poses: np.ndarray) -> list[str]:
    """TUM trajectory lines ``t tx ty tz qx qy qz qw`` of poses (M, 4, 4) at times [µs]."""
    from scipy.spatial.transform import Rotation

    quats = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x, y, z, w
    return [f"{t * 1e-6:.6f} " + " ".join(f"{v:.9f}" for v in (*T[:3, 3], *q))
            for t, T, q in zip(times_us, poses, quats)]


def _microseconds(ms: float, option: str) -> int:
    us = int(round(ms * 1000))
    if us < 1:
        raise ValueError(f"{option} must be at least 0.001 ms (1 µs), got {ms}")
    return us


def run_fit(args: argparse.Namespace) -> int:
    """Run the command; returns the exit status."""
    from cmax import viz
    from cmax.fitting import fit_sequence
    from cmax.fitting.window import LOW_PARALLAX_PX
    from cmax.io import read, read_gyro

    events = read(args.file)
    gyro = None if args.gyro is None else read_gyro(args.gyro)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    options = {key: value for key, value in (("solver", args.solver), ("max_events", args.max_events))
               if value is not None}   # None: the library's default (one source: fit / FitSettings)
    sequence_model = args.model or _sequence_default("model")()
    window_us = (_sequence_default("window_us")() if args.window_ms is None
                 else _microseconds(args.window_ms, "--window-ms"))
    if args.step_ms is not None:
        options["step_us"] = _microseconds(args.step_ms, "--step-ms")
    sequence = fit_sequence(events, args.K, sequence_model, window_us=window_us, speed=args.speed,
                            gyro=gyro, zero_rotation_start=args.zero_rotation_start, **options)
    windows = []
    for i, r in enumerate(sequence.results):
        if r.depth is not None:
            save_npz_atomic(out / f"depth_{i:05d}.npz", depth=r.depth, mask=r.mask, depth_spread=r.depth_spread,
                            inverse_depth_grid=r.inverse_depth_grid, t_ref_us=r.t_ref_us, K=args.K)
            viz.save_png(out / f"depth_{i:05d}.png", viz.depth_image(np.where(r.mask, r.depth, np.nan)))
        windows.append({"t0_us": r.t0_us, "t1_us": r.t1_us, "t_ref_us": r.t_ref_us, "v": r.v.tolist(),
                        "omega": r.omega.tolist(), "flow": None if r.flow is None else r.flow.tolist(),
                        "objective_after": r.objective_after, "seconds": r.seconds, "iterations": r.iterations,
                        "message": r.message,
                        "scale_known": r.scale_known, "parallax_px": r.parallax_px})
    write_text_atomic(out / "trajectory.txt", "\n".join(tum_lines(sequence.times_us, sequence.poses)) + "\n")
    summary = {"file": str(args.file), "model": sequence_model, "K": args.K.tolist(),
               "window_ms": window_us / 1000,
               "speed": args.speed, "gyro": None if args.gyro is None else str(args.gyro),
               "solver": args.solver or _fit_default("solver")(),
               "zero_rotation_start": args.zero_rotation_start, "windows": windows}
    write_text_atomic(out / "summary.json", json.dumps(summary, indent=2))
    low = sum(w["parallax_px"] is not None and w["parallax_px"] < LOW_PARALLAX_PX for w in windows)
    caveat = f" ({low} with under {LOW_PARALLAX_PX:g} px of parallax: their depth is poorly constrained)" if low else ""
    print(f"{len(windows)} windows fitted{caveat}; results in {out}")
    return 0
