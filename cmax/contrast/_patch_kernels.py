"""Compiled value and gradient of the per-patch variance of blurred bilinear IWEs.

For events at full-image pixels ``x, y`` (M,), each in patch ``patch`` (M,) whose frame of ``H x W``
pixels has its top-left pixel at ``offset[patch]``, :func:`patch_variances` returns

    Var_p = mean_u(B_p(u)^2) - mean_u(B_p(u))^2,   B_p = g * I_p,   p = 0 .. P-1

with ``I_p`` the bilinear image of patch ``p``'s events in its own frame (the votes and the rule for
points off the frame of :func:`cmax.iwe.accumulate_bilinear_indexed`: a corner off the frame is
dropped, a point whose corners all leave the one-pixel border votes nothing), ``g`` the Gaussian of
:func:`cmax.iwe.blur` (separable, zero padding, radius ``ceil(3 sigma)``) and the mean over the
``n = H W`` pixels (the population variance of :func:`cmax.objectives.variance`). It equals
``variance(blur(accumulate_bilinear_indexed(x - ox, y - oy, None, patch, P, H, W), sigma))`` to
float rounding, in one compiled pass per patch instead of a dozen torch operations and their autograd.

The gradient. ``dVar_p / dB_p(u) = (2/n) (B_p(u) - mean_p)``; the blur with zero padding and a
symmetric kernel is its own adjoint, so ``dVar_p / dI_p = (2/n) G_p`` with ``G_p = g * (B_p - mean_p)
= g * B_p - mean_p (g * 1)`` (the mean does not drop out: with zero padding ``g * 1``, the blur of
the frame's ones, is not 1 near the frame's border; it is separable, ``h_y(r) h_x(c)``). An event
at ``(x0 + fx, y0 + fy)`` puts ``(1-fx)(1-fy), fx(1-fy), (1-fx)fy, fx fy`` on pixels ``(x0, y0),
(x0+1, y0), (x0, y0+1), (x0+1, y0+1)``, so

    dVar_p/dx = (2/n) [(1-fy) (G(x0+1, y0) - G(x0, y0)) + fy (G(x0+1, y0+1) - G(x0, y0+1))]
    dVar_p/dy = (2/n) [(1-fx) (G(x0, y0+1) - G(x0, y0)) + fx (G(x0+1, y0+1) - G(x0+1, y0))]

with ``G = 0`` off the frame and both zero for a point that votes nothing (the torch path's
gradient, which treats ``floor`` and the validity test as constants).

The images and the blur run in the events' dtype (float32 or float64); the sums of the mean and of
the variance in float64. The events are grouped by patch (a counting sort) so that each patch's
images stay in small scratch buffers, and each blur runs only on the box that the patch's votes
touch, grown by the kernel's radius (a patch's events fill its core, not the margin of its frame); the
gradient's ``G`` is computed only on the pixels the votes touch, the only ones the events read.

References
----------
G. Gallego, H. Rebecq, D. Scaramuzza, "A unifying contrast maximization framework for event
cameras", CVPR 2018 (the bilinear IWE, its variance and the variance's gradient).
"""
from __future__ import annotations

import functools
import math

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from cmax._jit import kernel

__all__ = ["patch_variances", "gaussian_taps", "group_by_patch", "shift_by_patch", "flow_gradient_by_patch"]


@kernel
def _group(patch, count, order, starts):  # pragma: no cover - compiled
    """Counting sort: the events of patch ``p`` are ``order[starts[p]:starts[p + 1]]`` (in event order)."""
    starts[:] = 0
    for i in range(patch.shape[0]):
        starts[patch[i] + 1] += 1
    for p in range(count):
        starts[p + 1] += starts[p]
    fill = starts[:count].copy()
    for i in range(patch.shape[0]):
        p = patch[i]
        order[fill[p]] = i
        fill[p] += 1


