"""Event files in the DSEC HDF5 layout: streaming writer, windowed reader.

Layout (Gehrig et al., "DSEC", RA-L 2021), one group per file::

    events/x   (N,) uint16     pixel column
    events/y   (N,) uint16     pixel row
    events/t   (N,) int64      µs, relative to t_offset (DSEC uses uint32; int64 here
                               so that recordings longer than 71 minutes do not wrap)
    events/p   (N,) uint8      0 = OFF, 1 = ON
    ms_to_idx  (M,) uint64     ms_to_idx[k] = index of the first event with t >= 1000*k
    t_offset   ()   int64      µs added to events/t to give absolute time

``events/t`` and ``t_offset`` carry the attribute ``unit = "us"`` (files of
earlier versions, like DSEC's own, carry none: integer times are then µs),
plus file attributes ``width``, ``height`` and whatever the writer was given
(simulator settings, source). Files written here are chunked and compressed
(Blosc/LZ4 with byte shuffle through ``hdf5plugin`` by default, gzip on request)
and are readable by any DSEC loader that imports ``hdf5plugin``.
"""
from __future__ import annotations

import json
import os
import stat
import warnings
from pathlib import Path
from typing import Any, Callable, Iterator

import h5py
import hdf5plugin
import numpy as np

from cmax.events import (Events, _check_sensor_size, check_event_count, check_time_us, require_events,
                         window_steps, wrap_index)
from cmax.io._checks import (add_offset, check_allocated, check_implied_rate, check_not_nanoseconds, check_offset,
                             check_polarity_encoding, check_stated_size, check_time_unit, polarity_01, scalar_to_us,
                             times_to_us, unit_from_attrs)
from cmax.io.atomic import AtomicOutput, write_error
from cmax.io.errors import FormatError

__all__ = ["H5Writer", "H5Reader", "write_h5", "read_h5", "is_dsec_h5", "verify_h5"]

_COLUMNS = {"x": np.uint16, "y": np.uint16, "t": np.int64, "p": np.uint8}
_DEFAULT_CHUNK = 1 << 18
#: Attributes of the completion record that H5Writer writes last (see verify_h5).
_COMPLETION_ATTRS = ("event_count", "complete")
#: What h5py raises on corrupt files (its errors map HDF5 failures onto these built-ins).
H5_ERRORS = (OSError, KeyError, RuntimeError, TypeError, ValueError, IndexError)
_INT64_MAX = int(np.iinfo(np.int64).max)
_INT64_MIN = int(np.iinfo(np.int64).min)
#: ``ms_to_idx`` entries an :class:`H5Reader` loads and checks whole when it opens a file (2**20 ms: 17 minutes of
#: recording, 8 MB); a longer index (an hour-long video's) is read an entry at a time as windows need them, each
#: entry checked as it is read (:class:`_IndexOnDisk`), so opening costs neither its memory nor its reading.
MAX_INDEX_IN_MEMORY = 1 << 20


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
    >>> import tempfile
    >>> from cmax.io import read
    >>> path = Path(tempfile.mkdtemp()) / "out.h5"
    >>> chunks = [Events([0, 1], [0, 0], [10, 20], [1, 0], 346, 260), Events([5], [2], [30], [1], 346, 260)]
    >>> with H5Writer(path, 346, 260, source="demo") as writer:
    ...     for chunk in chunks:
    ...         writer.append(chunk)
    >>> events = read(path)
    >>> len(events), events.sensor_size, events.x.tolist()
    (3, (346, 260), [0, 1, 5])
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
        self._datasets["t"].attrs["unit"] = "us"

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
        require_events(events)
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
        """Refuse events whose span would make ``ms_to_idx`` (8 bytes per ms) out of all proportion,
        before anything is buffered or allocated (see :func:`check_index_span`)."""
        span_ms = (events.t_end - self._t_offset) // 1000
        check_index_span(span_ms + 1, self.count + len(events), self.path)

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
    def close(self, *, extra: Callable[[h5py.File], None] | None = None) -> Path:
        """Flush, write ``ms_to_idx``, ``t_offset`` and the completion record, rename to the final path.

        ``extra``, if given, is called with the open ``h5py.File`` after the events, ``ms_to_idx`` and
        ``t_offset`` and before the completion record, to add more datasets (``cmax scene``'s ground truth
        ``gt/``): they are part of the file that appears at ``path``, and a file cut short before them
        never passes :func:`verify_h5`. An error of ``extra`` aborts the writer (nothing appears).
        """
        if self._closed:
            return self.path
        self._guarded(self._finish, extra)
        self._closed = True
        try:
            return self._output.commit()
        except OSError as error:
            raise write_error(error, self.path) from None

    def _finish(self, extra: Callable[[h5py.File], None] | None = None) -> None:
        self._flush()
        # One closing entry pointing past the last event: windows ending after it resolve.
        closing = np.array([self._count], dtype=np.uint64)
        ms_to_idx = np.concatenate(self._ms_to_idx + [closing])
        self._file.create_dataset("ms_to_idx", data=ms_to_idx, **self._filters)
        self._file.create_dataset("t_offset", data=np.int64(self._t_offset or 0)).attrs["unit"] = "us"
        if extra is not None:
            extra(self._file)
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

    def __del__(self) -> None:
        """A writer dropped without :meth:`close` (a script without ``with`` that ends): say so, and remove its
        temporary file and lock (they were left without a word, and no output appeared)."""
        if getattr(self, "_closed", True):   # closed, aborted, or never opened (its __init__ raised)
            return
        try:
            warnings.warn(f"H5Writer of {self.path} was never closed: nothing was written there (its temporary file "
                          "is removed); call close() or use 'with H5Writer(...) as writer:'", UserWarning,
                          stacklevel=2)
            self.abort()
        except Exception:  # noqa: BLE001 - at interpreter shutdown the modules it needs may be gone
            pass


