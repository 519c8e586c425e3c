"""OpenCV's ``cv::log`` of float32 values (``log32f``), reimplemented bit for bit in numpy.

ESIM's reference implementation (``esim_py`` of uzh-rpg/rpg_vid2e) computes
log intensities with ``cv::log``; to give the same events, :mod:`cmax.sim.esim`
must round exactly as OpenCV's own algorithm does. The ``cv2`` wheels call
Intel IPP instead, which rounds differently, so the algorithm is rebuilt here
from its table and fused multiply-adds: :func:`_cv_log32f` on top of
:func:`_fma32`, a float32 fused multiply-add rounded once.

References
----------
OpenCV, ``modules/core/src/mathfuncs_core.simd.hpp`` (``log32f``, the SIMD path).
"""
from __future__ import annotations

import math

import numpy as np


def _log_table() -> np.ndarray:
    """OpenCV's ``logTab`` in float32: ``log(1 + k/256), 1/(1 + k/256)``, then ``log 2, 1/2``."""
    k = np.arange(256, dtype=np.float64)
    table = np.empty(512, np.float64)
    table[0::2], table[1::2] = np.log1p(k / 256.0), 256.0 / (256.0 + k)
    table[510], table[511] = math.log(2.0), 0.5
    return table.astype(np.float32)


_LOG_TABLE = _log_table()


_HALF_LOW = np.uint64(1 << 28)  # float64 bits of a value half-way between two float32 ...
_LOW_MASK = np.uint64((1 << 29) - 1)  # ... : the 29 dropped mantissa bits are 1000...0
_EXP_MASK = np.uint64(0x7FF << 52)
_MIN_NORMAL32 = np.uint64((1023 - 126) << 52)  # float64 exponent bits of 2**-126


def _fma32(a: np.ndarray, b: np.ndarray | np.float32, c: np.ndarray | np.float32) -> np.ndarray:
    """``fma(a, b, c)`` of float32 values rounded once to float32 (exact, in float64).

    ``a*b`` is exact in float64; the sum is rounded to float64 and then to
    float32. That double rounding can be wrong only when the float64 sum lies
    exactly half-way between two float32 values (its 29 low mantissa bits are
    ``100...0``) or below the float32 normal range; those few elements are
    resolved exactly by :func:`_fma32_exact`, the rest are rounded directly.
    """
    product = np.asarray(a, np.float64) * np.asarray(b, np.float64)
    total = product + np.asarray(c, np.float64)
    rounded = total.astype(np.float32)
    bits = total.view(np.uint64)
    suspect = (bits & _LOW_MASK) == _HALF_LOW
    suspect |= (bits & _EXP_MASK) < _MIN_NORMAL32
    if suspect.any():
        where = np.nonzero(suspect)
        pick = lambda v: np.broadcast_to(np.asarray(v, np.float32), total.shape)[where]  # noqa: E731
        rounded = np.array(rounded, np.float32, ndmin=1) if rounded.ndim == 0 else rounded
        rounded[where] = _fma32_exact(pick(a), pick(b), pick(c))
    return rounded


def _fma32_exact(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """:func:`_fma32` with every element resolved by the TwoSum error term (slow, exact)."""
    product = np.asarray(a, np.float64) * np.asarray(b, np.float64)
    addend = np.asarray(c, np.float64)
    total = product + addend
    partner = total - product
    error = (product - (total - partner)) + (addend - partner)  # total + error == exact sum
    rounded = total.astype(np.float32)
    side = np.sign(total - rounded)
    neighbour = np.nextafter(rounded, np.where(side > 0, np.float32(np.inf), np.float32(-np.inf)))
    halfway = (side != 0) & (total == (rounded.astype(np.float64) + neighbour) * 0.5)
    beyond = halfway & (np.sign(error) == side)  # exact sum past the half-way point
    return np.where(beyond, neighbour, rounded).astype(np.float32)


def _cv_log32f(x: np.ndarray) -> np.ndarray:
    """``cv::log`` of positive, normal float32 values, bit for bit, in numpy.

    OpenCV's own algorithm (``log32f`` in ``mathfuncs_core.simd.hpp``, the
    SIMD path with fused multiply-adds): the exponent times ``ln 2``, a
    256-entry table on the top 8 mantissa bits and a cubic in the rest. This
    is what the reference ESIM computed; the ``cv2`` wheels call Intel IPP
    instead, whose results differ in the last bit for about 40 % of the
    inputs, and the reference's crossings then differ for 0.15 % of events.
    """
    f32 = np.float32
    bits = np.ascontiguousarray(x, np.float32).view(np.int32)
    exponent = (((bits >> 23) & 255) - 127).astype(np.float32)
    mantissa = ((bits & ((1 << 15) - 1)) | (127 << 23)).view(np.float32)  # in [1, 1 + 2**-8)
    index = (bits >> 14) & 510
    y0 = _fma32(exponent, f32(math.log(2.0)), _LOG_TABLE[index])
    shift = np.where(index == 510, f32(-1.0 / 512.0), f32(0.0))
    x0 = _fma32(mantissa - f32(1.0), _LOG_TABLE[index + 1], shift)
    z = _fma32(x0, f32(1.0 / 3.0), f32(-0.5))
    z = _fma32(z, x0, f32(1.0))
    return _fma32(z, x0, y0).reshape(np.shape(x))
