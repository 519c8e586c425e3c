"""Checks every reader applies to raw columns: time units, time ranges, polarity encodings, sizes.

Nothing here guesses. A time column becomes int64 microseconds only under a
known unit (the format's own, a unit attribute in the file, or the caller's
``time_unit=``); float times are rounded to the nearest microsecond only under
such a unit; NaN, infinity and values outside int64 microseconds are named by
index. A polarity column becomes int8 {0 OFF, 1 ON} only from the encoding
the format (or the caller) states; any other value is refused, never mapped.
"""
from __future__ import annotations

import math
import os
from typing import Any

import numpy as np

from cmax.events import _check_sensor_size, float_step
from cmax.io.errors import FormatError

__all__ = [
    "TIME_UNITS", "POLARITY_ENCODINGS", "check_time_unit", "unit_from_attrs", "times_to_us",
    "scalar_to_us", "check_offset", "add_offset", "polarity_01", "check_allocated", "check_implied_rate",
    "check_not_nanoseconds", "MAX_EVENT_RATE_HZ",
]

#: Microseconds per unit of a stated time unit.
TIME_UNITS = {"us": 1, "ms": 1000, "s": 1_000_000}
_UNIT_ALIASES = {
    "us": "us", "µs": "us", "μs": "us", "usec": "us", "microsecond": "us", "microseconds": "us",
    "ms": "ms", "msec": "ms", "millisecond": "ms", "milliseconds": "ms",
    "s": "s", "sec": "s", "second": "s", "seconds": "s",
}
#: Polarity encodings a reader can be told: ``"01"`` (0 OFF, 1 ON) or ``"signed"`` (-1 OFF, +1 ON).
POLARITY_ENCODINGS = ("01", "signed")
_INT64_MAX = int(np.iinfo(np.int64).max)
_INT64_MIN = int(np.iinfo(np.int64).min)
#: Largest magnitude a float time may reach in µs (float64 holds integers exactly up to 2**53).
_FLOAT_US_LIMIT = float(2**62)


def check_time_unit(time_unit: object, name: str = "time_unit") -> str | None:
    """``None`` or the canonical name (``'us'``, ``'ms'``, ``'s'``) of a stated time unit."""
    if time_unit is None:
        return None
    if isinstance(time_unit, bytes):
        time_unit = time_unit.decode("utf-8", "replace")
    if not isinstance(time_unit, str) or time_unit.strip().lower() not in _UNIT_ALIASES:
        raise ValueError(f"{name} must be one of 'us', 'ms', 's' (or None), got {time_unit!r}")
    return _UNIT_ALIASES[time_unit.strip().lower()]


def unit_from_attrs(attrs: Any, where: str, keys: tuple[str, ...] = ("unit", "units", "time_unit")) -> str | None:
    """The time unit an HDF5 object's attributes state (the first of ``keys`` present), or None."""
    for key in keys:
        if key in attrs:
            try:
                return check_time_unit(attrs[key], f"{where} attribute {key!r}")
            except ValueError as error:
                raise FormatError(str(error)) from None
    return None


#: Rounding float times to whole µs that merges this many distinct consecutive times into one is a unit error.
_COLLAPSE = 100


def _smaller_unit_note(value: float, unit: str) -> str:
    """For a time ``value`` stated in ``unit`` too large for int64 µs: the smaller unit of :data:`TIME_UNITS` that
    puts it between 1973 and 2100 as seconds since 1970 (a recording's clock), and how to state it; "" if none does.

    >>> _smaller_unit_note(1500000000997210.0, "s")
    "; as us it is 1500000000.997210 s since 1970: state the unit with time_unit='us' (cmax: --time-unit us)"
    """
    for smaller in ("ms", "us"):
        if TIME_UNITS[smaller] < TIME_UNITS[unit] and 1e8 <= abs(value) * TIME_UNITS[smaller] * 1e-6 < 4.1e9:
            return (f"; as {smaller} it is {value * TIME_UNITS[smaller] * 1e-6:.6f} s since 1970: state the unit with "
                    f"time_unit='{smaller}' (cmax: --time-unit {smaller})")
    return ""


