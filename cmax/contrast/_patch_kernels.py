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
symmetric kernel is its own adjoint, so ``dVar_p / dI_p = (2/n) G_p`` with ``G_p = g * (B_p - mean_p)``
(the mean does not drop out: with zero padding ``g * 1`` is not 1 near the frame's border). An event
at ``(x0 + fx, y0 + fy)`` puts ``(1-fx)(1-fy), fx(1-fy), (1-fx)fy, fx fy`` on pixels ``(x0, y0),
(x0+1, y0), (x0, y0+1), (x0+1, y0+1)``, so

    dVar_p/dx = (2/n) [(1-fy) (G(x0+1, y0) - G(x0, y0)) + fy (G(x0+1, y0+1) - G(x0, y0+1))]
    dVar_p/dy = (2/n) [(1-fx) (G(x0, y0+1) - G(x0, y0)) + fx (G(x0+1, y0+1) - G(x0+1, y0))]

with ``G = 0`` off the frame and both zero for a point that votes nothing (the torch path's
gradient, which treats ``floor`` and the validity test as constants).

The images and the blur run in the events' dtype (float32 or float64); the sums of the mean and of
the variance in float64. The events are grouped by patch (a counting sort) so that each patch's
images stay in small scratch buffers.

References
----------
G. Gallego, H. Rebecq, D. Scaramuzza, "A unifying contrast maximization framework for event
cameras", CVPR 2018 (the bilinear IWE, its variance and the variance's gradient).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from cmax._jit import kernel

__all__ = ["patch_variances", "gaussian_taps"]


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
def _blur_into(padded, taps, rows, out):  # pragma: no cover - compiled
    """``out`` (H, W) = the separable blur of ``padded`` (H, W + 2R) (zeros in its R side columns).

    ``rows`` (H + 2R, W) is scratch whose R top and bottom rows are zero (they stay so). The inner
    loops run along a row into a fresh buffer (no aliasing: they vectorise); each output sums its
    taps in the order ``k = 0 .. 2R`` (with fused multiply-adds).
    """
    H, W = out.shape
    R = (taps.shape[0] - 1) // 2
    line = np.empty(W, out.dtype)
    for r in range(H):
        line[:] = 0
        for k in range(2 * R + 1):
            t = taps[k]
            for c in range(W):
                line[c] += t * padded[r, c + k]
        rows[R + r, :] = line
    for r in range(H):
        line[:] = 0
        for k in range(2 * R + 1):
            t = taps[k]
            for c in range(W):
                line[c] += t * rows[r + k, c]
        out[r, :] = line


@kernel
def _forward(x, y, offset, order, starts, taps, one, blurred, stats, padded, rows, column_sums):  # pragma: no cover
    """Blurred images ``blurred`` (P, H, W) and ``stats`` (P, 2) float64 = (mean, variance) of each patch.

    ``one`` is 1 in the images' dtype (the bilinear weights are computed in it, as the torch path does);
    ``padded`` (H, W + 2R) and ``rows`` (H + 2R, W) are zeroed scratch of that dtype; ``column_sums``
    (2, W) float64 scratch.
    """
    P, H, W = blurred.shape
    R = (taps.shape[0] - 1) // 2
    n = H * W
    for p in range(P):
        padded[:, :] = 0
        ox, oy = offset[p, 0], offset[p, 1]
        for j in range(starts[p], starts[p + 1]):
            i = order[j]
            lx, ly = x[i] - ox, y[i] - oy
            x0, y0 = np.floor(lx), np.floor(ly)
            if not (x0 >= -1 and x0 <= W - 1 and y0 >= -1 and y0 <= H - 1):
                continue
            fx, fy = lx - x0, ly - y0
            gx, gy = one - fx, one - fy
            ix, iy = int(x0), int(y0)
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
        image = blurred[p]
        _blur_into(padded, taps, rows, image)
        column_sums[:, :] = 0
        for r in range(H):
            for c in range(W):
                b = np.float64(image[r, c])
                column_sums[0, c] += b
                column_sums[1, c] += b * b
        mean = column_sums[0].sum() / n
        stats[p, 0] = mean
        stats[p, 1] = column_sums[1].sum() / n - mean * mean


@kernel
def _backward(x, y, offset, order, starts, taps, one, blurred, stats, scale, grad_x, grad_y, padded, rows,
              field):  # pragma: no cover - compiled
    """``grad_x, grad_y`` (M,) = ``sum_p scale[p] dVar_p / d(x, y)`` (see the module docstring).

    ``scale`` (P,) float64 is the upstream gradient; ``padded``, ``rows`` as :func:`_forward`, the
    right side columns of ``padded`` zero; ``field`` (H, W) scratch.
    """
    P, H, W = blurred.shape
    R = (taps.shape[0] - 1) // 2
    n = H * W
    for p in range(P):
        if starts[p] == starts[p + 1]:
            continue
        mean = stats[p, 0]
        for r in range(H):
            for c in range(W):
                padded[r, R + c] = blurred[p, r, c] - mean
        _blur_into(padded, taps, rows, field)
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
                 size: tuple[int, int], sigma: float) -> None:
        H, W = size
        P = offset.shape[0]
        self.x, self.y, self.offset = x, y, offset
        self.taps = gaussian_taps(sigma, x.dtype)
        self.one = x.dtype.type(1)
        R = (self.taps.shape[0] - 1) // 2
        self.order = np.empty(patch.shape[0], np.int64)
        self.starts = np.empty(P + 1, np.int64)
        _group(patch, P, self.order, self.starts)
        self.blurred = np.empty((P, H, W), x.dtype)
        self.stats = np.empty((P, 2))
        self.padded = np.zeros((H, W + 2 * R), x.dtype)
        self.rows = np.zeros((H + 2 * R, W), x.dtype)

    def forward(self) -> np.ndarray:
        """Fill the images and statistics; the variances (P,) float64."""
        _forward(self.x, self.y, self.offset, self.order, self.starts, self.taps, self.one, self.blurred, self.stats,
                 self.padded, self.rows, np.empty((2, self.blurred.shape[2])))
        return self.stats[:, 1]

    def backward(self, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gradients (M,), (M,) of ``sum_p scale[p] Var_p`` with respect to ``x`` and ``y``."""
        grad_x, grad_y = np.empty_like(self.x), np.empty_like(self.y)
        self.padded[:] = 0
        _backward(self.x, self.y, self.offset, self.order, self.starts, self.taps, self.one, self.blurred, self.stats,
                  np.ascontiguousarray(scale, dtype=np.float64), grad_x, grad_y, self.padded, self.rows,
                  np.empty(self.blurred.shape[1:], self.x.dtype))
        return grad_x, grad_y


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
        Event pixels in the full image [px].
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
