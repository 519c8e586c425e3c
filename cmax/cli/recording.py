"""Options shared by the commands that read a recording, and the calibration and time-slice helpers behind them.

* :func:`add_file_options` / :func:`file_kwargs`: ``--size``, ``--time-unit``, ``--polarity``, ``--sort``,
  ``--camera`` (an MVSEC file's) of the file tools (``cmax info``, ``cmax show``), passed to :func:`cmax.io.read`
  as keywords;
* :func:`add_recording_arguments`: ``--size``, ``--time-unit``, ``--polarity``, ``--t0``, ``--t1``, ``--camera`` of
  the commands that fit or predict (``cmax fit``, ``cmax depth``); :func:`time_slice` applies ``--t0`` /
  ``--t1``; :func:`tail_note` says what their windows leave out at the end; :func:`overlap` cuts the events to
  the span of a gyroscope's samples or of poses; :func:`open_streamed`: a DSEC-layout h5 file too long to hold,
  read window by window;
* :func:`add_camera_options`: ``--K`` or ``--calib`` (with ``--calib-camera``), and ``--distortion``, of the
  commands that need the intrinsics (``cmax fit``, ``cmax emvs``), :func:`calibration_of` and
  :func:`read_calibrated` behind them; :func:`intrinsics_argument`,
  :data:`distortion_argument`: their ``argparse`` types; ``--calib`` is read by :func:`cmax.io.read_calibration`
  (ECD ``calib.txt``, DSEC ``cam_to_cam.yaml``, a Kalibr camchain: radtan or equidistant, rectified when it gives
  ``rectification_matrix`` / ``projection_matrix``), a :class:`cmax.io.Calibration`.

No import here loads torch (the parsers are built at start-up).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from cmax._args import float_list, nonnegative_float, sensor_size
from cmax.camera import Camera, intrinsics_matrix
from cmax.io.calibration import DSEC_RECTIFY_MAP, Calibration, read_calibration, topic_side
from cmax.io.provenance import (CALIBRATION_NAMES, check_calibrated_frames, check_raw_dsec, file_intrinsics,
                                resize_note, resized_note, simulated_frames)

__all__ = ["add_file_options", "file_kwargs", "camera_read", "given_k_note", "add_recording_arguments",
           "add_camera_options", "calibration_of", "calibration_note", "check_calibration_camera",
           "read_calibrated", "intrinsics_argument", "no_intrinsics_message", "check_calibration_of_frames",
           "calibration_beside",
           "check_file_principal_point", "RAW_DSEC_CALIB", "RAW_DSEC_AS_RECORDED",
           "distortion_argument",
           "time_slice", "time_span_us", "file_span_us", "tail_note", "overlap", "StreamedEvents",
           "open_streamed", "event_span"]

#: How the command line gives DSEC's calibration for raw events, and says they are wanted as recorded: the words of
#: :func:`cmax.io.provenance.check_raw_dsec`'s refusal in ``cmax fit``, ``cmax emvs`` and ``cmax depth``.
RAW_DSEC_CALIB = "pass --calib {calib} (--calib-camera cam0, the default)"
RAW_DSEC_AS_RECORDED = "--as-recorded"

#: ``argparse`` type of ``--distortion k1,k2,p1,p2[,k3]`` (OpenCV order, dimensionless).
distortion_argument = float_list((4, 5), "--distortion (k1,k2,p1,p2[,k3])")


def add_file_options(parser: argparse.ArgumentParser) -> None:
    """``--size``, ``--time-unit``, ``--polarity``, ``--sort``, ``--camera``: what reading a file that does not
    state them needs (``cmax info``, ``cmax show``); :func:`file_kwargs` turns them into :func:`cmax.io.read`
    keywords."""
    parser.add_argument(
        "--size", type=sensor_size, default=None, metavar="WxH",
        help="sensor size [px], for files that do not store it (ECD text, .npy, original DSEC) "
             "(default: the file's own; a file without one is refused)",
    )
    parser.add_argument("--time-unit", choices=("us", "ms", "s"), default=None,
                        help="unit of the file's time stamps where the file does not state it (default: the format's "
                             "own, e.g. s for ECD text, µs for h5; never guessed where it states none)")
    _add_polarity(parser)
    _add_sort(parser)
    _add_camera(parser)


def _add_camera(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--camera", choices=("left", "right"), default=None,
                        help="camera of an MVSEC file, which holds a left and a right one (davis/left/events, "
                             "davis/right/events; default: left; cmax info names the cameras a file holds); with "
                             "--calib of MVSEC's Kalibr camchain, choose the same camera with --calib-camera "
                             "(cam0 left, cam1 right)")


def _add_polarity(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--polarity", choices=("01", "signed"), default=None,
                        help="polarity encoding of an h5, text or .npy file: 01 (0 OFF, 1 ON) or signed "
                        "(-1 OFF, +1 ON) (default: the format's own: 01; MVSEC: signed; never guessed)")


def _add_sort(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sort", action="store_true",
                        help="sort the events by time where the file's time goes back (ECD text, .npy, AEDAT4: "
                             "files read whole; default: refuse such a file)")


def file_kwargs(args: argparse.Namespace, path: Path | None = None) -> dict[str, int | str | None]:
    """The :func:`cmax.io.read` keywords of :func:`add_file_options`' options, or of
    :func:`add_recording_arguments`' (``polarity`` only when given; ``sort`` only when given,
    and refused for a ``path`` (default ``args.file``) of a format read by time span from disk; ``camera`` only
    when given, and refused for a ``path`` that is not an MVSEC file).

    >>> file_kwargs(argparse.Namespace(size=(346, 260), time_unit="us", polarity=None))
    {'width': 346, 'height': 260, 'time_unit': 'us'}
    """
    width, height = args.size if args.size else (None, None)
    options: dict[str, int | str | None] = {"width": width, "height": height, "time_unit": args.time_unit}
    if getattr(args, "polarity", None) is not None:
        options["polarity"] = args.polarity
    if getattr(args, "sort", False):
        from cmax.io import check_sortable, detect_format

        path = args.file if path is None else path
        check_sortable(path, detect_format(path), True)
        options["sort"] = True
    if getattr(args, "camera", None) is not None:
        from cmax.io import detect_format

        path = args.file if path is None else path
        if (kind := detect_format(path)) != "mvsec":
            raise ValueError(f"--camera applies to MVSEC files (a left and a right camera); {path} is a {kind} "
                             "file of one camera")
        options["camera"] = args.camera
    return options


def camera_read(kind: str, camera: str | None) -> str | None:
    """The camera whose events a command read from a file of format ``kind`` (:func:`cmax.io.detect_format`), for
    its record (``summary.json``): an MVSEC file's ``camera`` (``--camera``; None: its default, ``'left'``), None
    for a file of one camera.

    >>> camera_read("mvsec", None), camera_read("mvsec", "right"), camera_read("dsec", None)
    ('left', 'right', None)
    """
    return (camera or "left") if kind == "mvsec" else None


def add_recording_arguments(parser: argparse.ArgumentParser) -> None:
    """``--size``, ``--time-unit``, ``--polarity``, ``--t0``, ``--t1``, ``--sort``, ``--camera``: what a command
    reading any recording needs (``cmax fit``, ``cmax depth``); :func:`time_slice` applies ``--t0``/``--t1``."""
    parser.add_argument("--size", type=sensor_size, default=None, metavar="WxH",
                        help="sensor size [px] (also W,H), for files that do not store it (ECD .txt, .npy, DSEC as "
                             "shipped) (default: the file's own; a file without one is refused)")
    parser.add_argument("--time-unit", choices=("us", "ms", "s"), default=None,
                        help="unit of the file's time stamps where the file does not state it (default: the format's "
                             "own, e.g. s for ECD text, µs for h5; never guessed where it states none)")
    _add_polarity(parser)
    parser.add_argument("--t0", type=nonnegative_float, default=None,
                        help="start, seconds after the first event (default: the first event)")
    parser.add_argument("--t1", type=nonnegative_float, default=None,
                        help="end, seconds after the first event (default: the last event)")
    _add_sort(parser)
    _add_camera(parser)


def add_camera_options(parser: argparse.ArgumentParser, *, distortion_help: str = "") -> None:
    """``--K`` or ``--calib`` (one of them), ``--calib-camera``, ``--distortion`` and ``--as-recorded``;
    ``distortion_help`` ends the help of ``--distortion`` (what the command does with it)."""
    camera = parser.add_mutually_exclusive_group()
    camera.add_argument("--K", type=intrinsics_argument, default=None,
                        help="intrinsics fx,fy,cx,cy [px] (default: gt/K of an h5 file, e.g. one cmax scene wrote)")
    camera.add_argument("--calib", type=Path, default=None,
                        help="calibration file instead of --K/--distortion: ECD calib.txt (fx fy cx cy k1 k2 p1 p2 "
                             "k3), DSEC cam_to_cam.yaml, ROS camera_info .yaml or a Kalibr camchain .yaml (pinhole; "
                             "radtan or equidistant "
                             "fisheye; the camera --calib-camera); a camchain camera with rectification_matrix and "
                             "projection_matrix (MVSEC's) maps the events into that rectified frame and fits with its "
                             "K [px] (a note says so) (default: none, --K)")
    parser.add_argument("--calib-camera", default="cam0", metavar="NAME",
                        help="camera of a cam_to_cam.yaml: cam0 (raw events, DSEC's own: undistorted and "
                             "rectified with R_rect0 into camRect0's frame, that of DSEC's disparity maps) or camRect0 "
                             "(events already rectified; refused beside DSEC's rectify_map.h5); of a Kalibr camchain: "
                             "cam0, cam1, ... (default cam0)")
    parser.add_argument("--distortion", type=distortion_argument, default=None,
                        help=f"OpenCV k1,k2,p1,p2[,k3] of --K{distortion_help} (default: none, a pinhole camera)")
    parser.add_argument("--as-recorded", action="store_true",
                        help="take events beside DSEC's rectify_map.h5 (raw: distorted, not rectified) as recorded, "
                             "a pinhole's of --K, without --calib (default: off, such events are refused without "
                             "--calib)")


def calibration_note(calibration: Calibration, path: str | Path, camera: str,
                     events: str | Path | None = None) -> str | None:
    """What a command says when the ``--calib`` file ``path`` (camera ``camera``) maps the events into another
    frame than its lens's pinhole: the fisheye model, the rectification and the K the events then have (the one
    fitted); or when a DSEC rectified camera ``camRectN`` takes the events of ``events`` (the recording) as
    already rectified, which no event file states (DSEC ships its events raw); None for a radtan camera without
    rectification."""
    if _is_dsec_rectified(camera, calibration):
        return (f"{path} ({camera}): {camera} is the rectified camera: the events of {events or 'the recording'} are "
                f"taken as already undistorted and rectified (the file cannot say); DSEC's own events "
                f"(events/left/events.h5) are raw: for those pass --calib-camera cam{camera[7:]}, which rectifies "
                f"them into {camera}'s frame")
    if calibration.model != "equidistant" and calibration.rectified_K is None and calibration.rectification is None:
        return None
    K = calibration.pinhole_K
    lens = "an equidistant (fisheye) lens" if calibration.model == "equidistant" else f"a {calibration.model} lens"
    if calibration.rectified_from is not None:
        where = (f"undistorted and rectified (its {calibration.rectified_from}) into the rectified frame, "
                 f"K = fx {K[0, 0]:g}, fy {K[1, 1]:g}, cx {K[0, 2]:g}, cy {K[1, 2]:g} (the frame of DSEC's disparity "
                 "maps and rectify_map.h5); the K and depth maps of the results are that frame's")
    elif calibration.rectified_K is not None or calibration.rectification is not None:
        where = (f"undistorted and rectified (its rectification_matrix / projection_matrix) into the rectified frame, "
                 f"K = fx {K[0, 0]:g}, fy {K[1, 1]:g}, cx {K[0, 2]:g}, cy {K[1, 2]:g} (the frame of a stereo rig's "
                 "rectified depth, e.g. MVSEC's depth_image_rect); the K and depth maps of the results are that "
                 "frame's")
    else:
        where = (f"undistorted onto a pinhole with the lens's K = fx {K[0, 0]:g}, fy {K[1, 1]:g}, cx {K[0, 2]:g}, "
                 f"cy {K[1, 2]:g}")
    return f"{path} ({camera}): {lens}; the events are {where}"


def _is_dsec_rectified(camera: str, calibration: Calibration) -> bool:
    """Whether ``camera`` is a DSEC ``cam_to_cam.yaml``'s rectified camera ``camRectN`` (no distortion)."""
    return camera.startswith("camRect") and camera[7:].isdigit() and calibration.distortion is None


