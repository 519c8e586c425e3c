"""The finished chunks of a long video's conversion, kept on disk as it goes, so that a killed ``cmax simulate``
loses at most the chunk it was simulating and the next run continues it, with the same events, bit for bit.

Beside the output ``<name>.h5`` the folder ``.<name>.h5.chunks/`` holds ``run.json`` (what the conversion is: the
source's signature with the SHA-256 of its bytes, the settings, the digest of cmax's code; :mod:`cmax.io.window_store`)
and, per chunk of
``chunk_frames`` video frames:

* ``chunk_<k>.events``: the chunk's events in time order, as blocks of at most :data:`BLOCK_EVENTS` events:
  a header of two little-endian int64 (the block's events ``n``, its compressed bytes), then, deflated (zlib
  format; ISA-L's where installed), the columns ``x`` (n,) uint16, ``y`` (n,) uint16, ``dt`` (n,) int64 (each
  time [µs] minus the one before; the first one's minus 0) as its 8 byte planes (8, n) uint8, least significant
  first, and ``p`` (n,) int8, little-endian;
* ``chunk_<k>.state.npz``: what the conversion carries into the next chunk: the simulator's state
  (:meth:`cmax.sim.esim.EventSimulator.state`: reference log intensity, last-crossing times, thresholds, the
  noise generator; several bytes a pixel, so it is kept for the last :data:`KEPT_STATES` chunks only); the
  adaptive sampler restarts from the chunk's last video frame, decoded again;
* ``chunk_<k>.json``, written last: the run's digest, the chunk's video frames ``[first_frame, end_frame)``, the
  counts so far (samples, capped intervals), the first and last frame times [µs], the SHA-256 of the last video
  frame's pixels, of all the chunk's frames (times and pixels: a resumed conversion decodes them again and
  compares, so a video replaced by another of the same size and modification time is not continued) and of both
  files, and whether it is the final chunk (the source ended).

Every file is written atomically (:mod:`cmax.io.atomic`), the record last, so a chunk with a record is complete.
A conversion holds the lock ``.<name>.h5.chunks.lock`` (beside the folder) while it runs, so a second conversion
into the same output fails at once rather than sharing the chunks.
A resumed conversion takes the chunks in order while each one's record names this run and the next frame, and
its files have the recorded SHA-256; the first that fails (and every later one) is removed and simulated
again, from the last chunk before it whose state is kept (the first frame when none is). A folder of another
run (another source, other settings, other code) is refused, or removed when the caller asks to start over.
The folder is removed once the output is complete.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import re
import shutil
import zlib
from pathlib import Path
from typing import Iterator

import numpy as np

from cmax.events import Events
from cmax.io.atomic import AtomicOutput, file_sha256, fsync_folder, write_bytes_atomic, write_error, \
    write_text_atomic
from cmax.io.window_store import run_differences, run_digest, write_run_record

try:    # ISA-L's deflate and inflate: the zlib format, several times faster (a dependency where it has wheels)
    from isal import isal_zlib as _deflate
except ImportError:  # pragma: no cover - machines without isal wheels
    _deflate = zlib

__all__ = ["DEFAULT_CHUNK_FRAMES", "KEPT_MODES", "KEPT_STATES", "KeptChunks", "ChunkWriter", "chunk_folder", "frame_digest",
           "kept_problem", "remove_chunk_folder", "written_from_chunks"]

#: Video frames per kept chunk by default (10 s of a 30 frames/s video).
DEFAULT_CHUNK_FRAMES = 300
#: What a conversion does with kept chunks: take them (another run's: ValueError), take them (another run's:
#: removed), or remove them all and start from the first frame.
KEPT_MODES = ("resume", "resume_or_restart", "restart")
#: Chunks whose simulator state is kept (the last ones): a resumed run continues from the last of them that
#: passes its check; a damaged chunk before them is simulated again from the first frame.
KEPT_STATES = 2
_RUN_FILE = "run.json"
_RECORD = re.compile(r"chunk_(\d{6})\.json")
#: Most events in one compressed block of a chunk's events file.
BLOCK_EVENTS = 1 << 18
_HEADER = np.dtype("<i8")
_COLUMNS = (("x", np.dtype("<u2")), ("y", np.dtype("<u2")), ("t", np.dtype("<i8")), ("p", np.dtype("i1")))


def _pack(columns: dict[str, np.ndarray]) -> bytes:
    """The bytes of a block's columns (``t`` already as differences): ``dt`` as byte planes, which deflate far
    better than whole int64 values (their high bytes are zero)."""
    parts = []
    for name, dtype in _COLUMNS:
        column = np.ascontiguousarray(columns[name], dtype)
        if name == "t":
            column = np.ascontiguousarray(column.view(np.uint8).reshape(-1, dtype.itemsize).T)
        parts.append(column.tobytes())
    return b"".join(parts)


def _unpack(data: bytes, n: int) -> list[np.ndarray]:
    """The columns ``x``, ``y``, ``dt``, ``p`` (n,) of a block's bytes (:func:`_pack`), native byte order."""
    columns, offset = [], 0
    for name, dtype in _COLUMNS:
        if name == "t":
            planes = np.frombuffer(data, np.uint8, n * dtype.itemsize, offset).reshape(dtype.itemsize, n)
            column = np.ascontiguousarray(planes.T).view(dtype).ravel()
        else:
            column = np.frombuffer(data, dtype, n, offset)
        columns.append(column.astype(dtype.newbyteorder("=")))
        offset += n * dtype.itemsize
    return columns


