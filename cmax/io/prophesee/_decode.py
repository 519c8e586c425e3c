"""Vectorized decoders of EVT 3.0 and EVT 2.0 words, chunk by chunk.

Each decoder turns one chunk of words into event columns (x, y, t, p) and
carries its state registers (time, y, base x, polarity) to the next chunk in
a state object, so chunks of any size give the same events as the whole
stream. The registers are forward-filled by cumulative counts of the words
that set them and vector masks are expanded with ``np.unpackbits``: no Python
loop over words. A word that cannot be decoded raises :class:`_WordError`
with its index in the chunk; the file reader turns it into a
:class:`~cmax.io.errors.FormatError` with the byte offset. The word layouts
are tabulated in :mod:`cmax.io.prophesee`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

_UNKNOWN = -(1 << 40)             # register value before the word that sets it

#: Bit k set: word type k is reserved (EVT 3.0: 0x1, 0x9, 0xB-0xD; EVT 2.0: all but
#: 0x0, 0x1, 0x8, 0xA, 0xE, 0xF).
_EVT3_RESERVED = 0x3A02
_EVT2_RESERVED = 0x3AFC


class _WordError(Exception):
    """A word that cannot be decoded, at ``index`` in the chunk."""

    def __init__(self, index: int, reason: str) -> None:
        super().__init__(reason)
        self.index, self.reason = int(index), reason


@dataclass(frozen=True)
class _Limits:
    """What the decoded events must satisfy: sensor size and (optionally) time order."""

    width: int
    height: int
    check_order: bool


@dataclass
class _Evt3State:
    th_raw: int = -1        # last raw 12-bit TIME_HIGH (-1: none yet)
    loops: int = 0          # 24-bit wraparounds so far
    high: int = _UNKNOWN    # loops * 4096 + th_raw
    time: int = _UNKNOWN    # current time base, µs
    y: int = -1
    base_x: int = _UNKNOWN  # current vector base x (after the vectors seen)
    pol: int = 0
    last_t: int = -1        # time of the last event decoded, µs


@dataclass
class _Evt2State:
    th_raw: int = -1
    loops: int = 0
    high: int = _UNKNOWN    # loops * 2**28 + th_raw, in units of 64 µs
    last_t: int = -1


#: Highest set bit of a 12-bit vector mask (-1 for an empty mask).
_HIGHEST_BIT = np.concatenate([[-1], np.floor(np.log2(np.arange(1, 4096))).astype(np.int16)])


def _unwrap_time_high(
    th_raw: np.ndarray, state: "_Evt3State | _Evt2State", bits: int
) -> np.ndarray:
    """Absolute time-high values of raw ``bits``-bit TIME_HIGH words; updates ``state``.

    A value that falls by more than half the range from the previous one is a
    wraparound (one more loop); smaller falls are kept (and caught as time
    going back).
    """
    prev = np.empty_like(th_raw)
    prev[0] = state.th_raw
    prev[1:] = th_raw[:-1]
    loops = state.loops + np.cumsum((prev - th_raw) > (1 << (bits - 1)))
    state.th_raw, state.loops = int(th_raw[-1]), int(loops[-1])
    return (loops << bits) + th_raw


def _check_reserved(types: np.ndarray, reserved: int, name: str) -> None:
    bad = (types.dtype.type(reserved) >> types) & 1
    if bad.any():
        i = int(np.argmax(bad))
        raise _WordError(i, f"reserved {name} word type {int(types[i]):#x}")


def _check_events(
    pos: np.ndarray, x_max: np.ndarray, y: np.ndarray, t: np.ndarray,
    state: "_Evt3State | _Evt2State", limits: _Limits,
) -> None:
    """Raise for event words (at ``pos``) outside the sensor or going back in time."""
    if not pos.size:
        return
    for name, column, limit in (("x", x_max, limits.width), ("y", y, limits.height)):
        if column.max() >= limit:
            i = int(np.argmax(column >= limit))
            raise _WordError(
                pos[i], f"event with {name}={int(column[i])} outside the "
                f"{limits.width}x{limits.height} sensor"
            )
    if limits.check_order:
        if t[0] < state.last_t:
            back, before = 0, state.last_t
        else:
            falls = np.flatnonzero(t[1:] < t[:-1])
            back = int(falls[0]) + 1 if falls.size else None
            before = None if back is None else int(t[back - 1])
        if back is not None:
            raise _WordError(
                pos[back], f"time goes back from {before} µs to {int(t[back])} µs "
                "(pass sort=True to sort the events by time)"
            )
    state.last_t = int(t[-1])


def _decode_evt3(words: np.ndarray, state: _Evt3State, limits: _Limits) -> tuple[np.ndarray, ...]:
    """Decode EVT 3.0 ``words`` (uint16, (n,)) from ``state``, which is updated in place.

    Returns x, y (uint16), t (int64 µs), p (int8), each (N,), in stream order.
    """
    types = words >> 12
    _check_reserved(types, _EVT3_RESERVED, "EVT 3.0")
    payload = (words & 0xFFF).astype(np.int32)

    # Time base: TIME_HIGH sets high (low restarts at 0), TIME_LOW sets low.
    is_time = (types == 0x8) | (types == 0x6)
    time_pos = np.flatnonzero(is_time)
    is_high = types[time_pos] == 0x8
    time_payload = payload[time_pos].astype(np.int64)
    high = np.empty(int(is_high.sum()) + 1, np.int64)
    high[0] = state.high
    if high.size > 1:
        high[1:] = _unwrap_time_high(time_payload[is_high], state, 12)
    time = np.empty(time_pos.size + 1, np.int64)
    time[0] = state.time
    time[1:] = high[np.cumsum(is_high)] * 4096 + np.where(is_high, 0, time_payload)
    state.high, state.time = int(high[-1]), int(time[-1])

    is_y = types == 0x0
    y_values = np.empty(int(is_y.sum()) + 1, np.int32)
    y_values[0] = state.y
    y_values[1:] = payload[is_y] & 0x7FF
    state.y = int(y_values[-1])

    # Address words in order: VECT_BASE_X sets base x and polarity, VECT_12 /
    # VECT_8 have events at base x + set bits and then add 12 / 8 to base x,
    # ADDR_X has one event at its own x and polarity.
    addr_pos = np.flatnonzero((types >= 0x2) & (types <= 0x5))
    addr_types = types[addr_pos]
    addr_payload = payload[addr_pos]
    is_base = addr_types == 0x3
    step = np.where(addr_types == 0x4, 12, np.where(addr_types == 0x5, 8, 0))
    before = np.cumsum(step) - step
    base_payload = addr_payload[is_base]
    offset = np.empty(base_payload.size + 1, np.int64)
    offset[0] = state.base_x
    offset[1:] = (base_payload & 0x7FF) - before[is_base]
    polarity = np.empty(base_payload.size + 1, np.int8)
    polarity[0] = state.pol
    polarity[1:] = base_payload >> 11
    base_count = np.cumsum(is_base)
    if addr_pos.size:
        state.base_x = int(offset[-1] + before[-1] + step[-1])
        state.pol = int(polarity[-1])

    is_event = ~is_base
    ev_pos = addr_pos[is_event]
    ev_types = addr_types[is_event]
    ev_payload = addr_payload[is_event]
    base_count = base_count[is_event]
    single = ev_types == 0x2
    x0 = np.where(single, ev_payload & 0x7FF, offset[base_count] + before[is_event])
    p = np.where(single, ev_payload >> 11, polarity[base_count]).astype(np.int8)
    mask = np.where(single, 1, np.where(ev_types == 0x4, ev_payload, ev_payload & 0xFF))
    t = time[np.cumsum(is_time, dtype=np.intp)[ev_pos]]
    y = y_values[np.cumsum(is_y, dtype=np.intp)[ev_pos]]

    known = (t >= 0) & (y >= 0) & (x0 >= 0) & (mask > 0)
    if not known.all():
        ev_pos, x0, y, t, p, mask = (a[known] for a in (ev_pos, x0, y, t, p, mask))
    _check_events(ev_pos, x0 + _HIGHEST_BIT[mask], y, t, state, limits)

    mask_bytes = mask.astype("<u2").view(np.uint8).reshape(-1, 2)
    bits = np.unpackbits(mask_bytes, axis=1, bitorder="little")
    flat = np.flatnonzero(bits.view(bool))
    row = flat >> 4
    x = x0.astype(np.uint16)[row]
    x += (flat & 15).astype(np.uint16)
    return x, y.astype(np.uint16)[row], t[row], p[row]


def _decode_evt2(words: np.ndarray, state: _Evt2State, limits: _Limits) -> tuple[np.ndarray, ...]:
    """Decode EVT 2.0 ``words`` (uint32, (n,)) from ``state``; as :func:`_decode_evt3`."""
    types = words >> 28
    _check_reserved(types, _EVT2_RESERVED, "EVT 2.0")
    is_high = types == 0x8
    high = np.empty(int(is_high.sum()) + 1, np.int64)
    high[0] = state.high
    if high.size > 1:
        high[1:] = _unwrap_time_high((words[is_high] & 0x0FFFFFFF).astype(np.int64), state, 28)
    state.high = int(high[-1])

    cd_pos = np.flatnonzero(types <= 0x1)
    cd = words[cd_pos]
    t = high[np.cumsum(is_high, dtype=np.intp)[cd_pos]] * 64 + ((cd >> 22) & 0x3F)
    known = t >= 0
    if not known.all():
        cd_pos, cd, t = cd_pos[known], cd[known], t[known]
    x, y = (cd >> 11) & 0x7FF, cd & 0x7FF
    _check_events(cd_pos, x, y, t, state, limits)
    return x.astype(np.uint16), y.astype(np.uint16), t, (cd >> 28).astype(np.int8)


@dataclass(frozen=True)
class _Codec:
    name: str               # "evt3" / "evt2"
    title: str              # "EVT 3.0"
    dtype: np.dtype
    decode: Callable
    new_state: Callable


_EVT3 = _Codec("evt3", "EVT 3.0", np.dtype("<u2"), _decode_evt3, _Evt3State)
_EVT2 = _Codec("evt2", "EVT 2.0", np.dtype("<u4"), _decode_evt2, _Evt2State)
