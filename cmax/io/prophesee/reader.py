"""Reading Prophesee RAW files: whole (:func:`read_evt3`, :func:`read_evt2`,
:func:`read_raw`, which dispatches on the header), chunk by chunk in bounded
memory (:func:`iter_evt3`, :func:`iter_evt2`, :func:`iter_raw`), a time span of
them in memory bounded by that span (``read_raw(..., t0_us=, t1_us=)``), or window
after window in time order (:class:`RawWindows`).

The header and sensor size are checked before any word is decoded. The
readers of a whole file read all its words at once, bound the event count
(:func:`~cmax.io.prophesee._decode._count`), allocate the four columns once and
decode into them (:mod:`cmax.io.prophesee._decode`); the iterators do the same
chunk by chunk. Errors report the byte offset of the bad word.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from cmax.events import Events, check_event_count, concatenate
from cmax.hot_pixels import pixel_counts
from cmax.io.errors import FormatError
from cmax.io.prophesee._decode import (
    _EVT2, _EVT3, _Codec, _count, _decode, _empty_columns, _Limits, _stream_error, _WordError,
)
from cmax.io.prophesee._header import PathLike, _read_header, _sensor_size

__all__ = ["CHUNK_BYTES", "read_raw", "read_evt3", "read_evt2", "iter_raw", "iter_evt3", "iter_evt2", "RawScan",
           "scan_raw", "RawWindows"]

#: Default bytes of raw words decoded at a time by the iterators.
CHUNK_BYTES = 1 << 18


def _check_chunk_bytes(chunk_bytes: int) -> int:
    if isinstance(chunk_bytes, bool) or not isinstance(chunk_bytes, (int, np.integer)):
        raise TypeError(f"chunk_bytes must be an integer, got {chunk_bytes!r}")
    if chunk_bytes <= 0:
        raise ValueError(f"chunk_bytes must be positive, got {chunk_bytes}")
    return int(chunk_bytes)


def _open_data(
    path: PathLike, codec: _Codec, width: int | None, height: int | None,
    chunk_bytes: int, check_order: bool,
) -> tuple[Path, _Limits, int, int]:
    """Check header, sensor size and file length before anything is decoded.

    Returns the path, the limits, the data offset and the number of words.
    """
    path = Path(path)
    _check_chunk_bytes(chunk_bytes)
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
    return path, _Limits(size.width, size.height, check_order, size.inferred_from), header.data_offset, n_bytes // word


def sorted_copy_line(path: PathLike) -> str:
    """The way through for a RAW file at ``path`` whose time goes back: the ``cmax`` commands read RAW files a time
    span at a time (``--sort`` does not apply), so the events of one that fits in memory are sorted once into a copy.
    """
    return ("a RAW file that fits in memory can be sorted once into a copy: python -c \"import cmax.io as io; "
            f"io.write_evt3('sorted.raw', io.read_raw({str(path)!r}, sort=True))\"")


def _decode_words(
    path: Path, codec: _Codec, words: np.ndarray, state: np.ndarray, limits: _Limits,
    offset: int,
) -> tuple[np.ndarray, ...]:
    """The (x, y, t, p) columns of ``words`` (which start at byte ``offset`` of the file)."""
    try:
        bound = _count(codec, words)
        check_event_count(bound, f"{path} (read whole; iter_{codec.name} streams it)")
        columns = _empty_columns(bound)
        end = _decode(codec, words, state, limits, columns, 0)
    except _WordError as error:
        at = offset + codec.dtype.itemsize * error.index
        if error.reason.startswith("time goes back"):     # cmax's --sort refuses RAW: the way through, here
            hint = f"{error.hint}; cmax's --sort does not apply to RAW files (read a time span at a time): " \
                   f"{sorted_copy_line(path)}"
        else:
            hint = error.hint
        raise FormatError(
            f"{path}: {error.reason}, at byte offset {at} ({codec.title} word){hint}"
        ) from None
    return columns if end == bound else tuple(column[:end] for column in columns)


def _chunks(
    path: Path, codec: _Codec, limits: _Limits, data_offset: int, chunk_bytes: int
) -> Iterator[tuple[np.ndarray, ...]]:
    word = codec.dtype.itemsize
    step = max(word, chunk_bytes - chunk_bytes % word)
    state = codec.new_state()
    offset, decoded = data_offset, 0
    with open(path, "rb") as f:
        f.seek(data_offset)
        while data := f.read(step):
            if len(data) % word:
                raise FormatError(f"{path}: the file changed while it was read")
            columns = _decode_words(path, codec, np.frombuffer(data, codec.dtype), state,
                                    limits, offset)
            offset += len(data)
            decoded += columns[0].size
            if columns[0].size:
                yield columns
    _check_stream(path, codec, state, (offset - data_offset) // word, decoded)


def _check_stream(path: Path, codec: _Codec, state: np.ndarray, n_words: int, decoded: int) -> None:
    """Refuse the ``n_words`` words of ``path``'s data, decoded into ``decoded`` events leaving ``state``, where
    they are not ``codec``'s event data although every word decoded (:func:`_stream_error`)."""
    reason = _stream_error(codec, state, n_words, decoded)
    if reason is not None:
        raise FormatError(f"{path}: {reason}")


