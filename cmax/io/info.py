"""Summary statistics of an event file, read with bounded memory."""
from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from cmax.events import Events
from cmax.hot_pixels import hot_pixels_of_counts, no_pixels, pixel_counts

__all__ = ["EventFileInfo", "file_info", "events_info", "duplicate_count"]

_CHUNK = 1 << 22


def duplicate_count(events: Events) -> int:
    """How many of ``events`` (sorted by time, as :class:`cmax.events.Events` holds them) repeat an earlier event
    exactly: the same ``x``, ``y``, ``t`` [µs] and polarity. A sensor's pixel fires at most once at a time stamp,
    so such rows come from a file written twice or merged with itself; they are counted, never dropped.

    >>> ev = Events([1, 1, 2, 1], [0, 0, 0, 0], [5, 5, 5, 6], [1, 1, 1, 1], 4, 2)
    >>> duplicate_count(ev)
    1
    """
    return _DuplicateCounter().add(events).total()


class _DuplicateCounter:
    """:func:`duplicate_count` over time-sorted chunks of one recording: the rows of a chunk's last time stamp are
    held back and counted with the next chunk, so a time stamp split between two chunks is counted whole."""

    def __init__(self) -> None:
        self._count = 0
        self._held: tuple[np.ndarray, np.ndarray] | None = None     # (t, pixel-polarity cell) of the last stamp

    def add(self, events: Events) -> "_DuplicateCounter":
        if not len(events):
            return self
        t = events.t.astype(np.int64)
        cell = (events.y.astype(np.int64) * events.width + events.x) * 2 + (events.p > 0)
        if self._held is not None:
            t, cell = np.concatenate([self._held[0], t]), np.concatenate([self._held[1], cell])
        last = int(np.searchsorted(t, t[-1]))                    # the rows of the last time stamp start here
        self._count += _duplicates(t[:last], cell[:last], 2 * events.width * events.height)
        self._held = (t[last:], cell[last:])
        return self

    def total(self) -> int:
        if self._held is not None:
            self._count += int(len(self._held[1]) - len(np.unique(self._held[1])))
            self._held = None
        return self._count


def _duplicates(t: np.ndarray, cell: np.ndarray, cells: int) -> int:
    """Rows of ``(t, cell)`` (``t`` sorted int64 µs, ``cell`` in ``[0, cells)``) equal to an earlier row."""
    if t.size < 2:
        return 0
    span = int(t[-1] - t[0]) + 1
    if span * cells < 2 ** 62:                                  # one int64 key: a single sort
        key = np.sort((t - t[0]) * cells + cell)
        return int(np.count_nonzero(key[1:] == key[:-1]))
    order = np.lexsort((cell, t))
    t, cell = t[order], cell[order]
    return int(np.count_nonzero((t[1:] == t[:-1]) & (cell[1:] == cell[:-1])))


