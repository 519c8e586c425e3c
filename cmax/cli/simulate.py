"""The ``cmax simulate`` command: videos, image sequences or whole collections to event files (ESIM).

One source (a video, an ECD or rpg_vid2e image folder, a timestamp file) to one h5 file with
``manifest.json`` beside it, or a collection (a folder of videos, a list file, a catalogue's folder) to
DSEC-layout h5 files in a folder; resumable through the manifest, in ``--workers`` processes.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Collection, Sequence

from cmax._args import api_default, library_default, nonnegative_int, positive_float, positive_int, sensor_size
from cmax._signals import Terminated, sigterm_as_interrupt, stop_if_terminated
from cmax.cli._common import given

__all__ = ["add_command", "run"]

#: Where the simulator's defaults live (read only for --help and for options left out).
_ESIM, _CONVERT = "cmax.sim.esim_settings:EsimSettings", "cmax.sim.convert:ConvertSettings"
#: simulate options (dest) -> EsimSettings / ConvertSettings fields; None on the command line = the library's default.
_ESIM_OPTIONS = {"cp": "cp", "cn": "cn", "threshold_sigma": "threshold_sigma", "refractory_us": "refractory_us",
                 "shot_noise": "shot_noise_rate_hz", "leak": "leak_rate_hz", "seed": "seed"}
_CONVERT_OPTIONS = {"size": "size", "adaptive": "adaptive", "lam": "lam", "method": "method", "t0": "t0_s",
                    "t1": "t1_s"}


def run(args: argparse.Namespace) -> int:
    """Convert the input; returns the exit status (1 when a video failed or yielded no events, or a catalogue's
    folder holds none of its videos; 143 after SIGTERM, 129 after SIGHUP, once the clean-up is done)."""
    try:
        with sigterm_as_interrupt():
            status = _run(args)
        stop_if_terminated()     # a SIGTERM whose exception was dropped while the last video was converted
        return status
    except Terminated as stop:
        print(f"cmax simulate: terminated ({stop.name}): the finished videos are kept and listed in the manifest; "
              "a rerun converts the others", file=sys.stderr)
        return stop.status


def _converted(names: set[str]):
    """The ``on_result`` of a conversion: note each finished video in ``names``, then stop if SIGTERM (or SIGHUP)
    came."""
    def record(result) -> None:
        names.add(result.name)
        stop_if_terminated()

    return record


def _run(args: argparse.Namespace) -> int:
    from cmax.sim.catalogue import parse_shard
    from cmax.sim.convert import ConvertSettings, collect_jobs, convert_collection
    from cmax.sim.esim import EsimSettings

    esim = EsimSettings(**given(args, _ESIM_OPTIONS))
    settings = ConvertSettings(esim, **given(args, _CONVERT_OPTIONS), K=_frames_intrinsics(args))
    _check_flow_size(settings, method_given=args.method is not None)
    shard = parse_shard(args.shard) if args.shard else None
    single = _single_input(args)
    if single is not None:
        return _simulate_one(args, single, settings)
    if args.output.exists() and not args.output.is_dir():   # was: "File exists: notes.txt", from the folder's mkdir
        raise FileExistsError(f"-o {args.output} is a file, not a folder: the outputs of {args.input} (NAME.h5 and "
                              "manifest.json) go into a folder; give a folder, or -o NAME.h5 for one video")
    jobs, missing = collect_jobs(args.input, catalogue=args.catalogue, shard=shard)
    if not jobs:  # a catalogue none of whose videos is there: a wrong folder or naming, not a success
        print(f"cmax simulate: error: {_nothing_found(args.input, missing, args.catalogue, args.shard)}",
              file=sys.stderr)
        return 1
    converted: set[str] = set()
    manifest = convert_collection(jobs, args.output, settings, workers=args.workers, missing=missing,
                                  catalogue=args.catalogue, shard=shard, progress=not args.quiet,
                                  on_result=_converted(converted), overwrite=args.overwrite,
                                  chunk_frames=_chunk_frames(args))
    status = _report_manifest(args.output / "manifest.json", manifest, [job.name for job in jobs], converted)
    if missing:
        print(f"  missing from {args.input}: {', '.join(missing)}", file=sys.stderr)
    return status


def _default_chunk_frames() -> int:
    """The library's video frames per kept chunk (:data:`cmax.sim.chunks.DEFAULT_CHUNK_FRAMES`)."""
    from cmax.sim.chunks import DEFAULT_CHUNK_FRAMES

    return DEFAULT_CHUNK_FRAMES