def chunk_folder(output: str | os.PathLike) -> Path:
    """The folder of the kept chunks of the conversion into ``output`` (``.<name>.h5.chunks`` beside it).

    Parameters
    ----------
    output : path
        The conversion's output file.

    >>> chunk_folder("out/a.h5").as_posix()
    'out/.a.h5.chunks'
    """
    output = Path(output)
    return output.with_name(f".{output.name}.chunks")


def frame_digest(frame: np.ndarray) -> str:
    """SHA-256 (hex) of a frame's shape, dtype and pixels: a resumed conversion checks that the video frame it
    decodes again is the one the chunk ended on.

    Parameters
    ----------
    frame : ndarray, shape (H, W) or (H, W, 3)
        A decoded video frame.
    """
    array = np.ascontiguousarray(frame)
    return hashlib.sha256(f"{array.shape}{array.dtype.str}".encode() + array.tobytes()).hexdigest()


def kept_problem(output: str | os.PathLike, run: dict) -> str | None:
    """Why the chunks kept beside ``output`` cannot be continued by the conversion ``run`` (one line naming each
    difference: another source, other settings, other code), or None when they can (or there are none).

    Parameters
    ----------
    output : path
        The conversion's output file.
    run : dict
        What the new conversion is (as ``run.json`` records it).
    """
    folder = chunk_folder(output)
    if not folder.is_dir() or not any(_RECORD.fullmatch(path.name) for path in folder.iterdir()):
        return None
    try:
        recorded = json.loads((folder / _RUN_FILE).read_text())
    except (OSError, ValueError):
        recorded = None
    if not isinstance(recorded, dict):
        return (f"{folder / _RUN_FILE} is missing or unreadable, so the chunks kept in {folder} cannot be checked: "
                "pass --overwrite (kept='resume_or_restart') to start over")
    differences = run_differences(recorded, run)
    if not differences:
        return None
    return (f"cannot resume the conversion kept in {folder}: it was another run (" + "; ".join(differences)
            + "): give the same video and options, or --overwrite (kept='resume_or_restart') to start over")


def remove_chunk_folder(output: str | os.PathLike) -> None:
    """Remove the chunks kept beside ``output`` (:func:`chunk_folder`): the folder is first renamed to
    ``.<name>.h5.chunks.removed`` (one step) and then deleted, so that a removal cut short (Ctrl-C, a kill) never
    leaves a part of it to be read as kept chunks (a folder without its ``run.json`` is refused); a ``.removed``
    folder left by such a removal is deleted too.

    Parameters
    ----------
    output : path
        The conversion's output file.
    """
    folder = chunk_folder(output)
    removed = folder.with_name(folder.name + ".removed")
    shutil.rmtree(removed, ignore_errors=True)
    try:
        os.rename(folder, removed)
    except FileNotFoundError:
        pass
    except OSError:       # cannot rename (a file system's limits): removed in place
        removed = folder
    shutil.rmtree(removed, ignore_errors=True)
    fsync_folder(folder.parent)


def written_from_chunks(output: str | os.PathLike, run: dict) -> bool:
    """Whether ``output`` is the file a conversion ``run`` wrote from the chunks kept beside it and was killed
    before recording (so it may be written again from them): the chunks are this run's (:func:`kept_problem`,
    each record naming the run's digest), they run from the first to the final one (the source ended), and
    ``output`` is a complete file of :class:`cmax.io.h5.H5Writer` holding as many events as they do, written by a
    conversion (its ``simulator`` attribute) from the chunks' first frame on (its ``t_offset``). A file of
    anyone else (a user's recording beside a stale chunk folder, another run's output) is not.

    Parameters
    ----------
    output : path
        The conversion's output file.
    run : dict
        What the conversion is (as ``run.json`` records it).
    """
    from cmax.io.h5 import verify_h5

    folder, digest, events = chunk_folder(output), run_digest(run), 0
    if not folder.is_dir() or kept_problem(output, run) is not None:
        return False
    for index in range(len(list(folder.glob("chunk_*.json")))):
        try:
            record = json.loads((folder / f"chunk_{index:06d}.json").read_text())
            if record["run"] != digest or record["index"] != index:
                return False
            events += int(record["events"])
            if record["final"] is True:
                verify_h5(output, events=events)
                return _written_by_cmax(output, int(record["first_t_us"]))
        except (OSError, ValueError, KeyError, TypeError):
            return False
    return False


