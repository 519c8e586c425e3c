"""Event files in the DSEC HDF5 layout: streaming writer, windowed reader.

Layout (Gehrig et al., "DSEC", RA-L 2021), one group per file::

    events/x   (N,) uint16     pixel column
    events/y   (N,) uint16     pixel row
    events/t   (N,) int64      µs, relative to t_offset (DSEC uses uint32; int64 here
                               so that recordings longer than 71 minutes do not wrap)
    events/p   (N,) uint8      0 = OFF, 1 = ON
    ms_to_idx  (M,) uint64     ms_to_idx[k] = index of the first event with t >= 1000*k
    t_offset   ()   int64      µs added to events/t to give absolute time

plus file attributes ``width``, ``height`` and whatever the writer was given
(simulator settings, source). Files written here are chunked and compressed
(Blosc/LZ4 with byte shuffle through ``hdf5plugin`` by default, gzip on request)
and are readable by any DSEC loader that imports ``hdf5plugin``.
"""
from __future__ import annotations

import json
import os
import stat
from pathlib import Path
from typing import Any, Iterator

import h5py
import hdf5plugin
import numpy as np

from cmax.events import Events, _check_sensor_size, check_event_count, check_time_us, window_steps
from cmax.io.atomic import AtomicOutput, write_error
from cmax.io.errors import FormatError

__all__ = ["H5Writer", "H5Reader", "write_h5", "read_h5", "is_dsec_h5", "verify_h5"]

_COLUMNS = {"x": np.uint16, "y": np.uint16, "t": np.int64, "p": np.uint8}
_DEFAULT_CHUNK = 1 << 18
#: Attributes of the completion record that H5Writer writes last (see verify_h5).
_COMPLETION_ATTRS = ("event_count", "complete")
#: ms_to_idx length (ms) a writer allows whatever the event count, and per event beyond it.
_INDEX_FLOOR_MS = 1 << 24
_INDEX_MS_PER_EVENT = 64

#: What h5py raises on corrupt files (its errors map HDF5 failures onto these built-ins).
H5_ERRORS = (OSError, KeyError, RuntimeError, TypeError, ValueError, IndexError)
_INT64_MAX = int(np.iinfo(np.int64).max)
_INT64_MIN = int(np.iinfo(np.int64).min)


def _compression(name: str) -> dict[str, Any]:
    if name == "blosc":
        return dict(hdf5plugin.Blosc(cname="lz4", clevel=5, shuffle=hdf5plugin.Blosc.SHUFFLE))
    if name == "gzip":
        return {"compression": "gzip", "compression_opts": 4, "shuffle": True}
    if name == "none":
        return {}
    raise ValueError(f"compression must be 'blosc', 'gzip' or 'none', got {name!r}")


def _attr_value(value: Any) -> Any:
    """An HDF5-storable form of an attribute (dicts and lists become JSON)."""
    if isinstance(value, (dict, list, tuple)) and not isinstance(value, np.ndarray):
        return json.dumps(value)
    if isinstance(value, Path):
        return str(value)
    if value is None:
        return "null"
    return value


def decode_attrs(attrs: Any) -> dict[str, Any]:
    """HDF5 attributes as plain Python: bytes decoded, JSON strings parsed, numpy scalars unwrapped."""
    out: dict[str, Any] = {}
    for key, value in attrs.items():
        if isinstance(value, bytes):
            value = value.decode()
        if isinstance(value, str) and value[:1] in "[{":
            try:
                value = json.loads(value)
            except json.JSONDecodeError:
                pass
        out[key] = value.item() if isinstance(value, np.generic) else value
    return out


