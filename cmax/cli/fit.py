"""The ``cmax fit`` command: fit a recording window by window and write depth, trajectory and summary.

Registered by :func:`cmax.cli.build_parser` through :func:`add_command`; :func:`run` runs it.

Outputs in ``-o outdir/``: ``depth_XXXXX.npz`` (``depth``, ``mask``,
``depth_spread``, ``inverse_depth_grid``, ``t_ref_us``, ``K``) and ``depth_XXXXX.png`` per
window (se3; the map with a colour bar in metres, unlabelled without ``--speed``), ``trajectory.txt`` in TUM format (``t[s] tx ty tz qx qy qz qw``,
camera-to-world, the first window's start as the origin; ``#`` lines on top state the frame and the unit of the
translation: metres with ``--speed``, else up to scale, each window at 1 m/s) and
``summary.json`` (settings, per-window twist, objective, parallax, seconds, quality verdict with its
reason, low-motion cause and alternatives, the counts of each verdict, the starts of the windows
skipped for too few events, across which the trajectory carries the last fitted twist, and the end of the
recording after the last whole window, not fitted: a note says so; every note printed, and the warnings, once per
kind with how often they came). Each window's verdict is printed on a line of its own and counted in the summary
line (``docs/quality.md``); the exit status is 1 when no window was fitted or every fitted one failed.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import warnings
from pathlib import Path

import numpy as np

from cmax._args import (add_duration_options, api_default, float_list, grid_shape, library_default, positive_float,
                        positive_int)
from cmax.cli._common import named_pixels, output_folder
from cmax.cli.recording import (StreamedEvents, add_camera_options, add_recording_arguments, calibration_hint,
                                calibration_note, calibration_of, camera_read, check_file_principal_point, event_span,
                                given_k_note, no_intrinsics_message, open_streamed, overlap, read_calibrated,
                                tail_note)
from cmax.io import run_folder
from cmax.io.atomic import save_npz_atomic, write_text_atomic
from cmax.io.provenance import file_depth_range, file_intrinsics
from cmax.io.window_store import (WINDOWS_FOLDER, PendingSignatures, WindowStore, code_digest, command_record,
                                  file_signatures, interrupted_windows, stopped_line)

__all__ = ["OPTION_OF_SETTING", "add_command", "advice", "completed_status", "earlier_results", "grouped_warnings",
           "hot_pixel_note", "option_words", "run", "run_record", "tum_lines", "unscaled_range_note",
           "unmapped_pixels", "verdict_counts", "window_line"]

#: A run's private folders ``-o/.fit.<16 hex>.partial`` (:func:`cmax.io.run_folder.staged_run`).
_STAGE_PREFIX = "fit"
#: A whole DSEC-layout h5 file (no ``--t0`` / ``--t1``) with more events than this (2**25, about 440 MB of them) is
#: fitted window by window from the file, holding one window at a time, not read whole first (the fits are the same).
STREAM_ABOVE_EVENTS = 1 << 25


def add_command(subparsers) -> argparse.ArgumentParser:
    """Add ``fit`` to an ``argparse`` sub-parser collection; returns the new parser."""
    parser = subparsers.add_parser(
        "fit", help="depth and motion per window by contrast maximization",
        description="Depth and motion of every window of an event file by contrast maximization (cmax.fit_sequence), "
        "each with a verdict (ok, ambiguous, low parallax, failed, and why): depth_00000.npz and .png per window (depth "
        "[m], up to scale without --speed), trajectory.txt (TUM, camera-to-world) and, last, summary.json in the "
        "output folder (docs/fitting.md).")
    parser.add_argument("file", type=Path, help="event file (any format cmax.io.read reads)")
    add_camera_options(parser, distortion_help=": each event is warped from its undistorted position (unrounded)")
    parser.add_argument("-o", "--output", required=True, type=Path, help="output folder")
    add_recording_arguments(parser)
    api_default(parser.add_argument("--depth-range", type=float_list((2,), "--depth-range (near,far)"), default=None,
                                    metavar="NEAR,FAR", help="se3: depth bounds [m] (in units of --speed x 1 s "
                                    "without it; give the scene's own range when known): the range the file "
                                    "records for its scene (cmax scene), else"),
                _settings_default("depth_range"))
    api_default(parser.add_argument("--model", choices=("se3", "rotation", "flow"), default=None,
                                    help="motion model"), _sequence_default("model"))
    add_duration_options(parser, "window", dest="window_ms", unit="ms", help="window length",
                         default=lambda: _sequence_default("window_us")() / 1000)
    api_default(parser.add_argument("--min-events", type=positive_int, default=None,
                                    help="windows with fewer events are skipped, not fitted (at least 10; a sparse "
                                         "recording: a lower value or a longer --window-ms)"),
                _sequence_default("min_events"))
    add_duration_options(parser, "step", dest="step_ms", unit="ms", help="step between window starts",
                         default="the window length")
    parser.add_argument("--speed", type=positive_float, default=None,
                        help="known speed [m/s] (metric depth; default: unknown, depth up to scale)")
    parser.add_argument("--gyro", type=Path, default=None,
                        help="gyroscope samples (se3): an .aedat4 file (its IMU stream) or a text file of "
                             "'t wx wy wz' lines [s, rad/s], camera axes (turned into the rectified frame with a "
                             "rectifying --calib), the events' clock; each window's "
                             "rotation is held at their mean, only direction and depth are fitted (default: none, the rotation is fitted)")
    parser.add_argument("--gyro-axes", default=None, metavar="AXES",
                        help="the camera's x,y,z as signed axes of --gyro's IMU, e.g. --gyro-axes=-x,y,-z (with '=': "
                             "the value starts with '-') (default: a DAVIS's AEDAT4 IMU is turned by -x,y,-z, as "
                             "rpg_dvs_ros does; another camera's must be stated; a text file is in camera axes already)")
    parser.add_argument("--omega", type=float_list((3,), "--omega (wx,wy,wz)"), default=None, metavar="WX,WY,WZ",
                        help="se3: a known, constant angular velocity [rad/s] of every window, camera axes (turned "
                             "into the rectified frame with a rectifying --calib) (e.g. "
                             "0,0,0 for a linear stage or a straight drive): held like --gyro's, only direction and "
                             "depth are fitted; not with --gyro (default: none, the rotation is fitted)")
    parser.add_argument("--zero-rotation-start", action="store_true",
                        help="se3: also start the motion refinement from the flows explained without rotation "
                             "and keep the better (vehicles: on a forward drive it found forward motion where the "
                             "default ended at a pitching plane; one more refinement per window)")
    api_default(parser.add_argument("--polish", choices=("none", "depth", "depth_motion"), default=None,
                                    help="se3: end each window on the objective the network trains on "
                                         "(cmax.contrast.SHARED_OBJECTIVE; the depth grid, or it and the motion; "
                                         "cmax.FitSettings.polish): a few seconds more per window, docs/fitting.md"),
                lambda: _settings_default("polish")().value)
    api_default(parser.add_argument("--depth-grid", type=grid_shape, default=None, metavar="ROWS,COLS",
                                    help="se3: nodes of the inverse-depth grid, at most the sensor's rows and columns "
                                         "(cmax.fit(depth_grid=))"), _fit_default("depth_grid"))
    api_default(parser.add_argument("--solver", choices=("scipy", "casadi", "torch"), default=None,
                                    help="optimisation back end"), _fit_default("solver"))
    parser.add_argument("--jobs", type=positive_int, default=1,
                        help="worker processes: above 1 the windows are fitted in parallel, each from a cold start "
                             "(cmax.fit_sequence(jobs=, warm_start=False))")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    api_default(parser.add_argument("--members", type=positive_int, default=None,
                                    help="se3: fit the motion on this many draws of each window (other subsamples "
                                         "and dithers) and keep their consensus: nearer the truth on average, "
                                         "the motion stages' time times N (cmax.FitSettings.motion_members)"),
                _settings_default("motion_members"))
    api_default(parser.add_argument("--max-events", type=positive_int, default=None,
                                    help="windows with more events are subsampled to this many (cmax.FitSettings."
                                         "max_events); default: by the sensor, 60,000 events up to 346x260 pixels, "
                                         "on a larger sensor that many times sqrt(width height / (346 260)): "
                                         "110,876 at 640x480, 192,043 at 1280x720 (cmax.fitting.settings."
                                         "max_events_for); se3: a window fitted on fewer than 0.25 events per pixel "
                                         "is at best ambiguous, counted on a sensor larger than 346x260 over "
                                         "sqrt(width height 346 260) pixels: 41,560 events at 640x480, 71,984 at "
                                         "1280x720 (cmax.fitting.QualitySettings.min_event_density, "
                                         "min_event_density_area)"), _settings_default("max_events"))
    api_default(parser.add_argument("--max-omega", type=positive_float, default=None,
                                    help="se3 and rotation: bound of each fitted angular-velocity component [rad/s]; a "
                                         "window that ends on it is reported, never clipped (cmax.FitSettings."
                                         "max_omega)"), _settings_default("max_omega"))
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the results of an earlier run in -o (else refused: its windows would mix with "
                             "this run's); they stay until this run has written all of its own")
    parser.add_argument("--resume", action="store_true",
                        help="continue an interrupted run into -o: its finished windows (kept in -o/.fit.windows as "
                             "each is done) are checked (the same event, --gyro and --calib files by their SHA-256, "
                             "the same options) and taken, the others fitted (default: off; a folder holding an "
                             "interrupted run's windows is refused without --resume or --overwrite; with "
                             "--overwrite too, an earlier complete run's results in -o are replaced at the end; "
                             "without it, a complete run of the same files and options in -o is left as it is: "
                             "nothing to do, unless a result it lists is missing or changed: then it runs again)")
    parser.add_argument("--keep-hot-pixels", action="store_true",
                        help="fit every event; by default the events of hot pixels (far more events than the scene's "
                             "edges give any pixel, or firing alone at a steady rate: a defect; or locked to a 100/120 "
                             "Hz mains flicker: a lamp) are left out and named in a note "
                             "(cmax.FitSettings.hot_pixels)")
    parser.set_defaults(run=run)
    return parser


def _sequence_default(name: str):
    return library_default("cmax.fitting.sequence:fit_sequence", name)


def _fit_default(name: str):
    return library_default("cmax.fitting.api:fit", name)


def _settings_default(name: str):
    return library_default("cmax.fitting.settings:FitSettings", name)


def earlier_results(out: Path) -> list[Path]:
    """The files of an earlier ``cmax fit`` in the folder ``out``: ``depth_<k>.npz`` / ``.png`` (``k`` five digits
    or more, as fit names them), ``trajectory.txt``, ``summary.json`` (:data:`cmax.io.run_folder.RESULT_NAMES`);
    empty when there are none (or no folder). Other files, such as a user's ``depth_groundtruth.png``, are not."""
    return run_folder.run_results(out, ("fit",))