def _written_by_cmax(output: Path, first_t_us: int) -> bool:
    """Whether the complete h5 file ``output`` was written by a conversion (its ``simulator`` attribute names
    cmax) whose first frame was at ``first_t_us`` [µs] (its ``t_offset``)."""
    import h5py

    with h5py.File(output, "r") as file:
        simulator = file.attrs.get("simulator")
        return (isinstance(simulator, str) and simulator.startswith("cmax ") and "t_offset" in file
                and int(file["t_offset"][()]) == first_t_us)


class KeptChunks:
    """The kept chunks of the conversion into ``output`` (see the module notes).

    Parameters
    ----------
    output : path
        The conversion's output file; the chunks are in :func:`chunk_folder` of it.
    run : dict
        What the conversion is, JSON-ready: ``{"source": signature, "settings": {...}, "code": digest, ...}``.
    kept : {"resume", "resume_or_restart", "restart"}
        See :data:`KEPT_MODES`.

    Attributes
    ----------
    records : list of dict
        The verified chunks, in order (empty when there is nothing to resume).
    redone : int
        Chunks found that failed their check (removed, to be simulated again).

    Raises
    ------
    ValueError
        ``kept="resume"`` and the folder holds chunks of another run (the message names each difference), or its
        ``run.json`` is unreadable.
    """

    def __init__(self, output: str | os.PathLike, run: dict, *, kept: str = "resume") -> None:
        if kept not in KEPT_MODES:
            raise ValueError(f"kept must be one of {', '.join(KEPT_MODES)}, got {kept!r}")
        self.folder, self.output = chunk_folder(output), Path(output)
        self.run, self.digest = run, run_digest(run)
        self.records: list[dict] = []
        self.redone = 0
        if not self.folder.is_dir():
            return
        problem = None if kept == "restart" else kept_problem(output, run)
        if kept == "restart" or (problem is not None and kept == "resume_or_restart"):
            self.remove()
        elif problem is not None:
            raise ValueError(problem)
        else:
            self.records = self._verified()

    # -- reading ----------------------------------------------------------------------------
    def _verified(self) -> list[dict]:
        """The chunks that pass their check, in order from the first; the first that fails and all after it are
        removed (counted in :attr:`redone`)."""
        records: list[dict] = []
        for index in range(len(list(self.folder.glob("chunk_*.json")))):
            record = self._record(index, records[-1] if records else None)
            if record is None:
                break
            records.append(record)
            if record["final"]:
                break
        if records and not records[-1]["final"]:    # continued from the last chunk whose state is kept
            while records and not self._state_path(len(records) - 1).is_file():
                records.pop()
        for path in sorted(self.folder.iterdir()):
            match = _RECORD.fullmatch(path.name)
            if match and int(match.group(1)) >= len(records):
                self.redone += 1
                for stale in (path, self._events_path(int(match.group(1))), self._state_path(int(match.group(1)))):
                    stale.unlink(missing_ok=True)
        if not records:      # nothing to continue from (perhaps a killed writer's temporaries): start afresh
            self.remove()
        return records

    def _record(self, index: int, previous: dict | None) -> dict | None:
        """The record of chunk ``index`` if the chunk passes its check (it follows ``previous``), else None."""
        try:
            record = json.loads((self.folder / f"chunk_{index:06d}.json").read_text())
            first = 0 if previous is None else previous["end_frame"]
            if (record["run"] != self.digest or record["index"] != index or record["first_frame"] != first
                    or record["end_frame"] < first or not isinstance(record["final"], bool)):
                return None
            state = self._state_path(index)       # kept for the last KEPT_STATES chunks only
            if (file_sha256(self._events_path(index)) != record["events_sha256"]
                    or (os.path.lexists(state) and file_sha256(state) != record["state_sha256"])):
                return None
        except (OSError, ValueError, KeyError, TypeError):
            return None
        return record

    @property
    def frames(self) -> int:
        """Video frames the verified chunks cover (0 when none)."""
        return self.records[-1]["end_frame"] if self.records else 0

    @property
    def events(self) -> int:
        """Events the verified chunks hold."""
        return sum(record["events"] for record in self.records)

    def state(self) -> dict[str, np.ndarray]:
        """The simulator's state after the last verified chunk (:meth:`cmax.sim.esim.EventSimulator.restore`)."""
        with np.load(self._state_path(len(self.records) - 1), allow_pickle=False) as saved:
            return {name: saved[name] for name in saved.files}

    def iter_events(self, width: int, height: int) -> Iterator[Events]:
        """The events of the verified chunks, in order, a block (at most :data:`BLOCK_EVENTS`) at a time.

        Parameters
        ----------
        width, height : int
            The sensor's size [px].
        """
        for index in range(len(self.records)):
            last_t = 0
            with open(self._events_path(index), "rb") as file:
                while header := file.read(2 * _HEADER.itemsize):
                    n, size = (int(v) for v in np.frombuffer(header, _HEADER))
                    columns = _unpack(_deflate.decompress(file.read(size)), n)
                    columns[2] = last_t + np.cumsum(columns[2])
                    last_t = int(columns[2][-1])
                    yield Events._trusted(*columns, width, height)

    # -- writing ----------------------------------------------------------------------------
    def _events_path(self, index: int) -> Path:
        return self.folder / f"chunk_{index:06d}.events"

    def _state_path(self, index: int) -> Path:
        return self.folder / f"chunk_{index:06d}.state.npz"

    def open_chunk(self) -> "ChunkWriter":
        """A writer of the next chunk's events (its file is written to a private temporary until
        :meth:`save`)."""
        write_run_record(self.folder, self.run)       # with the first chunk: what the run is
        return ChunkWriter(self._events_path(len(self.records)), self.output)

    def save(self, writer: "ChunkWriter", state: dict[str, np.ndarray], record: dict) -> dict:
        """Keep the chunk whose events ``writer`` holds, with the simulator's ``state`` after it; ``record`` holds
        its frames and counts (``end_frame``, ``samples``, ``capped``, ``first_t_us``, ``last_t_us``,
        ``frame_sha256``, ``frames_sha256``, ``final``, ``width``, ``height``). Returns the full record, written last."""
        index = len(self.records)
        events_sha = writer.commit()
        buffer = io.BytesIO()
        np.savez(buffer, **state)
        state_bytes = buffer.getvalue()
        write_bytes_atomic(self._state_path(index), state_bytes)
        full = dict(record, run=self.digest, index=index, first_frame=self.frames, events=writer.count,
                    events_sha256=events_sha, state_sha256=hashlib.sha256(state_bytes).hexdigest())
        write_text_atomic(self.folder / f"chunk_{index:06d}.json", json.dumps(full, indent=1))
        self.records.append(full)
        if index >= KEPT_STATES:                   # a state as large as a few frames: the last ones are enough
            self._state_path(index - KEPT_STATES).unlink(missing_ok=True)
        return full

    def remove(self) -> None:
        """Remove the folder (the output is complete, or the run starts over): :func:`remove_chunk_folder`."""
        remove_chunk_folder(self.output)


