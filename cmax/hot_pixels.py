"""Hot pixels: pixels that fire far more often than a moving scene makes any pixel fire.

A hot pixel (a sensor defect) or a pixel on a flickering light fires at a steady rate whatever the
camera does, so its events carry no motion, and in contrast maximization a few of them pull the fit
(measured in ``docs/fitting.md``). A moving edge makes a pixel fire a few to a few tens of times as it
passes (its contrast over the contrast threshold), so the event counts of a window's active pixels
have a short tail, while a hot pixel's count grows with the window's length. The rule, as the per-pixel
rate filters of the cameras' own software (dv-processing's ``HotPixelFilter``, Metavision's activity
filters) but without a calibration recording:

    hot  <=>  count > max(factor * p99(counts of the active pixels), min_events)

By construction at most 1% of the active pixels can exceed it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cmax.events import Events, require_events

__all__ = ["HotPixelFilter", "check_filter", "hot_pixels", "hot_pixels_of_counts", "no_pixels", "pixel_counts",
           "without_pixels"]


@dataclass(frozen=True)
class HotPixelFilter:
    """The rule of :func:`hot_pixels` with its two constants, as the fit (``FitSettings.hot_pixels``) and
    EMVS (``EMVS.hot_pixels``) take it; ``None`` in their place keeps every event.

    >>> HotPixelFilter(factor=0)
    Traceback (most recent call last):
    ...
    ValueError: factor must be a positive number, got 0
    """

    factor: float = 8.0
    min_events: int = 30

    def __post_init__(self) -> None:
        _check(self.factor, self.min_events)

    def find(self, events: Events) -> np.ndarray:
        """The hot pixels of ``events``: ``(K, 2)`` int64 ``(x, y)`` (:func:`hot_pixels`)."""
        return hot_pixels(events, self.factor, self.min_events)

    def apply(self, events: Events) -> tuple[Events, np.ndarray]:
        """``events`` without the events of their hot pixels, and those pixels ``(K, 2)`` ``(x, y)``."""
        hot = self.find(events)
        return without_pixels(events, hot), hot


def check_filter(value: object) -> None:
    """Refuse a ``hot_pixels`` setting that is neither a :class:`HotPixelFilter` nor None."""
    if value is not None and not isinstance(value, HotPixelFilter):
        raise TypeError(f"hot_pixels must be a cmax.hot_pixels.HotPixelFilter or None, got {type(value).__name__}")


def no_pixels() -> np.ndarray:
    """An empty ``(0, 2)`` int64 list of pixels ``(x, y)`` (no hot pixel)."""
    return np.zeros((0, 2), np.int64)


def pixel_counts(events: Events) -> np.ndarray:
    """The events of each pixel, (height, width) int64."""
    flat = events.y.astype(np.int64) * events.width + events.x
    return np.bincount(flat, minlength=events.width * events.height).reshape(events.height, events.width)


def _check(factor: object, min_events: object) -> None:
    if isinstance(factor, bool) or not (isinstance(factor, (int, float, np.number)) and np.isfinite(factor)
                                        and factor > 0):
        raise ValueError(f"factor must be a positive number, got {factor!r}")
    if not (isinstance(min_events, (int, np.integer)) and not isinstance(min_events, bool) and min_events >= 0):
        raise ValueError(f"min_events must be a whole number >= 0, got {min_events!r}")


def hot_pixels(events: Events, factor: float = 8.0, min_events: int = 30) -> np.ndarray:
    """The hot pixels of ``events``: ``(K, 2)`` int64 ``(x, y)``, sorted by ``y * width + x``.

    A pixel is hot when it holds more than ``factor`` times the 99th percentile of the event counts of
    the pixels with events, and more than ``min_events`` events (module docstring).

    >>> import numpy as np
    >>> x = np.r_[np.arange(100) % 10, np.full(50, 3)]           # 100 pixels with one event, one with 51
    >>> events = Events(x, np.r_[np.arange(100) // 10, np.full(50, 2)], np.arange(150), np.ones(150), 10, 10)
    >>> hot_pixels(events).tolist()
    [[3, 2]]
    """
    require_events(events)
    return hot_pixels_of_counts(pixel_counts(events), factor, min_events)


def hot_pixels_of_counts(counts: np.ndarray, factor: float = 8.0, min_events: int = 30) -> np.ndarray:
    """:func:`hot_pixels` from the per-pixel event counts ``counts`` (H, W) of a window or a recording:
    ``(K, 2)`` int64 ``(x, y)``, sorted by ``y * W + x``."""
    _check(factor, min_events)
    counts = np.asarray(counts)
    if counts.ndim != 2:
        raise ValueError(f"counts must be an (H, W) image of per-pixel event counts, got shape {counts.shape}")
    active = counts[counts > 0]
    if not active.size:
        return no_pixels()
    threshold = max(factor * float(np.percentile(active, 99)), float(min_events))
    y, x = np.nonzero(counts > threshold)
    return np.column_stack([x, y]).astype(np.int64)


def without_pixels(events: Events, pixels: np.ndarray) -> Events:
    """``events`` without those of ``pixels`` ``(K, 2)`` ``(x, y)`` (the others in their order)."""
    pixels = np.asarray(pixels, dtype=np.int64).reshape(-1, 2)
    if not len(pixels):
        return events
    drop = np.zeros(events.width * events.height, bool)
    drop[pixels[:, 1] * events.width + pixels[:, 0]] = True
    return events[~drop[events.y.astype(np.int64) * events.width + events.x]]
