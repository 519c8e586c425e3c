"""The ``cmax scene`` command: a synthetic preset scene simulated to one h5 file with ground-truth depth and poses."""
from __future__ import annotations

import argparse
import os
from pathlib import Path

from cmax._args import api_default, default_of, library_default, nonnegative_int, positive_float, sensor_size

__all__ = ["add_command", "run", "scene_duration", "scene_size", "check_output", "check_depth_maps", "MIN_SIZE"]

#: Suffixes of the HDF5 file ``cmax scene`` writes.
H5_SUFFIXES = (".h5", ".hdf5")
#: Most memory the ground-truth depth maps of one scene may take [bytes] (they are held until written).
MAX_DEPTH_BYTES = 4 << 30


#: Longest scene [s] (that of :func:`cmax.sim.presets.make_scene`).
MAX_DURATION_S = 600.0
#: Smallest sensor (width, height) [px] of a scene: the smallest that ``cmax fit``'s default depth grid (24 rows x
#: 32 columns) fits; a smaller one gives a handful of events (10x10: 17 in 0.5 s of the slider) that no command
#: here can fit, and 1x1 failed inside the renderer.
MIN_SIZE = (32, 24)
#: Shortest scene [s]: one microsecond, the time resolution of events (a shorter one renders a single frame).
MIN_DURATION_S = 1e-6


def scene_duration(text: str) -> float:
    """``argparse`` type of ``--duration``: seconds in [:data:`MIN_DURATION_S`, :data:`MAX_DURATION_S`].

    >>> scene_duration("1e-7")
    Traceback (most recent call last):
    ...
    argparse.ArgumentTypeError: expected at least 1e-06 s (one microsecond, the time resolution of events), got '1e-7'
    """
    value = positive_float(text)
    if value > MAX_DURATION_S:
        raise argparse.ArgumentTypeError(f"expected seconds in (0, {MAX_DURATION_S:g}], got {text!r}")
    if value < MIN_DURATION_S:
        raise argparse.ArgumentTypeError(f"expected at least {MIN_DURATION_S:g} s (one microsecond, the time "
                                         f"resolution of events), got {text!r}")
    return value


def scene_size(text: str) -> tuple[int, int]:
    """``argparse`` type of ``--size``: a sensor size (:func:`cmax._args.sensor_size`) of at least :data:`MIN_SIZE`.

    >>> scene_size("10x10")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    argparse.ArgumentTypeError: expected at least 32x24 pixels (the smallest sensor cmax fit's default ...), got '10x10'
    """
    width, height = sensor_size(text)
    if width < MIN_SIZE[0] or height < MIN_SIZE[1]:
        raise argparse.ArgumentTypeError(f"expected at least {MIN_SIZE[0]}x{MIN_SIZE[1]} pixels (the smallest sensor "
                                         f"cmax fit's default 24x32 depth grid fits), got {text!r}")
    return width, height