def _iter(path, codec, width, height, chunk_bytes, sort) -> Iterator[Events]:
    path, limits, data_offset, _ = _open_data(path, codec, width, height, chunk_bytes, not sort)
    chunks = _chunks(path, codec, limits, data_offset, int(chunk_bytes))
    return _iter_events(path, chunks, limits.width, limits.height, sort)


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
    path, limits, data_offset, n_words = _open_data(
        path, codec, width, height, chunk_bytes, not sort)
    words = np.fromfile(path, codec.dtype, count=n_words, offset=data_offset)
    if words.size != n_words:
        raise FormatError(f"{path}: the file changed while it was read")
    state = codec.new_state()
    columns = _decode_words(path, codec, words, state, limits, data_offset)
    _check_stream(path, codec, state, n_words, columns[0].size)
    if sort:
        t = columns[2]
        if t.size > 1 and np.any(t[1:] < t[:-1]):
            order = np.argsort(t, kind="stable")
            columns = [column[order] for column in columns]
    return Events._trusted(*columns, limits.width, limits.height)


def _read_span(path, codec, width, height, chunk_bytes, sort, t0_us: int | None, t1_us: int | None) -> Events:
    """The events with ``t0_us <= t < t1_us`` (None: no bound) decoded chunk by chunk: memory holds the span and
    one chunk, and decoding stops at the first chunk that reaches ``t1_us`` (a valid stream's time does not go
    back; with ``sort`` each chunk is sorted and disorder across chunks raises, as :func:`iter_evt3`)."""
    _, limits, _, _ = _open_data(path, codec, width, height, chunk_bytes, not sort)
    lo, hi = -(2**62) if t0_us is None else int(t0_us), 2**62 if t1_us is None else int(t1_us)
    kept, count = [], 0
    for chunk in _iter(path, codec, width, height, chunk_bytes, sort):
        part = chunk.slice_time(lo, hi)
        if len(part):
            count = check_event_count(count + len(part), f"{path}: the span [{lo}, {hi}) µs")
            kept.append(part)
        if int(chunk.t[-1]) >= hi:
            break
    if not kept:
        return Events._trusted(*_empty_columns(0), limits.width, limits.height)
    return concatenate(kept)