def calibration_of(args: argparse.Namespace) -> Calibration:
    """The :class:`Calibration` of :func:`add_camera_options`' options: ``--K`` and ``--distortion`` (radtan)
    as given (no size), or those of the ``--calib`` file (:func:`cmax.io.read_calibration`), which refuses
    ``--distortion`` beside it. Without ``--calib``, events beside DSEC's ``rectify_map.h5`` (raw) are refused
    unless ``--as-recorded`` (:func:`cmax.io.provenance.check_raw_dsec`)."""
    if args.calib is None:
        if not getattr(args, "as_recorded", False):
            check_raw_dsec(args.file, RAW_DSEC_CALIB, RAW_DSEC_AS_RECORDED)
        if args.calib_camera != "cam0":     # else taken and ignored: the --K (or the file's gt/K) would be used
            raise ValueError(f"--calib-camera {args.calib_camera} chooses a camera of a --calib file (a DSEC "
                             "cam_to_cam.yaml or a Kalibr camchain): give --calib too")
        return Calibration(args.K, None if args.distortion is None else np.asarray(args.distortion, dtype=np.float64),
                           None)
    if args.distortion is not None:
        raise ValueError("--calib gives the distortion: pass --calib or --K with --distortion, not both")
    calibration = read_calibration(args.calib, args.calib_camera)
    if calibration.size is None:
        check_calibration_of_frames(args.calib, calibration.K, calibration.distortion, args.file)
    check_calibration_camera(calibration, args.calib, args.calib_camera, args.file, getattr(args, "camera", None))
    return calibration


