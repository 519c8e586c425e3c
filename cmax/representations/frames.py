"""Event frame (counts per pixel and polarity) and time surface (decayed latest time).

Both go through the flat (polarity, pixel) index of
:mod:`cmax.representations._common`: counts by a compiled loop into the
float32 frame / ``index_add_``, the per-pixel latest time by ``np.maximum.at``
/ ``scatter_reduce_``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cmax.events import Events  # noqa: F401  (the doctests' namespace)
from cmax.representations import _common
from cmax.representations._common import (
    Array, EventsLike, _check_optional_time, _check_output_size, _chunks, _index_numpy,
    _index_torch, _inspect, _pixel_counts,
)

__all__ = ["event_frame", "time_surface", "EventFrame", "TimeSurface"]


def _check_bool(name: str, value: object) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be a bool, got {value!r}")
    return bool(value)


def _check_tau(tau_us: object) -> float:
    if isinstance(tau_us, (bool, np.bool_)) or not isinstance(tau_us, (int, float, np.number)):
        raise TypeError(f"tau_us must be a number of microseconds, got {tau_us!r}")
    tau = float(tau_us)
    if not np.isfinite(tau) or tau <= 0:
        raise ValueError(f"tau_us must be positive and finite, got {tau_us}")
    return tau


# -- event frame -----------------------------------------------------------------------------
def event_frame(events: EventsLike, *, signed: bool = False) -> Array:
    """Events counted per pixel and polarity.

    Parameters
    ----------
    events : Events or EventTensors
        N events (numpy in, numpy out; torch in, torch out on the same device).
    signed : bool, keyword-only
        Return the (H, W) sum of signed polarities (ON - OFF counts) instead.

    Returns
    -------
    ndarray or Tensor, float32
        Shape (2, H, W): channel 0 counts OFF events, channel 1 ON events, so
        ``frame.sum() == N``. With ``signed=True``, shape (H, W). Counts are
        exact up to 2**24 events per pixel.

    Examples
    --------
    >>> ev = Events([0, 0, 1], [0, 0, 0], [0, 1, 2], [1, 0, 1], width=2, height=1)
    >>> event_frame(ev)[:, 0].tolist(), event_frame(ev, signed=True).tolist()
    ([[1.0, 0.0], [1.0, 1.0]], [[0.0, 1.0]])
    """
    signed = _check_bool("signed", signed)
    kind, _ = _inspect(events)
    height, width = events.height, events.width
    _check_output_size((2, height, width), f"event frame of a {width}x{height} sensor")
    if kind == "numpy":
        frame = _pixel_counts(events, np.float32).reshape(2, height, width)
        return frame[1] - frame[0] if signed else frame
    import torch

    index = _index_torch(events)
    ones = torch.ones(1, dtype=torch.float32, device=index.device).expand(index.shape[0])
    frame = torch.zeros(2 * height * width, dtype=torch.float32, device=index.device)
    frame = frame.index_add_(0, index, ones).view(2, height, width)
    return frame[1] - frame[0] if signed else frame


# -- time surface ----------------------------------------------------------------------------
def time_surface(
    events: EventsLike, *, tau_us: float = 50_000.0, t_ref_us: int | None = None
) -> Array:
    """Exponentially decayed time of each pixel's latest event, per polarity.

    ``S(c, y, x) = exp(-(t_ref - t_last(c, y, x)) / tau)`` where ``t_last`` is
    the time of the latest event of polarity ``c`` (0 = OFF, 1 = ON) at the
    pixel, and ``S = 0`` where the pixel has no such event.

    Parameters
    ----------
    events : Events or EventTensors
        N events (numpy in, numpy out; torch in, torch out on the same device).
    tau_us : float, keyword-only
        Decay constant in microseconds, > 0.
    t_ref_us : int, optional, keyword-only
        Reference time in microseconds, default the last event time. It must
        not precede any event (slice with :meth:`Events.slice_time` first).

    Returns
    -------
    ndarray or Tensor, shape (2, H, W), float32, values in [0, 1]

    References
    ----------
    X. Lagorce et al., "HOTS: a hierarchy of event-based time-surfaces for
    pattern recognition", TPAMI 2017, doi:10.1109/TPAMI.2016.2574707.

    Examples
    --------
    >>> ev = Events([0, 0], [0, 0], [0, 1000], [1, 1], width=1, height=1)
    >>> round(float(time_surface(ev, tau_us=1000.0, t_ref_us=2000)[1, 0, 0]), 4)
    0.3679
    """
    tau = _check_tau(tau_us)
    t_ref = _check_optional_time("t_ref_us", t_ref_us)
    kind, t_range = _inspect(events)
    height, width = events.height, events.width
    _check_output_size((2, height, width), f"time surface of a {width}x{height} sensor")
    size = 2 * height * width
    if t_range is None:
        zeros = np.zeros((2, height, width), np.float32)
        if kind == "numpy":
            return zeros
        import torch

        return torch.zeros((2, height, width), dtype=torch.float32, device=events.t.device)
    t_min, t_max = t_range
    t_ref = t_max if t_ref is None else t_ref
    if t_ref < t_max:
        raise ValueError(f"t_ref_us={t_ref} precedes the last event at t={t_max} µs")
    age_origin = t_ref - t_min  # latest times are kept relative to t_min, so never negative
    if kind == "numpy":
        latest = np.full(size, -1, np.int64)
        index_buffer = np.empty(min(len(events), _common._CHUNK), np.intp)
        for run in _chunks(0, len(events)):  # np.maximum.at: an order-free running maximum
            np.maximum.at(latest, _index_numpy(events, run, index_buffer), events.t[run] - t_min)
        seen = latest >= 0
        surface = np.zeros(size, np.float64)
        surface[seen] = np.exp(-(age_origin - latest[seen]).astype(np.float64) / tau)
        return surface.astype(np.float32).reshape(2, height, width)
    import torch

    t = events.t.to(torch.int64)
    latest = torch.full((size,), -1, dtype=torch.int64, device=t.device)
    latest.scatter_reduce_(0, _index_torch(events), t - t_min, "amax", include_self=True)
    decay = torch.exp(-(age_origin - latest).to(torch.float64) / tau)
    surface = torch.where(latest >= 0, decay, torch.zeros((), dtype=torch.float64, device=t.device))
    return surface.to(torch.float32).view(2, height, width)


# -- settings objects ------------------------------------------------------------------------
@dataclass(frozen=True)
class EventFrame:
    """Stored settings for :func:`event_frame`; calling it on events returns (2, H, W) float32 counts, or (H, W)
    when ``signed``."""

    signed: bool = False

    def __post_init__(self) -> None:
        _check_bool("signed", self.signed)

    def __call__(self, events: EventsLike) -> Array:
        return event_frame(events, signed=self.signed)


@dataclass(frozen=True)
class TimeSurface:
    """Stored settings for :func:`time_surface`: the decay ``tau_us`` [µs] (reference time: the last event);
    calling it on events returns (2, H, W) float32."""

    tau_us: float = 50_000.0

    def __post_init__(self) -> None:
        _check_tau(self.tau_us)

    def __call__(self, events: EventsLike) -> Array:
        return time_surface(events, tau_us=self.tau_us)