#: ``ms_to_idx`` may hold up to this many entries whatever the event count (2**24 ms, 4.7 hours) ...
MIN_INDEX_ENTRIES = 1 << 24
#: ... and beyond that at most this many per event (a recording of fewer than one event per
#: 64 ms on average over hours is a time stamp off by orders of magnitude, not a recording).
INDEX_ENTRIES_PER_EVENT = 64


def check_index_span(entries: int, events: int, path: Path) -> None:
    """Refuse an ``ms_to_idx`` of ``entries`` (one per ms of the time span) for only ``events`` events.

    The index costs 8 bytes per millisecond of the span, so one time stamp off by
    2**40 µs would need 8 GiB for a handful of events; such a span is refused,
    naming it, before anything is allocated.
    """
    limit = max(MIN_INDEX_ENTRIES, INDEX_ENTRIES_PER_EVENT * int(events))
    if entries > limit:
        raise ValueError(
            f"{path}: the events span {(entries - 2) / 3.6e6:,.1f} hours after t_offset, so ms_to_idx would need "
            f"{entries:,} entries ({8 * entries / 2**30:,.1f} GiB) for {events:,} events (at most "
            f"max(2**24, {INDEX_ENTRIES_PER_EVENT} per event) are built); a time stamp is probably off "
            "(a wrong unit or a corrupt value)"
        )


