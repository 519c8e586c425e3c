"""Event file formats: one :func:`read` that detects the format, and one writer layout.

==================  ==========================  ========================================================================
format              detected by                 reader
==================  ==========================  ========================================================================
DSEC HDF5           ``events/{x,y,t,p}``        :func:`read_h5`, :class:`H5Reader`
MVSEC HDF5          ``davis/<cam>/events``      :func:`read_mvsec`
ECD text            ``.txt``                    :func:`read_txt` (width/height, or a ``W H`` first line)
AEDAT 4.0           ``#!AER-DAT4.0`` magic      :func:`read_aedat4`, :func:`read_aedat4_imu`, :func:`read_aedat4_frames`
Prophesee EVT2/3    ``%`` header, ``.raw``      :func:`read_raw`, :func:`read_evt2`, :func:`read_evt3`
NumPy               ``.npy`` structured x,y,t,p :meth:`Events.from_structured`
==================  ==========================  ========================================================================

Every reader raises :class:`FormatError` (a :class:`ValueError`) on bytes it
cannot decode. Files are written in the DSEC layout only (:func:`write_h5`,
:class:`H5Writer`). Calibration files (ECD ``calib.txt``, DSEC ``cam_to_cam.yaml``,
Kalibr camchains, ROS ``camera_info``) are read by :func:`read_calibration` into a
:class:`Calibration` (:mod:`cmax.io.calibration`).
"""
from __future__ import annotations

import bisect
import inspect
import os
import warnings
import zipfile
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from cmax.events import Events, check_duplicate_fields, check_event_count, field_rename_hint, structured_fields
from cmax.io._checks import (check_implied_rate, check_not_nanoseconds, check_polarity_encoding, check_stated_size,
                             check_time_unit, polarity_01, times_to_us)
from cmax.io.aedat4 import read_aedat4, read_aedat4_frames, read_aedat4_imu
from cmax.io.calibration import Calibration, read_calibration
from cmax.io.errors import FormatError
from cmax.io.gyro import read_gyro
from cmax.io.h5 import H5_ERRORS, H5Reader, H5Writer, is_dsec_h5, read_h5, write_h5
from cmax.io.mvsec import MVSEC_CAMERAS, MVSEC_HEIGHT, MVSEC_WIDTH, read_mvsec
from cmax.io.prophesee import read_evt2, read_evt3, read_raw, write_evt2, write_evt3
from cmax.io.prophesee.reader import sorted_copy_line
from cmax.io.text import read_txt, write_txt

__all__ = [
    "FormatError", "SORTABLE_FORMATS", "check_sortable", "detect_format", "read",
    "H5Reader", "H5Writer", "read_h5", "write_h5",
    "read_mvsec", "read_txt", "write_txt", "read_aedat4", "read_aedat4_imu", "read_aedat4_frames", "read_gyro",
    "read_raw", "read_evt2", "read_evt3", "write_evt2", "write_evt3", "npy_time_span",
    "Calibration", "read_calibration",
]

FORMATS = ("dsec", "mvsec", "txt", "aedat4", "raw", "npy")
#: Formats decoded whole, which :func:`read` can sort by time (``sort=True``); the others are read a time span at
#: a time from disk, so their events must be stored in time order.
SORTABLE_FORMATS = ("txt", "npy", "aedat4")
#: Suffixes of video files: frames, not events (:func:`detect_format` points them to ``cmax simulate``,
#: :mod:`cmax.sim.convert` converts them).
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".m4v", ".webm", ".mpg", ".mpeg", ".wmv", ".flv", ".ts")