@dataclass(frozen=True)
class EventFileInfo:
    """What ``cmax info`` prints about an event file.

    Times in µs; ``rate_hz`` in events per second; ``on_fraction`` is the
    share of ON events (0.5 = balanced); ``pixel_counts`` (height, width)
    the events of each pixel (its hot pixels: :meth:`hot_pixels`); ``camera``: the camera summarised in a
    file of several (MVSEC), ``cameras`` its cameras and their events (None for other files); ``duplicates``: the
    events that repeat an earlier one exactly (:func:`duplicate_count`; None where not counted: Prophesee RAW);
    ``size_inferred_from``: the header line of a RAW file that does not state its sensor size from which the size
    was inferred (a camera's name: a guess, said on the sensor line), None for a stated or given size;
    ``time_unit_assumed``: the file's integer times were read as µs, its format's default, with neither the file nor
    the caller stating a unit (said on the time line: the readers refuse only the units they can tell apart);
    ``streams``: the other streams of an AEDAT4 file beside its events, each with what reads it
    (:func:`aedat4_stream_notes`; empty for other files).
    """

    path: str
    format: str
    count: int
    width: int
    height: int
    t_start_us: int | None
    t_end_us: int | None
    on_count: int
    attrs: dict[str, Any] = field(default_factory=dict)
    pixel_counts: np.ndarray | None = None
    camera: str | None = None
    cameras: dict[str, int] | None = None
    duplicates: int | None = None
    size_inferred_from: str | None = None
    time_unit_assumed: bool = False
    streams: tuple[str, ...] = ()

    @property
    def duration_s(self) -> float:
        if self.t_start_us is None or self.t_end_us is None:
            return 0.0
        return (self.t_end_us - self.t_start_us) / 1e6

    @property
    def rate_hz(self) -> float:
        return self.count / self.duration_s if self.duration_s > 0 else float("nan")

    @property
    def on_fraction(self) -> float:
        return self.on_count / self.count if self.count else float("nan")

    def hot_pixels(self) -> np.ndarray:
        """``(K, 2)`` ``(x, y)`` of the pixels that :class:`cmax.hot_pixels.HotPixelFilter`'s default count rule
        calls hot over the whole recording (empty without counts; its rule of lone steady pixels needs the
        events' times, which this summary does not keep)."""
        return no_pixels() if self.pixel_counts is None else hot_pixels_of_counts(self.pixel_counts)

    def _hot_line(self) -> str:
        hot = self.hot_pixels()
        if not len(hot):
            return ("hot pixels  none by count (no pixel fires far more than the others; cmax fit and cmax emvs also "
                    "look in each window for pixels firing alone at a steady rate or with a lamp's flicker)")
        counts = self.pixel_counts[hot[:, 1], hot[:, 0]]
        order = np.argsort(-counts, kind="stable")
        rate = (lambda n: f", {n / self.duration_s:,.0f} Hz") if self.duration_s > 0 else (lambda n: "")
        named = "; ".join(f"({x}, {y}) {n:,} events{rate(n)}" for (x, y), n in zip(hot[order][:5], counts[order][:5]))
        return (f"hot pixels  {len(hot)}: {named}{'; ...' if len(hot) > 5 else ''} (cmax fit and cmax emvs "
                "leave such pixels out)")

    def _rate_line(self) -> str:
        """The event rate, or n/a where the events span no time (one event, or all at one time stamp)."""
        if self.duration_s > 0 and self.rate_hz < 500:   # "0.000 Mev/s" would read as no events
            return f"rate        {self.rate_hz:,.1f} ev/s"
        if self.duration_s > 0:
            return f"rate        {self.rate_hz / 1e6:.3f} Mev/s"
        return "rate        n/a (the events span 0 µs)"

    def _camera_line(self) -> str:
        """Which camera of a file of several the block summarises, and how to read the others.

        >>> EventFileInfo("rig.hdf5", "mvsec", 5, 346, 260, 0, 9, 2, camera="left",
        ...               cameras={"left": 5, "right": 7})._camera_line()
        'camera      left (davis/left/events); the file also holds right (7 events): --camera right reads it'
        """
        others = [f"{name} ({count:,} events): --camera {name} reads it"
                  for name, count in (self.cameras or {}).items() if name != self.camera]
        held = "; the file also holds " + ", ".join(others) if others else "; the file holds no other camera"
        return f"camera      {self.camera} (davis/{self.camera}/events){held}"

    def _inferred_note(self) -> str:
        """After the sensor size, when the file does not state it and it was inferred from a camera's name.

        >>> EventFileInfo("a.raw", "raw", 1, 640, 480, 0, 0, 1,
        ...               size_inferred_from="plugin_name hal_plugin_gen3_fx3")._inferred_note()
        " (not stated by the file: inferred from its 'plugin_name hal_plugin_gen3_fx3' line; --size WxH gives the sensor's)"
        """
        if self.size_inferred_from is None:
            return ""
        return (f" (not stated by the file: inferred from its '{self.size_inferred_from}' line; --size WxH gives "
                "the sensor's)")

    def _assumed_note(self) -> str:
        """After the times, when their unit was assumed (µs) rather than stated.

        >>> EventFileInfo("a.h5", "dsec", 1, 8, 8, 0, 1999, 1, time_unit_assumed=True)._assumed_note()
        " (the file states no unit: integer times read as µs, the format's default; --time-unit ms or s if they are not)"
        """
        if not self.time_unit_assumed:
            return ""
        return (" (the file states no unit: integer times read as µs, the format's default; --time-unit ms or s if "
                "they are not)")

    def _duplicates_line(self) -> str:
        """The events that repeat an earlier one exactly (only printed when there are some).

        >>> EventFileInfo("a.h5", "dsec", 2000, 64, 48, 0, 9, 900, duplicates=1000)._duplicates_line()
        'duplicates  1,000 events (50.0%) repeat an earlier event exactly (same x, y, t and polarity): a file written twice or merged with itself? They are read as they are (counted twice); a pixel fires once at a time stamp'
        """
        return (f"duplicates  {self.duplicates:,} events ({100 * self.duplicates / self.count:.1f}%) repeat an earlier "
                "event exactly (same x, y, t and polarity): a file written twice or merged with itself? They are "
                "read as they are (counted twice); a pixel fires once at a time stamp")

    def lines(self) -> list[str]:
        """Human-readable lines, one fact each."""
        out = [
            f"file        {self.path}",
            f"format      {self.format}",
            *([self._camera_line()] if self.camera is not None else []),
            f"sensor      {self.width} x {self.height}{self._inferred_note()}",
            f"events      {self.count:,}",
        ]
        if self.count:
            out += [
                f"time        {self.t_start_us} .. {self.t_end_us} µs{self._assumed_note()}",
                f"duration    {self.duration_s:.6f} s",
                self._rate_line(),
                f"polarity    {self.on_count:,} ON / {self.count - self.on_count:,} OFF "
                f"({100 * self.on_fraction:.1f}% ON)",
            ]
            if self.pixel_counts is not None:
                out.append(self._hot_line())
            if self.duplicates:
                out.append(self._duplicates_line())
        if self.streams:
            out.append(f"streams     {'; '.join(self.streams)}")
        for key, value in sorted(self.attrs.items()):
            if key not in ("width", "height"):
                out.append(f"attr        {key} = {value}")
        return out