class _FdFile:
    """A binary file object over a descriptor, for h5py's file-object driver.

    A failing write (full disk, file-size limit) is never reported to HDF5: the
    first OS error is kept in :attr:`error` and every later write is dropped
    (as after :meth:`discard`), so the library always sees success and the
    writer checks :attr:`error` after each step. HDF5 must not see the failure:
    a failed flush leaves its objects half closed, and the next HDF5 call (or the
    interpreter's exit) dies with SIGSEGV.
    """

    def __init__(self, fd: int) -> None:
        self._fd, self._position, self._discard = fd, 0, False
        self.error: OSError | None = None

    def discard(self) -> None:
        self._discard = True

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        base = {os.SEEK_SET: 0, os.SEEK_CUR: self._position}.get(whence)
        self._position = (os.fstat(self._fd).st_size if base is None else base) + offset
        return self._position

    def tell(self) -> int:
        return self._position

    def readinto(self, buffer) -> int:
        view = memoryview(buffer).cast("B")
        if hasattr(os, "preadv"):
            count = os.preadv(self._fd, [view], self._position)
        else:
            data = os.pread(self._fd, view.nbytes, self._position)
            count = len(data)
            view[:count] = data
        self._position += count
        return count

    def read(self, size: int = -1) -> bytes:
        if size < 0:
            size = max(os.fstat(self._fd).st_size - self._position, 0)
        data = os.pread(self._fd, size, self._position)
        self._position += len(data)
        return data

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        if not self._discard:
            try:
                done = 0
                while done < view.nbytes:
                    done += os.pwrite(self._fd, view[done:], self._position + done)
            except OSError as error:
                self.error, self._discard = error, True
        self._position += view.nbytes
        return view.nbytes

    def truncate(self, size: int | None = None) -> int:
        size = self._position if size is None else size
        if not self._discard:
            try:
                os.ftruncate(self._fd, size)
            except OSError as error:
                self.error, self._discard = error, True
        return size

    def flush(self) -> None:
        pass