def _other_h5_layout(file: h5py.File) -> str:
    """What an HDF5 file that is neither DSEC nor MVSEC holds, for the refusal: an ``events`` table of 4 columns
    (v2e's layout), ``events/xs, ys, ts, ps`` (event_utils' and E2VID's), ``CD/events`` (Metavision's), else its
    top-level names; nothing in them is read as events, as their column order or time unit is not stated."""
    names = sorted(file.keys())
    events = file.get("events")
    if isinstance(events, h5py.Dataset) and events.ndim == 2 and events.shape[1] == 4:
        return (f"; it holds a table 'events' of shape {events.shape} (as v2e writes), whose column order and time "
                "unit the file does not state: once you know them, cmax.Events.from_array(table, width, height, "
                "order='txyp') reads it (times in integer µs)")
    if isinstance(events, h5py.Group) and all(name in events for name in ("xs", "ys", "ts", "ps")):
        return ("; it holds events/xs, ys, ts, ps (the event_utils / E2VID layout): build cmax.Events(x, y, t, p, "
                "width, height) from them, with ts converted to integer µs (the file does not state its unit)")
    if isinstance(file.get("CD"), h5py.Group) and "events" in file["CD"]:
        return ("; it holds CD/events (Metavision's HDF5 event file, compressed with its ECF codec): read it with "
                "Metavision's SDK and build cmax.Events(x, y, t, p, width, height) from its columns (t in µs)")
    return f"; its top-level names: {', '.join(names[:8]) or 'none'}{', ...' if len(names) > 8 else ''}"


def _other_event_layouts(file: h5py.File) -> list[str]:
    """Event data of other layouts than DSEC's that a DSEC-layout HDF5 ``file`` holds too, each named by its path
    and layout: MVSEC's ``davis/<camera>/events`` (with its rows), Metavision's ``CD/events``, event_utils'
    ``events/xs, ys, ts, ps``."""
    found = []
    for camera in MVSEC_CAMERAS:
        table = file.get(f"davis/{camera}/events")
        if isinstance(table, h5py.Dataset):
            rows = f", {table.shape[0]:,} rows" if table.ndim == 2 else ""
            found.append(f"davis/{camera}/events (MVSEC{rows})")
    if isinstance(file.get("CD"), h5py.Group) and "events" in file["CD"]:
        found.append("CD/events (Metavision)")
    if all(name in file["events"] for name in ("xs", "ys", "ts", "ps")):
        found.append("events/xs, ys, ts, ps (event_utils / E2VID)")
    return found


def _warn_other_layouts(file: h5py.File, path: Path) -> None:
    """Warn that the DSEC-layout ``file`` at ``path``, read as DSEC, holds events of other layouts too
    (:func:`_other_event_layouts`), naming them and what reads MVSEC's; silent where it holds none."""
    others = _other_event_layouts(file)
    if not others:
        return
    mvsec = any(other.startswith("davis/") for other in others)
    warnings.warn(
        f"{path} holds events in another layout too: {'; '.join(others)}, which is not read: its DSEC-layout "
        "events/x, y, t, p are (detected first)"
        + ("; cmax.io.read_mvsec(path, camera=...) reads the MVSEC events" if mvsec else ""),
        UserWarning, stacklevel=3,
    )


def _npz_message(path: Path) -> str:
    """Why the NumPy archive ``path`` (``np.savez``) is not read as events, naming the arrays it holds and the call
    that reads one of them."""
    try:
        with np.load(path, allow_pickle=False) as archive:
            names = list(archive.files)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
        return f"{path} is not a readable .npz archive ({type(error).__name__}: {error})"
    if {"x", "y", "t", "p"} <= set(names):             # np.savez(x=, y=, t=, p=): rpg_vid2e's ESIM, numpy dumps
        return (f"{path} is a NumPy .npz archive of the arrays {names[:8]}{' ...' if len(names) > 8 else ''}: an .npz "
                "of separate arrays is not read: build cmax.Events(x, y, t, p, width, height) from them "
                "(time_unit='s' for float seconds) and np.save('events.npy', events.to_structured())")
    first = names[0] if names else "events"
    return (f"{path} is a NumPy .npz archive of the arrays {names[:8]}{' ...' if len(names) > 8 else ''}, not one "
            f"event array: save the events with np.save (a structured .npy), or read one array, e.g. "
            f"cmax.Events.from_structured(np.load({str(path)!r})[{first!r}], width, height)")