def times_to_us(t: np.ndarray, unit: str, where: str) -> np.ndarray:
    """A raw time column as int64 µs under ``unit`` (canonical); may return ``t`` itself, modified.

    Integers are scaled exactly (overflow refused); floats are checked for
    NaN/infinity, scaled and rounded to the nearest microsecond (``np.rint``,
    half to even). Float times whose rounding to whole µs would merge at least :data:`_COLLAPSE` of their
    distinct consecutive values into one (when there are at least as many) are refused: that is another unit, not
    sub-µs precision (seconds read as µs, an ECD text file with ``time_unit='us'``, collapse the whole
    recording into a microsecond), and so are float times whose dtype cannot hold every microsecond where
    they lie (float32 beyond 2**24 µs). Raises :class:`FormatError` naming ``where`` and the index.
    """
    factor = TIME_UNITS[unit]
    kind = t.dtype.kind
    if kind in "iu":
        if not t.size:
            return t.astype(np.int64)
        if kind == "u" and t.dtype.itemsize == 8 and int(t.max()) > _INT64_MAX // factor:
            i = int(np.argmax(t))
            raise FormatError(f"{where}[{i}] = {int(t[i])} {unit} does not fit into int64 microseconds")
        if factor != 1:
            low, high = int(t.min()), int(t.max())
            if high * factor > _INT64_MAX or low * factor < _INT64_MIN:
                i = int(np.argmax(t)) if high * factor > _INT64_MAX else int(np.argmin(t))
                raise FormatError(f"{where}[{i}] = {int(t[i])} {unit} does not fit into int64 microseconds"
                                  f"{_smaller_unit_note(float(t[i]), unit)}")
            return t.astype(np.int64) * factor
        return t if t.dtype == np.int64 else t.astype(np.int64)
    if kind == "f":
        scaled = np.multiply(t, float(factor), dtype=np.float64)
        finite = np.isfinite(scaled)
        if not finite.all():
            i = int(np.flatnonzero(~finite)[0])
            raise FormatError(f"{where}[{i}] is {t[i]}, a non-finite time (times must be finite)")
        if scaled.size and np.abs(scaled).max() > _FLOAT_US_LIMIT:
            i = int(np.argmax(np.abs(scaled)))
            raise FormatError(f"{where}[{i}] = {t[i]} {unit} does not fit into int64 microseconds"
                              f"{_smaller_unit_note(float(t[i]), unit)}")
        if scaled.size:
            i, step = float_step(t)
            step_us = step * factor
            if step_us > 1:
                raise FormatError(f"{where}[{i}] = {t[i]} {unit} is a {t.dtype} number, whose values there lie "
                                  f"{step_us:.3g} µs apart: microseconds are already lost (store times as int64 "
                                  "µs or float64)")
        rounded = np.rint(scaled)
        distinct = int(np.count_nonzero(np.diff(scaled))) + 1 if scaled.size else 0
        if distinct >= _COLLAPSE:
            kept = int(np.count_nonzero(np.diff(rounded))) + 1
            if kept * _COLLAPSE < distinct:
                raise FormatError(f"{where} holds {distinct:,} distinct times stated in {unit}, which rounding to whole "
                                  f"microseconds merges into {kept:,} (from {float(t[0])!r} to {float(t[-1])!r} "
                                  f"{unit}): another unit? (time_unit='s' or 'ms'; cmax: --time-unit s)")
        return rounded.astype(np.int64)
    raise FormatError(f"{where} must hold numbers (times), got dtype {t.dtype}")


def scalar_to_us(value: Any, unit: str, where: str) -> int:
    """One stored time (e.g. ``t_offset``) as int µs under ``unit``, with the checks of :func:`times_to_us`."""
    array = np.asarray(value)
    if array.shape not in ((), (1,)):
        raise FormatError(f"{where} must be a single number, got shape {array.shape}")
    return int(times_to_us(array.reshape(1), unit, where)[0])


def check_offset(t_us: np.ndarray, offset_us: int, where: str) -> None:
    """Refuse ``t_us + offset_us`` beyond int64 (``t_us`` non-decreasing: its ends bound it)."""
    if not offset_us or not t_us.size:
        return
    first, last = int(t_us[0]) + offset_us, int(t_us[-1]) + offset_us
    if last > _INT64_MAX or first < _INT64_MIN:
        i, value = (t_us.size - 1, int(t_us[-1])) if last > _INT64_MAX else (0, int(t_us[0]))
        raise FormatError(
            f"{where}[{i}] = {value} µs plus t_offset = {offset_us} µs overflows int64 microseconds"
        )


