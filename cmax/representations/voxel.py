"""The voxel grid (event volume) of Zhu et al. (2019): numpy or torch, one window or a batch.

Numpy input takes one of three equivalent methods (per-event weights, or two
``np.bincount`` per bin interval of the time-sorted events, signed or split
by polarity), picked from the number of events per pixel; torch input goes
through ``index_add_``, and :func:`voxel_grid_batch` builds the grids of
several windows in one pass.

Reference: A. Z. Zhu, L. Yuan, K. Chaney, K. Daniilidis, "Unsupervised
event-based learning of optical flow, depth, and egomotion", CVPR 2019,
doi:10.1109/CVPR.2019.00108.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np

from cmax.events import Events, EventTensors
from cmax.representations import _common
from cmax.representations._common import (
    Array, EventsLike, _check_int, _check_optional_time, _check_output_size, _chunks,
    _index_numpy, _inspect, _on_torch, _pixel_counts, _polarity_ok, _refuse_polarity, _stats_torch,
)

if TYPE_CHECKING:  # pragma: no cover
    import torch

__all__ = ["voxel_grid", "voxel_grid_batch", "VoxelGrid", "NORMALIZATIONS"]

#: Time normalizations of :func:`voxel_grid`: ``"paper"`` (Zhu et al.: ``t*`` in ``[0, B-1]``) and
#: ``"tonic"`` (tonic's ``ToVoxelGrid``: ``t*`` in ``[0, B]``, weight beyond bin B-1 dropped).
NORMALIZATIONS = ("paper", "tonic")

_FLOAT64_EXACT = 2**53  # integers below this are exact in float64


def _window(
    t_range: tuple[int, int] | None, t0_us: int | None, t1_us: int | None
) -> tuple[int, int]:
    """The normalisation window (t0, span) in µs, checked against the events' times."""
    if t0_us is not None and t1_us is not None and t1_us < t0_us:
        raise ValueError(f"t1_us ({t1_us}) must not be smaller than t0_us ({t0_us})")
    if t_range is None:
        t0 = 0 if t0_us is None else t0_us
        return t0, (t0 if t1_us is None else t1_us) - t0
    t_min, t_max = t_range
    t0 = t_min if t0_us is None else t0_us
    t1 = t_max if t1_us is None else t1_us
    if t_min < t0:
        raise ValueError(f"an event at t={t_min} µs lies before the window start t0_us={t0} µs")
    if t_max > t1:
        raise ValueError(f"an event at t={t_max} µs lies after the window end t1_us={t1} µs")
    if t1 < t0:
        raise ValueError(f"the window [{t0}, {t1}] µs is empty (t1 < t0)")
    return t0, t1 - t0