def detect_format(path: str | os.PathLike) -> str:
    """Name of the event format of ``path`` (one of :data:`FORMATS`), from its bytes.

    Magic bytes decide first (HDF5, AEDAT4, NumPy, Prophesee ``%`` header), the
    suffix ``.txt`` second; an empty ``.txt`` is ECD text of zero events (as
    :func:`write_txt` writes it), any other empty file is refused.
    """
    path = Path(path)
    if path.is_dir():
        raise FormatError(_folder_message(path))
    if not path.is_file():
        if path.exists():                                # a device, a FIFO, a socket: exists, holds no file
            raise FormatError(f"{path} is not a regular file (a device, a pipe or a socket): give an event file")
        raise FileNotFoundError(f"no such event file: {path}")
    with open(path, "rb") as handle:
        head = handle.read(16)
    if not head:
        if path.suffix.lower() in (".txt", ".csv"):
            return "txt"                                 # ECD text of zero events (write_txt writes it so)
        raise FormatError(f"{path} is empty (0 bytes): no events to read")
    if head.startswith(b"\x89HDF\r\n\x1a\n"):
        try:
            with h5py.File(path, "r") as file:
                if is_dsec_h5(file):
                    _warn_other_layouts(file, path)
                    return "dsec"
                if "davis" in file:
                    return "mvsec"
                layout = _other_h5_layout(file)
        except H5_ERRORS as error:  # truncated or corrupt HDF5 (h5py raises OSError, KeyError, ...)
            raise FormatError(f"{path} is not a readable HDF5 file ({error})") from None
        raise FormatError(f"{path} is HDF5 but neither DSEC (events/x..p) nor MVSEC (davis/...){layout}")
    if head.startswith(b"#!AER-DAT4"):
        return "aedat4"
    if head.startswith(b"#!AER-DAT"):
        version = head[len(b"#!AER-DAT"):].split(b"\r")[0].split(b"\n")[0].decode("ascii", "replace")
        raise FormatError(f"{path} is an AEDAT {version} file (jAER / cAER; DVS Gesture ships AEDAT 3.1), which is "
                          "not read (AEDAT 4.0 is): decode it with a reader of that version and build "
                          "cmax.Events(x, y, t, p, width, height) from its columns (t in µs)")
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    if head.startswith(b"% ") or path.suffix.lower() == ".raw":
        return "raw"
    if path.suffix.lower() in (".txt", ".csv"):
        return "txt"
    if head.startswith(b"PK\x03\x04") and path.suffix.lower() == ".npz":
        raise FormatError(_npz_message(path))
    video = path.suffix.lower() in VIDEO_SUFFIXES
    raise FormatError(
        f"cannot tell the event format of {path}: expected DSEC/MVSEC HDF5, AEDAT4, "
        "Prophesee .raw, ECD .txt or a structured .npy"
        + ("; a video becomes events with `cmax simulate VIDEO -o events.h5`" if video else "")
    )



def _folder_message(folder: Path) -> str:
    """Why ``folder`` is not read as events, naming the ``events.txt`` inside (an ECD sequence) or its frames."""
    message = f"{folder} is a folder, not an event file"
    if (folder / "events.txt").is_file():
        message += f": its events are in {folder / 'events.txt'} (give that file)"
        if _holds_frames(folder):
            message += "; its frames become events with `cmax simulate FOLDER -o events.h5`"
    elif _holds_frames(folder):
        message += (": a sequence of frames (ECD images.txt, ESIM timestamps.txt) becomes events with "
                    "`cmax simulate FOLDER -o events.h5`")
    return message


def _holds_frames(folder: Path) -> bool:
    """Whether ``folder`` looks like a frame sequence: a timestamp file of ECD or ESIM, or ``images/``."""
    return any((folder / name).exists() for name in ("images.txt", "timestamps.txt", "images"))