def check_calibration_camera(calibration: Calibration, calib: str | Path, calib_camera: str, path: str | Path,
                             camera: str | None) -> None:
    """ValueError when the ``--calib`` camera ``calib_camera`` of ``calib`` is, by its ``rostopic``
    (:func:`cmax.io.calibration.topic_side`), the other camera of the stereo rig than the one whose events are read from the MVSEC file
    ``path`` (``camera``, ``--camera``; None: left): the left camera's lens and rectification would be applied to the
    right camera's events without a word. Files of other formats hold one camera: nothing to check. ValueError
    too when ``calib_camera`` is a DSEC rectified camera ``camRectN`` and DSEC's :data:`DSEC_RECTIFY_MAP` lies
    beside ``path``: those events are raw (distorted, unrectified), and ``camN`` rectifies them."""
    if _is_dsec_rectified(calib_camera, calibration) and (Path(path).parent / DSEC_RECTIFY_MAP).is_file():
        raise ValueError(f"{calib}: {calib_camera} is the rectified camera, but {Path(path).parent / DSEC_RECTIFY_MAP} "
                         f"lies beside {path}: DSEC's events are raw (distorted, not rectified); pass --calib-camera "
                         f"cam{calib_camera[7:]} to undistort and rectify them into {calib_camera}'s frame")
    side = topic_side(calibration.topic)
    if side is None:
        return
    from cmax.io import detect_format

    try:
        if detect_format(path) != "mvsec":
            return
    except (OSError, ValueError):
        return                                   # the reader says what is wrong with the file, in its own words
    read = camera or "left"
    if side != read:
        default = "" if camera else ", the default"
        raise ValueError(f"{calib}: {calib_camera} is the {side} camera (rostopic {calibration.topic.strip()}), "
                         f"but the events of {path} are the {read} camera's (--camera {read}{default}): choose the "
                         f"camchain's {read} camera with --calib-camera (MVSEC: cam0 left, cam1 right), or --camera "
                         f"{side}")


