"""What ``cmax show`` draws: a time window of an event file as one picture."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from cmax.events import Events
from cmax.representations import event_frame, voxel_grid
from cmax.viz import depth_panel, enlarge, event_panel, hstack, readable_zoom, titled, vstack, voxel_grid_image

__all__ = ["read_window", "render_window", "render_events", "SHOW_PERCENTILE", "SHOW_GAMMA"]

#: Longest time (s) accepted for ``t0``/``dt``: about 31,700 years, far beyond any recording,
#: yet small enough that microseconds stay exact integers.
_MAX_SECONDS = 1e12
#: Contrast of ``cmax show``: colours saturate at this percentile of the non-zero pixels, and grow as
#: ``(value / saturation) ** SHOW_GAMMA`` below it. A few very active pixels (a flickering lamp holds
#: 1-5% of the active pixels of the DAVIS pegboard recording, at 5-10x the counts of the rest) then
#: saturate instead of setting the scale for the whole picture.
SHOW_PERCENTILE = 90.0
SHOW_GAMMA = 0.5
#: Widest picture [px] the panels are laid out to; sensors wider than _WIDE_SENSOR px draw the
#: event-volume bins at half size, in rows.
_LAYOUT_WIDTH = 1800
_WIDE_SENSOR = 640


def _check_seconds(name: str, value: object) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a number of seconds, got {value!r}")
    if not np.isfinite(value) or abs(value) > _MAX_SECONDS:
        raise ValueError(f"{name} must be a finite number of seconds (at most {_MAX_SECONDS:g}), got {value}")


def _check_start(path: Path, t0_s: float, t_start: int, t_end: int) -> None:
    """Refuse a window that starts after the last event of the file."""
    if t_start + round(t0_s * 1e6) > t_end:
        raise ValueError(
            f"t0 = {t0_s:g} s is past the end of {path.name}: its events span {(t_end - t_start) * 1e-6:.6g} s"
        )


def read_window(
    path: str | os.PathLike, t0_s: float, dt_s: float, *,
    width: int | None = None, height: int | None = None, time_unit: str | None = None, **options: Any,
) -> tuple[Events, np.ndarray | None]:
    """Events of the file at ``path`` in ``[t0_s, t0_s + dt_s)`` seconds after its first event, and the ground-truth
    depth (H, W) nearest to the window's middle when the file has a ``gt/`` group and that map's time lies
    within the window (None otherwise: a map of another time would be drawn as this window's).

    ``width``, ``height`` [px]: the sensor size of a file that does not store it; ``time_unit``: the unit of the
    file's time stamps where it is not implied (see :func:`cmax.io.read`); ``options`` (e.g.
    ``polarity='signed'``) go to the reader.
    A DSEC-layout h5 or MVSEC file is read from disk over the window only, a Prophesee RAW file decoded up
    to the window's end holding only the window (a recording longer than :data:`cmax.events.MAX_EVENTS` can
    be drawn), a ``.npy`` (without ``sort``) over the window's rows only; other formats are read whole, then cut.
    Raises ``ValueError`` when ``t0`` lies after the file's last event.
    """
    from cmax.io import H5Reader, detect_format, read

    for name, value in (("dt", dt_s), ("t0", t0_s)):
        _check_seconds(name, value)
    if dt_s <= 0:
        raise ValueError(f"dt must be positive seconds, got {dt_s}")
    if round(dt_s * 1e6) < 1:   # a window of 0 µs after rounding to the events' resolution: never any event
        raise ValueError(f"dt must be at least 1e-06 s (one microsecond, the time resolution of events), got {dt_s}")
    if t0_s < 0:
        raise ValueError(f"t0 must be >= 0 seconds after the first event, got {t0_s}")
    path = Path(path)
    kind = detect_format(path)
    if kind == "raw" and time_unit in (None, "us") and not options:
        return _read_raw_window(path, t0_s, dt_s, width, height), None
    if kind == "mvsec":
        return _read_mvsec_window(path, t0_s, dt_s, width, height, time_unit, options), None
    if kind == "npy" and not options.get("sort"):
        return _read_npy_window(path, t0_s, dt_s, width, height, time_unit, options), None
    if kind != "dsec":
        events = read(path, width=width, height=height, time_unit=time_unit, **options)
        if not len(events):
            return events, None
        _check_start(path, t0_s, events.t_start, events.t_end)
        start = events.t_start + round(t0_s * 1e6)
        return events.slice_time(start, start + round(dt_s * 1e6)), None
    with H5Reader(path, width=width, height=height, time_unit=time_unit, **options) as reader:
        if not len(reader):
            return reader.read(), None
        _check_start(path, t0_s, reader.t_start, reader.t_end)
        start = reader.t_start + round(t0_s * 1e6)
        stop = start + round(dt_s * 1e6)
        events = reader.window(start, stop)
        depth = None
        gt = reader.file.get("gt")
        if gt is not None and "depth" in gt and "depth_t" in gt and len(gt["depth_t"]):
            times = gt["depth_t"][:]
            index = int(np.argmin(np.abs(times - (start + stop) // 2)))
            if start <= times[index] < stop:
                depth = gt["depth"][index]
    return events, depth


def _read_raw_window(path: Path, t0_s: float, dt_s: float, width: int | None, height: int | None) -> Events:
    """Events of ``[t0, t0 + dt)`` seconds after the first event of a Prophesee RAW file, decoded chunk by chunk
    up to the window's end (:func:`cmax.io.read` with ``t0_us``/``t1_us``): memory holds the window and one chunk,
    not the recording. Only for an empty window is the file decoded to its end (bounded memory,
    :func:`cmax.io.prophesee.scan_raw`), to tell a window past the last event (ValueError) from a gap."""
    from cmax.io import read
    from cmax.io.prophesee import iter_raw, scan_raw

    first = next(iter_raw(path, width=width, height=height), None)
    if first is None:                                    # no events: as read() gives them
        return read(path, width=width, height=height)
    t_start = int(first.t[0])
    start = t_start + round(t0_s * 1e6)
    events = read(path, width=width, height=height, t0_us=start, t1_us=start + round(dt_s * 1e6))
    if not len(events):
        _check_start(path, t0_s, t_start, scan_raw(path, width=width, height=height).last_us)
    return events


def _read_npy_window(path: Path, t0_s: float, dt_s: float, width: int | None, height: int | None,
                     time_unit: str | None, options: dict[str, Any]) -> Events:
    """Events of ``[t0, t0 + dt)`` seconds after the first event of a structured ``.npy``: its first and last times
    from those two rows (:func:`cmax.io.npy_time_span`), the window's rows by a binary search of the
    memory-mapped times (:func:`cmax.io.read` with ``t0_us``/``t1_us``), not the whole file."""
    from cmax.io import npy_time_span, read

    span = npy_time_span(path, time_unit=time_unit)
    if span is None:                                     # no events: as read() gives them
        return read(path, width=width, height=height, time_unit=time_unit, **options)
    _check_start(path, t0_s, *span)
    start = span[0] + round(t0_s * 1e6)
    return read(path, width=width, height=height, time_unit=time_unit, t0_us=start,
                t1_us=start + round(dt_s * 1e6), **options)


def _read_mvsec_window(
    path: Path, t0_s: float, dt_s: float, width: int | None, height: int | None, time_unit: str | None,
    options: dict[str, Any],
) -> Events:
    """Events of ``[t0, t0 + dt)`` seconds after the first event of an MVSEC file: the first and last rows give
    the span, a bisection on disk the window's rows (:func:`cmax.io.read` with ``t0_us``/``t1_us``), so only
    those are read, not the camera's whole (N, 4) float64 table."""
    from cmax.io import read
    from cmax.io.mvsec import mvsec_time_span

    span = mvsec_time_span(path, camera=options.get("camera", "left"), time_unit=time_unit)
    if span is None:
        return read(path, width=width, height=height, time_unit=time_unit, **options)
    _check_start(path, t0_s, *span)
    start = span[0] + round(t0_s * 1e6)
    return read(path, width=width, height=height, time_unit=time_unit, t0_us=start,
                t1_us=start + round(dt_s * 1e6), **options)