class H5Writer:
    """Write events to a DSEC-layout HDF5 file chunk by chunk, with bounded memory.

    The file is written by the protocol of :mod:`cmax.io.atomic`: an exclusive
    lock on ``<path>.lock`` first (a second writer of the same path fails with
    :class:`~cmax.io.atomic.OutputLockedError` and changes nothing), then a
    private temporary ``<path>.<hex>.partial`` created without following links,
    renamed to ``path`` only when the writer closes without an exception. The
    last things written are the attributes ``event_count`` and ``complete``
    (:func:`verify_h5` checks them), so a file cut short never passes as
    complete. ``ms_to_idx`` is built on the fly.

    A write error (full disk, file-size limit) raises :class:`OSError` naming
    ``path`` with the errno kept, after removing the temporary file.

    Parameters
    ----------
    path : str or Path
        Output file; its folder must exist.
    width, height : int
        Sensor size in pixels (stored as attributes).
    t_offset_us : int, optional
        Absolute time (µs) subtracted from every event; default: the time of
        the first event appended.
    chunk_size : int
        Events buffered in memory before a write, and the HDF5 chunk length.
    compression : {'blosc', 'gzip', 'none'}
    overwrite : bool
        Replace an existing file at ``path`` (only when the write succeeds).
    **attrs
        File attributes (numbers, strings, arrays; dicts and lists as JSON).

    Examples
    --------
    >>> with H5Writer("out.h5", 346, 260, source="demo") as writer:  # doctest: +SKIP
    ...     for chunk in chunks:
    ...         writer.append(chunk)
    """

    def __init__(
        self,
        path: str | os.PathLike,
        width: int,
        height: int,
        *,
        t_offset_us: int | None = None,
        chunk_size: int = _DEFAULT_CHUNK,
        compression: str = "blosc",
        overwrite: bool = False,
        **attrs: Any,
    ) -> None:
        self.path = Path(path)
        self.width, self.height = _check_sensor_size(width, height)
        if int(chunk_size) <= 0:
            raise ValueError(f"chunk_size must be positive, got {chunk_size}")
        self._filters = _compression(compression)
        self._chunk_size = int(chunk_size)
        self._t_offset = None if t_offset_us is None else int(t_offset_us)
        self._buffer: list[Events] = []
        self._buffered = 0
        self._count = 0
        self._last_t: int | None = None
        self._ms_to_idx: list[np.ndarray] = []
        self._ms_filled = 0  # entries of ms_to_idx already known
        self._closed = True
        self._output = AtomicOutput(self.path, overwrite=overwrite)
        self._raw = _FdFile(self._output.fd)
        self._file = None
        self._closed = False
        self._guarded(self._create, attrs)

    def _create(self, attrs: dict[str, Any]) -> None:
        self._file = h5py.File(self._raw, "w")
        self._file.attrs["width"] = self.width
        self._file.attrs["height"] = self.height
        self._file.attrs["layout"] = "dsec"
        for key, value in attrs.items():
            if key in _COMPLETION_ATTRS:
                raise ValueError(f"attribute {key!r} is reserved for the completion record")
            self._file.attrs[key] = _attr_value(value)
        group = self._file.create_group("events")
        self._datasets = {
            name: group.create_dataset(
                name, shape=(0,), maxshape=(None,), dtype=dtype,
                chunks=(self._chunk_size,), **self._filters,
            )
            for name, dtype in _COLUMNS.items()
        }

    def _guarded(self, action, *args) -> Any:
        """Run a step that writes; on any failure remove the temporary file (a write error names ``path``)."""
        try:
            result = action(*args)
        except BaseException as error:
            self.abort()
            if self._raw.error is not None:
                raise write_error(self._raw.error, self.path) from None
            if isinstance(error, OSError) and error.errno is not None:
                raise write_error(error, self.path) from None
            raise
        if self._raw.error is not None:
            self.abort()
            raise write_error(self._raw.error, self.path) from None
        return result

    # -- appending --------------------------------------------------------------------
    def append(self, events: Events) -> None:
        """Append events later than (or at the time of) everything written so far."""
        if self._closed:
            raise ValueError(f"the writer of {self.path} is closed")
        if not isinstance(events, Events):
            raise TypeError(f"events must be cmax.Events, got {type(events).__name__}")
        if events.sensor_size != (self.width, self.height):
            raise ValueError(
                f"events have sensor {events.sensor_size}, the file has {(self.width, self.height)}"
            )
        if not len(events):
            return
        if self._last_t is not None and events.t_start < self._last_t:
            raise ValueError(
                f"events must be appended in time order: they start at {events.t_start} µs, "
                f"the file already holds events up to {self._last_t} µs"
            )
        if self._t_offset is None:
            self._t_offset = events.t_start
        if events.t_start < self._t_offset:
            raise ValueError(
                f"events start at {events.t_start} µs, before t_offset_us={self._t_offset}"
            )
        self._check_index_span(events)
        self._last_t = events.t_end
        self._buffer.append(events)
        self._buffered += len(events)
        if self._buffered >= self._chunk_size:
            self._guarded(self._flush)

    def _check_index_span(self, events: Events) -> None:
        """Refuse events whose time would make ``ms_to_idx`` (8 bytes per ms) out of all proportion.

        Allowed: ``max(2**24, 64 * events)`` ms after ``t_offset`` (4.6 hours
        whatever the count; longer recordings with at least one event per 64 ms
        on average). One wrong timestamp would otherwise allocate gigabytes.
        """
        span_ms = (events.t_end - self._t_offset) // 1000 + 1
        count = self.count + len(events)
        allowed = max(_INDEX_FLOOR_MS, _INDEX_MS_PER_EVENT * count)
        if span_ms > allowed:
            raise ValueError(
                f"{self.path}: {count:,} events would span {span_ms:,} ms after t_offset={self._t_offset} µs "
                f"(the last at t={events.t_end} µs), an ms_to_idx of {8 * span_ms / 2**30:.1f} GiB; "
                f"a timestamp is probably wrong (allowed: max(2**24, {_INDEX_MS_PER_EVENT} per event) ms)"
            )

    def _flush(self) -> None:
        if not self._buffered:
            return
        columns = {
            name: np.concatenate([getattr(part, name) for part in self._buffer])
            for name in "xytp"
        }
        columns["t"] = columns["t"] - self._t_offset
        start, stop = self._count, self._count + self._buffered
        for name, dataset in self._datasets.items():
            dataset.resize((stop,))
            dataset[start:stop] = columns[name].astype(_COLUMNS[name], copy=False)
        self._extend_ms_to_idx(columns["t"], start)
        self._count = stop
        self._buffer, self._buffered = [], 0

    def _extend_ms_to_idx(self, t_rel: np.ndarray, first_index: int) -> None:
        """Fill ms_to_idx for every millisecond boundary at or before the last time seen."""
        last_ms = int(t_rel[-1]) // 1000  # boundaries 1000*k <= t_last are now determined
        if last_ms < self._ms_filled:
            return
        boundaries = np.arange(self._ms_filled, last_ms + 1, dtype=np.int64) * 1000
        indices = first_index + np.searchsorted(t_rel, boundaries, side="left")
        self._ms_to_idx.append(indices.astype(np.uint64))
        self._ms_filled = last_ms + 1

    # -- closing ----------------------------------------------------------------------
    def close(self) -> Path:
        """Flush, write ``ms_to_idx``, ``t_offset`` and the completion record, rename to the final path."""
        if self._closed:
            return self.path
        self._guarded(self._finish)
        self._closed = True
        try:
            return self._output.commit()
        except OSError as error:
            raise write_error(error, self.path) from None

    def _finish(self) -> None:
        self._flush()
        # One closing entry pointing past the last event: windows ending after it resolve.
        closing = np.array([self._count], dtype=np.uint64)
        ms_to_idx = np.concatenate(self._ms_to_idx + [closing])
        self._file.create_dataset("ms_to_idx", data=ms_to_idx, **self._filters)
        self._file.create_dataset("t_offset", data=np.int64(self._t_offset or 0))
        self._file.attrs["event_count"] = np.int64(self._count)
        self._file.attrs["complete"] = True  # the last thing written
        self._file.close()

    def abort(self) -> None:
        """Drop the temporary file and release the lock; nothing appears at the final path."""
        if self._closed:
            return
        self._closed = True
        self._raw.discard()  # closing cannot fail on a full disk any more
        try:
            if self._file is not None:
                self._file.close()
        except H5_ERRORS:
            pass
        finally:
            self._output.abort()

    @property
    def count(self) -> int:
        """Events appended so far (written or buffered)."""
        return self._count + self._buffered

    def __enter__(self) -> "H5Writer":
        return self

    def __exit__(self, exc_type, exc, traceback) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_h5(
    path: str | os.PathLike, events: Events, *, overwrite: bool = False,
    compression: str = "blosc", **attrs: Any,
) -> Path:
    """Write ``events`` to a DSEC-layout HDF5 file (atomically); returns the path."""
    if not isinstance(events, Events):
        raise TypeError(f"events must be cmax.Events, got {type(events).__name__}")
    t_offset = events.t_start if len(events) else 0
    with H5Writer(
        path, events.width, events.height, t_offset_us=t_offset, overwrite=overwrite,
        compression=compression, **attrs,
    ) as writer:
        for start in range(0, len(events), writer._chunk_size):
            writer.append(events[start: start + writer._chunk_size])
    return Path(path)


