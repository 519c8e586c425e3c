"""The ``cmax scene`` command: a synthetic preset scene simulated to one h5 file with ground-truth depth and poses."""
from __future__ import annotations

import argparse
from pathlib import Path

from cmax._args import api_default, default_of, library_default, nonnegative_int, positive_float, sensor_size

__all__ = ["add_command", "run"]


def run(args: argparse.Namespace) -> int:
    """Render, simulate and write the scene; returns the exit status (0)."""
    from cmax.sim.esim import EventSimulator
    from cmax.sim.presets import make_scene
    from cmax.sim.synthetic import simulate_scene

    width, height = args.size
    scene = make_scene(args.preset, seed=args.seed, width=width, height=height,
                       duration_s=max(args.duration, 1.0))
    settings = dict(scene.recommended_simulator)
    settings["seed"] = args.seed
    for name in ("cp", "cn"):
        if getattr(args, name) is not None:
            settings[name] = getattr(args, name)
    rate = {} if args.depth_rate is None else {"depth_rate_hz": args.depth_rate}
    sequence = simulate_scene(scene, args.duration, EventSimulator(**settings), progress=True, **rate)
    path = sequence.save(args.output, overwrite=args.overwrite)
    print(f"wrote {path}: {len(sequence.events):,} events, {len(sequence.depth_t_us)} depth maps, "
          f"{len(sequence.poses_t_us)} poses, {len(sequence.frame_t_us)} rendered frames")
    return 0


def add_command(subparsers) -> argparse.ArgumentParser:
    """Add ``scene`` to an ``argparse`` sub-parser collection; returns the new parser."""
    from cmax.sim.presets import PRESETS, make_scene

    depth_rate = library_default("cmax.sim.synthetic:simulate_scene", "depth_rate_hz")  # loads torch: --help only

    parser = subparsers.add_parser(
        "scene", help="simulate a synthetic scene with ground-truth depth and poses",
        description="Render a preset scene at adaptive times, simulate its events (ESIM) and write "
        "one DSEC-layout h5 file with the ground truth in gt/ (depth, depth_t, poses, poses_t, K).",
    )
    parser.add_argument("preset", choices=sorted(PRESETS), help="scene preset")
    parser.add_argument("-o", "--output", type=Path, required=True, help="output .h5 file")
    parser.add_argument("--duration", type=float, default=2.0, help="seconds to simulate (checked by the scene)")
    parser.add_argument("--seed", type=nonnegative_int, default=default_of(make_scene, "seed"),
                        help="seed of the scene and of the simulator")
    parser.add_argument("--size", type=sensor_size, metavar="WxH", help="sensor size (a DAVIS346)",
                        default=(default_of(make_scene, "width"), default_of(make_scene, "height")))
    parser.add_argument("--cp", type=float, default=None, help="ON threshold (default: the preset's)")
    parser.add_argument("--cn", type=float, default=None, help="OFF threshold (default: the preset's)")
    api_default(parser.add_argument("--depth-rate", type=positive_float, default=None,
                                    help="ground-truth depth maps per second"), depth_rate)
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    parser.set_defaults(run=run)
    return parser