#: MVSEC's Kalibr camchains (``camchain-imucam-indoor_flying.yaml``, ...), which :func:`calibration_hint` names too.
MVSEC_CAMCHAIN_GLOB = "camchain-imucam-*.yaml"


def calibration_beside(path: str | Path) -> Path | None:
    """The first data-set calibration file that lies beside the event file ``path``: ``calib.txt`` (ECD),
    ``cam_to_cam.yaml`` (DSEC) or an MVSEC camchain (:data:`MVSEC_CAMCHAIN_GLOB`), looked for in its folder, that
    folder's ``calibration/``, the folder above and its ``calibration/``, and the ``calibration/`` two folders above
    (DSEC's ``<sequence>/events/left/events.h5`` beside ``<sequence>/calibration/cam_to_cam.yaml``); None when there
    is none. Found, never read."""
    folder = Path(path).resolve().parent
    for place in (folder, folder / "calibration", folder.parent, folder.parent / "calibration",
                  folder.parent.parent / "calibration"):
        for name in (*CALIBRATION_NAMES, *sorted(p.name for p in place.glob(MVSEC_CAMCHAIN_GLOB))):
            if (place / name).is_file():
                return place / name
    return None


def _dsec_camera_words(calib: Path) -> str:
    """What ``--calib-camera`` a DSEC ``cam_to_cam.yaml`` takes for its raw events; empty for another file."""
    return (" (DSEC: --calib-camera cam0, the default, for its raw events, which it rectifies into camRect0's frame)"
            if calib.name == "cam_to_cam.yaml" else "")


def calibration_hint(args: argparse.Namespace) -> str | None:
    """A note when no ``--calib`` or ``--distortion`` was given but a data set's calibration file lies beside
    ``args.file`` (its folder or the one above, or a ``calibration/`` folder in either or two folders above, as in
    DSEC's ``<sequence>/events/left/events.h5`` and ``<sequence>/calibration/cam_to_cam.yaml``; an MVSEC camchain
    :data:`MVSEC_CAMCHAIN_GLOB` too), or DSEC's ``rectify_map.h5`` lies beside it without a calibration file
    (the events are raw; nothing under ``--as-recorded``, which says they are wanted so), or the file is
    MVSEC's (whose fisheye lenses a pinhole misses: the note names the camchain to pass), or None. It is not read (never guessed): the note says how to use it."""
    if args.calib is not None or args.distortion is not None:
        return None
    folder = Path(args.file).resolve().parent
    if (found := calibration_beside(args.file)) is not None:
        return (f"{found} lies beside the events but was not read: pass --calib {found}{_dsec_camera_words(found)} "
                "to use its intrinsics and lens distortion (without it the camera is a pinhole; a lens's "
                "distortion biases the fitted rotation and depth, docs/limits.md)")
    if (folder / DSEC_RECTIFY_MAP).is_file() and not getattr(args, "as_recorded", False):   # DSEC's, no calibration
        return (f"DSEC's {folder / DSEC_RECTIFY_MAP} lies beside the events, so they are raw (distorted, not "
                "rectified into camRect0's frame, that of DSEC's disparity maps) and are fitted as a pinhole's: pass "
                "--calib <sequence>/calibration/cam_to_cam.yaml (DSEC's calibration download; --calib-camera cam0, "
                "the default), which undistorts and rectifies them")
    from cmax.io import detect_format

    try:
        mvsec = detect_format(args.file) == "mvsec"
    except (OSError, ValueError):
        return None
    if mvsec:
        return ("MVSEC's DAVIS cameras look through fisheye lenses (Kalibr equidistant: far from a pinhole's "
                "image toward the corners) and its depth maps are rectified: without --calib the events are "
                "fitted as a pinhole's; pass --calib camchain-imucam-<sequence>.yaml, MVSEC's calibration of the "
                "sequence (--calib-camera cam0 left, cam1 right), to undistort and rectify them")
    return None