def verify_h5(path: str | os.PathLike, *, events: int | None = None) -> int:
    """Check that ``path`` is a complete file of :class:`H5Writer`; returns its event count.

    Complete means: a regular file (not a link), readable HDF5 with the DSEC
    datasets, the completion record written last (``complete`` true and
    ``event_count`` equal to the length of every ``events/*`` column and to the
    last ``ms_to_idx`` entry), and ``events`` events when given. Raises
    :class:`FormatError` naming what is missing, :class:`FileNotFoundError`.
    """
    path = Path(path)
    try:
        info = os.lstat(path)
    except FileNotFoundError:
        raise FileNotFoundError(f"no such event file: {path}") from None
    if not stat.S_ISREG(info.st_mode):
        raise FormatError(f"{path} is not a regular file")
    try:
        with h5py.File(path, "r") as file:
            if not is_dsec_h5(file) or "ms_to_idx" not in file:
                raise FormatError(f"{path} lacks the datasets of a DSEC event file")
            attrs = file.attrs
            if not bool(attrs.get("complete", False)) or "event_count" not in attrs:
                raise FormatError(f"{path} has no completion record (not written to the end)")
            count = int(attrs["event_count"])
            lengths = {name: file["events"][name].shape for name in "xytp"}
            ms_to_idx = file["ms_to_idx"]
            last = int(ms_to_idx[-1]) if ms_to_idx.shape and ms_to_idx.shape[0] else -1
    except FormatError:
        raise
    except H5_ERRORS as error:
        raise FormatError(f"{path} is not a readable HDF5 file ({type(error).__name__}: {error})") from None
    if any(shape != (count,) for shape in lengths.values()) or last != count:
        raise FormatError(f"{path}: completion record says {count} events, the datasets hold {lengths}, "
                          f"ms_to_idx ends at {last}")
    if events is not None and count != int(events):
        raise FormatError(f"{path} holds {count} events, expected {int(events)}")
    return count


def is_dsec_h5(file: h5py.File) -> bool:
    """Whether an open HDF5 file has the DSEC event layout."""
    return "events" in file and isinstance(file["events"], h5py.Group) and all(
        name in file["events"] for name in "xytp"
    )


