"""Reader of iniVation AEDAT 4.0 files (DV software; DAVIS and DVXplorer cameras).

Layout of a file, as read here (all integers little-endian):

1. the 14-byte magic ``#!AER-DAT4.0\\r\\n``;
2. an ``int32`` size and that many bytes of a FlatBuffer ``IOHeader``
   (identifier ``IOHE``): ``compression`` (int32: 0 none, 1 LZ4, 2 LZ4 high,
   3 Zstd, 4 Zstd high), ``dataTablePosition`` (int64, -1 if none) and
   ``infoNode``, an XML document with one node per stream (``typeIdentifier``
   ``EVTS``, ``FRME``, ``IMUS``, ``TRIG``; ``originalOutputName``; an ``info``
   node with ``sizeX``/``sizeY`` for cameras);
3. packets, each an 8-byte header (``int32`` stream id, ``int32`` size) and
   ``size`` bytes of a compressed, size-prefixed FlatBuffer whose identifier
   is the stream's type identifier;
4. optionally a compressed ``FileDataTable`` (identifier ``FTAB``) indexing the
   packets.

Packets are walked from the header on. The header's ``dataTablePosition`` is
not trusted to end the walk (the DAVIS346 recording in the test data declares
it 1,024 bytes before the table really starts, inside the last event packet):
the walk ends where the bytes decode as the ``FTAB`` index, or at the end of
the file when the header declares no index. A file that declares an index but
ends without one is truncated and raises :class:`FormatError`. Only the packets
of the stream asked for are decompressed and checked.

The FlatBuffers are decoded by hand, bounds-checked and never past the buffer
(:mod:`cmax.io._flatbuffers` describes their layout). Events are a
vector of 16-byte structs (``int64 t``, ``int16 x``, ``int16 y``, ``bool on``,
3 bytes of padding) decoded with one :func:`numpy.frombuffer` per packet; IMU
samples are a vector of tables, decoded with numpy gathers (no loop over
samples).

Time stamps are returned as the file stores them: int64 microseconds since the
Unix epoch (DV adds the camera's ``tsOffset`` before writing).

References
----------
iniVation, "AEDAT 4.0" file format and the dv-processing FlatBuffer schemas
(``IOHeader``, ``EventPacket``, ``IMUPacket``, ``Frame``, ``FileDataTable``).
FlatBuffers documentation, "FlatBuffer Internals" (the binary layout).
"""
from __future__ import annotations

import os
import struct
import warnings
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from cmax.events import Events, _check_sensor_size, check_event_count
from cmax.io._flatbuffers import _Flatbuffer, _table_vector
from cmax.io.errors import FormatError

__all__ = [
    "Aedat4Stream",
    "ApsFrames",
    "ImuSamples",
    "aedat4_streams",
    "read_aedat4",
    "read_aedat4_frames",
    "read_aedat4_imu",
]

MAGIC = b"#!AER-DAT4.0\r\n"
_COMPRESSIONS = {0: "none", 1: "lz4", 2: "lz4_high", 3: "zstd", 4: "zstd_high"}

#: One AEDAT4 event (flatbuffer struct ``Event``): 16 bytes with 3 of padding.
_EVENT_DTYPE = np.dtype(
    {"names": ["t", "x", "y", "p"], "formats": ["<i8", "<i2", "<i2", "u1"],
     "offsets": [0, 8, 10, 12], "itemsize": 16}
)
#: Fields of the ``IMU`` table in schema order: (name, dtype).
_IMU_FIELDS = (
    ("t", "<i8"), ("temperature", "<f4"),
    ("ax", "<f4"), ("ay", "<f4"), ("az", "<f4"),
    ("gx", "<f4"), ("gy", "<f4"), ("gz", "<f4"),
    ("mx", "<f4"), ("my", "<f4"), ("mz", "<f4"),
)