def read_calibrated(args: argparse.Namespace, calib_size: tuple[int, int] | None):
    """``(events, origin_us)``: the events of ``args.file`` (:func:`cmax.io.read` with :func:`file_kwargs`) between
    ``--t0`` and ``--t1`` (:func:`time_slice`), and the time [µs] of the file's first event, which ``--t0`` and
    the times a command prints count from; a file that stores no size takes the calibration's (``calib_size``, from
    :func:`calibration_of`) unless ``--size`` gives one. A DSEC-layout h5 file is read from disk only over that
    span, a Prophesee RAW file decoded up to its end holding only the span (a recording too long to hold,
    :data:`cmax.events.MAX_EVENTS`, can be fitted a part at a time); other formats are decoded whole, then cut.
    Refuses a file without events and events of another sensor than the calibrated one."""
    from cmax.events import EventLimitError
    from cmax.io import detect_format, read

    options = file_kwargs(args)
    t0_s, t1_s = getattr(args, "t0", None), getattr(args, "t1", None)

    def read_span(**size):
        span = file_span_us(args.file, {**options, **size}, t0_s, t1_s)
        bounds = {} if span is None else {"t0_us": span[1], "t1_us": span[2]}
        events = read(args.file, **{**options, **size, **bounds})
        if span is None:
            origin = int(events.t[0]) if len(events) else 0
            return (events if not len(events) else time_slice(events, t0_s, t1_s)), origin
        if len(events) == 0:
            raise ValueError(f"no events between --t0 {t0_s} s and --t1 {t1_s} s")
        return events, span[0]

    try:
        try:
            events, origin = read_span()
        except ValueError as error:   # a file that stores no size: the calibration's resolution, when it has one
            if calib_size is None or args.size is not None or "width=" not in str(error):
                raise
            events, origin = read_span(width=calib_size[0], height=calib_size[1])
    except EventLimitError as error:
        if detect_format(args.file) not in ("dsec", "raw"):
            raise
        raise EventLimitError(f"{error}; on the command line, --t0 / --t1 read a part of it") from None
    if len(events) == 0:
        raise ValueError(f"{args.file} holds no events")
    _check_calibrated_size(args, calib_size, events.width, events.height)
    return events, origin


def _check_calibrated_size(args: argparse.Namespace, calib_size: tuple[int, int] | None, width: int,
                           height: int) -> None:
    """ValueError when the events come from another sensor than the one ``--calib`` calibrates: the size the
    calibration states (``calib_size``), or for one that states none, the size of the frames of the ECD sequence
    it lies in (:func:`cmax.io.provenance.check_calibrated_frames`)."""
    if calib_size is not None and (width, height) != tuple(calib_size):
        raise ValueError(f"{args.calib} calibrates a {calib_size[0]}x{calib_size[1]} camera ({args.calib_camera}), "
                         f"the events come from a {width}x{height} sensor")
    if calib_size is None and getattr(args, "calib", None) is not None:
        check_calibrated_frames(args.calib, args.file, width, height)


def file_span_us(path, options: dict, t0_s: float | None,
                 t1_s: float | None) -> tuple[int, int, int | None] | None:
    """``(first_us, t0_us, t1_us)``: a file's first event and the absolute span [µs] of ``--t0`` / ``--t1``, for
    the files that can be read a span at a time, from their first event alone (and last, for a DSEC-layout h5:
    :class:`cmax.io.H5Reader`; a Prophesee RAW file's first chunk, :func:`cmax.io.prophesee.iter_raw`, its end
    open without ``--t1``); None for other formats, an empty file, or when neither bound is given. ``options``:
    the :func:`cmax.io.read` keywords of the file."""
    from cmax.io import H5Reader, detect_format
    from cmax.io.prophesee import iter_raw

    if t0_s is None and t1_s is None:
        return None
    kind = detect_format(path)
    if kind == "dsec":
        with H5Reader(path, **options) as reader:
            if not len(reader):
                return None
            return (reader.t_start, *time_span_us(reader.t_start, reader.t_end, t0_s, t1_s))
    if kind == "raw" and options.get("time_unit") in (None, "us") and "polarity" not in options:
        first = next(iter_raw(path, width=options.get("width"), height=options.get("height")), None)
        if first is None:
            return None
        return (int(first.t[0]), *time_span_us(int(first.t[0]), None, t0_s, t1_s))
    return None


def intrinsics_argument(text: str) -> np.ndarray:
    """``argparse`` type of ``--K fx,fy,cx,cy`` [px]: the validated (3, 3) float64 matrix (``cmax fit``,
    ``cmax emvs``, ``python -m learned.predict``).

    >>> intrinsics_argument("200,200,120,90")
    array([[200.,   0., 120.],
           [  0., 200.,  90.],
           [  0.,   0.,   1.]])
    """
    try:
        fx, fy, cx, cy = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--K must be fx,fy,cx,cy (four numbers), got {text!r}") from None
    try:
        return intrinsics_matrix([fx, fy, cx, cy])
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"--K: {error}") from None


