"""The ESIM event model: events from a sequence of time-stamped frames.

Each pixel keeps a reference log intensity ``L_ref``, initialised to the
first frame. Between two samples the log intensity

    L = log(I / 255 + eps)                (I: 8-bit grey value in [0, 255])

is taken as linear in time. Every crossing of ``L_ref + k*Cp`` (ON) or
``L_ref - k*Cn`` (OFF), ``k = 1, 2, ...``, emits one event, time-stamped by
linear interpolation inside the interval, and moves ``L_ref`` by one
threshold. A pixel may fire several events per interval; they all have the
polarity of the change, since ``L`` is monotonic between two samples.

The arithmetic follows the reference C++ implementation (``esim_py`` of
uzh-rpg/rpg_vid2e) so that both give the same events on the same frames:

* ``L`` is float32: ``log(I * float32(1/255) + float32(eps))`` with OpenCV's
  own ``cv::log`` algorithm, reimplemented bit for bit in
  :mod:`cmax.sim._cvlog` (the ``cv2`` wheels call Intel IPP instead, which
  rounds differently). For uint8 frames a 256-entry table of these values
  is used; integer-valued float frames give the same values.
* ``L_ref`` is a float32 value that moves one float32 threshold at a time
  (``L_ref += C`` in float32, sequentially). This matters: a pixel that
  returns to the grey value it started from lands *exactly* on a crossing
  level, and whether it fires depends on the float32 rounding of that sum.
  The sequential sums are computed by ``np.add.accumulate`` along rows of
  candidate levels, vectorised over pixels.
* Crossing times are ``t0 + (level - L0) / (L1 - L0) * (t1 - t0)``, with the
  two differences in float32 and the rest in float64, then rounded to whole
  microseconds, half up: ``floor(tau + 0.5)``. A crossing therefore lies in
  ``[t0, t1]`` µs.

Events of one interval are ordered by time, ties by pixel in raster order
(row-major, ``y * width + x``), then by crossing order; this is a stable
version of the reference's ``std::sort`` by time. On the reference's own test
frames (``esim_truck_pan``, Cp = Cn = 0.2 and 0.1) the events agree one to
one with the C++ ESIM's, within 1 µs (``tests/test_sim_esim.py``).

Everything is vectorised over pixels; Python loops run over frames, over
the few power-of-two groups of crossings per pixel, and (with a refractory
period only) over the rank of an event within its pixel in one interval.

References
----------
H. Rebecq, D. Gehrig, D. Scaramuzza. "ESIM: an Open Event Camera Simulator."
Conference on Robot Learning (CoRL), 2018.
https://proceedings.mlr.press/v87/rebecq18a.html
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from cmax.events import Events
from cmax.sim._cvlog import _cv_log32f, _fma32  # noqa: F401  (_fma32: imported by the tests)

__all__ = [
    "MIN_THRESHOLD",
    "MIN_THRESHOLD_FRACTION",
    "Crossings",
    "EsimSettings",
    "EventSimulator",
    "log_intensity",
    "threshold_crossings",
]

#: Per-pixel thresholds drawn with ``threshold_sigma > 0`` are clipped to at
#: least this fraction of the nominal threshold (``0.1 * cp`` and ``0.1 * cn``).
MIN_THRESHOLD_FRACTION = 0.1

#: Smallest accepted ``cp`` / ``cn``: float32 log levels (resolution ~5e-7)
#: must move by a threshold, and a full 0..255 change then gives at most
#: about 7,000 events per pixel and interval.
MIN_THRESHOLD = 1e-3

_NEVER = np.iinfo(np.int64).min // 4  # last event time of a pixel that has not fired yet
_MAX_SENSOR_SIZE = 65535
_FLOAT32_TINY = float(np.finfo(np.float32).tiny)
_REAL_TYPES = (int, float, np.integer, np.floating)


# -- settings ---------------------------------------------------------------------------
def _real(name: str, value: object, *, positive: bool) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, _REAL_TYPES):
        raise TypeError(f"{name} must be a real number, got {value!r}")
    value = float(value)
    if not math.isfinite(value) or value < 0 or (positive and value == 0):
        kind = "positive" if positive else "non-negative"
        raise ValueError(f"{name} must be a finite {kind} number, got {value}")
    return value


def _check_log_eps(value: object) -> float:
    value = _real("log_eps", value, positive=True)
    if not _FLOAT32_TINY <= value <= 1e30:
        raise ValueError(
            f"log_eps must lie in [{_FLOAT32_TINY:.3g}, 1e30] (a normal float32), got {value}"
        )
    return value


def _whole(name: str, value: object) -> int:
    """An integer from an int or a float holding a whole number."""
    if isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be an integer, got {value!r}")
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        if math.isfinite(value) and float(value).is_integer():
            return int(value)
        raise ValueError(f"{name} must be a whole number of microseconds, got {value}")
    raise TypeError(f"{name} must be an integer, got {value!r}")


@dataclass(frozen=True)
class EsimSettings:
    """Settings of the ESIM event model; validated on construction.

    Attributes
    ----------
    cp, cn : float
        ON and OFF contrast thresholds in log-intensity units (> 0).
    threshold_sigma : float
        Relative standard deviation of the per-pixel threshold mismatch: a
        fixed map ``C * (1 + threshold_sigma * N(0, 1))`` per polarity, drawn
        once per sensor from ``seed`` and clipped to at least
        ``MIN_THRESHOLD_FRACTION * C``. 0 (default) disables it.
    refractory_us : int
        Refractory period in µs (>= 0). An event of a pixel less than
        ``refractory_us`` after that pixel's previous *emitted* event is
        dropped, but ``L_ref`` still moves by its threshold: the pixel is
        reset while blind, as in the reference ESIM.
    log_eps : float
        ``eps`` of ``L = log(I/255 + eps)`` (> 0).
    seed : int or None
        Seed of the threshold map and the noise (>= 0); None draws fresh
        entropy once per simulator.
    shot_noise_rate_hz : float
        Rate of shot-noise events per pixel in Hz (>= 0): a Poisson process
        per pixel, polarity ON or OFF with equal probability, uniform times.
    leak_rate_hz : float
        Rate of leak events per pixel in Hz on a static scene (>= 0): the
        reference level of every pixel drifts down by ``leak_rate_hz * Cp``
        per second, so that ON events appear at that rate (the v2e model),
        with a random per-pixel phase drawn at the first frame.
    """

    cp: float = 0.2
    cn: float = 0.2
    threshold_sigma: float = 0.0
    refractory_us: int = 0
    log_eps: float = 1e-3
    seed: int | None = None
    shot_noise_rate_hz: float = 0.0
    leak_rate_hz: float = 0.0

    def __post_init__(self) -> None:
        fix = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731
        for name in ("cp", "cn"):
            value = _real(name, getattr(self, name), positive=True)
            if value < MIN_THRESHOLD:
                raise ValueError(f"{name} must be at least {MIN_THRESHOLD}, got {value}")
            fix(name, value)
        fix("threshold_sigma", _real("threshold_sigma", self.threshold_sigma, positive=False))
        refractory = _whole("refractory_us", self.refractory_us)
        if refractory < 0:
            raise ValueError(f"refractory_us must be >= 0 µs, got {refractory}")
        fix("refractory_us", refractory)
        fix("log_eps", _check_log_eps(self.log_eps))
        if self.seed is not None:
            seed = self.seed
            if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)):
                raise TypeError(f"seed must be a non-negative integer or None, got {self.seed!r}")
            if self.seed < 0:
                raise ValueError(f"seed must be a non-negative integer or None, got {self.seed}")
            fix("seed", int(self.seed))
        for name in ("shot_noise_rate_hz", "leak_rate_hz"):
            fix(name, _real(name, getattr(self, name), positive=False))


# -- log intensity ----------------------------------------------------------------------
def _grey_frame(frame: object, name: str) -> np.ndarray:
    """(H, W) grey values as uint8 or float32 from a checked (H, W) or BGR (H, W, 3) frame."""
    array = np.asarray(frame)
    if array.dtype.kind == "b" or array.dtype.kind not in "uif":
        raise TypeError(f"{name} must hold grey values (uint8 or float), got dtype {array.dtype}")
    colour = array.ndim == 3 and array.shape[2] == 3
    if array.ndim != 2 and not colour:
        raise ValueError(f"{name} must have shape (H, W) or (H, W, 3) (BGR), got {array.shape}")
    if array.shape[0] == 0 or array.shape[1] == 0:
        raise ValueError(f"{name} must not be empty, got shape {array.shape}")
    if array.shape[0] > _MAX_SENSOR_SIZE or array.shape[1] > _MAX_SENSOR_SIZE:
        raise ValueError(f"{name} is larger than {_MAX_SENSOR_SIZE} pixels: {array.shape}")
    if array.dtype != np.uint8:
        if array.dtype.kind == "f" and not np.isfinite(array).all():
            raise ValueError(f"{name} contains NaN or infinite values")
        low, high = array.min(), array.max()
        if low < 0 or high > 255:
            raise ValueError(f"{name} must hold grey values in [0, 255], got [{low}, {high}]")
        array = array.astype(np.uint8 if array.dtype.kind in "iu" else np.float32)
    if colour:
        array = cv2.cvtColor(np.ascontiguousarray(array), cv2.COLOR_BGR2GRAY)
    return array


def _log_float32(grey: np.ndarray, log_eps: float) -> np.ndarray:
    """``cv::log(grey * float32(1/255) + float32(eps))`` in float32, same shape."""
    scaled = grey.astype(np.float32) * np.float32(1.0 / 255.0) + np.float32(log_eps)
    return _cv_log32f(scaled)


def _log_grey(grey: np.ndarray, log_eps: float, table: np.ndarray | None = None) -> np.ndarray:
    """Log of checked grey values: a 256-entry table for uint8 and whole-numbered floats."""
    table = _log_float32(np.arange(256, dtype=np.float32), log_eps) if table is None else table
    if grey.dtype != np.uint8:
        whole = grey.astype(np.uint8)  # the same float32 values give the same logs
        if not np.array_equal(whole, grey):
            return _log_float32(grey, log_eps)
        grey = whole
    return cv2.LUT(grey, table)  # = table[grey], 8x faster


def log_intensity(frame: object, log_eps: float = 1e-3) -> np.ndarray:
    """Log intensity ``L = log(I/255 + eps)`` of one frame, as ESIM computes it.

    Parameters
    ----------
    frame : array_like, shape (H, W) or (H, W, 3)
        Grey values in [0, 255] (uint8, any integer type or float). Colour
        frames are taken as **BGR** (OpenCV's order, as read by
        ``cv2.VideoCapture``) and converted with ``cv2.COLOR_BGR2GRAY``.
    log_eps : float
        ``eps`` (> 0).

    Returns
    -------
    ndarray, shape (H, W), float32
        ``log(I * float32(1/255) + float32(eps))`` in float32, bit for bit as
        OpenCV's ``cv::log`` (see the module notes); a uint8 frame and the
        same values as floats give identical results.

    Examples
    --------
    >>> log_intensity(np.full((2, 3), 255, np.uint8)).shape
    (2, 3)
    """
    log_eps = _check_log_eps(log_eps)
    return _log_grey(_grey_frame(frame, "frame"), log_eps)


# -- the crossings of one interval ------------------------------------------------------
class Crossings(NamedTuple):
    """Threshold crossings of one interval, as returned by :func:`threshold_crossings`.

    ``pixel`` (M,) int64 flat pixel indices, sorted, each pixel's crossings in
    order; ``level`` (M,) float32 crossed levels; ``polarity`` (M,) int8
    (1 ON, 0 OFF); ``ref`` (N,) float32 the reference levels after the interval.
    """

    pixel: np.ndarray
    level: np.ndarray
    polarity: np.ndarray
    ref: np.ndarray


def _bucket_levels(ref, log0, log1, step, up, count):
    """Sequential float32 levels ``ref + k*step`` (k = 1..width), (m, width), and how
    many of each row are crossed (the leading ``lo < level <= hi`` ones, sign-flipped down).

    Levels are strictly monotonic along a row, so the crossed ones are a prefix
    once the first lies beyond ``log0``.
    """
    width = int(count.max())
    sign = np.where(up, np.float32(1), np.float32(-1))
    if width <= 16:  # column by column: cheaper than accumulate along short rows
        columns = [ref + step]
        for _ in range(width - 1):
            columns.append(columns[-1] + step)  # sequential, like L_ref += C
        levels = np.stack(columns, axis=1)
    else:
        levels = np.empty((ref.size, width), np.float32)
        levels[:, 0] = ref + step
        levels[:, 1:] = step[:, None]
        np.add.accumulate(levels, axis=1, dtype=np.float32, out=levels)
        columns = levels.T
    high = log1 * sign
    crossed = np.zeros(ref.size, np.int64)
    for column in columns:
        crossed += column * sign <= high
    crossed[levels[:, 0] * sign <= log0 * sign] = 0
    return levels, crossed


def threshold_crossings(
    ref: np.ndarray,
    log0: np.ndarray,
    log1: np.ndarray,
    c_on: np.ndarray | np.float32,
    c_off: np.ndarray | np.float32,
) -> Crossings:
    """All crossings of ``ref + k*c_on`` / ``ref - k*c_off`` between two samples.

    A pixel whose log intensity goes up from ``log0`` to ``log1`` crosses the
    levels ``ref + k*c_on`` with ``log0 < level <= log1``, ``k = 1, 2, ...``
    (down: ``ref - k*c_off`` with ``log1 <= level < log0``); its reference
    ends on the last level crossed. Levels are float32 running sums, as in
    the reference ESIM. No loop over pixels: each pixel within 10 % of a
    threshold from its next level gets ``floor((log1 - ref)/C) + 2``
    candidate levels (grouped by powers of two of that number), computed with
    ``np.add.accumulate``; float32 rounding moves a level by far less than
    that margin.

    Parameters
    ----------
    ref, log0, log1 : ndarray, shape (N,), float32
        Reference levels and the log intensity at the two samples.
    c_on, c_off : float32 scalar or ndarray, shape (N,)
        Positive ON and OFF thresholds.

    Returns
    -------
    Crossings
        Sorted by pixel, then in crossing (= time) order.
    """
    arrays = {"ref": ref, "log0": log0, "log1": log1}
    for name, value in (("c_on", c_on), ("c_off", c_off)):
        if np.ndim(value):
            arrays[name] = value
        elif not (isinstance(value, np.float32) and value > 0):
            raise ValueError(
                f"{name} must be a positive float32 or a (N,) float32 array, got {value!r}"
            )
    for name, value in arrays.items():
        is_float32 = isinstance(value, np.ndarray) and value.dtype == np.float32
        if not is_float32 or value.shape != ref.shape:
            raise ValueError(
                f"{name} must be a float32 array of the shape of ref {np.shape(ref)}, got "
                f"{getattr(value, 'dtype', type(value).__name__)} {np.shape(value)}"
            )
    if ref.ndim != 1:
        raise ValueError(f"ref must be one-dimensional (N,), got shape {ref.shape}")
    near_on, near_off = np.float32(0.9) * c_on, np.float32(-0.9) * c_off
    rows = _near_rows(ref, log0, log1, near_on, near_off)
    ref_out = ref.copy()
    pixel, level, polarity = _crossings(rows, ref_out, log0, log1, c_on, c_off, by_pixel=True)
    return Crossings(pixel, level, polarity, ref_out)


def _near_rows(ref, log0, log1, near_on, near_off) -> np.ndarray:
    """Pixels within 10 % of a threshold from their next level in the direction of change.

    ``near_on = 0.9 * c_on`` and ``near_off = -0.9 * c_off`` (float32).
    """
    beyond = log1 - ref
    near = beyond > near_on
    near |= beyond < near_off
    rows = np.flatnonzero(near)
    beyond, log0_r, log1_r = beyond[rows], log0[rows], log1[rows]
    return rows[np.where(beyond > 0, log1_r > log0_r, log1_r < log0_r)]


def _crossings(rows, ref, log0, log1, c_on, c_off, *, by_pixel):
    """(pixel, level, polarity) of the crossings of ``rows``; moves ``ref`` in place.

    Each pixel's crossings are contiguous and in order; the pixels are sorted
    when ``by_pixel`` (otherwise grouped by the number of candidate levels).
    """
    if not rows.size:
        none = np.empty(0, np.int64)
        return none, none.astype(np.float32), none.astype(np.int8)
    ref_r, log0_r, log1_r = ref[rows], log0[rows], log1[rows]
    up = log1_r > log0_r
    c_on_r = c_on[rows] if np.ndim(c_on) else c_on
    c_off_r = c_off[rows] if np.ndim(c_off) else c_off
    step = np.where(up, c_on_r, -c_off_r).astype(np.float32)
    exact = (log1_r.astype(np.float64) - ref_r) / step  # levels reached, in exact arithmetic
    count = np.floor(exact).astype(np.int64) + 2  # candidates, >= 2
    bucket = np.frexp(count.astype(np.float64))[1]  # 2**(b-1) <= count < 2**b
    present = np.flatnonzero(np.bincount(bucket))
    parts = []
    for b in present:
        sel = np.flatnonzero(bucket == b) if present.size > 1 else slice(None)
        levels, n = _bucket_levels(
            ref_r[sel], log0_r[sel], log1_r[sel], step[sel], up[sel], count[sel]
        )
        valid = np.arange(levels.shape[1]) < n[:, None]
        fired = np.flatnonzero(n)
        rows_b = rows[sel]
        ref[rows_b[fired]] = levels[fired, n[fired] - 1]
        parts.append((np.repeat(rows_b, n), levels[valid], np.repeat(up[sel], n)))
    if len(parts) == 1:
        pixel, level, polarity = parts[0]
        return pixel, level, polarity.view(np.int8)
    pixel = np.concatenate([part[0] for part in parts])
    level = np.concatenate([part[1] for part in parts])
    polarity = np.concatenate([part[2] for part in parts]).view(np.int8)
    if by_pixel:
        order = np.argsort(pixel, kind="stable")
        pixel, level, polarity = pixel[order], level[order], polarity[order]
    return pixel, level, polarity


def _refractory_keep(
    pixel: np.ndarray, t: np.ndarray, last_t: np.ndarray, refractory_us: int
) -> np.ndarray:
    """Which events survive the refractory period; updates ``last_t`` (N,) in place.

    ``pixel`` is grouped by pixel with times non-decreasing in each group.
    Loops over the rank of an event in its pixel (a handful per interval),
    vectorised over pixels: an event is kept when it comes at least
    ``refractory_us`` after the pixel's last kept event.
    """
    keep = np.zeros(pixel.size, bool)
    if not pixel.size:
        return keep
    starts = np.flatnonzero(np.r_[True, pixel[1:] != pixel[:-1]])
    counts = np.diff(np.r_[starts, pixel.size])
    order = np.argsort(-counts, kind="stable")
    starts, counts = starts[order], counts[order]
    last = last_t[pixel[starts]]
    for rank in range(int(counts[0])):
        groups = int(np.count_nonzero(counts > rank)) if rank else counts.size
        index = starts[:groups] + rank
        ok = t[index] - last[:groups] >= refractory_us
        keep[index[ok]] = True
        last[:groups] = np.where(ok, t[index], last[:groups])
    last_t[pixel[starts]] = last
    return keep


# -- the simulator ----------------------------------------------------------------------
class EventSimulator:
    """ESIM (Rebecq et al., CoRL 2018): events from time-stamped frames.

    Parameters
    ----------
    cp, cn, threshold_sigma, refractory_us, log_eps, seed, shot_noise_rate_hz, leak_rate_hz
        See :class:`EsimSettings` (the thresholds are stored as float32).

    Notes
    -----
    :meth:`simulate` runs a whole sequence; :meth:`step` feeds one frame at a
    time and keeps the state in between (the first frame only initialises
    ``L_ref``); ``simulate(frames, t)`` equals the concatenated ``step`` calls
    of a fresh simulator. Frames are (H, W) grey or (H, W, 3) **BGR** values
    in [0, 255]; times are int64 microseconds. Noise events (shot noise) are
    added on top of the signal: they neither move ``L_ref`` nor count for
    the refractory period. Leak events come from the drifting reference and
    are ordinary crossings. The threshold map, leak phase and noise are drawn
    from one generator seeded by ``seed``; :meth:`reset` restarts it, so a
    simulator gives the same events every time it is run.

    Examples
    --------
    >>> frames = np.stack([np.full((2, 2), v, np.uint8) for v in (50, 100, 50)])
    >>> events = EventSimulator(cp=0.2, cn=0.2).simulate(frames, np.array([0, 1000, 2000]))
    >>> len(events), int(events.p.sum()), events.t[:4].tolist()
    (24, 12, [290, 290, 290, 290])
    """

    def __init__(
        self,
        cp: float = 0.2,
        cn: float = 0.2,
        threshold_sigma: float = 0.0,
        refractory_us: int = 0,
        log_eps: float = 1e-3,
        seed: int | None = None,
        *,
        shot_noise_rate_hz: float = 0.0,
        leak_rate_hz: float = 0.0,
    ) -> None:
        self.settings = EsimSettings(
            cp, cn, threshold_sigma, refractory_us, log_eps, seed, shot_noise_rate_hz, leak_rate_hz
        )
        self._entropy = np.random.SeedSequence(self.settings.seed).entropy
        self._table = _log_float32(np.arange(256, dtype=np.float32), self.settings.log_eps)
        self.reset()

    @classmethod
    def from_settings(cls, settings: EsimSettings) -> "EventSimulator":
        """A simulator with the given :class:`EsimSettings`."""
        if not isinstance(settings, EsimSettings):
            raise TypeError(f"settings must be EsimSettings, got {type(settings).__name__}")
        s = settings
        return cls(s.cp, s.cn, s.threshold_sigma, s.refractory_us, s.log_eps, s.seed,
                   shot_noise_rate_hz=s.shot_noise_rate_hz, leak_rate_hz=s.leak_rate_hz)

    def __repr__(self) -> str:
        return f"EventSimulator({self.settings})"

    # -- state ----------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget all state; the next frame initialises the simulator again."""
        self._rng = np.random.default_rng(np.random.SeedSequence(self._entropy))
        self._shape: tuple[int, int] | None = None
        self._t_us = 0
        self._log = self._ref = self._last_t = None
        self._c_on: np.ndarray | np.float32 = np.float32(self.settings.cp)
        self._c_off: np.ndarray | np.float32 = np.float32(self.settings.cn)

    @property
    def initialized(self) -> bool:
        """Whether a first frame has been seen since construction or :meth:`reset`."""
        return self._shape is not None

    @property
    def t_us(self) -> int | None:
        """Time of the last frame in µs, or None before the first one."""
        return self._t_us if self.initialized else None

    @property
    def reference(self) -> np.ndarray | None:
        """The per-pixel reference log intensity ``L_ref``, (H, W) float32 (a copy), or None."""
        return None if self._ref is None else self._ref.reshape(self._shape).copy()

    def _initialize(self, log: np.ndarray, t_us: int) -> None:
        s, n = self.settings, log.size
        self._shape, self._t_us = log.shape, t_us
        self._log = log.ravel().copy()
        if s.threshold_sigma > 0:
            for name, c in (("_c_on", s.cp), ("_c_off", s.cn)):
                drawn = c * (1.0 + s.threshold_sigma * self._rng.standard_normal(n))
                drawn = np.maximum(drawn, MIN_THRESHOLD_FRACTION * c)
                setattr(self, name, drawn.astype(np.float32))
        self._ref = self._log.copy()
        if s.leak_rate_hz > 0:  # random phase of the leak: L_ref in (L - Cp, L]
            phase = self._rng.random(n, dtype=np.float32)
            self._ref = (self._ref - phase * self._c_on).astype(np.float32)
        self._last_t = np.full(n, _NEVER, np.int64) if s.refractory_us > 0 else None
        self._near_on = np.float32(0.9) * self._c_on
        self._near_off = np.float32(-0.9) * self._c_off

    # -- one interval ---------------------------------------------------------------------
    def _advance(self, log: np.ndarray, t_us: int) -> Events:
        s = self.settings
        height, width = self._shape
        n_pixels, dt = height * width, t_us - self._t_us
        log1 = log.ravel()
        drift = None
        if s.leak_rate_hz > 0:  # crossings of L + drift against a fixed L_ref, then L_ref -= drift
            drift = (np.float32(s.leak_rate_hz * dt * 1e-6) * self._c_on).astype(np.float32)
            log1 = (log1 + drift).astype(np.float32)
        log0, ref = self._log, self._ref  # ref (owned) moves in place
        rows = _near_rows(ref, log0, log1, self._near_on, self._near_off)
        pixel, level, polarity = _crossings(
            rows, ref, log0, log1, self._c_on, self._c_off, by_pixel=self._last_t is not None
        )
        log0_e = log0[pixel]
        tau = (level - log0_e).astype(np.float64) * dt / (log1[pixel] - log0_e).astype(np.float64)
        tau += 0.5
        t_rel = np.clip(np.floor(tau, out=tau), 0, dt, out=tau).astype(np.int64)
        if self._last_t is not None:
            keep = _refractory_keep(pixel, self._t_us + t_rel, self._last_t, s.refractory_us)
            pixel, polarity, t_rel = pixel[keep], polarity[keep], t_rel[keep]
        if drift is not None:
            self._ref = (ref - drift).astype(np.float32)
        noise = s.shot_noise_rate_hz > 0
        if noise:
            count = self._rng.poisson(s.shot_noise_rate_hz * n_pixels * dt * 1e-6)
            pixel = np.r_[pixel, self._rng.integers(0, n_pixels, count)]
            t_rel = np.r_[t_rel, self._rng.integers(1, dt + 1, count)]
            polarity = np.r_[polarity, self._rng.integers(0, 2, count).astype(np.int8)]
        self._log, self._t_us = log.ravel(), t_us  # log is a fresh array, owned
        if dt * n_pixels < 2**62:  # equal keys of signal events are identical events
            order = np.argsort(t_rel * n_pixels + pixel, kind="stable" if noise else None)
        else:  # pragma: no cover - intervals of years on big sensors
            order = np.lexsort((pixel, t_rel))
        y, x = np.divmod(pixel[order], width)
        t_rel = t_rel[order]
        t_rel += t_us - dt
        return Events._trusted(
            x.astype(np.uint16), y.astype(np.uint16), t_rel, polarity[order], width, height
        )

    # -- public ---------------------------------------------------------------------------
    def step(self, frame: object, t_us: int) -> Events:
        """Feed one frame taken at ``t_us``; return the events since the previous frame.

        Parameters
        ----------
        frame : array_like, shape (H, W) or (H, W, 3)
            Grey values in [0, 255] (uint8 or float); colour is BGR.
        t_us : int
            Time of the frame in µs, larger than that of the previous frame.

        Returns
        -------
        Events
            Events with ``t_prev <= t <= t_us``, sorted by time; none for the
            first frame, which only initialises ``L_ref``.
        """
        t_us = _whole("t_us", t_us)
        grey = _grey_frame(frame, "frame")
        if self._shape is not None:
            if grey.shape != self._shape:
                raise ValueError(f"frame has shape {grey.shape[:2]}, earlier frames {self._shape}")
            if t_us <= self._t_us:
                raise ValueError(f"t_us must increase: got {t_us} µs after {self._t_us} µs")
        return self._feed(_log_grey(grey, self.settings.log_eps, self._table), t_us)

    def _feed(self, log: np.ndarray, t_us: int) -> Events:
        if self._shape is None:
            self._initialize(log, t_us)
            return Events.empty(log.shape[1], log.shape[0])
        return self._advance(log, t_us)

    def simulate(self, frames: object, timestamps_us: object) -> Events:
        """Events of a whole sequence, from a fresh state.

        Parameters
        ----------
        frames : array_like, shape (T, H, W) or (T, H, W, 3)
            Grey values in [0, 255] (uint8 or float); colour is BGR.
        timestamps_us : array_like, shape (T,)
            Frame times in µs, integers, strictly increasing.

        Returns
        -------
        Events
            All events, sorted by time; width W, height H. Afterwards the
            simulator holds the state after the last frame, so :meth:`step`
            can go on.
        """
        frames = np.asarray(frames)
        if frames.ndim not in (3, 4) or (frames.ndim == 4 and frames.shape[3] != 3):
            raise ValueError(
                f"frames must have shape (T, H, W) or (T, H, W, 3), got {frames.shape}"
            )
        times = _timestamps(timestamps_us)
        if times.size != frames.shape[0]:
            raise ValueError(
                f"timestamps_us has {times.size} entries but frames has {frames.shape[0]} frames"
            )
        self.reset()
        eps = self.settings.log_eps
        parts = [
            self._feed(_log_grey(_grey_frame(frame, f"frames[{i}]"), eps, self._table), int(t_us))
            for i, (frame, t_us) in enumerate(zip(frames, times))
        ]
        if not parts:
            raise ValueError("frames must hold at least one frame")
        height, width = self._shape
        columns = (np.concatenate([getattr(part, name) for part in parts]) for name in "xytp")
        return Events._trusted(*columns, width, height)


def _timestamps(values: object) -> np.ndarray:
    times = np.asarray(values)
    if times.ndim != 1:
        raise ValueError(f"timestamps_us must be one-dimensional (T,), got shape {times.shape}")
    if times.dtype.kind == "b" or times.dtype.kind not in "iuf":
        raise TypeError(f"timestamps_us must hold integer microseconds, got dtype {times.dtype}")
    if times.dtype.kind == "f":
        if not np.isfinite(times).all() or not np.array_equal(times, np.round(times)):
            raise ValueError("timestamps_us must hold whole, finite numbers of microseconds")
    times = times.astype(np.int64)
    bad = np.flatnonzero(np.diff(times) <= 0)
    if bad.size:
        i = int(bad[0])
        raise ValueError(
            f"timestamps_us must be strictly increasing; timestamps_us[{i + 1}]={times[i + 1]} µs "
            f"follows timestamps_us[{i}]={times[i]} µs"
        )
    return times