@dataclass(frozen=True)
class Aedat4Stream:
    """One stream (DV output) of an AEDAT4 file, from the header's XML.

    ``id`` is the stream id of its packets; ``type_identifier`` one of
    ``"EVTS"``, ``"FRME"``, ``"IMUS"``, ``"TRIG"`` (others are listed but not
    decoded); ``name`` the DV output name (e.g. ``"events"``); ``width`` and
    ``height`` the sensor size in pixels (``None`` for IMU and trigger streams);
    ``compression`` the file's packet compression (``"none"``, ``"lz4"``,
    ``"lz4_high"``, ``"zstd"``, ``"zstd_high"``); ``source`` the camera.
    """

    id: int
    type_identifier: str
    name: str
    width: int | None
    height: int | None
    compression: str
    description: str = ""
    source: str = ""


@dataclass(frozen=True, eq=False)
class ImuSamples:
    """N inertial samples of an AEDAT4 ``IMUS`` stream, in file order.

    Attributes
    ----------
    t : ndarray, shape (N,), int64
        Time stamps in microseconds (Unix epoch, as stored).
    accelerometer : ndarray, shape (N, 3), float32
        Acceleration (x, y, z) in g (9.81 m/s²), as stored.
    gyroscope : ndarray, shape (N, 3), float32
        Angular velocity (x, y, z) in degrees per second, as stored.
    temperature : ndarray, shape (N,), float32
        IMU temperature in degrees Celsius.
    magnetometer : ndarray, shape (N, 3), float32, or None
        Magnetic field in µT; ``None`` when no sample carries one (DAVIS).
    """

    t: np.ndarray
    accelerometer: np.ndarray
    gyroscope: np.ndarray
    temperature: np.ndarray
    magnetometer: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.t.size)


@dataclass(frozen=True, eq=False)
class ApsFrames:
    """N intensity frames of an AEDAT4 ``FRME`` stream, in file order.

    Attributes
    ----------
    t : ndarray, shape (N,), int64
        The frame's time stamp in µs (DV's ``timestamp`` field; for DAVIS
        cameras the middle of the exposure).
    t_exposure_start, t_exposure_end : ndarray, shape (N,), int64
        Start and end of the exposure in µs.
    t_frame_start, t_frame_end : ndarray, shape (N,), int64
        Start and end of the frame's readout in µs.
    images : ndarray, shape (N, H, W) or (N, H, W, C), uint8 or uint16
        Pixels, row-major; C is 3 (BGR) or 4 (BGRA) for colour frames.
    origin : ndarray, shape (N, 2), int64
        ``(x, y)`` sensor pixel of each image's top-left corner (non-zero for
        a region of interest); images are not shifted or padded.
    """

    t: np.ndarray
    t_exposure_start: np.ndarray
    t_exposure_end: np.ndarray
    t_frame_start: np.ndarray
    t_frame_end: np.ndarray
    images: np.ndarray
    origin: np.ndarray

    def __len__(self) -> int:
        return int(self.t.size)


# -- container -------------------------------------------------------------------------
@dataclass(frozen=True)
class _File:
    where: str
    data: bytes
    compression: int
    streams: tuple[Aedat4Stream, ...]
    packets: tuple[tuple[int, int, int], ...]  # (stream id, body start, body size)


#: Most bytes a packet may decompress to per compressed byte. Event and IMU packets
#: of real recordings expand 2-5 times (16-byte events with varying time stamps cannot
#: shrink to a quarter of a byte); a packet claiming more is crafted or corrupt and is
#: refused before its output is allocated.
MAX_EXPANSION = 64
_SLACK = 1024  # plus this many bytes, for tiny packets


def _packet_limit(size: int, stream: Aedat4Stream | None = None) -> int:
    """Largest decompressed size accepted for a packet of ``size`` compressed bytes.

    Frame packets may also hold one uncompressed frame of the stream's sensor
    (up to 4 channels of 16 bits), however well a uniform image compresses.
    """
    limit = MAX_EXPANSION * int(size) + _SLACK
    if stream is not None and stream.type_identifier == "FRME":
        limit += 8 * (stream.width or 0) * (stream.height or 0)
    return limit


def _too_large(where: str, size: int, limit: int) -> FormatError:
    return FormatError(
        f"{where}: a packet of {size:,} compressed bytes decompresses to more than {limit:,} bytes "
        f"(over {MAX_EXPANSION}x; crafted or corrupt), refused before allocating"
    )