def render_events(
    events: Events, *, mode: str = "both", bins: int = 5, depth: np.ndarray | None = None,
    title: str = "",
) -> np.ndarray:
    """Picture (BGR uint8) of events: event frame (with its ON/OFF legend), event-volume bins,
    or both (``mode``: ``"frame"``, ``"voxel"`` or ``"both"``, ``bins`` of the volume); plus the ``depth``
    (H, W) [m] with its colour bar in metres; ``title``, followed by the number of events, above the event frame,
    or above the whole picture when there is none (``"voxel"``).

    Contrast: :data:`SHOW_PERCENTILE` and :data:`SHOW_GAMMA`. Layout: the event frame
    and the depth side by side when they fit in about 1800 px, else one above the other; the
    bins in rows of up to 1800 px, at half size on sensors wider than 640 px; the frame and the depth of
    a sensor narrower than :data:`cmax.viz.MIN_PICTURE_WIDTH` enlarged by a whole factor.
    """
    if mode not in ("frame", "voxel", "both"):
        raise ValueError(f"mode must be 'frame', 'voxel' or 'both', got {mode!r}")
    width = events.width
    wide = width > _WIDE_SENSOR
    zoom = readable_zoom(width)   # small sensors drawn enlarged: titles, legend and colour bar stay readable
    top = []
    if mode in ("frame", "both"):
        counts = event_frame(events)
        top.append(event_panel(np.stack([enlarge(c, zoom) for c in counts]), f"{title}{len(events):,} events",
                               percentile=SHOW_PERCENTILE, gamma=SHOW_GAMMA))
    if depth is not None:
        top.append(depth_panel(enlarge(np.asarray(depth, dtype=np.float32), zoom), None, "ground-truth depth"))
    rows = []
    if top:
        rows.append(hstack(top) if sum(p.shape[1] for p in top) <= _LAYOUT_WIDTH else vstack(top))
    if mode in ("voxel", "both"):
        shrink = 2 if wide else 1
        columns = max(1, min(bins, _LAYOUT_WIDTH // (width * zoom // shrink + 4)))
        volume = voxel_grid(events, bins=bins)
        volume = np.stack([enlarge(b, zoom) for b in volume]) if zoom > 1 else volume
        rows.append(voxel_grid_image(volume, columns=columns, shrink=shrink, percentile=SHOW_PERCENTILE,
                                     gamma=SHOW_GAMMA))
    if mode == "voxel":   # no event frame to carry the title: above the picture (was: none, no file or window)
        return titled(vstack(rows), f"{title}{len(events):,} events")
    return vstack(rows)


def render_window(
    path: str | os.PathLike, *, t0_s: float = 0.0, dt_s: float = 0.05, mode: str = "both",
    bins: int = 5, width: int | None = None, height: int | None = None, time_unit: str | None = None,
    require_events: bool = False, **options: Any,
) -> np.ndarray:
    """Picture of ``[t0_s, t0_s + dt_s)`` seconds after the first event of the file at ``path`` (see
    :func:`render_events`: ``mode``, ``bins``); ``width``, ``height``, ``time_unit`` and ``options`` (e.g.
    ``polarity='signed'``) go to the reader, as in :func:`read_window`. Returns a BGR uint8 picture (h, w, 3).

    ``require_events``: raise ``ValueError`` naming the file and the window when the window holds no event (an
    empty file, or a gap in the recording) instead of drawing a blank picture (``cmax show`` sets it)."""
    events, depth = read_window(path, t0_s, dt_s, width=width, height=height, time_unit=time_unit, **options)
    if require_events and not len(events):
        raise ValueError(_no_events(Path(path), t0_s, dt_s, width=width, height=height, time_unit=time_unit,
                                    **options))
    span = f" (events over {(int(events.t[-1]) - int(events.t[0])) * 1e-3:.3g} ms)" if len(events) else ""
    title = f"{Path(path).name}, {t0_s:g} s + {dt_s * 1e3:g} ms{span}: "   # a file may end within the window
    return render_events(events, mode=mode, bins=bins, depth=depth, title=title)


def _no_events(path: Path, t0_s: float, dt_s: float, **reader: Any) -> str:
    """Why the window ``[t0_s, t0_s + dt_s)`` s of ``path`` (``reader``: :func:`read_window`'s keywords) has
    nothing to draw: the file holds no events (its first microsecond, where every other file has its first event,
    is empty too), or the window falls in a gap of the recording."""
    if not len(read_window(path, 0.0, 1e-6, **reader)[0]):
        return f"{path.name} holds no events: nothing to draw"
    return (f"no events in the window [{t0_s:g}, {t0_s + dt_s:g}) s after the first event of {path.name} (a gap in "
            "the recording): nothing to draw; choose another t0 or a longer dt")
