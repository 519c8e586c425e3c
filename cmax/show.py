"""What ``cmax show`` draws: a time window of an event file as one picture."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from cmax.events import Events
from cmax.representations import event_frame, voxel_grid
from cmax.viz import depth_image, event_frame_image, hstack, titled, vstack, voxel_grid_image

__all__ = ["read_window", "render_window", "render_events"]

#: Longest time (s) accepted for ``t0``/``dt``: about 31,700 years, far beyond any recording,
#: yet small enough that microseconds stay exact integers.
_MAX_SECONDS = 1e12


def read_window(
    path: str | os.PathLike, t0_s: float, dt_s: float, *,
    width: int | None = None, height: int | None = None, time_unit: str | None = None,
) -> tuple[Events, np.ndarray | None]:
    """Events of ``[t0, t0 + dt)`` seconds after the first event, and the ground-truth
    depth (H, W) nearest to the window's middle when the file has a ``gt/`` group.
    ``time_unit``: the unit of the file's time stamps where it is not implied (see :func:`cmax.io.read`)."""
    from cmax.io import H5Reader, detect_format, read

    for name, value in (("dt", dt_s), ("t0", t0_s)):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise TypeError(f"{name} must be a number of seconds, got {value!r}")
        if not np.isfinite(value) or abs(value) > _MAX_SECONDS:
            raise ValueError(
                f"{name} must be a finite number of seconds (at most {_MAX_SECONDS:g}), got {value}"
            )
    if dt_s <= 0:
        raise ValueError(f"dt must be positive seconds, got {dt_s}")
    if t0_s < 0:
        raise ValueError(f"t0 must be >= 0 seconds after the first event, got {t0_s}")
    path = Path(path)
    if detect_format(path) != "dsec":
        events = read(path, width=width, height=height, time_unit=time_unit)
        if not len(events):
            return events, None
        start = events.t_start + round(t0_s * 1e6)
        return events.slice_time(start, start + round(dt_s * 1e6)), None
    with H5Reader(path, width=width, height=height, time_unit=time_unit) as reader:
        if not len(reader):
            return reader.read(), None
        start = reader.t_start + round(t0_s * 1e6)
        stop = start + round(dt_s * 1e6)
        events = reader.window(start, stop)
        depth = None
        gt = reader.file.get("gt")
        if gt is not None and "depth" in gt and "depth_t" in gt and len(gt["depth_t"]):
            index = int(np.argmin(np.abs(gt["depth_t"][:] - (start + stop) // 2)))
            depth = gt["depth"][index]
    return events, depth


def render_events(
    events: Events, *, mode: str = "both", bins: int = 5, depth: np.ndarray | None = None,
    title: str = "",
) -> np.ndarray:
    """Picture (BGR uint8) of events: event frame, event-volume bins, or both; plus depth."""
    if mode not in ("frame", "voxel", "both"):
        raise ValueError(f"mode must be 'frame', 'voxel' or 'both', got {mode!r}")
    top = []
    if mode in ("frame", "both"):
        top.append(titled(event_frame_image(event_frame(events)), f"{title}{len(events):,} events"))
    if depth is not None:
        top.append(titled(depth_image(depth), "ground-truth depth"))
    rows = [hstack(top)] if top else []
    if mode in ("voxel", "both"):
        rows.append(voxel_grid_image(voxel_grid(events, bins=bins)))
    return vstack(rows)


def render_window(
    path: str | os.PathLike, *, t0_s: float = 0.0, dt_s: float = 0.05, mode: str = "both",
    bins: int = 5, width: int | None = None, height: int | None = None, time_unit: str | None = None,
) -> np.ndarray:
    """Picture of ``[t0, t0 + dt)`` seconds after the first event of a file."""
    events, depth = read_window(path, t0_s, dt_s, width=width, height=height, time_unit=time_unit)
    title = f"{dt_s * 1e3:g} ms: "
    return render_events(events, mode=mode, bins=bins, depth=depth, title=title)
