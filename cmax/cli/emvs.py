"""The ``cmax emvs`` command: semi-dense depth of a recording from known poses (EMVS).

Registered by :func:`cmax.cli.build_parser` through :func:`add_command`; :func:`run` runs it.

Outputs in ``-o outdir/``: ``depth.npz`` (``depth``, ``confidence``, ``mask``,
``t_ref_us``, ``T_w_ref``, ``K``, ``depth_range``), ``depth.png`` (confidence
and coloured depth with a scale bar in metres; titled ``up to scale``, the bar without a unit, for poses up
to scale), ``points.ply`` (the
semi-dense point cloud in the world frame) and, moved in last, ``summary.json`` (the run's record of
completion: its input, settings and files, with what the run was -- its input files' signatures, options and code
-- and each result's size and SHA-256, so that ``--resume`` of the same run finds it complete; a folder without it
holds no complete run, :mod:`cmax.io.run_folder`); one summary line on stdout. The poses come from
``--poses`` (a TUM file) or, without it, from the ground truth an h5 file stores (``gt/poses``,
``gt/poses_t``: what ``cmax scene`` writes).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from cmax._args import api_default, float_list, int_at_least, nonnegative_float
from cmax.camera import intrinsics_oddity
from cmax.cli._common import named_pixels, output_folder
from cmax.cli.recording import (add_camera_options, add_file_options, calibration_hint, calibration_note,
                                calibration_of, check_file_principal_point, given_k_note, no_intrinsics_message,
                                overlap, read_calibrated)
from cmax.io import Calibration, run_folder
from cmax.io.atomic import save_npz_atomic, write_text_atomic
from cmax.io.provenance import file_depth_range, file_intrinsics, resized_note

#: ``cmax emvs`` notes the share of the depth map on the nearest or farthest plane from this share on.
EMVS_BOUND_NOTE = 0.05
#: The files a run writes into ``-o`` (``summary.json``, its record of completion, last).
RESULTS = ("depth.npz", "depth.png", "points.ply", "summary.json")

__all__ = ["RESULTS", "add_command", "run", "camera_for", "earlier_results", "file_trajectory", "run_record"]

_range_numbers = float_list((2,), "--depth-range (near,far)")


def _depth_range(text: str) -> tuple[float, ...]:
    """``argparse`` type of ``--depth-range NEAR,FAR`` [m]: two finite numbers with 0 < NEAR < FAR."""
    near, far = _range_numbers(text)
    if not 0 < near < far:
        raise argparse.ArgumentTypeError(f"--depth-range must be NEAR,FAR with 0 < NEAR < FAR [m], got {text!r}")
    return near, far


#: ``argparse`` type of ``--planes``: EMVS needs two depth planes at least.
_planes = int_at_least(2)


def _emvs_default(name: str):
    def default():
        from cmax.emvs import EMVS

        return EMVS.__dataclass_fields__[name].default
    return default


def add_command(subparsers) -> argparse.ArgumentParser:
    """Add ``emvs`` to an ``argparse`` sub-parser collection; returns the new parser."""
    parser = subparsers.add_parser(
        "emvs", help="semi-dense depth from events and known poses (EMVS space sweep)",
        description="EMVS (Rebecq et al., IJCV 2018): vote the events into a Disparity Space Image on the "
        "reference view at the middle of their time span, using the poses of a TUM trajectory file "
        "(t[s] tx ty tz qx qy qz qw, camera-to-world, on the events' clock: what `cmax fit` writes, or "
        "ground truth) or, without --poses, the file's own gt/poses (cmax scene); write depth.npz, depth.png, "
        "points.ply and, last, summary.json (a folder without it holds no complete run) to the output folder.")
    parser.add_argument("file", type=Path, help="event file (any format cmax.io.read reads)")
    parser.add_argument("--poses", type=Path, default=None,
                        help="TUM trajectory file (default: gt/poses of an h5 file, as cmax scene writes it)")
    parser.add_argument("-o", "--output", required=True, type=Path, help="output folder")
    add_camera_options(parser)
    api_default(parser.add_argument("--depth-range", type=_depth_range, default=None, metavar="NEAR,FAR",
                                    help="depth range of the planes [m]: the scene's own range when the file "
                                    "records one (cmax scene), else"), _emvs_default("depth_range"))
    api_default(parser.add_argument("--planes", type=_planes, default=None, help="number of depth planes (>= 2)"),
                _emvs_default("n_planes"))
    parser.add_argument("--t0", type=nonnegative_float, default=None,
                        help="start, seconds after the first event (default: the first event)")
    parser.add_argument("--t1", type=nonnegative_float, default=None,
                        help="end, seconds after the first event (default: the last event)")
    parser.add_argument("--keep-hot-pixels", action="store_true",
                        help="every event votes; by default the events of hot pixels (far more events than the "
                             "scene's edges give any pixel, or firing alone at a steady rate: a defect; or locked to a "
                             "100/120 Hz mains flicker: a lamp) do not, and a note names "
                             "them (cmax.EMVS.hot_pixels)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the results of an earlier run in -o (else refused); they stay until this run "
                             "has written all of its own")
    parser.add_argument("--resume", action="store_true",
                        help="for a requeued job: when -o holds the complete results of the same run (the same "
                             "event, --poses and --calib files by their SHA-256, the same options and code), with "
                             "every result file as it was written, do nothing and exit 0; when some of them are "
                             "missing or changed, run again and replace them; else run as without it (default: "
                             "off; complete results of another run are refused, as without it)")
    parser.add_argument("--quiet", action="store_true",
                        help="no progress bar (shown only when stderr is a terminal)")
    add_file_options(parser)   # --size, --time-unit, --polarity
    parser.set_defaults(run=run)
    return parser


def camera_for(path: Path, width: int, height: int, K: np.ndarray | None, calibration: Calibration):
    """The :class:`cmax.Camera` of a recording of a ``width`` x ``height`` [px] sensor: ``--K`` (3, 3) [px] or, for
    an h5 file, its ``gt/K``, with the distortion (and rectification) of ``calibration``
    (:func:`cmax.cli.recording.calibration_of`); ValueError when its principal point lies outside the sensor
    (another size's K, as ``cmax fit``)."""
    name = "K"
    if K is None:
        K = file_intrinsics(path)
        if K is None:
            raise ValueError(no_intrinsics_message(path))
        name = f"{path}: gt/K"
    check_file_principal_point(K, path, width, height, name)
    return calibration.camera(width, height, K)


def file_trajectory(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """``(times_us (M,) int64, T_w_c (M, 4, 4))``: the ground-truth poses ``gt/poses_t``, ``gt/poses`` of an h5
    file (as ``cmax scene`` writes them, on the clock :func:`cmax.io.read` gives its events); None when the file
    is not h5 or stores none. Validated by :func:`cmax.emvs.poses.as_trajectory`."""
    import h5py

    from cmax.emvs.poses import as_trajectory

    try:
        with h5py.File(path, "r") as file:
            if "gt" not in file or "poses" not in file["gt"] or "poses_t" not in file["gt"]:
                return None
            times, poses = np.asarray(file["gt/poses_t"][()]), np.asarray(file["gt/poses"][()])
    except OSError:                     # not an h5 file
        return None
    return as_trajectory((times, poses), name=f"{path}: gt/poses")


def run(args: argparse.Namespace) -> int:
    """Run the command; returns the exit status. The results are written as ``cmax fit`` writes its own
    (:func:`cmax.io.run_folder.staged_run`): a folder with an earlier run's results (of ``cmax emvs``, ``cmax fit``
    or ``cmax depth``) is refused without ``--overwrite``, a second run into the same folder meanwhile (of any of
    them) is refused, a failed run changes nothing, and one interrupted while its files move in leaves no
    summary.json. With ``--resume``, complete results of the same run in the folder are left as they are (one line,
    exit 0: :func:`cmax.io.run_folder.check_complete`); the same run's results with a file missing or changed are
    made again."""
    from cmax.emvs import read_tum_trajectory
    from cmax.io.window_store import PendingSignatures, code_digest

    out = output_folder(args.output, "depth.npz, depth.png and points.ply")
    trajectory = None if args.poses is None else read_tum_trajectory(args.poses)   # a bad file: before the events
    hashing = None
    try:
        with run_folder.staged_run(out, "emvs", earlier_results, overwrite=args.overwrite, what=", ".join(RESULTS),
                                   why="that this run would replace", resume=args.resume) as stage:
            # the input files are hashed while EMVS runs; a --resume into complete results waits for them first
            hashing = PendingSignatures(_input_paths(args), progress=not args.quiet)
            options, code = argparse.Namespace(**vars(args)), code_digest("cmax")

            def record() -> dict:   # waits for the input files' signatures
                return run_record(options, hashing.result(), code=code)

            complete = run_folder.resumed_into_complete(out, resume=args.resume, overwrite=args.overwrite)
            if complete is not None:   # the same run has nothing to do (or its damaged files are made again)
                damaged = run_folder.check_complete(out, complete, record(), command="cmax emvs")
                print(f"cmax emvs: note: {damaged}", file=sys.stderr)
            return _emvs_into(stage, out, args, trajectory, record)
    except run_folder.ResultsComplete as complete:   # --resume of a run whose results are all in out
        print(complete)
        return 0
    finally:
        if hashing is not None:    # stopped within one block, never left running
            hashing.close()


#: The options of ``cmax emvs`` that change no result: left out of :func:`run_record`.
_NOT_RESULTS = ("command", "output", "quiet", "overwrite", "resume", "run", "debug")


def _input_paths(args: argparse.Namespace) -> dict:
    """The input files of a run of ``cmax emvs`` by the name its record gives them (None: not given)."""
    return {"file": args.file, "poses": args.poses, "calib": args.calib}


def run_record(args: argparse.Namespace, files: dict, *, code: str) -> dict:
    """What a run of ``cmax emvs`` is, recorded in its ``summary.json`` (``"run"``) for ``--resume`` to compare
    (:func:`cmax.io.run_folder.check_complete`): the version of cmax and ``code``, the digest of its code
    (:func:`cmax.io.window_store.code_digest`), the signatures ``files`` (size, modification time, SHA-256:
    :func:`cmax.io.window_store.file_signatures`) of the event file, ``--poses`` and ``--calib``, and every other
    option of ``args`` (the parsed options; the paths of those files only through their signatures, so that a
    moved file, the same bytes, is the same run).

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.
    files : dict
        The input files' signatures by name (``file``, ``poses``, ``calib``; None: not given).
    code : str
        The digest of cmax's code.
    """
    from cmax.io.window_store import command_record

    return command_record(args, files, code=code, ignored=_NOT_RESULTS)


def summary_units(scale_known: bool) -> dict[str, str]:
    """The units and frames of what ``cmax emvs`` writes, keyed by field (``summary.json``'s ``units``, as
    ``cmax fit`` and ``cmax depth`` write their own). Lengths are metres when ``scale_known`` (ground-truth
    poses, or a trajectory of ``cmax fit`` with ``--speed``), else the poses' own unit.

    >>> summary_units(False)["depth_range, median_depth_m"][:40]
    "the poses' unit, not metres (up to scale"
    """
    length = "m" if scale_known else ("the poses' unit, not metres (up to scale: a cmax fit trajectory without "
                                      "--speed, metres at a speed of 1 m/s)")
    return {
        "t_ref_us": "µs on the file's clock: the reference view's time, the middle of the events' span",
        "depth_range, median_depth_m": length,
        "mask_pixels": "px: the pixels of depth.npz's mask",
        "depth.npz": f"depth (H, W) [{length}]: z-depth seen from the reference view, valid where mask; confidence "
                     "(H, W): the DSI's maximum per pixel [votes]; T_w_ref (4, 4): the reference camera to the "
                     f"poses' world, translation [{length}]; t_ref_us [µs]; K [px]: the DSI's pinhole (with a "
                     f"rectifying --calib: the rectified frame's); depth_range [{length}]",
        "points.ply": f"x y z [{length}], the world frame of the poses",
    }


def earlier_results(out: Path) -> list[Path]:
    """The files of an earlier ``cmax emvs`` in the folder ``out`` (:data:`RESULTS`); empty when none (or no folder)."""
    return run_folder.run_results(out, ("emvs",))


def _emvs_into(stage: Path, out: Path, args: argparse.Namespace, trajectory, record) -> int:
    """:func:`run`'s work once ``out`` is held: read the events, run EMVS, write :data:`RESULTS` into the empty
    folder ``stage`` (moved into ``out`` by :func:`run`), ``summary.json`` with the run's ``record()``
    (:func:`run_record`); returns the exit status."""
    from cmax import viz
    from cmax.emvs import EMVS
    from cmax.emvs.poses import trajectory_up_to_scale

    calibration = calibration_of(args)
    K, calib_size = calibration.K, calibration.size
    if (unlike := given_k_note(args.file, K)) is not None:
        print(f"cmax emvs: note: {unlike}", file=sys.stderr)
    if args.calib is not None and (said := calibration_note(calibration, args.calib, args.calib_camera, args.file)):
        print(f"cmax emvs: note: {said}", file=sys.stderr)
    events, _ = read_calibrated(args, calib_size)    # --t0 / --t1 applied
    if trajectory is None:
        trajectory = file_trajectory(args.file)
        if trajectory is None:
            raise ValueError(f"{args.file} stores no poses (gt/poses): give them with --poses traj.txt (TUM: "
                             "t[s] tx ty tz qx qy qz qw, camera-to-world, e.g. the trajectory.txt of cmax fit)")
    events, cut = overlap(events, trajectory[0], "poses", args.poses or f"{args.file}: gt/poses",
                          "EMVS on the overlap")
    if cut:
        print(f"cmax emvs: note: {cut}", file=sys.stderr)
    camera = camera_for(args.file, events.width, events.height, K, calibration)
    if (odd := intrinsics_oddity(camera.K, camera.width, camera.height)) is not None:   # as cmax fit warns
        resized = resized_note(args.file)
        print(f"cmax emvs: note: {odd}" + (f"; {resized}" if resized else ""), file=sys.stderr)
    metric = args.poses is None or not trajectory_up_to_scale(args.poses)
    depth_range = args.depth_range
    if depth_range is None:
        depth_range = file_depth_range(args.file)
        if depth_range is not None:
            print(f"cmax emvs: note: planes over {depth_range[0]:g}-{depth_range[1]:g} m, the depth range the file "
                  "records for its scene (--depth-range to change it)", file=sys.stderr)
        else:   # said: cmax fit searched its own, wider default; the planes should span the scene's depths
            near, far = EMVS.depth_range
            print(f"cmax emvs: note: planes over {near:g}-{far:g} {'m' if metric else '(up to scale)'}, EMVS's "
                  "default depth range: --depth-range NEAR,FAR gives the scene's (after cmax fit, the range it "
                  "searched: its summary.json's depth_range)", file=sys.stderr)
    options = {key: value for key, value in (("depth_range", depth_range), ("n_planes", args.planes))
               if value is not None}   # None: EMVS's own default
    if args.keep_hot_pixels:
        options["hot_pixels"] = None
    if hint := calibration_hint(args):
        print(f"cmax emvs: note: {hint}", file=sys.stderr)
    if not metric:
        print(f"cmax emvs: note: the poses of {args.poses} are up to scale (its header says so: cmax fit without "
              "--speed moves each window at 1 m/s): the depths, the planes' range and points.ply are in the "
              "trajectory's unit, not metres", file=sys.stderr)
    progress = not args.quiet and sys.stderr.isatty()   # a bar in a terminal, not in a log
    result = EMVS(camera, progress=progress, **options).run(events, trajectory)
    save_npz_atomic(stage / "depth.npz", depth=result.depth, confidence=result.confidence, mask=result.mask,
              t_ref_us=np.int64(result.t_ref_us), T_w_ref=result.T_w_ref, K=result.K,
              depth_range=np.array(result.depth_range))
    result.plot(stage / "depth.png", zoom=viz.readable_zoom(events.width), metric=metric)   # small sensors enlarged
    result.save_ply(stage / "points.ply")
    depths = result.depth[result.mask]
    median_m = float(np.median(depths)) if depths.size else None
    from cmax.cli.recording import camera_read
    from cmax.io import detect_format

    record = {"command": "emvs", "file": str(args.file),
              "camera": camera_read(detect_format(args.file), getattr(args, "camera", None)), "poses": str(args.poses or f"{args.file}: gt/poses"),
              "events": len(events), "t_ref_us": int(result.t_ref_us), "n_planes": int(result.n_planes),
              "depth_range": [float(v) for v in result.depth_range], "mask_pixels": int(result.mask.sum()),
              "median_depth_m": median_m, "scale_known": metric, "files": list(RESULTS),
              "units": summary_units(metric), "run": record(),
              run_folder.OUTPUTS_KEY: run_folder.output_records(stage)}
    write_text_atomic(stage / "summary.json", json.dumps(record, indent=2) + "\n")   # moved in last (publish)
    if len(result.hot_pixels):
        print(f"cmax emvs: note: {len(result.hot_pixels)} hot pixel(s) fire without motion (far more than the "
              f"scene's edges make any pixel fire, alone at a steady rate, or with a lamp's 100/120 Hz flicker) "
              f"({named_pixels(result.hot_pixels)}): their events did not vote (--keep-hot-pixels keeps "
              "them)", file=sys.stderr)
    for end, share in result.on_bounds().items():
        if share >= EMVS_BOUND_NOTE:
            plane = result.depth_range[0 if end == "near" else 1]
            print(f"cmax emvs: note: {share:.1%} of the depth map lies on the {end} plane ({plane:g} "
                  f"{'m' if metric else 'up to scale'}): the range's "
                  f"end rather than a measurement (the scene {'nearer' if end == 'near' else 'farther'} than the "
                  f"range, or too little parallax to tell); --depth-range widens it", file=sys.stderr)
    median = "n/a" if median_m is None else f"{median_m:.3f} {'m' if metric else '(up to scale)'}"
    print(f"emvs: {len(events):,} events, {result.n_planes} planes, {int(result.mask.sum()):,} px in the mask "
          f"({result.mask.mean():.1%}), median depth {median}, {result.seconds:.2f} s "
          f"({len(events) / max(result.seconds, 1e-9) / 1e6:.3g} Mev/s); results in {out}")
    return 0
