"""Hot pixels: pixels that fire far more often than a moving scene makes any pixel fire.

A hot pixel (a sensor defect) or a pixel on a flickering light fires at a steady rate whatever the
camera does, so its events carry no motion, and in contrast maximization a few of them pull the fit
(measured in ``docs/fitting.md``). A moving edge makes a pixel fire a few to a few tens of times as it
passes (its contrast over the contrast threshold), so the event counts of a window's active pixels
have a short tail, while a hot pixel's count grows with the window's length. The rule, as the per-pixel
rate filters of the cameras' own software (dv-processing's ``HotPixelFilter``, Metavision's activity
filters) but without a calibration recording:

    hot  <=>  count > max(factor * p99(counts of the active pixels), min_events)

By construction at most 1% of the active pixels can exceed it. That rule alone misses a hot pixel that
fires less than about 1% of a window's events (its count stays under 8 times the 99th percentile), and
such pixels still pull the fit. A second rule finds them by what sets them apart besides their count
(:func:`lone_steady_pixels`, when the events' times are at hand): a moving edge that makes a pixel fire
passes over its neighbours too, so a scene pixel shares its count with at least two of its eight
neighbours, while a hot pixel fires alone; and a steady rate spreads a pixel's events over the whole
window one at a time, while an edge passes a pixel in a fraction of it and makes it fire a burst of events
(its contrast over the threshold) each time. So a pixel is also hot when

    count >= neighbour_min_events  and  count > neighbour_factor * (busiest neighbour's count + 1)
    and  its event times pass a Kolmogorov-Smirnov test of a constant rate over the window
         (sqrt(count) * D < 1.63, the 1% level)
    and  its gaps are not bursty: the number of gaps shorter than half the mean gap (a share
         1 - exp(-1/2) of a constant rate's) stays within 2.5 binomial standard deviations of that share

(two hot pixels side by side hide each other: rare, as they lie at random).

A pixel on a light that flickers with the mains (100 Hz, or 120 Hz where the mains is 60 Hz) fires as
often as its neighbours on the same light, so neither rule finds it, yet a few dozen such pixels pull a
rotation fit by 15-20% with an ``ok`` verdict. Its events of one polarity come at one phase of the
flicker in cycle after cycle, which a moving edge's do not: a third rule (:func:`flicker_pixels`) calls a
pixel hot when, for 100 or 120 Hz, its events of one polarity hold a Rayleigh statistic of phase locking
``n R^2 >= 9.2`` (p = 1e-4 for times at random) with a mean resultant length ``R >= 0.7``, and fall in at
least half of the window's cycles (at least 3 of them), their phases locked from cycle to cycle, and it
belongs to a 2 x 2 square of such pixels (a lamp lights an area; a line 1 px wide is a moving texture).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cmax.events import Events, require_events

__all__ = ["HotPixelFilter", "check_filter", "flicker_pixels", "hot_pixels", "hot_pixels_of_counts",
           "lone_steady_pixels", "no_pixels", "off_pixels", "pixel_counts", "without_pixels"]

#: The Kolmogorov-Smirnov statistic ``sqrt(n) * D`` above which ``n`` event times are not those of a constant
#: rate, at the 1% level (the asymptotic critical value; conservative for small ``n``).
KS_CRITICAL_1PCT = 1.63
#: Mains flicker frequencies [Hz] that :func:`flicker_pixels` tests (twice 50 Hz and twice 60 Hz).
MAINS_FLICKER_HZ = (100.0, 120.0)
#: Rayleigh statistic ``n R^2`` above which a pixel's phases are locked to the flicker (p = 1e-4 at random).
FLICKER_RAYLEIGH = 9.2
#: The least mean resultant length ``R`` of a flickering pixel's phases (1: all at one phase).
FLICKER_MIN_R = 0.7

#: The binomial z-score of a pixel's short gaps (under half its mean gap) above which it fires in bursts.
BURST_Z = 2.5


@dataclass(frozen=True)
class HotPixelFilter:
    """The rules of :func:`hot_pixels` with their constants, as the fit (``FitSettings.hot_pixels``) and
    EMVS (``EMVS.hot_pixels``) take it; ``None`` in their place keeps every event.

    >>> HotPixelFilter(factor=0)
    Traceback (most recent call last):
    ...
    ValueError: factor must be a positive number, got 0
    """

    factor: float = 8.0
    min_events: int = 30
    #: The rule of lone, steady pixels (:func:`lone_steady_pixels`); None: the count rule alone.
    neighbour_factor: float | None = 8.0
    neighbour_min_events: int = 20
    #: The flicker frequencies [Hz] of the rule of flickering pixels (:func:`flicker_pixels`); None: not tested.
    flicker_hz: tuple[float, ...] | None = MAINS_FLICKER_HZ

    def __post_init__(self) -> None:
        _check(self.factor, self.min_events)
        if self.neighbour_factor is not None:
            _check(self.neighbour_factor, self.neighbour_min_events, "neighbour_")
        if self.flicker_hz is not None:
            _check_frequencies(self.flicker_hz)

    def find(self, events: Events) -> np.ndarray:
        """The hot pixels of ``events``: ``(K, 2)`` int64 ``(x, y)`` (:func:`hot_pixels`)."""
        return hot_pixels(events, self.factor, self.min_events, self.neighbour_factor, self.neighbour_min_events,
                          self.flicker_hz)

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


def _check(factor: object, min_events: object, prefix: str = "") -> None:
    if isinstance(factor, bool) or not (isinstance(factor, (int, float, np.number)) and np.isfinite(factor)
                                        and factor > 0):
        raise ValueError(f"{prefix}factor must be a positive number, got {factor!r}")
    if not (isinstance(min_events, (int, np.integer)) and not isinstance(min_events, bool) and min_events >= 0):
        raise ValueError(f"{prefix}min_events must be a whole number >= 0, got {min_events!r}")


def _check_frequencies(flicker_hz: object) -> None:
    values = np.asarray(flicker_hz, dtype=object).ravel() if isinstance(flicker_hz, (tuple, list)) else None
    if values is None or not len(values) or not all(
            isinstance(f, (int, float, np.number)) and not isinstance(f, bool) and np.isfinite(f) and f > 0
            for f in values):
        raise ValueError(f"flicker_hz must be a tuple of positive frequencies in Hz, got {flicker_hz!r}")


def hot_pixels(events: Events, factor: float = 8.0, min_events: int = 30, neighbour_factor: float | None = 8.0,
               neighbour_min_events: int = 20, flicker_hz: tuple[float, ...] | None = MAINS_FLICKER_HZ) -> np.ndarray:
    """The hot pixels of ``events``: ``(K, 2)`` int64 ``(x, y)``, sorted by ``y * width + x``.

    A pixel is hot when it holds more than ``factor`` times the 99th percentile of the event counts of
    the pixels with events, and more than ``min_events`` events; or when it fires alone at a steady rate
    (:func:`lone_steady_pixels` with ``neighbour_factor`` and ``neighbour_min_events``; None: not tested);
    or when its events lock to the phase of a flicker at one of ``flicker_hz`` (:func:`flicker_pixels`;
    None: not tested). Module docstring.

    >>> import numpy as np
    >>> x = np.r_[np.arange(100) % 10, np.full(50, 3)]           # 100 pixels with one event, one with 51
    >>> events = Events(x, np.r_[np.arange(100) // 10, np.full(50, 2)], np.arange(150), np.ones(150), 10, 10)
    >>> hot_pixels(events).tolist()
    [[3, 2]]
    """
    require_events(events)
    counts = pixel_counts(events)
    found = [hot_pixels_of_counts(counts, factor, min_events)]
    if neighbour_factor is not None:
        found.append(lone_steady_pixels(events, neighbour_factor, neighbour_min_events, counts=counts))
    if flicker_hz is not None:
        found.append(flicker_pixels(events, flicker_hz))
    flat = np.unique(np.concatenate([pixels[:, 1] * events.width + pixels[:, 0] for pixels in found]))
    return np.column_stack([flat % events.width, flat // events.width]).astype(np.int64)


def flicker_pixels(events: Events, flicker_hz: tuple[float, ...] = MAINS_FLICKER_HZ) -> np.ndarray:
    """The pixels of ``events`` on a flickering light: ``(K, 2)`` int64 ``(x, y)``, sorted by ``y * width + x``.

    For each frequency ``f`` of ``flicker_hz`` [Hz] over which the window spans at least 3 cycles, and each
    polarity, the phases ``2 pi f (t - t[0])`` of a pixel's events give a mean resultant length ``R`` (1: all at
    one phase, about ``1 / sqrt(n)`` for times at random); the pixel flickers when ``n R^2 >=
    FLICKER_RAYLEIGH``, ``R >= FLICKER_MIN_R``, its events fall in at least half of the window's cycles, and
    the mean phases of those cycles (one unit vector each, so that one burst of an edge counts once) have a
    mean resultant length ``>= FLICKER_MIN_R`` too; and it belongs to a 2 x 2 square of such pixels (a lamp
    lights an area, while a moving texture that happens to repeat at 100 Hz, e.g. a dashed road marking, locks a
    lone pixel or a line one pixel wide).

    >>> t = np.r_[np.arange(10) * 10_000 + 2_000, np.arange(10) * 10_000 + 7_000]   # ON, then OFF, at 100 Hz
    >>> x, y = np.repeat([1, 2, 1, 2], 20), np.repeat([1, 1, 2, 2], 20)           # on 2x2 pixels of a lamp
    >>> lamp = Events(x, y, np.tile(t, 4), np.tile(np.r_[np.ones(10), np.zeros(10)], 4), 4, 4, sort=True)
    >>> flicker_pixels(lamp).tolist()
    [[1, 1], [2, 1], [1, 2], [2, 2]]
    """
    require_events(events)
    _check_frequencies(flicker_hz)
    width, size = events.width, events.width * events.height
    if len(events) < 2:
        return no_pixels()
    flat = events.y.astype(np.int64) * width + events.x
    span_s = float(events.t[-1] - events.t[0]) * 1e-6
    by_polarity = []
    for polarity in (0, 1):                          # n R^2 >= FLICKER_RAYLEIGH needs at least as many events
        chosen = events.p == polarity
        n = np.bincount(flat[chosen], minlength=size)
        chosen &= n[flat] >= FLICKER_RAYLEIGH
        # the candidate pixels and each event's among them: the sums below run over these, not the whole sensor
        candidates, pixel = np.unique(flat[chosen], return_inverse=True)
        by_polarity.append((candidates, n[candidates], pixel, (events.t[chosen] - events.t[0]) * 1e-6))
    flickering = np.zeros(size, bool)
    for f in flicker_hz:
        cycles = span_s * f
        if cycles < 3:
            continue
        for candidates, n, pixel, seconds in by_polarity:
            m = candidates.size
            turns = seconds * f
            cycle = np.floor(turns).astype(np.int64)
            angle = 2 * np.pi * turns
            cos, sin = np.cos(angle), np.sin(angle)
            resultant = np.hypot(np.bincount(pixel, cos, m), np.bincount(pixel, sin, m))
            r = resultant / np.maximum(n, 1)
            # each cycle's mean phase as one unit vector: a burst within one cycle counts once
            pairs, pair_of = np.unique(pixel * (int(cycles) + 1) + cycle, return_inverse=True)
            pair_x = np.bincount(pair_of, cos, len(pairs))
            pair_y = np.bincount(pair_of, sin, len(pairs))
            norm = np.maximum(np.hypot(pair_x, pair_y), 1e-12)
            owner = pairs // (int(cycles) + 1)
            cycles_hit = np.bincount(owner, minlength=m)
            r_cycles = np.hypot(np.bincount(owner, pair_x / norm, m), np.bincount(owner, pair_y / norm, m))
            r_cycles /= np.maximum(cycles_hit, 1)
            flickering[candidates] |= ((n * r**2 >= FLICKER_RAYLEIGH) & (r >= FLICKER_MIN_R)
                                       & (r_cycles >= FLICKER_MIN_R) & (cycles_hit >= max(3, cycles / 2)))
    lit = flickering.reshape(events.height, width)
    square = np.pad(lit[:-1, :-1] & lit[1:, :-1] & lit[:-1, 1:] & lit[1:, 1:], 1)   # 2x2 squares, by top-left
    in_square = square[1:, 1:] | square[:-1, 1:] | square[1:, :-1] | square[:-1, :-1]
    kept = np.flatnonzero(lit & in_square)
    return np.column_stack([kept % width, kept // width]).astype(np.int64)


def lone_steady_pixels(events: Events, neighbour_factor: float = 8.0, min_events: int = 20, *,
                       counts: np.ndarray | None = None) -> np.ndarray:
    """The pixels of ``events`` that fire alone at a steady rate: ``(K, 2)`` int64 ``(x, y)``, sorted by
    ``y * width + x``.

    A pixel qualifies when it holds at least ``min_events`` events, more than ``neighbour_factor`` times
    ``1 +`` the count of its busiest of 8 neighbours (pixels outside the sensor count 0), its event times
    pass a Kolmogorov-Smirnov test of a constant rate over the window ``[t[0], t[-1]]``
    (``sqrt(n) * D < KS_CRITICAL_1PCT``), and its gaps are not bursty (:func:`_burst_z` below ``BURST_Z``).
    ``counts`` (H, W): :func:`pixel_counts` of ``events`` if known.

    >>> rng = np.random.default_rng(0)                      # 400 pixels with one event each, one steady pixel
    >>> x = np.r_[np.arange(400) % 20, np.full(25, 7)]
    >>> y = np.r_[np.arange(400) // 20, np.full(25, 3)]
    >>> t = np.r_[rng.integers(0, 10_000, 400), np.arange(25) * 400]
    >>> lone_steady_pixels(Events(x, y, t, np.ones(425), 20, 20, sort=True)).tolist()
    [[7, 3]]
    """
    require_events(events)
    _check(neighbour_factor, min_events, "neighbour_")
    counts = pixel_counts(events) if counts is None else counts
    height, width = counts.shape
    ys, xs = np.nonzero(counts >= max(min_events, 1))
    if not len(ys):
        return no_pixels()
    padded = np.pad(counts, 1)
    neighbours = np.stack([padded[ys + 1 + dy, xs + 1 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx])
    alone = counts[ys, xs] > neighbour_factor * (neighbours.max(axis=0) + 1)
    candidates = ys[alone].astype(np.int64) * width + xs[alone]
    if not len(candidates) or len(events) < 2 or events.t[-1] == events.t[0]:
        return no_pixels()
    flat = events.y.astype(np.int64) * width + events.x
    chosen = np.isin(flat, candidates)
    order = np.argsort(flat[chosen], kind="stable")           # by pixel, each pixel's times in time order
    pixel, times = flat[chosen][order], events.t[chosen][order]
    starts = np.searchsorted(pixel, candidates)
    ends = np.searchsorted(pixel, candidates, side="right")
    t0, span = float(events.t[0]), float(events.t[-1] - events.t[0])
    steady = [_ks_uniform((times[a:b] - t0) / span) < KS_CRITICAL_1PCT and _burst_z(times[a:b], span) < BURST_Z
              for a, b in zip(starts, ends)]
    kept = candidates[np.asarray(steady, bool)]
    return np.column_stack([kept % width, kept // width]).astype(np.int64)


def _burst_z(times: np.ndarray, span: float) -> float:
    """How bursty the sorted times ``times`` (n,) [µs] of one pixel over a window ``span`` µs long are: the
    binomial z-score of the number of its n - 1 gaps shorter than half the mean gap ``span / n``, whose share
    at a constant rate is ``1 - exp(-1/2)``."""
    gaps = np.diff(times.astype(np.float64))
    share = 1.0 - np.exp(-0.5)
    expected = share * len(gaps)
    return float((np.sum(gaps < 0.5 * span / len(times)) - expected) / np.sqrt(expected * (1.0 - share)))


def _ks_uniform(u: np.ndarray) -> float:
    """``sqrt(n) * D``: the Kolmogorov-Smirnov statistic of the sorted values ``u`` (n,) in [0, 1] against the
    uniform distribution."""
    n = len(u)
    i = np.arange(1, n + 1)
    return float(max((i / n - u).max(), (u - (i - 1) / n).max()) * np.sqrt(n))


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
    return events[off_pixels(events, pixels)]


def off_pixels(events: Events, pixels: np.ndarray) -> np.ndarray:
    """Which of ``events`` (N,) bool lie off ``pixels`` ``(K, 2)`` ``(x, y)``: those :func:`without_pixels` keeps."""
    pixels = np.asarray(pixels, dtype=np.int64).reshape(-1, 2)
    drop = np.zeros(events.width * events.height, bool)
    drop[pixels[:, 1] * events.width + pixels[:, 0]] = True
    return ~drop[events.y.astype(np.int64) * events.width + events.x]
