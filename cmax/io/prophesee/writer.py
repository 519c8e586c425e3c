"""Writing Prophesee RAW files: EVT 3.0 (:func:`write_evt3`) and EVT 2.0 (:func:`write_evt2`).

The encoders are compiled loops (numba, :mod:`cmax._jit`) that run block by
block (``_ENCODE_BLOCK`` events at a time) into a buffer sized by a bound,
carrying the last event's time and row from one block to the next. A file is
written by the protocol of :mod:`cmax.io.atomic` (a lock, a private
``<path>.<hex>.partial`` file never reached through a link, fsync and rename
when complete); a write error (full disk, file-size limit) names the file and
leaves nothing under its name.
"""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from cmax._jit import kernel
from cmax.events import Events
from cmax.io.atomic import AtomicOutput, write_with
from cmax.io.prophesee._header import PathLike

__all__ = ["write_evt3", "write_evt2"]

_MAX_COORDINATE = 2048            # both formats carry 11-bit coordinates
_MAX_T = 1 << 40             # encoder limit (µs), see write_evt3
_ENCODE_BLOCK = 1 << 18           # events encoded at a time


class _Previous(NamedTuple):
    """The last event already encoded (None before the first): time (µs) and row."""

    t: int
    y: int


@kernel
def _encode_evt3_words(x, y, t, p, has_previous, previous_t, previous_y, out):
    """Fill ``out`` (uint16) with the EVT 3.0 words of sorted events; returns the word count.

    Units: a run of >= 3 events with equal (t, y, p) and increasing x in one
    12-pixel block is one vector unit, any other event a unit of its own.
    Before each unit: TIME_HIGH words (one per 2047 of increase; the first
    unit of a file ramps from 0, at least one word), TIME_LOW if the time
    changed or a TIME_HIGH was written, ADDR_Y if the row changed, and
    VECT_BASE_X before a vector unless the previous unit was a vector of the
    block before with the same time, row and polarity.

    A run starts a vector only if the next two events continue it; an event of a run of two is a
    unit of its own, and so is the next one.
    """
    # Each event is tested against the next two in one branch-free expression: almost every event of
    # a real recording is a unit of its own, and following every run to its end (the earlier loop)
    # mispredicted its branches (measured: docs/speed.md).
    n, w = t.size, 0
    high_before = (previous_t >> 12) if has_previous else 0
    known = has_previous                  # whether last_t / last_y hold a unit's values
    last_t, last_y = previous_t, previous_y
    last_vector, last_p, last_block = False, -1, -1
    first = not has_previous              # the file's first unit: at least one TIME_HIGH
    i = 0
    while i < n:
        ut, uy, up, ux = t[i], np.int64(y[i]), np.int64(p[i]), np.int64(x[i])
        ub = ux // 12
        j = i + 1
        if i + 2 < n:
            x1, x2 = np.int64(x[i + 1]), np.int64(x[i + 2])
            starts = ((t[i + 1] == ut) & (t[i + 2] == ut) & (np.int64(y[i + 1]) == uy)
                      & (np.int64(y[i + 2]) == uy) & (np.int64(p[i + 1]) == up) & (np.int64(p[i + 2]) == up)
                      & (x1 // 12 == ub) & (x2 // 12 == ub) & (x1 > ux) & (x2 > x1))
            if starts:
                j = i + 3
                while (j < n and t[j] == ut and y[j] == uy and p[j] == up and x[j] // 12 == ub
                       and x[j] > x[j - 1]):
                    j += 1
        vector = j - i >= 3
        high = ut >> 12
        count = 0
        if first or high != high_before:
            count = (high - high_before + 2046) // 2047
            if first:
                count = max(count, 1)
            for k in range(count):
                value = high if k == count - 1 else high_before + 2047 * (k + 1)
                out[w] = 0x8000 | (value & 0xFFF)
                w += 1
        first = False
        has_low = count > 0 or not known or ut != last_t
        has_y = not known or uy != last_y
        if has_low:
            out[w] = 0x6000 | (ut & 0xFFF)
            w += 1
        if has_y:
            out[w] = uy
            w += 1
        if vector:
            chained = (last_vector and not has_low and not has_y and up == last_p
                       and ub == last_block + 1)
            if not chained:
                out[w] = 0x3000 | (up << 11) | (12 * ub)
                w += 1
            mask = 0
            for k in range(i, j):
                mask |= 1 << (np.int64(x[k]) - 12 * ub)
            out[w] = 0x4000 | mask
        else:
            out[w] = 0x2000 | (up << 11) | ux
        w += 1
        high_before, last_t, last_y, known = high, ut, uy, True
        last_vector, last_p, last_block = vector, up, ub
        i = j
    return w


@kernel
def _encode_evt2_words(x, y, t, p, has_previous, previous_t, out):
    """Fill ``out`` (uint32) with the EVT 2.0 words of sorted events; returns the word count.

    A TIME_HIGH word (one per 2**27 - 1 of increase; the first event of a file
    ramps from 0, at least one word) whenever ``t >> 6`` changes, then one CD word per event.
    """
    max_step = (1 << 27) - 1
    high_before = (previous_t >> 6) if has_previous else 0
    w = 0
    for i in range(t.size):
        high = t[i] >> 6
        count = (high - high_before + max_step - 1) // max_step
        if not has_previous and i == 0:
            count = max(count, 1)
        for k in range(count):
            value = high if k == count - 1 else high_before + max_step * (k + 1)
            out[w] = (0x8 << 28) | (value & 0x0FFFFFFF)
            w += 1
        out[w] = ((np.int64(p[i]) << 28) | ((t[i] & 0x3F) << 22)
                  | (np.int64(x[i]) << 11) | np.int64(y[i]))
        w += 1
        high_before = high
    return w


def _word_bound(t: np.ndarray, previous: _Previous | None, shift: int, max_step: int,
                per_event: int) -> int:
    """More words than the encoders can write for times ``t`` (non-decreasing)."""
    before = 0 if previous is None else previous.t >> shift
    return per_event * t.size + ((int(t[-1]) >> shift) - before) // max_step + 2


def _encode_evt3(x, y, t, p, previous: _Previous | None) -> np.ndarray:
    """EVT 3.0 words ('<u2') for sorted events, following ``previous``.

    Runs of >= 3 events sharing (t, y, p) with increasing x in one 12-pixel
    block become one VECT_12 word (after a VECT_BASE_X unless the previous
    vector ended where this one starts); other events become ADDR_X words.
    """
    if not t.size:
        return np.empty(0, "<u2")
    out = np.empty(_word_bound(t, previous, 12, 2047, 5), "<u2")
    last = previous or _Previous(-1, -1)
    n = _encode_evt3_words(x, y, t, p, previous is not None, last.t, last.y, out)
    return out[:n]


def _encode_evt2(x, y, t, p, previous: _Previous | None) -> np.ndarray:
    """EVT 2.0 words ('<u4'): TIME_HIGH when t >> 6 changes, one CD word per event."""
    if not t.size:
        return np.empty(0, "<u4")
    out = np.empty(_word_bound(t, previous, 6, (1 << 27) - 1, 2), "<u4")
    n = _encode_evt2_words(x, y, t, p, previous is not None,
                           -1 if previous is None else previous.t, out)
    return out[:n]


def _write(path: PathLike, events: Events, version: str, encode, t_limit: int | None, overwrite: bool) -> Path:
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
        raise ValueError(f"times must be below {t_limit} µs (2**40, 12.7 days of a sensor's clock) for EVT {version}, "
                         f"got {int(events.t[-1])}: times since the epoch? write t - t[0]")
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

    return write_with(path, fill, overwrite=overwrite)  # lock, private temporary file, fsync, rename (cmax.io.atomic)


def write_evt3(path: PathLike, events: Events, *, overwrite: bool = False) -> Path:
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
    overwrite : bool, keyword-only
        Replace an existing ``path``; by default an existing file raises
        :class:`FileExistsError` and is left untouched.

    Returns
    -------
    Path
        The file written.
    """
    return _write(path, events, "3.0", _encode_evt3, _MAX_T, overwrite)


def write_evt2(path: PathLike, events: Events, *, overwrite: bool = False) -> Path:
    """Write events as a Prophesee EVT 2.0 RAW file (atomically), one CD word per event.

    ``events``: sensor at most 2048x2048, times ``0 <= t < 2**40`` µs (a sensor's clock: the 28-bit TIME_HIGH
    wraps every 2**34 µs, and each wrap from 0 to ``t`` costs words, about 750 kB for epoch-like times, which
    other readers unwrap as they see fit). :func:`read_evt2` gives back exactly ``events``. An existing ``path``
    raises :class:`FileExistsError` unless ``overwrite=True``; returns the path written.
    """
    return _write(path, events, "2.0", _encode_evt2, _MAX_T, overwrite)