def tum_lines(times_us: np.ndarray, poses: np.ndarray) -> list[str]:
    """TUM trajectory lines ``t tx ty tz qx qy qz qw`` of poses (M, 4, 4) at times [µs]."""
    from scipy.spatial.transform import Rotation

    quats = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x, y, z, w
    return [f"{t * 1e-6:.6f} " + " ".join(f"{v:.9f}" for v in (*T[:3, 3], *q))
            for t, T, q in zip(times_us, poses, quats)]


#: The settings of :class:`cmax.FitSettings` that ``cmax fit`` options give, by the option's name.
OPTION_OF_SETTING = {"depth_range": "--depth-range", "max_events": "--max-events", "motion_members": "--members",
                     "depth_grid": "--depth-grid", "polish": "--polish", "solver": "--solver", "max_omega": "--max-omega"}


def option_words(message: str) -> str:
    """A settings error in the command line's words: each setting :data:`OPTION_OF_SETTING` names, as its option.

    >>> option_words("depth_range must satisfy 0 < near < far (metres), got (3.0, 1.0)")
    '--depth-range must satisfy 0 < near < far (metres), got (3.0, 1.0)'
    >>> option_words("omega_z ended on its bound: raise FitSettings.max_omega")
    'omega_z ended on its bound: raise --max-omega'
    """
    import re

    return re.sub(r"\b(?:FitSettings\.)?(" + "|".join(OPTION_OF_SETTING) + r")\b", lambda m: OPTION_OF_SETTING[m.group(1)],
                  message)


def _microseconds(ms: float, option: str) -> int:
    us = int(round(ms * 1000))
    if us < 1:
        raise ValueError(f"{option} must be at least 0.001 ms (1 µs), got {ms}")
    return us


class _CountedWindows:
    """Events (or :class:`~cmax.cli.recording.StreamedEvents`) behind the reader protocol of :func:`fit_sequence`
    (``window(t0_us, t1_us)``, ``t_start``, ``t_end``), advancing a progress bar by one each time a window is done
    (the next one is taken)."""

    def __init__(self, events, bar) -> None:
        self.events, self.bar, self.taken = events, bar, 0
        self.t_start, self.t_end = event_span(events)

    def window(self, t0_us: int, t1_us: int):
        if self.taken and self.bar.n < self.bar.total:
            self.bar.update(1)
        self.taken += 1
        if isinstance(self.events, StreamedEvents):
            return self.events.window(t0_us, t1_us)
        return self.events.slice_time(t0_us, t1_us)

    def finish(self) -> None:
        self.bar.update(max(0, min(self.taken, self.bar.total) - self.bar.n))
        self.bar.close()


