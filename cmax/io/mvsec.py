"""MVSEC HDF5 files (Zhu et al., "The Multivehicle Stereo Event Camera Dataset", RA-L 2018).

Events are stored per camera as ``davis/<left|right>/events``, an (N, 4)
float64 array with columns ``x, y, t [s], p in {-1, +1}`` from a DAVIS346
(346 x 260). Ground-truth depth and poses live in separate ``*_gt.hdf5`` files.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator

import h5py
import numpy as np

from cmax.events import EventLimitError, Events, check_event_count, check_time_us
from cmax.io._checks import TIME_UNITS, check_allocated, check_polarity_encoding, check_time_unit, polarity_01, times_to_us
from cmax.io.errors import FormatError
from cmax.io.h5 import H5_ERRORS

__all__ = ["read_mvsec", "iter_mvsec", "mvsec_time_span", "mvsec_cameras", "MVSEC_CAMERAS", "MVSEC_WIDTH",
           "MVSEC_HEIGHT"]

MVSEC_WIDTH, MVSEC_HEIGHT = 346, 260
#: The cameras of an MVSEC rig, as its files name them (``davis/<camera>/events``); ``read_mvsec``'s default first.
MVSEC_CAMERAS = ("left", "right")


def _check_camera(camera: object) -> None:
    """ValueError unless ``camera`` is one of :data:`MVSEC_CAMERAS`."""
    if camera not in MVSEC_CAMERAS:
        raise ValueError(f"camera must be 'left' or 'right', got {camera!r}")


def _unreadable(path: Path, error: BaseException) -> FormatError:
    """The FormatError of an MVSEC file that h5py cannot read (truncated or corrupt HDF5), naming ``error``."""
    return FormatError(f"{path} is not a readable MVSEC HDF5 file ({type(error).__name__}: {error})")


def _events_dataset(file: h5py.File, path: Path, camera: str) -> h5py.Dataset:
    key = f"davis/{camera}/events"
    if key not in file:
        others = [name for name in MVSEC_CAMERAS if name != camera and f"davis/{name}/events" in file]
        if others:
            raise FormatError(f"{path} has no dataset {key!r}; it holds the events of the {others[0]} camera: read "
                              f"them with camera={others[0]!r} (cmax: --camera {others[0]})")
        raise FormatError(f"{path} has no dataset {key!r} (not an MVSEC data file? MVSEC keeps its events in the "
                          "*_data.hdf5 files, the depth and poses in *_gt.hdf5)")
    dataset = file[key]
    if not isinstance(dataset, h5py.Dataset) or dataset.ndim != 2 or dataset.shape[1] != 4:
        raise FormatError(f"{path}:{key} must be a dataset of shape (N, 4), got {getattr(dataset, 'shape', dataset)}")
    check_allocated(dataset, f"{path}: {key}")
    return dataset


def read_mvsec(
    path: str | os.PathLike, *, camera: str = "left",
    t0_us: int | None = None, t1_us: int | None = None, time_unit: str | None = None,
    polarity: str = "signed",
) -> Events:
    """Read the events of one MVSEC ``camera`` (``'left'`` or ``'right'``) from the ``*_data.hdf5`` at ``path``,
    optionally only ``[t0_us, t1_us)`` [µs].

    Time stamps (MVSEC: seconds since the epoch; ``time_unit`` states another
    unit) become integer microseconds by rounding to the nearest µs (half to
    even); polarity -1/+1 (MVSEC's encoding; ``polarity='01'`` states 0/1)
    becomes 0/1, any other value raises :class:`FormatError`. A time window is
    located by binary search on the time column on disk, so only that slice is read.
    Without ``time_unit``, times that are all whole numbers (at least 100 distinct, in the rows read or the file's
    first 4096) are refused as integer microseconds stored as floats, not read as seconds (days of recording);
    with ``time_unit='ms'`` or ``'us'``, times with decimals that all lie where MVSEC's seconds since 1970 lie
    (1973 to 2103, :data:`_UNIX_SECONDS`) are refused as such seconds, not read as milliseconds (a recording 1000
    times shorter) or microseconds; in any unit, times that lie after 2103 as seconds since 1970 are refused,
    naming the smaller unit that puts them between 1973 and 2103 (milliseconds since 1970 read as seconds).
    """
    _check_camera(camera)
    unit = check_time_unit(time_unit) or "s"
    polarity = check_polarity_encoding(polarity)
    per_us = 1.0 / TIME_UNITS[unit]
    path = Path(path)
    t0_us = None if t0_us is None else check_time_us("t0_us", t0_us)
    t1_us = None if t1_us is None else check_time_us("t1_us", t1_us)
    if not path.is_file():
        raise FileNotFoundError(f"no such event file: {path}")
    try:
        with h5py.File(path, "r") as file:
            dataset = _events_dataset(file, path, camera)
            # a window's few rows may not show it: the file's first rows do
            _refuse_misread_times(dataset[:_SAMPLE_ROWS, 2], time_unit is not None, unit,
                                  f"{path}: davis/{camera}/events")
            # Read with a 2 µs margin, then cut exactly on the rounded integer times.
            start, stop = 0, dataset.shape[0]
            if t0_us is not None:
                start = _first_at_or_after(dataset, (t0_us - 2) * per_us)
            if t1_us is not None:
                stop = _first_at_or_after(dataset, (t1_us + 2) * per_us)
            check_event_count(stop - start, f"{path}: rows [{start}, {stop})")
            table = dataset[start:max(start, stop)]
    except (FormatError, EventLimitError):
        raise
    except H5_ERRORS as error:  # truncated or corrupt HDF5
        raise _unreadable(path, error) from None
    events = _table_events(table, path, camera, unit, polarity, time_unit is not None)
    if t0_us is None and t1_us is None:
        return events
    return events.slice_time(
        -(2**62) if t0_us is None else t0_us, 2**62 if t1_us is None else t1_us
    )


#: This many distinct times, every one a whole number, are not MVSEC's seconds (which carry decimals).
_WHOLE_TIMES = 100
#: Rows from a file's start whose times are checked for whole numbers where a window or its ends alone are read.
_SAMPLE_ROWS = 4096


def _refuse_whole_seconds(t: np.ndarray, where: str) -> None:
    """Refuse a time column ``t`` read as MVSEC's seconds by default (no unit stated) whose every value is a whole
    number, at least :data:`_WHOLE_TIMES` of them distinct: integer µs (or ms, ns) stored as floats, which would read
    as days of recording. ``where`` names the file and dataset."""
    if t.size < _WHOLE_TIMES or not np.array_equal(t, np.round(t)) or np.abs(t).max() * 1e6 >= 2.0**62:
        return                          # (times too large for µs as seconds: named by times_to_us with their unit)
    distinct = int(np.count_nonzero(np.diff(t))) + 1
    if distinct >= _WHOLE_TIMES:
        raise FormatError(
            f"{where}[:, 2] (t): every time is a whole number ({distinct:,} distinct, from {t[0]:.0f} to {t[-1]:.0f}), "
            "but MVSEC states seconds with decimals: these look like integer microseconds. State the unit: "
            "time_unit='us' (cmax: --time-unit us), or time_unit='s' if they are whole seconds"
        )


#: Seconds since 1970 of March 1973 and of 2103: a time column whose values all lie between them, with decimals, holds
#: UNIX seconds, MVSEC's own clock (its recordings of 2017-2018: about 1.5e9 s).
_UNIX_SECONDS = (1e8, 4.2e9)


#: The names of :data:`TIME_UNITS` in words, for refusals.
_UNIT_WORDS = {"us": "microseconds", "ms": "milliseconds", "s": "seconds"}
#: 2103-01-01 as µs since 1970 (the end of :data:`_UNIX_SECONDS`): times read beyond it belong to no clock.
_AFTER_2103_US = _UNIX_SECONDS[1] * 1e6


def _refuse_unix_seconds_as(t: np.ndarray, unit: str, where: str) -> None:
    """Refuse a time column ``t`` stated to be milliseconds or microseconds (``unit`` ``'ms'`` or ``'us'``) whose
    values carry decimals and all lie within :data:`_UNIX_SECONDS`: MVSEC's seconds since 1970, which in ``unit``
    would make the recording 1000 (or a million) times shorter on a clock started 100 s to 49 days before it. The
    rounding check of :func:`cmax.io._checks.times_to_us` refuses such times only at high event rates (where whole
    µs merge them); a slow recording passed it. Whole-number times (integers stored as floats) are not refused.
    ``where`` names the file and dataset."""
    if not t.size or not np.isfinite(t).all():
        return                          # (non-finite times: named by times_to_us)
    low, high = float(t.min()), float(t.max())
    if not (_UNIX_SECONDS[0] <= low and high < _UNIX_SECONDS[1]) or np.array_equal(t, np.round(t)):
        return
    from datetime import datetime, timezone

    date = datetime.fromtimestamp(low, timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC")
    words = _UNIT_WORDS[unit]
    store = ("store them as microseconds (t * 1000) and pass time_unit='us'" if unit == "ms"
             else "store them rounded to whole microseconds (np.rint(t)), which are not refused")
    raise FormatError(
        f"{where}[:, 2] (t): time_unit={unit!r} states {words}, but these times ({low!r} to {high!r}, with "
        f"decimals) are seconds since 1970 as MVSEC records them ({date}): read as {words}, {t.size:,} events of "
        f"{high - low:.6g} s would last {high - low:.6g} {unit}. Leave time_unit out (MVSEC's seconds; cmax: no "
        f"--time-unit); if they really are {words}, {store}"
    )


def _refuse_after_2103(t: np.ndarray, unit: str, unit_stated: bool, where: str) -> None:
    """Refuse a time column ``t`` that read in ``unit`` (stated by the caller if ``unit_stated``, else MVSEC's
    seconds) lies after the year 2103 as seconds since 1970 (beyond :data:`_AFTER_2103_US`): no clock, neither
    since 1970 nor since boot, reads so; the unit is another. The refusal names the smaller unit that puts the
    times between 1973 and 2103 (milliseconds since 1970 read as seconds: the year 47,000), when one does.
    Times too large for int64 µs are left to :func:`cmax.io._checks.times_to_us`, which names the unit the same
    way. ``where`` names the file and dataset."""
    finite = t[np.isfinite(t)] if t.dtype.kind == "f" else t
    if not finite.size:
        return
    i = int(np.argmax(np.abs(finite)))
    value = float(finite[i])
    value_us = abs(value) * TIME_UNITS[unit]
    if value_us <= _AFTER_2103_US or value_us > 2.0**62:
        return
    fits = [smaller for smaller in ("ms", "us") if TIME_UNITS[smaller] < TIME_UNITS[unit]
            and _UNIX_SECONDS[0] <= abs(value) * TIME_UNITS[smaller] * 1e-6 < _UNIX_SECONDS[1]]
    read_as = f"time_unit={unit!r}" if unit_stated else "MVSEC's seconds (no time_unit)"
    advice = (f"these are {_UNIT_WORDS[fits[0]]} since 1970 ({abs(value) * TIME_UNITS[fits[0]] * 1e-6:.6f} s): "
              f"state time_unit={fits[0]!r} (cmax: --time-unit {fits[0]})" if fits else
              "no unit of 's', 'ms', 'us' puts them between 1973 and 2103: convert them to microseconds")
    raise FormatError(
        f"{where}[:, 2] (t): the time {value!r}, read as {read_as}, lies in the year "
        f"{value_us * 1e-6 / 3.15576e7 + 1970:.0f} as seconds since 1970, past 2103, where no clock reads; {advice}"
    )


def _refuse_misread_times(t: np.ndarray, unit_stated: bool, unit: str, where: str) -> None:
    """The checks of an MVSEC time column ``t`` before it is read in ``unit``: times past 2103 in that unit are
    refused (:func:`_refuse_after_2103`); without a stated unit (``unit_stated`` False), whole numbers are
    (:func:`_refuse_whole_seconds`); stated as milliseconds or microseconds, MVSEC's seconds since 1970 are
    (:func:`_refuse_unix_seconds_as`). ``where`` names the file and dataset."""
    _refuse_after_2103(t, unit, unit_stated, where)
    if not unit_stated:
        _refuse_whole_seconds(t, where)
    elif unit in ("ms", "us"):
        _refuse_unix_seconds_as(t, unit, where)


def _refuse_time_going_back(t_us: np.ndarray, path: Path, camera: str) -> None:
    """Refuse times ``t_us`` (µs, of rows read from ``davis/<camera>/events`` of ``path``) that go back, with the way
    through: MVSEC files are read a time span at a time (bisection on disk), so ``sort`` / ``--sort`` do not apply
    to them (the generic refusal of :class:`Events` pointed at ``--sort``, which then refused MVSEC files)."""
    back = np.flatnonzero(t_us[1:] < t_us[:-1])
    if not back.size:
        return
    i = int(back[0])
    raise FormatError(
        f"{path}: davis/{camera}/events[:, 2] (t): the time goes back from {int(t_us[i])} µs to {int(t_us[i + 1])} µs "
        f"(rows {i} and {i + 1} of those read); MVSEC files are read a time span at a time, so their rows must be in "
        "time order and --sort does not apply: write a sorted copy once: python -c \"import h5py, numpy as np; "
        f"e = h5py.File({str(path)!r})['davis/{camera}/events'][:]; h5py.File('sorted.hdf5', 'w')"
        f"['davis/{camera}/events'] = e[np.argsort(e[:, 2], kind='stable')]\""
    )


def _table_events(table: np.ndarray, path: Path, camera: str, unit: str, polarity: str,
                  unit_stated: bool = True) -> Events:
    """The events of rows (N, 4) ``x, y, t, p`` of ``davis/<camera>/events``: finite, times in ``unit`` rounded to
    µs (refused when ``unit_stated`` is False, seconds by default, and every time is a whole number:
    :func:`_refuse_whole_seconds`), polarities in the encoding ``polarity`` mapped to 0/1, in time order
    (FormatError naming the file)."""
    where = f"{path}: davis/{camera}/events"
    if not np.isfinite(table[:, [0, 1, 3]]).all():
        raise FormatError(f"{where} contains non-finite values")
    _refuse_misread_times(table[:, 2], unit_stated, unit, where)
    t_us = times_to_us(table[:, 2], unit, f"{where}[:, 2] (t)")
    _refuse_time_going_back(t_us, path, camera)
    p = polarity_01(table[:, 3], polarity, f"{where}[:, 3] (p)")
    try:
        return Events(table[:, 0], table[:, 1], t_us, p, MVSEC_WIDTH, MVSEC_HEIGHT, time_unit="us")
    except ValueError as error:
        raise FormatError(f"{path}: {error}") from None


def iter_mvsec(
    path: str | os.PathLike, *, camera: str = "left", time_unit: str | None = None, polarity: str = "signed",
    chunk_rows: int = 1 << 22,
) -> Iterator[Events]:
    """The events of one MVSEC camera, ``chunk_rows`` rows at a time: memory holds one chunk (a camera of a long
    recording, 32 bytes a row as float64 on disk, need not fit). Each chunk is read and checked as
    :func:`read_mvsec` reads its rows, and a time that goes back from one chunk to the next raises FormatError.

    >>> import h5py, tempfile
    >>> path = Path(tempfile.mkdtemp()) / "rig.hdf5"
    >>> with h5py.File(path, "w") as file:
    ...     file["davis/left/events"] = [[1, 2, 10.0, -1], [3, 4, 10.5, 1], [5, 6, 11.0, 1]]
    >>> [chunk.t.tolist() for chunk in iter_mvsec(path, chunk_rows=2)]
    [[10000000, 10500000], [11000000]]
    """
    _check_camera(camera)
    if isinstance(chunk_rows, bool) or not isinstance(chunk_rows, (int, np.integer)) or chunk_rows < 1:
        raise ValueError(f"chunk_rows must be a whole number >= 1, got {chunk_rows!r}")
    unit = check_time_unit(time_unit) or "s"
    polarity = check_polarity_encoding(polarity)
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such event file: {path}")
    try:
        file = h5py.File(path, "r")
    except H5_ERRORS as error:  # truncated or corrupt HDF5
        raise _unreadable(path, error) from None
    with file:
        dataset, last = _events_dataset(file, path, camera), None
        for start in range(0, dataset.shape[0], int(chunk_rows)):
            try:
                table = dataset[start:start + int(chunk_rows)]
            except H5_ERRORS as error:
                raise FormatError(f"{path}: davis/{camera}/events: unreadable rows from {start} "
                                  f"({type(error).__name__}: {error})") from None
            events = _table_events(table, path, camera, unit, polarity, time_unit is not None)
            if last is not None and int(events.t[0]) < last:
                raise FormatError(f"{path}: davis/{camera}/events: corrupt events at row {start}: t must be sorted "
                                  f"in non-decreasing order ({int(events.t[0])} µs comes after {last} µs)")
            last = int(events.t[-1])
            yield events


def mvsec_time_span(
    path: str | os.PathLike, *, camera: str = "left", time_unit: str | None = None,
) -> tuple[int, int] | None:
    """``(first_us, last_us)``: the times of the first and last events of one MVSEC camera, from those two rows
    alone (the rows are in time order, as :func:`read_mvsec` checks where it reads), rounded as
    :func:`read_mvsec` rounds them, and the file's first rows checked as it checks them (whole-number times without
    ``time_unit``); None for a camera without events."""
    _check_camera(camera)
    unit = check_time_unit(time_unit) or "s"
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such event file: {path}")
    try:
        with h5py.File(path, "r") as file:
            dataset = _events_dataset(file, path, camera)
            if not dataset.shape[0]:
                return None
            _refuse_misread_times(dataset[:_SAMPLE_ROWS, 2], time_unit is not None, unit,
                                  f"{path}: davis/{camera}/events")
            ends = np.array([dataset[0, 2], dataset[-1, 2]], dtype=dataset.dtype)
    except FormatError:
        raise
    except H5_ERRORS as error:  # truncated or corrupt HDF5
        raise _unreadable(path, error) from None
    first, last = times_to_us(ends, unit, f"{path}: davis/{camera}/events[[0, -1], 2] (t)").tolist()
    return int(first), int(last)


def mvsec_cameras(path: str | os.PathLike) -> dict[str, int]:
    """``{camera: rows}``: the cameras of :data:`MVSEC_CAMERAS` whose ``davis/<camera>/events`` an MVSEC file
    holds, and how many events each stores (its rows; nothing else is read). Raises FormatError for a file that
    is not a readable HDF5 file.

    >>> import h5py, numpy as np, tempfile
    >>> path = Path(tempfile.mkdtemp()) / "rig.hdf5"
    >>> with h5py.File(path, "w") as file:
    ...     file["davis/left/events"], file["davis/right/events"] = np.zeros((3, 4)), np.zeros((5, 4))
    >>> mvsec_cameras(path)
    {'left': 3, 'right': 5}
    """
    path = Path(path)
    try:
        with h5py.File(path, "r") as file:
            found = {camera: file.get(f"davis/{camera}/events") for camera in MVSEC_CAMERAS}
            return {camera: int(dataset.shape[0]) for camera, dataset in found.items()
                    if isinstance(dataset, h5py.Dataset) and dataset.ndim == 2}
    except H5_ERRORS as error:  # truncated or corrupt HDF5
        raise _unreadable(path, error) from None


def _first_at_or_after(dataset: h5py.Dataset, t_s: float) -> int:
    """Row of the first event with time >= t_s, by bisection on disk."""
    lo, hi = 0, dataset.shape[0]
    while hi - lo > 65536:
        mid = (lo + hi) // 2
        if dataset[mid, 2] < t_s:
            lo = mid + 1
        else:
            hi = mid
    return lo + int(np.searchsorted(dataset[lo:hi, 2], t_s, side="left"))
