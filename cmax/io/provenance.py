"""What an h5 event file written by cmax records beside its events: the camera (``gt/K``), the scene of
``cmax scene`` (its depth range), and the frames a ``cmax simulate`` conversion came from (their size before
``--size``, the folder they lie in, a calibration file beside them).

Reading only: every function opens the file read-only and answers None for a file that records nothing (or is no
h5 file). The command line (:mod:`cmax.cli.recording`) and :mod:`learned.data` word their notes and refusals
from these.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from cmax.camera import check_intrinsics

__all__ = ["CALIBRATION_NAMES", "file_intrinsics", "h5_intrinsics", "file_depth_range", "simulated_frames",
           "simulated_sizes", "source_calibration", "resized_note", "resize_note", "calibrated_frames",
           "check_calibrated_frames", "dsec_calibration_path", "check_raw_dsec"]

#: Calibration files the data sets ship beside their recordings: ECD's ``calib.txt``, DSEC's ``cam_to_cam.yaml``.
CALIBRATION_NAMES = ("calib.txt", "cam_to_cam.yaml")
#: The h5 attributes of a ``cmax simulate`` conversion that say where its frames came from.
_CONVERSION_ATTRS = ("source_size", "width", "height", "source")

#: ``((W, H) of the frames, (w, h) of the sensor)`` [px] of a conversion.
Sizes = tuple[tuple[int, int], tuple[int, int]]


def file_intrinsics(path: str | Path) -> np.ndarray | None:
    """``gt/K`` (3, 3) [px] of the h5 event file ``path`` (as ``cmax scene`` and the simulator write it), validated;
    None when the file is not h5 or stores none (ValueError when it stores a bad one)."""
    import h5py

    try:
        file = h5py.File(path, "r")
    except OSError:                     # not an h5 file
        return None
    with file:
        return h5_intrinsics(file, path)


def h5_intrinsics(file, path: str | Path) -> np.ndarray | None:
    """``gt/K`` (3, 3) [px] of an open h5 ``file`` (``h5py.File``) whose path is ``path``, validated; None when it
    stores none (ValueError, naming ``path``, when it stores a bad one)."""
    if "gt" not in file or "K" not in file["gt"]:
        return None
    try:
        return check_intrinsics(np.asarray(file["gt/K"][()]), f"{path}: gt/K")
    except TypeError as error:
        raise ValueError(str(error)) from None


def file_depth_range(path: str | Path) -> tuple[float, float] | None:
    """``(near, far)`` [m] that the h5 file ``path`` of ``cmax scene`` records for its scene (attribute ``scene``,
    ``depth_range_m``); None for any other file, or a record without a valid range."""
    import h5py

    try:
        with h5py.File(path, "r") as file:
            record = file.attrs.get("scene")
    except OSError:                     # not an h5 file
        return None
    try:
        near, far = (float(v) for v in json.loads(record)["depth_range_m"])
    except (TypeError, ValueError, KeyError):
        return None
    return (near, far) if 0 < near < far < float("inf") else None


def simulated_frames(path: str | Path) -> tuple[Sizes | None, Path | None]:
    """``(sizes, calibration)`` of a ``cmax simulate`` conversion ``path``, from one opening of the file: its
    :func:`simulated_sizes` and its :func:`source_calibration` (each None when the file does not record it)."""
    attrs = _conversion_attrs(path)
    return _sizes_of(attrs), _calibration_beside(attrs)


def simulated_sizes(path: str | Path) -> Sizes | None:
    """``((W, H) of the frames, (w, h) of the sensor)`` [px] of the ``cmax simulate`` conversion ``path`` (h5
    attribute ``source_size``: the frames' size before ``--size``), or None for any other file."""
    return _sizes_of(_conversion_attrs(path))


def source_calibration(path: str | Path) -> Path | None:
    """A calibration file (:data:`CALIBRATION_NAMES`) in the folder the ``cmax simulate`` conversion ``path`` was
    made from (h5 attribute ``source``: an ECD or rpg_vid2e image folder, its ``images/``, or a timestamp file, or
    the folder above), or None."""
    return _calibration_beside(_conversion_attrs(path))


def resized_note(path: str | Path) -> str | None:
    """For the ``cmax simulate`` conversion ``path`` whose frames ``--size`` resized (:func:`simulated_sizes`): how
    a K of those frames scales to its pixels (``cv2.resize``'s pixel centres: ``cx' = (cx + 0.5) sx - 0.5``); else
    None."""
    return resize_note(path, simulated_sizes(path))


def resize_note(path: str | Path, sizes: Sizes | None) -> str | None:
    """:func:`resized_note` of the file ``path`` whose :func:`simulated_sizes` are ``sizes`` (``((W, H), (w, h))``
    [px], or None), without opening it; None when the sizes are unknown or equal.

    >>> print(resize_note("conv.h5", ((48, 32), (24, 16))))
    conv.h5 was simulated from 48x32 frames resized to 24x16 (--size): a K of those frames scales to fx*0.5, fy*0.5, (cx+0.5)*0.5-0.5, (cy+0.5)*0.5-0.5
    """
    if sizes is None or sizes[0] == sizes[1]:
        return None
    (W, H), (w, h) = sizes
    sx, sy = w / W, h / H
    return (f"{path} was simulated from {W}x{H} frames resized to {w}x{h} (--size): a K of those frames scales "
            f"to fx*{sx:.6g}, fy*{sy:.6g}, (cx+0.5)*{sx:.6g}-0.5, (cy+0.5)*{sy:.6g}-0.5")


def _conversion_attrs(path: str | Path) -> dict:
    """The attributes of :data:`_CONVERSION_ATTRS` that the h5 file ``path`` holds, read in one opening (empty for
    a file that is not h5)."""
    import h5py

    try:
        with h5py.File(path, "r") as file:
            return {key: file.attrs[key] for key in _CONVERSION_ATTRS if key in file.attrs}
    except (OSError, KeyError, TypeError, ValueError):   # not an h5 file, or unreadable attributes
        return {}


def _sizes_of(attrs: dict) -> Sizes | None:
    """:func:`simulated_sizes` of a file's :func:`_conversion_attrs`."""
    try:
        stored = [int(v) for v in json.loads(attrs["source_size"])]
        size = (int(attrs["width"]), int(attrs["height"]))
    except (KeyError, TypeError, ValueError):   # not a conversion, or one of unknown frames
        return None
    if len(stored) != 2 or min(stored) <= 0:
        return None
    return (stored[0], stored[1]), size


def _calibration_beside(attrs: dict) -> Path | None:
    """:func:`source_calibration` of a file's :func:`_conversion_attrs`."""
    if "source" not in attrs:
        return None
    source = Path(str(attrs["source"]))
    folder = source if source.is_dir() else source.parent
    for place in (folder, folder.parent):
        for name in CALIBRATION_NAMES:
            if (place / name).is_file():
                return place / name
    return None


#: The first bytes of a PNG file and the type of its first chunk, whose first 8 bytes are its width and height.
_PNG_SIGNATURE, _PNG_HEADER = b"\x89PNG\r\n\x1a\n", b"IHDR"


def calibrated_frames(calib: str | Path) -> tuple[tuple[int, int], Path] | None:
    """``((width, height) [px], frame)``: the size of the first frame of the sequence the calibration file
    ``calib`` lies in, where it lies in an Event Camera Dataset sequence (ECD: ``calib.txt`` beside ``images.txt``,
    whose first line ``t images/frame_00000000.png`` names a PNG frame of the same sensor); None where there is no
    such list or its first frame is no readable PNG. The size is the PNG's own (its IHDR chunk): the sensor that
    ``calib``, which states none, calibrates. Only the list's first line and the frame's first 24 bytes are read.

    >>> calibrated_frames("no/such/calib.txt") is None
    True
    """
    folder = Path(calib).parent
    try:
        with open(folder / "images.txt", encoding="utf-8", errors="replace") as listing:
            first = next((line for line in listing if line.strip() and not line.lstrip().startswith("#")), "")
        fields = first.split()
        if len(fields) < 2:
            return None
        frame = folder / fields[1]
        with open(frame, "rb") as png:
            head = png.read(24)
    except OSError:
        return None
    if len(head) < 24 or head[:8] != _PNG_SIGNATURE or head[12:16] != _PNG_HEADER:
        return None
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    return ((width, height), frame) if width > 0 and height > 0 else None


def check_calibrated_frames(calib: str | Path, path: str | Path, width: int, height: int) -> None:
    """ValueError when the calibration file ``calib``, which states no sensor size, lies in a sequence whose frames
    (:func:`calibrated_frames`) are of another size than the ``width`` x ``height`` [px] sensor of the events of
    ``path``: it calibrates another camera (ECD's DAVIS240C ``calib.txt`` for a DAVIS346's events). Nothing is
    checked where no frames lie beside it: a calib.txt alone cannot tell its sensor.

    >>> check_calibrated_frames("no/such/calib.txt", "ev.h5", 346, 260)
    """
    frames = calibrated_frames(calib)
    if frames is not None and frames[0] != (width, height):
        (W, H), frame = frames
        raise ValueError(f"{calib} states no sensor size, but the frames of its sequence ({frame}, listed in "
                         f"images.txt beside it) are {W}x{H}: it calibrates a {W}x{H} sensor, the events of {path} "
                         f"come from a {width}x{height} one; give this sensor's calibration")


def dsec_calibration_path(path: str | Path) -> str:
    """DSEC's ``<sequence>/calibration/cam_to_cam.yaml`` of its events ``path`` (``<sequence>/events/left/events.h5``)
    where it exists, else that pattern.

    >>> dsec_calibration_path("no/such/events.h5")
    '<sequence>/calibration/cam_to_cam.yaml'
    """
    found = Path(path).resolve().parents[2:3]
    found = [place / "calibration" / "cam_to_cam.yaml" for place in found]
    return str(found[0]) if found and found[0].is_file() else "<sequence>/calibration/cam_to_cam.yaml"


def check_raw_dsec(path: str | Path, give: str, as_recorded: str) -> None:
    """ValueError when DSEC's ``rectify_map.h5`` lies beside the event file ``path``: its events are raw
    (distorted, not rectified into camRect0's frame, the frame of DSEC's disparity maps), and the caller, which
    calls this only where no calibration was given, would take them as a pinhole's. The one policy of ``cmax fit``,
    ``cmax emvs``, ``cmax depth`` and ``learned.train``; each words how to give the calibration, ``give`` (a
    format string whose ``{calib}`` is :func:`dsec_calibration_path` and ``{map}`` the rectify_map.h5), and how
    to say the events are wanted as recorded, ``as_recorded``.

    >>> check_raw_dsec("no/such/events.h5", "--calib {calib}", "--as-recorded")
    """
    from cmax.io.calibration import DSEC_RECTIFY_MAP

    beside = Path(path).parent / DSEC_RECTIFY_MAP
    if not beside.is_file():
        return
    how = give.format(calib=dsec_calibration_path(path), map=beside)
    raise ValueError(f"DSEC's {beside} lies beside {path}, so its events are raw (distorted, not rectified into "
                     f"camRect0's frame, whose K DSEC's disparity maps have), and no calibration was given: {how}, "
                     f"which rectifies them into that frame and gives its K; or {as_recorded} to take them as "
                     "recorded (a pinhole's, unrectified)")