def _depth_scale(results) -> "object":
    """One colour scale for every depth picture of a run: the 1-99th percentiles of all windows' depths on their
    masks (None when no window has a depth). Not ``--depth-range``: a wide search range (0.05-50 m) drew a scene
    at 0.5-5 m in one colour."""
    from cmax import viz

    maps = [r.depth[r.mask] for r in results if r.depth is not None]   # the depths on the masks: all it needs
    try:
        return viz.DepthScale.from_depths(maps) if maps else None
    except ValueError:  # no window holds a depth on its mask
        return None


def unmapped_pixels(camera) -> int:
    """How many of the ``camera``'s (:class:`cmax.Camera`) sensor pixels have no pixel of the undistorted (and
    rectified) image: none (NaN in :attr:`~cmax.Camera.undistortion_map`) or the nearest one outside the
    ``width`` x ``height`` image; :meth:`~cmax.Camera.undistort_events` drops their events."""
    from cmax.camera import nearest_pixels

    _, inside = nearest_pixels(camera.undistortion_map.reshape(-1, 2), camera.width, camera.height)
    return int(inside.size - inside.sum())


def summary_units(scale_known: bool) -> dict[str, str]:
    """The units and frames of what ``cmax fit`` writes, keyed by field (``summary.json``'s ``units``).

    Lengths are metres when ``scale_known`` (``--speed`` given), else metres at a speed of 1 m/s (each
    window's ``v`` a unit vector): the same convention as ``trajectory.txt``'s header (:func:`tum_header`).

    >>> summary_units(True)["v"]
    'm/s, camera frame (x right, y down, z forward)'
    >>> summary_units(False)["depth_range"]
    'm at a speed of 1 m/s (no --speed: up to scale)'
    """
    length = "m" if scale_known else "m at a speed of 1 m/s (no --speed: up to scale)"
    axes = "camera frame (x right, y down, z forward)"
    return {
        "t0_us, t1_us, t_ref_us, skipped_us, uncovered_us": "µs on the file's clock (t0_us, t1_us: the window's "
                                                            "first and last events; t_ref_us: the depth map's time)",
        "t0_s, t1_s": "s after the first event (--t0, --t1)",
        "window_ms, step_ms": "ms",
        "v": f"m/s, {axes}" if scale_known else f"unit vector (no --speed: direction only), {axes}",
        "omega": f"rad/s, {axes}",
        "flow": "px/s (x, y)",
        "depth_range": length,
        "K": "px: the pinhole of the fitted pixels (with --calib of a rectified camera, MVSEC's: the rectified "
             "frame's, in which v, omega and the depth maps are too)",
        "parallax_px": "px: median over the events of how far the fitted translation moves each over the window",
        "objective_after": "contrast of the warped events, 1 = the unwarped events' (unitless)",
        "seconds": "wall-clock seconds of the window's fit",
        "depth_NNNNN.npz": f"depth (H, W): z-depth [{length}] seen at t_ref_us, valid where mask; depth_spread: "
                           "range of log inverse depth over the 3x3 grid nodes around each pixel (large at depth "
                           "edges); inverse_depth_grid: the grid's nodes [1/depth unit]; K [px]",
        "trajectory.txt": f"TUM: t [s] tx ty tz [{length}] qx qy qz qw, camera-to-world (the lens's own frame, also "
                          "when --calib rectifies the events: its header says so)",
    }


def unscaled_range_note(near: float, far: float) -> str:
    """The note for a depth range ``near``-``far`` [m] (``--depth-range``, or the one a scene file records) bounding
    an se3 fit without ``--speed``: the fit's depths are then in units of the speed x 1 s (each window at 1 m/s), so the
    range bounds the scene in metres only for a camera moving at about 1 m/s.

    >>> unscaled_range_note(0.5, 2.0)[:60]
    "without --speed the fit's depths are in units of the speed x"
    """
    return (f"without --speed the fit's depths are in units of the speed x 1 s (each window is fitted at 1 m/s), not "
            f"metres: the depth range {near:g}-{far:g} bounds the scene in metres only for a camera moving at about "
            f"1 m/s (at 0.3 m/s a scene at {near:g}-{far:g} m lies at {near / 0.3:.3g}-{far / 0.3:.3g} in these "
            "units, partly beyond the range); --speed gives metres")


def verdict_counts(counts: dict[str, int]) -> str:
    """The summary line's verdict counts, e.g. ``3 ok, 2 ambiguous (1 resolved), 0 low parallax, 1 failed``."""
    resolved = f" ({counts['resolved']} resolved)" if counts.get("ambiguous") else ""
    return (f"{counts['ok']} ok, {counts['ambiguous']} ambiguous{resolved}, {counts['low_parallax']} low parallax, "
            f"{counts['failed']} failed")