#: What reads each kind of AEDAT4 stream other than events (:func:`aedat4_stream_notes`).
_AEDAT4_READERS = {"IMUS": "IMU samples: cmax fit --gyro FILE holds each window's rotation at their mean "
                           "(cmax.io.read_aedat4_imu)",
                   "FRME": "APS frames (cmax.io.read_aedat4_frames)"}


def aedat4_stream_notes(streams) -> tuple[str, ...]:
    """One note per stream of an AEDAT4 file that is not its events (``streams``: the file's
    :class:`cmax.io.aedat4.Aedat4Stream` list, :func:`cmax.io.aedat4.aedat4_streams`): its name, kind and what
    reads it, so that ``cmax info`` tells a DAVIS user that the file's own IMU can be ``--gyro``.

    >>> from cmax.io.aedat4 import Aedat4Stream
    >>> aedat4_stream_notes([Aedat4Stream(0, "EVTS", "events", 346, 260, "lz4"),
    ...                      Aedat4Stream(1, "IMUS", "imu", None, None, "lz4")])[0][:40]
    "'imu' (IMUS): IMU samples: cmax fit --gy"
    """
    return tuple(f"{stream.name!r} ({stream.type_identifier}): "
                 f"{_AEDAT4_READERS.get(stream.type_identifier, 'not read by cmax')}"
                 for stream in streams if stream.type_identifier != "EVTS")


def events_info(events: Events, *, path: str = "", format: str = "") -> EventFileInfo:
    """Summary of events already in memory."""
    return EventFileInfo(
        path=path, format=format, count=len(events), width=events.width, height=events.height,
        t_start_us=events.t_start if len(events) else None,
        t_end_us=events.t_end if len(events) else None,
        on_count=int(np.count_nonzero(events.p)), pixel_counts=pixel_counts(events),
        duplicates=duplicate_count(events),
    )


