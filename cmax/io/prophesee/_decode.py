"""Compiled decoders of EVT 3.0 and EVT 2.0 words, into preallocated columns.

Decoding a run of words takes two passes: :func:`_count` checks that no word
type is reserved and returns an upper bound of the events the words hold (for
EVT 3.0 the set bits of the vector masks and one per ADDR_X word, from a table
of all 65536 words; for EVT 2.0 one per word); the caller
allocates the four columns once and :func:`_decode` fills them in one
sequential pass over the words, carrying the state registers (time, y, base
x, polarity, last time) in a small array, so runs of any size (one chunk or a
whole file) give the same events as the whole stream. The loops are numba
kernels (:mod:`cmax._jit`). A word that cannot be decoded raises
:class:`_WordError` with its index in the run; the file reader turns it into
a :class:`~cmax.io.errors.FormatError` with the byte offset. The word layouts
are tabulated in :mod:`cmax.io.prophesee`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from cmax._jit import kernel

_UNKNOWN = -(1 << 40)             # register value before the word that sets it

#: Bit k set: word type k is reserved (EVT 3.0: 0x1, 0x9, 0xB-0xD; EVT 2.0: all but
#: 0x0, 0x1, 0x8, 0xA, 0xE, 0xF).
_EVT3_RESERVED = 0x3A02
_EVT2_RESERVED = 0x3AFC

# State registers, int64 each: raw TIME_HIGH (-1: none yet), wraparounds so far,
# unwrapped time high, time base (µs), y, base x, polarity, time of the last event,
# events of words skipped for want of a time, a row or a base x (before the word that sets it).
_TH_RAW, _LOOPS, _HIGH, _TIME, _Y, _BASE_X, _POL, _LAST_T, _SKIPPED = range(9)

# Error codes of the kernels.
_OK, _X_OUTSIDE, _Y_OUTSIDE, _TIME_BACK = 0, 2, 3, 4


class _WordError(Exception):
    """A word that cannot be decoded, at ``index`` in the run; ``hint``: advice to add after where it is."""

    def __init__(self, index: int, reason: str, hint: str = "") -> None:
        super().__init__(reason)
        self.index, self.reason, self.hint = int(index), reason, hint


@dataclass(frozen=True)
class _Limits:
    """What the decoded events must satisfy: sensor size and (optionally) time order.

    ``inferred_from``: the header line the size is only inferred from (e.g.
    ``plugin_name hal_plugin_gen3_fx3``), named with an event outside it; None
    for a size stated by the header or given by the caller.
    """

    width: int
    height: int
    check_order: bool
    inferred_from: str | None = None


def _new_state() -> np.ndarray:
    """Registers before the first word: (9,) int64 (see ``_TH_RAW`` ... ``_SKIPPED``)."""
    return np.array([-1, 0, _UNKNOWN, _UNKNOWN, -1, _UNKNOWN, 0, -1, 0], np.int64)


def _evt3_word_events() -> np.ndarray:
    """Events each 16-bit EVT 3.0 word holds, (65536,) uint8; 255 for a reserved type."""
    words = np.arange(1 << 16)
    kind = words >> 12
    set_bits = np.cumsum([(words >> bit) & 1 for bit in range(12)], axis=0)  # in bits 0..k
    count = np.zeros(words.size, np.uint8)
    count[kind == 0x2] = 1
    count[kind == 0x4] = set_bits[11][kind == 0x4]
    count[kind == 0x5] = set_bits[7][kind == 0x5]
    count[(_EVT3_RESERVED >> kind) & 1 == 1] = 255
    return count


#: Events per EVT 3.0 word (255: reserved type), and the highest set bit of a 12-bit mask.
_EVT3_WORD_EVENTS = _evt3_word_events()
_HIGHEST_BIT = np.concatenate([[-1], np.floor(np.log2(np.arange(1, 4096)))]).astype(np.int64)


@kernel
def _event_error(column, row, time, last_t, width, height, check_order):
    """(error code, two values) of an event word: its highest x, row and time; ``_OK`` if fine."""
    if column >= width:
        return _X_OUTSIDE, column, np.int64(0)
    if row >= height:
        return _Y_OUTSIDE, row, np.int64(0)
    if check_order and time < last_t:
        return _TIME_BACK, last_t, time
    return _OK, np.int64(0), np.int64(0)


@kernel
def _count_evt3(words):
    """(upper bound of the events, index of the first reserved word or -1) of uint16 ``words``."""
    total = 0
    for i in range(words.size):
        count = _EVT3_WORD_EVENTS[words[i]]
        if count == 255:
            return total, i
        total += count
    return total, -1


@kernel
def _count_evt2(words):
    """(number of words, index of the first reserved word or -1) of uint32 ``words``.

    Every word holds at most one event, so the bound is the word count.
    """
    bad = 0
    for i in range(words.size):     # no early exit: the loop vectorizes
        bad |= (_EVT2_RESERVED >> (words[i] >> 28)) & 1
    if bad:
        for i in range(words.size):
            if (_EVT2_RESERVED >> (words[i] >> 28)) & 1:
                return words.size, i
    return words.size, -1


@kernel
def _decode_evt3_words(words, state, width, height, check_order, x, y, t, p, start):
    """Decode EVT 3.0 ``words`` into the columns from index ``start``; updates ``state``.

    Returns (end index, error code, word index, two error values).
    """
    th_raw, loops, high, time = state[0], state[1], state[2], state[3]
    row, base_x, pol, last_t, skipped = state[4], state[5], state[6], state[7], state[8]
    n, code, at, a, b = start, _OK, -1, np.int64(0), np.int64(0)
    for i in range(words.size):
        w = np.int64(words[i])
        kind = w >> 12
        payload = w & 0xFFF
        if kind == 0x0:
            row = payload & 0x7FF
        elif kind == 0x8:
            if th_raw - payload > 2048:
                loops += 1
            th_raw = payload
            high = (loops << 12) + payload
            time = high * 4096
        elif kind == 0x6:
            time = high * 4096 + payload
        elif kind == 0x3:
            base_x = payload & 0x7FF
            pol = payload >> 11
        elif kind == 0x2:
            if time < 0 or row < 0:
                skipped += 1
                continue
            column = payload & 0x7FF
            code, a, b = _event_error(column, row, time, last_t, width, height, check_order)
            if code != _OK:
                at = i
                break
            last_t = time
            x[n] = column
            y[n] = row
            t[n] = time
            p[n] = payload >> 11
            n += 1
        elif kind == 0x4 or kind == 0x5:
            x0 = base_x
            mask = payload if kind == 0x4 else payload & 0xFF
            base_x += 12 if kind == 0x4 else 8
            if mask == 0:
                continue
            if time < 0 or row < 0 or x0 < 0:
                skipped += _EVT3_WORD_EVENTS[w]
                continue
            top = _HIGHEST_BIT[mask]
            code, a, b = _event_error(x0 + top, row, time, last_t, width, height, check_order)
            if code != _OK:
                at = i
                break
            last_t = time
            for bit in range(top + 1):
                if (mask >> bit) & 1:
                    x[n] = x0 + bit
                    y[n] = row
                    t[n] = time
                    p[n] = pol
                    n += 1
    state[0], state[1], state[2], state[3] = th_raw, loops, high, time
    state[4], state[5], state[6], state[7], state[8] = row, base_x, pol, last_t, skipped
    return n, code, at, a, b


@kernel
def _decode_evt2_words(words, state, width, height, check_order, x, y, t, p, start):
    """Decode EVT 2.0 ``words`` as :func:`_decode_evt3_words` (only TIME_HIGH and CD words matter)."""
    th_raw, loops, high, last_t, skipped = state[0], state[1], state[2], state[7], state[8]
    n, code, at, a, b = start, _OK, -1, np.int64(0), np.int64(0)
    for i in range(words.size):
        w = np.int64(words[i])
        kind = w >> 28
        if kind == 0x8:
            payload = w & 0x0FFFFFFF
            if th_raw - payload > (1 << 27):
                loops += 1
            th_raw = payload
            high = (loops << 28) + payload
        elif kind <= 0x1:
            time = high * 64 + ((w >> 22) & 0x3F)
            if time < 0:
                skipped += 1
                continue
            column, row = (w >> 11) & 0x7FF, w & 0x7FF
            code, a, b = _event_error(column, row, time, last_t, width, height, check_order)
            if code != _OK:
                at = i
                break
            last_t = time
            x[n] = column
            y[n] = row
            t[n] = time
            p[n] = kind
            n += 1
    state[0], state[1], state[2], state[7], state[8] = th_raw, loops, high, last_t, skipped
    return n, code, at, a, b


@dataclass(frozen=True)
class _Codec:
    name: str               # "evt3" / "evt2"
    title: str              # "EVT 3.0"
    dtype: np.dtype
    count: Callable         # words -> (bound, first reserved word or -1)
    decode_words: Callable

    def new_state(self) -> np.ndarray:
        return _new_state()


def _count(codec: _Codec, words: np.ndarray) -> int:
    """Upper bound of the events in ``words``; raises :class:`_WordError` at a reserved word."""
    total, bad = codec.count(words)
    if bad >= 0:
        kind = int(words[bad]) >> (8 * codec.dtype.itemsize - 4)
        raise _WordError(bad, f"reserved {codec.title} word type {kind:#x}")
    return int(total)


def _decode(
    codec: _Codec, words: np.ndarray, state: np.ndarray, limits: _Limits,
    columns: tuple[np.ndarray, ...], start: int,
) -> int:
    """Decode ``words`` into ``columns`` (x, y uint16, t int64, p int8) from index ``start``.

    The columns must have room for :func:`_count`'s bound after ``start``.
    Returns the index after the last event written; updates ``state``; raises
    :class:`_WordError` for an event outside the sensor or going back in time.
    """
    end, code, index, a, b = codec.decode_words(
        words, state, limits.width, limits.height, limits.check_order, *columns, start)
    if code == _X_OUTSIDE or code == _Y_OUTSIDE:
        name = "x" if code == _X_OUTSIDE else "y"
        raise _WordError(index, f"event with {name}={a} outside the "
                         f"{limits.width}x{limits.height} sensor", _inferred_note(limits))
    if code == _TIME_BACK:
        raise _WordError(index, f"time goes back from {a} µs to {b} µs "
                         "(pass sort=True to sort the events by time)")
    return int(end)


def _stream_error(codec: _Codec, state: np.ndarray, n_words: int, decoded: int) -> str | None:
    """Why ``n_words`` words (a whole stream, decoded into ``decoded`` events, leaving ``state``) that decode
    without an error are not event data of ``codec``'s format, or None: no TIME_HIGH word at all (every Prophesee
    stream sets its clock with one; zeros, 0xFF bytes, ASCII text under a RAW header hold none), or more events in
    words skipped for want of a time, row or base x than events decoded (a stray TIME_HIGH in such bytes). Valid
    streams skip only the few event words before their first TIME_HIGH / ADDR_Y."""
    if not n_words:
        return None
    what = (f"not {codec.title} event data (zeros, 0xFF bytes, text, or another format under a RAW header?): check "
            "that the file is a Prophesee recording and that its header states its format")
    if state[_TH_RAW] < 0:
        return (f"its {n_words:,} words of {codec.title} data hold no TIME_HIGH word (type 0x8), which every "
                f"Prophesee stream sets its clock with, so no event has a time: {what}")
    skipped = int(state[_SKIPPED])
    if skipped > decoded:
        needed = ("a time (TIME_HIGH)" if codec.name == "evt2" else
                  "a time, row or base x (TIME_HIGH, ADDR_Y, VECT_BASE_X)")
        return (f"{skipped:,} of the {skipped + decoded:,} events its words hold come before {needed} and only "
                f"{decoded:,} after: {what}")
    return None


def _inferred_note(limits: _Limits) -> str:
    """What to add to "outside the sensor" when the size is only inferred from the header's camera name."""
    if limits.inferred_from is None:
        return ""
    return (f"; the header does not state the sensor size, {limits.width}x{limits.height} is only inferred from "
            f"its '{limits.inferred_from}' line: pass the sensor's width= and height= (cmax: --size WxH)")


def _empty_columns(n: int) -> tuple[np.ndarray, ...]:
    """Uninitialised x, y (uint16), t (int64), p (int8) columns of length ``n``."""
    return np.empty(n, np.uint16), np.empty(n, np.uint16), np.empty(n, np.int64), np.empty(n, np.int8)


_EVT3 = _Codec("evt3", "EVT 3.0", np.dtype("<u2"), _count_evt3, _decode_evt3_words)
_EVT2 = _Codec("evt2", "EVT 2.0", np.dtype("<u4"), _count_evt2, _decode_evt2_words)