# -- voxel grid ------------------------------------------------------------------------------
def voxel_grid(
    events: EventsLike,
    bins: int = 5,
    *,
    t0_us: int | None = None,
    t1_us: int | None = None,
    normalization: str = "paper",
    pixels: np.ndarray | None = None,
) -> Array:
    r"""The event volume of Zhu et al. (2019): signed polarities spread linearly over time bins.

    .. math::

        E(x, y, b) = \sum_i p_i \max(0, 1 - |b - t^*_i|), \qquad
        t^*_i = (B - 1) \frac{t_i - t_0}{t_N - t_0},

    for ``b = 0 .. B-1``, with the paper's signed polarity ``p_i`` in {-1, +1}
    (OFF = -1). Each event's weight (1 in total) is split between the two bins
    around ``t*_i``, so the sum over bins equals the per-pixel sum of signed
    polarities. Normalised time is computed in float64 from the integer
    differences ``t_i - t_0`` (no loss on absolute time stamps).

    Parameters
    ----------
    events : Events or EventTensors
        N events. Numpy in gives a numpy array; torch in gives a tensor on the
        events' device. Torch polarity may be {0, 1} or {-1, +1} (integer or float), or bool;
        other values raise :class:`ValueError`, as :class:`~cmax.events.Events` does.
    bins : int
        Number of time bins B >= 1. ``bins=1`` gives the signed event frame.
    t0_us, t1_us : int, optional, keyword-only
        The window ``[t_0, t_N]`` in microseconds; by default the first and last
        event times (the min and max of ``t``). Every event must lie inside.
    normalization : {"paper", "tonic"}, keyword-only
        ``"paper"`` (default): ``t*`` as above, in ``[0, B-1]``, so the first and
        last events sit on the first and last bins. ``"tonic"``: the convention of
        tonic's ``ToVoxelGrid``, ``t* = B (t_i - t_0) / (t_N - t_0)`` in ``[0, B]``,
        whose weight above bin B-1 is dropped (the last event is lost): the first B
        bins of the paper's volume with B+1 bins. When ``t_N == t_0`` both put every
        event in bin 0 (tonic divides by zero there).
    pixels : array_like, shape (N, 2), optional, keyword-only
        Sub-pixel positions ``(x, y)`` [px] of the events (numpy :class:`Events` only), e.g. their exact
        undistorted and rectified positions (:meth:`cmax.Camera.undistorted_pixels`) in place of their integer
        pixels: each event's weight is also split bilinearly over the 4 pixels around its position (as DSEC's
        and E-RAFT's loaders do after ``rectify_map.h5``), so a lens that spreads the pixels apart leaves no
        pixels without events. Weight falling outside the image is dropped; rows with a NaN (no position) are
        left out. Inside the image, the sum over bins and pixels is the sum of signed polarities.

    Returns
    -------
    ndarray or Tensor, shape (B, H, W), float32

    Notes
    -----
    When ``t_N == t_0`` (a single event, all events at one time stamp, or a
    zero-length window) ``t*`` is undefined; it is taken as 0, so every event
    lands in bin 0 with weight ``p_i``. No events give zeros.

    Numpy input uses the time order of :class:`Events`; torch input may come in
    any order. Torch input is validated with one device synchronisation (the
    bounds of ``x``, ``y`` and ``t`` are read back). Numpy accumulates in
    float64, torch in float32: they agree to about 1e-6 relative.

    Examples
    --------
    >>> ev = Events([0, 1, 1], [0, 0, 0], [0, 50, 100], [1, 1, 0], width=2, height=1)
    >>> voxel_grid(ev, bins=3)[:, 0].tolist()
    [[1.0, 0.0], [0.0, 1.0], [0.0, -1.0]]
    >>> voxel_grid(ev.to_torch(), bins=3).shape
    torch.Size([3, 1, 2])
    """
    bins = _check_int("bins", bins, minimum=1)
    if normalization not in NORMALIZATIONS:
        raise ValueError(f"normalization must be one of {NORMALIZATIONS}, got {normalization!r}")
    if normalization == "tonic":
        return voxel_grid(events, bins + 1, t0_us=t0_us, t1_us=t1_us, pixels=pixels)[:bins]
    t0_us = _check_optional_time("t0_us", t0_us)
    t1_us = _check_optional_time("t1_us", t1_us)
    kind, t_range = _inspect(events)
    _check_output_size(
        (bins, events.height, events.width), f"bins={bins} on a {events.width}x{events.height} sensor"
    )
    t0, span = _window(t_range, t0_us, t1_us)
    if pixels is not None:
        if kind != "numpy":
            raise TypeError("pixels= takes numpy cmax.Events; the torch path spreads integer pixels only")
        return _voxel_grid_bilinear(events, _check_pixels(pixels, len(events)), bins, t0, span)
    if kind == "numpy":
        return _voxel_grid_numpy(events, bins, t0, span)
    return _voxel_grid_torch(events, bins, t0, span)


def _check_pixels(pixels: object, n: int) -> np.ndarray:
    """``pixels`` as an (n, 2) float64 array [px]; ValueError naming ``pixels`` otherwise."""
    try:
        xy = np.asarray(pixels, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"pixels must be an (N, 2) array of numbers [px], got {type(pixels).__name__}") from None
    if xy.shape != (n, 2):
        raise ValueError(f"pixels must have shape ({n}, 2), one (x, y) [px] per event, got {xy.shape}")
    return xy