def file_info(
    path: str | os.PathLike, *, width: int | None = None, height: int | None = None,
    time_unit: str | None = None, **options: Any,
) -> EventFileInfo:
    """Summary of an event file; DSEC and MVSEC files are read in chunks (bounded memory) and every row is
    checked as the readers check it (a NaN time or a step back in the middle raises FormatError);
    Prophesee RAW files are decoded chunk by chunk (:func:`cmax.io.prophesee.iter_raw`).

    ``time_unit`` and ``options`` (e.g. ``polarity='signed'``, an MVSEC file's ``camera='right'``) go to the
    reader (an MVSEC file's summary names its camera and the other one it holds):
    times are never guessed and polarities never mapped silently, so a file
    whose ``events/p`` holds -1/+1 is refused unless ``polarity='signed'`` is given.
    """
    from cmax.io import FormatError, H5Reader, detect_format, read

    path = Path(path)
    kind = detect_format(path)
    if kind == "raw" and time_unit in (None, "us") and not options:
        return _raw_info(path, width, height)
    if kind == "mvsec":
        return _mvsec_info(path, width, height, time_unit, options)
    if kind != "dsec":
        events = read(path, width=width, height=height, time_unit=time_unit, **options)
        info = events_info(events, path=str(path), format=kind)
        if kind == "aedat4":
            from cmax.io.aedat4 import aedat4_streams

            info = replace(info, streams=aedat4_stream_notes(aedat4_streams(path)))
        # a .npy's float times need a stated unit; its integer ones are µs when none is stated
        return replace(info, time_unit_assumed=kind == "npy" and time_unit is None)
    with H5Reader(path, width=width, height=height, time_unit=time_unit, **options) as reader:
        # Every row is read and checked (coordinates, finite and sorted times, polarity), chunk by
        # chunk, so a NaN or a step back in the middle is named here as the readers name it.
        on_count, last_t, duplicates = 0, None, _DuplicateCounter()
        pixels = np.zeros((reader.height, reader.width), np.int64)
        for start in range(0, len(reader), _CHUNK):
            chunk = reader.read_rows(start, start + _CHUNK)
            if last_t is not None and int(chunk.t[0]) < last_t:
                raise FormatError(
                    f"{path}: events/t: corrupt events at row {start}: t must be sorted in non-decreasing "
                    f"order ({int(chunk.t[0])} µs comes after {last_t} µs)"
                )
            last_t = int(chunk.t[-1])
            on_count += int(np.count_nonzero(chunk.p))
            pixels += pixel_counts(chunk)
            duplicates.add(chunk)
        return EventFileInfo(
            path=str(path), format="dsec", count=len(reader), width=reader.width,
            height=reader.height, t_start_us=reader.t_start if len(reader) else None,
            t_end_us=reader.t_end if len(reader) else None, on_count=on_count,
            attrs=reader.attrs, pixel_counts=pixels, duplicates=duplicates.total(),
            time_unit_assumed=reader.time_unit_assumed,
        )


def _mvsec_info(path: Path, width: int | None, height: int | None, time_unit: str | None,
                options: dict[str, Any]) -> EventFileInfo:
    """:func:`file_info` of one camera of an MVSEC file (``options``: ``camera``, ``polarity``), read :data:`_CHUNK`
    rows at a time (:func:`cmax.io.mvsec.iter_mvsec`: a camera of any length), naming the cameras the file holds."""
    from cmax.io import check_sortable
    from cmax.io._checks import check_stated_size
    from cmax.io.mvsec import MVSEC_HEIGHT, MVSEC_WIDTH, iter_mvsec, mvsec_cameras

    options = dict(options)
    check_sortable(path, "mvsec", options.pop("sort", False))
    check_stated_size(width, height, (MVSEC_WIDTH, MVSEC_HEIGHT), f"{path} (MVSEC, a DAVIS346)")
    count, on_count, first, last, duplicates = 0, 0, None, None, _DuplicateCounter()
    pixels = np.zeros((MVSEC_HEIGHT, MVSEC_WIDTH), np.int64)
    for chunk in iter_mvsec(path, time_unit=time_unit, chunk_rows=_CHUNK, **options):
        if len(chunk):
            first = int(chunk.t[0]) if first is None else first
            last = int(chunk.t[-1])
        count += len(chunk)
        on_count += int(np.count_nonzero(chunk.p))
        pixels += pixel_counts(chunk)
        duplicates.add(chunk)
    return EventFileInfo(path=str(path), format="mvsec", count=count, width=MVSEC_WIDTH, height=MVSEC_HEIGHT,
                         t_start_us=first, t_end_us=last, on_count=on_count, pixel_counts=pixels,
                         duplicates=duplicates.total(),
                         camera=options.get("camera", "left"), cameras=mvsec_cameras(path))


def _raw_info(path: Path, width: int | None, height: int | None) -> EventFileInfo:
    """:func:`file_info` of a Prophesee RAW file, decoded chunk by chunk (a file of any length)."""
    from cmax.io.prophesee import scan_raw

    scan = scan_raw(path, width=width, height=height)
    return EventFileInfo(path=str(path), format="raw", count=scan.count, width=scan.width, height=scan.height,
                         t_start_us=scan.first_us, t_end_us=scan.last_us, on_count=scan.on_count,
                         pixel_counts=scan.pixel_counts, size_inferred_from=scan.size_inferred_from)