def _decompress(body: bytes | memoryview, compression: int, where: str, limit: int | None = None) -> bytes:
    """The decompressed bytes of one packet, refusing output beyond ``limit`` (default
    :func:`_packet_limit` of the body's size) without allocating it."""
    limit = _packet_limit(len(body)) if limit is None else int(limit)
    if compression == 0:
        return bytes(body)
    if compression in (1, 2):
        import lz4.frame

        decompressor = lz4.frame.LZ4FrameDecompressor()
        try:
            out = decompressor.decompress(body, max_length=limit)
        except Exception as error:  # lz4 raises RuntimeError on bad input
            raise FormatError(f"{where}: LZ4 decompression failed ({error})") from error
        if not decompressor.eof:
            if not decompressor.needs_input:
                raise _too_large(where, len(body), limit)
            raise FormatError(f"{where}: the LZ4 frame ends early (truncated)")
        if decompressor.unused_data:
            raise FormatError(f"{where}: {len(decompressor.unused_data)} bytes follow the LZ4 frame")
        return out
    if compression in (3, 4):
        try:
            import zstandard
        except ImportError as error:
            raise FormatError(
                f"{where}: the file is Zstd-compressed; install the 'zstandard' package to read it"
            ) from error
        try:
            declared = zstandard.frame_content_size(bytes(body))
            if declared > limit:
                raise _too_large(where, len(body), limit)
            return zstandard.ZstdDecompressor().decompress(bytes(body), max_output_size=limit)
        except zstandard.ZstdError as error:
            raise FormatError(f"{where}: Zstd decompression failed ({error})") from error
    raise FormatError(f"{where}: unknown compression code {compression}")


def _parse_info(xml: str, compression: int, where: str) -> tuple[Aedat4Stream, ...]:
    try:
        root = ElementTree.fromstring(xml)
    except ElementTree.ParseError as error:
        raise FormatError(
            f"{where}: the header's XML info node does not parse ({error})"
        ) from error
    out_info = next((n for n in root.iter("node") if n.get("name") == "outInfo"), None)
    if out_info is None:
        raise FormatError(f"{where}: the header's XML has no 'outInfo' node (the streams)")

    def attrs(node: ElementTree.Element) -> dict[str, str]:
        return {a.get("key", ""): (a.text or "") for a in node.findall("attr")}

    streams = []
    for node in out_info.findall("node"):
        name = node.get("name", "")
        if not name.isdigit():
            continue
        values = attrs(node)
        info_node = node.find("node[@name='info']")
        info = attrs(info_node) if info_node is not None else {}
        try:
            width = int(info["sizeX"]) if "sizeX" in info else None
            height = int(info["sizeY"]) if "sizeY" in info else None
        except ValueError as error:
            raise FormatError(f"{where}: stream {name} has a non-integer sizeX/sizeY") from error
        streams.append(Aedat4Stream(
            id=int(name), type_identifier=values.get("typeIdentifier", ""),
            name=values.get("originalOutputName", ""), width=width, height=height,
            compression=_COMPRESSIONS[compression], description=values.get("typeDescription", ""),
            source=info.get("source", ""),
        ))
    if not streams:
        raise FormatError(f"{where}: the header's XML describes no streams")
    return tuple(streams)


