"""Prophesee RAW files: vectorized EVT 3.0 and EVT 2.0 decoders and encoders.

A RAW file is an ASCII header of lines starting with ``%`` (optionally closed
by ``% end``) followed by little-endian words. Layouts, from Prophesee's
public format documentation (docs.prophesee.ai, "EVT 2.0 Format",
"EVT 3.0 Format"); bits are numbered from the least significant:

EVT 3.0, 16-bit words, type in bits 15..12:

==========  ====  ===========================================================
word        type  payload
==========  ====  ===========================================================
ADDR_Y      0x0   y in 10..0 (bit 11, master/slave, is ignored)
ADDR_X      0x2   one event at x = 10..0, polarity = bit 11, current y and time
VECT_BASE_X 0x3   base x = 10..0 and polarity = bit 11 for the vectors after it
VECT_12     0x4   events at base x + i for each set bit i of 11..0; base x += 12
VECT_8      0x5   events at base x + i for each set bit i of 7..0; base x += 8
TIME_LOW    0x6   low 12 bits of the 24-bit time base (µs)
CONTINUED_4 0x7   skipped (extra data of a previous word)
TIME_HIGH   0x8   high 12 bits of the time base; the low part restarts at 0
EXT_TRIGGER 0xA   skipped (external trigger edges are not camera events)
OTHERS      0xE   skipped (monitoring and vendor extensions)
CONTINUED12 0xF   skipped (extra data of a previous word)
==========  ====  ===========================================================

EVT 2.0, 32-bit words, type in bits 31..28: CD_OFF (0x0) and CD_ON (0x1)
carry time low 6 bits in 27..22, x in 21..11, y in 10..0; TIME_HIGH (0x8)
carries the upper 28 bits of the 34-bit time in 27..0; EXT_TRIGGER (0xA),
OTHERS (0xE) and CONTINUED (0xF) are skipped.

Other word types are reserved by the format; meeting one raises
:class:`~cmax.io.errors.FormatError` (this is also how garbage is detected),
as do a byte count that is not a whole number of words, an unterminated header
and events outside the sensor.

Decoding is vectorized: the state registers (time, y, base x, polarity) are
forward-filled by cumulative counts of the words that set them, vector masks
are expanded with ``np.unpackbits``, and the decoder state is carried from one
chunk to the next, so :func:`iter_evt3` / :func:`iter_evt2` decode files of any
size in bounded memory and give exactly what :func:`read_evt3` /
:func:`read_evt2` give. Words before the first TIME_HIGH (and events before the
first ADDR_Y / VECT_BASE_X that define them) have no defined time or address
and are skipped.

Time: the 24-bit (EVT 3.0) and 34-bit (EVT 2.0) time wraps around (every
16.8 s and 4.8 h); a TIME_HIGH value that falls by more than half its range is
read as a wraparound, so times come out as monotonic int64 microseconds. Both
formats carry time as a running base that the sensor only moves forward, so a
stream whose time goes back is corrupt: the readers raise on it by default;
``sort=True`` instead sorts stably (see :func:`read_evt3`). A TIME_LOW that is
lower than the one before, with no TIME_HIGH change, only moves the time base
(cameras emit such words a few µs early right after a TIME_HIGH, with no events
attached); it is not a wraparound. Some third-party decoders add 4096 µs at
each such fall, which also counts every genuine rollover twice; this decoder
does not (see ``tests/test_io_prophesee.py``).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, NamedTuple, Union

import numpy as np

from cmax.events import Events, _check_sensor_size
from cmax.io.errors import FormatError

__all__ = [
    "read_raw", "read_evt3", "read_evt2", "iter_evt3", "iter_evt2", "write_evt3", "write_evt2",
]

PathLike = Union[str, "os.PathLike[str]"]

#: Default bytes of raw words decoded at a time; the working memory is about 50
#: times this (small chunks also stay in cache: 256 KiB decodes faster than 16 MiB).
CHUNK_BYTES = 1 << 18

_MAX_HEADER_BYTES = 1 << 20
_MAX_COORDINATE = 2048            # both formats carry 11-bit coordinates
_UNKNOWN = -(1 << 40)             # register value before the word that sets it
_EVT3_MAX_T = 1 << 40             # encoder limit (µs), see write_evt3
_ENCODE_BLOCK = 1 << 18           # events encoded at a time

#: Sensor sizes of HAL plugins, matched as substrings of ``plugin_name``, in order.
_PLUGIN_SIZES = (
    ("genx320", (320, 320)),
    ("gen41", (1280, 720)),
    ("imx636", (1280, 720)),
    ("gen4", (1280, 720)),
    ("gen31", (640, 480)),
    ("gen3", (640, 480)),
)

#: Bit k set: word type k is reserved (EVT 3.0: 0x1, 0x9, 0xB-0xD; EVT 2.0: all but
#: 0x0, 0x1, 0x8, 0xA, 0xE, 0xF).
_EVT3_RESERVED = 0x3A02
_EVT2_RESERVED = 0x3AFC


# -- header ---------------------------------------------------------------------------
@dataclass(frozen=True)
class _Header:
    """The ``%`` lines of a RAW file as ``key -> value`` and where the words start."""

    fields: dict[str, str]
    data_offset: int

    def event_format(self) -> str | None:
        """``"evt3"``, ``"evt2"``, another lower-case name, or None if undeclared."""
        fmt = self.fields.get("format")
        if fmt:
            name = fmt.split(";")[0].strip().lower()
            return {"evt3": "evt3", "evt2": "evt2"}.get(name, name)
        evt = self.fields.get("evt")
        if evt:
            version = evt.strip()
            return {"3.0": "evt3", "3": "evt3", "2.0": "evt2", "2": "evt2"}.get(
                version, f"evt {version}"
            )
        return None

    def sensor_size(self) -> tuple[int, int] | None:
        """(width, height) from the ``format``, ``geometry`` or ``plugin_name`` lines."""
        options = dict(
            part.split("=", 1) for part in self.fields.get("format", "").split(";") if "=" in part
        )
        options = {key.strip().lower(): value.strip() for key, value in options.items()}
        if "width" in options and "height" in options:
            return int(options["width"]), int(options["height"])
        geometry = self.fields.get("geometry", "").lower().split("x")
        if len(geometry) == 2:
            return int(geometry[0]), int(geometry[1])
        plugin = self.fields.get("plugin_name", "").lower()
        for pattern, size in _PLUGIN_SIZES:
            if pattern in plugin:
                return size
        generation = self.fields.get("sensor_generation", "").split(".")[0].strip()
        return {"3": (640, 480), "4": (1280, 720)}.get(generation)


def _read_header(path: Path) -> _Header:
    with open(path, "rb") as f:
        head = f.read(_MAX_HEADER_BYTES + 1)
    fields: dict[str, str] = {}
    pos = 0
    while pos < len(head) and head[pos:pos + 1] == b"%":
        end = head.find(b"\n", pos)
        if end < 0:
            raise FormatError(
                f"{path}: header line at byte {pos} has no end of line "
                "(truncated file, or not a Prophesee RAW file)"
            )
        line = head[pos + 1:end].decode("utf-8", "replace").strip()
        pos = end + 1
        if line.lower() == "end":
            break
        key, _, value = line.partition(" ")
        if key:
            fields[key.lower()] = value.strip()
        if pos > _MAX_HEADER_BYTES:
            raise FormatError(f"{path}: header longer than {_MAX_HEADER_BYTES} bytes")
    return _Header(fields, pos)


def _sensor_size(
    header: _Header, width: int | None, height: int | None, path: Path
) -> tuple[int, int]:
    if (width is None) != (height is None):
        raise ValueError("give both width and height, or neither")
    if width is not None:
        return _check_sensor_size(width, height)
    try:
        size = header.sensor_size()
    except ValueError:
        raise FormatError(f"{path}: unreadable sensor size in the header {header.fields}") from None
    if size is None:
        raise FormatError(
            f"{path}: the header gives no sensor size (no 'format ...;width=;height=', "
            "'geometry WxH' or known plugin_name line); pass width= and height="
        )
    try:
        return _check_sensor_size(*size)
    except (TypeError, ValueError) as error:
        raise FormatError(f"{path}: bad sensor size in the header: {error}") from None


# -- decoder core -----------------------------------------------------------------------
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


def _check_chunk_bytes(chunk_bytes: int) -> int:
    if isinstance(chunk_bytes, bool) or not isinstance(chunk_bytes, (int, np.integer)):
        raise TypeError(f"chunk_bytes must be an integer, got {chunk_bytes!r}")
    if chunk_bytes <= 0:
        raise ValueError(f"chunk_bytes must be positive, got {chunk_bytes}")
    return int(chunk_bytes)


def _decode_file(
    path: PathLike, codec: _Codec, width: int | None, height: int | None,
    chunk_bytes: int, check_order: bool,
) -> tuple[tuple[int, int], Iterator[tuple[np.ndarray, ...]]]:
    """Sensor size and an iterator of (x, y, t, p) columns of each chunk with events.

    Header, sensor size and file length are checked here, before anything is
    decoded; the words are checked as they are decoded.
    """
    path = Path(path)
    chunk_bytes = _check_chunk_bytes(chunk_bytes)
    header = _read_header(path)
    declared = header.event_format()
    if declared is not None and declared != codec.name:
        raise FormatError(f"{path}: the header declares {declared!r}, not {codec.title}")
    size = _sensor_size(header, width, height, path)
    word = codec.dtype.itemsize
    n_bytes = path.stat().st_size - header.data_offset
    if n_bytes % word:
        raise FormatError(
            f"{path}: {n_bytes} bytes of {codec.title} data is not a whole number of "
            f"{word}-byte words (truncated file?)"
        )
    step = max(word, chunk_bytes - chunk_bytes % word)
    limits = _Limits(size[0], size[1], check_order)
    return size, _chunks(path, codec, limits, header.data_offset, step)


def _chunks(
    path: Path, codec: _Codec, limits: _Limits, data_offset: int, step: int
) -> Iterator[tuple[np.ndarray, ...]]:
    state = codec.new_state()
    offset = data_offset
    with open(path, "rb") as f:
        f.seek(data_offset)
        while data := f.read(step):
            if len(data) % codec.dtype.itemsize:
                raise FormatError(f"{path}: the file changed while it was read")
            try:
                columns = codec.decode(np.frombuffer(data, codec.dtype), state, limits)
            except _WordError as error:
                at = offset + codec.dtype.itemsize * error.index
                raise FormatError(
                    f"{path}: {error.reason}, at byte offset {at} ({codec.title} word)"
                ) from None
            offset += len(data)
            if columns[0].size:
                yield columns


def _iter(path, codec, width, height, chunk_bytes, sort) -> Iterator[Events]:
    (w, h), chunks = _decode_file(path, codec, width, height, chunk_bytes, not sort)
    return _iter_events(path, chunks, w, h, sort)


def _iter_events(path, chunks, width, height, sort) -> Iterator[Events]:
    last_t = None
    for x, y, t, p in chunks:
        if sort:
            if t.size > 1 and np.any(t[1:] < t[:-1]):
                order = np.argsort(t, kind="stable")
                x, y, t, p = x[order], y[order], t[order], p[order]
            if last_t is not None and t[0] < last_t:
                raise FormatError(
                    f"{path}: events of one chunk (from {int(t[0])} µs) are older than the "
                    f"previous chunk's last ({last_t} µs); the disorder spans chunks: use a "
                    "larger chunk_bytes or read the whole file"
                )
            last_t = int(t[-1])
        yield Events._trusted(x, y, t, p, width, height)


def _read(path, codec, width, height, chunk_bytes, sort) -> Events:
    (w, h), chunks = _decode_file(path, codec, width, height, chunk_bytes, not sort)
    parts = list(chunks)
    if not parts:
        return Events.empty(w, h)
    columns = [part[0] if len(parts) == 1 else np.concatenate(part) for part in zip(*parts)]
    if sort:
        t = columns[2]
        if t.size > 1 and np.any(t[1:] < t[:-1]):
            order = np.argsort(t, kind="stable")
            columns = [column[order] for column in columns]
    return Events._trusted(*columns, w, h)


# -- public readers -------------------------------------------------------------------
def read_evt3(
    path: PathLike, *, width: int | None = None, height: int | None = None,
    sort: bool = False, chunk_bytes: int = CHUNK_BYTES,
) -> Events:
    """Read a Prophesee EVT 3.0 RAW file.

    Parameters
    ----------
    path : str or Path
        The ``.raw`` file: ``%`` header lines, then little-endian 16-bit words.
    width, height : int, optional, keyword-only
        Sensor size in pixels; by default from the header (``format
        EVT3;width=;height=``, ``geometry WxH`` or a known ``plugin_name``).
        Given, they take precedence over the header.
    sort : bool, keyword-only
        If the stream's time goes back (which the format does not produce;
        a sign of corruption), sort the events stably by time instead of
        raising :class:`FormatError`.
    chunk_bytes : int, keyword-only
        Bytes decoded at a time (bounds the working memory, not the result).

    Returns
    -------
    Events
        N events: x, y uint16 (pixels), t int64 (µs, the sensor's absolute time,
        wraparounds unrolled), p int8 {0, 1}, in stream order.

    Raises
    ------
    FormatError
        Truncated or corrupt data, reserved word types, events outside the
        sensor, an unknown sensor size, or a header declaring another format.

    Examples
    --------
    >>> events = read_evt3("recording.raw")          # doctest: +SKIP
    >>> events.sensor_size                           # doctest: +SKIP
    (1280, 720)
    """
    return _read(path, _EVT3, width, height, chunk_bytes, sort)


def read_evt2(
    path: PathLike, *, width: int | None = None, height: int | None = None,
    sort: bool = False, chunk_bytes: int = CHUNK_BYTES,
) -> Events:
    """Read a Prophesee EVT 2.0 RAW file (32-bit words); as :func:`read_evt3`.

    Times are 34-bit (TIME_HIGH 28 bits of 64 µs plus 6 bits per event),
    unrolled across wraparounds into int64 µs.
    """
    return _read(path, _EVT2, width, height, chunk_bytes, sort)


def iter_evt3(
    path: PathLike, *, width: int | None = None, height: int | None = None,
    sort: bool = False, chunk_bytes: int = CHUNK_BYTES,
) -> Iterator[Events]:
    """Yield the events of an EVT 3.0 file chunk by chunk, in bounded memory.

    Each chunk decodes ``chunk_bytes`` of words (rounded down to whole words)
    with the decoder state carried over, so the concatenated chunks equal
    :func:`read_evt3`; chunks without events are not yielded. Header, sensor
    size and file length are checked when called; corrupt words raise
    :class:`FormatError` when reached. With ``sort=True`` each chunk is sorted
    stably, and disorder spanning two chunks raises :class:`FormatError`.
    """
    return _iter(path, _EVT3, width, height, chunk_bytes, sort)


def iter_evt2(
    path: PathLike, *, width: int | None = None, height: int | None = None,
    sort: bool = False, chunk_bytes: int = CHUNK_BYTES,
) -> Iterator[Events]:
    """Yield the events of an EVT 2.0 file chunk by chunk; as :func:`iter_evt3`."""
    return _iter(path, _EVT2, width, height, chunk_bytes, sort)


def read_raw(
    path: PathLike, *, width: int | None = None, height: int | None = None,
    sort: bool = False, chunk_bytes: int = CHUNK_BYTES,
) -> Events:
    """Read a Prophesee RAW file in the format its header declares.

    Dispatches on ``% evt 3.0`` / ``% format EVT3...`` to :func:`read_evt3` and
    on ``% evt 2.0`` / ``% format EVT2...`` to :func:`read_evt2`; other options
    as there. Raises :class:`FormatError` when the header declares no format
    or one that is not supported (e.g. EVT 2.1).
    """
    header = _read_header(Path(path))
    declared = header.event_format()
    codecs = {"evt3": _EVT3, "evt2": _EVT2}
    if declared not in codecs:
        raise FormatError(
            f"{path}: " + (
                "the header declares no event format ('% evt 3.0' or '% format EVT3' line); "
                "call read_evt3 or read_evt2 directly" if declared is None
                else f"unsupported event format {declared!r} (EVT 3.0 and EVT 2.0 are read)"
            )
        )
    return _read(path, codecs[declared], width, height, chunk_bytes, sort)


# -- encoders -------------------------------------------------------------------------
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
    path = Path(path)
    partial = path.with_name(path.name + ".partial")
    try:
        with open(partial, "wb") as f:
            f.write(header)
            previous = None
            for start in range(0, len(events), _ENCODE_BLOCK):
                block = events[start:start + _ENCODE_BLOCK]
                f.write(encode(block.x, block.y, block.t, block.p, previous).data)
                previous = _Previous(int(block.t[-1]), int(block.y[-1]))
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise


def write_evt3(path: PathLike, events: Events) -> None:
    """Write events as a Prophesee EVT 3.0 RAW file (atomically: ``<path>.partial``, then rename).

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