def advice(counts: dict[str, int], model: str, rotation_known: bool = False, no_motion: int = 0,
           cell_noise: int = 0, unsteady: int = 0, sparse: int = 0, *, single_window: bool = False,
           sparse_needs: int | None = None, small_parallax: int = 0, noisy: int = 0,
           densest: int | None = None) -> list[str]:
    """What to try when at least half of the fitted windows are low parallax or ambiguous and unresolved (one
    line each; none otherwise); ``rotation_known``: the run held the rotation (``--gyro``, ``--omega``);
    ``no_motion``: how many of the low-parallax windows show no motion at all (the permutation test,
    :attr:`cmax.fitting.quality.LowMotionCause.NO_MOTION`), for which a longer window is no cure;
    ``cell_noise`` (flow, rotation): how many have a motion that sharpens only parts of the image
    (:attr:`~cmax.fitting.quality.LowMotionCause.CELL_NOISE`): too little motion, or parts that move
    differently, for which a longer window is no cure either; ``unsteady`` (se3): how many of the unresolved
    ambiguous windows are so because their motion is not steady (``Quality.unsteady``: a start or a stop), for
    which a shorter window is the cure; ``sparse`` (se3): how many of the other unresolved ambiguous windows are
    so because they were fitted on too few events per pixel (``Quality.sparse``), for which more events are the
    cure. ``single_window``: one window spans the whole recording (a longer ``--window-ms`` cannot give more);
    ``sparse_needs``: the events a window must be fitted on to reach the density the verdict asks, when that is
    more than ``--max-events`` lets through (then only a larger ``--max-events`` helps a sparse window);
    ``densest``: the most events any window of the run holds (None: not counted); under ``sparse_needs`` no
    ``--max-events`` reaches the density, and the advice says so (longer windows, or a longer recording, do);
    ``small_parallax`` (se3): how many of the other unresolved ambiguous windows are so because their parallax is
    under ``QualitySettings.min_ok_parallax_px`` (``Quality.small_parallax``), for which more parallax or a known
    rotation is the cure; ``noisy`` (se3): how many of the other unresolved ambiguous windows are so because too many
    of their events are background-activity noise (``Quality.noisy``), for which a longer window is no cure.

    >>> advice({"ok": 0, "ambiguous": 0, "resolved": 0, "low_parallax": 1, "failed": 0}, "se3", True, single_window=True)
    ['1 of 1 windows have too little parallax: their translation and depth are not measured; a longer span of events (the run is one window over all of them) gives more parallax']
    >>> advice({"ok": 0, "ambiguous": 2, "resolved": 0, "low_parallax": 0, "failed": 0}, "se3", sparse=2,
    ...        sparse_needs=71_984)[0]
    '2 of 2 windows stay ambiguous because they were fitted on too few events per pixel to vouch for their direction (QualitySettings.min_event_density): a larger --max-events (at least 71,984 on this sensor) gives them more; a longer --window-ms alone does not (a window is subsampled to --max-events)'
    >>> advice({"ok": 0, "ambiguous": 1, "resolved": 0, "low_parallax": 0, "failed": 0}, "se3", sparse=1,
    ...        sparse_needs=230_400, densest=219_517, single_window=True)[0].split(": ", 1)[1]
    'no --max-events reaches that density: the window holds 219,517 events, fewer than the 230,400 this sensor needs; a longer span of events (the run is one window over all of them) gives more'

    >>> advice({"ok": 1, "ambiguous": 0, "resolved": 0, "low_parallax": 3, "failed": 0}, "se3")[0][:40]
    '3 of 4 windows have too little parallax:'
    >>> advice({"ok": 3, "ambiguous": 1, "resolved": 0, "low_parallax": 0, "failed": 0}, "se3")
    []
    """
    total = sum(counts[k] for k in ("ok", "ambiguous", "low_parallax", "failed"))
    unresolved = counts["ambiguous"] - counts.get("resolved", 0)
    longer = ("a longer span of events (the run is one window over all of them)" if single_window
              else "a longer --window-ms")
    lines = []
    if total and 2 * counts["low_parallax"] >= total:
        if counts["low_parallax"] > cell_noise:
            lines.append(f"{counts['low_parallax'] - cell_noise} of {total} windows have too little "
                         + (f"parallax: their translation and depth are not measured; {longer} gives more parallax"
                            + ("" if rotation_known else ", --model rotation fits the rotation alone")
                            if model == "se3" else f"motion to measure: {longer} gives more"))
        if cell_noise:
            lines.append(f"{cell_noise} of {total} windows have a fitted {model} that sharpens only parts of the "
                         f"image: either too little motion ({longer} gives more) or parts that move "
                         "differently (depth differences, or a motion that changes within a window: --model se3 or a "
                         "shorter --window-ms)")
        if no_motion:
            lines.append(f"{no_motion} of them show no motion at all (the fitted motion sharpens the events with their "
                         "timestamps shuffled as much): sensor noise, flicker or a static scene; check the recording")
    if total and model == "se3" and 2 * unresolved >= total:
        known = "" if rotation_known else ("a known rotation (--gyro, or --omega 0,0,0 for a rig that does not "
                                           "rotate) or ")
        if unresolved > unsteady + sparse + small_parallax + noisy:
            lines.append(f"{unresolved - unsteady - sparse - small_parallax - noisy} of {total} windows stay ambiguous "
                         f"(an alternative motion scores as well): {known}{longer} tells them apart")
        if noisy:
            lines.append(f"{noisy} of {total} windows stay ambiguous because too many of their events are "
                         "background-activity noise (QualitySettings.max_noise_share): leave the isolated events out "
                         "before fitting (cmax.fitting.quality.isolated_events) or lower the sensor's background "
                         f"activity; {longer} does not help (the noise grows with it)")
        if small_parallax:
            lines.append(f"{small_parallax} of {total} windows stay ambiguous because their parallax is too small to "
                         "tell the translation direction from a rotation (QualitySettings.min_ok_parallax_px): "
                         f"{known}{longer} gives more parallax")
        if sparse:
            cure = (f"a larger --max-events (at least {sparse_needs:,} on this sensor) gives them more; a longer "
                    "--window-ms alone does not (a window is subsampled to --max-events)" if sparse_needs else f"{longer} gives them more")
            if sparse_needs and densest is not None and densest < sparse_needs:   # no --max-events can help
                cure = (f"no --max-events reaches that density: the {'window' if single_window else 'densest window'}"
                        f" holds {densest:,} events, fewer than the {sparse_needs:,} this sensor needs; "
                        + (f"{longer} gives more" if single_window else
                           f"{longer} with --max-events of at least {sparse_needs:,} gives more"))
            lines.append(f"{sparse} of {total} windows stay ambiguous because they were fitted on too few events per "
                         f"pixel to vouch for their direction (QualitySettings.min_event_density): {cure}")
        if unsteady:
            lines.append(f"{unsteady} of {total} windows stay ambiguous because the camera starts or stops inside "
                         "them (their event rate changes beyond QualitySettings.max_rate_change between their "
                         "halves): a shorter --window-ms keeps the motion steady within each window")
    return lines


def densest_window(events, first_us: int, last_us: int, window_us: int, step_us: int) -> int | None:
    """The most events any window ``[start, start + window_us)`` of the run holds (its starts from
    :func:`cmax.events.window_starts` over ``[first_us, last_us]`` [µs], ``step_us`` apart), counted by a binary
    search of the times of ``events`` (:class:`cmax.Events`); None for events streamed from a file (not held).

    >>> import cmax
    >>> events = cmax.Events([0] * 5, [0] * 5, [0, 1, 2, 10, 11], [1] * 5, 2, 2)
    >>> densest_window(events, 0, 11, 10, 10)
    3
    """
    from cmax.events import Events, window_starts

    if not isinstance(events, Events):
        return None
    starts = window_starts(first_us, last_us, window_us, step_us)
    if not len(starts):
        return None
    bounds = np.searchsorted(events.t, np.stack([starts, starts + window_us]))
    return int((bounds[1] - bounds[0]).max())