def _voxel_grid_bilinear(events: Events, pixels: np.ndarray, bins: int, t0: int, span: int) -> np.ndarray:
    """(B, H, W) float32: each event's signed polarity spread linearly over the two time bins around ``t*`` and
    bilinearly over the 4 pixels around its position ``pixels`` (N, 2) [px]; weight outside the image, and
    events with a non-finite position, are dropped."""
    height, width = events.height, events.width
    plane = height * width
    grid = np.zeros(bins * plane, np.float64)
    signs = np.array([-1.0, 1.0])
    for run in _chunks(0, len(events)):
        xy = pixels[run]
        keep = np.isfinite(xy).all(axis=1)
        xy, t, p = xy[keep], events.t[run][keep], events.p[run][keep]
        if not len(t):   # every position of the run non-finite (beyond the lens's reach): nothing to spread
            continue
        if bins == 1 or span == 0:
            low, fraction = np.zeros(len(t), np.intp), np.zeros(len(t))
        else:
            t_star = _elapsed(t, t0, np.empty(len(t), np.float64)) * (bins - 1) / span
            low = np.minimum(np.floor(t_star).astype(np.intp), bins - 2)
            fraction = t_star - low
        corner = np.floor(xy)
        dx, dy = xy[:, 0] - corner[:, 0], xy[:, 1] - corner[:, 1]
        col, row = corner[:, 0].astype(np.intp), corner[:, 1].astype(np.intp)
        signed = signs[p]
        for ox, oy, w_xy in ((0, 0, (1 - dx) * (1 - dy)), (1, 0, dx * (1 - dy)), (0, 1, (1 - dx) * dy),
                             (1, 1, dx * dy)):
            c, r = col + ox, row + oy
            inside = (c >= 0) & (c < width) & (r >= 0) & (r < height)
            flat = (r * width + c)[inside]
            w = (signed * w_xy)[inside]
            f, b = fraction[inside], low[inside]
            grid += np.bincount(b * plane + flat, weights=w * (1 - f), minlength=bins * plane)
            if bins > 1:
                grid += np.bincount((b + 1) * plane + flat, weights=w * f, minlength=bins * plane)
    return grid.astype(np.float32).reshape(bins, height, width)


def _voxel_grid_numpy(
    events: Events, bins: int, t0: int, span: int, *, method: str | None = None
) -> np.ndarray:
    """Numpy voxel grid of time-sorted events, by one of three equivalent methods.

    'weights' (:func:`_voxel_grid_weights`) has the lowest fixed cost, 'signed'
    and 'split' (:func:`_voxel_grid_runs`) the lowest cost per event; by
    default the method is picked from the number of events per pixel.
    """
    height, width = events.height, events.width
    plane = height * width
    n = len(events)
    if n == 0:
        return np.zeros((bins, height, width), np.float32)
    if bins == 1 or span == 0:  # t* = 0 for every event: the signed event frame in bin 0
        counts = _pixel_counts(events)
        grid = np.zeros((bins, plane), np.float32)
        np.subtract(counts[plane:], counts[:plane], out=grid[0], casting="unsafe")
        return grid.reshape(bins, height, width)
    if method is None:
        method = "weights" if n < plane // 2 else "signed" if n < 4 * (bins - 1) * plane else "split"
    if method == "weights":
        grid = _voxel_grid_weights(events, bins, t0, span)
    else:
        grid = _voxel_grid_runs(events, bins, t0, span, split_polarity=method == "split")
    return grid.reshape(bins, height, width)


def _elapsed(t: np.ndarray, t0: int, out: np.ndarray) -> np.ndarray:
    """``t - t0`` in float64 (exact below 2**53 µs), written into ``out``."""
    out = out[: t.size]
    if max(abs(int(t[0])), abs(int(t[-1])), abs(t0)) < _FLOAT64_EXACT:
        return np.subtract(t, t0, out=out, dtype=np.float64)  # both operands exact in float64
    out[...] = t - t0
    return out


