"""The event generation kernel of ESIM: threshold crossings of one interval and their times.

Between two samples a pixel's log intensity goes from ``log0`` to ``log1``
(linear in time). Its reference level ``ref`` moves by one threshold per
event: going up it crosses ``ref + C``, ``ref + 2C``, ... (ON), going down
``ref - C``, ``ref - 2C``, ... (OFF), every level with ``log0 < level <= log1``
(down: ``log1 <= level < log0``). The levels are float32 running sums
(``L_ref += C`` in float32, one threshold at a time), exactly as the reference
C++ ESIM computes them: a pixel that returns to its starting grey value lands
*exactly* on a level, and whether it fires depends on that rounding.

The kernel works in *signed* space: with ``s = +1`` (up) or ``-1`` (down),
``s * level`` grows by ``|C|`` per crossing, and because float32 rounding is
symmetric in sign, ``s * (ref + k*(s*C))`` summed sequentially equals
``s*ref + C + ... + C`` summed sequentially. One comparison ``s*level <=
s*log1`` then serves both polarities.

:class:`~cmax.sim.esim.EventSimulator` runs the compiled kernels at the end
of this module (:func:`_interval_crossings`, :func:`_sorted_by_time`: the same
arithmetic, pixel by pixel) unless it needs the refractory period or shot
noise, which use the vectorised functions. Cost of those: per interval a few vectorised passes over the pixels whose log
intensity moved within 10 % of a threshold of their next level (the *near*
pixels; on real video a few percent of the sensor), then one short pass per
rank of crossing over the pixels still crossing (most pixels fire once or not
at all). Pixels still crossing after :data:`_ITERATIONS` ranks (strong edges,
flashes) are finished in one go with ``np.add.accumulate`` along rows of
candidate levels, grouped by powers of two of their count.

References
----------
H. Rebecq, D. Gehrig, D. Scaramuzza. "ESIM: an Open Event Camera Simulator." CoRL 2018.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from cmax._jit import kernel

__all__ = ["Crossings", "crossing_times", "fire", "near_pixels", "refractory_keep", "sort_events",
           "threshold_crossings"]

#: Ranks of crossing handled one pass each before the remaining pixels are
#: finished with running sums along rows (see the module docstring).
_ITERATIONS = 16
_ONE, _MINUS_ONE = np.float32(1.0), np.float32(-1.0)
_NEAR = np.float32(0.9)


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


def near_pixels(ref: np.ndarray, log1: np.ndarray, near_on, near_off) -> np.ndarray:
    """Flat indices (sorted, int64) of pixels within 10 % of a threshold of their next level.

    ``near_on = 0.9 * c_on`` and ``near_off = -0.9 * c_off`` (float32 scalars
    or (N,) arrays). Every pixel that can cross a level lies in this set: a
    crossing needs ``|log1 - ref| >= C`` in exact arithmetic, and float32
    rounding moves the levels by far less than ``0.1 * C``.
    """
    beyond = log1 - ref
    near = beyond > near_on
    near |= beyond < near_off
    return np.flatnonzero(near)


def _empty() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    none = np.empty(0, np.int64)
    return none, none.astype(np.float32), none.astype(np.int8)


def fire(rows, ref, log0, log1, c_on, c_off, *, by_pixel: bool):
    """(pixel, level, polarity) of the crossings of pixels ``rows``; moves ``ref`` in place.

    Parameters
    ----------
    rows : ndarray, int64, shape (R,)
        Sorted candidate pixels (a superset of the pixels that cross, e.g.
        :func:`near_pixels`).
    ref : ndarray, float32, shape (N,)
        Reference levels; the crossing pixels' entries end on their last level.
    log0, log1 : ndarray, float32, shape (N,)
        Log intensity at the two samples.
    c_on, c_off : float32 scalar or ndarray, float32, shape (N,)
        Positive thresholds.
    by_pixel : bool
        Sort the output by pixel (each pixel's crossings in order); otherwise
        the crossings come grouped by rank (all first crossings, then all
        second ones, ...), which is enough when the caller sorts by time.

    Returns
    -------
    pixel : ndarray, int64, (M,); level : ndarray, float32, (M,); polarity : ndarray, int8, (M,)
    """
    if not rows.size:
        return _empty()
    l0, l1 = log0[rows], log1[rows]
    up = l1 > l0
    sign = np.where(up, _ONE, _MINUS_ONE)
    if np.ndim(c_on) or np.ndim(c_off):
        step = np.where(up, np.broadcast_to(c_on, ref.shape)[rows], np.broadcast_to(c_off, ref.shape)[rows])
    else:
        step = np.where(up, c_on, c_off)
    high = l1 * sign
    signed = ref[rows] * sign
    signed += step  # s * (first level)
    hit = signed <= high
    hit &= signed > l0 * sign  # the first level lies beyond log0 (else nothing is crossed)
    active = np.flatnonzero(hit)
    if not active.size:
        return _empty()
    indices, levels = [active], [signed[active]]
    last = signed  # per row: the signed level of its latest crossing (valid where fired)
    for _ in range(_ITERATIONS - 1):
        following = levels[-1] + step[active]
        more = following <= high[active]
        if not more.any():
            active = active[:0]
            break
        active, following = active[more], following[more]
        last[active] = following
        indices.append(active)
        levels.append(following)
    fired = indices[0]
    ref[rows[fired]] = last[fired] * sign[fired]
    index = indices[0] if len(indices) == 1 else np.concatenate(indices)
    pixel = rows[index]
    level = (levels[0] if len(levels) == 1 else np.concatenate(levels)) * sign[index]
    polarity = up[index].view(np.int8)
    if active.size:  # pixels still crossing: finish them with running sums
        tail = _bucketed(rows[active], ref, log0, log1, c_on, c_off)
        pixel = np.concatenate([pixel, tail[0]])
        level = np.concatenate([level, tail[1]])
        polarity = np.concatenate([polarity, tail[2]])
    if by_pixel and len(indices) > 1:
        order = np.argsort(pixel, kind="stable")
        pixel, level, polarity = pixel[order], level[order], polarity[order]
    return pixel, level, polarity


def _bucket_levels(ref, log0, log1, step, up, count):
    """Sequential float32 levels ``ref + k*step`` (k = 1..width), (m, width), and how
    many of each row are crossed (the leading ``lo < level <= hi`` ones, sign-flipped down).

    Levels are strictly monotonic along a row, so the crossed ones are a prefix
    once the first lies beyond ``log0``.
    """
    width = int(count.max())
    sign = np.where(up, _ONE, _MINUS_ONE)
    levels = np.empty((ref.size, width), np.float32)
    levels[:, 0] = ref + step
    levels[:, 1:] = step[:, None]
    np.add.accumulate(levels, axis=1, dtype=np.float32, out=levels)  # sequential, like L_ref += C
    high = log1 * sign
    crossed = np.count_nonzero(levels * sign[:, None] <= high[:, None], axis=1)
    crossed[levels[:, 0] * sign <= log0 * sign] = 0
    return levels, crossed


def _bucketed(rows, ref, log0, log1, c_on, c_off):
    """:func:`fire` for pixels with many crossings, sorted by pixel; moves ``ref`` in place.

    Each pixel gets ``floor((log1 - ref)/C) + 2`` candidate levels (a margin
    of at least one threshold over float32 rounding), computed as running
    sums; pixels are grouped by powers of two of that count.
    """
    ref_r, log0_r, log1_r = ref[rows], log0[rows], log1[rows]
    up = log1_r > log0_r
    c_on_r = c_on[rows] if np.ndim(c_on) else c_on
    c_off_r = c_off[rows] if np.ndim(c_off) else c_off
    step = np.where(up, c_on_r, -c_off_r).astype(np.float32)
    exact = (log1_r.astype(np.float64) - ref_r) / step  # levels reached, in exact arithmetic
    count = np.floor(exact).astype(np.int64) + 2  # candidates, >= 2
    bucket = np.frexp(count.astype(np.float64))[1]  # 2**(b-1) <= count < 2**b
    parts = []
    for b in np.flatnonzero(np.bincount(bucket)):
        sel = np.flatnonzero(bucket == b)
        levels, n = _bucket_levels(ref_r[sel], log0_r[sel], log1_r[sel], step[sel], up[sel], count[sel])
        valid = np.arange(levels.shape[1]) < n[:, None]
        fired = np.flatnonzero(n)
        rows_b = rows[sel]
        ref[rows_b[fired]] = levels[fired, n[fired] - 1]
        parts.append((np.repeat(rows_b, n), levels[valid], np.repeat(up[sel], n)))
    pixel = np.concatenate([part[0] for part in parts])
    level = np.concatenate([part[1] for part in parts])
    polarity = np.concatenate([part[2] for part in parts]).view(np.int8)
    order = np.argsort(pixel, kind="stable")
    return pixel[order], level[order], polarity[order]


def crossing_times(pixel: np.ndarray, level: np.ndarray, log0: np.ndarray, log1: np.ndarray,
                   dt_us: int) -> np.ndarray:
    """Times of crossings in whole µs after the interval's start, int64, shape (M,).

    ``tau = (level - log0) * dt / (log1 - log0)`` with the two differences in
    float32 and the rest in float64 (as the reference ESIM), rounded half up:
    ``floor(tau + 0.5)``. Since ``level`` lies between ``log0`` (excluded) and
    ``log1`` and rounding is monotonic, ``0 <= t <= dt_us``.
    """
    log0_e = log0[pixel]
    tau = (level - log0_e).astype(np.float64)
    tau *= dt_us
    tau /= log1[pixel] - log0_e
    tau += 0.5
    return np.floor(tau, out=tau).astype(np.int64)


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
    the reference ESIM (see the module docstring for the algorithm).

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

    Examples
    --------
    >>> import numpy as np
    >>> c = np.float32(0.1)
    >>> out = threshold_crossings(np.zeros(1, np.float32), np.zeros(1, np.float32),
    ...                           np.full(1, 0.25, np.float32), c, c)
    >>> out.pixel.tolist(), out.polarity.tolist(), round(float(out.ref[0]), 6)
    ([0, 0], [1, 1], 0.2)
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
    for name in ("c_on", "c_off"):
        if np.ndim(arrays.get(name, 1.0)) and not (arrays[name] > 0).all():
            raise ValueError(f"{name} must hold positive thresholds")
    rows = near_pixels(ref, log1, _NEAR * c_on, -_NEAR * c_off)
    ref_out = ref.copy()
    pixel, level, polarity = fire(rows, ref_out, log0, log1, c_on, c_off, by_pixel=True)
    return Crossings(pixel, level, polarity, ref_out)


def refractory_keep(pixel: np.ndarray, t: np.ndarray, last_t: np.ndarray,
                    refractory_us: int) -> np.ndarray:
    """Which events survive the refractory period (bool, (M,)); updates ``last_t`` (N,) in place.

    ``pixel`` is grouped by pixel with times non-decreasing in each group
    (``fire(..., by_pixel=True)``). Loops over the rank of an event in its
    pixel (a handful per interval), vectorised over pixels: an event is kept
    when it comes at least ``refractory_us`` after the pixel's last kept event.
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


def sort_events(pixel: np.ndarray, t_rel: np.ndarray, polarity: np.ndarray, n_pixels: int,
                dt_us: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Events of one interval sorted by time, then pixel (raster order), then polarity.

    The three columns are packed into one int64 key, ``t << (b + 1) | pixel << 1 |
    polarity`` with ``2**b >= n_pixels``, which is sorted by value (no index
    array, no gathers) and unpacked with shifts; intervals too long for the
    key (``dt_us >= 2**(62 - b)``) fall back to ``np.lexsort``.

    Parameters
    ----------
    pixel, t_rel : ndarray, int64, shape (M,)
        Flat pixel index in ``[0, n_pixels)`` and time in µs in ``[0, dt_us]``.
    polarity : ndarray, int8, shape (M,)
        0 or 1.

    Returns
    -------
    pixel, t_rel : ndarray, int64; polarity : ndarray, int8 -- new arrays, sorted.
    """
    bits = max(1, (n_pixels - 1).bit_length())
    if dt_us >= 2 ** (62 - bits):  # pragma: no cover - intervals of weeks
        order = np.lexsort((polarity, pixel, t_rel))
        return pixel[order], t_rel[order], polarity[order]
    key = t_rel << (bits + 1)
    key |= pixel << 1
    key |= polarity
    key.sort()
    polarity = (key & 1).astype(np.int8)
    key >>= 1
    pixel = key & ((1 << bits) - 1)
    key >>= bits
    return pixel, key, polarity


# -- compiled interval kernel -----------------------------------------------------------------
@kernel
def _interval_crossings(ref, log0, log1, c_on, c_off, near_on, near_off, dt_us, limit):
    """Crossings of every pixel in one interval, pixel by pixel; moves ``ref`` in place.

    ``c_on``, ``c_off``, ``near_on``, ``near_off`` are float32 arrays of length 1
    (one threshold for all pixels) or N. A first pass finds the pixels within
    10 % of a threshold of their next level (:func:`near_pixels`' test) and
    bounds their crossings by ``floor(|log1 - ref| / C) + 2`` (the margin of
    :func:`_bucketed`); the second computes, per such pixel, the levels as
    the float32 running sums of :func:`fire` in signed space and the times as
    :func:`crossing_times`. Returns (pixel int64, t_rel int64, polarity int8),
    (M,) each, grouped by pixel in raster order, each pixel's crossings in
    order, whether the bound held (it always should; the caller raises if not),
    and the bound. A bound over ``limit`` returns at once, before allocating:
    no crossings, ``ref`` untouched.
    """
    n = ref.size
    per_pixel = c_on.size > 1
    rows = np.empty(n, np.int64)
    n_rows, bound = 0, 0
    for i in range(n):
        k = i if per_pixel else 0
        beyond = log1[i] - ref[i]
        if beyond > near_on[k] or beyond < near_off[k]:
            rows[n_rows] = i
            n_rows += 1
            step = c_on[k] if beyond > 0 else c_off[k]
            bound += np.int64(abs(np.float64(beyond)) / np.float64(step)) + 2
    if bound > limit:
        return np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0, np.int8), True, bound
    pixel = np.empty(bound, np.int64)
    t_rel = np.empty(bound, np.int64)
    polarity = np.empty(bound, np.int8)
    m, held = 0, True
    for r in range(n_rows):
        i = rows[r]
        k = i if per_pixel else 0
        l0, l1 = log0[i], log1[i]
        up = l1 > l0
        sign = np.float32(1.0) if up else np.float32(-1.0)
        step = c_on[k] if up else c_off[k]
        high = l1 * sign
        level = ref[i] * sign + step
        if not (level <= high and level > l0 * sign):
            continue
        span = np.float64(l1 - l0)
        while True:
            if m == bound:
                held = False
                break
            pixel[m] = i
            t_rel[m] = np.int64(np.floor(np.float64(level * sign - l0) * dt_us / span + 0.5))
            polarity[m] = up
            m += 1
            following = level + step
            if not following <= high:
                break
            level = following
        ref[i] = level * sign
    return pixel[:m], t_rel[:m], polarity[:m], held, bound


def crossing_bound(rows: np.ndarray, ref: np.ndarray, log1: np.ndarray, c_on, c_off) -> int:
    """At most how many crossings pixels ``rows`` make from ``ref`` to ``log1``: ``floor(|log1 - ref| / C) + 2``
    each (the margin of :func:`_bucketed`), summed; the bound :func:`_interval_crossings` allocates."""
    beyond = log1[rows].astype(np.float64) - ref[rows]
    c_on_r = c_on[rows] if np.ndim(c_on) else c_on
    c_off_r = c_off[rows] if np.ndim(c_off) else c_off
    step = np.where(beyond > 0, c_on_r, c_off_r).astype(np.float64)
    return int(np.sum(np.floor(np.abs(beyond) / step).astype(np.int64) + 2))


@kernel
def _sorted_by_time(pixel, t_rel, polarity, dt_us, width, t_start, x, y, t, p, offset):
    """Write events (grouped by pixel) into x, y, t, p from ``offset``, sorted by time.

    A stable counting sort on ``t_rel`` in ``[0, dt_us]`` scatters each event
    straight to its place (a stable merge sort when the interval is long
    against the event count), keeping the pixel order, then the crossing
    order, among equal times; x, y are ``pixel % width`` and ``pixel //
    width``, t is ``t_start + t_rel``.
    """
    m = pixel.size
    if dt_us + 1 <= 4 * m + 4096:
        slot = np.zeros(dt_us + 2, np.int64)
        for j in range(m):
            slot[t_rel[j] + 1] += 1
        slot[0] = offset
        for b in range(1, dt_us + 2):
            slot[b] += slot[b - 1]
        for j in range(m):
            at = slot[t_rel[j]]
            slot[t_rel[j]] = at + 1
            q = pixel[j]
            x[at] = q % width
            y[at] = q // width
            t[at] = t_start + t_rel[j]
            p[at] = polarity[j]
    else:
        order = np.argsort(t_rel, kind="mergesort")
        for r in range(m):
            j = order[r]
            q = pixel[j]
            x[offset + r] = q % width
            y[offset + r] = q // width
            t[offset + r] = t_start + t_rel[j]
            p[offset + r] = polarity[j]