def _chunk_frames(args: argparse.Namespace) -> int | None:
    """``--chunk-frames``: video frames per kept chunk, None for no chunks (0)."""
    return _default_chunk_frames() if args.chunk_frames is None else args.chunk_frames or None


def _frames_intrinsics(args: argparse.Namespace) -> tuple[float, float, float, float] | None:
    """``(fx, fy, cx, cy)`` [px] of the frames from ``--K`` or ``--calib`` (with ``--calib-camera``), or None.

    The output stores a pinhole ``gt/K`` only: a calibration with lens distortion is refused (the events keep the
    lens's distortion, which a fit must undo: give that calibration to cmax fit/emvs/depth instead)."""
    if getattr(args, "calib", None) is None:
        K = getattr(args, "K", None)
        return None if K is None else (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    import numpy as np

    from cmax.io import read_calibration

    calibration = read_calibration(args.calib, args.calib_camera)
    K, distortion = calibration.K, calibration.distortion
    rectified = calibration.rectified_K is not None or calibration.rectification is not None
    if calibration.model == "equidistant" or rectified:
        lens = "an equidistant (fisheye) lens" if calibration.model == "equidistant" else "a lens"
        lens += " and a rectification" if rectified else ""
        raise ValueError(f"{args.calib} ({args.calib_camera}) states {lens}, "
                         "which the output's gt/K (a pinhole K) cannot hold: convert without --calib and give "
                         f"--calib {args.calib} to cmax fit, emvs or depth (it undistorts the events)")
    if distortion is not None and np.any(np.asarray(distortion) != 0):
        raise ValueError(f"{args.calib} states a lens distortion ({', '.join(f'{v:g}' for v in distortion)}), which "
                         "the output's gt/K (a pinhole K) cannot hold: convert without --calib and give "
                         f"--calib {args.calib} to cmax fit, emvs or depth (it undistorts the events)")
    return float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])


def _check_flow_size(settings, *, method_given: bool) -> None:
    """Refuse a ``--size`` smaller than flow interpolation needs before any video is decoded (else every video
    of a folder failed one by one with the library's words)."""
    from cmax.sim.interpolation import MIN_FLOW_SIZE

    if settings.adaptive and settings.method == "flow" and settings.size and min(settings.size) < MIN_FLOW_SIZE:
        width, height = settings.size
        which = "--method flow" if method_given else "--method flow (the default)"
        raise ValueError(f"--size {width}x{height} is smaller than the {MIN_FLOW_SIZE}x{MIN_FLOW_SIZE} pixels that "
                         f"{which} needs: pass --method linear (or --no-adaptive)")


def _nothing_found(folder: Path, missing: Sequence[str], catalogue: str | None, shard: str | None) -> str:
    """Why a catalogue conversion has no video to convert (``missing``: the entries looked for), in one line.

    >>> _nothing_found(Path("slowtv"), ["00000", "00001"], "slowtv", None)[:60]
    'no video to convert: none of the 2 entries of the slowtv cat'
    """
    from cmax.sim.convert import VIDEO_SUFFIXES

    found = sorted(p.name for p in folder.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES) if folder.is_dir() else []
    there = (f"; {folder} holds {len(found)} other video(s): {', '.join(found[:3])}{', ...' if len(found) > 3 else ''}"
             if found else f"; {folder} holds no video")
    part = f" (shard {shard})" if shard else ""
    first = missing[0] if missing else "00000"
    return (f"no video to convert: none of the {len(missing)} entries of the {catalogue} catalogue{part} has a video "
            f"in {folder} (named by index: {first}{VIDEO_SUFFIXES[0]}, ...){there}; nothing was written")