def _voxel_grid_weights(events: Events, bins: int, t0: int, span: int) -> np.ndarray:
    """(B, H*W) float32 from per-event linear weights, binned with ``np.bincount``."""
    n, plane = len(events), events.width * events.height
    chunk = min(n, _common._CHUNK)
    fraction, lower = np.empty(chunk, np.float64), np.empty(chunk, np.intp)
    index, weights = np.empty(2 * chunk, np.intp), np.empty(2 * chunk, np.float64)
    signs = np.array([-1.0, 1.0])
    grid = None
    for run in _chunks(0, n):
        m = run.stop - run.start
        t_star = _elapsed(events.t[run], t0, fraction)  # t* = (t - t0)(B-1) / span: exact at B-1
        t_star *= bins - 1
        t_star /= span
        low = lower[:m]
        low[...] = t_star  # floor, as t* >= 0
        np.minimum(low, bins - 2, out=low)  # t* = B-1 reaches bin B-1 through the right weight
        t_star -= low  # now the fraction in [0, 1]
        left, right = index[:m], index[m: 2 * m]
        np.multiply(low, events.height, out=left)
        left += events.y[run]
        left *= events.width
        left += events.x[run]
        np.add(left, plane, out=right)
        signed = np.take(signs, events.p[run], out=weights[:m])
        np.multiply(signed, t_star, out=weights[m: 2 * m])
        signed -= weights[m: 2 * m]
        part = np.bincount(index[: 2 * m], weights=weights[: 2 * m], minlength=bins * plane)
        if grid is None:
            grid = part
        else:
            grid += part
    return grid.astype(np.float32).reshape(bins, plane)