def _read_header(data: bytes, where: str) -> tuple[int, int, tuple[Aedat4Stream, ...], int]:
    """``(compression, data table position, streams, first packet byte)``."""
    if not data.startswith(MAGIC):
        found = data[: len(MAGIC)]
        raise FormatError(
            f"{where}: not an AEDAT 4.0 file (starts with {found!r}, expected {MAGIC!r})"
        )
    if len(data) < len(MAGIC) + 4:
        raise FormatError(f"{where}: truncated inside the header size")
    (size,) = struct.unpack_from("<i", data, len(MAGIC))
    end = len(MAGIC) + 4 + size
    if size < 12 or end > len(data):
        raise FormatError(
            f"{where}: the header claims {size} bytes but the file has "
            f"{len(data) - len(MAGIC) - 4} after the size (truncated or corrupt)"
        )
    fb = _Flatbuffer(
        data[len(MAGIC) + 4: end], b"IOHE", f"{where} (IOHeader)", size_prefixed=False
    )
    compression = fb.scalar(fb.root, 0, "<i", 0)
    table_position = fb.scalar(fb.root, 1, "<q", -1)
    if compression not in _COMPRESSIONS:
        fb.fail(f"unknown compression code {compression}")
    start, length = fb.vector(fb.root, 2)
    try:
        xml = bytes(fb.span(start, length)).decode("utf-8")
    except UnicodeDecodeError as error:
        raise FormatError(f"{where}: the header's XML info node is not UTF-8") from error
    return compression, table_position, _parse_info(xml, compression, where), end


def _is_data_table(data: bytes, pos: int, compression: int, where: str) -> bool:
    try:
        table = _decompress(memoryview(data)[pos:], compression, where)
    except FormatError:
        return False
    return table[8:12] == b"FTAB" or table[4:8] == b"FTAB"


def _open(path: str | os.PathLike) -> _File:
    where = os.fspath(path)
    data = Path(path).read_bytes()
    compression, table_position, streams, pos = _read_header(data, where)
    known = {stream.id for stream in streams}
    packets = []
    while pos < len(data):
        if len(data) - pos < 8:
            raise FormatError(f"{where}: truncated inside a packet header at byte {pos}")
        stream_id, size = struct.unpack_from("<ii", data, pos)
        if (pos == table_position or stream_id not in known) and _is_data_table(
            data, pos, compression, where
        ):
            return _File(where, data, compression, streams, tuple(packets))
        if stream_id not in known:
            raise FormatError(f"{where}: the bytes at {pos} are neither a packet of a stream the "
                              f"header describes (they name stream {stream_id}) nor a readable "
                              "packet index (truncated or corrupt)")
        if size <= 0 or pos + 8 + size > len(data):
            raise FormatError(f"{where}: the packet at byte {pos} claims {size} bytes; "
                              f"{len(data) - pos - 8} remain (truncated or corrupt)")
        packets.append((stream_id, pos + 8, size))
        pos += 8 + size
    if table_position >= 0:
        raise FormatError(f"{where}: the file ends at byte {len(data)} without the packet index "
                          f"its header declares (truncated)")
    return _File(where, data, compression, streams, tuple(packets))


def _select(file: _File, stream: int | str | None, kind: str) -> Aedat4Stream:
    candidates = [s for s in file.streams if s.type_identifier == kind]
    if stream is None:
        if not candidates:
            raise ValueError(f"{file.where} has no {kind} stream; it has "
                             f"{[(s.id, s.type_identifier, s.name) for s in file.streams]}")
        if len(candidates) > 1:   # two cameras (a stereo rig): the others' data would be left out unsaid
            warnings.warn(
                f"{file.where} holds {len(candidates)} {kind} streams {[(s.id, s.name) for s in candidates]}: "
                f"read the first, {candidates[0].id} {candidates[0].name!r}; pass stream= (an id or a name, "
                "e.g. cmax.io.read(path, stream=1)) to read another",
                UserWarning, stacklevel=3,
            )
        return candidates[0]
    if isinstance(stream, (bool, np.bool_)) or not isinstance(stream, (int, np.integer, str)):
        raise TypeError(f"stream must be a stream id (int), a name (str) or None, got {stream!r}")
    for s in candidates:
        if (s.name == stream) if isinstance(stream, str) else (s.id == int(stream)):
            return s
    raise ValueError(f"{file.where} has no {kind} stream {stream!r}; its {kind} streams are "
                     f"{[(s.id, s.name) for s in candidates]}")


def _bodies(file: _File, stream: Aedat4Stream) -> Iterator[tuple[int, _Flatbuffer]]:
    """``(packet byte, flatbuffer)`` of each packet of ``stream``, in file order."""
    identifier = stream.type_identifier.encode("ascii", "replace")
    for stream_id, start, size in file.packets:
        if stream_id != stream.id:
            continue
        where = f"{file.where} (packet at byte {start - 8})"
        body = _decompress(memoryview(file.data)[start: start + size], file.compression, where,
                           _packet_limit(size, stream))
        yield start - 8, _Flatbuffer(body, identifier, where)


