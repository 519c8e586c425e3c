"""Adaptive temporal sampling of videos: interpolated frames between video frames.

ESIM (Rebecq et al. 2018) takes the log intensity ``L = log(I/255 + eps)``
(``eps = 1e-3``, ``I`` the grey value in [0, 255]) as linear in time between
two samples. That is only faithful when consecutive samples are close, so the
paper (Sec. 3.1, eq. 1) samples adaptively::

    t_{k+1} = t_k + lambda * C / max_{x,y} |dL(x, y; t_k)/dt|

For a video the frames are given; this module inserts interpolated frames
(:mod:`cmax.sim.interpolation`: linear blending or DIS optical flow) between
two consecutive video frames so that **no pixel's log intensity changes by
more than** ``lam * threshold`` **between consecutive samples**.

Per interval ``[t0, t1]`` (video frames ``I0``, ``I1``):

1. If ``max |L(I1) - L(I0)| <= lam * threshold`` nothing is inserted.
2. ``method="flow"``: the DIS optical flow of the pair is computed once, and
   *key frames* are rendered by flow warping at ``K - 1`` evenly spaced times,
   ``K = ceil(largest displacement / 1 pixel)``: between two key frames every
   point moves by at most a pixel, where blending approximates motion well.
   ``method="linear"``: no key frames (``K = 1``).
3. Between consecutive key frames (or ``I0``, ``I1``) frames are blended
   linearly in intensity, at times chosen by eq. 1 step by step: from the
   sample at ``t`` the next is at ``t + s``, ``s`` the largest step that keeps
   every pixel within the bound -- in closed form for linear blending
   (:meth:`cmax.sim.interpolation.LinearPair.max_step`, exact), rounded down
   to whole µs. Each frame is **checked** against the previous sample (every
   pixel, ``L`` in float32) before it is yielded; should float32 rounding
   break the bound, the step shrinks and the frame is rendered again
   (:attr:`IntervalReport.rejected`). Frames are yielded as they are made:
   only the last sample is kept (constant memory).
4. Steps are at least 1 µs (timestamps stay strictly increasing integers) and
   an interval holds at most ``max_insert`` inserted frames (key frames
   included). When one of these caps forces a step beyond the bound the
   interval is *capped*: its measured ``max_dlog`` exceeds the bound and the
   result says so (:attr:`UpsampleResult.capped`,
   :attr:`IntervalReport.capped`). Nothing is raised.

Why the steps are not uniform: linear in intensity, a pixel that starts near
black changes its log intensity fastest at the start of the interval
(``dL/da = dI / (I + 255 eps)``: a 0 -> 30 grey change moves ``L`` by 4.8 in
total but at 117 per interval at ``a = 0``). Uniform sub-intervals sized for
the fastest moment of the worst pixel need up to ~25 times more frames than
steps that follow eq. 1, which only need about ``max |total dL| / bound``.
And why key frames: rendering a flow-warped frame costs four ``cv2.remap``
passes and its bound can only be checked by trial, while a blended frame costs
two array operations and its step is exact; rendering every sample by flow was
many times slower for at most sub-pixel differences.

Limits: ``cv2.remap`` resolves sample positions to float32 precision (about
``6e-8 * W`` pixels), so a pure-black pixel next to a white one in frames wider
than about 1000 pixels may step by slightly more than ``0.1`` in ``L`` however
fine the sampling: such intervals end capped.

References
----------
H. Rebecq, D. Gehrig, D. Scaramuzza. "ESIM: an Open Event Camera Simulator." CoRL 2018.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Callable, Iterable, Iterator, Literal

import numpy as np

from cmax.sim.interpolation import (
    LOG_EPS,
    MIN_FLOW_SIZE,
    FlowPair,
    LinearPair,
    Method,
    check_frame,
    check_method,
    interpolate_frames,
    log_intensity,
    make_pair,
)

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

_MARGIN = 1e-4  # relative safety margin on the bound (float32 log rounding)
_SAFETY = 0.9  # after a rejected step: aim a little below the bound ...
_MIN_SHRINK = 0.1  # ... shrinking the step at most tenfold
#: Largest motion (pixels) between two flow key frames; linear blending in between.
_KEY_PX = 1.0


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
        True when ``max_insert`` or the interval length in µs (one sample per
        µs at most) forced a step with ``max_dlog > lam * threshold``.
    rejected : int
        Frames rendered and rejected (the step was too long) while the
        interval was sampled: the cost of the search, 0 for ``"linear"``
        apart from float rounding.
    """

    index: int
    t0_us: int
    t1_us: int
    inserted: int
    max_dlog: float
    capped: bool
    rejected: int = 0


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
    if isinstance(max_insert, (bool, np.bool_)) or not isinstance(max_insert, (int, np.integer)):
        raise TypeError(f"max_insert must be an integer, got {max_insert!r}")
    if max_insert < 0:
        raise ValueError(f"max_insert must be >= 0, got {max_insert}")
    check_method(method, flow_preset)
    return _Settings(bound, str(method), int(max_insert), str(flow_preset))


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


# -- one interval -------------------------------------------------------------------------
def _max_abs_diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)))