def _codec_of(path: PathLike):
    """The codec of the event format a RAW file's header declares (FormatError for none or another)."""
    declared = _read_header(Path(path)).event_format()
    codecs = {"evt3": _EVT3, "evt2": _EVT2}
    if declared not in codecs:
        raise FormatError(
            f"{path}: " + (
                "the header declares no event format ('% evt 3.0' or '% format EVT3' line); "
                "call read_evt3 or read_evt2 directly" if declared is None
                else f"unsupported event format {declared!r} (EVT 3.0 and EVT 2.0 are read)"
            )
        )
    return codecs[declared]


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
        EVT3;width=;height=``, ``geometry WxH``, else implied by a known
        ``plugin_name`` or ``sensor_generation``). Given, they must equal a
        size the header states (else :class:`ValueError`); they replace one
        only implied by the camera's name (a guess: expelliarmus and tonic
        name ``hal_plugin_gen3_fx3`` for every file they save).
    sort : bool, keyword-only
        If the stream's time goes back (which the format does not produce;
        a sign of corruption), sort the events stably by time instead of
        raising :class:`FormatError`.
    chunk_bytes : int, keyword-only
        Checked only, for the iterators' sake: the whole file's words are
        read at once (at most a third of the result's size).

    Returns
    -------
    Events
        N events: x, y uint16 (pixels), t int64 (µs, the sensor's absolute time,
        wraparounds unrolled), p int8 {0, 1}, in stream order.

    Raises
    ------
    FormatError
        Truncated or corrupt data, reserved word types, events outside the
        sensor, an unknown sensor size, or a header declaring another format;
        words that decode but are no Prophesee stream (no TIME_HIGH word, or
        more events before the first time and row than after: zeros, text).

    Examples
    --------
    >>> import tempfile
    >>> from cmax.io.prophesee.writer import write_evt3
    >>> path = Path(tempfile.mkdtemp()) / "recording.raw"
    >>> path = write_evt3(path, Events([3, 4, 5], [7, 7, 7], [100, 100, 250], [1, 1, 0], 1280, 720))
    >>> events = read_evt3(path)
    >>> events.sensor_size, events.x.tolist(), events.t.tolist(), events.p.tolist()
    ((1280, 720), [3, 4, 5], [100, 100, 250], [1, 1, 0])
    """
    return _read(path, _EVT3, width, height, chunk_bytes, sort)


def read_evt2(
    path: PathLike, *, width: int | None = None, height: int | None = None,
    sort: bool = False, chunk_bytes: int = CHUNK_BYTES,
) -> Events:
    """Read a Prophesee EVT 2.0 RAW file (32-bit words); ``path``, ``width``, ``height``, ``sort`` and
    ``chunk_bytes`` as for :func:`read_evt3`.

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
    :class:`FormatError` when reached, words that are no Prophesee stream at
    all (no TIME_HIGH word: zeros, text) after the last chunk. With ``sort=True`` each chunk is sorted
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
    sort: bool = False, chunk_bytes: int = CHUNK_BYTES, t0_us: int | None = None, t1_us: int | None = None,
) -> Events:
    """Read a Prophesee RAW file in the format its header declares.

    Dispatches on ``% evt 3.0`` / ``% format EVT3...`` to :func:`read_evt3` and
    on ``% evt 2.0`` / ``% format EVT2...`` to :func:`read_evt2`; ``path``, ``width``, ``height``, ``sort`` and
    ``chunk_bytes`` as there. Raises :class:`FormatError` when the header declares no format
    or one that is not supported (e.g. EVT 2.1).

    ``t0_us``, ``t1_us`` (absolute µs, None: no bound): only the events with ``t0_us <= t < t1_us``, decoded
    chunk by chunk (``chunk_bytes``) so that memory holds that span and one chunk, not the file; decoding
    stops at the first chunk that reaches ``t1_us``.
    """
    codec = _codec_of(path)
    if t0_us is None and t1_us is None:
        return _read(path, codec, width, height, chunk_bytes, sort)
    return _read_span(path, codec, width, height, chunk_bytes, sort, t0_us, t1_us)


def iter_raw(
    path: PathLike, *, width: int | None = None, height: int | None = None,
    sort: bool = False, chunk_bytes: int = CHUNK_BYTES,
) -> Iterator[Events]:
    """Yield the events of a RAW file chunk by chunk in the format its header declares; as :func:`iter_evt3`."""
    return _iter(path, _codec_of(path), width, height, chunk_bytes, sort)


@dataclass(frozen=True)
class RawScan:
    """What one decoding pass over a RAW file finds: the sensor size [px], the event and ON-event counts, the
    first and last events' times [µs] (None without events) and the events of each pixel, (height, width);
    ``size_inferred_from``: the header line a size the header does not state was inferred from (a known
    ``plugin_name`` / ``sensor_generation``: a guess), None for a stated or given size."""

    width: int
    height: int
    count: int
    on_count: int
    first_us: int | None
    last_us: int | None
    pixel_counts: np.ndarray | None = None
    size_inferred_from: str | None = None