def _check_order(t: np.ndarray, where: str, what: str, sort: bool) -> np.ndarray | None:
    """None if ``t`` is non-decreasing; the sorting permutation if ``sort``; else raise."""
    decreasing = np.flatnonzero(t[1:] < t[:-1])
    if not decreasing.size:
        return None
    if sort:
        return np.argsort(t, kind="stable")
    i = int(decreasing[0])
    raise FormatError(f"{where}: {what} time goes back ({t[i + 1]} µs after {t[i]} µs at index "
                      f"{i + 1}); pass sort=True to sort by time (cmax: --sort)")


def _check_epoch_times(t: np.ndarray, where: str, what: str) -> None:
    """Refuse times ``t`` (N,) int64 [µs since the Unix epoch, the unit AEDAT 4.0 states] that lie after the year
    2100 or before 1970 by as much: no DV recording holds them; integer nanoseconds since 1970 (about 1.7e18)
    written by another tool would read as the year 55,000, each interval 1000 times too long. ``what`` names the
    stream ("event", "IMU")."""
    if not t.size:
        return
    from cmax.io._checks import _YEAR_2100_US

    low, high = int(t.min()), int(t.max())
    worst = high if abs(high) >= abs(low) else low
    if abs(worst) < _YEAR_2100_US:
        return
    index = int(np.flatnonzero(t == worst)[0])
    seconds = worst / 1e9
    nanoseconds = (f"; these look like nanoseconds ({seconds:.3f} s since 1970 if so), which the tool that wrote "
                   "the file stored in place of µs: decode the file with that tool (or dv-processing) and convert "
                   "the times to integer µs (t // 1000)" if 1e8 <= seconds < 4.2e9 else
                   " (a corrupt packet?)")
    raise FormatError(f"{where}: {what} time {worst} µs at index {index} lies beyond the year 2100 as µs since the "
                      f"Unix epoch, the unit AEDAT 4.0 stores (DV writes no such time){nanoseconds}")


# -- public API ------------------------------------------------------------------------
def aedat4_streams(path: str | os.PathLike) -> list[Aedat4Stream]:
    """The streams of an AEDAT4 file, from its header (packets are not read).

    Parameters
    ----------
    path : str or path-like
        The ``.aedat4`` file.

    Returns
    -------
    list of Aedat4Stream
        In the header's order, e.g. ``[Aedat4Stream(id=0, type_identifier='EVTS',
        name='events', width=346, height=260, compression='lz4', ...), ...]``.

    Raises
    ------
    FormatError
        If the file is not AEDAT 4.0 or its header is truncated or corrupt.
    """
    where = os.fspath(path)
    with open(path, "rb") as handle:
        head = handle.read(len(MAGIC) + 4)
        if head.startswith(MAGIC) and len(head) == len(MAGIC) + 4:
            (size,) = struct.unpack_from("<i", head, len(MAGIC))
            head += handle.read(max(size, 0))
    return list(_read_header(head, where)[2])