def _single_input(args: argparse.Namespace) -> Path | None:
    """The frame source of a one-file conversion (``-o F.h5``): a video, or an image folder's folder/timestamp
    file; None for a collection (a folder of videos, a list file, a catalogue)."""
    from cmax.sim.convert import VIDEO_SUFFIXES

    _check_output_suffix(args.output)
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
        from cmax.sim.video import bare_stream_problem

        if source.is_file() and (problem := bare_stream_problem(source)) is not None:   # clip.mjpeg
            raise ValueError(problem)
        raise ValueError(f"INPUT must be a video ({', '.join(VIDEO_SUFFIXES)}), an image folder with images.txt or "
                         "images/ (or imgs/) + timestamps.txt, or a timestamp file when OUTPUT is one .h5 file, "
                         f"got {source}")
    from cmax.sim.video import avi_rate_problem, mp4_timing_problem

    if source.is_file() and (problem := avi_rate_problem(source) or mp4_timing_problem(source)) is not None:
        raise ValueError(problem)                         # no frame rate or durations: the times would be made up
    return source


#: Image sub-folders beside a timestamps.txt: ESIM's ``images/``, rpg_vid2e's upsampler's ``imgs/``.
_IMAGE_SUBFOLDERS = ("images", "imgs")
#: Suffixes of HDF5 files (compared in lower case); cmax simulate writes ``.h5`` only.
_H5_SUFFIXES = (".h5", ".hdf5", ".hdf", ".he5")


def _check_output_suffix(output: Path) -> None:
    """Refuse ``-o`` ending in an HDF5 suffix other than ``.h5`` (``x.hdf5``, ``X.H5``): taken for a folder, it
    made a folder of that name. The outputs are named ``<stem>.h5`` (the manifest's entries), so the suffix is
    not kept either.

    >>> _check_output_suffix(Path("clip.hdf5"))
    Traceback (most recent call last):
    ...
    ValueError: -o clip.hdf5: cmax simulate writes .h5 files (manifest entries are NAME.h5): give -o clip.h5
    """
    if output.suffix != ".h5" and output.suffix.lower() in _H5_SUFFIXES:
        raise ValueError(f"-o {output}: cmax simulate writes .h5 files (manifest entries are NAME.h5): give -o "
                         f"{output.with_suffix('.h5')}")


def _image_folder(source: Path) -> Path | None:
    """The path :func:`cmax.sim.video.open_source` reads for an image sequence, or None if ``source`` is none.

    * ECD: a folder holding ``images.txt`` (lines ``t images/frame_00000000.png``), that file, or the
      folder of images with ``images.txt`` in its parent;
    * rpg_vid2e / ESIM: a folder holding ``images/`` (rpg_vid2e's upsampler: ``imgs/``) and ``timestamps.txt``,
      a folder of images with ``timestamps.txt`` in it or in its parent, or the ``timestamps.txt`` file.

    A folder of images (and no videos) with neither is a ValueError that says how to write the times.
    """
    from cmax.sim.video import IMAGE_SUFFIXES

    if source.is_file():
        for images in _IMAGE_SUBFOLDERS:
            if source.name == "timestamps.txt" and (source.parent / images).is_dir():
                return source.parent / images
        return source if source.name in ("images.txt", "timestamps.txt") else None
    if not source.is_dir():
        return None
    if (source / "images.txt").is_file():
        return source / "images.txt"
    for images in _IMAGE_SUBFOLDERS:
        if (source / images).is_dir() and (source / "timestamps.txt").is_file():
            return source / images
    if not any(p.suffix.lower() in IMAGE_SUFFIXES for p in source.iterdir()):
        return None
    if (source / "timestamps.txt").is_file():
        return source
    if (source.parent / "images.txt").is_file():   # ECD's images/ (its lines name them from the parent)
        return source.parent / "images.txt"
    if (source.parent / "timestamps.txt").is_file():
        return source
    from cmax.sim.convert import VIDEO_SUFFIXES

    names = [p.suffix.lower() for p in source.iterdir()]
    if any(suffix in VIDEO_SUFFIXES for suffix in names):
        return None                                  # videos beside the images: a collection
    count = sum(suffix in IMAGE_SUFFIXES for suffix in names)
    raise ValueError(f"{source} holds {count} images but no times for them: write timestamps.txt beside them (one "
                     "time in seconds per image, in name order, as rpg_vid2e/ESIM do; or images.txt as ECD), e.g. at "
                     f"25 frames/s: python -c \"print('\\n'.join(f'{{i / 25:.6f}}' for i in range({count})))\" > "
                     f"{source / 'timestamps.txt'}")