def grouped_warnings(caught: list) -> list[dict]:
    """The warnings of a run (``warnings.catch_warnings(record=True)``), one entry per kind: the same category and
    the same words once the numbers are left out (a warning of every window is said once, with how often it came
    and, for a window's warning (``window i: ...``, as :func:`~cmax.fitting.fit_sequence` words them), which windows).
    Each entry: ``category`` (class name), ``count`` (how many times it came), ``windows`` (the windows' numbers,
    ascending, each once; empty for a warning of the run), ``message`` (the first one) and ``text`` (the line to
    print).

    >>> import warnings
    >>> caught = [warnings.WarningMessage(UserWarning(f"window {i}: parallax 0.{i} px"), UserWarning, "f.py", 1)
    ...           for i in (0, 1, 2, 5)]
    >>> [line["text"] for line in grouped_warnings(caught)]
    ['UserWarning (4 times, windows 0-2, 5; the first): window 0: parallax 0.0 px']
    """
    import re

    groups: dict[tuple[str, str], dict] = {}
    for item in caught:
        message = str(item.message)
        key = (item.category.__name__, re.sub(r"[-+]?\d[\d.,:e+-]*", "#", message))
        entry = groups.setdefault(key, {"category": key[0], "count": 0, "windows": [], "message": message})
        entry["count"] += 1
        if (window := re.match(r"window (\d+): ", message)) is not None:
            entry["windows"].append(int(window.group(1)))
    for entry in groups.values():
        entry["windows"] = sorted(set(entry["windows"]))
        which = f", windows {_ranges(entry['windows'])}" if len(entry["windows"]) > 1 else ""
        times = f" ({entry['count']} times{which}; the first)" if entry["count"] > 1 else ""
        entry["text"] = f"{entry['category']}{times}: {entry['message']}"
    return list(groups.values())


def _ranges(numbers: list[int]) -> str:
    """Ascending distinct whole numbers in a few words: ``[0, 1, 2, 5]`` -> ``'0-2, 5'``."""
    from cmax.fitting.sequence import _runs

    return ", ".join(str(r[0]) if len(r) == 1 else f"{r[0]}-{r[-1]}" for r in _runs(numbers))


def window_line(index: int, result, first_us: int) -> str:
    """One window's verdict line: its time (seconds after the first event), verdict, reason, resolution."""
    t0, t1 = (result.t0_us - first_us) * 1e-6, (result.t1_us - first_us) * 1e-6
    q = result.quality
    if q is None:
        return f"window {index} ({t0:.3f}-{t1:.3f} s): no verdict"
    resolution = f"; {q.resolution}" if q.resolution else ""
    return f"window {index} ({t0:.3f}-{t1:.3f} s): {q.verdict.value.replace('_', ' ')}: {q.reason}{resolution}"


def hot_pixel_note(results) -> str | None:
    """One sentence on the hot pixels the fits left out (``FitResult.hot_pixels``), or None when none."""
    hot = [r.hot_pixels for r in results if len(r.hot_pixels)]
    if not hot:
        return None
    pixels, counts = np.unique(np.concatenate(hot), axis=0, return_counts=True)
    pixels = pixels[np.argsort(-counts, kind="stable")]          # the pixels hot in most windows first
    return (f"{len(pixels)} hot pixel(s) fire without motion (far more than the scene's edges make any pixel fire, "
            f"alone at a steady rate, or with a lamp's 100/120 Hz flicker), in {len(hot)} of "
            f"{len(results)} windows ({named_pixels(pixels)}): their events were left out of those windows' fits "
            "(--keep-hot-pixels keeps them)")


def run(args: argparse.Namespace) -> int:
    """Run the command; returns the exit status (1 when no window could be fitted, or every fitted one failed).

    The run holds ``-o`` (the lock ``.results.lock`` in it, shared with ``cmax emvs`` and ``cmax depth``) from its
    look at earlier results to its last file: a second run into the same folder meanwhile is refused at once. A
    folder with an earlier run's results (of any of the three) is refused without ``--overwrite``. The results are
    written into a private folder and moved in once all are written (:func:`cmax.io.run_folder.publish`:
    summary.json last): a failed run leaves ``-o`` as it was, one interrupted while moving its files in leaves no
    summary.json, and two runs' windows never mix."""
    from cmax.fitting import FitSettings
    from cmax.fitting.api import MIN_WINDOW_EVENTS
    from cmax.io.gyro import parse_axes

    out = output_folder(args.output, "the depth maps and the summary")
    # The options are checked before the file is read (a mistake is named at once, in the options' words):
    sequence_model = args.model or _sequence_default("model")()
    for option, given in (("--omega", args.omega is not None), ("--speed", args.speed is not None),
                          ("--gyro", args.gyro is not None), ("--zero-rotation-start", args.zero_rotation_start),
                          ("--members", args.members is not None), ("--depth-grid", args.depth_grid is not None),
                          ("--polish", args.polish is not None), ("--depth-range", args.depth_range is not None)):
        if given and sequence_model != "se3":   # the other models fit no depth: taken, it would do nothing
            raise ValueError(f"{option} applies to --model se3, not {sequence_model}")
    if args.max_omega is not None and sequence_model == "flow":
        raise ValueError("--max-omega applies to --model se3 and rotation, not flow (a flow has no rotation)")
    if args.omega is not None and args.gyro is not None:
        raise ValueError("--omega is a constant rotation, --gyro a measured one: pass one of them")
    if args.gyro_axes is not None:
        if args.gyro is None:
            raise ValueError("--gyro-axes turns the readings of --gyro: pass --gyro too")
        try:
            parse_axes(args.gyro_axes)
        except ValueError as error:
            raise ValueError(f"--gyro-axes: {error}") from None
    range_note = None
    if args.depth_range is None and sequence_model == "se3":
        args.depth_range = file_depth_range(args.file)
        if args.depth_range is not None:
            range_note = (f"depth over {args.depth_range[0]:g}-{args.depth_range[1]:g} m, the depth range the file "
                          "records for its scene (--depth-range to change it)")
    notes = [range_note] if range_note else []
    if args.depth_range is not None and args.speed is None and sequence_model == "se3":
        notes.append(unscaled_range_note(*args.depth_range))
    options = {key: value for key, value in (("solver", args.solver), ("depth_grid", args.depth_grid),
                                             ("max_events", args.max_events),
                                             ("motion_members", args.members), ("depth_range", args.depth_range),
                                             ("polish", args.polish), ("max_omega", args.max_omega))
               if value is not None}
    if args.keep_hot_pixels:
        options["hot_pixels"] = None
    # None above: the library's default (one source: fit_sequence / fit / FitSettings)
    try:
        settings = FitSettings(**{key: value for key, value in options.items()
                                  if key in FitSettings.__dataclass_fields__})
    except ValueError as error:
        raise ValueError(option_words(str(error))) from None
    min_events = args.min_events or _sequence_default("min_events")()
    if min_events < MIN_WINDOW_EVENTS:
        raise ValueError(f"--min-events must be at least {MIN_WINDOW_EVENTS} (the fewest events a window can be "
                         f"fitted with), got {min_events}")
    depth_grid = tuple(args.depth_grid or _fit_default("depth_grid")())
    window_us = (_sequence_default("window_us")() if args.window_ms is None
                 else _microseconds(args.window_ms, "--window-ms"))
    step_us = window_us if args.step_ms is None else _microseconds(args.step_ms, "--step-ms")
    hashing = None
    try:
        with run_folder.staged_run(out, _STAGE_PREFIX, earlier_results, overwrite=args.overwrite,
                                   what="depth_*.npz, summary.json, ...", resume=args.resume) as stage:
            # the input files are hashed while the windows are fitted: the store waits for their signatures only
            # to compare them with kept windows (--resume) or to record them with the first window it saves
            hashing = PendingSignatures(_input_paths(args), progress=not args.quiet)
            record = _pending_record(args, hashing)
            complete = run_folder.resumed_into_complete(out, resume=args.resume, overwrite=args.overwrite)
            if complete is not None:   # a complete run's results: the same run has nothing to do, another is refused
                damaged = run_folder.check_complete(out, complete, record(), command="cmax fit")
                print(f"cmax fit: note: {damaged}", file=sys.stderr)   # the same run, files missing: run again
            store = WindowStore(out, record, resume=args.resume, overwrite=args.overwrite)
            status = _fit_into(stage, out, args, sequence_model=sequence_model, options=options, settings=settings,
                               min_events=min_events, depth_grid=depth_grid, window_us=window_us, step_us=step_us,
                               notes=notes, store=store)
            store.run    # every input hashed whole and unchanged (else refused) before the results are published
    except run_folder.ResultsComplete as complete:   # --resume of a run whose results are all in out
        print(complete)
        return completed_status(complete.summary)
    except KeyboardInterrupt as stop:   # Ctrl-C, or SIGTERM (cmax._signals): say what is kept
        if not (kept := interrupted_windows(out)):
            raise
        line, status = stopped_line("cmax fit", stop, kept, out / WINDOWS_FOLDER)
        print(line, file=sys.stderr)
        return status
    finally:
        if hashing is not None:    # stopped within one block, never left running
            hashing.close()
    store.remove()   # the results are in out: the finished windows are no longer needed
    return status


