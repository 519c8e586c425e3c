"""The ``cmax`` command line: one entry point, one sub-command per task.

``cmax info FILE``            counts, duration, rate, resolution, polarity balance
``cmax show FILE -o out.png`` event frame or event-volume bins of a time window
``cmax scene PRESET -o F.h5``  synthetic scene: events plus ground-truth depth and poses
``cmax fit FILE --K ...``     depth and motion per window by contrast maximization
``cmax demo``                 the end-to-end demo on data it makes itself
``cmax simulate IN -o OUT``   videos to event files (ESIM), with a resumable manifest
``cmax manifest merge ...``   join the manifests of several machines or shards

Each sub-command parses its arguments, calls the library, and prints or
writes the result; no numerical code lives here.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Callable, Sequence

__all__ = ["main", "build_parser"]


def _sensor_size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 346x260, got {text!r}") from None
    if not (0 < width <= 65535 and 0 < height <= 65535):
        raise argparse.ArgumentTypeError(f"width and height must be in [1, 65535] pixels, got {text!r}")
    return width, height


def _add_size_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--size", type=_sensor_size, default=None, metavar="WxH",
        help="sensor size, for files that do not store it (ECD text, .npy, original DSEC)",
    )
    parser.add_argument("--time-unit", choices=("us", "ms", "s"), default=None,
                        help="unit of the file's time stamps where the file does not state it (never guessed)")


def _size_kwargs(args: argparse.Namespace) -> dict[str, int | str | None]:
    width, height = args.size if args.size else (None, None)
    return {"width": width, "height": height, "time_unit": args.time_unit}


# -- info ------------------------------------------------------------------------------
def _cmd_info(args: argparse.Namespace) -> int:
    from cmax.io.info import file_info

    for path in args.files:
        print("\n".join(file_info(path, **_size_kwargs(args)).lines()))
    return 0


def _add_info(subparsers) -> None:
    parser = subparsers.add_parser("info", help="summary of event files", description=_cmd_info.__doc__)
    parser.add_argument("files", nargs="+", type=Path, help="event files (any supported format)")
    _add_size_option(parser)
    parser.set_defaults(run=_cmd_info)


# -- show ------------------------------------------------------------------------------
def _cmd_show(args: argparse.Namespace) -> int:
    from cmax.show import render_window

    image = render_window(
        args.file, t0_s=args.t0, dt_s=args.dt, mode=args.mode, bins=args.bins, **_size_kwargs(args)
    )
    from cmax.viz import save_image

    output = args.output or args.file.with_suffix(".png")
    save_image(output, image)
    print(f"wrote {output}")
    return 0


def _add_show(subparsers) -> None:
    parser = subparsers.add_parser(
        "show", help="draw a time window of an event file as a PNG",
        description="Draw the events of [t0, t0 + dt) as an event frame (ON blue, OFF red) "
        "or as the bins of the event volume; ground-truth depth is drawn beside them when the file has it.",
    )
    parser.add_argument("file", type=Path)
    parser.add_argument("--t0", type=float, default=0.0, help="window start in seconds after the first event (default 0)")
    parser.add_argument("--dt", type=float, default=0.05, help="window length in seconds (default 0.05)")
    parser.add_argument("--mode", choices=("frame", "voxel", "both"), default="both")
    parser.add_argument("--bins", type=int, default=5, help="bins of the event volume (default 5)")
    parser.add_argument("-o", "--output", type=Path, default=None, help="picture path, .png, .jpg or .jpeg (default: FILE with .png)")
    _add_size_option(parser)
    parser.set_defaults(run=_cmd_show)


# -- demo ------------------------------------------------------------------------------
def _cmd_demo(args: argparse.Namespace) -> int:
    from cmax.demo import run_demo

    width, height = args.size
    report = run_demo(args.output, seed=args.seed, duration_s=args.duration, window_s=args.window,
                      width=width, height=height)
    print(f"demo report: {report.report_png}")
    return 0


def _add_demo(subparsers) -> None:
    parser = subparsers.add_parser(
        "demo", help="end-to-end demo on data it makes itself",
        description="Render a synthetic scene, simulate its events, fit depth and motion with cmax.fit, run "
        "EMVS with the true poses, score both against ground truth, and write report.png, report.md and "
        "summary.txt.",
    )
    parser.add_argument("-o", "--output", type=Path, default=Path("demo_output"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--duration", type=float, default=0.5, help="seconds of scene to simulate")
    parser.add_argument("--window", type=float, default=0.1665, help="seconds of the window cmax.fit fits")
    parser.add_argument("--size", type=_sensor_size, default=(240, 180), help="sensor WIDTHxHEIGHT")
    parser.set_defaults(run=_cmd_demo)


# -- scene -----------------------------------------------------------------------------
def _cmd_scene(args: argparse.Namespace) -> int:
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
    sequence = simulate_scene(
        scene, args.duration, EventSimulator(**settings), depth_rate_hz=args.depth_rate, progress=True,
    )
    path = sequence.save(args.output, overwrite=args.overwrite)
    print(f"wrote {path}: {len(sequence.events):,} events, {len(sequence.depth_t_us)} depth maps, "
          f"{len(sequence.poses_t_us)} poses, {len(sequence.frame_t_us)} rendered frames")
    return 0


def _add_scene(subparsers) -> None:
    from cmax.sim.presets import PRESETS

    parser = subparsers.add_parser(
        "scene", help="simulate a synthetic scene with ground-truth depth and poses",
        description="Render a preset scene at adaptive times, simulate its events (ESIM) and write "
        "one DSEC-layout h5 file with the ground truth in gt/ (depth, depth_t, poses, poses_t, K).",
    )
    parser.add_argument("preset", choices=sorted(PRESETS))
    parser.add_argument("-o", "--output", type=Path, required=True, help="output .h5 file")
    parser.add_argument("--duration", type=float, default=2.0, help="seconds to simulate (default 2)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--size", type=_sensor_size, default=(346, 260), metavar="WxH",
                        help="sensor size (default 346x260, a DAVIS346)")
    parser.add_argument("--cp", type=float, default=None, help="ON threshold (default: the preset's)")
    parser.add_argument("--cn", type=float, default=None, help="OFF threshold (default: the preset's)")
    parser.add_argument("--depth-rate", type=float, default=20.0, help="ground-truth depth maps per second")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    parser.set_defaults(run=_cmd_scene)


def _add_fit(subparsers) -> None:
    from cmax.fitting.cli import add_fit_command

    add_fit_command(subparsers)


def _add_emvs(subparsers) -> None:
    from cmax.emvs_cli import add_emvs_command

    add_emvs_command(subparsers)


# -- simulate / manifest ---------------------------------------------------------------
def _cmd_simulate(args: argparse.Namespace) -> int:
    from cmax.sim.catalogue import parse_shard
    from cmax.sim.convert import VIDEO_SUFFIXES, ConvertSettings, collect_jobs, convert_collection, convert_video
    from cmax.sim.esim import EsimSettings

    esim = EsimSettings(args.cp, args.cn, args.threshold_sigma, args.refractory_us, seed=args.seed,
                        shot_noise_rate_hz=args.shot_noise, leak_rate_hz=args.leak)
    settings = ConvertSettings(esim, size=args.size, adaptive=args.adaptive, lam=args.lam,
                               method=args.method, t0_s=args.t0, t1_s=args.t1)
    shard = parse_shard(args.shard) if args.shard else None
    if args.input.is_file() and args.output.suffix == ".h5" and not args.catalogue:
        if args.input.suffix.lower() not in VIDEO_SUFFIXES:
            raise ValueError(f"INPUT must be a video ({', '.join(VIDEO_SUFFIXES)}) when OUTPUT is one .h5 file, "
                             f"got {args.input}")
        result = convert_video(args.input, args.output, settings, overwrite=args.overwrite)
        print(f"wrote {result.output}: {result.events:,} events from {result.frames} frames "
              f"({result.samples} samples), {result.duration_s:.2f} s of video")
        return 0
    jobs, missing = collect_jobs(args.input, catalogue=args.catalogue, shard=shard)
    manifest = convert_collection(jobs, args.output, settings, workers=args.workers, missing=missing,
                                  catalogue=args.catalogue, shard=shard, progress=not args.quiet)
    totals = manifest["totals"]
    print(f"{args.output / 'manifest.json'}: {totals['ok']} videos ok, {totals['failed']} failed, "
          f"{totals['events']:,} events")
    for name, entry in manifest["videos"].items():
        if entry["status"] != "ok":
            print(f"  failed {name}: {entry['error']}", file=sys.stderr)
    if missing:
        print(f"  missing from {args.input}: {', '.join(missing)}", file=sys.stderr)
    return 1 if totals["failed"] else 0


def _add_simulate(subparsers) -> None:
    parser = subparsers.add_parser(
        "simulate", help="convert videos to event files (ESIM), one or a whole collection",
        description="Convert a video file (-o F.h5), a folder of videos, a list file (one video per "
        "line, optional tab and category) or a catalogue's folder (--catalogue slowtv) to DSEC-layout "
        "h5 files in the folder -o, with manifest.json; resumable, in --workers processes.",
    )
    parser.add_argument("input", type=Path, help="video file, folder of videos, or list file")
    parser.add_argument("-o", "--output", type=Path, required=True, help="output .h5 file or folder")
    parser.add_argument("--cp", type=float, default=0.2, help="ON threshold (default 0.2)")
    parser.add_argument("--cn", type=float, default=0.2, help="OFF threshold (default 0.2)")
    parser.add_argument("--threshold-sigma", type=float, default=0.0, help="per-pixel threshold mismatch")
    parser.add_argument("--refractory-us", type=int, default=0, help="refractory period in µs")
    parser.add_argument("--shot-noise", type=float, default=0.0, help="shot-noise rate per pixel (Hz)")
    parser.add_argument("--leak", type=float, default=0.0, help="leak-event rate per pixel (Hz)")
    parser.add_argument("--seed", type=int, default=0, help="seed of mismatch and noise (default 0)")
    parser.add_argument("--size", type=_sensor_size, default=None, metavar="WxH", help="resize frames")
    parser.add_argument("--adaptive", action=argparse.BooleanOptionalAction, default=True,
                        help="insert interpolated frames (adaptive sampling, default on)")
    parser.add_argument("--lam", type=float, default=0.5, help="lambda of adaptive sampling (default 0.5)")
    parser.add_argument("--method", choices=("flow", "linear"), default="flow", help="interpolation")
    parser.add_argument("--t0", type=float, default=None, help="start, seconds into each video")
    parser.add_argument("--t1", type=float, default=None, help="end, seconds into each video")
    parser.add_argument("--workers", type=int, default=1, help="parallel processes (default 1)")
    parser.add_argument("--catalogue", choices=("slowtv",), default=None,
                        help="INPUT is the folder of a catalogue's videos named by index (00000.mp4)")
    parser.add_argument("--shard", default=None, metavar="i/n", help="convert shard i of n (0-based)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output .h5")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.set_defaults(run=_cmd_simulate)


def _cmd_manifest(args: argparse.Namespace) -> int:
    from cmax.sim.convert import load_manifest, merge_manifests, write_manifest

    merged = merge_manifests([load_manifest(path) for path in args.manifests])
    write_manifest(args.output, merged)
    totals = merged["totals"]
    print(f"wrote {args.output}: {totals['videos']} videos ({totals['failed']} failed), "
          f"{len(merged['missing'])} missing")
    return 0


def _add_manifest(subparsers) -> None:
    parser = subparsers.add_parser("manifest", help="join the manifests of several conversions")
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    merge = actions.add_parser("merge", help="merge manifest.json files (shards, machines)")
    merge.add_argument("manifests", nargs="+", type=Path)
    merge.add_argument("-o", "--output", type=Path, required=True)
    merge.set_defaults(run=_cmd_manifest)


_COMMANDS: tuple[Callable, ...] = (_add_info, _add_show, _add_scene, _add_fit, _add_emvs, _add_demo,
                                   _add_simulate, _add_manifest)


def build_parser() -> argparse.ArgumentParser:
    """The ``cmax`` argument parser with all sub-commands."""
    from cmax import __version__

    parser = argparse.ArgumentParser(
        prog="cmax", description="Event cameras: simulation, file formats, contrast maximization."
    )
    parser.add_argument("--version", action="version", version=f"evtslowtv {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in _COMMANDS:
        add(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``cmax`` console script; returns the exit status.

    Errors a user can fix (bad files, bad arguments) print one line on stderr
    and exit with status 2 instead of a traceback.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "run", None):
        parser.print_help()
        return 2
    from cmax.io import FormatError

    try:
        return int(args.run(args) or 0)
    except (FormatError, ValueError, TypeError, OSError) as error:  # OSError: missing, exists, denied
        message = " ".join(str(error).split())  # one line
        print(f"cmax {args.command}: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
