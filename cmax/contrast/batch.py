"""One event type for the contrast core: the events of one window or of a batch of windows.

:class:`EventWindows` holds N events of B windows concatenated, each event with
the index of its window, and per window its intrinsics, duration and
(optionally) known speed. The fit uses B = 1 (:meth:`EventWindows.from_events`),
training uses B > 1 (:meth:`EventWindows.from_windows`, :meth:`EventWindows.from_padded`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch

from cmax.camera import pinhole_events, sensor_pixels
from cmax.events import Events
from cmax.warp import DepthGrid, WarpEvents

__all__ = ["EventWindows"]


@dataclass(frozen=True, eq=False)
class EventWindows:
    """Events of B windows, concatenated, each with the index of its window.

    Attributes
    ----------
    x, y : Tensor (N,)
        Pixel coordinates [px] (dithered / undistorted by the caller).
    t : Tensor (N,)
        Seconds since the start of the event's window.
    polarity : Tensor (N,)
        Signed polarity -1/+1.
    window : Tensor (N,) int64
        Window of each event, ``0 <= window < count``.
    K : Tensor (B, 3, 3)
        Intrinsics [px] of each window.
    duration_s : Tensor (B,)
        Duration of each window [s] (its first to its last event), > 0.
    width, height : int
        Sensor size shared by the windows [px].
    speed : Tensor (B,) or None
        Known ``|v|`` [m/s] of each window: objectives that take a twist
        rescale its ``v`` to this norm (the contrast fixes only depth x speed,
        so this is the metric anchor); NaN for a window of unknown speed and
        None for all leave ``v`` as given.
    """

    x: torch.Tensor
    y: torch.Tensor
    t: torch.Tensor
    polarity: torch.Tensor
    window: torch.Tensor
    K: torch.Tensor
    duration_s: torch.Tensor
    width: int
    height: int
    speed: torch.Tensor | None = None

    def __post_init__(self) -> None:
        n = self.x.shape
        if self.x.dim() != 1 or not (self.y.shape == self.t.shape == self.polarity.shape == self.window.shape == n):
            raise ValueError("x, y, t, polarity, window must share one shape (N,), got "
                             f"{[tuple(a.shape) for a in (self.x, self.y, self.t, self.polarity, self.window)]}")
        if self.x.dtype not in (torch.float32, torch.float64):   # half types: torch.linalg.inv of K has none
            raise TypeError(f"x must be a float32 or float64 tensor, got {self.x.dtype} (.to(torch.float32))")
        if self.window.dtype != torch.int64:
            raise TypeError(f"window must be an int64 tensor, got {self.window.dtype}")
        B = self.K.shape[0] if self.K.dim() == 3 else -1
        if self.K.shape != (B, 3, 3) or B < 1:
            raise ValueError(f"K must have shape (B, 3, 3) with B >= 1, got {tuple(self.K.shape)}")
        if self.duration_s.shape != (B,):
            raise ValueError(f"duration_s must be ({B},), got {tuple(self.duration_s.shape)}")
        if self.speed is not None and self.speed.shape != (B,):
            raise ValueError(f"speed must be ({B},) m/s (NaN: unknown), got {tuple(self.speed.shape)}")
        if int(self.width) < 1 or int(self.height) < 1:
            raise ValueError(f"width and height must be positive, got {self.width}, {self.height}")
        devices = {str(a.device) for a in self._tensors()}
        if len(devices) > 1:
            raise ValueError(f"x, y, t, polarity, window, K, duration_s and speed must be on one device, got "
                             f"{sorted(devices)} (EventWindows.to(device=...) moves them all)")
        if self.x.device.type == "meta":   # shapes only: meta tensors hold no values to check
            return
        if not bool(torch.isfinite(self.K).all()):
            raise ValueError(f"K must be finite (no NaN or inf), got {self.K.tolist()}")
        if not bool(((self.K[:, 0, 0] > 0) & (self.K[:, 1, 1] > 0)).all()):
            raise ValueError(f"K must have positive focal lengths fx = K[:, 0, 0], fy = K[:, 1, 1] [px], got "
                             f"{self.K[:, 0, 0].tolist()}, {self.K[:, 1, 1].tolist()}")
        if not bool((self.duration_s > 0).all()):
            raise ValueError(f"duration_s must be ({B},) and > 0 s, got {self.duration_s.tolist()}")
        if self.speed is not None and not bool((torch.isnan(self.speed) | (self.speed >= 0)).all()):
            raise ValueError(f"speed must be ({B},) and >= 0 m/s (NaN: unknown), got {self.speed}")
        if n[0] and (int(self.window.min()) < 0 or int(self.window.max()) >= B):
            raise ValueError(f"window indices must lie in [0, {B}), got [{int(self.window.min())}, "
                             f"{int(self.window.max())}]")
        with torch.no_grad():
            for name in ("x", "y", "t"):
                value = getattr(self, name)
                if n[0] and not bool(torch.isfinite(value).all()):
                    raise ValueError(f"{name} must be finite (no NaN or inf)")
            if n[0]:
                slack = 1e-6 * self.duration_s.abs().max() + 1e-9   # float rounding of the times
                late = self.t - self.duration_s.to(self.t.dtype)[self.window]
                if bool((self.t < -slack).any()) or bool((late > slack).any()):
                    raise ValueError("t must be seconds since the start of each event's window, within [0, duration_s]"
                                     f" (got {float(self.t.min()):.6g}..{float(self.t.max()):.6g} s against durations "
                                     f"up to {float(self.duration_s.max()):.6g} s: microseconds?)")

    @property
    def count(self) -> int:
        """Number of windows B."""
        return int(self.K.shape[0])

    @property
    def dtype(self) -> torch.dtype:
        return self.x.dtype

    def __len__(self) -> int:
        return int(self.x.shape[0])

    def rays(self) -> torch.Tensor:
        """``K_b^-1 (x, y, 1)`` of every event (N, 3); kept for the next call unless the pixels or the
        intrinsics carry a gradient."""
        return self._kept("rays", self._rays)

    def _rays(self) -> torch.Tensor:
        pixels = torch.stack([self.x, self.y, torch.ones_like(self.x)], -1)
        return torch.einsum("nij,nj->ni", torch.linalg.inv(self.K.to(self.dtype))[self.window], pixels)

    def window_bounds(self) -> tuple[tuple[int, int], ...] | None:
        """``(start, end)`` of each window's events when every window's events are one contiguous run in window
        order (as :meth:`from_windows` and :meth:`from_padded` make them), else None."""
        return self._kept("bounds", self._window_bounds)

    def _window_bounds(self) -> tuple[tuple[int, int], ...] | None:
        window = self.window
        if len(window) and not bool((window[1:] >= window[:-1]).all()):
            return None
        ends = torch.cumsum(torch.bincount(window, minlength=self.count), 0).tolist()
        return tuple(zip([0] + ends[:-1], ends))

    def grid_weights(self, shape: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
        """Node indices (N, 4) int64, offset to each event's window (``window * gh * gw``), and bilinear
        weights (N, 4) of every event on a depth grid of ``shape`` (gh, gw) (:class:`cmax.warp.DepthGrid`);
        kept for the next call with that shape unless the pixels carry a gradient."""
        gh, gw = int(shape[0]), int(shape[1])

        def compute() -> tuple[torch.Tensor, torch.Tensor]:
            index, weight = DepthGrid((gh, gw), self.width, self.height).weights(self.x, self.y)
            return index + (self.window * (gh * gw))[:, None], weight

        return self._kept(("grid", gh, gw), compute)

    def _kept(self, key: object, compute):
        """``compute()``, computed once per key for a batch whose pixels and intrinsics need no gradient (the
        batch is immutable: a frozen dataclass of tensors nobody writes to)."""
        if self.x.requires_grad or self.y.requires_grad or self.K.requires_grad:
            return compute()
        kept = self.__dict__.setdefault("_kept_values", {})
        if key not in kept:
            kept[key] = compute()
        return kept[key]

    def _tensors(self) -> tuple[torch.Tensor, ...]:
        return tuple(a for a in (self.x, self.y, self.t, self.polarity, self.window, self.K, self.duration_s,
                                 self.speed) if a is not None)

    @property
    def device(self) -> torch.device:
        return self.x.device

    def to(self, dtype: torch.dtype | None = None, *, device: torch.device | str | None = None) -> "EventWindows":
        """The same events with the floating-point tensors (and the intrinsics, durations, speeds) in ``dtype``
        (None: as they are) and every tensor, the window indices too, on ``device`` (None: where it is)."""
        cast = lambda a: None if a is None else a.to(device=device, dtype=dtype)  # noqa: E731
        window = self.window if device is None else self.window.to(device)
        return EventWindows(cast(self.x), cast(self.y), cast(self.t), cast(self.polarity), window, cast(self.K),
                            cast(self.duration_s), self.width, self.height, cast(self.speed))

    def window_sum(self, values: torch.Tensor) -> torch.Tensor:
        """The sum (B,) over each window's events of ``values`` (N,), on the batch's device, in their dtype."""
        return torch.zeros(self.count, dtype=values.dtype, device=self.device).index_add(0, self.window, values)

    def with_speed(self, speed: torch.Tensor | Sequence[float] | None) -> "EventWindows":
        """The same events with the known speed (B,) [m/s] of each window (None: unknown)."""
        speed = None if speed is None else torch.as_tensor(speed, dtype=self.dtype).reshape(-1)
        return EventWindows(self.x, self.y, self.t, self.polarity, self.window, self.K, self.duration_s,
                            self.width, self.height, speed)

    @classmethod
    def from_warp_events(cls, windows: Sequence[WarpEvents], *, speed: Sequence[float] | None = None
                         ) -> "EventWindows":
        """Concatenate prepared ``windows`` (:meth:`cmax.warp.WarpEvents.from_events`) of one sensor size; ``speed``:
        the known ``|v|`` [m/s] of each window, or None."""
        if not windows or not all(isinstance(w, WarpEvents) for w in windows):
            raise TypeError("windows must be a non-empty sequence of cmax.warp.WarpEvents")
        size = (windows[0].width, windows[0].height)
        for i, w in enumerate(windows):
            if (w.width, w.height) != size:
                raise ValueError(f"windows[{i}] is {w.width}x{w.height}, windows[0] is {size[0]}x{size[1]}")
        dtype = windows[0].x.dtype
        lengths = torch.tensor([len(w) for w in windows])
        index = torch.repeat_interleave(torch.arange(len(windows)), lengths)
        cat = lambda name: torch.cat([getattr(w, name).to(dtype) for w in windows])  # noqa: E731
        duration = torch.tensor([w.duration_s for w in windows], dtype=torch.float64).to(dtype)
        K = torch.stack([w.K.to(dtype) for w in windows])
        out = cls(cat("x"), cat("y"), cat("t"), cat("polarity"), index, K, duration, size[0], size[1])
        return out.with_speed(speed)

    @classmethod
    def from_events(cls, events: Events, K: object, *, speed: float | None = None, **prepare) -> "EventWindows":
        """One window (B = 1) from ``events`` (:class:`cmax.Events`) and intrinsics ``K`` (3, 3), or the :class:`cmax.Camera`
        of their sensor, whose distortion is undone as :func:`cmax.fit` undoes it: each event the camera keeps
        (:func:`cmax.camera.pinhole_events`) is dithered over its sensor pixel and mapped through the lens,
        unrounded (:func:`cmax.camera.sensor_pixels`, :meth:`cmax.Camera.undistort_points`), with the fit's
        seeded subset and dither, so that both read the same positions.

        ``prepare`` goes to :meth:`cmax.warp.WarpEvents.from_events` (``max_events``,
        ``seed``, ``dtype``, ``pixels``, ``dither``; ``pixels`` and ``lens`` not with a lens camera, which
        gives them); ``speed`` is the known ``|v|`` [m/s].
        """
        warp_events = _prepared(events, K, prepare)
        if len(warp_events) < 2 or warp_events.duration_s <= 0:
            raise ValueError(f"events: need at least 2 events spanning a non-zero time, got {len(warp_events)}")
        return cls.from_warp_events([warp_events], speed=None if speed is None else [float(speed)])

    @classmethod
    def from_windows(cls, windows: Sequence[tuple[Events, object]], *, speed: Sequence[float] | None = None,
                     **prepare) -> "EventWindows":
        """B windows from ``windows``, a list of ``(events, K)`` pairs of one sensor size, ``K`` (3, 3) or a
        :class:`cmax.Camera` (its events prepared as :meth:`from_events` prepares them); ``speed`` (B,) [m/s] or
        None and ``**prepare`` as :meth:`from_events`."""
        if not windows:
            raise ValueError("windows: need at least one (events, K) pair")
        return cls.from_warp_events([_prepared(ev, K, prepare) for ev, K in windows], speed=speed)

    @classmethod
    def from_padded(cls, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, polarity: torch.Tensor,
                    valid: torch.Tensor, duration_s: torch.Tensor, K: torch.Tensor, *, width: int, height: int,
                    speed: torch.Tensor | None = None) -> "EventWindows":
        """From padded (B, Nmax) tensors (a collated data loader batch) and ``valid``, a (B, Nmax) bool mask of real events.

        ``x``, ``y`` [px]; ``polarity`` is signed (-1/+1); ``t`` in seconds since each window's start;
        ``width``, ``height``: the sensor size [px];
        ``duration_s`` (B,); ``K`` (B, 3, 3); ``speed`` (B,) [m/s] or None.
        """
        if x.dim() != 2 or not (x.shape == y.shape == t.shape == polarity.shape == valid.shape):
            raise ValueError(f"x, y, t, polarity, valid must share one shape (B, Nmax), got {tuple(x.shape)}, "
                             f"{tuple(y.shape)}, {tuple(t.shape)}, {tuple(polarity.shape)}, {tuple(valid.shape)}")
        if valid.dtype != torch.bool:
            raise TypeError(f"valid must be a bool tensor, got {valid.dtype}")
        index = torch.arange(x.shape[0], device=x.device)[:, None].expand_as(x)
        return cls(x[valid], y[valid], t[valid], polarity[valid], index[valid], K.to(x.dtype),
                   duration_s.to(x.dtype), int(width), int(height),
                   None if speed is None else speed.to(x.dtype))


def _prepared(events: Events, K: object, prepare: dict) -> WarpEvents:
    """``events`` with intrinsics ``K`` (3, 3) or a :class:`cmax.Camera` as :func:`cmax.fit` warps them: through
    :func:`cmax.camera.pinhole_events`, and for a camera with a lens each event dithered over its sensor pixel
    and mapped through the lens (:meth:`cmax.warp.WarpEvents.from_events` with ``pixels`` and ``lens``, the
    fit's one code path); ``prepare``: the other keywords of that method."""
    sensor = sensor_pixels(events, K)
    if sensor is None:
        return WarpEvents.from_events(*pinhole_events(events, K), **prepare)
    given = sorted({"pixels", "lens"} & set(prepare))
    if given:
        raise ValueError(f"{', '.join(given)}: not with a cmax.Camera with a lens, whose events are dithered over "
                         "their sensor pixels and mapped through the lens (give the undistorted events and the "
                         "camera's pinhole_K to pass your own positions)")
    undistorted, pinhole = pinhole_events(events, K)
    return WarpEvents.from_events(undistorted, pinhole, pixels=sensor, lens=K.undistort_points, **prepare)