def _simulate_one(args: argparse.Namespace, source: Path, settings) -> int:
    """``cmax simulate SOURCE -o F.h5``: one conversion with progress and a manifest beside F.h5."""
    from cmax.sim.chunks import chunk_folder
    from cmax.sim.convert import VideoJob, convert_collection, load_manifest

    output = args.output
    manifest_path = output.parent / "manifest.json"
    manifest = load_manifest(manifest_path) if manifest_path.is_file() else None
    listed = manifest["videos"].get(output.stem) if manifest else None
    # with kept chunks beside it, the file may be this conversion's, written from them and then killed: the
    # conversion checks that under the folder's lock (refused unless it is)
    if (output.exists() and not args.overwrite and not (listed and listed.get("status") == "ok")
            and not chunk_folder(output).is_dir() and not output.is_dir()):   # a folder: refused for what it is below
        raise FileExistsError(f"{output} exists and is not a finished conversion of {manifest_path}; "
                              "pass --overwrite to replace it")
    job = VideoJob(output.stem, source)
    # --overwrite: the old entry is dropped under the folder's lock once the settings match (a refused run
    # changes nothing); the old file is replaced atomically when the new one is complete.
    converted: set[str] = set()
    manifest = convert_collection([job], output.parent, settings, workers=1, progress=not args.quiet,
                                  redo=[job.name] if args.overwrite else (), overwrite=args.overwrite,
                                  on_result=_converted(converted), chunk_frames=_chunk_frames(args))
    return _report_manifest(manifest_path, manifest, [job.name], converted)


def _report_manifest(path: Path, manifest: dict, names: Sequence[str], converted: Collection[str]) -> int:
    """Print the outcome of a conversion (outputs as paths in the folder of ``path``, the manifest): first one
    line saying what this run did (videos of ``names`` converted, skipped as already converted, failed), then
    what the folder's manifest holds (other runs' videos too); 1 when a video of this run (``names``) failed or
    yielded no events, else 0. Videos of ``names`` not in ``converted`` were skipped (an earlier run converted
    them; output and source verified) and are said to be. Failures the manifest holds from other runs into the
    same folder are counted in one line, not in the status."""
    from cmax.sim.convert import entry_output

    totals, videos = manifest["totals"], manifest["videos"]
    done = [name for name in names if videos.get(name, {}).get("status") == "ok"]
    made = [name for name in done if name in converted]
    empty = [name for name in done if videos[name].get("events", 0) == 0]
    failed = [name for name in names if videos.get(name, {}).get("status", "ok") != "ok"]
    made_events = sum(int(videos[name].get("events", 0)) for name in made)
    note = f", {len(empty)} with no events" if empty else ""
    videos_ok = f"{totals['ok']} video{'' if totals['ok'] == 1 else 's'} ok"
    print(f"this run: converted {len(made)} video{'' if len(made) == 1 else 's'} ({made_events:,} events), "
          f"{len(done) - len(made)} skipped (done before, verified), {len(failed)} failed{note}; {path} holds "
          f"{videos_ok}, {totals['failed']} failed, {totals['events']:,} events")
    for name in names:
        entry = videos.get(name, {})
        if entry.get("status") == "ok" and name not in empty:
            done = "" if name in converted else f"already converted from {entry['source']} (verified), "
            print(f"  {entry_output(entry, path.parent)}: {done}{entry['events']:,} events from {entry['frames']} "
                  f"frames ({entry['samples']} samples), {entry['duration_s']:.2f} s of video")
    for name in failed:
        print(f"  failed {name}: {videos[name]['error']}", file=sys.stderr)
    others = sorted(name for name, entry in videos.items() if entry["status"] != "ok" and name not in failed)
    if others:
        print(f"  ({len(others)} other video(s) of {path.name} failed in earlier runs: {', '.join(others[:5])}"
              f"{', ...' if len(others) > 5 else ''})", file=sys.stderr)
    for name in empty:
        entry = videos[name]
        print(f"  no events from {name}: {entry['frames']} frame(s) over {entry['duration_s']:.3f} s "
              f"(events need at least two frames that differ by a threshold); {entry_output(entry, path.parent)} "
              "holds 0 events",
              file=sys.stderr)
    return 1 if failed or empty else 0