def _linear_segment(frame0: np.ndarray, log0: np.ndarray, frame1: np.ndarray, log1: np.ndarray,
                    t0: int, t1: int, target: float, max_insert: int):
    """Yield the frames inserted into ``[t0, t1]`` by linear blending, eq. 1 step by step;
    return ``(max_dlog, capped, inserted, rejected)``."""
    direct = _max_abs_diff(log1, log0)
    if direct <= target:
        return direct, False, 0, 0
    pair, span = LinearPair(frame0, frame1, target), t1 - t0
    t, frame, log = t0, frame0, log0
    worst_all, capped, inserted, rejected = 0.0, False, 0, 0
    while True:
        step_us = pair.max_step(frame, target) * span
        while True:
            forced = inserted >= max_insert
            t_next = t1 if forced else int(min(t1, t + max(1.0, math.floor(step_us))))
            if t_next == t1:
                frame_next, log_next = frame1, log1
            else:
                frame_next = pair.frame((t_next - t0) / span)
                log_next = log_intensity(frame_next)
            worst = _max_abs_diff(log_next, log)
            if worst <= target or forced or t_next == t + 1:
                break
            rejected += 1  # float32 rounding beat the margin: shrink the step
            step_us = (t_next - t) * max(_MIN_SHRINK, _SAFETY * target / worst)
        capped |= worst > target
        worst_all = max(worst_all, worst)
        if t_next == t1:
            return worst_all, capped, inserted, rejected
        yield frame_next, t_next
        inserted += 1
        t, frame, log = t_next, frame_next, log_next


def _key_times(pair: FlowPair, t0: int, t1: int) -> list[int]:
    """Inner key-frame times of a flow interval: the motion split into steps of at most
    ``_KEY_PX`` pixels, evenly spaced, at most one per µs."""
    count = min(t1 - t0, max(1, math.ceil(pair.motion_px / _KEY_PX)))
    return [t0 + (k * (t1 - t0)) // count for k in range(1, count)]


def _sample_interval(make_flow: Callable[[], FlowPair] | None, frame0: np.ndarray,
                     log0: np.ndarray, frame1: np.ndarray, log1: np.ndarray, t0: int, t1: int,
                     bound: float, max_insert: int):
    """Yield the inserted ``(frame, t_us)`` of ``[t0, t1]`` (see the module docstring);
    return ``(max_dlog, capped, inserted, rejected)``.

    ``make_flow`` builds the flow pair of the interval (None: linear blending
    only); its key frames split the interval into linear segments.
    """
    target = bound * (1 - _MARGIN)
    direct = _max_abs_diff(log1, log0)
    if direct <= target:
        return direct, False, 0, 0
    flow = None if make_flow is None else make_flow()
    keys = [] if flow is None else _key_times(flow, t0, t1)
    t, frame, log = t0, frame0, log0
    worst_all, capped, inserted, rejected = 0.0, False, 0, 0
    for end in keys + [t1]:
        if end == t1 or inserted >= max_insert:  # out of key frames or of the budget
            end, end_frame, end_log = t1, frame1, log1
        else:
            end_frame = flow.frame((end - t0) / (t1 - t0))  # type: ignore[union-attr]
            end_log = log_intensity(end_frame)
        worst, cut, count, retried = yield from _linear_segment(
            frame, log, end_frame, end_log, t, end, target, max_insert - inserted)
        worst_all, capped = max(worst_all, worst), capped or cut
        inserted, rejected = inserted + count, rejected + retried
        if end == t1:
            return worst_all, capped, inserted, rejected
        yield end_frame, end
        inserted += 1
        t, frame, log = end, end_frame, end_log
    raise AssertionError("unreachable: the last segment ends at t1")  # pragma: no cover


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
        frame = check_frame(frame_in, index, shape, settings.method)
        if index == 0 and np.asarray(frame_in).dtype.kind == "f":  # the first frame tells the scale
            from cmax.sim.esim import unit_range_note

            note = unit_range_note(frame, "frames")
            if note is not None:
                warnings.warn(note, UserWarning, stacklevel=3)
        t = _check_time(t_in, index, None if previous is None else previous[2])
        shape, log = frame.shape, log_intensity(frame)
        if previous is not None:
            frame0, log0, t0 = previous
            make_flow = None if settings.method == "linear" else (
                lambda: make_pair(frame0, frame, "flow", settings.flow_preset, state))
            max_dlog, capped, inserted, rejected = yield from _sample_interval(
                make_flow, frame0, log0, frame, log, t0, t, settings.bound, settings.max_insert)
            if report is not None:
                report(IntervalReport(index - 1, t0, t, inserted, max_dlog, capped, rejected))
        yield frame.copy(), t
        previous = (frame, log, t)
    if shape is None:
        raise ValueError("the frame source yielded no frames")


# -- public API -------------------------------------------------------------------------
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

    Only the previous input frame and the last sample are kept, so a video
    of hours streams in constant memory. See the module docstring for the
    algorithm, caps and limits.

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
        frames were yielded (inserted, rejected and whether it was capped).

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

    Warns
    -----
    UserWarning
        When the first frame is float in [0, 1] with fractional values
        (:func:`cmax.sim.esim.unit_range_note`): most likely a [0, 1] image,
        sampled as given (nearly black to ESIM), not rescaled.

    Examples
    --------
    >>> import numpy as np
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
    >>> import numpy as np
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