@kernel(fastmath={"contract"})
def _blur_box(padded, taps, rows, out, r_lo, r_hi, c_lo, c_hi):  # pragma: no cover - compiled
    """Separable blur (zero padding) of an image that is zero outside rows ``r_lo..r_hi`` and columns
    ``c_lo..c_hi`` (inclusive), written to ``out`` (H, W) on that box grown by R and cut to the frame.

    The image is ``padded`` (H, W + 2R): pixel ``(r, c)`` at ``[r, R + c]``, zero elsewhere. ``rows``
    (H + 2R, W) is zero scratch (it is left zero). Outside the grown box ``out`` is not written (the
    blur is zero there). The inner loops run along a row into a fresh buffer (no aliasing: they
    vectorise); each output sums its taps in the order ``k = 0 .. 2R`` (with fused multiply-adds).
    """
    H, W = out.shape
    R = (taps.shape[0] - 1) // 2
    c0, c1 = max(c_lo - R, 0), min(c_hi + R, W - 1) + 1
    m = c1 - c0
    line = np.empty(m, out.dtype)
    for r in range(r_lo, r_hi + 1):   # loops over views from index 0: no negative-index checks, they vectorise
        line[:] = 0
        for k in range(2 * R + 1):
            t = taps[k]
            source = padded[r, c0 + k:c1 + k]
            for c in range(m):
                line[c] += t * source[c]
        target = rows[R + r, c0:c1]
        for c in range(m):
            target[c] = line[c]
    for r in range(max(r_lo - R, 0), min(r_hi + R, H - 1) + 1):
        line[:] = 0
        for k in range(2 * R + 1):
            t = taps[k]
            source = rows[r + k, c0:c1]
            for c in range(m):
                line[c] += t * source[c]
        target = out[r, c0:c1]
        for c in range(m):
            target[c] = line[c]
    for r in range(r_lo, r_hi + 1):
        target = rows[R + r, c0:c1]
        for c in range(m):
            target[c] = 0


@kernel(fastmath={"contract"})
def _blur_within(padded, taps, rows, out, r_lo, r_hi, o_r0, o_r1, o_c0, o_c1):  # pragma: no cover - compiled
    """:func:`_blur_box` of an image that is zero outside rows ``r_lo..r_hi``, written to ``out`` (H, W) only on
    rows ``o_r0..o_r1`` and columns ``o_c0..o_c1`` (inclusive, inside the frame): each of those pixels is the value
    :func:`_blur_box` gives it, bit for bit (the same taps summed in the same order ``k = 0 .. 2R``), the passes
    running only over the rows and columns it reads. ``padded``, ``rows``: as :func:`_blur_box` (left zero).
    """
    H, W = out.shape
    R = (taps.shape[0] - 1) // 2
    m = o_c1 + 1 - o_c0
    line = np.empty(m, out.dtype)
    first, last = max(o_r0 - R, r_lo), min(o_r1 + R, r_hi)
    for r in range(first, last + 1):
        line[:] = 0
        for k in range(2 * R + 1):
            t = taps[k]
            source = padded[r, o_c0 + k:o_c1 + 1 + k]
            for c in range(m):
                line[c] += t * source[c]
        target = rows[R + r, o_c0:o_c1 + 1]
        for c in range(m):
            target[c] = line[c]
    for r in range(o_r0, o_r1 + 1):
        line[:] = 0
        for k in range(2 * R + 1):
            t = taps[k]
            source = rows[r + k, o_c0:o_c1 + 1]
            for c in range(m):
                line[c] += t * source[c]
        target = out[r, o_c0:o_c1 + 1]
        for c in range(m):
            target[c] = line[c]
    for r in range(first, last + 1):
        target = rows[R + r, o_c0:o_c1 + 1]
        for c in range(m):
            target[c] = 0