def read_aedat4(
    path: str | os.PathLike, *, stream: int | str | None = None, sort: bool = False
) -> Events:
    """Read the polarity events of one ``EVTS`` stream of an AEDAT4 file.

    Parameters
    ----------
    path : str or path-like
        The ``.aedat4`` file (read whole into memory).
    stream : int, str or None, keyword-only
        Stream id or DV output name (e.g. ``"events"``); ``None`` takes the
        first ``EVTS`` stream (a ``UserWarning`` names the others where there are several).
    sort : bool, keyword-only
        DV writes each stream in time order and so this reader by default
        raises :class:`FormatError` if time ever decreases; ``sort=True``
        sorts the events by time (stable) instead.

    Returns
    -------
    Events
        N events; ``x``, ``y`` uint16 pixels, ``t`` int64 µs since the Unix
        epoch (as stored), ``p`` int8 {0 OFF, 1 ON}; sensor size from the
        stream's ``sizeX``/``sizeY``.

    Raises
    ------
    FormatError
        If the file is not AEDAT 4.0, is truncated or corrupt, an event
        lies outside the sensor, or a time lies beyond the year 2100 as µs
        since the epoch (nanoseconds written by another tool, named so).
    ValueError
        If the file has no such event stream.

    Examples
    --------
    A recording of a DAVIS346 (needs the file: ``cmax`` writes no AEDAT4):

    >>> events = read_aedat4("davis.aedat4")  # doctest: +SKIP
    >>> events.sensor_size, len(events)        # doctest: +SKIP
    ((346, 260), 117667)
    """
    file = _open(path)
    chosen = _select(file, stream, "EVTS")
    if chosen.width is None or chosen.height is None:
        raise FormatError(f"{file.where}: event stream {chosen.id} has no sizeX/sizeY in its info")
    try:
        _check_sensor_size(chosen.width, chosen.height)
    except (TypeError, ValueError) as error:
        raise FormatError(f"{file.where}: event stream {chosen.id} declares a bad sensor size (sizeX/sizeY): "
                          f"{error}") from None
    parts, total = [], 0
    for _, fb in _bodies(file, chosen):
        start, length = fb.vector(fb.root, 0)
        parts.append(np.frombuffer(fb.span(start, 16 * length), _EVENT_DTYPE))
        total = check_event_count(total + length, f"{file.where}: event stream {chosen.id}")
    raw = np.concatenate(parts) if parts else np.empty(0, _EVENT_DTYPE)
    x, y, t, p = raw["x"], raw["y"], raw["t"], raw["p"]
    if raw.size:
        for name, column, size in (("x", x, chosen.width), ("y", y, chosen.height)):
            bad = np.flatnonzero((column < 0) | (column >= size))
            if bad.size:
                raise FormatError(
                    f"{file.where}: event {bad[0]} has {name}={column[bad[0]]}, outside the "
                    f"{chosen.width}x{chosen.height} sensor"
                )
        if p.max() > 1:
            raise FormatError(f"{file.where}: event polarity byte {p.max()} is not a bool")
    _check_epoch_times(t, file.where, "event")
    order = _check_order(t, file.where, "event", sort)
    if order is not None:
        x, y, t, p = x[order], y[order], t[order], p[order]
    return Events._trusted(
        x.astype(np.uint16), y.astype(np.uint16), t.astype(np.int64), p.astype(np.int8),
        chosen.width, chosen.height,
    )


def read_aedat4_imu(
    path: str | os.PathLike, *, stream: int | str | None = None, sort: bool = False
) -> ImuSamples:
    """Read the inertial samples of one ``IMUS`` stream of an AEDAT4 file.

    Parameters
    ----------
    path : str or path-like
        The ``.aedat4`` file.
    stream : int, str or None, keyword-only
        Stream id or DV output name (e.g. ``"imu"``); ``None`` takes the first
        ``IMUS`` stream (a ``UserWarning`` names the others where there are several).
    sort : bool, keyword-only
        Sort by time instead of raising :class:`FormatError` when time decreases.

    Returns
    -------
    ImuSamples
        ``t`` (N,) int64 µs; ``accelerometer`` (N, 3) float32 g; ``gyroscope``
        (N, 3) float32 deg/s; ``temperature`` (N,) float32 °C; ``magnetometer``
        (N, 3) float32 µT or ``None``. Units are those DV stores; nothing is
        converted.

    Raises
    ------
    FormatError
        If the file is not AEDAT 4.0 or is truncated or corrupt.
    ValueError
        If the file has no such IMU stream.
    """
    file = _open(path)
    chosen = _select(file, stream, "IMUS")
    parts = []
    for _, fb in _bodies(file, chosen):
        start, length = fb.vector(fb.root, 0)
        fb.span(start, 4 * length)
        parts.append(_table_vector(fb, start, length, _IMU_FIELDS))
    if not parts:
        parts = [{key: np.empty(0, kind) for name, dtype in _IMU_FIELDS
                  for key, kind in ((name, dtype), (name + "?", bool))}]
    columns = {key: np.concatenate([part[key] for part in parts]) for key in parts[0]}
    _check_epoch_times(columns["t"], file.where, "IMU")
    order = _check_order(columns["t"], file.where, "IMU", sort)
    if order is not None:
        columns = {name: values[order] for name, values in columns.items()}

    def triple(prefix: str) -> np.ndarray:
        return np.stack([columns[prefix + axis] for axis in "xyz"], axis=1).astype(np.float32)

    has_magnetometer = any(columns[f"m{axis}?"].any() for axis in "xyz")
    return ImuSamples(
        t=columns["t"].astype(np.int64), accelerometer=triple("a"), gyroscope=triple("g"),
        temperature=columns["temperature"].astype(np.float32),
        magnetometer=triple("m") if has_magnetometer else None,
    )