def write_h5(
    path: str | os.PathLike, events: Events, *, overwrite: bool = False,
    compression: str = "blosc", **attrs: Any,
) -> Path:
    """Write ``events`` to a DSEC-layout HDF5 file at ``path`` (atomically); returns the path.

    ``overwrite``: replace an existing file (only once the new one is complete; else ``FileExistsError``);
    ``compression``: ``'blosc'``, ``'gzip'`` or ``'none'``; ``**attrs``: file attributes, as :class:`H5Writer`.
    The HDF5 chunks are as long as the events when they are fewer than :class:`H5Writer`'s default (a small file
    is not padded to a whole chunk).
    """
    require_events(events)
    t_offset = events.t_start if len(events) else 0
    with H5Writer(
        path, events.width, events.height, t_offset_us=t_offset, overwrite=overwrite,
        chunk_size=min(_DEFAULT_CHUNK, max(len(events), 1)), compression=compression, **attrs,
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


class _CallerError(ValueError):
    """A caller's argument that contradicts the file (kept apart from h5py's errors on corrupt files)."""


def _whole_size(value: object, name: str, path: Path) -> int:
    """An h5 file's ``width`` / ``height`` attribute as a whole number of pixels (FormatError, naming the file, for
    80.5, a string or an array: never rounded)."""
    array = np.asarray(value.decode() if isinstance(value, bytes) else value)
    if array.size == 1:                                  # [346], as some writers (MATLAB) store a scalar
        array = array.reshape(())
    if array.shape == () and array.dtype.kind == "U" and str(array).strip().isdigit():   # "346", as some tools write
        return int(str(array))
    if array.shape != () or array.dtype.kind not in "iuf" or not np.isfinite(array) or float(array) != int(array):
        raise FormatError(f"{path}: its {name} attribute must be a whole number of pixels, got {value!r}")
    return int(array)


def _check_half_size(attrs: Any, width: int | None, height: int | None, path: Path) -> None:
    """For a file whose attributes state one of ``width`` / ``height``: the caller's size must agree with it
    (:class:`_CallerError`), and without a caller's size :class:`FormatError` names the missing half."""
    name, missing = ("width", "height") if "width" in attrs else ("height", "width")
    value = _whole_size(attrs[name], name, path)
    given = width if name == "width" else height
    if width is None or height is None:
        raise FormatError(f"{path} states its sensor's {name} ({value}) but not its {missing}; pass width= and "
                          f"height= (cmax: --size WxH) with {name}={value}")
    if given != value:
        raise _CallerError(f"width={width}, height={height} contradicts the {name} {value} that {path} states; "
                           f"give {name}={value} (the file states no {missing})")


#: Rows of ``events/x`` / ``events/y`` read at a time by :func:`_sensor_resolution` (bounded memory).
_EXTENT_CHUNK = 1 << 22


def _coordinate_extent(columns: dict, path: Path) -> tuple[int, int] | None:
    """``(max x, max y)`` [px] of the ``events/x`` and ``events/y`` datasets in ``columns``, read
    :data:`_EXTENT_CHUNK` rows at a time; None for a file without events."""
    n = columns["x"].shape[0]
    if not n:
        return None
    top = [-1, -1]
    try:
        for start in range(0, n, _EXTENT_CHUNK):
            for axis, name in enumerate("xy"):
                chunk = columns[name][start: start + _EXTENT_CHUNK]
                top[axis] = max(top[axis], int(np.max(chunk)))
    except H5_ERRORS as error:
        raise FormatError(f"{path}: cannot read events/x, events/y ({error})") from None
    return top[0], top[1]


def _resolution_numbers(value: object, path: Path) -> tuple[int, int]:
    """The two whole numbers [px] of a ``sensor_resolution`` attribute ``value`` (in an order it does not state);
    FormatError naming the file for anything else."""
    try:
        numbers = [_whole_size(v, "sensor_resolution", path) for v in np.asarray(value).ravel()]
    except (TypeError, ValueError):
        numbers = []
    if len(numbers) != 2 or min(numbers) < 1:
        raise FormatError(f"{path}: its sensor_resolution attribute must be two whole numbers of pixels (height, "
                          f"width or width, height), got {value!r}; pass width= and height= (cmax: --size WxH)")
    return numbers[0], numbers[1]


def _sensor_resolution(value: object, columns: dict, width: int | None, height: int | None,
                       path: Path) -> tuple[int | None, int | None]:
    """``(width, height)`` [px] of a file whose only size is a ``sensor_resolution`` attribute ``value`` (two whole
    numbers, written ``(height, width)`` by event_utils / HQF converters, ``(width, height)`` by others: the file
    does not say which). Square, or only one order holding every event (``events/x`` below the width,
    ``events/y`` below the height, from ``columns``): that order. A caller's ``width``, ``height`` must be one of
    the two orders (:class:`_CallerError` otherwise) and chooses it. Both orders holding every event, or neither:
    FormatError naming the attribute and both readings (never guessed)."""
    a, b = _resolution_numbers(value, path)
    orders = {(b, a): f"(height, width), a {b}x{a} sensor", (a, b): f"(width, height), a {a}x{b} sensor"}
    if width is not None and height is not None:
        if (width, height) not in orders:
            raise _CallerError(f"width={width}, height={height} contradicts the sensor_resolution attribute {a}, {b} "
                               f"that {path} states (either order: {' or '.join(orders.values())})")
        return width, height
    extent = _coordinate_extent(columns, path)
    if a == b:
        fit = [(a, a)]
    else:
        fit = [size for size in orders if extent is not None and extent[0] < size[0] and extent[1] < size[1]]
    if len(fit) == 1:
        return fit[0]
    reach = "it holds no events" if extent is None else f"its events reach x = {extent[0]}, y = {extent[1]}"
    if not fit:
        raise FormatError(f"{path}: its sensor_resolution attribute {a}, {b} does not hold every event in either "
                          f"order ({' or '.join(orders.values())}): {reach}; pass width= and height= (cmax: --size "
                          "WxH)")
    raise FormatError(f"{path}: its sensor_resolution attribute {a}, {b} does not state its order, and both "
                      f"{' and '.join(orders.values())} hold every event ({reach}); pass width= and height= (cmax: "
                      "--size WxH)")


class H5Reader:
    """Random access to a DSEC-layout HDF5 event file.

    ``window(t0_us, t1_us)`` reads only the rows between the two times, located
    through ``ms_to_idx`` alone (or a binary search of ``events/t`` on disk
    when the file has no index); the index entries a window uses are checked
    against the times read, so an index that disagrees with ``events/t``
    raises :class:`FormatError` instead of giving empty windows. Times are
    absolute µs (``t_offset`` added; overflow of int64 is refused).

    Nothing is guessed: integer ``events/t`` is µs (the layout's unit) unless
    the file or the caller states another; float times are refused unless a
    unit is stated, and then rounded to the nearest µs (half to even). NaN or
    infinite times, coordinates outside the sensor, time going back,
    polarities outside the stated encoding and a ``t_offset`` of no stated
    unit that is negative or a float another unit could mean (1600000000.0)
    raise :class:`FormatError`. The
    checks are min/max and order passes over the columns read (no sort).

    Parameters
    ----------
    path : str or Path
    width, height : int, optional
        Sensor size, for files without ``width``/``height`` attributes (original
        DSEC files are 640x480 and carry none). A size that differs from the
        one the file's attributes state raises :class:`ValueError`.
    time_unit : {'us', 'ms', 's'}, optional
        Unit of ``events/t`` and ``t_offset``; default: the unit the file states
        (attribute ``unit``/``units`` of ``events/t``, or ``time_unit`` of the
        file), else µs for integer times. Must agree with a unit the file states
        (files of :class:`H5Writer` state ``"us"``); files that state none (DSEC's
        own, earlier versions of this writer) with integer times are µs by default.
    polarity : {'01', 'signed'}
        Encoding of ``events/p``: ``'01'`` (0 OFF, 1 ON, the layout's) or
        ``'signed'`` (-1 OFF, +1 ON). Other values raise :class:`FormatError`.
    """

    def __init__(
        self, path: str | os.PathLike, *, width: int | None = None, height: int | None = None,
        time_unit: str | None = None, polarity: str = "01",
    ) -> None:
        self.path = Path(path)
        time_unit = check_time_unit(time_unit)
        self._polarity = check_polarity_encoding(polarity)
        if width is not None and height is not None:  # the caller's own values: errors stay theirs
            _check_sensor_size(width, height)
        if not self.path.is_file():
            if self.path.exists() and not self.path.is_dir():   # a device, a FIFO, a socket: exists, holds no file
                raise FormatError(f"{self.path} is not a regular file (a device, a pipe or a socket): give an "
                                  "event file")
            raise FileNotFoundError(f"no such event file: {self.path}")
        try:
            self._file = h5py.File(self.path, "r")
        except OSError as error:
            raise FormatError(f"{self.path} is not a readable HDF5 file ({error})") from None
        try:
            self._open(width, height, time_unit)
        except FormatError:
            self._file.close()
            raise
        except _CallerError as error:  # the caller's arguments, not the file: not "corrupt"
            self._file.close()
            raise ValueError(str(error)) from None
        except H5_ERRORS as error:  # corrupt metadata surfaces as any of these from h5py
            self._file.close()
            raise FormatError(f"{self.path}: corrupt HDF5 file ({type(error).__name__}: {error})") from None
        except BaseException:
            self._file.close()
            raise

    def _open(self, width: int | None, height: int | None, time_unit: str | None) -> None:
        if not is_dsec_h5(self._file):
            raise FormatError(
                f"{self.path} lacks the DSEC datasets events/x, events/y, events/t, events/p"
            )
        self._columns = {}
        for name in "xytp":
            column = self._file["events"][name]
            if not isinstance(column, h5py.Dataset):
                raise FormatError(f"{self.path}: events/{name} must be a dataset, got a {type(column).__name__}")
            self._columns[name] = column
        lengths = {name: column.shape for name, column in self._columns.items()}
        if len(set(lengths.values())) != 1 or len(lengths["t"]) != 1:
            raise FormatError(f"{self.path}: events/* must be 1-D of equal length, got {lengths}")
        for name, column in self._columns.items():
            check_allocated(column, f"{self.path}: events/{name}")
        attrs = self._file.attrs
        if "width" in attrs and "height" in attrs:
            stated = _whole_size(attrs["width"], "width", self.path), _whole_size(attrs["height"], "height", self.path)
            if "sensor_resolution" in attrs and stated not in (
                    resolution := _resolution_numbers(attrs["sensor_resolution"], self.path), resolution[::-1]):
                raise FormatError(f"{self.path} contradicts itself: its width and height attributes state a "
                                  f"{stated[0]}x{stated[1]} sensor, its sensor_resolution attribute {resolution[0]}, "
                                  f"{resolution[1]} (in either order) another; fix the file's attributes")
            try:
                width, height = check_stated_size(width, height, stated, self.path)
            except ValueError as error:
                raise _CallerError(str(error)) from None
        elif "width" in attrs or "height" in attrs:      # half a size: the half stated still binds the caller's
            _check_half_size(attrs, width, height, self.path)
        elif "sensor_resolution" in attrs:               # event_utils' / HQF's (height, width), others' (width, height)
            width, height = _sensor_resolution(attrs["sensor_resolution"], self._columns, width, height, self.path)
        if width is None or height is None:
            raise FormatError(
                f"{self.path} stores no sensor size; pass width= and height= (cmax: --size WxH; DSEC: 640x480)"
            )
        self.width, self.height = _check_sensor_size(width, height)
        self.time_unit = self._time_unit(time_unit)
        self._ms_to_idx = None
        self.t_offset_us, unstated, value = 0, False, None
        try:
            if "t_offset" in self._file:
                offset = self._dataset("t_offset")
                own_unit = unit_from_attrs(offset.attrs, f"{self.path}: t_offset")
                value = offset[()]
                if own_unit is None and not self._unit_stated and _fractional_float(value):
                    raise _FractionalOffset(value)
                unstated = own_unit is None and not self._unit_stated and not self._written_here()
                self.t_offset_us = scalar_to_us(value, own_unit or self.time_unit, f"{self.path}: t_offset")
            if "ms_to_idx" in self._file:
                index = self._dataset("ms_to_idx")
                long = index.ndim == 1 and index.shape[0] > MAX_INDEX_IN_MEMORY
                self._ms_to_idx = _IndexOnDisk(index, len(self), self.path) if long else index[:]
        except _FractionalOffset as error:
            raise FormatError(
                f"{self.path}: t_offset holds the fractional number {error.value!r}, not whole microseconds (the "
                "layout's unit), and neither t_offset, the file nor the caller states its unit; state it with a "
                "'unit' attribute on t_offset ('s', 'ms' or 'us'), or time_unit= (cmax: --time-unit) when events/t "
                "has the same unit"
            ) from None
        except H5_ERRORS as error:
            raise FormatError(f"{self.path}: unreadable t_offset or ms_to_idx ({error})") from None
        if unstated:
            _check_unstated_offset(value, self.path)
        if isinstance(self._ms_to_idx, np.ndarray):
            self._ms_to_idx = _checked_ms_to_idx(self._ms_to_idx, len(self), self.path)
        self._check_times_against_index()

    def _check_times_against_index(self) -> None:
        """Check the last event's time against ``ms_to_idx`` (an index whose last entry holds every row must end
        after it: else windows past the index's end would come out empty) and, for integer ``events/t`` whose unit
        neither the file nor the caller states (:attr:`time_unit_assumed`: µs by the layout), refuse it where the
        file contradicts that unit: an ``ms_to_idx`` (one entry a millisecond) far longer than the times span as µs,
        a mean rate no sensor reaches (:func:`check_implied_rate`), or times after the year 2100 (nanoseconds:
        :func:`check_not_nanoseconds`). Reads two rows and one index entry. Not seen: times in ms of a slow
        recording whose ``ms_to_idx`` was built as if they were µs."""
        n, index = len(self), self._ms_to_idx
        if not n:
            return
        column, where = self._columns["t"], f"{self.path}: events/t"
        try:
            raw_first, raw_last = column[0:1], column[n - 1: n]
        except H5_ERRORS as error:
            raise FormatError(f"{self.path}: cannot read events/t ({error})") from None
        unit_note = ("" if not self.time_unit_assumed else
                     " (read as microseconds, the layout's unit, which neither the file nor the caller states: "
                     "in milliseconds? pass time_unit='ms', cmax: --time-unit ms)")
        try:
            last_us = int(self._t_us(raw_last, where)[0])
        except ValueError:            # NaN, fractional, beyond int64: refused by the read, naming the row
            return
        if index is not None and len(index) and int(index[-1]) == n and last_us >= 1000 * (len(index) - 1):
            # events past the index's end: as µs the times are too LONG, so milliseconds cannot be the way out
            nanoseconds = last_us >= 100_000 * max(len(index) - 1, 1)      # far past the index, not just beyond
            finer = ("" if not self.time_unit_assumed or not nanoseconds else
                     " (read as microseconds, the layout's unit, which neither the file nor the caller states: in "
                     "nanoseconds, 1000 times the index's span? convert events/t to integer µs, t // 1000, and "
                     "read it again)")
            raise FormatError(
                f"{self.path}: ms_to_idx ends at {len(index) - 1} ms with every row before it, but the last event of "
                f"events/t lies {last_us / 1000:,.3f} ms after t_offset{finer}; else the index is corrupt"
            )
        if not self.time_unit_assumed:     # stated, or H5Writer's (µs, with or without the attribute)
            return
        first, last = int(raw_first[0]), int(raw_last[0])        # µs after t_offset, if µs they are
        entries, span_ms = (0 if index is None else len(index)), max(last, 0) // 1000 + 2
        if entries > 10 * span_ms + 10:
            raise FormatError(
                f"{self.path}: ms_to_idx has {entries:,} entries (one a millisecond: {entries / 1000:,.1f} s) but "
                f"events/t ends {last / 1000:,.1f} ms after t_offset{unit_note}; else the index is corrupt"
            )
        check_not_nanoseconds(self.t_offset_us + max(first, last, key=abs), where)
        check_implied_rate(n, first, last, where)

    def _dataset(self, name: str) -> h5py.Dataset:
        """A top-level dataset, checked to be one and to store the data it declares."""
        dataset = self._file[name]
        if not isinstance(dataset, h5py.Dataset):
            raise FormatError(f"{self.path}: {name} must be a dataset, got a {type(dataset).__name__}")
        if dataset.size > 1 and name == "t_offset":
            raise FormatError(f"{self.path}: t_offset must be a single number, got shape {dataset.shape}")
        check_allocated(dataset, f"{self.path}: {name}")
        return dataset

    def _time_unit(self, stated: str | None) -> str:
        """The unit of ``events/t``: the caller's and the file's must agree; float times need one."""
        column = self._columns["t"]
        in_file = unit_from_attrs(column.attrs, f"{self.path}: events/t") or unit_from_attrs(
            self._file.attrs, f"{self.path}", keys=("time_unit",)
        )
        if stated is not None and in_file is not None and stated != in_file:
            raise FormatError(
                f"{self.path}: time_unit={stated!r} contradicts the unit the file states ({in_file!r})"
            )
        if stated not in (None, "us") and in_file is None and self._written_here() and column.dtype.kind in "iu":
            raise FormatError(
                f"{self.path}: time_unit={stated!r} contradicts the file's layout: H5Writer (attribute "
                "layout='dsec') stores integer µs; leave time_unit out"
            )
        unit = stated or in_file
        self._unit_stated = unit is not None     # else integer times are µs by the layout, unstated
        if unit is None:
            if column.dtype.kind == "f":
                raise FormatError(
                    f"{self.path}: events/t holds {column.dtype} times and neither the file nor the caller "
                    "states their unit; pass time_unit='s', 'ms' or 'us' (cmax: --time-unit); "
                    "times are never guessed"
                )
            if column.dtype.kind not in "iu":
                raise FormatError(f"{self.path}: events/t must hold numbers, got dtype {column.dtype}")
            unit = "us"
        return unit

    def _written_here(self) -> bool:
        """Whether :class:`H5Writer` wrote the file (attribute ``layout='dsec'``, in every version; the
        ``unit`` attributes of ``events/t`` came later)."""
        layout = self._file.attrs.get("layout")
        if isinstance(layout, bytes):
            layout = layout.decode("utf-8", "replace")
        return isinstance(layout, str) and layout == "dsec"

    # -- metadata ---------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self._columns["t"].shape[0])

    @property
    def time_unit_assumed(self) -> bool:
        """Whether ``events/t`` is read as µs by the layout alone: neither the file (a unit attribute, or the
        ``layout='dsec'`` of :class:`H5Writer`, µs in every version) nor the caller states its unit."""
        return not self._unit_stated and not self._written_here()

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
            raw = self._columns["t"][row: row + 1]
        except H5_ERRORS as error:
            raise FormatError(f"{self.path}: cannot read events/t[{row}] ({error})") from None
        where = f"{self.path}: events/t"
        return int(add_offset(self._t_us(raw, where), self.t_offset_us, where)[0])

    def _t_us(self, raw: np.ndarray, where: str) -> np.ndarray:
        return times_to_us(raw, self.time_unit, where)

    def _require_events(self) -> None:
        if not len(self):
            raise ValueError(f"{self.path} holds no events")

    # -- reading ----------------------------------------------------------------------
    def _bisect_on_disk(self, t_rel: int, lo: int, hi: int) -> int:
        """First row in ``[lo, hi)`` with t >= t_rel (µs after t_offset), reading single rows until 4096 remain."""
        column, where = self._columns["t"], f"{self.path}: events/t"
        while hi - lo > 4096:
            mid = (lo + hi) // 2
            if int(self._t_us(column[mid: mid + 1], where)[0]) < t_rel:
                lo = mid + 1
            else:
                hi = mid
        return lo + int(np.searchsorted(self._t_us(column[lo:hi], where), t_rel, side="left"))

    def _index_row(self, t_rel: int, ceil: bool) -> tuple[int, int | None]:
        """``(row, k)``: the row ``ms_to_idx[k]`` with ``k`` the ms boundary at or before
        (``ceil``: at or after) ``t_rel``, so that every event before ``row`` is earlier than
        ``t_rel`` (or, with ``ceil``, every event from ``row`` on is not earlier). Outside the
        index's span the rows are bisected on disk and ``k`` is None (nothing to verify)."""
        index, n = self._ms_to_idx, len(self)
        if t_rel < 0:
            return (0, None) if index[0] == 0 else (self._bisect_on_disk(t_rel, 0, int(index[0])), None)
        k = -(-t_rel // 1000) if ceil else t_rel // 1000
        if k >= len(index):
            last = int(index[-1])
            return (n, None) if last == n else (self._bisect_on_disk(t_rel, last, n), None)
        return int(index[k]), k

    def _check_index(self, t: np.ndarray, first_row: int, row: int, k: int | None) -> None:
        """Check ``ms_to_idx[k] == row`` against the times ``t`` of rows from ``first_row``:
        the event before ``row`` is earlier than ``k`` ms, the event at ``row`` is not."""
        if k is None:
            return
        boundary = self.t_offset_us + 1000 * k
        before, at = row - 1 - first_row, row - first_row
        wrong = (0 <= before < t.size and t[before] >= boundary) or (0 <= at < t.size and t[at] < boundary)
        if wrong:
            shown = int(t[at]) if 0 <= at < t.size else int(t[before])
            raise FormatError(
                f"{self.path}: ms_to_idx disagrees with events/t: ms_to_idx[{k}] = {row}, but the first "
                f"event at or after {k} ms is elsewhere (events/t near row {row}: {shown - self.t_offset_us} µs "
                "after t_offset); the index is corrupt (read the file whole, or rewrite it)"
            )

    def _read(self, start: int, stop: int) -> Events:
        """Validated events of rows ``[start, stop)`` (already clipped), one h5py read per column."""
        check_event_count(stop - start, f"{self.path}: rows [{start}, {stop})")
        try:
            columns = {name: self._columns[name][start:stop] for name in "xytp"}
        except H5_ERRORS as error:
            raise FormatError(f"{self.path}: cannot read rows [{start}, {stop}) ({error})") from None
        return _checked_columns(
            columns, self.width, self.height, self.time_unit, self.t_offset_us, self._polarity,
            f"{self.path}: events/", start,
        )

    def read_rows(self, start: int, stop: int) -> Events:
        """Events ``start:stop`` by row index (clipped to the file's rows).

        Raises :class:`~cmax.events.EventLimitError` before reading when the
        rows exceed :data:`cmax.events.MAX_EVENTS`, and :class:`FormatError`
        when the stored rows are corrupt (undecodable chunks, coordinates
        outside the sensor, time going back or non-finite, polarity outside
        the stated encoding, int64 overflow with ``t_offset``).
        """
        start, stop = max(0, int(start)), min(len(self), int(stop))
        return self._read(start, max(start, stop))

    def window(self, t0_us: int, t1_us: int) -> Events:
        """Events with ``t0_us <= t < t1_us`` (absolute µs), reading only that slice.

        Times are integer µs (floats must be whole). The rows come from
        ``ms_to_idx`` (one read, one row of margin each side to check the index
        entries used). A window holding more than
        :data:`cmax.events.MAX_EVENTS` events raises
        :class:`~cmax.events.EventLimitError` before anything is read; iterate
        over :meth:`windows` of a shorter duration instead.
        """
        t0_us, t1_us = check_time_us("t0_us", t0_us), check_time_us("t1_us", t1_us)
        if t1_us < t0_us:
            raise ValueError(f"t1_us ({t1_us}) must not be smaller than t0_us ({t0_us})")
        t0_rel = min(max(t0_us - self.t_offset_us, _INT64_MIN), _INT64_MAX)
        t1_rel = min(max(t1_us - self.t_offset_us, _INT64_MIN), _INT64_MAX)
        n = len(self)
        try:
            if self._ms_to_idx is None or not n:
                return self.read_rows(self._bisect_on_disk(t0_rel, 0, n), self._bisect_on_disk(t1_rel, 0, n))
            (lo, k0), (hi, k1) = self._index_row(t0_rel, False), self._index_row(t1_rel, True)
        except H5_ERRORS as error:
            raise FormatError(f"{self.path}: cannot search events/t ({error})") from None
        hi = max(hi, lo)
        check_event_count(hi - lo, f"{self.path}: the window [{t0_us}, {t1_us}) µs")
        first = max(lo - 1, 0)
        events = self._read(first, min(hi + 1, n))
        self._check_index(events.t, first, lo, k0)
        self._check_index(events.t, first, hi, k1)
        return events.slice_time(t0_us, t1_us)

    def read(self) -> Events:
        """All events (loads the whole file)."""
        return self.read_rows(0, len(self))

    def windows(self, duration_us: int, *, step_us: int | None = None) -> Iterator[Events]:
        """Consecutive windows of ``duration_us`` [µs] from the first event, starting every ``step_us`` [µs]
        (default: ``duration_us``)."""
        duration, step = window_steps(duration_us, step_us)
        if not len(self):
            return
        start, end = self.t_start, self.t_end
        while start <= end:
            yield self.window(start, start + duration)
            start += step

    def close(self) -> None:
        """Close the file (also on leaving a ``with`` block)."""
        self._file.close()

    def __enter__(self) -> "H5Reader":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"H5Reader({str(self.path)!r}, n={len(self)}, sensor={self.width}x{self.height})"


def _checked_columns(
    columns: dict[str, np.ndarray], width: int, height: int, time_unit: str, t_offset_us: int,
    polarity: str, where: str, first_row: int = 0,
) -> Events:
    """:class:`Events` from raw file columns, checked in min/max and order passes (no sort, no copy
    of columns already of the container's dtypes; ``t`` converted once and offset in place)."""
    x = _checked_coordinate(columns["x"], width, where, "x", "width", first_row)
    y = _checked_coordinate(columns["y"], height, where, "y", "height", first_row)
    p = polarity_01(columns["p"], polarity, where + "p")
    t = times_to_us(columns["t"], time_unit, where + "t")
    check_offset(t, t_offset_us, where + "t")
    _sorted_plus_offset(t, t_offset_us, where + "t", first_row)
    if not x.size == y.size == t.size == p.size:
        raise FormatError(f"{where}x/y/t/p differ in length")
    return Events._trusted(x, y, t, p, width, height)


def _checked_coordinate(
    values: np.ndarray, size: int, where: str, name: str, size_name: str, first_row: int
) -> np.ndarray:
    """A coordinate column as uint16 within ``[0, size)``; FormatError naming the first bad row."""
    if values.dtype.kind not in "iu":
        raise FormatError(f"{where}{name} must hold integer pixels, got dtype {values.dtype}")
    if not values.size:
        return values.astype(np.uint16)
    low = 0 if values.dtype.kind == "u" else int(values.min())  # one pass for unsigned columns
    if low < 0 or int(values.max()) >= size:
        bad = int(np.flatnonzero((values < 0) | (values >= size))[0])
        raise FormatError(
            f"{where}{name}: corrupt events at row {first_row + bad}: {name} must lie in [0, {size_name}={size}), "
            f"got {values[bad]}"
        )
    return values if values.dtype == np.uint16 else values.astype(np.uint16)


_SORT_BLOCK = 1 << 16


#: What a time going back in a DSEC-layout file leaves the user to do (``--sort`` is refused for it).
_UNSORTED_WAY_OUT = ("; DSEC-layout files are read a time span at a time, so their rows must be in time order and "
                     "--sort does not apply: write a copy whose events/x, y, t, p are each reordered by "
                     "np.argsort(t, kind='stable') (cmax.io.write_h5 of cmax.Events(..., sort=True) writes one)")


def _sorted_plus_offset(t: np.ndarray, offset: int, where: str, first_row: int) -> None:
    """Check that int64 ``t`` never decreases and add ``offset`` in place, block by block so that
    each block is compared and shifted while in cache. The caller has checked that the first and
    last times plus ``offset`` fit into int64 (enough once the order holds; on disorder this raises
    before any out-of-order value escapes)."""
    n, shift = t.size, np.int64(offset)
    back = np.empty(min(n, _SORT_BLOCK), bool)
    for start in range(0, n, _SORT_BLOCK):
        stop = min(start + _SORT_BLOCK, n)
        after = t[start + 1: stop + 1]  # one more than the block: the pair across the boundary
        went_back = np.less(after, t[start: start + after.size], out=back[: after.size])
        if went_back.any():
            i = start + int(np.flatnonzero(went_back)[0])
            wrapped = _UNSORTED_WAY_OUT if wrap_index(t[i: i + 2]) is None else (
                f"; a drop of {(int(t[i]) - int(t[i + 1])) / 60e6:.1f} min from near 2**32 µs: a uint32 microsecond "
                "clock that wrapped at 2**32 µs (71.6 min), not events out of order; unwrap the times: t = "
                "t.astype(np.int64) + 2**32 * np.cumsum(np.r_[0, np.diff(t.astype(np.int64)) < -2**31])")
            raise FormatError(
                f"{where}: corrupt events at row {first_row + i + 1}: t must be sorted in non-decreasing order "
                f"({int(t[i + 1])} µs comes after {int(t[i])} µs, before t_offset){wrapped}"
            )
        if shift:
            t[start:stop] += shift


class _FractionalOffset(Exception):
    """A float ``t_offset`` with a fraction, read where no unit is stated (see :func:`_fractional_float`)."""

    def __init__(self, value: Any) -> None:
        super().__init__(value)
        self.value = float(np.asarray(value).reshape(()))


def _fractional_float(value: Any) -> bool:
    """Whether a stored ``t_offset`` is one finite float with a fraction: not whole µs, the layout's unit, so
    it cannot be read without a stated unit (seconds, as a re-export may store them, read as µs would be 10^6
    too small). A whole float (1.6e15) is µs as an integer would be; other shapes are left to
    :func:`~cmax.io._checks.scalar_to_us`."""
    array = np.asarray(value)
    if array.size != 1 or array.dtype.kind != "f":
        return False
    number = float(array.reshape(()))
    return bool(np.isfinite(number)) and not number.is_integer()


#: A whole float ``t_offset`` at least this large (in magnitude) lies past the year 2103 as milliseconds (and
#: seconds) since 1970, so of the units a file may state only µs can be meant (1.6e15: 2020 as µs since 1970).
_ONLY_MICROSECONDS = 4.2e12


def _check_unstated_offset(value: Any, path: Path) -> None:
    """Refuse a ``t_offset`` whose unit neither it, the file nor the caller states where µs (DSEC's int64 scalar,
    the layout's unit) is not the only reading: a negative one (DSEC's is never: the events would lie before the
    clock's zero; an offset meant to be subtracted?), or a whole float other than 0 below
    :data:`_ONLY_MICROSECONDS` (1600000000.0 is 2020 as seconds since 1970 and 26.7 min as µs). ``value``: the
    stored scalar; ``path`` names the file. Fractional floats are refused before (:class:`_FractionalOffset`);
    integers of 0 and above, 0.0 and whole floats from 4.2e12 on are read as µs."""
    array = np.asarray(value)
    if array.size != 1 or array.dtype.kind not in "iuf":
        return                                            # other shapes and kinds: scalar_to_us refuses them
    number = array.reshape(()).item()
    if array.dtype.kind == "f" and not np.isfinite(number):
        return                                            # NaN / inf: times_to_us names them
    way = ("state it with a 'unit' attribute on t_offset ('us', 's' or 'ms'; cmax.io.write_h5 writes 'us'), or "
           "time_unit= (cmax: --time-unit) when events/t has the same unit")
    if number < 0:
        raise FormatError(
            f"{path}: t_offset is {number!r}, negative, and neither t_offset, the file nor the caller states its "
            "unit: DSEC's t_offset is the int64 µs added to events/t for absolute times, never negative (the "
            "events would lie before the clock's zero: an offset meant to be subtracted?); if the absolute times "
            f"really are events/t plus {number!r} µs, {way}")
    if array.dtype.kind == "f" and number != 0 and abs(number) < _ONLY_MICROSECONDS:
        raise FormatError(
            f"{path}: t_offset holds the float {number!r} and neither t_offset, the file nor the caller states its "
            f"unit, which a float leaves open (DSEC stores t_offset as an int64 of µs): read as µs it is "
            f"{number / 1e6:,.6f} s, read as seconds {number!r} s; {way}")


class _IndexOnDisk:
    """``ms_to_idx`` of a long recording (more than :data:`MAX_INDEX_IN_MEMORY` entries), read an entry at a time:
    ``index[k]`` (``k`` may be negative) is the row of the first event at or after ``k`` ms, checked to lie in
    ``[0, count]``; :meth:`H5Reader.window` checks the entries it uses against the times it reads."""

    def __init__(self, dataset: h5py.Dataset, count: int, path: Path) -> None:
        if dataset.dtype.kind not in "iu":
            raise FormatError(f"{path}: ms_to_idx must be a 1-D integer array, got {dataset.dtype} {dataset.shape}")
        self._dataset, self._count, self._path, self._size = dataset, int(count), path, int(dataset.shape[0])

    def __len__(self) -> int:
        return self._size

    def __getitem__(self, k: int) -> int:
        k = int(k) + (self._size if k < 0 else 0)
        value = int(self._dataset[k])
        if not 0 <= value <= self._count:
            raise FormatError(f"{self._path}: corrupt ms_to_idx (entry {k} is {value}, not a row index in "
                              f"[0, {self._count}])")
        return value


def _checked_ms_to_idx(ms_to_idx: np.ndarray, count: int, path: Path) -> np.ndarray:
    """``ms_to_idx`` as int64 after checking it: 1-D, non-decreasing, within ``[0, count]``."""
    if ms_to_idx.ndim != 1 or ms_to_idx.dtype.kind not in "iu":
        raise FormatError(f"{path}: ms_to_idx must be a 1-D integer array, got {ms_to_idx.dtype} {ms_to_idx.shape}")
    if not ms_to_idx.size:
        raise FormatError(f"{path}: ms_to_idx is empty (the layout has at least one entry)")
    if int(ms_to_idx.min()) < 0 or int(ms_to_idx.max()) > count or np.any(
        np.diff(ms_to_idx.astype(np.int64)) < 0
    ):
        raise FormatError(
            f"{path}: corrupt ms_to_idx (entries must be non-decreasing row indices in [0, {count}])"
        )
    return ms_to_idx.astype(np.int64)


def read_h5(
    path: str | os.PathLike, *, width: int | None = None, height: int | None = None,
    t0_us: int | None = None, t1_us: int | None = None, time_unit: str | None = None,
    polarity: str = "01",
) -> Events:
    """Read the DSEC-layout file at ``path``, whole or the window ``[t0_us, t1_us)`` [µs].

    ``width``, ``height`` [px]: for a file that stores no sensor size (DSEC as shipped: 640 x 480);
    ``time_unit`` and ``polarity`` as for :class:`H5Reader` (float times need a
    stated unit; polarity is never mapped silently).
    """
    with H5Reader(path, width=width, height=height, time_unit=time_unit, polarity=polarity) as reader:
        if t0_us is None and t1_us is None:
            return reader.read()
        return reader.window(
            -(2**62) if t0_us is None else t0_us, 2**62 if t1_us is None else t1_us
        )