def given_k_note(path: str | Path, given: np.ndarray | None) -> str | None:
    """A note when the h5 file ``path`` stores a ``gt/K`` (3, 3) [px] other than the ``given`` one (``--K`` /
    ``--calib``), which is used: the file's is the camera it was rendered or simulated with (``cmax scene``,
    ``cmax simulate --K``). None when either is missing (or the stored one is invalid) or they agree.

    >>> given_k_note("missing.h5", np.eye(3)) is None
    True
    """
    if given is None:
        return None
    try:
        stored = file_intrinsics(path)
    except (ValueError, OSError):
        return None
    if stored is None or np.allclose(stored, given, rtol=1e-6, atol=1e-9):
        return None

    def words(K: np.ndarray) -> str:
        return f"fx {K[0, 0]:g}, fy {K[1, 1]:g}, cx {K[0, 2]:g}, cy {K[1, 2]:g}"

    return (f"{path} stores gt/K ({words(stored)}) unlike the K given ({words(np.asarray(given))}): the given one is "
            "used; leave --K / --calib out to use the file's")


def no_intrinsics_message(path: str | Path, calib: str = "--calib FILE") -> str:
    """The error for an event file that stores no ``gt/K`` and was given no ``--K`` / ``--calib``: what to pass,
    and for a ``cmax simulate`` conversion where its K comes from (:func:`cmax.io.provenance.resized_note`); the
    file is opened once."""
    message = f"{path} stores no intrinsics (gt/K): give them with --K fx,fy,cx,cy or {calib}"
    sizes, beside = simulated_frames(path)
    if sizes is None:
        found = calibration_beside(path)
        return message if found is None else (f"{message}; {found} lies beside the events: --calib {found}"
                                              f"{_dsec_camera_words(found)}")
    if beside is not None:
        message += f"; {beside} lies beside the frames it was simulated from"
    if sizes[0] == sizes[1]:
        return (f"{message} (a conversion of frames by cmax simulate: the intrinsics of the camera that shot them, "
                "when known; a video carries none)" if beside is None else f"{message}: --calib {beside}")
    return f"{message}; {resize_note(path, sizes)}"


def check_calibration_of_frames(calib: str | Path, K: np.ndarray, distortion: np.ndarray | None,
                                path: str | Path) -> None:
    """Refuse the calibration file ``calib`` (intrinsics ``K`` (3, 3) [px], OpenCV ``distortion``) for the event
    file ``path`` when ``calib`` is the one beside the frames a ``cmax simulate`` conversion was made from
    (:func:`cmax.io.provenance.source_calibration`) and ``--size`` resized those frames
    (:func:`cmax.io.provenance.simulated_sizes`): it calibrates the frames, not the file's pixels, and used as it is every focal length and the principal point would be off by
    the scale (an ECD ``calib.txt`` states no resolution, so nothing else tells). The error gives the scaled
    ``--K`` (:meth:`cmax.camera.Camera.scaled`, ``cv2.resize``'s pixel centres) and the same ``--distortion`` (its
    coefficients act on normalised coordinates, which a scaling leaves alone)."""
    sizes, beside = simulated_frames(path)
    if sizes is None or sizes[0] == sizes[1] or beside is None or not _same_file(beside, calib):
        return
    (W, H), (w, h) = sizes
    frames = Camera(K, W, H).scaled(w, h)
    scaled = f"--K {frames.fx:.6g},{frames.fy:.6g},{frames.cx:.6g},{frames.cy:.6g}"
    if distortion is not None and np.any(distortion):
        scaled += " --distortion " + ",".join(f"{v:.9g}" for v in distortion)
    raise ValueError(f"{calib} calibrates the {W}x{H} frames that {path} was simulated from, but --size resized "
                     f"them to {w}x{h}: its intrinsics do not fit these pixels; give them scaled: {scaled}")


def _same_file(a: str | Path, b: str | Path) -> bool:
    """Whether two paths name one file (False when either is missing)."""
    try:
        return Path(a).samefile(b)
    except OSError:
        return False


def check_file_principal_point(K: np.ndarray, path: str | Path, width: int, height: int, name: str = "K") -> None:
    """:func:`cmax.camera.check_principal_point` for the event file ``path``, its error followed by
    :func:`cmax.io.provenance.resized_note` when ``--size`` resized its frames (the usual cause: the frames'
    calibration, unscaled)."""
    from cmax.camera import check_principal_point

    try:
        check_principal_point(K, width, height, name)
    except ValueError as error:
        note = resized_note(path)
        raise ValueError(str(error) if note is None else f"{error}; {note}") from None


