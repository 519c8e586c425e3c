"""The network's input volume in one compiled pass: :func:`cmax.representations.voxel_grid`, faster.

:func:`event_volume` computes the same 5-bin event volume as
:func:`cmax.representations.voxel_grid` (``normalization="paper"``: signed
polarity -1/+1 spread linearly over the two bins around
``t* = (B-1)(t - t_0)/(t_N - t_0)``, window from the first to the last event)
with a numba kernel that visits each event once and accumulates in float64,
so the two agree to float32 rounding. It exists for inference, where the volume
is a large share of the per-window time at 346x260 (see
``benchmarks/results/speed_learned.md``); training keeps ``voxel_grid``.
"""
from __future__ import annotations

import numpy as np

from cmax._jit import kernel
from cmax.events import Events, require_events

__all__ = ["event_volume"]


@kernel
def _accumulate(x, y, t, p, width, height, bins, t0, span, out):  # pragma: no cover - compiled
    """Add each event's linear weights into ``out`` (height * width, bins) float32, pixel-major."""
    scale = (bins - 1) / span if span > 0 else 0.0
    for i in range(t.shape[0]):
        sign = 1.0 if p[i] else -1.0
        pixel = np.int64(y[i]) * width + np.int64(x[i])
        if bins == 1 or span == 0:
            out[pixel, 0] += sign
            continue
        t_star = (t[i] - t0) * scale
        low = min(np.int64(t_star), bins - 2)   # floor (t* >= 0); t* = B-1 goes to bin B-1 through the right weight
        right = t_star - low
        out[pixel, low] += sign * (1.0 - right)
        out[pixel, low + 1] += sign * right


def event_volume(events: Events, bins: int = 5) -> np.ndarray:
    """The event volume (bins, H, W) float32 of ``events`` (equal to ``voxel_grid(events, bins)`` to ~1e-6).

    Parameters
    ----------
    events : Events
        N time-sorted events (numpy); the window is ``[t_0, t_N]``, their first and last time stamps [µs].
    bins : int
        Time bins B >= 1.

    Returns
    -------
    ndarray, shape (bins, events.height, events.width), float32

    Examples
    --------
    >>> ev = Events([0, 1, 1], [0, 0, 0], [0, 50, 100], [1, 1, 0], width=2, height=1)
    >>> event_volume(ev, bins=3)[:, 0].tolist()
    [[1.0, 0.0], [0.0, 1.0], [0.0, -1.0]]
    """
    events = require_events(events)
    if isinstance(bins, bool) or not isinstance(bins, (int, np.integer)) or bins < 1:
        raise ValueError(f"bins must be an integer >= 1, got {bins!r}")
    out = np.zeros((events.height * events.width, int(bins)), np.float32)
    if len(events):
        t0 = int(events.t[0])
        _accumulate(events.x, events.y, events.t, events.p, events.width, events.height, int(bins), t0,
                    int(events.t[-1]) - t0, out)
    return np.ascontiguousarray(out.T).reshape(int(bins), events.height, events.width)