@kernel
def _forward(x, y, offset, order, starts, taps, one, blurred, stats, boxes, padded, rows,
             column_sums, votes):  # pragma: no cover - compiled
    """Blurred images ``blurred`` (P, H, W), ``stats`` (P, 2) float64 = (mean, variance) of each patch.

    ``boxes`` (P, 4) int64 receives ``(r0, r1, c0, c1)``: rows ``r0..r1`` and columns ``c0..c1``
    (inclusive) of ``blurred[p]`` hold the blurred image, zero outside (not written; ``r1 < r0`` when
    the patch has no votes); ``votes`` (P, 4) int64 the same of the pixels the votes fell on (the box before
    the blur grew it). ``one`` is 1 in the images' dtype (the bilinear weights are computed in
    it, as the torch path does); ``padded`` (H, W + 2R) and ``rows`` (H + 2R, W) are zero scratch of
    that dtype (left zero); ``column_sums`` (2, W) float64 scratch.
    """
    P, H, W = blurred.shape
    R = (taps.shape[0] - 1) // 2
    n = H * W
    for p in range(P):
        ox, oy = offset[p, 0], offset[p, 1]
        r_lo, r_hi, c_lo, c_hi = H, -1, W, -1
        for j in range(starts[p], starts[p + 1]):
            i = order[j]
            lx, ly = x[i] - ox, y[i] - oy
            x0, y0 = np.floor(lx), np.floor(ly)
            if not (x0 >= -1 and x0 <= W - 1 and y0 >= -1 and y0 <= H - 1):
                continue
            fx, fy = lx - x0, ly - y0
            gx, gy = one - fx, one - fy
            ix, iy = int(x0), int(y0)
            if ix >= 0 and iy >= 0 and ix + 1 < W and iy + 1 < H:   # all four corners inside: no tests
                top, bottom = padded[iy], padded[iy + 1]
                top[R + ix] += gx * gy
                top[R + ix + 1] += fx * gy
                bottom[R + ix] += gx * fy
                bottom[R + ix + 1] += fx * fy
                r_lo, r_hi, c_lo, c_hi = min(r_lo, iy), max(r_hi, iy + 1), min(c_lo, ix), max(c_hi, ix + 1)
                continue
            if iy >= 0:
                if ix >= 0:
                    padded[iy, R + ix] += gx * gy
                if ix + 1 < W:
                    padded[iy, R + ix + 1] += fx * gy
            if iy + 1 < H:
                if ix >= 0:
                    padded[iy + 1, R + ix] += gx * fy
                if ix + 1 < W:
                    padded[iy + 1, R + ix + 1] += fx * fy
            r_lo, r_hi = min(r_lo, max(iy, 0)), max(r_hi, min(iy + 1, H - 1))
            c_lo, c_hi = min(c_lo, max(ix, 0)), max(c_hi, min(ix + 1, W - 1))
        if r_hi < r_lo:
            boxes[p, 0], boxes[p, 1], boxes[p, 2], boxes[p, 3] = 0, -1, 0, -1
            votes[p, 0], votes[p, 1], votes[p, 2], votes[p, 3] = 0, -1, 0, -1
            stats[p, 0] = stats[p, 1] = 0.0
            continue
        votes[p, 0], votes[p, 1], votes[p, 2], votes[p, 3] = r_lo, r_hi, c_lo, c_hi
        image = blurred[p]
        _blur_box(padded, taps, rows, image, r_lo, r_hi, c_lo, c_hi)
        for r in range(r_lo, r_hi + 1):
            padded[r, R + c_lo:R + c_hi + 1] = 0
        r0, r1, c0, c1 = max(r_lo - R, 0), min(r_hi + R, H - 1), max(c_lo - R, 0), min(c_hi + R, W - 1)
        boxes[p, 0], boxes[p, 1], boxes[p, 2], boxes[p, 3] = r0, r1, c0, c1
        column_sums[:, :] = 0
        sums, squares = column_sums[0, :c1 + 1 - c0], column_sums[1, :c1 + 1 - c0]
        for r in range(r0, r1 + 1):
            row = image[r, c0:c1 + 1]
            for c in range(c1 + 1 - c0):
                b = np.float64(row[c])
                sums[c] += b
                squares[c] += b * b
        mean = column_sums[0].sum() / n
        stats[p, 0] = mean
        stats[p, 1] = column_sums[1].sum() / n - mean * mean