def completed_status(summary: dict) -> int:
    """The exit status a complete run of ``cmax fit`` had, from its ``summary.json`` (``summary``): 1 when it
    fitted no window or every fitted one failed, else 0 (what ``--resume`` of that run returns again).

    Parameters
    ----------
    summary : dict
        The run's ``summary.json``.

    >>> completed_status({"windows": [{"verdict": "failed"}]}), completed_status({"windows": [{"verdict": "ok"}]})
    (1, 0)
    """
    windows = summary.get("windows") or []
    return 1 if not windows or all(w.get("verdict") == "failed" for w in windows if isinstance(w, dict)) else 0


#: The options of ``cmax fit`` that change no result: left out of :func:`run_record`.
_NOT_RESULTS = ("command", "output", "quiet", "overwrite", "resume", "run", "jobs")


def _input_paths(args: argparse.Namespace) -> dict:
    """The input files of a run of ``cmax fit`` by the name its record gives them (None: not given)."""
    return {"file": args.file, "calib": args.calib, "gyro": args.gyro}


def _pending_record(args: argparse.Namespace, hashing: PendingSignatures):
    """:func:`run_record` of ``args`` as they are now and of the code of cmax now, with the input files' signatures
    ``hashing`` gives: a callable that waits for them (:class:`cmax.io.window_store.WindowStore`'s ``run``)."""
    options, code = argparse.Namespace(**vars(args)), code_digest("cmax")
    return lambda: run_record(options, hashing.result(), code=code)


def run_record(args: argparse.Namespace, files: dict | None = None, *, code: str | None = None) -> dict:
    """What a run of ``cmax fit`` is, for ``--resume`` to check (:class:`cmax.io.window_store.WindowStore`): the
    signatures (size, modification time, SHA-256) of the event file and of ``--calib`` / ``--gyro``, the version of
    cmax and a digest of its code, and every option that changes a window's fit (``args``, the parsed options; ``--jobs`` only as
    whether the windows are warm-started, ``jobs == 1``; the paths of those files only through their signatures, so
    that a moved file, the same bytes, resumes). ``files``: those signatures when they are taken already
    (:class:`cmax.io.window_store.PendingSignatures`), else they are taken here
    (:func:`cmax.io.window_store.file_signatures`); ``code``: the digest of cmax's code when taken already
    (:func:`cmax.io.window_store.code_digest`)."""
    files = file_signatures(_input_paths(args), progress=not args.quiet) if files is None else files
    return command_record(args, files, code=code_digest("cmax") if code is None else code, ignored=_NOT_RESULTS,
                          extra={"warm_start": args.jobs == 1})