def read_aedat4_frames(
    path: str | os.PathLike, *, stream: int | str | None = None
) -> ApsFrames:
    """Read the intensity (APS) frames of one ``FRME`` stream of an AEDAT4 file.

    Each packet of the stream holds one ``Frame`` table: time stamps, OpenCV
    type code (0 8-bit gray, 2 16-bit gray, 16/18 BGR, 24/26 BGRA), size,
    position and the pixel bytes.

    Parameters
    ----------
    path : str or path-like
        The ``.aedat4`` file.
    stream : int, str or None, keyword-only
        Stream id or DV output name (e.g. ``"frames"``); ``None`` takes the
        first ``FRME`` stream (a ``UserWarning`` names the others where there are several).

    Returns
    -------
    ApsFrames
        ``t`` and the exposure and readout limits (N,) int64 µs, ``images``
        (N, H, W) or (N, H, W, C), uint8 or uint16, and ``origin`` (N, 2), in
        file order.

    Raises
    ------
    FormatError
        If the file is not AEDAT 4.0, is truncated or corrupt.
    ValueError
        If the file has no such frame stream, or its frames differ in size or format.
    """
    file = _open(path)
    chosen = _select(file, stream, "FRME")
    times, images = [], []  # one frame per packet: a loop over frames, not pixels
    for packet, fb in _bodies(file, chosen):
        stamps = [fb.scalar(fb.root, index, "<q", 0) for index in range(5)]
        stamps += [fb.scalar(fb.root, index, "<h", 0) for index in (8, 9)]
        code = fb.scalar(fb.root, 5, "<b", 0)
        width, height = fb.scalar(fb.root, 6, "<h", 0), fb.scalar(fb.root, 7, "<h", 0)
        depth, channels = code & 7, (code >> 3) + 1
        if depth not in (0, 2) or channels not in (1, 3, 4) or width < 0 or height < 0:
            fb.fail(f"unsupported frame format {code} or size {width}x{height}")
        dtype = np.dtype(np.uint8 if depth == 0 else "<u2")
        start, length = fb.vector(fb.root, 10)
        expected = width * height * channels * dtype.itemsize
        if length != expected:
            fb.fail(f"a {width}x{height} frame (format {code}) has {length} bytes, not {expected}")
        image = np.frombuffer(fb.span(start, length), dtype).reshape(
            (height, width) if channels == 1 else (height, width, channels)
        ).astype(dtype.newbyteorder("="))
        if images and (image.shape != images[0].shape or image.dtype != images[0].dtype):
            raise ValueError(
                f"{file.where}: frame at byte {packet} is {image.shape} {image.dtype}, the first "
                f"is {images[0].shape} {images[0].dtype}; cannot stack them"
            )
        times.append(stamps)
        images.append(image)
    table = np.array(times, np.int64).reshape(-1, 7)
    shape = (0, chosen.height or 0, chosen.width or 0)
    return ApsFrames(
        t=table[:, 0].copy(),
        t_frame_start=table[:, 1].copy(), t_frame_end=table[:, 2].copy(),
        t_exposure_start=table[:, 3].copy(), t_exposure_end=table[:, 4].copy(),
        images=np.stack(images) if images else np.empty(shape, np.uint8),
        origin=table[:, 5:7].copy(),
    )