class H5Reader:
    """Random access to a DSEC-layout HDF5 event file.

    ``window(t0_us, t1_us)`` reads only the rows between the two times, found
    through ``ms_to_idx`` (or a binary search of ``events/t`` on disk when the
    file has no index). Times are absolute µs (``t_offset`` added).

    Parameters
    ----------
    path : str or Path
    width, height : int, optional
        Sensor size, for files without ``width``/``height`` attributes (original
        DSEC files are 640x480 and carry none).
    """

    def __init__(
        self, path: str | os.PathLike, *, width: int | None = None, height: int | None = None
    ) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"no such event file: {self.path}")
        try:
            self._file = h5py.File(self.path, "r")
        except OSError as error:
            raise FormatError(f"{self.path} is not a readable HDF5 file ({error})") from None
        if width is not None and height is not None:  # the caller's own values: errors stay theirs
            _check_sensor_size(width, height)
        try:
            self._open(width, height)
        except FormatError:
            self._file.close()
            raise
        except H5_ERRORS as error:  # corrupt metadata surfaces as any of these from h5py
            self._file.close()
            raise FormatError(f"{self.path}: corrupt HDF5 file ({type(error).__name__}: {error})") from None
        except BaseException:
            self._file.close()
            raise

    def _open(self, width: int | None, height: int | None) -> None:
        if not is_dsec_h5(self._file):
            raise FormatError(
                f"{self.path} lacks the DSEC datasets events/x, events/y, events/t, events/p"
            )
        self._columns = {name: self._file["events"][name] for name in "xytp"}
        lengths = {name: column.shape for name, column in self._columns.items()}
        if len(set(lengths.values())) != 1 or len(lengths["t"]) != 1:
            raise FormatError(f"{self.path}: events/* must be 1-D of equal length, got {lengths}")
        attrs = self._file.attrs
        if width is None and height is None and "width" in attrs and "height" in attrs:
            width, height = int(attrs["width"]), int(attrs["height"])
        if width is None or height is None:
            raise FormatError(
                f"{self.path} stores no sensor size; pass width= and height= (DSEC: 640, 480)"
            )
        self.width, self.height = _check_sensor_size(width, height)
        try:
            self.t_offset_us = int(self._file["t_offset"][()]) if "t_offset" in self._file else 0
            self._ms_to_idx = self._file["ms_to_idx"][:] if "ms_to_idx" in self._file else None
        except H5_ERRORS as error:
            raise FormatError(f"{self.path}: unreadable t_offset or ms_to_idx ({error})") from None
        if self._ms_to_idx is not None:
            self._ms_to_idx = _checked_ms_to_idx(self._ms_to_idx, len(self), self.path)

    # -- metadata ---------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self._columns["t"].shape[0])

    @property
    def attrs(self) -> dict[str, Any]:
        """File attributes as a dict (JSON strings decoded)."""
        return decode_attrs(self._file.attrs)

    @property
    def file(self) -> h5py.File:
        """The open :class:`h5py.File` (for groups beyond the events, e.g. ``gt/``)."""
        return self._file

    @property
    def t_start(self) -> int:
        """Time of the first event (µs)."""
        self._require_events()
        return self._time_at(0)

    @property
    def t_end(self) -> int:
        """Time of the last event (µs)."""
        self._require_events()
        return self._time_at(len(self) - 1)

    def _time_at(self, row: int) -> int:
        try:
            return int(self._columns["t"][row]) + self.t_offset_us
        except H5_ERRORS as error:
            raise FormatError(f"{self.path}: cannot read events/t[{row}] ({error})") from None

    def _require_events(self) -> None:
        if not len(self):
            raise ValueError(f"{self.path} holds no events")

    # -- reading ----------------------------------------------------------------------
    def _bounds(self, t_rel: int) -> tuple[int, int]:
        """Row range that surely contains the first event with relative time >= t_rel."""
        n = len(self)
        if t_rel < 0:
            return 0, 0
        ms = t_rel // 1000
        if ms >= len(self._ms_to_idx):
            return n, n
        lo = int(self._ms_to_idx[ms])
        hi = int(self._ms_to_idx[ms + 1]) if ms + 1 < len(self._ms_to_idx) else n
        return lo, min(max(hi, lo), n)

    def _index_at(self, t_us: int) -> int:
        """Index of the first event with t >= t_us: one ms of rows through ``ms_to_idx``,
        bisected on disk when that ms holds many rows (or the file has no index)."""
        t_rel = int(t_us) - self.t_offset_us
        if t_rel > _INT64_MAX:
            return len(self)
        t_rel = max(t_rel, _INT64_MIN)
        if self._ms_to_idx is None:
            return self._bisect_on_disk(t_rel, 0, len(self))
        lo, hi = self._bounds(t_rel)
        if hi <= lo:
            return lo
        return self._bisect_on_disk(t_rel, lo, hi)

    def _bisect_on_disk(self, t_rel: int, lo: int, hi: int) -> int:
        """First row in ``[lo, hi)`` with t >= t_rel, reading single rows until 4096 remain."""
        column = self._columns["t"]
        while hi - lo > 4096:
            mid = (lo + hi) // 2
            if column[mid] < t_rel:
                lo = mid + 1
            else:
                hi = mid
        return lo + int(np.searchsorted(column[lo:hi], t_rel, side="left"))

    def read_rows(self, start: int, stop: int) -> Events:
        """Events ``start:stop`` by row index (clipped to the file's rows).

        Raises :class:`~cmax.events.EventLimitError` before reading when the
        rows exceed :data:`cmax.events.MAX_EVENTS`, and :class:`FormatError`
        when the stored rows are corrupt (undecodable chunks, coordinates
        outside the sensor, time going back).
        """
        start, stop = max(0, int(start)), min(len(self), int(stop))
        stop = max(start, stop)
        check_event_count(stop - start, f"{self.path}: rows [{start}, {stop})")
        try:
            columns = {name: self._columns[name][start:stop] for name in "xytp"}
        except H5_ERRORS as error:
            raise FormatError(f"{self.path}: cannot read rows [{start}, {stop}) ({error})") from None
        try:
            return Events(
                columns["x"], columns["y"], columns["t"].astype(np.int64) + self.t_offset_us,
                columns["p"], self.width, self.height,
            )
        except (TypeError, ValueError) as error:
            raise FormatError(f"{self.path}: corrupt events in rows [{start}, {stop}): {error}") from None

    def window(self, t0_us: int, t1_us: int) -> Events:
        """Events with ``t0_us <= t < t1_us`` (absolute µs), reading only that slice.

        Times are integer µs (floats must be whole). A window holding more than
        :data:`cmax.events.MAX_EVENTS` events raises
        :class:`~cmax.events.EventLimitError` before anything is read; iterate
        over :meth:`windows` of a shorter duration instead.
        """
        t0_us, t1_us = check_time_us("t0_us", t0_us), check_time_us("t1_us", t1_us)
        if t1_us < t0_us:
            raise ValueError(f"t1_us ({t1_us}) must not be smaller than t0_us ({t0_us})")
        try:
            start, stop = self._index_at(t0_us), self._index_at(t1_us)
        except H5_ERRORS as error:
            raise FormatError(f"{self.path}: cannot search events/t ({error})") from None
        return self.read_rows(start, stop)

    def read(self) -> Events:
        """All events (loads the whole file)."""
        return self.read_rows(0, len(self))

    def windows(self, duration_us: int, *, step_us: int | None = None) -> Iterator[Events]:
        """Consecutive windows of ``duration_us`` from the first event (step defaults to it)."""
        duration, step = window_steps(duration_us, step_us)
        if not len(self):
            return
        start, end = self.t_start, self.t_end
        while start <= end:
            yield self.window(start, start + duration)
            start += step

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> "H5Reader":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"H5Reader({str(self.path)!r}, n={len(self)}, sensor={self.width}x{self.height})"