def add_offset(t_us: np.ndarray, offset_us: int, where: str) -> np.ndarray:
    """``t_us + offset_us`` in place (``t_us`` int64, non-decreasing), refusing int64 overflow."""
    check_offset(t_us, offset_us, where)
    if offset_us and t_us.size:
        t_us += np.int64(offset_us)
    return t_us


def check_polarity_encoding(polarity: object) -> str:
    """The validated polarity encoding name (one of :data:`POLARITY_ENCODINGS`)."""
    if polarity not in POLARITY_ENCODINGS:
        raise ValueError(f"polarity must be one of {POLARITY_ENCODINGS}, got {polarity!r}")
    return str(polarity)


def polarity_01(p: np.ndarray, encoding: str, where: str) -> np.ndarray:
    """A raw polarity column as int8 {0 OFF, 1 ON}, from the stated ``encoding``.

    ``"01"``: values must be 0 or 1 (bool allowed); ``"signed"``: values must be
    -1 or +1. Anything else raises :class:`FormatError` listing the values found;
    the cost is a min/max pass (plus a zero count for ``"signed"``).
    """
    if p.dtype.kind == "b":
        if encoding == "signed":
            raise FormatError(f"{where} holds booleans, not the stated -1/+1 polarity")
        return p.view(np.int8)
    if p.dtype.kind not in "iuf":
        raise FormatError(f"{where} must hold polarities as numbers, got dtype {p.dtype}")
    if not p.size:
        return np.empty(0, np.int8)
    low, high = (0 if p.dtype.kind == "u" else p.min()), p.max()
    if encoding == "01":
        if low >= 0 and high <= 1 and (p.dtype.kind != "f" or np.all((p == 0) | (p == 1))):
            return p.view(np.int8) if p.dtype.itemsize == 1 and p.dtype.kind in "iu" else p.astype(np.int8)
    elif low >= -1 and high <= 1 and np.count_nonzero(p) == p.size and (
        p.dtype.kind != "f" or np.all(np.abs(p) == 1)
    ):
        return (p > 0).view(np.int8)
    values = np.unique(p)
    shown = values[:6].tolist()
    stated = "0 (OFF) / 1 (ON)" if encoding == "01" else "-1 (OFF) / +1 (ON)"
    other = "signed" if encoding == "01" else "01"
    fits_other = set(values.tolist()) <= ({-1, 1} if other == "signed" else {0, 1})
    advice = (f"pass polarity={other!r} (cmax: --polarity {other}) if the file stores that encoding" if fits_other
              else "they fit neither 0/1 nor -1/+1: convert the column to one of them")
    raise FormatError(
        f"{where} holds the polarity values {shown}{' ...' if values.size > 6 else ''}, but the "
        f"stated encoding is {stated}; {advice} (polarities are never mapped silently)"
    )


#: The highest mean event rate [events/s] a recording read in an assumed time unit may imply: above the fastest
#: sensor's rated peak (Sony/Prophesee IMX636: 1.066e9 events/s), which a short recording of one burst reaches as its
#: mean; a recording's mean lies at or below its peak.
MAX_EVENT_RATE_HZ = 1.1e9
#: Recordings of fewer events than this are never refused for their rate (a short burst proves nothing).
_RATE_MIN_EVENTS = 10_000


def check_implied_rate(count: int, first_us: int, last_us: int, where: str) -> None:
    """Refuse ``count`` events from ``first_us`` to ``last_us`` [µs], times whose unit was ASSUMED to be µs (the
    format's default, stated by neither the file nor the caller), when their mean rate exceeds
    :data:`MAX_EVENT_RATE_HZ`: no sensor produces it, and integer times in milliseconds read as µs (a user's export)
    make a recording 1000 times shorter and its rate 1000 times higher. ``where`` names the file and column.
    Not seen: milliseconds of a recording slow enough that 1000 times its rate stays below the limit.

    >>> check_implied_rate(3_000_000, 0, 1_999, "a.h5: events/t")   # 3 M events in 2 ms
    Traceback (most recent call last):
    ...
    cmax.io.errors.FormatError: a.h5: events/t, read as microseconds ... a mean of 1.5e+09 events/s, ...
    """
    span_us = int(last_us) - int(first_us) + 1
    if count < _RATE_MIN_EVENTS or span_us <= 0:
        return
    rate = count / (span_us * 1e-6)
    if rate > MAX_EVENT_RATE_HZ:
        raise FormatError(
            f"{where}, read as microseconds (the format's default unit, which neither the file nor the caller states), "
            f"puts {count:,} events in {span_us / 1000:.1f} ms: a mean of {rate:.1e} events/s, more than any event "
            f"sensor produces (MAX_EVENT_RATE_HZ = {MAX_EVENT_RATE_HZ:g}); if these times are milliseconds pass "
            "time_unit='ms' (cmax: --time-unit ms), if they are microseconds (a simulation) time_unit='us'"
        )