class ChunkWriter:
    """The events of one chunk, compressed block by block into a private temporary file
    (:class:`cmax.io.atomic.AtomicOutput`) as they come, renamed by :meth:`commit`; :meth:`abort` removes it.

    Parameters
    ----------
    path : path
        The chunk's events file.
    output : path
        The conversion's output, named in errors (a full disk, a file-size limit).
    """

    def __init__(self, path: Path, output: Path) -> None:
        self.output = output
        self._file = AtomicOutput(path, overwrite=True)
        self._digest = hashlib.sha256()
        self._pending: list[Events] = []
        self._buffered = self.count = 0
        self._last_t = 0

    def append(self, events: Events) -> None:
        """Append ``events`` (in time order after those appended so far)."""
        if len(events):
            self._pending.append(events)
            self._buffered += len(events)
            self.count += len(events)
            if self._buffered >= BLOCK_EVENTS:
                self._flush()

    def _flush(self) -> None:
        """Write the pending events as one compressed block."""
        if not self._buffered:
            return
        columns = {name: np.concatenate([getattr(events, name) for events in self._pending]) for name in "xytp"}
        t = columns["t"]
        columns["t"] = np.diff(t, prepend=np.int64(self._last_t))
        self._last_t = int(t[-1])
        data = _deflate.compress(_pack(columns), 1)
        block = np.array([self._buffered, len(data)], _HEADER).tobytes() + data
        self._pending, self._buffered = [], 0
        try:
            self._file.write(block)
        except OSError as error:
            self.abort()
            raise self._error(error) from None
        self._digest.update(block)

    def _error(self, error: OSError) -> OSError:
        """``error`` naming the output whose chunk could not be written."""
        return write_error(error, self.output, f"keeping a chunk of it ({self._file.path.name} in "
                                               f"{self._file.path.parent})")

    def commit(self) -> str:
        """Write what is pending and rename the file into place; returns its SHA-256 (hex)."""
        self._flush()
        try:
            self._file.commit()
        except OSError as error:
            raise self._error(error) from None
        return self._digest.hexdigest()

    def abort(self) -> None:
        """Remove the temporary file (the chunk is not kept)."""
        self._file.abort()
