"""Noise models of the ESIM event model: threshold mismatch, leak and shot noise.

Pure functions of a ``numpy.random.Generator``; :class:`cmax.sim.esim.EventSimulator`
calls them in a fixed order from one generator seeded by its ``seed``, so a
seeded simulator gives the same events every time.

References
----------
Y. Hu, S.-C. Liu, T. Delbruck. "v2e: From Video Frames to Realistic DVS Events."
CVPR Workshops 2021 (leak and shot noise models).
"""
from __future__ import annotations

import numpy as np

from cmax.sim.esim_settings import MIN_THRESHOLD_FRACTION

__all__ = ["leak_drift", "leak_phase", "shot_noise", "threshold_map"]


def threshold_map(rng: np.random.Generator, threshold: float, sigma: float, n_pixels: int) -> np.ndarray:
    """Per-pixel thresholds ``C * (1 + sigma * N(0, 1))``, at least ``MIN_THRESHOLD_FRACTION * C``.

    Returns
    -------
    ndarray, float32, shape (n_pixels,)
        Thresholds in log-intensity units (fixed for the sensor's life).
    """
    drawn = threshold * (1.0 + sigma * rng.standard_normal(n_pixels))
    return np.maximum(drawn, MIN_THRESHOLD_FRACTION * threshold).astype(np.float32)


def leak_phase(rng: np.random.Generator, ref: np.ndarray, c_on: np.ndarray | np.float32) -> np.ndarray:
    """Reference levels with a random leak phase: ``ref - u * c_on``, ``u ~ U[0, 1)`` per pixel.

    ``ref`` (N,) float32; returns a new (N,) float32 array in ``(ref - c_on, ref]``.
    """
    phase = rng.random(ref.size, dtype=np.float32)
    return (ref - phase * c_on).astype(np.float32)


def leak_drift(leak_rate_hz: float, dt_us: int, c_on: np.ndarray | np.float32) -> np.ndarray | np.float32:
    """Drop of the reference level over ``dt_us`` µs: ``leak_rate_hz * dt * c_on`` (float32).

    A static pixel then emits ON events at ``leak_rate_hz`` (the v2e leak model).
    """
    return (np.float32(leak_rate_hz * dt_us * 1e-6) * c_on).astype(np.float32)


def shot_noise(rng: np.random.Generator, rate_hz: float, n_pixels: int,
               dt_us: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shot-noise events of one interval: a Poisson process per pixel at ``rate_hz``.

    Returns
    -------
    pixel : ndarray, int64, (K,)
        Flat pixel indices, uniform over the sensor.
    t_rel : ndarray, int64, (K,)
        Times in µs after the interval's start, uniform in ``[1, dt_us]``.
    polarity : ndarray, int8, (K,)
        0 (OFF) or 1 (ON) with equal probability.
    """
    count = rng.poisson(rate_hz * n_pixels * dt_us * 1e-6)
    pixel = rng.integers(0, n_pixels, count)
    t_rel = rng.integers(1, dt_us + 1, count)
    polarity = rng.integers(0, 2, count).astype(np.int8)
    return pixel, t_rel, polarity