def read(
    path: str | os.PathLike, *, width: int | None = None, height: int | None = None,
    t0_us: int | None = None, t1_us: int | None = None, time_unit: str | None = None, sort: bool = False,
    **options: Any,
) -> Events:
    """Read events from any supported file, detecting its format.

    Parameters
    ----------
    path : str or Path
    width, height : int, optional
        Sensor size, needed where the file does not store it (ECD text, NumPy,
        original DSEC files); it overrides nothing a file states: a size that
        differs from the file's raises :class:`ValueError`.
    t0_us, t1_us : int, optional
        Keep only ``t0_us <= t < t1_us`` (absolute µs). HDF5 files read only
        that slice from disk, Prophesee RAW files decode chunk by chunk up to its
        end holding only the slice, a ``.npy`` (without ``sort``) only its rows, found by a
        binary search of its memory-mapped times; other formats are decoded whole, then cut.
    time_unit : {'us', 'ms', 's'}, optional
        Unit of the file's time stamps where the format leaves it open (DSEC
        HDF5 with float times, ECD text or MVSEC in another unit than seconds,
        NumPy). Never guessed: float times without a stated unit are refused;
        integer ones (DSEC HDF5, NumPy) are µs by the format, refused where the
        file contradicts it (an ``ms_to_idx`` spanning far more, a mean rate no
        sensor produces: times in ms?).
        AEDAT4 and Prophesee files store integer µs; another unit is refused.
    sort : bool
        Sort the events by time (stable) instead of refusing a file whose
        time goes back; for the formats decoded whole (:data:`SORTABLE_FORMATS`:
        ECD text, NumPy, AEDAT4), refused for the others.
    **options
        Passed to the format's reader (e.g. ``camera='right'`` for MVSEC,
        ``polarity='signed'`` for a DSEC, text or NumPy file storing -1/+1); one
        the format's reader does not take is a :class:`TypeError` naming the
        file, the format detected and the options that format takes.

    Returns
    -------
    Events
    """
    path = Path(path)
    kind = detect_format(path)
    time_unit = check_time_unit(time_unit)
    check_sortable(path, kind, sort)
    if kind in ("aedat4", "raw") and time_unit not in (None, "us"):
        raise ValueError(f"{path} ({kind}) stores integer microseconds; time_unit={time_unit!r} does not apply")
    if kind in ("aedat4", "raw") and "polarity" in options:
        raise ValueError(f"{path} ({kind}) states its polarities itself; polarity={options['polarity']!r} does not apply")
    _check_options(path, kind, options)
    if kind == "dsec":
        return read_h5(path, width=width, height=height, t0_us=t0_us, t1_us=t1_us, time_unit=time_unit, **options)
    if kind == "mvsec":
        check_stated_size(width, height, (MVSEC_WIDTH, MVSEC_HEIGHT), f"{path} (MVSEC, a DAVIS346)")
        return read_mvsec(path, t0_us=t0_us, t1_us=t1_us, time_unit=time_unit, **options)
    if kind == "aedat4":
        events = read_aedat4(path, sort=sort, **options)
        check_stated_size(width, height, events.sensor_size, path)
    elif kind == "raw":
        events = read_raw(path, width=width, height=height, t0_us=t0_us, t1_us=t1_us, **options)
    elif kind == "txt":       # rpg_e2vid's text files state their size on their first line
        events = read_txt(path, width=width, height=height, time_unit=time_unit, sort=sort, **options)
    else:
        if width is None or height is None:
            raise ValueError(f"{path} ({kind}) stores no sensor size: pass width= and height= (cmax: --size WxH)")
        events = _read_npy(path, width, height, time_unit=time_unit, sort=sort, t0_us=t0_us, t1_us=t1_us, **options)
    if t0_us is None and t1_us is None:
        return events
    return events.slice_time(
        -(2**62) if t0_us is None else t0_us, 2**62 if t1_us is None else t1_us
    )


#: The keyword arguments of :func:`read` itself, taken for every format.
_READ_OWN = ("width", "height", "t0_us", "t1_us", "time_unit", "sort")
#: How the messages name each format.
_FORMAT_NAMES = {"dsec": "DSEC HDF5", "mvsec": "MVSEC HDF5", "txt": "ECD text", "aedat4": "AEDAT4",
                 "raw": "Prophesee RAW", "npy": "NumPy .npy"}


def _check_options(path: Path, kind: str, options: dict[str, Any]) -> None:
    """Refuse the ``options`` (``**options`` of :func:`read`) that the reader of format ``kind`` does not take, with
    a TypeError naming the file ``path``, the format detected and the keyword arguments that format takes (Python's
    own message named neither the file nor the format)."""
    reader = {"dsec": read_h5, "mvsec": read_mvsec, "txt": read_txt, "aedat4": read_aedat4, "raw": read_raw,
              "npy": _read_npy}[kind]   # the reader read() hands the format to
    takes = [name for name, parameter in inspect.signature(reader).parameters.items()
             if parameter.kind is inspect.Parameter.KEYWORD_ONLY and name not in _READ_OWN]
    unknown = [name for name in options if name not in takes]
    if unknown:
        own = ", ".join(f"{name}=" for name in _READ_OWN)
        given = ", ".join(f"{name}=" for name in unknown)
        raise TypeError(f"{path} is {_FORMAT_NAMES[kind]}, whose reader takes no {given}: it takes "
                        f"{', '.join(f'{name}=' for name in takes) or 'no option'} besides read()'s own {own}")