@kernel
def _backward(x, y, offset, order, starts, taps, one, blurred, stats, boxes, scale, grad_x, grad_y, padded, rows,
              field, ones_y, ones_x, votes):  # pragma: no cover - compiled
    """``grad_x, grad_y`` (M,) = ``sum_p scale[p] dVar_p / d(x, y)`` (see the module docstring).

    ``G = g * (B - mean)`` is ``g * B`` (non-zero on the box of :func:`_forward` grown by R) minus
    ``mean ones_y[r] ones_x[c]``, the blur of the frame's ones (separable), computed into ``field``
    (H, W) scratch only on the pixels the events read: the box of their votes (``votes`` (P, 4) of
    :func:`_forward`; the rest of ``field`` is left as it was, unread). ``scale`` (P,) float64 is the upstream
    gradient; ``padded``, ``rows`` as :func:`_forward`; ``ones_y`` (H,), ``ones_x`` (W,) of the images' dtype.
    """
    P, H, W = blurred.shape
    R = (taps.shape[0] - 1) // 2
    n = H * W
    for p in range(P):
        if starts[p] == starts[p + 1]:
            continue
        r0, r1, c0, c1 = boxes[p, 0], boxes[p, 1], boxes[p, 2], boxes[p, 3]
        if r1 >= r0:    # else no event votes: each one's gradient is 0 below, and G is not read
            for r in range(r0, r1 + 1):
                target, source = padded[r, R + c0:R + c1 + 1], blurred[p, r, c0:c1 + 1]
                for c in range(c1 + 1 - c0):
                    target[c] = source[c]
            v0, v1, u0, u1 = votes[p, 0], votes[p, 1], votes[p, 2], votes[p, 3]
            _blur_within(padded, taps, rows, field, r0, r1, v0, v1, u0, u1)
            for r in range(r0, r1 + 1):
                padded[r, R + c0:R + c1 + 1] = 0
            mean = stats[p, 0]
            for r in range(v0, v1 + 1):
                row, level = field[r], mean * ones_y[r]
                for c in range(u0, u1 + 1):
                    row[c] -= level * ones_x[c]
        s = 2.0 * scale[p] / n
        ox, oy = offset[p, 0], offset[p, 1]
        for j in range(starts[p], starts[p + 1]):
            i = order[j]
            lx, ly = x[i] - ox, y[i] - oy
            x0, y0 = np.floor(lx), np.floor(ly)
            if not (x0 >= -1 and x0 <= W - 1 and y0 >= -1 and y0 <= H - 1):
                grad_x[i] = 0
                grad_y[i] = 0
                continue
            fx, fy = lx - x0, ly - y0
            ix, iy = int(x0), int(y0)
            if ix >= 0 and iy >= 0 and ix + 1 < W and iy + 1 < H:   # all four corners inside: no tests
                top, bottom = field[iy], field[iy + 1]
                g00, g10, g01, g11 = top[ix], top[ix + 1], bottom[ix], bottom[ix + 1]
                grad_x[i] = s * ((one - fy) * (g10 - g00) + fy * (g11 - g01))
                grad_y[i] = s * ((one - fx) * (g01 - g00) + fx * (g11 - g10))
                continue
            g00 = g10 = g01 = g11 = one - one
            if iy >= 0:
                if ix >= 0:
                    g00 = field[iy, ix]
                if ix + 1 < W:
                    g10 = field[iy, ix + 1]
            if iy + 1 < H:
                if ix >= 0:
                    g01 = field[iy + 1, ix]
                if ix + 1 < W:
                    g11 = field[iy + 1, ix + 1]
            grad_x[i] = s * ((one - fy) * (g10 - g00) + fy * (g11 - g01))
            grad_y[i] = s * ((one - fx) * (g01 - g00) + fx * (g11 - g10))


@kernel
def shift_by_patch(x, y, dt, patch, flow, out_x, out_y):  # pragma: no cover - compiled
    """``out = (x - flow[patch, 0] dt, y - flow[patch, 1] dt)`` (M,) in the events' dtype: each patch's events
    moved by its own constant flow ``flow`` (P, 2) (the patch flows' warp, one pass instead of numpy's six)."""
    for i in range(x.shape[0]):
        p = patch[i]
        out_x[i] = x[i] - flow[p, 0] * dt[i]
        out_y[i] = y[i] - flow[p, 1] * dt[i]