def time_span_us(first_us: int, last_us: int | None, t0_s: float | None,
                 t1_s: float | None) -> tuple[int, int | None]:
    """``[t0, t1)`` [µs, absolute] of ``--t0`` / ``--t1`` (seconds after the first event ``first_us``; None: no
    bound) in a recording whose last event is at ``last_us`` (None: not known yet, ``t1`` then None without
    ``--t1``); ValueError when that span is empty.

    >>> time_span_us(1_000_000, 1_900_000, 0.25, 0.5)
    (1250000, 1500000)
    """
    t0 = first_us + int(round((t0_s or 0.0) * 1e6))
    if t1_s is None and last_us is None:
        return t0, None
    t1 = last_us + 1 if t1_s is None else first_us + int(round(t1_s * 1e6))
    if t1_s is None and t0 >= t1:
        raise ValueError(f"--t0 {t0_s} s is past the recording's last event ({(last_us - first_us) * 1e-6:.6f} s "
                         "after its first)")
    if t1 <= t0:
        start = "0.0 (the first event, --t0 left out)" if t0_s is None else t0_s   # was: "got None and 0.0"
        raise ValueError(f"--t1 must be after --t0, got {start} and {t1_s}")
    return t0, t1


def time_slice(events, t0_s: float | None, t1_s: float | None):
    """The events of ``[first + t0_s, first + t1_s)`` (seconds after the first event; None: no bound).

    >>> import numpy as np
    >>> from cmax.events import Events
    >>> t_us = np.arange(0, 1_000_000, 100_000)  # one event every 0.1 s
    >>> events = Events(np.zeros(10), np.zeros(10), t_us, np.ones(10), 4, 4)
    >>> time_slice(events, 0.25, 0.5).t.tolist()
    [300000, 400000]
    """
    if t0_s is None and t1_s is None:
        return events
    events = events.slice_time(*time_span_us(int(events.t[0]), int(events.t[-1]), t0_s, t1_s))
    if len(events) == 0:
        raise ValueError(f"no events between --t0 {t0_s} s and --t1 {t1_s} s")
    return events


#: :func:`tail_note` is silent about an end shorter than this fraction of a window (the few µs that windows of whole
#: µs leave when they cannot divide the recording exactly).
TAIL_NOTE_FRACTION = 0.01


