"""Settings of the ESIM event model (:class:`EsimSettings`) and their validation."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["MIN_THRESHOLD", "MIN_THRESHOLD_FRACTION", "EsimSettings"]

#: Per-pixel thresholds drawn with ``threshold_sigma > 0`` are clipped to at
#: least this fraction of the nominal threshold (``0.1 * cp`` and ``0.1 * cn``).
MIN_THRESHOLD_FRACTION = 0.1

#: Smallest accepted ``cp`` / ``cn``: float32 log levels (resolution ~5e-7)
#: must move by a threshold, and a full 0..255 change then gives at most
#: about 7,000 events per pixel and interval.
MIN_THRESHOLD = 1e-3

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