#: 2100-01-01 in µs since 1970: a time in µs beyond it belongs to no clock (neither since 1970 nor since boot).
_YEAR_2100_US = 4_102_444_800 * 1_000_000


def check_not_nanoseconds(t_us: int, where: str) -> None:
    """Refuse a time ``t_us`` [µs] whose unit was ASSUMED to be µs (stated by neither the file nor the caller) when
    it lies after the year 2100 as µs since 1970 and between 1973 and 2103 as nanoseconds since 1970: integer
    nanoseconds (a ROS or Metavision export; since 1970 about 1.7e18) read as µs put a recording in the year 55,000
    and make it 1000 times longer. ``where`` names the file and column. Other huge times are left to the checks of
    int64 overflow.

    >>> check_not_nanoseconds(1_700_000_000_000_000_000, "a.npy: field t")
    Traceback (most recent call last):
    ...
    cmax.io.errors.FormatError: a.npy: field t: the time 1700000000000000000, read as microseconds ...: these look
    like nanoseconds (1700000000.000 s since 1970 if so); ...
    """
    seconds = int(t_us) / 1e9
    if abs(int(t_us)) < _YEAR_2100_US or not 1e8 <= seconds < 4.2e9:   # µs, or not nanoseconds since 1970 either
        return
    raise FormatError(
        f"{where}: the time {int(t_us)}, read as microseconds (the format's default unit, which neither the file nor "
        f"the caller states), lies after the year 2100 as µs since 1970: these look like nanoseconds ({seconds:.3f} "
        "s since 1970 if so); convert the times to integer microseconds (t // 1000) and read them again"
    )


def check_allocated(dataset: Any, where: str) -> None:
    """Refuse an HDF5 dataset whose declared length exceeds the data the file really stores.

    A chunked dataset must have every chunk it declares written, a contiguous one
    its whole extent; otherwise reading it would conjure fill values (and memory)
    out of a few bytes of metadata. O(1): only the chunk count is asked.
    """
    shape = dataset.shape
    if shape is None or not len(shape) or not dataset.size:
        return
    dsid = dataset.id
    if dataset.chunks is not None:
        needed = math.prod(-(-n // c) for n, c in zip(shape, dataset.chunks))
        stored = dsid.get_num_chunks()
        if stored < needed:
            raise FormatError(
                f"{where} declares {dataset.size:,} entries in {needed:,} chunks but the file stores "
                f"only {stored:,} of them (truncated or crafted; refusing to allocate)"
            )
    elif dataset.external is None and dsid.get_storage_size() < dataset.size * dataset.dtype.itemsize:
        raise FormatError(
            f"{where} declares {dataset.size:,} entries but the file stores only "
            f"{dsid.get_storage_size():,} of their {dataset.size * dataset.dtype.itemsize:,} bytes "
            "(truncated or crafted; refusing to allocate)"
        )


def check_stated_size(
    width: int | None, height: int | None, stated: tuple[int, int], where: str | os.PathLike
) -> tuple[int, int]:
    """The sensor size ``stated`` by the file ``where``, after checking the caller's ``width``/``height``.

    A caller's size is for files that store none: one given for a file that
    states its own must equal it (pixels), else :class:`ValueError`; nothing is
    overridden or ignored silently. ``stated`` is returned unchanged.

    >>> check_stated_size(None, None, (64, 48), "a.h5"), check_stated_size(64, 48, (64, 48), "a.h5")
    ((64, 48), (64, 48))
    """
    if width is None and height is None:
        return stated
    if width is None or height is None:
        raise ValueError("give both width and height, or neither")
    width, height = _check_sensor_size(width, height)
    if (width, height) != tuple(stated):
        raise ValueError(
            f"width={width}, height={height} contradicts the {stated[0]}x{stated[1]} sensor that {where} "
            "states; leave the size out (it is for files that do not store one)"
        )
    return stated