@kernel
def flow_gradient_by_patch(gx, gy, dt, patch, grad):  # pragma: no cover - compiled
    """``grad`` (P, 2) float64 (zeroed here) ``+= -(g dt)`` of each event, summed per patch in event order:
    the gradient of :func:`shift_by_patch`'s flows for ``dL/d out = (gx, gy)``."""
    grad[:, :] = 0.0
    for i in range(gx.shape[0]):
        p = patch[i]
        grad[p, 0] += -(gx[i] * dt[i])
        grad[p, 1] += -(gy[i] * dt[i])


@functools.lru_cache(maxsize=32)
def _taps(sigma: float, dtype: str) -> np.ndarray:
    """:func:`gaussian_taps`, kept (read-only) for the next evaluation with the same blur."""
    taps = gaussian_taps(sigma, np.dtype(dtype))
    taps.setflags(write=False)
    return taps


def _blurred_ones(taps: np.ndarray, length: int) -> np.ndarray:
    """The 1-D blur (zero padding) of ``length`` ones: ``(g * 1)[c] = sum_k g[k] [0 <= c + k - R < length]``."""
    R = (taps.shape[0] - 1) // 2
    ones = np.zeros(length + 2 * R)
    ones[R:R + length] = 1
    return np.convolve(ones, taps.astype(np.float64), mode="valid")


def gaussian_taps(sigma: float, dtype: np.dtype) -> np.ndarray:
    """The 1-D kernel (2R + 1,) of :func:`cmax.iwe.blur` for ``sigma`` [px] in ``dtype``; ``[1]`` when ``sigma <= 0``.

    Computed as ``cmax.iwe._gaussian_kernel`` does (in ``dtype``, normalised to sum 1), so that both
    paths blur with the same taps.

    Examples
    --------
    >>> gaussian_taps(1.0, np.float64).shape
    (7,)
    """
    if sigma <= 0:
        return np.ones(1, dtype=dtype)
    torch_dtype = torch.from_numpy(np.zeros(0, dtype=dtype)).dtype
    radius = max(1, math.ceil(3 * sigma))
    offsets = torch.arange(-radius, radius + 1, dtype=torch_dtype)
    taps = torch.exp(-offsets * offsets / (2.0 * sigma * sigma))
    return (taps / taps.sum()).numpy()


