"""The event container: four contiguous columns plus the sensor size.

An event camera reports, for each pixel whose log intensity changed by a
contrast threshold, a tuple ``(x, y, t, p)``. :class:`Events` holds N such
events as four numpy columns with fixed dtypes:

==========  =========  ==========================================
column      dtype      meaning
==========  =========  ==========================================
``x``       uint16     column, ``0 <= x < width``
``y``       uint16     row, ``0 <= y < height``
``t``       int64      time stamp in microseconds, non-decreasing
``p``       int8       polarity, 0 = OFF (darker), 1 = ON (brighter)
==========  =========  ==========================================

The signed polarity of the paper (-1/+1) is derived on demand with
:meth:`Events.signed_polarity`; it is never stored. Every constructor
validates its input and raises :class:`ValueError` or :class:`TypeError`
naming the offending argument; nothing is clipped, reordered or dropped
silently.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterator, NamedTuple, Sequence

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    import torch

__all__ = [
    "Events", "EventTensors", "EventLimitError", "MAX_EVENTS", "STRUCTURED_DTYPE", "FIELD_ALIASES", "concatenate",
    "check_event_count", "window_starts", "uncovered_tail", "require_events", "structured_fields", "float_step",
    "wrap_index", "FIELD_SPELLINGS", "field_rename_hint", "DUPLICATE_SPELLINGS", "check_duplicate_fields",
    "polarity_hint", "conversion_hint",
]

#: dtype of :meth:`Events.to_structured` (tonic / Prophesee field names).
STRUCTURED_DTYPE = np.dtype([("x", "<u2"), ("y", "<u2"), ("t", "<i8"), ("p", "i1")])

#: Other names of the fields ``t`` and ``p`` that :meth:`Events.from_structured` reads where ``t`` / ``p``
#: are absent: dv-processing's ``EventStore.numpy()`` (``timestamp`` [µs], ``x``, ``y``, ``polarity``).
FIELD_ALIASES = {"t": "timestamp", "p": "polarity"}


def structured_fields(names: Sequence[str]) -> dict[str, str | None]:
    """The field that holds each of ``x, y, t, p`` in a structured array with field ``names``: the column's
    own name where present, else its :data:`FIELD_ALIASES` name (which may be absent too: check it)."""
    return {name: name if name in names else FIELD_ALIASES.get(name) for name in "xytp"}

#: Other names under which a structured array may hold one of ``x, y, t, p`` a second time (dv-processing's
#: ``timestamp``, ``polarity``; event_utils' ``xs, ys, ps``; ``pol``): :func:`check_duplicate_fields` reads the pair
#: where the two agree and refuses it where they differ. Other time spellings (``ts``, ``time``, ``t_us``) are not
#: compared: they may hold the times in another unit.
DUPLICATE_SPELLINGS = {"x": ("xs",), "y": ("ys",), "t": ("timestamp",), "p": ("polarity", "ps", "pol", "polarities")}


def check_duplicate_fields(array: np.ndarray, fields: dict[str, str], source: str = "array") -> None:
    """Refuse the structured ``array`` (N,) that holds a column twice, the field read (``fields``: column ->
    field, :func:`structured_fields`) and another of its names (:data:`DUPLICATE_SPELLINGS`), with values that
    differ: which one is right is not guessed. The error names both fields and the first differing row;
    polarities are compared as ON / OFF (``> 0``), so 0/1 and -1/+1 of the same events agree. ``source`` names
    the array in the message (a file path). Equal columns pass silently.

    >>> pair = np.array([(1, 10, 10), (2, 20, 21)], dtype=[("x", "u2"), ("t", "i8"), ("timestamp", "i8")])
    >>> check_duplicate_fields(pair, {"x": "x", "t": "t"})
    Traceback (most recent call last):
    ...
    ValueError: array holds fields 't' and 'timestamp', which differ from row 1 on (20 vs 21): say which one holds t by dropping the other: numpy.lib.recfunctions.drop_fields(array, 'timestamp') (or rename_fields)
    """
    names = array.dtype.names or ()
    for column, field in fields.items():
        for other in DUPLICATE_SPELLINGS.get(column, ()) + (column,):
            if other == field or other not in names or field not in names:
                continue
            read, second = np.asarray(array[field]), np.asarray(array[other])
            differ = (read > 0) != (second > 0) if column == "p" else read != second
            if differ.any():
                row = int(differ.argmax())
                raise ValueError(f"{source} holds fields {field!r} and {other!r}, which differ from row {row:,} on "
                                 f"({read[row]} vs {second[row]}): say which one holds {column} by dropping the "
                                 f"other: numpy.lib.recfunctions.drop_fields(array, {other!r}) (or rename_fields)")


#: How other tools spell the fields (event_utils' ``xs, ys, ts, ps``, ``time``, ``pol``): not read under these names
#: (nothing is renamed silently), but named in the refusal with the call that renames them (:func:`field_rename_hint`).
FIELD_SPELLINGS = {"x": ("xs",), "y": ("ys",), "t": ("ts", "time", "times", "timestamps", "t_us"),
                   "p": ("ps", "pol", "polarities")}


def field_rename_hint(names: Sequence[str], missing: Sequence[str], source: str = "array") -> str:
    """For a structured array with field ``names`` that lacks the columns ``missing`` (of ``x, y, t, p``): the call
    that renames the fields spelt as other tools spell them (:data:`FIELD_SPELLINGS`, or the column's name in
    upper case) to ``x, y, t, p``, as a clause to append to a refusal; "" where no field is. ``source``: the
    expression the call names the array by (e.g. ``"np.load('ev.npy')"``).

    >>> field_rename_hint(["x", "y", "ts", "p"], ["t"])
    ": if 'ts' holds t, rename it: numpy.lib.recfunctions.rename_fields(array, {'ts': 't'})"
    """
    lower = {str(name).lower(): str(name) for name in names}
    renames = {}
    for column in missing:
        found = [lower[spelling] for spelling in (column, *FIELD_SPELLINGS.get(column, ())) if spelling in lower]
        if found:
            renames[found[0]] = column
    if not renames:
        return ""
    held = ", ".join(f"{field!r} holds {column}" for field, column in renames.items())
    return (f": if {held}, rename {'it' if len(renames) == 1 else 'them'}: "
            f"numpy.lib.recfunctions.rename_fields({source}, {renames!r})")


_MAX_SENSOR_SIZE = 65535
#: Most pixels a sensor may have (8192 x 8192): the largest event cameras hold about a million. A size read from a
#: file drives per-pixel arrays (counts, images, hot-pixel maps), so a corrupt or crafted header declaring
#: 65535 x 65535 would ask for tens of GB: refused with the other size checks.
MAX_SENSOR_PIXELS = 1 << 26

#: Most events one in-memory :class:`Events` may hold (2**28, about 3.5 GB of columns).
#: Larger requests (a whole long recording, a huge window) raise :class:`EventLimitError`
#: before anything is allocated; stream them instead (``H5Reader.windows``,
#: ``iter_evt3``/``iter_evt2``, ``H5Writer``), or raise this module attribute deliberately.
MAX_EVENTS = 1 << 28

_INT64_MAX = int(np.iinfo(np.int64).max)
_INT64_MIN = int(np.iinfo(np.int64).min)


def require_events(events: object, name: str = "events") -> "Events":
    """``events`` when it is :class:`Events`; otherwise a ``TypeError`` that names the conversion for what
    was given: a structured array (tonic's, Metavision's, dv-processing's; by field names), an (N, 4)
    array (columns named by ``order``), :class:`EventTensors` (torch) or a path (:func:`cmax.io.read`)."""
    if isinstance(events, Events):
        return events
    raise TypeError(f"{name} must be cmax.Events, got {type(events).__name__}{conversion_hint(events)}")


def conversion_hint(events: object) -> str:
    """The clause that names the conversion to :class:`Events` of ``events``, something else (a structured array
    by its field names, an (N, 4) array by ``order``, :class:`EventTensors`, a path), for a ``TypeError``;
    "" where none is known."""
    if isinstance(events, EventTensors):
        hint = "; these are the torch tensors of Events.to_torch(): pass the Events they came from"
    elif getattr(getattr(events, "dtype", None), "names", None):
        hint = (f" (a structured array with fields {list(events.dtype.names)}): "
                "cmax.Events.from_structured(array, width, height) reads it by its field names")
    elif getattr(events, "ndim", None) == 2 and getattr(events, "shape", (0, 0))[1] == 4:
        hint = (f" of shape {tuple(events.shape)}: cmax.Events.from_array(array, width, height, order='xytp') "
                "names its columns (times in integer µs)")
    elif isinstance(events, (str, os.PathLike)):
        hint = f" ({events!s}): read the file with cmax.io.read(path) first"
    else:
        hint = ""
    return hint


class EventLimitError(ValueError):
    """More events were asked for than :data:`MAX_EVENTS` allows in memory at once."""


def check_event_count(count: int, what: str) -> int:
    """Raise :class:`EventLimitError` when ``count`` exceeds :data:`MAX_EVENTS`; returns ``count``.

    ``what`` names the request in the message (e.g. ``"the window [t0, t1)"``).
    """
    limit = int(MAX_EVENTS)
    if int(count) > limit:
        raise EventLimitError(
            f"{what} holds {int(count):,} events, more than cmax.events.MAX_EVENTS={limit:,} "
            "that fit in memory at once; read it in windows (H5Reader.windows, iter_evt3, "
            "iter_evt2) or raise cmax.events.MAX_EVENTS deliberately"
        )
    return int(count)


def check_time_us(name: str, value: object) -> int:
    """A time in integer microseconds: an int, or a float holding a whole finite number.

    Raises :class:`TypeError` (not a number) or :class:`ValueError` (NaN,
    infinite, or a fraction of a microsecond) naming ``name``. Python integers
    of any size are accepted (times beyond int64 lie after every event).
    """
    if isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be integer microseconds, got {value!r}")
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        if not np.isfinite(value):
            raise ValueError(f"{name} must be a finite time in microseconds, got {value}")
        if not float(value).is_integer():
            raise ValueError(f"{name} must be whole microseconds, got {value}")
        return int(value)
    raise TypeError(f"{name} must be integer microseconds, got {value!r} ({type(value).__name__})")


class EventTensors(NamedTuple):
    """Events as torch tensors, as returned by :meth:`Events.to_torch`.

    ``x``, ``y`` and ``t`` are int64 tensors of shape (N,) (pixels and
    microseconds); ``p`` is int8 in {0, 1}, or float32 in {-1, +1} when
    signed polarity was asked for. ``width`` and ``height`` give the sensor.
    """

    x: "torch.Tensor"
    y: "torch.Tensor"
    t: "torch.Tensor"
    p: "torch.Tensor"
    width: int
    height: int


def _check_sensor_size(width: object, height: object) -> tuple[int, int]:
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            raise TypeError(f"{name} must be an integer number of pixels, got {value!r}")
        if not 0 < int(value) <= _MAX_SENSOR_SIZE:
            raise ValueError(f"{name} must be in [1, {_MAX_SENSOR_SIZE}] pixels, got {value}")
    if int(width) * int(height) > MAX_SENSOR_PIXELS:
        raise ValueError(f"a {int(width)}x{int(height)} sensor ({int(width) * int(height):,} pixels) is larger than "
                         f"any event camera (cmax.events.MAX_SENSOR_PIXELS = {MAX_SENSOR_PIXELS:,}): a corrupt or "
                         "crafted size?")
    return int(width), int(height)


def _one_dimensional(name: str, values: object) -> np.ndarray:
    """``values`` (a sequence, numpy array or torch tensor) as a numpy array, refused unless it is (N,)."""
    if hasattr(values, "detach") and hasattr(values, "cpu"):  # a torch tensor
        values = values.detach().cpu().numpy()
    array = np.asarray(values)
    if array.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional (N,), got shape {array.shape}")
    return array


def _as_column(name: str, values: object) -> np.ndarray:
    """A 1-D numpy array from ``values``, with NaN/inf and shape checks."""
    array = _one_dimensional(name, values)
    if array.dtype.kind not in "biuf":
        raise TypeError(f"{name} must hold numbers, got dtype {array.dtype}{_time_dtype_hint(name, array.dtype)}")
    if array.dtype.kind == "f":
        finite = np.isfinite(array)
        if not finite.all():
            bad = int(np.flatnonzero(~finite)[0])
            raise ValueError(f"{name} contains a non-finite value ({array[bad]}) at index {bad}")
        if array.size and not np.array_equal(array, np.round(array)):
            bad = int(np.flatnonzero(array != np.round(array))[0])
            raise ValueError(
                f"{name} must hold whole numbers, got {array[bad]} at index {bad}"
                + (" (times are integer microseconds; from float seconds: np.rint(t * 1e6).astype(np.int64), or "
                   "state their unit: time_unit='s')"
                   if name == "t" else "")
            )
    return array


def _time_dtype_hint(name: str, dtype: np.dtype) -> str:
    """For a column ``name`` of ``dtype`` refused as not numbers: the conversion of numpy's durations and dates
    (evlib's and polars' ``Duration``, pandas' ``Timedelta``) to integer µs where ``name`` is ``t``; else ""."""
    if name != "t" or dtype.kind not in "mM":
        return ""
    kind = "timedelta64" if dtype.kind == "m" else "datetime64"
    return (f" (numpy times carry their unit: integer µs{' since 1970' if dtype.kind == 'M' else ''} are "
            f"t.astype('{kind}[us]').astype(np.int64), which cuts finer times to whole µs)")


def _coordinates(name: str, values: object, size: int, size_name: str) -> np.ndarray:
    array = _as_column(name, values)
    if array.size:
        low, high = array.min(), array.max()
        if low < 0 or high >= size:
            bad = int(np.flatnonzero((array < 0) | (array >= size))[0])
            raise ValueError(
                f"{name} must lie in [0, {size_name}={size}), got {array[bad]} at index {bad}"
            )
    return array.astype(np.uint16, copy=False)


def _swapped_size_hint(x: object, y: object, width: int, height: int) -> str:
    """For columns ``x``, ``y`` [px] refused on a ``width`` x ``height`` sensor: a clause saying the size looks
    swapped where every event lies inside a ``height`` x ``width`` one (an image's shape is (height, width); tonic's
    ``sensor_size`` is (width, height, polarities)); "" otherwise, or where the columns are not numbers."""
    if width == height:
        return ""
    try:
        x, y = _as_column("x", x), _as_column("y", y)
    except (TypeError, ValueError):
        return ""
    if not x.size or x.size != y.size or min(x.min(), y.min()) < 0 or x.max() >= height or y.max() >= width:
        return ""
    return (f"; every event lies inside a {height}x{width} sensor: width and height swapped? (Events takes "
            f"width={height}, height={width} for them: an image's shape is (height, width), tonic's sensor_size "
            "(width, height, polarities))")


def _column_order_hint(array: np.ndarray, order: str) -> str:
    """For an (N, 4) ``array`` whose columns, named by ``order``, were refused: a clause naming the one column in
    time order (non-decreasing and not constant) where ``order`` puts ``t`` in another, and the ``order`` that
    reads it as ``t`` (ECD/rpg text files and v2e tables are t, x, y, p); "" otherwise. Only a hint: nothing is
    read in another order."""
    if array.shape[0] < 2 or array.dtype.kind not in "iuf":
        return ""
    ordered = [i for i in range(4) if array[-1, i] > array[0, i] and np.all(array[1:, i] >= array[:-1, i])]
    if len(ordered) != 1 or order[ordered[0]] == "t":
        return ""
    others = [name for name in order if name != "t"]
    suggested = "".join(others[:ordered[0]] + ["t"] + others[ordered[0]:])
    return (f"; column {ordered[0]} is the one in time order, not column {order.index('t')}: are the columns "
            f"{', '.join(suggested)}? (order={suggested!r}; ECD/rpg text files and v2e tables are t, x, y, p)")


def _base(values: object) -> object:
    """``values`` as the numpy array whose memory a stored column could share (a torch tensor's numpy view;
    anything else as given: only arrays can share memory)."""
    if hasattr(values, "detach") and hasattr(values, "numpy"):
        try:
            return values.detach().cpu().numpy()
        except (RuntimeError, TypeError):
            return values
    return values


def float_step(values: np.ndarray) -> tuple[int, float]:
    """``(i, step)``: the index of the largest magnitude in the float array ``values`` (non-empty) and the gap from
    it to the next value its dtype holds below it (in ``values``' unit): times whose step exceeds 1 µs have lost
    microseconds.

    >>> import numpy as np
    >>> float_step(np.array([3.0, 2.0**24 + 2], np.float32))
    (1, 2.0)
    """
    i = int(np.argmax(np.abs(values)))
    largest = np.abs(values[i])
    return i, float(largest - np.nextafter(largest, values.dtype.type(0)))


#: A uint32 microsecond clock wraps after this many µs (71.6 min).
UINT32_WRAP_US = 2**32


def wrap_index(t: np.ndarray) -> int | None:
    """The first index ``i`` of the int64 times ``t`` (µs) where they drop as a uint32 microsecond clock does when
    it wraps: ``t[i - 1]`` in ``[2**31, 2**32)``, ``t[i]`` in ``[0, 2**32)`` and more than ``2**31`` µs
    (35.8 min) below it; None if they never do.

    >>> wrap_index(np.array([4294967000, 4294967290, 4, 300]))
    2
    >>> wrap_index(np.array([5, 3, 10])) is None
    True
    """
    t = np.asarray(t)
    drop = np.flatnonzero((t[:-1] >= 2**31) & (t[:-1] < UINT32_WRAP_US) & (t[1:] >= 0) & (t[1:] < t[:-1] - 2**31))
    return int(drop[0]) + 1 if drop.size else None


def wrap_message(t: np.ndarray, i: int) -> str:
    """Why the times ``t`` (µs) that drop at index ``i`` (:func:`wrap_index`) cannot be sorted, and how to unwrap."""
    return (f"t drops from {int(t[i - 1])} µs at index {i - 1} to {int(t[i])} µs at index {i}, "
            f"{(int(t[i - 1]) - int(t[i])) / 60e6:.1f} min back: a uint32 microsecond clock that wrapped at "
            f"2**32 µs (71.6 min), not events out of order (sorting would put the later ones first); unwrap the "
            f"times: t = t.astype(np.int64) + 2**32 * np.cumsum(np.r_[0, np.diff(t.astype(np.int64)) < -2**31])")


def _timestamps(values: object) -> np.ndarray:
    array = _as_column("t", values)
    if array.dtype.kind == "u" and array.size and array.max() > np.iinfo(np.int64).max:
        raise ValueError("t does not fit into int64 microseconds")
    if array.dtype.kind == "f" and array.size and np.abs(array).max() > 2**62:
        raise ValueError("t does not fit into int64 microseconds")
    if array.dtype.kind == "f" and array.size:
        i, step = float_step(array)
        if step > 1:
            raise ValueError(f"t[{i}] = {array[i]} µs is a {array.dtype} number, whose values there lie "
                             f"{step:.3g} µs apart: microseconds are already lost (pass int64 microseconds)")
    array = array.astype(np.int64, copy=False)
    if array.size > 1:
        decreasing = np.flatnonzero(array[1:] < array[:-1])
        if decreasing.size:
            i = int(decreasing[0])
            wrapped = wrap_index(array)
            if wrapped is not None:
                raise ValueError(wrap_message(array, wrapped))
            raise ValueError(
                f"t must be sorted in non-decreasing order; t[{i + 1}]={array[i + 1]} µs comes "
                f"after t[{i}]={array[i]} µs (pass sort=True to sort by time explicitly; cmax: --sort)"
            )
    return array


def _stated_times(values: object, time_unit: object) -> np.ndarray:
    """The time column ``values`` (N,) in the stated ``time_unit`` (``'us'``, ``'ms'``, ``'s'`` or an alias) as
    int64 µs, converted by the file readers' :func:`cmax.io._checks.times_to_us` (integers scaled exactly, floats
    rounded to the nearest µs; overflow, NaN and a unit that rounding collapses are refused)."""
    from cmax.io._checks import check_time_unit, times_to_us

    unit = check_time_unit(time_unit)
    array = _one_dimensional("t", values)
    if array.dtype.kind not in "iuf":
        raise TypeError(f"t must hold numbers (times in {unit}), got dtype {array.dtype}"
                        f"{_time_dtype_hint('t', array.dtype)}")
    try:
        return times_to_us(array, unit, "t")
    except ValueError as error:         # a FormatError names a file; these are the caller's numbers
        raise ValueError(str(error)) from None


def _check_assumed_microseconds(t: np.ndarray) -> None:
    """Refuse the sorted int64 times ``t`` [µs by assumption, no unit stated] by the file readers' rule
    (:func:`cmax.io._checks.check_not_nanoseconds`, then :func:`cmax.io._checks.check_implied_rate`), as a
    :class:`ValueError`."""
    if not t.size:
        return
    from cmax.io._checks import check_implied_rate, check_not_nanoseconds

    try:
        check_not_nanoseconds(max(int(t[0]), int(t[-1]), key=abs), "t")
        check_implied_rate(int(t.size), int(t[0]), int(t[-1]), "t")
    except ValueError as error:         # a FormatError names a file; these are the caller's numbers
        raise ValueError(str(error)) from None


def _polarities(values: object) -> np.ndarray:
    """Polarity as int8 {0,1} from {0,1}, {-1,+1} or bool input."""
    array = _as_column("p", values)
    if array.dtype.kind == "b":
        return array.astype(np.int8)
    if not array.size:
        return array.astype(np.int8)
    present = np.unique(array)
    if np.isin(present, (0, 1)).all():
        return array.astype(np.int8, copy=False)
    if np.isin(present, (-1, 1)).all():
        return (array > 0).astype(np.int8)
    raise ValueError(
        "p must hold polarities as {0, 1}, {-1, +1} or bool; got the values "
        f"{present[:6].tolist()}{' ...' if present.size > 6 else ''}{polarity_hint(present.tolist())}"
    )


def polarity_hint(values: Sequence[float]) -> str:
    """For the distinct polarity ``values`` refused as neither {0, 1} nor {-1, +1}: a clause naming the encoding
    they look like and the explicit conversion ({0, 255}: an 8-bit image's; {1, 255}: -1/+1 cast to uint8, where
    -1 wraps to 255), to append to the refusal; "" otherwise. Nothing is mapped here.

    >>> polarity_hint([0, 255])
    '; 0/255 as an 8-bit image stores them? if 255 is ON pass p > 0'
    """
    present = set(values)
    if present <= {0, 255}:
        return "; 0/255 as an 8-bit image stores them? if 255 is ON pass p > 0"
    if present <= {1, 255}:
        return "; -1/+1 cast to uint8 (-1 wraps to 255)? convert p to int8 (255 becomes -1)"
    return ""


@dataclass(frozen=True, eq=False, repr=False)
class Events:
    """N events of a ``width`` x ``height`` sensor, sorted by time.

    Parameters
    ----------
    x, y : array_like, shape (N,)
        Pixel column and row, integers (any integer dtype, or floats holding
        whole numbers) with ``0 <= x < width`` and ``0 <= y < height``.
    t : array_like, shape (N,)
        Time stamps in microseconds (integers), non-decreasing.
    p : array_like, shape (N,)
        Polarity as {0, 1}, {-1, +1} or bool; stored as int8 {0, 1}.
    width, height : int
        Sensor size in pixels.
    sort : bool, keyword-only
        Sort the events by time (stable) instead of raising on unsorted ``t``.
    time_unit : {None, "us", "ms", "s"}, keyword-only
        The unit of ``t``. None (default): microseconds by assumption, checked by the file readers' rule for times
        whose unit nobody stated (:func:`cmax.io._checks.check_not_nanoseconds`,
        :func:`cmax.io._checks.check_implied_rate`): refused when a time lies after the year 2100 as µs since 1970
        and between 1973 and 2103 as ns (integer nanoseconds, a ROS or Metavision export), or when at least 10,000
        events imply a mean rate above ``MAX_EVENT_RATE_HZ`` (1.1e9 events/s: milliseconds of a fast recording).
        Not seen by that rule: nanoseconds since boot (convert them, ``t // 1000``), milliseconds of a recording
        slower than 1.1e6 events/s (state ``time_unit='ms'``). A stated unit is converted as the readers convert it (:func:`cmax.io._checks.times_to_us`:
        integers scaled exactly, floats such as seconds rounded to the nearest µs) and not checked further;
        ``"us"`` accepts a simulation's burst of many events a µs.

    The columns are checked once and are read-only afterwards (``ev.x += 1`` raises); an input array that
    the stored column would share memory with is copied, so changing it later does not change the events.

    Examples
    --------
    >>> ev = Events([0, 1, 2], [0, 0, 1], [10, 20, 30], [1, -1, 1], width=4, height=3)
    >>> len(ev), ev.p.tolist(), ev.signed_polarity().tolist()
    (3, [1, 0, 1], [1.0, -1.0, 1.0])
    >>> ev.slice_time(15, 30).t.tolist()
    [20]
    """

    x: np.ndarray
    y: np.ndarray
    t: np.ndarray
    p: np.ndarray
    width: int
    height: int

    def __init__(
        self,
        x: object,
        y: object,
        t: object,
        p: object,
        width: int,
        height: int,
        *,
        sort: bool = False,
        time_unit: str | None = None,
    ) -> None:
        width, height = _check_sensor_size(width, height)
        x_in, y_in, t_in, p_in = x, y, t, p
        for name, values in (("x", x), ("y", y), ("t", t), ("p", p)):
            shape = np.shape(values)  # no conversion for arrays and views
            if len(shape) == 1:
                check_event_count(shape[0], f"the column {name}")
        try:
            x = _coordinates("x", x, width, "width")
            y = _coordinates("y", y, height, "height")
        except ValueError as error:
            raise ValueError(f"{error}{_swapped_size_hint(x_in, y_in, width, height)}") from None
        p = _polarities(p)
        t_checked = _as_column("t", t) if time_unit is None else _stated_times(t, time_unit)
        lengths = {"x": x.size, "y": y.size, "t": t_checked.size, "p": p.size}
        if len(set(lengths.values())) != 1:
            raise ValueError(f"x, y, t and p must have the same length, got {lengths}")
        if sort:
            if t_checked.dtype.kind in "iu" and t_checked.size > 1:
                wrapped = wrap_index(t_checked)
                if wrapped is not None:
                    raise ValueError(wrap_message(t_checked, wrapped))
            order = np.argsort(t_checked, kind="stable")
            x, y, p, t_checked = x[order], y[order], p[order], t_checked[order]
        t = _timestamps(t_checked)
        if time_unit is None:
            _check_assumed_microseconds(t)
        # A column that is still the caller's array (already of the stored dtype) is copied: the caller may change
        # its buffer later, and the checks above (coordinates inside the sensor, time sorted) must keep holding.
        x, y, t, p = (np.array(column) if isinstance(given, np.ndarray) and np.may_share_memory(column, given)
                      else column for column, given in ((x, _base(x_in)), (y, _base(y_in)), (t, _base(t_in)),
                                                        (p, _base(p_in))))
        self._set(x, y, t, p, width, height)

    # -- construction -----------------------------------------------------------------
    def _set(self, x, y, t, p, width, height) -> None:
        """Store the columns as read-only views: validated once, they cannot be changed through the events
        (``ev.x += 1`` raises), so the compiled kernels can index with them without bounds checks."""
        for name, value in (("x", x), ("y", y), ("t", t), ("p", p)):
            column = np.ascontiguousarray(value).view()
            column.flags.writeable = False
            object.__setattr__(self, name, column)
        object.__setattr__(self, "width", width)
        object.__setattr__(self, "height", height)

    @classmethod
    def _trusted(cls, x, y, t, p, width: int, height: int) -> "Events":
        """Build without validation from columns already of the right dtypes and order."""
        events = cls.__new__(cls)
        events._set(x, y, t, p, width, height)
        return events

    @classmethod
    def empty(cls, width: int, height: int) -> "Events":
        """No events on a ``width`` x ``height`` sensor."""
        width, height = _check_sensor_size(width, height)
        return cls._trusted(
            np.empty(0, np.uint16), np.empty(0, np.uint16), np.empty(0, np.int64),
            np.empty(0, np.int8), width, height,
        )

    @classmethod
    def concatenate(cls, parts: Sequence["Events"]) -> "Events":
        """Join ``parts`` (a sequence of Events of the same sensor), in order (:func:`cmax.concatenate`); raises if
        time would decrease."""
        return concatenate(parts)

    @classmethod
    def from_structured(
        cls, array: np.ndarray, width: int, height: int, *, sort: bool = False, time_unit: str | None = None
    ) -> "Events":
        """Events from a structured array with fields ``x, y, t, p`` (any order): tonic's and
        Prophesee Metavision's layout; dv-processing's ``timestamp`` and ``polarity`` are read as ``t``
        and ``p`` where those are absent (:data:`FIELD_ALIASES`); other spellings (``ts``) are refused, naming
        the rename. A column held twice (``t`` and ``timestamp``, ``x`` and ``xs``, ``p`` and ``polarity``:
        :data:`DUPLICATE_SPELLINGS`) is read where the two agree, refused where they differ
        (:func:`check_duplicate_fields`).

        Fields may have any integer or bool dtype (``t`` in microseconds unless ``time_unit`` states another:
        ``'ms'``, ``'s'``, e.g. float seconds with ``'s'``; unstated µs are checked as :class:`Events` checks them:
        integer nanoseconds since 1970, or a mean rate above 1.1e9 events/s, refused);
        polarity may be {0, 1}, {-1, +1} or bool. Extra fields are ignored. ``width``, ``height``: the
        sensor size [px]; ``sort``: sort the events by time (stable) where it goes back, else refused.
        """
        array = np.asarray(array)
        names = array.dtype.names
        if names is None:
            raise TypeError(
                f"array must be a structured array with fields x, y, t, p; got dtype {array.dtype}"
            )
        fields = structured_fields(names)
        missing = [name for name, field in fields.items() if field not in names]
        if missing:
            raise ValueError(f"array lacks the field(s) {missing}; it has {list(names)}"
                             f"{field_rename_hint(names, missing)}")
        if array.ndim != 1:
            raise ValueError(f"array must be one-dimensional (N,), got shape {array.shape}")
        check_duplicate_fields(array, fields)
        return cls(*(array[fields[name]] for name in "xytp"), width, height, sort=sort, time_unit=time_unit)

    @classmethod
    def from_array(
        cls, array: object, width: int, height: int, *, order: str = "xytp", sort: bool = False,
        time_unit: str | None = None,
    ) -> "Events":
        """Events from an (N, 4) array whose columns are named by ``order``.

        ``order`` is a permutation of ``"xytp"``, e.g. ``"txyp"`` for the ECD
        text layout. Time is in integer microseconds unless ``time_unit`` states another (``'s'`` for the ECD
        text's float seconds); unstated µs are checked as :class:`Events` checks them. A
        structured array (named fields, e.g. a tonic data set's events) is read
        by its field names (:meth:`from_structured`), not by ``order``. ``width``, ``height``: the sensor
        size [px]; ``sort``: sort the events by time (stable) where it goes back, else refused.
        """
        if sorted(order) != sorted("xytp") or len(order) != 4:
            raise ValueError(f"order must be a permutation of 'xytp', got {order!r}")
        if hasattr(array, "detach"):
            array = array.detach().cpu().numpy()
        array = np.asarray(array)
        if array.dtype.names is not None:
            return cls.from_structured(array, width, height, sort=sort, time_unit=time_unit)
        if array.ndim != 2 or array.shape[1] != 4:
            raise ValueError(f"array must have shape (N, 4), got {array.shape}")
        columns = {name: array[:, i] for i, name in enumerate(order)}
        try:
            return cls(columns["x"], columns["y"], columns["t"], columns["p"], width, height, sort=sort,
                       time_unit=time_unit)
        except ValueError as error:
            hint = _column_order_hint(array, order)
            if not hint or isinstance(error, EventLimitError):
                raise
            raise ValueError(f"{error}{hint}") from None

    # -- conversion -------------------------------------------------------------------
    def to_structured(self) -> np.ndarray:
        """A structured array of dtype :data:`STRUCTURED_DTYPE` (fields x, y, t, p)."""
        out = np.empty(len(self), STRUCTURED_DTYPE)
        out["x"], out["y"], out["t"], out["p"] = self.x, self.y, self.t, self.p
        return out

    def to_array(self, order: str = "xytp") -> np.ndarray:
        """An (N, 4) int64 array with columns in ``order`` (a permutation of 'xytp')."""
        if sorted(order) != sorted("xytp") or len(order) != 4:
            raise ValueError(f"order must be a permutation of 'xytp', got {order!r}")
        return np.stack([getattr(self, name).astype(np.int64) for name in order], axis=1)

    def signed_polarity(self, dtype: np.dtype | type = np.float32) -> np.ndarray:
        """Polarity as -1 (OFF) / +1 (ON), shape (N,) of ``dtype`` (default float32), the paper's ``p_i``."""
        return (2 * self.p.astype(dtype) - 1).astype(dtype, copy=False)

    def to_torch(self, device: object = None, *, signed_polarity: bool = False) -> EventTensors:
        """The columns as torch tensors on ``device`` (None: the CPU): x, y, t int64 (t in µs); p int8 in {0, 1},
        or float32 ±1 with ``signed_polarity``."""
        import torch

        p = (
            torch.from_numpy(self.signed_polarity(np.float32))
            if signed_polarity
            else torch.from_numpy(self.p.copy())
        )
        return EventTensors(        # copies: a tensor changed in place must not change these (read-only) events
            torch.from_numpy(self.x.astype(np.int64)).to(device),
            torch.from_numpy(self.y.astype(np.int64)).to(device),
            torch.from_numpy(self.t.copy()).to(device),
            p.to(device),
            self.width,
            self.height,
        )

    # -- properties -------------------------------------------------------------------
    @property
    def sensor_size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels."""
        return self.width, self.height

    @property
    def t_start(self) -> int:
        """Time of the first event in µs (raises on empty events)."""
        self._require_events("t_start")
        return int(self.t[0])

    @property
    def t_end(self) -> int:
        """Time of the last event in µs (raises on empty events)."""
        self._require_events("t_end")
        return int(self.t[-1])

    @property
    def duration_us(self) -> int:
        """``t_end - t_start`` in µs; 0 for fewer than two events."""
        return int(self.t[-1] - self.t[0]) if len(self) > 1 else 0

    def _require_events(self, what: str) -> None:
        if not len(self):
            raise ValueError(f"{what} is undefined for empty events")

    # -- container protocol -----------------------------------------------------------
    def __len__(self) -> int:
        return int(self.t.size)

    def __getitem__(self, index: object) -> "Events | tuple[int, int, int, int]":
        """An int gives one event ``(x, y, t, p)``; a slice, boolean mask or
        increasing index array gives :class:`Events`."""
        if isinstance(index, (int, np.integer)):
            i = int(index)
            return int(self.x[i]), int(self.y[i]), int(self.t[i]), int(self.p[i])
        if isinstance(index, slice):
            if index.step is not None and index.step < 0:
                raise IndexError("events cannot be indexed with a negative step (time order)")
            return Events._trusted(
                self.x[index], self.y[index], self.t[index], self.p[index],
                self.width, self.height,
            )
        selection = np.asarray(index)
        if selection.dtype == bool:
            if selection.shape != self.t.shape:
                raise IndexError(
                    f"boolean mask must have shape {self.t.shape}, got {selection.shape}"
                )
        elif selection.dtype.kind in "iu" and selection.ndim == 1:
            if selection.size > 1 and np.any(np.diff(selection) < 0):
                raise IndexError("an index array must be non-decreasing to keep events in time order")
        else:
            raise IndexError(f"events cannot be indexed with {type(index).__name__}")
        return Events._trusted(
            self.x[selection], self.y[selection], self.t[selection], self.p[selection],
            self.width, self.height,
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Events):
            return NotImplemented
        return self.sensor_size == other.sensor_size and all(
            np.array_equal(getattr(self, name), getattr(other, name)) for name in "xytp"
        )

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        span = f", t=[{self.t[0]}, {self.t[-1]}] µs" if len(self) else ""
        return f"Events(n={len(self)}, sensor={self.width}x{self.height}{span})"

    # -- time slicing -----------------------------------------------------------------
    def index_at(self, t_us: int) -> int:
        """Index of the first event with ``t >= t_us`` (binary search).

        ``t_us``: integer microseconds (a float must hold a whole number); times
        beyond the int64 range give 0 or ``len(self)``.
        """
        t_us = check_time_us("t_us", t_us)
        if t_us > _INT64_MAX:
            return len(self)
        if t_us < _INT64_MIN:
            return 0
        return int(np.searchsorted(self.t, np.int64(t_us), side="left"))

    def slice_time(self, t0_us: int, t1_us: int) -> "Events":
        """Events with ``t0_us <= t < t1_us`` (a view, found by binary search).

        Times are integer microseconds (floats must hold whole numbers: a
        fraction of a µs is refused, not rounded); ``t0_us == t1_us`` gives no
        events; ``t1_us < t0_us`` raises :class:`ValueError`.
        """
        t0_us, t1_us = check_time_us("t0_us", t0_us), check_time_us("t1_us", t1_us)
        if t1_us < t0_us:
            raise ValueError(f"t1_us ({t1_us}) must not be smaller than t0_us ({t0_us})")
        return self[self.index_at(t0_us): self.index_at(t1_us)]

    def windows(
        self,
        *,
        duration_us: int | None = None,
        count: int | None = None,
        step_us: int | None = None,
        t_start_us: int | None = None,
    ) -> Iterator["Events"]:
        """Iterate over windows of fixed duration or of a fixed number of events.

        Give exactly one of ``duration_us`` (windows ``[t0 + k*step, t0 + k*step + duration)`` [µs],
        ``step_us`` defaulting to ``duration_us``, ``t0`` = ``t_start_us`` defaulting to the first event) or
        ``count`` (consecutive windows of ``count`` events; the last may be shorter).
        """
        if (duration_us is None) == (count is None):
            raise ValueError("give exactly one of duration_us and count")
        if count is not None:
            if step_us is not None or t_start_us is not None:
                raise ValueError("step_us and t_start_us apply to windows by duration only")
            if isinstance(count, (bool, np.bool_)) or not isinstance(count, (int, np.integer)):
                raise TypeError(f"count must be an integer number of events, got {count!r}")
            if int(count) <= 0:
                raise ValueError(f"count must be positive, got {count}")
            for start in range(0, len(self), int(count)):
                yield self[start: start + int(count)]
            return
        duration, step = window_steps(duration_us, step_us)
        if not len(self):
            return
        start = self.t_start if t_start_us is None else check_time_us("t_start_us", t_start_us)
        while start <= self.t_end:
            yield self.slice_time(start, start + duration)
            start += step


def window_steps(duration_us: int, step_us: int | None) -> tuple[int, int]:
    """Validated ``(duration, step)`` in µs of sliding windows; the step defaults to the duration."""
    duration = check_time_us("duration_us", duration_us)
    if duration <= 0:
        raise ValueError(f"duration_us must be positive, got {duration_us}")
    step = duration if step_us is None else check_time_us("step_us", step_us)
    if step <= 0:
        raise ValueError(f"step_us must be positive, got {step_us}")
    return duration, step


#: A window counts as whole when it ends at most this fraction of its length after the last event: a recording's
#: end is known only to within the gap after its last event (the events of ``--t0 0.6 --t1 0.8`` end a few µs
#: before 0.8 s, and 100 ms windows from the first of them should still be two).
WINDOW_END_TOLERANCE = 0.01


def window_starts(first_us: int, last_us: int, window_us: int, step_us: int) -> np.ndarray:
    """Starts (N,) int64 [µs] of the whole windows ``[t0, t0 + window_us)`` from ``first_us``, every ``step_us``,
    that end by ``last_us + 1`` (``last_us``: the last event, inclusive), or at most
    :data:`WINDOW_END_TOLERANCE` of a window later. Empty when even one window is longer.

    >>> window_starts(0, 249, 100, 100).tolist()          # 250 µs of events: two whole windows
    [0, 100]
    >>> window_starts(0, 249, 100, 50).tolist()           # overlapping windows
    [0, 50, 100, 150]
    >>> window_starts(6, 199_992, 100_000, 100_000).tolist()   # the last ends 14 µs after the last event
    [6, 100006]
    """
    slack = int(WINDOW_END_TOLERANCE * int(window_us))
    return np.arange(int(first_us), int(last_us) + 2 + slack - int(window_us), int(step_us), dtype=np.int64)


def uncovered_tail(first_us: int, last_us: int, window_us: int, step_us: int) -> tuple[int, int] | None:
    """``(start, end)`` [µs], ``end`` exclusive, of the recording after its last whole window (the windows of
    :func:`window_starts`), which a window-by-window fit leaves out; None when the windows reach ``last_us``
    (or when no window fits at all: then nothing is covered, which callers report on its own).

    >>> uncovered_tail(0, 249, 100, 100)                  # the last 50 µs
    (200, 250)
    >>> uncovered_tail(0, 299, 100, 100) is None
    True
    """
    starts = window_starts(first_us, last_us, window_us, step_us)
    if not len(starts):
        return None
    end = int(starts[-1]) + int(window_us)
    return (end, int(last_us) + 1) if end <= int(last_us) else None


def concatenate(parts: Sequence[Events]) -> Events:
    """Join ``parts`` (a sequence of :class:`Events` of the same sensor), in order; raises if time would decrease."""
    parts = list(parts)
    if not parts:
        raise ValueError("parts must hold at least one Events object")
    for i, part in enumerate(parts):
        if not isinstance(part, Events):
            raise TypeError(f"parts[{i}] must be Events, got {type(part).__name__}")
        if part.sensor_size != parts[0].sensor_size:
            raise ValueError(
                f"parts[{i}] has sensor {part.sensor_size}, parts[0] has {parts[0].sensor_size}"
            )
    non_empty = [part for part in parts if len(part)]
    for i in range(1, len(non_empty)):
        if non_empty[i].t[0] < non_empty[i - 1].t[-1]:
            raise ValueError(
                f"events would go back in time: a part starts at {non_empty[i].t[0]} µs after "
                f"one that ends at {non_empty[i - 1].t[-1]} µs"
            )
    width, height = parts[0].sensor_size
    return Events._trusted(
        *(np.concatenate([getattr(part, name) for part in parts]) for name in "xytp"),
        width, height,
    )