def _voxel_grid_runs(
    events: Events, bins: int, t0: int, span: int, split_polarity: bool
) -> np.ndarray:
    """(B, H*W) float32 from two ``np.bincount`` per bin interval of the sorted events.

    Events with ``k <= t* < k+1`` (the last run also holds ``t* = B-1``) are
    contiguous because ``t`` is sorted. Over such a run, per pixel, let
    ``S = sum p_i`` and ``V = sum p_i (t*_i - k) = a sum p_i (t_i - t_0) - k S``,
    ``a = (B-1)/span``; the linear weights then sum to ``S - V`` in bin k and
    ``V`` in bin k+1. With ``split_polarity`` the sums are taken per polarity
    over the (polarity, pixel) index, unweighted and weighted by ``t - t0``,
    and the signs are applied to the (2, H*W) sums; otherwise the per-event
    weights carry the sign (more per-event work, half the per-pixel work).
    """
    plane, n, t = events.width * events.height, len(events), events.t
    # first event with t* >= k  <=>  (t - t0)(B-1) >= k span  <=>  t >= t0 + ceil(k span / (B-1))
    starts = [t0 + -(-k * span // (bins - 1)) for k in range(1, bins - 1)]
    edges = [0, *np.searchsorted(t, np.array(starts, np.int64), side="left").tolist(), n]
    size = 2 * plane if split_polarity else plane
    chunk = min(n, _common._CHUNK)
    index_buffer, time_buffer = np.empty(chunk, np.intp), np.empty(chunk, np.float64)
    sign_buffer = None if split_polarity else np.empty(chunk, np.float64)
    signs = np.array([-1.0, 1.0])
    grid = np.empty((bins, plane), np.float32)
    scratch = np.empty(plane, np.float64)
    carry = None  # the weight that the run before passes on to bin k
    # Few fresh arrays: each large allocation costs page faults comparable to a pass over it.
    for k in range(bins - 1):
        count = timed = None
        for run in _chunks(edges[k], edges[k + 1]):
            elapsed = _elapsed(t[run], t0, time_buffer)
            if split_polarity:
                index = _index_numpy(events, run, index_buffer)
                counted = np.bincount(index, minlength=size)
            else:
                index = index_buffer[: run.stop - run.start]
                np.multiply(events.y[run], events.width, out=index, dtype=np.intp)
                index += events.x[run]
                signed = np.take(signs, events.p[run], out=sign_buffer[: index.size])
                elapsed *= signed
                counted = np.bincount(index, weights=signed, minlength=size)
            summed = np.bincount(index, weights=elapsed, minlength=size)
            if count is None:
                count, timed = counted, summed
            else:
                count += counted
                timed += summed
        if count is None:  # no event in this interval
            count, timed = np.zeros(size), np.zeros(size)
        if split_polarity:  # ON minus OFF, in place (count stays int64)
            count[plane:] -= count[:plane]
            timed[plane:] -= timed[:plane]
            count, timed = count[plane:], timed[plane:]
        timed *= (bins - 1) / span
        if k:
            timed -= np.multiply(count, k, out=scratch)  # V = sum p_i (t*_i - k)
        np.subtract(count, timed, out=scratch)  # S - V
        if carry is not None:
            scratch += carry
        grid[k] = scratch
        carry = timed
    grid[bins - 1] = carry
    return grid


def _signed_torch(p: "torch.Tensor") -> "torch.Tensor":
    """The paper's polarity, -1 (OFF) / +1 (ON), as a new float32 tensor."""
    import torch

    return _on_torch(p).to(torch.float32).mul_(2).sub_(1)


def _voxel_grid_flat_torch(
    x: "torch.Tensor", y: "torch.Tensor", t: "torch.Tensor", p: "torch.Tensor",
    width: int, height: int, bins: int,
    t0: "int | torch.Tensor", span: "int | torch.Tensor", offset: "int | torch.Tensor", size: int,
) -> "torch.Tensor":
    """Voxel grid(s) accumulated into a flat float32 tensor of ``size``.

    ``t0``, ``span`` and ``offset`` (added to each event's flat index) are
    scalars or per-event (N,) tensors. On the CPU the events go through in
    chunks: in-place steps on cache-sized temporaries, where fresh (N,)
    tensors would cost page faults comparable to the arithmetic itself.
    """
    import torch

    out = torch.zeros(size, dtype=torch.float32, device=t.device)
    n = t.shape[0]
    chunk = _common._CHUNK if t.device.type == "cpu" else max(n, 1)
    for start in range(0, n, chunk):
        run = slice(start, min(start + chunk, n))
        part = [
            v[run] if isinstance(v, torch.Tensor) and v.ndim == 1 else v for v in (t0, span, offset)
        ]
        _accumulate_voxels_torch(out, x[run], y[run], t[run], p[run], width, height, bins, *part)
    return out


def _accumulate_voxels_torch(
    out: "torch.Tensor", x: "torch.Tensor", y: "torch.Tensor", t: "torch.Tensor",
    p: "torch.Tensor", width: int, height: int, bins: int,
    t0: "int | torch.Tensor", span: "int | torch.Tensor", offset: "int | torch.Tensor",
) -> None:
    import torch

    plane = width * height
    signed = _signed_torch(p)
    index = torch.sub(t.to(torch.int64), t0)
    if bins > 1:
        # span 0 means t == t0 for every event of the window: t* = 0, all in bin 0
        span = torch.clamp(torch.as_tensor(span, device=t.device, dtype=torch.int64), min=1)
        t_star = index.mul_(bins - 1).to(torch.float64).div_(span)  # exact at t* = B-1
        index.copy_(t_star).clamp_(max=bins - 2)  # floor (t* >= 0); t* = B-1 goes right
        right = t_star.sub_(index).to(torch.float32).mul_(signed)
        del t_star
        signed.sub_(right)  # now the left weight
        index.mul_(plane)
    else:
        index.zero_()
    index.add_(y, alpha=width).add_(x)
    if not isinstance(offset, int) or offset:
        index.add_(offset)
    out.index_add_(0, index, signed)
    if bins > 1:
        out.index_add_(0, index.add_(plane), right)


def _voxel_grid_torch(events: EventTensors, bins: int, t0: int, span: int) -> "torch.Tensor":
    width, height = events.width, events.height
    flat = _voxel_grid_flat_torch(
        events.x, events.y, events.t, events.p, width, height, bins,
        t0, span, 0, bins * width * height,
    )
    return flat.view(bins, height, width)


def voxel_grid_batch(samples: Sequence[EventTensors], bins: int = 5) -> "torch.Tensor":
    """Voxel grids of K windows at once, shape (K, B, H, W), float32 (torch only).

    Equivalent to ``torch.stack([voxel_grid(s, bins) for s in samples])`` (each
    window normalised by its own first and last event time) but built with one
    ``index_add_`` pass over the concatenated events. All samples must share the
    sensor size and device; each sample's polarity is read in its own encoding
    (one bool, another float {-1, +1}); empty samples give zeros.

    Examples
    --------
    >>> a = Events([0, 1], [0, 0], [0, 10], [1, 1], width=2, height=1).to_torch()
    >>> voxel_grid_batch([a, a], bins=2).shape
    torch.Size([2, 2, 1, 2])
    """
    import torch

    bins = _check_int("bins", bins, minimum=1)
    if isinstance(samples, EventTensors) or not isinstance(samples, Sequence) or not samples:
        raise TypeError("samples must be a non-empty sequence (list) of EventTensors")
    for i, sample in enumerate(samples):
        if not isinstance(sample, EventTensors):
            raise TypeError(f"samples[{i}] must be EventTensors, got {type(sample).__name__}")
        for name in "xytp":
            column = getattr(sample, name)
            if not isinstance(column, torch.Tensor) or column.device != samples[0].t.device:
                raise TypeError(f"samples[{i}].{name} must be a tensor on {samples[0].t.device}")
        if (sample.width, sample.height) != (samples[0].width, samples[0].height):
            raise ValueError(
                f"samples[{i}] has sensor {sample.width}x{sample.height}, "
                f"samples[0] has {samples[0].width}x{samples[0].height}"
            )
    _check_output_size(
        (len(samples), bins, samples[0].height, samples[0].width),
        f"{len(samples)} samples of bins={bins} on a {samples[0].width}x{samples[0].height} sensor",
    )
    for i, sample in enumerate(samples):      # one column's dtype for all: a bool p would make -1.0 True (ON)
        if sample.p.dtype.is_complex:
            raise TypeError(f"samples[{i}].p must be integer, bool or real, got {sample.p.dtype}")
    polarity_ok = torch.stack([_polarity_ok(s.p) for s in samples]).tolist()   # one device synchronisation
    for i, ok in enumerate(polarity_ok):
        if not ok:
            _refuse_polarity(f"samples[{i}].p", samples[i].p)
    joined = EventTensors(
        *(torch.cat([getattr(s, name).to(getattr(samples[0], name).dtype) for s in samples])
          for name in "xyt"),
        torch.cat([_on_torch(s.p) for s in samples]),   # each sample's own encoding, as voxel_grid reads it
        samples[0].width, samples[0].height,
    )
    _stats_torch(joined)  # validates dtypes, devices and bounds once
    width, height, device = joined.width, joined.height, joined.t.device
    count = len(samples)
    lengths = torch.tensor([s.t.shape[0] for s in samples], device=device)
    sample = torch.repeat_interleave(torch.arange(count, device=device), lengths)
    t = joined.t.to(torch.int64)
    first = torch.zeros(count, dtype=torch.int64, device=device).scatter_reduce_(
        0, sample, t, "amin", include_self=False
    )
    last = torch.zeros(count, dtype=torch.int64, device=device).scatter_reduce_(
        0, sample, t, "amax", include_self=False
    )
    size = bins * width * height
    flat = _voxel_grid_flat_torch(
        joined.x, joined.y, t, joined.p, width, height, bins,
        first[sample], (last - first)[sample], sample * size, count * size,
    )
    return flat.view(count, bins, height, width)


@dataclass(frozen=True)
class VoxelGrid:
    """Stored settings for :func:`voxel_grid`: ``bins`` (B) and the time ``normalization`` (``"paper"`` or
    ``"tonic"``); calling it on events returns (B, H, W) float32."""

    bins: int = 5
    normalization: str = "paper"

    def __post_init__(self) -> None:
        _check_int("bins", self.bins, minimum=1)
        if self.normalization not in NORMALIZATIONS:
            raise ValueError(f"normalization must be one of {NORMALIZATIONS}, got {self.normalization!r}")

    def __call__(self, events: EventsLike) -> Array:
        return voxel_grid(events, self.bins, normalization=self.normalization)
