"""Writing Prophesee RAW files: EVT 3.0 (:func:`write_evt3`) and EVT 2.0 (:func:`write_evt2`).

The encoders are vectorized over events and run block by block
(``_ENCODE_BLOCK`` events at a time), carrying the last event's time and row
from one block to the next. A file is written by the protocol of
:mod:`cmax.io.atomic` (a lock, a private ``<path>.<hex>.partial`` file never
reached through a link, fsync and rename when complete); a write error (full
disk, file-size limit) names the file and leaves nothing under its name.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from cmax.events import Events
from cmax.io.atomic import AtomicOutput, write_with
from cmax.io.prophesee._header import PathLike

__all__ = ["write_evt3", "write_evt2"]

_MAX_COORDINATE = 2048            # both formats carry 11-bit coordinates
_EVT3_MAX_T = 1 << 40             # encoder limit (µs), see write_evt3
_ENCODE_BLOCK = 1 << 18           # events encoded at a time


class _Previous(NamedTuple):
    """The last event already encoded (None before the first): time (µs) and row."""

    t: int
    y: int


def _time_high_words(
    high: np.ndarray, max_step: int, previous_high: int | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """TIME_HIGH words to emit before each unit, so that no step exceeds ``max_step``.

    ``high`` (U,) holds the absolute time-high of each unit (non-decreasing).
    A unit gets one word per ``max_step`` of increase (none if unchanged); the
    first unit of a file gets a ramp from 0, at least one word. Returns the
    count (U,), the values, and each value's position within its unit.
    """
    previous = np.empty_like(high)
    previous[0] = 0 if previous_high is None else previous_high
    previous[1:] = high[:-1]
    count = (high - previous + max_step - 1) // max_step
    if previous_high is None:
        count[0] = max(int(count[0]), 1)
    unit = np.repeat(np.arange(high.size), count)
    k = np.arange(unit.size) - np.repeat(np.cumsum(count) - count, count)
    values = np.where(k == count[unit] - 1, high[unit], previous[unit] + max_step * (k + 1))
    return count, values, k


def _changed(values: np.ndarray, previous: int | None) -> np.ndarray:
    """Whether each value differs from the one before it (the first from ``previous``)."""
    changed = np.empty(values.size, bool)
    changed[0] = previous is None or values[0] != previous
    changed[1:] = values[1:] != values[:-1]
    return changed


def _scatter(n_words: int, dtype: str, parts) -> np.ndarray:
    words = np.empty(n_words, dtype)
    for positions, values in parts:
        words[positions] = values
    return words


def _encode_evt3(x, y, t, p, previous: _Previous | None) -> np.ndarray:
    """EVT 3.0 words ('<u2') for sorted events, following ``previous``.

    Runs of >= 3 events sharing (t, y, p) with increasing x in one 12-pixel
    block become one VECT_12 word (after a VECT_BASE_X unless the previous
    vector ended where this one starts); other events become ADDR_X words.
    """
    x, y, p = x.astype(np.int32), y.astype(np.int32), p.astype(np.int32)
    block = x // 12
    new_run = np.ones(t.size, bool)
    new_run[1:] = (
        (t[1:] != t[:-1]) | (y[1:] != y[:-1]) | (p[1:] != p[:-1])
        | (block[1:] != block[:-1]) | (x[1:] <= x[:-1])
    )
    run_start = np.flatnonzero(new_run)
    run_length = np.diff(np.append(run_start, t.size))
    vector_run = run_length >= 3
    unit_start = np.flatnonzero(new_run | ~np.repeat(vector_run, run_length))
    vector = np.repeat(vector_run, np.where(vector_run, 1, run_length))
    ut, uy, up, ux, ub = (a[unit_start] for a in (t, y, p, x, block))
    mask = np.bitwise_or.reduceat(np.left_shift(1, x - 12 * block), unit_start)

    n_high, high_values, k = _time_high_words(
        ut >> 12, 2047, None if previous is None else previous.t >> 12
    )
    has_low = _changed(ut, None if previous is None else previous.t) | (n_high > 0)
    has_y = _changed(uy, None if previous is None else previous.y)
    chained = np.zeros(ut.size, bool)   # base x is already right: previous vector's block + 1
    chained[1:] = (
        vector[1:] & vector[:-1] & ~has_low[1:] & ~has_y[1:]
        & (up[1:] == up[:-1]) & (ub[1:] == ub[:-1] + 1)
    )
    has_base = vector & ~chained
    total = n_high + has_low + has_y + has_base + 1
    first = np.cumsum(total) - total
    low_pos = first + n_high
    y_pos = low_pos + has_low
    base_pos = y_pos + has_y
    return _scatter(int(total.sum()), "<u2", (
        (np.repeat(first, n_high) + k, 0x8000 | (high_values & 0xFFF)),
        (low_pos[has_low], 0x6000 | (ut[has_low] & 0xFFF)),
        (y_pos[has_y], uy[has_y]),
        (base_pos[has_base], 0x3000 | (up[has_base] << 11) | (12 * ub[has_base])),
        (first + total - 1, np.where(vector, 0x4000 | mask, 0x2000 | (up << 11) | ux)),
    ))


def _encode_evt2(x, y, t, p, previous: _Previous | None) -> np.ndarray:
    """EVT 2.0 words ('<u4'): TIME_HIGH when t >> 6 changes, one CD word per event."""
    n_high, high_values, k = _time_high_words(
        t >> 6, (1 << 27) - 1, None if previous is None else previous.t >> 6
    )
    first = np.cumsum(n_high + 1) - (n_high + 1)
    cd = (
        (p.astype(np.int64) << 28) | ((t & 0x3F) << 22)
        | (x.astype(np.int64) << 11) | y.astype(np.int64)
    )
    return _scatter(int(n_high.sum()) + t.size, "<u4", (
        (np.repeat(first, n_high) + k, (0x8 << 28) | (high_values & 0x0FFFFFFF)),
        (first + n_high, cd),
    ))


def _write(path: PathLike, events: Events, version: str, encode, t_limit: int | None) -> None:
    if not isinstance(events, Events):
        raise TypeError(f"events must be Events, got {type(events).__name__}")
    width, height = events.sensor_size
    if width > _MAX_COORDINATE or height > _MAX_COORDINATE:
        raise ValueError(
            f"EVT formats hold sensors up to {_MAX_COORDINATE}x{_MAX_COORDINATE}, "
            f"got {width}x{height}"
        )
    if len(events) and events.t[0] < 0:
        raise ValueError(f"EVT formats hold times >= 0 µs, got t[0]={int(events.t[0])}")
    if t_limit is not None and len(events) and events.t[-1] >= t_limit:
        raise ValueError(f"times must be below {t_limit} µs for EVT 3.0, got {int(events.t[-1])}")
    header = (
        f"% evt {version}\n% format EVT{version[0]};height={height};width={width}\n"
        f"% geometry {width}x{height}\n% generator evtslowtv\n% end\n"
    ).encode("ascii")

    def fill(output: AtomicOutput) -> None:
        output.write(header)
        previous = None
        for start in range(0, len(events), _ENCODE_BLOCK):
            block = events[start:start + _ENCODE_BLOCK]
            output.write(encode(block.x, block.y, block.t, block.p, previous))
            previous = _Previous(int(block.t[-1]), int(block.y[-1]))

    write_with(path, fill)  # lock, private temporary file, fsync, rename (cmax.io.atomic)


def write_evt3(path: PathLike, events: Events) -> None:
    """Write events as a Prophesee EVT 3.0 RAW file (atomically: a private temporary file, then rename).

    The header declares ``evt 3.0``, ``format EVT3;height=H;width=W`` and
    ``geometry WxH``. Runs of at least three events with equal (t, y, p) and
    increasing x within one 12-pixel block become VECT_12 words, other events
    ADDR_X words; :func:`read_evt3` gives back exactly ``events`` (same order).

    Parameters
    ----------
    path : str or Path
        Output file; its folder must exist.
    events : Events
        Sensor at most 2048x2048; times ``0 <= t < 2**40`` µs (the 24-bit time
        is written with a TIME_HIGH word at least every 8.4 s, so huge absolute
        times would cost many words).
    """
    _write(path, events, "3.0", _encode_evt3, _EVT3_MAX_T)


def write_evt2(path: PathLike, events: Events) -> None:
    """Write events as a Prophesee EVT 2.0 RAW file (atomically), one CD word per event.

    ``events``: sensor at most 2048x2048, times ``t >= 0`` µs. :func:`read_evt2`
    gives back exactly ``events``.
    """
    _write(path, events, "2.0", _encode_evt2, None)