class _Workspace:
    """Arrays of one evaluation: the events grouped by patch, the blurred images and their statistics."""

    def __init__(self, x: np.ndarray, y: np.ndarray, patch: np.ndarray, offset: np.ndarray,
                 size: tuple[int, int], sigma: float,
                 grouping: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        H, W = size
        P = offset.shape[0]
        self.x, self.y, self.offset = x, y, offset
        self.taps = _taps(float(sigma), x.dtype.str)
        self.one = x.dtype.type(1)
        R = (self.taps.shape[0] - 1) // 2
        self.order, self.starts = group_by_patch(patch, P) if grouping is None else grouping
        self.blurred = np.empty((P, H, W), x.dtype)
        self.stats = np.empty((P, 2))
        self.boxes = np.empty((P, 4), np.int64)
        self.votes = np.empty((P, 4), np.int64)
        self.padded = np.zeros((H, W + 2 * R), x.dtype)
        self.rows = np.zeros((H + 2 * R, W), x.dtype)

    def forward(self) -> np.ndarray:
        """Fill the images and statistics; the variances (P,) float64."""
        _forward(self.x, self.y, self.offset, self.order, self.starts, self.taps, self.one, self.blurred, self.stats,
                 self.boxes, self.padded, self.rows, np.empty((2, self.blurred.shape[2])), self.votes)
        return self.stats[:, 1]

    def backward(self, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gradients (M,), (M,) of ``sum_p scale[p] Var_p`` with respect to ``x`` and ``y``."""
        grad_x, grad_y = np.empty_like(self.x), np.empty_like(self.y)
        P, H, W = self.blurred.shape
        _backward(self.x, self.y, self.offset, self.order, self.starts, self.taps, self.one, self.blurred, self.stats,
                  self.boxes, np.ascontiguousarray(scale, dtype=np.float64), grad_x, grad_y, self.padded, self.rows,
                  np.empty((H, W), self.x.dtype), _blurred_ones(self.taps, H).astype(self.x.dtype),
                  _blurred_ones(self.taps, W).astype(self.x.dtype), self.votes)
        return grad_x, grad_y


def group_by_patch(patch: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """``(order (M,), starts (count + 1,))`` int64: the events of patch ``p`` are ``order[starts[p]:starts[p + 1]]``
    (a counting sort of ``patch`` (M,) int64; the same for every evaluation of one event set)."""
    order, starts = np.empty(patch.shape[0], np.int64), np.empty(count + 1, np.int64)
    _group(patch, count, order, starts)
    return order, starts


def _numpy(tensor: torch.Tensor, dtype: np.dtype | None = None) -> np.ndarray:
    return np.ascontiguousarray(tensor.detach().numpy(), dtype=dtype)


class _PatchVariances(torch.autograd.Function):
    """:func:`patch_variances` with its compiled backward."""

    @staticmethod
    def forward(ctx, x, y, patch, offset, size, sigma):  # type: ignore[override]
        dtype = x.detach().numpy().dtype
        work = _Workspace(_numpy(x), _numpy(y, dtype), _numpy(patch, np.int64), _numpy(offset, dtype), size, sigma)
        ctx.work = work
        return torch.from_numpy(work.forward().astype(dtype))

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        grad_x, grad_y = ctx.work.backward(grad.detach().numpy())
        return (torch.from_numpy(grad_x) if ctx.needs_input_grad[0] else None,
                torch.from_numpy(grad_y) if ctx.needs_input_grad[1] else None, None, None, None, None)


def patch_variances(x: torch.Tensor, y: torch.Tensor, patch: torch.Tensor, offset: torch.Tensor,
                    size: tuple[int, int], sigma: float) -> torch.Tensor:
    """Variance (P,) of each patch's blurred bilinear IWE (see the module docstring); differentiable in ``x, y``.

    Parameters
    ----------
    x, y : Tensor (M,), float32 or float64, CPU
        Event pixels in the full image [px]; an event with a non-finite coordinate votes nothing.
    patch : Tensor (M,), integer
        The patch of each event, ``0 <= patch < P``.
    offset : Tensor (P, 2)
        Top-left pixel ``(x, y)`` of each patch's frame [px].
    size : (int, int)
        ``(H, W)`` of every patch frame [px].
    sigma : float
        Blur [px]; ``<= 0``: none.

    Returns
    -------
    Tensor (P,), the dtype of ``x``

    Examples
    --------
    >>> x, y = torch.tensor([1.5, 2.0]), torch.tensor([1.0, 1.0])
    >>> patch_variances(x, y, torch.tensor([0, 0]), torch.zeros(1, 2), (2, 4), 0.0).tolist()
    [0.25]
    """
    if x.dtype not in (torch.float32, torch.float64) or x.device.type != "cpu":
        raise TypeError(f"x must be a CPU float32 or float64 tensor, got {x.dtype} on {x.device}")
    if x.dim() != 1 or y.shape != x.shape or patch.shape != x.shape:
        raise ValueError(f"x, y and patch must have one shape (M,), got {tuple(x.shape)}, {tuple(y.shape)}, "
                         f"{tuple(patch.shape)}")
    if offset.dim() != 2 or offset.shape[1] != 2:
        raise ValueError(f"offset must have shape (P, 2), got {tuple(offset.shape)}")
    H, W = int(size[0]), int(size[1])
    if H <= 0 or W <= 0:
        raise ValueError(f"size must be positive (H, W), got {size}")
    if patch.numel() and (int(patch.min()) < 0 or int(patch.max()) >= offset.shape[0]):
        raise ValueError(f"patch must lie in [0, {offset.shape[0]}), got [{int(patch.min())}, {int(patch.max())}]")
    return _PatchVariances.apply(x, y, patch, offset.to(x.dtype), (H, W), float(sigma))
