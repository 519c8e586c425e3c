"""Adaptive temporal sampling of videos: interpolated frames between video frames.

ESIM (Rebecq et al. 2018) takes the log intensity ``L = log(I/255 + eps)``
(``eps = 1e-3``, ``I`` the grey value in [0, 255]) as linear in time between
two samples. That is only faithful when consecutive samples are close, so the
paper (Sec. 3.1, eq. 1) samples adaptively::

    t_{k+1} = t_k + lambda * C / max_{x,y} |dL(x, y; t_k)/dt|

For a video the frames are given; this module inserts interpolated frames
between two consecutive video frames so that **no pixel's log intensity changes
by more than** ``lam * threshold`` **between consecutive samples**.

Per interval ``[t0, t1]`` (video frames ``I0``, ``I1``):

1. If ``max |L(I1) - L(I0)| <= lam * threshold`` nothing is inserted.
2. Otherwise the interval is cut into ``n`` sub-intervals with evenly spaced
   integer times ``t_k = t0 + floor(k * (t1 - t0) / n)``, ``k = 0..n``. ``n``
   starts from an estimate of ``max |dL/dt|`` (exact for ``method="linear"``:
   ``|dI| / (min(I0, I1) + 255 eps)``; for ``method="flow"`` probed by finite
   differences at a few times).
3. The frames at ``t_1 .. t_{n-1}`` are interpolated and the bound is
   **checked on them** (every pixel, every consecutive pair, ``L`` in float32).
   Flow interpolation is not monotonic per pixel, so the check can fail; then
   ``n`` grows (``n <- max(n + 1, ceil(1.05 n * worst / bound))``) and the
   interval is rendered again, until the bound holds.
4. ``n`` never exceeds ``max_insert + 1`` nor ``t1 - t0`` (timestamps stay
   strictly increasing integers, so an interval of ``d`` µs holds at most
   ``d - 1`` inserted frames). When one of these caps stops the refinement
   the interval is *capped*: it keeps the capped number of frames, its
   measured ``max_dlog`` exceeds the bound, and the result says so
   (:attr:`UpsampleResult.capped`, :attr:`IntervalReport.capped`). Nothing is
   raised.

Interpolation (``method``):

* ``"linear"``: ``I(a) = (1 - a) I0 + a I1`` in intensity (``a`` the fraction
  of the interval). Near black a small intensity step is a large log step, so
  dark pixels need many samples: the exact count is used.
* ``"flow"``: dense optical flow by DIS (Kroeger et al. 2016, OpenCV's
  ``cv2.DISOpticalFlow``), forward ``F01`` and backward ``F10`` once per
  interval. The flows toward time ``a`` are approximated as in Super SloMo
  (Jiang et al. 2018), ``F_a0 = -(1-a) a F01 + a^2 F10`` and
  ``F_a1 = (1-a)^2 F01 - a (1-a) F10``; both frames are warped toward time
  ``a`` (``cv2.remap``, bilinear, border replicated) and blended with weights
  ``(1 - a, a)``. Flow is *unreliable* at a pixel when it fails the
  forward-backward check (Sundaram et al. 2010:
  ``|F01 + F10(x + F01)|^2 > 0.01 (|F01|^2 + |F10(x + F01)|^2) + 0.5``), points
  outside the frame, or does not explain the change better than no motion
  (photometric error after warping, 5x5 box mean, larger than the error of
  the unwarped frames plus 1 grey level: a pure brightness change). The
  reliability maps are warped along with the frames, and the output is
  ``m * flow_blend + (1 - m) * linear_blend`` with ``m = V0 * V1``, which
  equals ``I0`` at ``a = 0`` and ``I1`` at ``a = 1`` and is continuous in
  ``a``, so refinement converges.

Limits: ``cv2.remap`` resolves sample positions to float32 precision (about
``6e-8 * W`` pixels), so a pure-black pixel next to a white one in frames wider
than about 1000 pixels may step by slightly more than ``0.1`` in ``L`` however
fine the sampling: such intervals end capped. Frames are kept in memory while
an interval is refined when they fit in 256 MiB; otherwise the verified
frames are rendered a second time when yielded.

References
----------
H. Rebecq, D. Gehrig, D. Scaramuzza. "ESIM: an Open Event Camera Simulator." CoRL 2018.
T. Kroeger, R. Timofte, D. Dai, L. Van Gool. "Fast Optical Flow using Dense Inverse
Search." ECCV 2016. https://doi.org/10.1007/978-3-319-46493-0_29
H. Jiang et al. "Super SloMo: High Quality Estimation of Multiple Intermediate Frames
for Video Interpolation." CVPR 2018.
N. Sundaram, T. Brox, K. Keutzer. "Dense Point Trajectories by GPU-Accelerated Large
Displacement Optical Flow." ECCV 2010.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Iterable, Iterator, Literal, Protocol

import cv2
import numpy as np

__all__ = [
    "LOG_EPS",
    "MIN_FLOW_SIZE",
    "IntervalReport",
    "UpsampleResult",
    "interpolate_frames",
    "iter_upsample",
    "log_intensity",
    "upsample",
]

#: ``eps`` of ``L = log(I/255 + eps)``.
LOG_EPS = 1e-3
#: Smallest frame side (pixels) for ``method="flow"``: OpenCV's DIS flow fails or
#: crashes on smaller or very flat frames.
MIN_FLOW_SIZE = 32

Method = Literal["flow", "linear"]
_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}
_CACHE_BYTES = 256 * 2**20  # frames kept while one interval is refined
_MARGIN = 1e-4  # relative safety margin on the bound (float32 log rounding)
_GROWTH = 1.05  # over-shoot of the refinement update
_PROBES = (0.0, 0.25, 0.5, 0.75, 0.999)  # times where dL/da is probed (flow)
_PROBE_DA = 1e-3


def log_intensity(frame: np.ndarray) -> np.ndarray:
    """Log intensity ``L = log(I/255 + LOG_EPS)`` of a grey frame.

    Parameters
    ----------
    frame : ndarray, shape (..., H, W)
        Grey values in [0, 255] (any real dtype).

    Returns
    -------
    ndarray, float32, same shape.
    """
    return np.log(np.asarray(frame, dtype=np.float32) * np.float32(1 / 255) + np.float32(LOG_EPS))


# -- results ------------------------------------------------------------------------------
@dataclass(frozen=True)
class IntervalReport:
    """What :func:`iter_upsample` did between input frames ``index`` and ``index + 1``.

    Attributes
    ----------
    index : int
        Interval number (0 for the first two input frames).
    t0_us, t1_us : int
        Times of the two input frames (µs).
    inserted : int
        Interpolated frames inserted (``n - 1`` for ``n`` sub-intervals).
    max_dlog : float
        Largest ``|L|`` change of any pixel between consecutive samples of the
        interval, after upsampling (log units).
    capped : bool
        True when ``max_insert`` or the interval length in µs stopped the
        refinement before ``max_dlog <= lam * threshold``.
    """

    index: int
    t0_us: int
    t1_us: int
    inserted: int
    max_dlog: float
    capped: bool


@dataclass(frozen=True, eq=False)
class UpsampleResult:
    """Upsampled frames from :func:`upsample`.

    Attributes
    ----------
    frames : ndarray, float32, shape (T', H, W)
        Input and inserted frames, grey values in [0, 255].
    timestamps_us : ndarray, int64, shape (T',)
        Strictly increasing times in µs.
    inserted : int
        Number of inserted frames, ``T' - T``.
    inserted_per_interval : ndarray, int64, shape (T - 1,)
        Inserted frames between input frames ``i`` and ``i + 1``.
    source_index : ndarray, int64, shape (T,)
        Position of each input frame in ``frames``.
    max_dlog_per_interval : ndarray, float32, shape (T - 1,)
        Largest ``|dL|`` between consecutive samples in each interval.
    capped : ndarray, bool, shape (T - 1,)
        Intervals where a cap stopped the refinement (see module docstring).
    bound : float
        ``lam * threshold`` (log units).
    """

    frames: np.ndarray
    timestamps_us: np.ndarray
    inserted: int
    inserted_per_interval: np.ndarray
    source_index: np.ndarray
    max_dlog_per_interval: np.ndarray
    capped: np.ndarray
    bound: float

    @property
    def bound_met(self) -> bool:
        """True when no interval was capped (every pixel within the bound)."""
        return not bool(self.capped.any())


# -- interpolation of one interval ------------------------------------------------------
class _Pair(Protocol):
    def frame(self, alpha: float) -> np.ndarray: ...

    def max_rate(self) -> float: ...


class _LinearPair:
    """``(1 - a) I0 + a I1``; ``max_rate`` is the exact ``max |dL/da|`` in nepers."""

    def __init__(self, frame0: np.ndarray, frame1: np.ndarray) -> None:
        self.frame0 = frame0
        self.delta = frame1 - frame0
        self.floor = np.minimum(frame0, frame1) + np.float32(255 * LOG_EPS)

    def frame(self, alpha: float) -> np.ndarray:
        return self.frame0 + np.float32(alpha) * self.delta

    def max_rate(self) -> float:
        return float(np.max(np.abs(self.delta) / self.floor))


def _warp(images: tuple[np.ndarray, ...], displacement: np.ndarray,
          grid: np.ndarray) -> list[np.ndarray]:
    """Each (H, W) float32 image sampled at ``x + displacement(x)``, bilinear, border replicated.

    One ``cv2.remap`` per single-channel image: OpenCV 5 interpolates
    one-channel float images at the exact map position, but quantises the map
    to 1/32 pixel for two-channel images, which makes values jump.
    """
    positions = grid + displacement
    return [cv2.remap(image, positions, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            for image in images]


def _reliability(frame0: np.ndarray, frame1: np.ndarray, flow01: np.ndarray,
                 flow10: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Soft map (H, W) float32 in [0, 1]: 1 where ``flow01`` (at frame-0 pixels) is reliable."""
    height, width = frame0.shape
    back = np.dstack(_warp(tuple(np.ascontiguousarray(flow10[..., i]) for i in (0, 1)), flow01, grid))
    err = np.sum((flow01 + back) ** 2, axis=2)
    ok = err <= 0.01 * (np.sum(flow01**2, axis=2) + np.sum(back**2, axis=2)) + 0.5
    target = grid + flow01
    ok &= (target[..., 0] >= 0) & (target[..., 0] <= width - 1)
    ok &= (target[..., 1] >= 0) & (target[..., 1] <= height - 1)
    (warped,) = _warp((frame1,), flow01, grid)
    e_flow = cv2.blur(np.abs(warped - frame0), (5, 5))
    e_still = cv2.blur(np.abs(frame1 - frame0), (5, 5))
    ok &= e_flow <= e_still + 1.0
    return cv2.GaussianBlur(ok.astype(np.float32), (0, 0), 1.0)


class _FlowPair:
    """Flow-based interpolation of one interval (see the module docstring)."""

    def __init__(self, frame0: np.ndarray, frame1: np.ndarray, dis: cv2.DISOpticalFlow,
                 grid: np.ndarray) -> None:
        u0 = np.clip(np.rint(frame0), 0, 255).astype(np.uint8)
        u1 = np.clip(np.rint(frame1), 0, 255).astype(np.uint8)
        self.flow01 = dis.calc(u0, u1, None)
        self.flow10 = dis.calc(u1, u0, None)
        self.grid = grid
        self.frame0 = frame0
        self.delta = frame1 - frame0
        self.sources0 = (frame0, _reliability(frame0, frame1, self.flow01, self.flow10, grid))
        self.sources1 = (frame1, _reliability(frame1, frame0, self.flow10, self.flow01, grid))

    def frame(self, alpha: float) -> np.ndarray:
        a = float(alpha)
        d0 = cv2.addWeighted(self.flow01, -(1 - a) * a, self.flow10, a * a, 0.0)
        d1 = cv2.addWeighted(self.flow01, (1 - a) ** 2, self.flow10, -a * (1 - a), 0.0)
        warped0, valid0 = _warp(self.sources0, d0, self.grid)
        warped1, valid1 = _warp(self.sources1, d1, self.grid)
        a32 = np.float32(a)
        linear = self.frame0 + a32 * self.delta
        flow = warped0 + a32 * (warped1 - warped0)
        return linear + (valid0 * valid1) * (flow - linear)

    def max_rate(self) -> float:
        rate = 0.0
        for a in _PROBES:
            change = log_intensity(self.frame(a + _PROBE_DA)) - log_intensity(self.frame(a))
            rate = max(rate, float(np.max(np.abs(change))) / _PROBE_DA)
        return rate


@dataclass(frozen=True)
class _Plan:
    times_us: np.ndarray  # (n + 1,) int64, t0 .. t1
    frames: list[np.ndarray] | None  # the n - 1 inner frames, when cached
    max_dlog: float
    capped: bool


def _times(t0: int, t1: int, n: int) -> np.ndarray:
    return t0 + (np.arange(n + 1, dtype=np.int64) * (t1 - t0)) // n


def _render(pair: _Pair, times: np.ndarray, log0: np.ndarray, log1: np.ndarray,
            keep: bool) -> tuple[float, list[np.ndarray] | None]:
    """Largest consecutive ``|dL|`` over ``times``; the inner frames when ``keep``."""
    t0, span = int(times[0]), float(times[-1] - times[0])
    frames: list[np.ndarray] | None = [] if keep else None
    worst, previous = 0.0, log0
    for t in times[1:-1]:
        frame = pair.frame((int(t) - t0) / span)
        current = log_intensity(frame)
        worst = max(worst, float(np.max(np.abs(current - previous))))
        previous = current
        if frames is not None:
            frames.append(frame)
    return max(worst, float(np.max(np.abs(log1 - previous)))), frames


def _plan_interval(pair_factory: Callable[[], _Pair], log0: np.ndarray, log1: np.ndarray,
                   t0: int, t1: int, bound: float, max_insert: int) -> tuple[_Plan, _Pair | None]:
    """Choose the sub-interval count of ``[t0, t1]`` and verify the bound on the frames."""
    target = bound * (1 - _MARGIN)
    direct = float(np.max(np.abs(log1 - log0)))
    if direct <= target:
        return _Plan(np.array([t0, t1], np.int64), [], direct, False), None
    span = t1 - t0
    n_cap = max(1, min(max_insert + 1, span))
    pair = pair_factory()
    rate = pair.max_rate()
    if isinstance(pair, _LinearPair):
        fraction = math.expm1(target) / rate  # exact for linear blending
    else:
        fraction = target / max(rate, 1e-12)
    gap_us = max(1, int(math.floor(fraction * span)))
    n = min(n_cap, max(2, -(-span // gap_us)))
    keep_bytes = log0.size * 4
    while True:
        times = _times(t0, t1, n)
        worst, frames = _render(pair, times, log0, log1, keep=(n - 1) * keep_bytes <= _CACHE_BYTES)
        if worst <= target or n >= n_cap:
            return _Plan(times, frames, worst, worst > target), pair
        n = min(n_cap, max(n + 1, int(math.ceil(_GROWTH * n * worst / target))))


# -- validation ---------------------------------------------------------------------------
def _positive(name: str, value: object) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a real number, got {value!r}")
    if not (math.isfinite(float(value)) and float(value) > 0):
        raise ValueError(f"{name} must be a finite positive number, got {value}")
    return float(value)


@dataclass(frozen=True)
class _Settings:
    bound: float
    method: str
    max_insert: int
    flow_preset: str


def _settings(threshold: object, lam: object, method: object, max_insert: object,
              flow_preset: object) -> _Settings:
    bound = _positive("threshold", threshold) * _positive("lam", lam)
    if method not in ("flow", "linear"):
        raise ValueError(f"method must be 'flow' or 'linear', got {method!r}")
    if isinstance(max_insert, (bool, np.bool_)) or not isinstance(max_insert, (int, np.integer)):
        raise TypeError(f"max_insert must be an integer, got {max_insert!r}")
    if max_insert < 0:
        raise ValueError(f"max_insert must be >= 0, got {max_insert}")
    if flow_preset not in _PRESETS:
        raise ValueError(f"flow_preset must be one of {sorted(_PRESETS)}, got {flow_preset!r}")
    return _Settings(bound, str(method), int(max_insert), str(flow_preset))


def _check_frame(frame: object, index: int, shape: tuple[int, ...] | None,
                 method: str) -> np.ndarray:
    """A float32 (H, W) copy of input frame ``index``, with shape and range checks."""
    array = np.asarray(frame)
    if array.dtype.kind not in "uif":
        raise TypeError(f"frame {index} must hold grey values, got dtype {array.dtype}")
    if array.ndim == 3 and array.shape[2] == 3 and array.dtype in (np.uint8, np.float32):
        array = cv2.cvtColor(np.ascontiguousarray(array), cv2.COLOR_BGR2GRAY)  # BGR, as ESIM
    if array.ndim != 2 or 0 in array.shape:
        raise ValueError(f"frame {index} must have shape (H, W) or (H, W, 3) BGR, got {array.shape}")
    if shape is not None and array.shape != shape:
        raise ValueError(f"frame {index} has shape {array.shape}, the first frame {shape}")
    if method == "flow" and min(array.shape) < MIN_FLOW_SIZE:
        raise ValueError(f"method='flow' needs frames of at least {MIN_FLOW_SIZE}x{MIN_FLOW_SIZE} "
                         f"pixels, got {array.shape}; use method='linear'")
    out = np.array(array, dtype=np.float32)
    low, high = float(out.min()), float(out.max())
    if not (0 <= low and high <= 255):  # also catches NaN
        raise ValueError(f"frame {index} must hold grey values in [0, 255], got [{low}, {high}]")
    return out


def _check_time(t: object, index: int, previous: int | None) -> int:
    if isinstance(t, (bool, np.bool_)):
        raise TypeError(f"timestamp {index} must be an integer number of µs, got {t!r}")
    if isinstance(t, (float, np.floating)) and float(t).is_integer():
        t = int(t)
    if not isinstance(t, (int, np.integer)):
        raise TypeError(f"timestamp {index} must be an integer number of µs, got {t!r}")
    t = int(t)
    if previous is not None and t <= previous:
        raise ValueError(f"timestamps must be strictly increasing: timestamp {index} = {t} µs "
                         f"follows {previous} µs")
    return t


# -- public API -------------------------------------------------------------------------
def _make_pair(frame0: np.ndarray, frame1: np.ndarray, settings: _Settings,
               state: dict[str, object]) -> _Pair:
    if settings.method == "linear":
        return _LinearPair(frame0, frame1)
    if "dis" not in state:
        state["dis"] = cv2.DISOpticalFlow_create(_PRESETS[settings.flow_preset])
        height, width = frame0.shape
        state["grid"] = np.dstack(np.meshgrid(np.arange(width, dtype=np.float32),
                                              np.arange(height, dtype=np.float32)))
    return _FlowPair(frame0, frame1, state["dis"], state["grid"])  # type: ignore[arg-type]


def _stream(source: Iterable[tuple[object, object]], settings: _Settings,
            report: Callable[[IntervalReport], None] | None) -> Iterator[tuple[np.ndarray, int]]:
    state: dict[str, object] = {}  # DIS instance and pixel grid, made once
    previous: tuple[np.ndarray, np.ndarray, int] | None = None  # frame, L, t
    shape: tuple[int, ...] | None = None
    for index, item in enumerate(source):
        try:
            frame_in, t_in = item  # type: ignore[misc]
        except (TypeError, ValueError):
            raise TypeError(f"item {index} of the frame source must be a (frame, t_us) pair") from None
        frame = _check_frame(frame_in, index, shape, settings.method)
        t = _check_time(t_in, index, None if previous is None else previous[2])
        shape, log = frame.shape, log_intensity(frame)
        if previous is not None:
            frame0, log0, t0 = previous
            plan, pair = _plan_interval(lambda: _make_pair(frame0, frame, settings, state),
                                        log0, log, t0, t, settings.bound, settings.max_insert)
            inner = plan.times_us[1:-1]
            if plan.frames is not None:
                yield from zip(plan.frames, (int(s) for s in inner))
            else:
                for s in inner:
                    yield pair.frame((int(s) - t0) / (t - t0)), int(s)  # type: ignore[union-attr]
            if report is not None:
                report(IntervalReport(index - 1, t0, t, int(inner.size), plan.max_dlog, plan.capped))
        yield frame.copy(), t
        previous = (frame, log, t)
    if shape is None:
        raise ValueError("the frame source yielded no frames")


def iter_upsample(
    frame_source: Iterable[tuple[np.ndarray, int]],
    threshold: float,
    *,
    lam: float = 0.5,
    method: Method = "flow",
    max_insert: int = 10_000,
    flow_preset: Literal["ultrafast", "fast", "medium"] = "medium",
    report: Callable[[IntervalReport], None] | None = None,
) -> Iterator[tuple[np.ndarray, int]]:
    """Stream a video with interpolated frames inserted (adaptive sampling, paper eq. 1).

    Only the previous input frame (and the frames of the current interval,
    up to 256 MiB) is kept, so a video of hours streams in constant memory.
    See the module docstring for the algorithm, caps and limits.

    Parameters
    ----------
    frame_source : iterable of (frame, t_us)
        Frames (H, W) grey in [0, 255] (any real dtype; uint8 or float32
        (H, W, 3) BGR is converted to grey), times in integer µs, strictly
        increasing; e.g. a :mod:`cmax.sim.video` source.
    threshold : float
        Contrast threshold ``C`` of the simulated camera (log units, > 0).
    lam : float
        Fraction ``lambda`` of ``C`` a pixel may change between samples (> 0).
    method : {"flow", "linear"}
        Interpolation: DIS optical flow warping (frames at least 32x32), or
        linear blending in intensity.
    max_insert : int
        Most frames inserted into one interval (>= 0).
    flow_preset : {"ultrafast", "fast", "medium"}
        DIS preset for ``method="flow"``.
    report : callable, optional
        Called with an :class:`IntervalReport` after each interval's inserted
        frames were yielded.

    Yields
    ------
    frame : ndarray, float32, shape (H, W)
        Grey values in [0, 255]; a new array every time.
    t_us : int
        Time in µs, strictly increasing.

    Raises
    ------
    ValueError, TypeError
        Bad settings (at the call), or, while iterating, a frame of another
        shape or out of range, a non-increasing time, an empty source.

    Examples
    --------
    >>> frames = np.zeros((2, 32, 32), np.float32); frames[1] += 100
    >>> out = list(iter_upsample(zip(frames, [0, 1_000_000]), 0.2, method="linear"))
    >>> len(out) > 2, out[0][1], out[-1][1]
    (True, 0, 1000000)
    """
    settings = _settings(threshold, lam, method, max_insert, flow_preset)
    return _stream(frame_source, settings, report)


def upsample(
    frames: np.ndarray,
    timestamps_us: np.ndarray,
    threshold: float,
    *,
    lam: float = 0.5,
    method: Method = "flow",
    max_insert: int = 10_000,
    flow_preset: Literal["ultrafast", "fast", "medium"] = "medium",
) -> UpsampleResult:
    """Insert interpolated frames so that ``|dL| <= lam * threshold`` between samples.

    The in-memory form of :func:`iter_upsample` (same frames, same times);
    the output holds every frame, so use the generator for long videos.

    Parameters
    ----------
    frames : array_like, shape (T, H, W) or (T, H, W, 3)
        Grey (or BGR, converted) frames in [0, 255], T >= 1.
    timestamps_us : array_like of int, shape (T,)
        Strictly increasing times in µs.
    threshold, lam, method, max_insert, flow_preset
        As in :func:`iter_upsample`.

    Returns
    -------
    UpsampleResult

    Examples
    --------
    >>> frames = np.zeros((2, 32, 32), np.float32); frames[1] += 100
    >>> result = upsample(frames, np.array([0, 1_000_000]), 0.2, method="linear")
    >>> result.frames.shape[0] == 2 + result.inserted, result.bound_met
    (True, True)
    """
    settings = _settings(threshold, lam, method, max_insert, flow_preset)
    frames = np.asarray(frames)
    if frames.ndim not in (3, 4) or frames.shape[0] == 0:
        raise ValueError(f"frames must have shape (T, H, W) with T >= 1, got {frames.shape}")
    times = np.asarray(timestamps_us)
    if times.shape != (frames.shape[0],):
        raise ValueError(f"timestamps_us must have shape ({frames.shape[0]},), got {times.shape}")
    if times.dtype.kind not in "iu":
        raise TypeError(f"timestamps_us must hold integer µs, got dtype {times.dtype}")
    if times.size > 1 and np.any(np.diff(times.astype(np.int64)) <= 0):
        i = int(np.flatnonzero(np.diff(times.astype(np.int64)) <= 0)[0])
        raise ValueError(f"timestamps_us must be strictly increasing: timestamps_us[{i + 1}] = "
                         f"{times[i + 1]} µs follows {times[i]} µs")
    reports: list[IntervalReport] = []
    out = list(_stream(zip(frames, times.tolist()), settings, reports.append))
    counts = np.array([r.inserted for r in reports], dtype=np.int64)
    return UpsampleResult(
        frames=np.stack([f for f, _ in out]),
        timestamps_us=np.array([t for _, t in out], dtype=np.int64),
        inserted=int(counts.sum()),
        inserted_per_interval=counts,
        source_index=np.concatenate([[0], np.cumsum(counts + 1)]).astype(np.int64),
        max_dlog_per_interval=np.array([r.max_dlog for r in reports], dtype=np.float32),
        capped=np.array([r.capped for r in reports], dtype=bool),
        bound=settings.bound,
    )


def interpolate_frames(
    frame0: np.ndarray,
    frame1: np.ndarray,
    alphas: Iterable[float],
    *,
    method: Method = "flow",
    flow_preset: Literal["ultrafast", "fast", "medium"] = "medium",
) -> np.ndarray:
    """Frames between ``frame0`` (alpha 0) and ``frame1`` (alpha 1), as :func:`upsample` makes them.

    Parameters
    ----------
    frame0, frame1 : array_like, shape (H, W)
        Grey frames in [0, 255].
    alphas : iterable of float, each in [0, 1]
        Fractions of the interval.
    method, flow_preset
        As in :func:`iter_upsample`.

    Returns
    -------
    ndarray, float32, shape (K, H, W)
    """
    settings = _settings(1.0, 1.0, method, 0, flow_preset)
    f0 = _check_frame(frame0, 0, None, settings.method)
    f1 = _check_frame(frame1, 1, f0.shape, settings.method)
    alphas = np.asarray(list(alphas), dtype=np.float64).reshape(-1)
    if np.any(~np.isfinite(alphas)) or np.any((alphas < 0) | (alphas > 1)):
        raise ValueError("alphas must lie in [0, 1]")
    pair = _make_pair(f0, f1, settings, {})
    if alphas.size == 0:
        return np.empty((0,) + f0.shape, np.float32)
    return np.stack([pair.frame(float(a)) for a in alphas])