def check_sortable(path: str | os.PathLike, kind: str, sort: object) -> None:
    """Refuse ``sort`` other than a bool, and ``sort=True`` for a ``kind`` of file (:func:`detect_format`'s name)
    not in :data:`SORTABLE_FORMATS`; ``path`` names the file in the error."""
    if not isinstance(sort, (bool, np.bool_)):
        raise TypeError(f"sort must be True or False, got {sort!r}")
    if sort and kind not in SORTABLE_FORMATS:
        way_out = f"; {sorted_copy_line(path)}" if kind == "raw" else ""
        raise ValueError(f"{path} ({kind}) is read a time span at a time from disk, so its events must be stored in "
                         f"time order; sorting applies to ECD text, .npy and AEDAT4 files{way_out}")


def _read_npy(
    path: Path, width: int, height: int, *, time_unit: str | None = None, polarity: str = "01", sort: bool = False,
    t0_us: int | None = None, t1_us: int | None = None,
) -> Events:
    """A structured ``.npy`` (fields x, y, t, p): integer ``t`` is µs unless ``time_unit`` says
    otherwise (refused where that makes a mean rate no sensor reaches, :func:`check_implied_rate`, or a time after
    the year 2100, :func:`check_not_nanoseconds`), float ``t`` needs ``time_unit``; ``p`` in the stated encoding
    (0/1 by default); ``sort``: sort by time (stable) instead of refusing a time that goes back. With ``t0_us`` /
    ``t1_us`` (and not ``sort``) only the rows of ``[t0_us, t1_us)`` are read (:func:`_npy_rows`)."""
    polarity = check_polarity_encoding(polarity)
    array, fields = _npy_table(path, time_unit)
    if time_unit is None and len(array):               # integer times, µs by assumption: a rate no sensor makes?
        ends = np.array(array[fields["t"]][[0, -1]]).astype(np.int64)
        check_implied_rate(len(array), int(ends[0]), int(ends[1]), f"{path}: field {fields['t']}")
        check_not_nanoseconds(max(int(ends[0]), int(ends[1]), key=abs), f"{path}: field {fields['t']}")
    if (t0_us is not None or t1_us is not None) and not sort:
        array = array[_npy_rows(array[fields["t"]], time_unit or "us", t0_us, t1_us, f"{path}: field {fields['t']}")]
    check_event_count(array.shape[0], f"{path}")
    check_duplicate_fields(array, fields, str(path))
    t = np.asarray(array[fields["t"]])
    t_us = times_to_us(t, time_unit or "us", f"{path}: field {fields['t']}")
    p = polarity_01(np.asarray(array[fields["p"]]), polarity, f"{path}: field {fields['p']}")
    try:
        return Events(array["x"], array["y"], t_us, p, width, height, sort=sort, time_unit="us")
    except (TypeError, ValueError) as error:
        raise FormatError(f"{path}: {error}") from None


def _npy_table(path: Path, time_unit: str | None) -> tuple[np.ndarray, dict[str, str]]:
    """The memory-mapped structured array of a ``.npy`` event file and its field names (``structured_fields``),
    checked: 1-D, fields x, y, t, p, times that are numbers, float times only with a stated ``time_unit``."""
    _check_data_length(path)
    try:
        array = np.load(path, mmap_mode="r", allow_pickle=False)
    except ValueError as error:
        raise FormatError(f"{path} is not a readable .npy file ({error})") from None
    names = array.dtype.names or ()
    fields = structured_fields(names)
    if array.ndim != 1 or any(field not in names for field in fields.values()):
        missing = [column for column, field in fields.items() if field not in names]
        table = (not names and array.ndim == 2 and array.shape[1] == 4)
        raise FormatError(f"{path}: expected a 1-D structured array with fields x, y, t, p (or dv-processing's "
                          f"timestamp, polarity); got dtype {array.dtype}, shape {array.shape}"
                          f"{field_rename_hint(names, missing, f'np.load({str(path)!r})') if array.ndim == 1 else ''}"
                          + (f": an (N, 4) table, whose column order and time unit the file does not state; once you "
                             f"know them, cmax.Events.from_array(np.load({str(path)!r}), width, height, "
                             "order='xytp') reads it (times in integer µs, or time_unit=)" if table else ""))
    t_dtype = array.dtype[fields["t"]]
    if t_dtype.kind not in "iuf":                      # before the unit checks, which read the times as numbers
        raise FormatError(f"{path}: field {fields['t']} must hold numbers (times), got dtype {t_dtype}")
    if t_dtype.kind == "f" and time_unit is None:
        raise FormatError(f"{path}: field {fields['t']} holds {t_dtype} times; state their unit with time_unit='s', "
                          "'ms' or 'us' (cmax: --time-unit; times are never guessed)")
    return array, fields


