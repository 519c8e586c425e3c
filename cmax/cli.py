"""The ``cmax`` command line: one entry point, one sub-command per task.

``cmax info FILE``            counts, duration, rate, resolution, polarity balance
``cmax show FILE -o out.png`` event frame or event-volume bins of a time window
``cmax scene PRESET -o F.h5``  synthetic scene: events plus ground-truth depth and poses
``cmax fit FILE --K ...``     depth and motion per window by contrast maximization
``cmax depth FILE -o out/``   depth and motion per window by the shipped depth-pose network
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
from typing import Any, Callable, Sequence

from cmax._args import (ArgumentParser, api_default, default_of, library_default, nonnegative_int, positive_float,
                        positive_int, run_main, sensor_size)

__all__ = ["main", "build_parser"]

_sensor_size = sensor_size  # the type of every WxH option (kept under its old name for importers)


#: Where the simulator's defaults live (read only for --help and for options left out).
_ESIM, _CONVERT = "cmax.sim.esim_settings:EsimSettings", "cmax.sim.convert:ConvertSettings"


def _given(args: argparse.Namespace, names: dict[str, str]) -> dict[str, Any]:
    """``{keyword: value}`` of the options in ``names`` (option dest -> keyword) that were given (not None)."""
    return {key: getattr(args, dest) for dest, key in names.items() if getattr(args, dest) is not None}


def _add_size_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--size", type=sensor_size, default=None, metavar="WxH",
        help="sensor size, for files that do not store it (ECD text, .npy, original DSEC)",
    )
    parser.add_argument("--time-unit", choices=("us", "ms", "s"), default=None,
                        help="unit of the file's time stamps where the file does not state it (never guessed)")
    parser.add_argument("--polarity", choices=("01", "signed"), default=None,
                        help="polarity encoding of an h5, text or .npy file: 01 (0 OFF, 1 ON) or signed "
                        "(-1 OFF, +1 ON) (default: 01; never guessed)")


def _size_kwargs(args: argparse.Namespace) -> dict[str, int | str | None]:
    width, height = args.size if args.size else (None, None)
    options = {"width": width, "height": height, "time_unit": args.time_unit}
    if args.polarity is not None:
        options["polarity"] = args.polarity
    return options


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
    parser.add_argument("file", type=Path, help="event file (any supported format)")
    # t0, dt, bins: validated by cmax.show.render_window (one-line errors naming the value)
    parser.add_argument("--t0", type=float, default=0.0, help="window start in seconds after the first event")
    parser.add_argument("--dt", type=float, default=0.05, help="window length in seconds")
    parser.add_argument("--mode", choices=("frame", "voxel", "both"), default="both",
                        help="event frame, event-volume bins, or both")
    parser.add_argument("--bins", type=int, default=5, help="bins of the event volume")
    parser.add_argument("-o", "--output", type=Path, default=None, help="picture path, .png, .jpg or .jpeg (default: FILE with .png)")
    _add_size_option(parser)
    parser.set_defaults(run=_cmd_show)


# -- demo ------------------------------------------------------------------------------
_DEMO_OPTIONS = {"seed": "seed", "duration": "duration_s", "window": "window_s"}


def _cmd_demo(args: argparse.Namespace) -> int:
    from cmax.demo import run_demo

    overrides = _given(args, _DEMO_OPTIONS)
    if args.size is not None:
        overrides["width"], overrides["height"] = args.size
    report = run_demo(args.output, **overrides)
    print(f"demo report: {report.report_png}")
    return 0


def _demo_default(name: str) -> Callable[[], Any]:
    if name != "size":
        return library_default("cmax.demo:DemoSettings", name)
    width, height = (library_default("cmax.demo:DemoSettings", side) for side in ("width", "height"))
    return lambda: (width(), height())


def _add_demo(subparsers) -> None:
    parser = subparsers.add_parser(
        "demo", help="end-to-end demo on data it makes itself",
        description="Render a synthetic scene, simulate its events, fit depth and motion with cmax.fit, run "
        "EMVS with the true poses, score both against ground truth, and write report.png, report.md and "
        "summary.txt.",
    )
    parser.add_argument("-o", "--output", type=Path, default=Path("demo_output"), help="output folder")
    api_default(parser.add_argument("--seed", type=nonnegative_int, default=None, help="seed of the scene"),
                _demo_default("seed"))
    api_default(parser.add_argument("--duration", type=positive_float, default=None,
                                    help="seconds of scene to simulate"), _demo_default("duration_s"))
    api_default(parser.add_argument("--window", type=positive_float, default=None,
                                    help="seconds of the window cmax.fit fits"), _demo_default("window_s"))
    api_default(parser.add_argument("--size", type=sensor_size, default=None, metavar="WxH",
                                    help="sensor WIDTHxHEIGHT"), _demo_default("size"))
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
    rate = {} if args.depth_rate is None else {"depth_rate_hz": args.depth_rate}
    sequence = simulate_scene(scene, args.duration, EventSimulator(**settings), progress=True, **rate)
    path = sequence.save(args.output, overwrite=args.overwrite)
    print(f"wrote {path}: {len(sequence.events):,} events, {len(sequence.depth_t_us)} depth maps, "
          f"{len(sequence.poses_t_us)} poses, {len(sequence.frame_t_us)} rendered frames")
    return 0


def _add_scene(subparsers) -> None:
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
    parser.set_defaults(run=_cmd_scene)


def _add_fit(subparsers) -> None:
    from cmax.fitting.cli import add_fit_command

    add_fit_command(subparsers)


def _add_emvs(subparsers) -> None:
    from cmax.emvs_cli import add_emvs_command

    add_emvs_command(subparsers)


def _add_depth(subparsers) -> None:
    from learned.predict import add_arguments, run

    parser = subparsers.add_parser(
        "depth", help="depth and motion per window by the learned depth-pose network",
        description="Depth maps [m] (npz and PNG with a colour bar) and twists of every window of an event file, "
        "by the depth-pose network shipped in the package (or --checkpoint); the same command as "
        "python -m learned.predict.")
    add_arguments(parser)
    parser.set_defaults(run=lambda args: run(args, "cmax depth"))


# -- simulate / manifest ---------------------------------------------------------------
#: simulate options (dest) -> EsimSettings / ConvertSettings fields; None on the command line = the library's default.
_ESIM_OPTIONS = {"cp": "cp", "cn": "cn", "threshold_sigma": "threshold_sigma", "refractory_us": "refractory_us",
                 "shot_noise": "shot_noise_rate_hz", "leak": "leak_rate_hz", "seed": "seed"}
_CONVERT_OPTIONS = {"size": "size", "adaptive": "adaptive", "lam": "lam", "method": "method", "t0": "t0_s",
                    "t1": "t1_s"}


def _cmd_simulate(args: argparse.Namespace) -> int:
    from cmax.sim.catalogue import parse_shard
    from cmax.sim.convert import ConvertSettings, collect_jobs, convert_collection
    from cmax.sim.esim import EsimSettings

    esim = EsimSettings(**_given(args, _ESIM_OPTIONS))
    settings = ConvertSettings(esim, **_given(args, _CONVERT_OPTIONS))
    shard = parse_shard(args.shard) if args.shard else None
    single = _single_input(args)
    if single is not None:
        return _simulate_one(args, single, settings)
    jobs, missing = collect_jobs(args.input, catalogue=args.catalogue, shard=shard)
    manifest = convert_collection(jobs, args.output, settings, workers=args.workers, missing=missing,
                                  catalogue=args.catalogue, shard=shard, progress=not args.quiet)
    status = _report_manifest(args.output / "manifest.json", manifest, [job.name for job in jobs])
    if missing:
        print(f"  missing from {args.input}: {', '.join(missing)}", file=sys.stderr)
    return status


def _single_input(args: argparse.Namespace) -> Path | None:
    """The frame source of a one-file conversion (``-o F.h5``): a video, or an image folder's folder/timestamp
    file; None for a collection (a folder of videos, a list file, a catalogue)."""
    from cmax.sim.convert import VIDEO_SUFFIXES

    source, single = args.input, args.output.suffix == ".h5" and not args.catalogue
    image_source = _image_folder(source)
    if image_source is not None:
        if not single:
            raise ValueError(f"{source} is an image folder (one sequence): give the output file as -o NAME.h5")
        return image_source
    if not single:
        return None
    if source.is_dir():
        return None  # a folder of videos into one .h5 file: refused by the collection with a clear message
    if not source.exists():
        raise FileNotFoundError(f"input not found: {source}")
    if source.suffix.lower() not in VIDEO_SUFFIXES:
        raise ValueError(f"INPUT must be a video ({', '.join(VIDEO_SUFFIXES)}), an image folder with images.txt or "
                         f"images/ + timestamps.txt, or a timestamp file when OUTPUT is one .h5 file, got {source}")
    return source


def _image_folder(source: Path) -> Path | None:
    """The path :func:`cmax.sim.video.open_source` reads for an image sequence, or None if ``source`` is none.

    * ECD: a folder holding ``images.txt`` (lines ``t images/frame_00000000.png``), or that file;
    * rpg_vid2e / ESIM: a folder holding ``images/`` and ``timestamps.txt``, a folder of images with
      ``timestamps.txt`` in it or in its parent, or the ``timestamps.txt`` file.
    """
    from cmax.sim.video import IMAGE_SUFFIXES

    if source.is_file():
        if source.name == "timestamps.txt" and (source.parent / "images").is_dir():
            return source.parent / "images"
        return source if source.name in ("images.txt", "timestamps.txt") else None
    if not source.is_dir():
        return None
    if (source / "images.txt").is_file():
        return source / "images.txt"
    if (source / "images").is_dir() and (source / "timestamps.txt").is_file():
        return source / "images"
    has_images = any(p.suffix.lower() in IMAGE_SUFFIXES for p in source.iterdir())
    if has_images and any((folder / "timestamps.txt").is_file() for folder in (source, source.parent)):
        return source
    return None


def _simulate_one(args: argparse.Namespace, source: Path, settings) -> int:
    """``cmax simulate SOURCE -o F.h5``: one conversion with progress and a manifest beside F.h5."""
    from cmax.sim.convert import VideoJob, convert_collection, load_manifest, write_manifest

    output = args.output
    manifest_path = output.parent / "manifest.json"
    manifest = load_manifest(manifest_path) if manifest_path.is_file() else None
    listed = manifest["videos"].get(output.stem) if manifest else None
    if output.exists() and not args.overwrite and not (listed and listed.get("status") == "ok"):
        raise FileExistsError(f"{output} exists and is not a finished conversion of {manifest_path}; "
                              "pass --overwrite to replace it")
    if args.overwrite and listed:   # forget the old entry: the video is redone, the old file replaced atomically
        write_manifest(manifest_path, {**manifest, "videos": {k: v for k, v in manifest["videos"].items()
                                                              if k != output.stem}})
    job = VideoJob(output.stem, source)
    manifest = convert_collection([job], output.parent, settings, workers=1, progress=not args.quiet)
    return _report_manifest(manifest_path, manifest, [job.name])


def _report_manifest(path: Path, manifest: dict, names: Sequence[str]) -> int:
    """Print the outcome of a conversion; 1 when a video failed or yielded no events, else 0."""
    totals, videos = manifest["totals"], manifest["videos"]
    empty = [name for name in names if videos.get(name, {}).get("status") == "ok"
             and videos[name].get("events", 0) == 0]
    note = f" ({len(empty)} of them with no events)" if empty else ""
    print(f"{path}: {totals['ok']} videos ok{note}, {totals['failed']} failed, {totals['events']:,} events")
    for name in names:
        entry = videos.get(name, {})
        if entry.get("status") == "ok" and name not in empty:
            print(f"  {entry['output']}: {entry['events']:,} events from {entry['frames']} frames "
                  f"({entry['samples']} samples), {entry['duration_s']:.2f} s of video")
    for name, entry in videos.items():
        if entry["status"] != "ok":
            print(f"  failed {name}: {entry['error']}", file=sys.stderr)
    for name in empty:
        entry = videos[name]
        print(f"  no events from {name}: {entry['frames']} frame(s) over {entry['duration_s']:.3f} s "
              f"(events need at least two frames that differ by a threshold); {entry['output']} holds 0 events",
              file=sys.stderr)
    return 1 if totals["failed"] or empty else 0


def _add_simulate(subparsers) -> None:
    parser = subparsers.add_parser(
        "simulate", help="convert videos or image sequences to event files (ESIM), one or a whole collection",
        description="Convert a video file, an image folder (ECD: images.txt; rpg_vid2e/ESIM: images/ + "
        "timestamps.txt) or a timestamp file to one h5 file (-o F.h5, with manifest.json beside it); or a "
        "folder of videos, a list file (one video per line, optional tab and category) or a catalogue's "
        "folder (--catalogue slowtv) to DSEC-layout h5 files in the folder -o, with manifest.json; "
        "resumable, in --workers processes. Exit status 1 when a video fails or yields no events.",
    )
    parser.add_argument("input", type=Path,
                        help="video file, image folder, timestamp file, folder of videos, or list file")
    parser.add_argument("-o", "--output", type=Path, required=True, help="output .h5 file or folder")
    # Simulator settings are validated by EsimSettings / ConvertSettings (one-line errors naming the value).
    esim = (("--cp", float, "cp", "ON threshold"), ("--cn", float, "cn", "OFF threshold"),
            ("--threshold-sigma", float, "threshold_sigma", "per-pixel threshold mismatch (std)"),
            ("--refractory-us", int, "refractory_us", "refractory period in µs"),
            ("--shot-noise", float, "shot_noise_rate_hz", "shot-noise rate per pixel (Hz)"),
            ("--leak", float, "leak_rate_hz", "leak-event rate per pixel (Hz)"))
    for option, kind, name, text in esim:
        api_default(parser.add_argument(option, type=kind, default=None, help=text), library_default(_ESIM, name))
    parser.add_argument("--seed", type=nonnegative_int, default=0,
                        help="seed of mismatch and noise (default 0, reproducible; the API's None draws a fresh one)")
    parser.add_argument("--size", type=sensor_size, default=None, metavar="WxH",
                        help="resize frames (default: the video's size)")
    api_default(parser.add_argument("--adaptive", action=argparse.BooleanOptionalAction, default=None,
                                    help="insert interpolated frames (adaptive sampling)"), library_default(_CONVERT, "adaptive"))
    api_default(parser.add_argument("--lam", type=float, default=None, help="lambda of adaptive sampling"),
                library_default(_CONVERT, "lam"))
    api_default(parser.add_argument("--method", choices=("flow", "linear"), default=None,
                                    help="interpolation of adaptive sampling"), library_default(_CONVERT, "method"))
    parser.add_argument("--t0", type=float, default=None,
                        help="start, seconds into each video (default: its start)")
    parser.add_argument("--t1", type=float, default=None,
                        help="end, seconds into each video (default: its end)")
    parser.add_argument("--workers", type=positive_int, default=1, help="parallel processes")
    parser.add_argument("--catalogue", choices=("slowtv",), default=None,
                        help="INPUT is the folder of a catalogue's videos named by index (00000.mp4)")
    parser.add_argument("--shard", default=None, metavar="i/n",
                        help="convert shard i of n (0-based; default: all)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output .h5")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.set_defaults(run=_cmd_simulate)


def _duplicates(paths: Sequence[Path], manifests: Sequence[dict]) -> tuple[list[str], list[str]]:
    """Names listed by several manifests: (conflicts: two different ``ok`` entries; notes: the others)."""
    seen: dict[str, list[tuple[Path, dict]]] = {}
    for path, manifest in zip(paths, manifests):
        for name, entry in manifest["videos"].items():
            seen.setdefault(name, []).append((path, entry))
    conflicts, notes = [], []
    for name, entries in sorted(seen.items()):
        if len(entries) < 2:
            continue
        oks = [(path, entry) for path, entry in entries if entry.get("status") == "ok"]
        where = ", ".join(f"{entry.get('status')} in {path}" for path, entry in entries)
        if len({repr(sorted((k, v) for k, v in e.items() if k != "wall_s")) for _, e in oks}) > 1:
            conflicts.append(f"{name} ({where})")
        else:
            kept = oks[0][0] if oks else entries[-1][0]
            notes.append(f"{name}: {where}; kept the entry of {kept}")
    return conflicts, notes


def _cmd_manifest(args: argparse.Namespace) -> int:
    from cmax.sim.convert import load_manifest, merge_manifests, write_manifest

    manifests = [load_manifest(path) for path in args.manifests]  # each checked: one line naming the file
    conflicts, notes = _duplicates(args.manifests, manifests)
    if conflicts:
        raise ValueError(f"{len(conflicts)} videos were converted differently in several manifests: "
                         f"{'; '.join(conflicts[:5])}{' ...' if len(conflicts) > 5 else ''}; "
                         "merge only one conversion of each video")
    merged = merge_manifests(manifests)
    write_manifest(args.output, merged)
    totals = merged["totals"]
    for note in notes:
        print(f"  listed more than once: {note}", file=sys.stderr)
    print(f"wrote {args.output}: {totals['videos']} videos ({totals['failed']} failed), "
          f"{len(merged['missing'])} missing, {len(notes)} listed more than once")
    return 0


def _add_manifest(subparsers) -> None:
    parser = subparsers.add_parser("manifest", help="join the manifests of several conversions",
                                   description="Join manifest.json files of several conversions.")
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    merge = actions.add_parser(
        "merge", help="merge manifest.json files (shards, machines)",
        description="Merge manifest.json files (shards, machines). A video listed by several manifests keeps its "
        "ok entry and is reported; two different ok entries of one video are refused (exit 2).")
    merge.add_argument("manifests", nargs="+", type=Path, help="manifest.json files")
    merge.add_argument("-o", "--output", type=Path, required=True, help="merged manifest to write")
    merge.set_defaults(run=_cmd_manifest)


_COMMANDS: tuple[Callable, ...] = (_add_info, _add_show, _add_scene, _add_fit, _add_depth, _add_emvs, _add_demo,
                                   _add_simulate, _add_manifest)


def build_parser() -> argparse.ArgumentParser:
    """The ``cmax`` argument parser with all sub-commands."""
    from cmax import __version__

    parser = ArgumentParser(
        prog="cmax", description="Event cameras: simulation, file formats, contrast maximization."
    )
    parser.add_argument("--version", action="version", version=f"evtslowtv {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in _COMMANDS:
        add(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``cmax`` console script; returns the exit status.

    A bad argument, and an error a user can fix (a bad or missing file, a value
    out of range: ``ValueError`` including :class:`cmax.io.FormatError`,
    ``TypeError``, ``OSError``), prints ONE line ``cmax COMMAND: error: ...`` on
    stderr and exits with status 2 instead of a traceback; ``cmax --debug ...``
    or ``CMAX_DEBUG=1`` shows the traceback.
    """
    return run_main(build_parser(), None, argv, prog=lambda args: f"cmax {args.command}")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