def check_output(path: Path, overwrite: bool) -> None:
    """Refuse, before anything is simulated, an output ``path`` that cannot be written or would be replaced
    without ``--overwrite``: not ``.h5``/``.hdf5``, a folder, an existing file, or in a missing or read-only folder.

    >>> check_output(Path("scene.txt"), False)
    Traceback (most recent call last):
    ...
    ValueError: -o scene.txt: cmax scene writes an HDF5 file: give a name ending in .h5
    """
    if path.is_dir():
        raise ValueError(f"-o {path} is a folder: give the file to write, e.g. {path / 'scene.h5'}")
    if path.suffix.lower() not in H5_SUFFIXES:
        raise ValueError(f"-o {path}: cmax scene writes an HDF5 file: give a name ending in .h5")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists: pass --overwrite to replace it")
    folder = path.parent
    if not folder.is_dir():
        raise FileNotFoundError(f"-o {path}: the folder {folder} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise PermissionError(f"-o {path}: the folder {folder} is not writable")


def check_depth_maps(duration_s: float, rate_hz: float, width: int, height: int) -> None:
    """Refuse a ``--depth-rate`` whose depth maps (float32, ``width`` x ``height``, every ``1/rate_hz`` s over
    ``duration_s``) would take more than :data:`MAX_DEPTH_BYTES`, before any is rendered.

    >>> check_depth_maps(2.0, 20.0, 346, 260)   # 41 maps, 15 MB
    >>> check_depth_maps(0.1, 1e9, 64, 48)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    ValueError: --depth-rate 1e+09 Hz asks for 100,000,001 depth maps of 64x48 over 0.1 s (1.1 TiB); ...
    """
    maps = int(duration_s * rate_hz + 1e-9) + 1
    size = maps * width * height * 4
    if size > MAX_DEPTH_BYTES:
        shown = next(f"{size / 2 ** p:.1f} {unit}" for p, unit in ((40, "TiB"), (30, "GiB"), (0, "B"))
                     if size >= 2 ** p)
        raise ValueError(f"--depth-rate {rate_hz:g} Hz asks for {maps:,} depth maps of {width}x{height} over "
                         f"{duration_s:g} s ({shown}); they must fit in {MAX_DEPTH_BYTES >> 30} GiB: give a lower rate")


def run(args: argparse.Namespace) -> int:
    """Render, simulate and write the scene; returns the exit status (0)."""
    from cmax.sim.esim import EventSimulator
    from cmax.sim.presets import make_scene
    from cmax.sim.synthetic import simulate_scene

    width, height = args.size
    check_output(args.output, args.overwrite)
    depth_rate = args.depth_rate if args.depth_rate is not None else default_of(simulate_scene, "depth_rate_hz")
    check_depth_maps(args.duration, depth_rate, width, height)
    scene = make_scene(args.preset, seed=args.seed, width=width, height=height,
                       duration_s=max(args.duration, 1.0))
    settings = dict(scene.recommended_simulator)
    settings["seed"] = args.seed
    for name in ("cp", "cn"):
        if getattr(args, name) is not None:
            settings[name] = getattr(args, name)
    sequence = simulate_scene(scene, args.duration, EventSimulator(**settings), progress=not args.quiet,
                              depth_rate_hz=depth_rate)
    try:
        path = sequence.save(args.output, overwrite=args.overwrite)
    except FileExistsError:   # not there at check_output: another run or program wrote it meanwhile
        if args.overwrite or not os.path.lexists(args.output):
            raise
        raise FileExistsError(f"{args.output} was written by another program while this scene was simulated (it "
                              "was not there at the start) and is kept: pass --overwrite to replace it, or give "
                              "another -o") from None
    K = sequence.K
    near, far = scene.info.depth_range_m
    print(f"wrote {path}: {len(sequence.events):,} events, {len(sequence.depth_t_us)} depth map(s), "
          f"{len(sequence.poses_t_us)} poses, {len(sequence.frame_t_us)} rendered frames; "
          f"--K {K[0, 0]:.6g},{K[1, 1]:.6g},{K[0, 2]:.6g},{K[1, 2]:.6g}, depth {near:g}-{far:g} m "
          "(both stored in the file)")
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
    parser.add_argument("--duration", type=scene_duration, default=2.0,
                        help=f"seconds to simulate (at most {MAX_DURATION_S:g})")
    parser.add_argument("--seed", type=nonnegative_int, default=default_of(make_scene, "seed"),
                        help="seed of the scene and of the simulator")
    parser.add_argument("--size", type=scene_size, metavar="WxH",
                        help=f"sensor size [px] (a DAVIS346), at least {MIN_SIZE[0]}x{MIN_SIZE[1]}",
                        default=(default_of(make_scene, "width"), default_of(make_scene, "height")))
    parser.add_argument("--cp", type=positive_float, default=None, help="ON threshold [log intensity] (default: the preset's)")
    parser.add_argument("--cn", type=positive_float, default=None, help="OFF threshold [log intensity] (default: the preset's)")
    api_default(parser.add_argument("--depth-rate", type=positive_float, default=None,
                                    help="ground-truth depth maps per second (held in memory: 4 GiB of them at most)"),
                depth_rate)
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(run=run)
    return parser