def add_command(subparsers) -> argparse.ArgumentParser:
    """Add ``simulate`` to an ``argparse`` sub-parser collection; returns the new parser."""
    parser = subparsers.add_parser(
        "simulate", help="convert videos or image sequences to event files (ESIM), one or a whole collection",
        description="Convert a video file, an image folder (ECD: images.txt; rpg_vid2e/ESIM: images/ or imgs/ + "
        "timestamps.txt) or a timestamp file to one h5 file (-o F.h5, with manifest.json beside it); or a "
        "folder of videos, a list file (one video per line, optional tab and category) or a catalogue's "
        "folder (--catalogue slowtv) to DSEC-layout h5 files in the folder -o, with manifest.json; "
        "resumable (finished videos are verified and skipped; a video killed part-way continues from its last "
        "kept chunk, see --chunk-frames), in --workers processes. Exit status 1 when a video fails or yields no events, or when "
        "none of a catalogue's videos (of its shard) is found.",
    )
    parser.unknown_hints = {"--resume": "cmax simulate resumes by itself: run the same command again (the finished "
                                        "videos are verified and skipped, a video stopped part-way continues from "
                                        "its kept chunks)"}
    parser.add_argument("input", type=Path,
                        help="video file, image folder, timestamp file, folder of videos, or list file")
    parser.add_argument("-o", "--output", type=Path, required=True, help="output .h5 file or folder")
    # Simulator settings are validated by EsimSettings / ConvertSettings (one-line errors naming the value).
    esim = (("--cp", float, "cp", "ON threshold [log intensity]"), ("--cn", float, "cn", "OFF threshold [log intensity]"),
            ("--threshold-sigma", float, "threshold_sigma", "per-pixel threshold mismatch: standard deviation, a fraction of --cp/--cn"),
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
    api_default(parser.add_argument("--lam", type=float, default=None, help="lambda of adaptive sampling: the largest change of a pixel's log intensity between frames, a fraction of min(--cp, --cn)"),
                library_default(_CONVERT, "lam"))
    api_default(parser.add_argument("--method", choices=("flow", "linear"), default=None,
                                    help="interpolation of adaptive sampling"), library_default(_CONVERT, "method"))
    parser.add_argument("--t0", type=float, default=None,
                        help="start, seconds after each video's (or image sequence's) first frame, whatever clock "
                        "its times are on (default: its start)")
    parser.add_argument("--t1", type=positive_float, default=None,
                        help="end, seconds after the first frame, after --t0 (default: its end)")
    from cmax.cli.recording import intrinsics_argument

    camera = parser.add_mutually_exclusive_group()
    camera.add_argument("--K", type=intrinsics_argument, default=None,
                        help="pinhole intrinsics fx,fy,cx,cy [px] of the frames as stored (before --size): each "
                        "output stores them as gt/K, scaled to its pixels, which cmax fit/emvs/depth read without "
                        "--K (default: none stored)")
    camera.add_argument("--calib", type=Path, default=None,
                        help="calibration file of the frames instead of --K: ECD calib.txt (fx fy cx cy, no "
                        "distortion), DSEC cam_to_cam.yaml or a Kalibr camchain .yaml (the camera --calib-camera); "
                        "one with lens distortion is refused (default: none)")
    parser.add_argument("--calib-camera", default="cam0", metavar="NAME",
                        help="camera of --calib's .yaml: cam0, camRect0, cam1, ... (default cam0)")
    parser.add_argument("--workers", type=positive_int, default=1, help="parallel processes (one video each)")
    parser.add_argument("--catalogue", choices=("slowtv",), default=None,
                        help="INPUT is the folder of a catalogue's videos named by index (00000.mp4) (default: none, INPUT is "
                        "a video, an image folder, a folder of videos or a list file)")
    parser.add_argument("--shard", default=None, metavar="i/n",
                        help="convert shard i of n (0-based; default: all)")
    api_default(parser.add_argument(
        "--chunk-frames", type=nonnegative_int, default=None, metavar="N",
        help="keep each video's events in chunks of N video frames (in .NAME.h5.chunks beside its output, removed "
        "when it is done), so that a killed conversion continues from its last chunk when run again, with the "
        "same events, bit for bit; 0: no chunks, a killed video starts over"), _default_chunk_frames)
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing output .h5 (-o F.h5: convert it again); a folder: replace the "
                        "files at its videos' outputs that its manifest does not list; and start over the videos "
                        "whose kept chunks are of another video or settings (each refused without it; chunks of "
                        "the same video and settings are continued: the same events)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.set_defaults(run=run)
    return parser