def scan_raw(path: PathLike, *, width: int | None = None, height: int | None = None,
             chunk_bytes: int = CHUNK_BYTES) -> RawScan:
    """:class:`RawScan` of a RAW file, decoded chunk by chunk (:func:`iter_raw`: a file of any length)."""
    _, limits, _, _ = _open_data(Path(path), _codec_of(path), width, height, chunk_bytes, True)
    count = on = 0
    first = last = None
    pixels = np.zeros((limits.height, limits.width), np.int64)
    for chunk in iter_raw(path, width=width, height=height, chunk_bytes=chunk_bytes):
        first = int(chunk.t[0]) if first is None else first
        last, count, on = int(chunk.t[-1]), count + len(chunk), on + int(np.count_nonzero(chunk.p))
        pixels += pixel_counts(chunk)
    return RawScan(limits.width, limits.height, count, on, first, last, pixels, limits.inferred_from)


class RawWindows:
    """Windows ``[t0_us, t1_us)`` of a RAW file, asked for in order of ``t0_us``, decoded chunk by chunk
    (:func:`iter_raw`): memory holds the events from the last asked ``t0_us`` on and one chunk, not the file.

    ``first_us`` / ``last_us`` (the first and last events' times [µs]), ``count``, ``width`` and ``height``
    come from one decoding pass over the file at construction (:func:`scan_raw`); ``window`` then decodes it
    a second time, as
    far as the windows reach. A window that starts before the one asked before raises ValueError (the events
    before it are gone); one of more than :data:`cmax.events.MAX_EVENTS` events raises
    :class:`cmax.events.EventLimitError`. ``close`` closes the file of the second pass (also closed when that
    pass ends).

    >>> import tempfile
    >>> from cmax.io.prophesee.writer import write_evt3
    >>> path = Path(tempfile.mkdtemp()) / "recording.raw"
    >>> path = write_evt3(path, Events([1, 2, 3, 4], [0, 0, 0, 0], [10, 20, 30, 40], [1, 0, 1, 0], 640, 480))
    >>> windows = RawWindows(path)
    >>> windows.first_us, windows.last_us, windows.window(15, 35).t.tolist(), windows.window(35, 50).t.tolist()
    (10, 40, [20, 30], [40])
    """

    def __init__(self, path: PathLike, *, width: int | None = None, height: int | None = None,
                 chunk_bytes: int = CHUNK_BYTES) -> None:
        self.path, self._options = Path(path), dict(width=width, height=height, chunk_bytes=chunk_bytes)
        scan = scan_raw(self.path, **self._options)
        self.width, self.height, self.count = scan.width, scan.height, scan.count
        self.first_us, self.last_us = scan.first_us, scan.last_us
        self._chunks: Iterator[Events] | None = None
        self._held: list[Events] = []
        self._asked: int | None = None

    def window(self, t0_us: int, t1_us: int) -> Events:
        """The events with ``t0_us <= t < t1_us`` (``t0_us`` not before the last window's)."""
        t0_us, t1_us = int(t0_us), int(t1_us)
        if self._asked is not None and t0_us < self._asked:
            raise ValueError(f"{self.path}: RawWindows reads forward: a window from {t0_us} µs comes after one from "
                             f"{self._asked} µs")
        if self._chunks is None:
            self._chunks = iter_raw(self.path, **self._options)
        self._asked = t0_us
        self._held = [chunk for chunk in self._held if int(chunk.t[-1]) >= t0_us]
        while self._chunks is not None and (not self._held or int(self._held[-1].t[-1]) < t1_us):
            chunk = next(self._chunks, None)
            if chunk is None:
                self._chunks = iter(())                    # exhausted: later windows hold what is held
                break
            if int(chunk.t[-1]) >= t0_us:
                self._held.append(chunk)
        parts = [part for part in (chunk.slice_time(t0_us, t1_us) for chunk in self._held) if len(part)]
        check_event_count(sum(len(part) for part in parts), f"{self.path}: the window [{t0_us}, {t1_us}) µs")
        if not parts:
            return Events._trusted(*_empty_columns(0), self.width, self.height)
        return parts[0] if len(parts) == 1 else concatenate(parts)

    def close(self) -> None:
        """Close the file of the second pass (later windows hold only what is already decoded)."""
        if self._chunks is not None and hasattr(self._chunks, "close"):
            self._chunks.close()
        self._chunks = iter(())