def _checked_ms_to_idx(ms_to_idx: np.ndarray, count: int, path: Path) -> np.ndarray:
    """``ms_to_idx`` as int64 after checking it: 1-D, non-decreasing, within ``[0, count]``."""
    if ms_to_idx.ndim != 1 or ms_to_idx.dtype.kind not in "iu":
        raise FormatError(f"{path}: ms_to_idx must be a 1-D integer array, got {ms_to_idx.dtype} {ms_to_idx.shape}")
    if ms_to_idx.size and (
        int(ms_to_idx.min()) < 0 or int(ms_to_idx.max()) > count or np.any(np.diff(ms_to_idx.astype(np.int64)) < 0)
    ):
        raise FormatError(
            f"{path}: corrupt ms_to_idx (entries must be non-decreasing row indices in [0, {count}])"
        )
    return ms_to_idx.astype(np.int64)


def read_h5(
    path: str | os.PathLike, *, width: int | None = None, height: int | None = None,
    t0_us: int | None = None, t1_us: int | None = None,
) -> Events:
    """Read a DSEC-layout file, whole or the window ``[t0_us, t1_us)``."""
    with H5Reader(path, width=width, height=height) as reader:
        if t0_us is None and t1_us is None:
            return reader.read()
        return reader.window(
            -(2**62) if t0_us is None else t0_us, 2**62 if t1_us is None else t1_us
        )