def _check_data_length(path: Path) -> None:
    """Refuse the ``.npy`` file at ``path`` whose data are not as long as its header declares: cut short (a copy
    stopped mid-write), or followed by more bytes (np.save writes none, and np.load ignores them, so rows appended
    without the header's shape being updated, e.g. by an interrupted npy-append-array or a logger writing records
    after the header, would be dropped without a word). Reads only the header."""
    try:
        with open(path, "rb") as handle:
            version = np.lib.format.read_magic(handle)
            read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0) else
                           np.lib.format.read_array_header_2_0)
            shape, _, dtype = read_header(handle)
            data_offset = handle.tell()
    except (OSError, ValueError) as error:
        raise FormatError(f"{path} is not a readable .npy file ({error})") from None
    if dtype.hasobject:                                  # pickled objects: np.load refuses them (allow_pickle=False)
        return
    rows, row = (shape[0] if shape else 1), dtype.itemsize
    declared = int(np.prod(shape, dtype=np.int64)) * row
    held = path.stat().st_size - data_offset
    if held == declared:
        return
    if held < declared:
        whole = f", {held // row:,} whole rows" if len(shape) == 1 and row else ""
        raise FormatError(f"{path}: its header declares {rows:,} rows of {row} bytes ({declared:,} bytes of data), "
                          f"but the file holds {held:,}{whole}: cut short (a truncated copy or an interrupted write)")
    extra = held - declared
    what = (f"{extra // row:,} rows ({extra:,} bytes) follow the {rows:,} rows its header declares" if row and
            extra % row == 0 else f"{extra:,} bytes follow the {rows:,} rows its header declares (rows of {row} bytes: "
            "not a whole number of them)")
    raise FormatError(
        f"{path}: {what}: rows appended without the header's shape being updated, or another file's bytes? (np.save "
        "writes none, np.load would drop them without a word); if they are rows of the same dtype, "
        f"np.save('fixed.npy', np.fromfile({str(path)!r}, dtype=np.load({str(path)!r}, mmap_mode='r').dtype, "
        f"offset={data_offset})) reads every row"
    )


def npy_time_span(path: str | os.PathLike, *, time_unit: str | None = None) -> tuple[int, int] | None:
    """``(first_us, last_us)``: the times of the first and last rows of the structured ``.npy`` event file at
    ``path``, from those two rows alone (in time order, as :func:`read` checks where it reads); None for a file of no events.
    ``time_unit`` as :func:`read` takes it."""
    path = Path(path)
    if detect_format(path) != "npy":
        raise FormatError(f"{path} is not a NumPy .npy file")
    array, fields = _npy_table(path, check_time_unit(time_unit))
    if not len(array):
        return None
    ends = np.array(array[fields["t"]][[0, -1]])
    first, last = times_to_us(ends, time_unit or "us", f"{path}: field {fields['t']}").tolist()
    return int(first), int(last)


def _npy_rows(t: np.ndarray, unit: str, t0_us: int | None, t1_us: int | None, where: str) -> slice:
    """Rows of the time column ``t`` (memory-mapped, in ``unit``, in time order) whose times in µs lie in
    ``[t0_us, t1_us)`` (None: unbounded), by binary search: O(log N) single rows read, not the column."""
    def at(row: int) -> int:
        return int(times_to_us(np.array(t[row: row + 1]), unit, where)[0])

    rows = range(len(t))
    start = 0 if t0_us is None else bisect.bisect_left(rows, int(t0_us), key=at)
    stop = len(t) if t1_us is None else max(start, bisect.bisect_left(rows, int(t1_us), key=at))
    return slice(start, stop)