def tail_note(first_us: int, last_us: int, window_us: int, step_us: int, *, option: str = "--window-ms",
              unit_us: int = 1000, events: int | None = None, origin_us: int | None = None) -> str | None:
    """The note of a window-by-window command on the end of the recording that its whole windows leave out
    (:func:`cmax.events.uncovered_tail`), with a window length ``option`` (in units of ``unit_us`` µs) whose
    windows tile the recording (when the windows do not overlap: up to a few µs, as whole µs rarely divide the
    recording); None when nothing, or less than :data:`TAIL_NOTE_FRACTION` of a window, is left out.
    ``events``: how many events that end holds (said when given); ``origin_us``: where the times it gives count
    from (the file's first event when ``--t0`` cut the events; default ``first_us``).

    >>> print(tail_note(0, 2_499_999, 1_000_000, 1_000_000))
    the last 500.0 ms of the recording (after 2.000 s) are shorter than a window (1000.0 ms) and are left out: --window-ms 833.333 covers it in 3 windows
    >>> tail_note(0, 2_999_999, 1_000_000, 1_000_000) is None
    True
    >>> print(tail_note(0, 4_999_999, 1_000_000, 3_000_000))
    windows of 1000 ms every 3000 ms leave the 2000 ms between them out, and the last 1000 ms of the recording (after 4.000 s), where the next step has no whole window
    >>> print(tail_note(0, 2_979, 1_000, 1_000))
    the last 0.980 ms of the recording (after 0.002 s) are shorter than a window (1.000 ms) and are left out: --window-ms 0.993 covers it in 3 windows
    """
    from cmax.events import uncovered_tail

    tail = uncovered_tail(first_us, last_us, window_us, step_us)
    if tail is None or tail[1] - tail[0] < TAIL_NOTE_FRACTION * window_us:
        return None
    start, end = tail
    held = "" if events is None else f", {events:,} events"
    origin = first_us if origin_us is None else origin_us
    tail_ms, window_ms = (end - start) * 1e-3, window_us * 1e-3
    digits = 1 if f"{tail_ms:.1f}" != f"{window_ms:.1f}" else 3       # 0.980 ms is not "1.0 ms" < 1.0 ms
    if step_us > window_us:     # the windows leave gaps: the end is short of a step, not of a window
        def ms(value_us: int) -> str:
            return f"{value_us * 1e-3:.3f}".rstrip("0").rstrip(".")

        return (f"windows of {ms(window_us)} ms every {ms(step_us)} ms leave the {ms(step_us - window_us)} ms between "
                f"them out, and the last {ms(end - start)} ms of the recording (after "
                f"{(start - origin) * 1e-6:.3f} s{held}), where the next step has no whole window")
    text = (f"the last {tail_ms:.{digits}f} ms of the recording (after {(start - origin) * 1e-6:.3f} s{held}) "
            f"are shorter than a window ({window_ms:.{digits}f} ms) and are left out")
    if step_us == window_us:
        span = int(last_us) - int(first_us) + 1
        count = -(-span // int(window_us))                  # ceil: windows a little shorter than asked
        length = span // count                              # whole µs, so that `count` of them fit in the span
        digits = len(str(unit_us)) - 1                      # down to 1 µs: 3 for ms, 6 for s
        value = f"{length / unit_us:.{digits}f}".rstrip("0").rstrip(".")
        text += f": {option} {value} covers it in {count} windows"
    return text


def overlap(events, times_us: np.ndarray, what: str, source: object, doing: str):
    """The events inside ``[times_us[0], times_us[-1]]`` (a gyroscope's samples, a trajectory's poses [µs], on
    the events' clock), and a note when some were cut (None when none); ValueError when nothing overlaps.
    ``events``: :class:`cmax.events.Events` or :class:`StreamedEvents` (whose cut events are not counted).
    ``what`` names the samples in the texts (a plural: ``"gyro samples"``, ``"poses"``), ``source`` their file,
    ``doing`` ends the note (e.g. ``"fitting the overlap"``).
    """
    first, last = event_span(events)
    lo, hi = max(first, int(times_us[0])), min(last, int(times_us[-1]))
    if hi <= lo:
        raise ValueError(f"the {what} of {source} ({times_us[0] * 1e-6:.6f}-{times_us[-1] * 1e-6:.6f} s) do not "
                         f"overlap the events ({first * 1e-6:.6f}-{last * 1e-6:.6f} s): are they on the same clock?")
    if lo == first and hi == last:
        return events, None
    kept = events.slice_time(lo, hi + 1)
    count = "" if isinstance(events, StreamedEvents) else f", {len(events) - len(kept):,} events"
    note = (f"the {what} of {source} cover {(hi - lo) * 1e-3:.1f} ms of the {(last - first) * 1e-3:.1f} ms of events "
            f"(cut {(lo - first) * 1e-3:.1f} ms at the start, {(last - hi) * 1e-3:.1f} ms at the end{count}): {doing}")
    return kept, note


def event_span(events) -> tuple[int, int]:
    """The first and last event times [µs] of :class:`cmax.events.Events` or :class:`StreamedEvents`."""
    if isinstance(events, StreamedEvents):
        return events.t_start, events.t_end
    return int(events.t[0]), int(events.t[-1])


class StreamedEvents:
    """A recording too long to hold, read window by window from a DSEC-layout h5 file
    (:class:`cmax.io.H5Reader`): the reader protocol of :func:`cmax.fitting.fit_sequence` (``window(t0_us,
    t1_us)``, ``t_start``, ``t_end``) with ``width``, ``height``, a span cut to ``[t_start, t_end]``
    (:meth:`slice_time`) and a ``transform`` applied to every window read (e.g. the undistortion)."""

    def __init__(self, reader, t_start: int, t_end: int, transform=None) -> None:
        self.reader, self.t_start, self.t_end, self.transform = reader, int(t_start), int(t_end), transform
        self.width, self.height = reader.width, reader.height

    def window(self, t0_us: int, t1_us: int):
        """The (transformed) events of ``[t0_us, t1_us)`` inside the span."""
        events = self.reader.window(max(int(t0_us), self.t_start), max(min(int(t1_us), self.t_end + 1), self.t_start))
        return events if self.transform is None else self.transform(events)

    def slice_time(self, t0_us: int, t1_us: int) -> "StreamedEvents":
        """The same recording over ``[t0_us, t1_us)`` (nothing is read)."""
        return StreamedEvents(self.reader, max(self.t_start, int(t0_us)), min(self.t_end, int(t1_us) - 1),
                              self.transform)

    def with_transform(self, transform) -> "StreamedEvents":
        """The same recording with ``transform`` applied to every window (after any it had)."""
        before = self.transform
        return StreamedEvents(self.reader, self.t_start, self.t_end,
                              transform if before is None else (lambda events: transform(before(events))))

    def close(self) -> None:
        self.reader.close()


def open_streamed(args: argparse.Namespace, calib_size: tuple[int, int] | None) -> StreamedEvents | None:
    """``args.file`` as :class:`StreamedEvents` when it is a DSEC-layout h5 file (None otherwise), its size from
    ``--size`` or the calibration (``calib_size``) when it stores none; checked as :func:`read_calibrated`
    checks the events (none, another sensor than the calibrated one)."""
    from cmax.io import H5Reader, detect_format

    if detect_format(args.file) != "dsec":
        return None
    options = file_kwargs(args)
    if options.get("width") is None and calib_size is not None:
        options.update(width=calib_size[0], height=calib_size[1])
    reader = H5Reader(args.file, **options)
    try:
        if not len(reader):
            raise ValueError(f"{args.file} holds no events")
        _check_calibrated_size(args, calib_size, reader.width, reader.height)
    except BaseException:
        reader.close()
        raise
    return StreamedEvents(reader, reader.t_start, reader.t_end)
