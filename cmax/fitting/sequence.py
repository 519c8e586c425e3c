"""``cmax.fit_sequence``: fit a recording window by window and integrate the trajectory."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cmax.events import Events
from cmax.fitting.window import FitResult, fit
from cmax.geometry import se3_exp

__all__ = ["SequenceResult", "fit_sequence"]


@dataclass(frozen=True, eq=False)
class SequenceResult:
    """Window-by-window fits and the integrated trajectory.

    Attributes
    ----------
    results : tuple of FitResult
    times_us : ndarray (M + 1,)
        Start of every window, then the end of the last.
    poses : ndarray (M + 1, 4, 4)
        ``T_w_c`` at ``times_us``, the first the identity; between two starts the
        camera moves with the window's constant twist (metric only when every
        window's ``scale_known``).
    """

    results: tuple
    times_us: np.ndarray
    poses: np.ndarray


def fit_sequence(source, K: object, model: str = "se3", *, window_us: int = 166_500, step_us: int | None = None,
                 speed: float | None = None, min_events: int = 1000, **fit_options) -> SequenceResult:
    """Fit consecutive windows of a recording, warm-starting each from the previous.

    Parameters
    ----------
    source : Events or cmax.io.H5Reader
        Anything with ``window(t0_us, t1_us)`` (a reader) or an :class:`Events`.
    K : array_like (3, 3)
    model : str
    window_us, step_us : int
        Window length and the step between window starts [µs] (``step_us`` defaults to ``window_us``).
    speed : float, optional
        Known speed [m/s] of every window.
    min_events : int
        Windows with fewer events are skipped (the pose is held by the last twist).
    **fit_options
        Passed to :func:`fit`.
    """
    step_us = window_us if step_us is None else int(step_us)
    if window_us <= 0 or step_us <= 0:
        raise ValueError(f"window_us and step_us must be positive, got {window_us}, {step_us}")
    if isinstance(source, Events):
        t_start, t_end = int(source.t[0]), int(source.t[-1])
        take = lambda a, b: source.slice_time(a, b) if hasattr(source, "slice_time") else _slice(source, a, b)  # noqa: E731
    elif hasattr(source, "window"):
        t_start, t_end = int(source.t_start), int(source.t_end)
        take = source.window
    else:
        raise TypeError(f"source must be Events or a reader with window(t0_us, t1_us), got {type(source).__name__}")
    results, times, poses = [], [t_start], [np.eye(4)]
    previous: FitResult | None = None
    t0 = t_start
    while t0 + window_us <= t_end + 1:
        events = take(t0, t0 + window_us)
        twist = previous.twist if previous is not None else np.zeros(6)
        if len(events) >= min_events and events.t[-1] > events.t[0]:
            previous = fit(events, K, model, speed=speed if model == "se3" else None, init=previous, **fit_options)
            results.append(previous)
            twist = previous.twist
        poses.append(poses[-1] @ se3_exp(twist * step_us * 1e-6))
        times.append(t0 + step_us)
        t0 += step_us
    return SequenceResult(tuple(results), np.asarray(times, np.int64), np.stack(poses))


def _slice(events: Events, t0_us: int, t1_us: int) -> Events:
    i, j = np.searchsorted(events.t, [t0_us, t1_us])
    return events[int(i):int(j)]