def _fit_into(stage: Path, out: Path, args: argparse.Namespace, *, sequence_model: str, options: dict,
              settings, min_events: int, depth_grid: tuple[int, int], window_us: int, step_us: int,
              notes: list[str], store: WindowStore) -> int:
    """:func:`run`'s work once the options are checked (``options``, the keywords of :func:`cmax.fit_sequence`;
    ``settings``, the :class:`cmax.FitSettings` they make; ``notes``, :func:`run`'s notes to print and record):
    read, fit, and write every result into the empty folder ``stage`` (moved into ``out`` by :func:`run`), each
    window's fit kept in ``store`` as it is done (and taken from it when an interrupted run left it); returns the
    exit status."""
    from tqdm.auto import tqdm

    from cmax import viz
    import cmax.events as cmax_events
    from cmax.events import EventLimitError, uncovered_tail, window_starts
    from cmax.emvs.poses import tum_header
    from cmax.fitting import fit_sequence
    from cmax.fitting.api import MIN_WINDOW_EVENTS
    from cmax.fitting.quality import LowMotionCause, Verdict, density_pixels
    from cmax.fitting.sequence import check_gyro, constant_gyro
    from cmax.fitting.settings import max_events_for
    from cmax.io import read_gyro
    from cmax.warp import DepthGrid

    calibration = calibration_of(args)
    K, calib_size = calibration.K, calibration.size
    notes = notes + ([unlike] if (unlike := given_k_note(args.file, K)) else [])
    if K is None:
        K = file_intrinsics(args.file)
        if K is None:
            raise ValueError(no_intrinsics_message(args.file, "--calib"))
    notes = notes + ([hint] if (hint := calibration_hint(args)) else [])
    if args.calib is not None and (said := calibration_note(calibration, args.calib, args.calib_camera, args.file)):
        notes.append(said)
    events = streamed = None
    try:
        streamed = open_streamed(args, calib_size) if args.t0 is None and args.t1 is None else None
    except (ValueError, OSError):   # read_calibrated below says what is wrong with the file, in its own words
        pass
    if streamed is not None:
        if STREAM_ABOVE_EVENTS < len(streamed.reader) <= cmax_events.MAX_EVENTS:   # past it: the note below
            events, origin_us = streamed, streamed.t_start      # one window in memory at a time, not all of them
            notes.append(f"{args.file} holds {len(streamed.reader):,} events: fitting it window by window from the "
                         "file, one window in memory at a time")
        else:
            streamed.close()
    try:
        if events is None:
            events, origin_us = read_calibrated(args, calib_size)   # --t0/--t1 applied; times print from the start
    except EventLimitError:                  # a whole DSEC-layout h5 file too long to hold: window by window
        if args.t0 is not None or args.t1 is not None or (events := open_streamed(args, calib_size)) is None:
            raise
        origin_us = events.t_start
        notes.append(f"{args.file} holds {len(events.reader):,} events, more than cmax.events.MAX_EVENTS="
                     f"{cmax_events.MAX_EVENTS:,}: fitting it window by window from the file")
    check_file_principal_point(K, args.file, events.width, events.height)   # cmax.fit's check, with --size's scale
    if not isinstance(events, StreamedEvents):          # in memory: counted as cmax info counts them (never dropped)
        from cmax.io.info import duplicate_count

        if repeated := duplicate_count(events):
            notes.append(f"{repeated:,} of the {len(events):,} events repeat an earlier event exactly (same x, y, t "
                         "and polarity: a file written twice or merged with itself?): fitted as they are, each "
                         "copy counted")
    if calibration.undistorts:          # one camera, its undistortion map computed once for every window
        camera = calibration.camera(events.width, events.height, K)
        undistort, K = camera.undistort_events, camera.pinhole_K   # the fit's K: the pixels' the events land on
    raw = None               # through a lens: the recorded events, which each window's fit undistorts itself
    if calibration.undistorts and isinstance(events, StreamedEvents):
        raw, events = events, events.with_transform(undistort)
        if lost := unmapped_pixels(camera):        # window by window: the pixels whose events are dropped, not counted
            notes.append(f"{lost:,} of the sensor's {camera.width * camera.height:,} pixels fall outside the image "
                         "once undistorted, or lie beyond the radius the distortion model reaches: their events are "
                         "dropped")
    if calibration.undistorts and not isinstance(events, StreamedEvents):
        raw, total = events, len(events)
        events = undistort(events)
        if len(events) < total:
            notes.append(f"{total - len(events):,} events fall outside the image once undistorted, or lie beyond the "
                         "radius the distortion model reaches (dropped)")
    gyro = None
    if args.omega is not None:
        first_us, last_us = event_span(events)
        gyro = constant_gyro(args.omega, first_us, last_us + 1)
    if args.gyro is not None:
        gyro = check_gyro(read_gyro(args.gyro, axes=args.gyro_axes))
        events, note = overlap(events, gyro[0], "gyro samples", args.gyro, "fitting the overlap")
        notes += [note] if note else []
    if gyro is not None and calibration.rectification is not None:   # camera axes -> the rectified frame fitted
        gyro = (gyro[0], gyro[1] @ calibration.rectification.T)
    if sequence_model == "se3":
        DepthGrid(depth_grid, events.width, events.height)
    first_us, last_us = event_span(events)
    span_us = last_us - first_us + 1
    single_window = window_us > span_us     # one window over every event: a longer --window-ms cannot help
    if single_window:
        what = "the recording" if args.t0 is None and args.t1 is None else "the span of --t0/--t1"
        notes.append(f"{what} ({span_us * 1e-3:.1f} ms) is shorter than the window ({window_us * 1e-3:.1f} ms): "
                     f"fitting one window over {'the whole recording' if what == 'the recording' else 'it'}")
        window_us = step_us = span_us
    n_windows = len(window_starts(first_us, last_us, window_us, step_us))
    tail = uncovered_tail(first_us, last_us, window_us, step_us)
    if tail is not None:
        held = None if isinstance(events, StreamedEvents) else len(events.slice_time(*tail))
        note = tail_note(first_us, last_us, window_us, step_us, events=held, origin_us=origin_us)
        notes += [note] if note else []     # None: too short an end to name
    for note in notes:
        print(f"cmax fit: note: {note}", file=sys.stderr)
    fitted, fit_K = events, K
    if raw is not None:    # the recorded events over the same span, and the camera: each event warped from its
        span = (events.t_start, events.t_end) if isinstance(events, StreamedEvents) else (first_us, last_us)
        fitted, fit_K = raw.slice_time(span[0], span[1] + 1), camera    # sub-pixel position (cmax.fit's)
    if args.jobs == 1:     # the bar ticks as each window is taken, i.e. when the one before is done
        source = _CountedWindows(fitted, tqdm(total=n_windows, desc="windows", unit="window", disable=args.quiet))
    else:                  # workers take windows ahead of their fits: fit_sequence's own bar counts results
        source = fitted
    try:
        with warnings.catch_warnings(record=True) as caught:   # said once each, after the bar, and recorded
            warnings.simplefilter("always")
            sequence = fit_sequence(source, fit_K, sequence_model, window_us=window_us, step_us=step_us,
                                    speed=args.speed, gyro=gyro, zero_rotation_start=args.zero_rotation_start,
                                    jobs=args.jobs, min_events=min_events,
                                    progress=args.jobs > 1 and not args.quiet, store=store, **options)
    finally:
        if args.jobs == 1:
            source.finish()
        if isinstance(events, StreamedEvents):
            events.close()
    if store.resumed or store.unreadable:
        redone = f"; {store.unreadable} unreadable window file(s) fitted again" if store.unreadable else ""
        notes.append(f"resumed: {store.resumed} of {len(sequence.results)} fitted windows taken from the "
                     f"interrupted run in {out} (same file and options){redone}")
        print(f"cmax fit: note: {notes[-1]}", file=sys.stderr)
    warned = grouped_warnings(caught)
    for line in warned:
        print(f"cmax fit: warning: {option_words(line['text'])}", file=sys.stderr)
    windows = []
    scale = _depth_scale(store.maps(i, r) for i, r in enumerate(sequence.results))
    for i, r in enumerate(sequence.results):
        r = store.maps(i, r)      # one window's maps in memory at a time
        if r.depth is not None:
            save_npz_atomic(stage / f"depth_{i:05d}.npz", depth=r.depth, mask=r.mask, depth_spread=r.depth_spread,
                            inverse_depth_grid=r.inverse_depth_grid, t_ref_us=r.t_ref_us, K=K)
            title = (f"window {i}, t_ref {(r.t_ref_us - origin_us) * 1e-6:.3f} s, "
                     f"depth [{'m' if r.scale_known else 'up to scale'}]"
                     + ("" if r.verdict is None else f", {r.verdict.value.replace('_', ' ')}"))
            depth = viz.enlarge(np.where(r.mask, r.depth, np.nan), viz.readable_zoom(r.depth.shape[1]))
            viz.save_png(stage / f"depth_{i:05d}.png", viz.depth_panel(depth, scale, title,
                                                                       unit="m" if r.scale_known else ""))
        windows.append({"index": i, "depth_file": f"depth_{i:05d}.npz" if r.depth is not None else None,
                        "t0_us": r.t0_us, "t1_us": r.t1_us, "t_ref_us": r.t_ref_us, "v": r.v.tolist(),
                        "omega": r.omega.tolist(), "flow": None if r.flow is None else r.flow.tolist(),
                        "objective_after": r.objective_after, "seconds": r.seconds, "iterations": r.iterations,
                        "message": r.message, "success": r.success,
                        "scale_known": r.scale_known, "parallax_px": r.parallax_px,
                        "hot_pixels": r.hot_pixels.tolist(),
                        **(r.quality.summary() if r.quality is not None else {"verdict": None})})
        print(window_line(i, r, origin_us))
    scale_known = bool(sequence.results) and all(r.scale_known for r in sequence.results)
    poses, header = sequence.poses, tum_header(scale_known)
    if calibration.rectification is not None:   # the lens's own frame, as MVSEC's poses and cmax emvs --calib take it
        T_rect_c = np.eye(4)
        T_rect_c[:3, :3] = calibration.rectification
        poses = poses @ T_rect_c
        source = (calibration.rectified_from or "rectification_matrix").split(" and ")[0]   # DSEC: extrinsics/R_rect0
        header.append(f"# the camera's own frame: the fit's rectified frame turned back by {args.calib}'s "
                      f"{source} (T_w_c = T_w_rect [R_rect | 0])")
    write_text_atomic(stage / "trajectory.txt", "\n".join(header + tum_lines(sequence.times_us, poses)) + "\n")
    late_notes = [hot_note] if (hot_note := hot_pixel_note(sequence.results)) else []
    causes = [None if r.quality is None else r.quality.cause for r in sequence.results]
    no_motion, cell_noise = causes.count(LowMotionCause.NO_MOTION), causes.count(LowMotionCause.CELL_NOISE)
    unresolved = [r.quality for r in sequence.results if r.verdict is Verdict.AMBIGUOUS and not r.quality.resolved]
    unsteady = sum(q.unsteady for q in unresolved)
    sparse = sum(q.sparse for q in unresolved)     # never unsteady too: verdict_of marks only an ok one sparse
    small = sum(q.small_parallax for q in unresolved)   # nor sparse: an ok one, once
    noisy = sum(q.noisy for q in unresolved)            # nor small parallax: an ok one, once
    needs = math.ceil(settings.quality.min_event_density
                      * density_pixels(events.width, events.height, settings.quality.min_event_density_area))
    kept = max_events_for(settings.max_events, events.width, events.height)
    late_notes += advice(sequence.counts(), sequence_model, args.gyro is not None or args.omega is not None,
                         no_motion, cell_noise, unsteady, sparse, single_window=single_window,
                         sparse_needs=needs if needs > kept else None, small_parallax=small,
                         noisy=noisy, densest=densest_window(fitted, first_us, last_us, window_us, step_us))
    failed = sum(r.verdict is Verdict.FAILED for r in sequence.results)
    if not windows:
        late_notes.append(f"no window was fitted: each has fewer than {min_events:,} events (over more than one "
                          f"time stamp); a longer --window-ms or a lower --min-events (at least {MIN_WINDOW_EVENTS}) "
                          "fits them")
    elif failed == len(windows):
        late_notes.append(f"every fitted window failed ({failed}): no depth or motion of this run can be trusted "
                          "(each window's line says why)")
    from cmax.io import detect_format

    summary = {"file": str(args.file), "camera": camera_read(detect_format(args.file), args.camera),
               "model": sequence_model, "K": K.tolist(),
               "distortion": None if calibration.distortion is None else calibration.distortion.tolist(),
               "distortion_model": None if calibration.distortion is None else calibration.model,
               "rectified": calibration.rectification is not None or calibration.rectified_K is not None,
               "calib": None if args.calib is None else str(args.calib),
               "window_ms": window_us / 1000, "step_ms": step_us / 1000, "min_events": min_events,
               "t0_s": args.t0, "t1_s": args.t1,
               "depth_range": list(args.depth_range or _settings_default("depth_range")()),
               "speed": args.speed, "gyro": None if args.gyro is None else str(args.gyro),
               "omega": None if args.omega is None else list(args.omega),
               "solver": args.solver or _fit_default("solver")(),
               "depth_grid": list(depth_grid),
               "zero_rotation_start": args.zero_rotation_start, "jobs": args.jobs,
               "members": args.members or _settings_default("motion_members")(),
               "polish": args.polish or _settings_default("polish")().value,
               "warm_start": args.jobs == 1, "keep_hot_pixels": args.keep_hot_pixels, "notes": notes + late_notes,
               "warnings": [{key: line[key] for key in ("category", "count", "windows", "message")}
                            for line in warned],
               "windows_total": n_windows, "skipped_us": sequence.skipped_us.tolist(),
               "uncovered_us": None if sequence.uncovered_us is None else list(sequence.uncovered_us),
               "verdicts": sequence.counts(), "units": summary_units(scale_known), "windows": windows,
               "run": store.run, run_folder.OUTPUTS_KEY: run_folder.output_records(stage)}
    write_text_atomic(stage / "summary.json", json.dumps(summary, indent=2))
    skipped = n_windows - len(windows)
    skip = f", {skipped} skipped (fewer than {min_events:,} events)" if skipped else ""
    print(f"{len(windows)} of {n_windows} windows fitted{skip}: {verdict_counts(sequence.counts())}; results in {out}")
    for line in late_notes:
        print(f"cmax fit: note: {line}", file=sys.stderr)
    return 1 if not windows or failed == len(windows) else 0
