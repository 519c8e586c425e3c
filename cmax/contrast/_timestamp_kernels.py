"""Compiled value and gradient of the average-timestamp images of :class:`cmax.contrast.AverageTimestamp`.

For events warped to two reference times (``r = 0``: the window's end, each event weighted by its
normalised time ``tau_i``; ``r = 1``: its start, weighted by ``1 - tau_i``), at pixels ``x[r, i], y[r, i]``,
each voting into the image of its window ``b`` and polarity, :func:`average_timestamp_images` returns
per window

    L_b = sum_r  sum_{p, u} A_{r,p,b}(u)^2 / n_{r,b},     A = S / (C + eps)

with ``C`` the bilinear image of the votes (``keep_i``) and ``S`` that of the weighted votes
(``keep_i w_{r,i}``), both by the rule of :func:`cmax.iwe.accumulate_bilinear_indexed` (a corner off the
frame is dropped, a point whose corners all leave the one-pixel border votes nothing), and ``n_{r,b}``
the number of pixels where either polarity has a vote (a constant for the gradient, as in the torch
path). With ``purge`` an event whose warp to either reference leaves the image (``0 <= x <= W - 1``,
``0 <= y <= H - 1``, NaN outside) has ``keep_i = 0``, otherwise 1; ``keep`` is a constant too.

The gradient. With upstream ``g_b`` and ``c = C(u) + eps``,

    dL/dC(u) = -2 g_b A^2 / (c n),   dL/dS(u) = 2 g_b A / (c n),
    dL/d(vote of event i at u) = keep_i (dL/dC(u) + w_{r,i} dL/dS(u)) = keep_i 2 g_b A (w_{r,i} - A) / (c n)
                               =: G_{r,i}(u)

and an event at ``(x0 + fx, y0 + fy)`` that puts ``(1-fx)(1-fy), fx(1-fy), (1-fx)fy, fx fy`` on pixels
``(x0, y0), (x0+1, y0), (x0, y0+1), (x0+1, y0+1)`` has

    dL/dx = (1-fy) (G(x0+1, y0) - G(x0, y0)) + fy (G(x0+1, y0+1) - G(x0, y0+1))
    dL/dy = (1-fx) (G(x0, y0+1) - G(x0, y0)) + fx (G(x0+1, y0+1) - G(x0+1, y0))

with ``G = 0`` off the frame (``floor`` and the validity test are constants, as in torch's autograd).

It equals the torch operations of :meth:`cmax.contrast.AverageTimestamp.__call__` to float rounding
(``tests/test_timestamp_kernels.py``): the images are accumulated in float64 in one pass over the events
and one over the pixels, instead of a dozen torch operations on ``4 B H W`` pixels and their autograd.

References
----------
A. Z. Zhu, L. Yuan, K. Chaney, K. Daniilidis, "Unsupervised event-based learning of optical flow, depth,
and egomotion", CVPR 2019; J. Hagenaars, F. Paredes-Valles, G. de Croon, "Self-supervised learning of
event-based optical flow with spiking neural networks", NeurIPS 2021 (the loss and the purge).
"""
from __future__ import annotations

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from cmax._jit import kernel

#: How far [px] past the outermost pixel centres a warped event still counts as inside the image: the float32
#: round trip ``K (K^-1 p)`` moves an event on the last column by ~2e-6 px, which must not purge it.
EDGE_TOLERANCE_PX = 1e-3

__all__ = ["average_timestamp_images", "compiled_images_apply"]


@kernel
def _keep(x, y, width, height, tol, purge, keep):  # pragma: no cover - compiled
    """``keep`` (N,) float64: 1, or with ``purge`` 0 for an event that either reference warps out of the image
    (by more than ``tol`` px past its outermost pixel centres)."""
    for i in range(keep.shape[0]):
        inside = True
        if purge:
            for r in range(x.shape[0]):
                if not (x[r, i] >= -tol and x[r, i] <= width - 1 + tol and y[r, i] >= -tol
                        and y[r, i] <= height - 1 + tol):
                    inside = False
        keep[i] = 1.0 if inside else 0.0


@kernel
def _corner(lx, ly, W, H):  # pragma: no cover - compiled
    """``(votes, ix, iy, fx, fy)`` of a point at ``(lx, ly)``: its top-left pixel and the fractions; ``votes``
    False when its corners all leave the one-pixel border of the ``W`` x ``H`` frame (or it is not finite)."""
    x0, y0 = np.floor(lx), np.floor(ly)
    if not (x0 >= -1 and x0 <= W - 1 and y0 >= -1 and y0 <= H - 1):
        return False, 0, 0, 0.0, 0.0
    return True, int(x0), int(y0), lx - x0, ly - y0


@kernel
def _vote(images, m, u, v, count, stamp):  # pragma: no cover - compiled
    images[m, u, v, 0] += count
    images[m, u, v, 1] += stamp


@kernel
def _average(image, u, v, eps):  # pragma: no cover - compiled
    """``A^2`` of pixel ``(u, v)`` of ``image`` (H, W, 2) holding ``C, S``, which it replaces by ``2 A / (C + eps), A``."""
    c = image[u, v, 0] + eps
    a = image[u, v, 1] / c
    image[u, v, 0] = 2.0 * a / c
    image[u, v, 1] = a
    return a * a


@kernel
def _forward(x, y, tau, base, windows, keep, eps, images, squares, active):  # pragma: no cover - compiled
    """Accumulate the images and reduce them: ``squares`` (2, B) float64, ``active`` (2, B) int64.

    ``images`` (2 * 2B, H, W, 2) float64, zero on entry, receives ``C`` and ``S`` in its last axis (both in
    one cache line); event ``i`` votes, for reference ``r``, into image ``r * 2B + base[i]`` (``base =
    polarity_on * B + window``) with weight ``tau`` (r = 0) or ``1 - tau`` (r = 1). On return the last axis
    holds what the gradient needs instead: ``2 A / (C + eps)`` and ``A``.
    """
    _, H, W, _ = images.shape
    B = windows
    for r in range(x.shape[0]):
        for i in range(x.shape[1]):
            k = keep[i]
            if k == 0.0:
                continue
            votes, ix, iy, fx, fy = _corner(x[r, i], y[r, i], W, H)
            if not votes:
                continue
            gx, gy = 1.0 - fx, 1.0 - fy
            m = r * 2 * B + base[i]
            w = tau[i] if r == 0 else 1.0 - tau[i]
            if iy >= 0:
                if ix >= 0:
                    _vote(images, m, iy, ix, k * gx * gy, k * w * gx * gy)
                if ix + 1 < W:
                    _vote(images, m, iy, ix + 1, k * fx * gy, k * w * fx * gy)
            if iy + 1 < H:
                if ix >= 0:
                    _vote(images, m, iy + 1, ix, k * gx * fy, k * w * gx * fy)
                if ix + 1 < W:
                    _vote(images, m, iy + 1, ix + 1, k * fx * fy, k * w * fx * fy)
    for r in range(x.shape[0]):
        for b in range(B):
            total, n = 0.0, 0
            off, on = images[r * 2 * B + b], images[r * 2 * B + B + b]   # the two polarities
            for u in range(H):
                for v in range(W):
                    c0, c1 = off[u, v, 0], on[u, v, 0]
                    if c0 + c1 > 0:
                        n += 1
                        total += _average(off, u, v, eps) + _average(on, u, v, eps)
            squares[r, b], active[r, b] = total, n


@kernel
def _vote_gradient(images, m, u, v, scale, w):  # pragma: no cover - compiled
    """``dL/dC + w dL/dS = scale (2 A / (C + eps)) (w - A)`` at pixel ``(u, v)`` of image ``m`` (upstream
    ``scale = g_b / n_{r,b}``; ``images`` as :func:`_forward` leaves it)."""
    return scale * images[m, u, v, 0] * (w - images[m, u, v, 1])


@kernel
def _backward(x, y, tau, base, windows, keep, images, scale, grad_x, grad_y):  # pragma: no cover
    """``grad_x, grad_y`` (2, N) float64 for upstream ``scale`` (2, B) = ``g_b / n_{r,b}`` (see the module
    docstring)."""
    _, H, W, _ = images.shape
    B = windows
    for r in range(x.shape[0]):
        for i in range(x.shape[1]):
            grad_x[r, i] = 0.0
            grad_y[r, i] = 0.0
            k = keep[i]
            if k == 0.0:
                continue
            votes, ix, iy, fx, fy = _corner(x[r, i], y[r, i], W, H)
            if not votes:
                continue
            m = r * 2 * B + base[i]
            s = scale[r, base[i] - B if base[i] >= B else base[i]]
            w = tau[i] if r == 0 else 1.0 - tau[i]
            g00 = g10 = g01 = g11 = 0.0
            if iy >= 0:
                if ix >= 0:
                    g00 = _vote_gradient(images, m, iy, ix, s, w)
                if ix + 1 < W:
                    g10 = _vote_gradient(images, m, iy, ix + 1, s, w)
            if iy + 1 < H:
                if ix >= 0:
                    g01 = _vote_gradient(images, m, iy + 1, ix, s, w)
                if ix + 1 < W:
                    g11 = _vote_gradient(images, m, iy + 1, ix + 1, s, w)
            grad_x[r, i] = k * ((1.0 - fy) * (g10 - g00) + fy * (g11 - g01))
            grad_y[r, i] = k * ((1.0 - fx) * (g01 - g00) + fx * (g11 - g10))


def _numpy(tensor: torch.Tensor, dtype: type = np.float64) -> np.ndarray:
    return np.ascontiguousarray(tensor.detach().numpy(), dtype=dtype)


class _AverageTimestampImages(torch.autograd.Function):
    """:func:`average_timestamp_images` with its compiled backward."""

    @staticmethod
    def forward(ctx, x, y, tau, base, windows, size, eps, purge):  # type: ignore[override]
        H, W = size
        xs, ys, taus, bases = _numpy(x), _numpy(y), _numpy(tau), _numpy(base, np.int64)
        keep = np.empty(xs.shape[1])
        _keep(xs, ys, W, H, EDGE_TOLERANCE_PX, bool(purge), keep)
        images = np.zeros((4 * windows, H, W, 2))
        squares, active = np.empty((2, windows)), np.empty((2, windows), np.int64)
        _forward(xs, ys, taus, bases, windows, keep, float(eps), images, squares, active)
        n = np.maximum(active, 1)
        ctx.saved = (xs, ys, taus, bases, windows, keep, images, n)
        return torch.from_numpy((squares / n).sum(0)).to(x.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        xs, ys, taus, bases, windows, keep, images, n = ctx.saved
        scale = np.ascontiguousarray(grad.numpy(), dtype=np.float64)[None, :] / n
        grad_x, grad_y = np.empty_like(xs), np.empty_like(ys)
        _backward(xs, ys, taus, bases, windows, keep, images, scale, grad_x, grad_y)
        dtype = grad.dtype
        return (torch.from_numpy(grad_x).to(dtype) if ctx.needs_input_grad[0] else None,
                torch.from_numpy(grad_y).to(dtype) if ctx.needs_input_grad[1] else None,
                None, None, None, None, None, None)


def compiled_images_apply(x: torch.Tensor, y: torch.Tensor) -> bool:
    """Whether :func:`average_timestamp_images` takes warped pixels ``x, y``: CPU float32/float64 (2, N)."""
    return (x.device.type == "cpu" and y.device.type == "cpu" and x.dtype in (torch.float32, torch.float64)
            and y.dtype == x.dtype and x.dim() == 2 and x.shape[0] == 2 and y.shape == x.shape)


def average_timestamp_images(x: torch.Tensor, y: torch.Tensor, tau: torch.Tensor, base: torch.Tensor,
                             windows: int, size: tuple[int, int], eps: float, purge: bool) -> torch.Tensor:
    """The average-timestamp loss (B,) of warped events (see the module docstring); differentiable in ``x, y``.

    Parameters
    ----------
    x, y : Tensor (2, N), float32 or float64, CPU
        Pixels [px] of every event warped to the window's end (row 0) and start (row 1).
    tau : Tensor (N,)
        Normalised time ``t / duration`` in [0, 1] of each event (a constant).
    base : Tensor (N,) int64
        ``(polarity > 0) * B + window`` of each event.
    windows : int
        ``B``.
    size : (H, W)
        Image size [px].
    eps : float
        Added to the vote count before dividing.
    purge : bool
        Drop the events that either warp moves out of the image.

    Returns
    -------
    Tensor (B,), the dtype of ``x``
        Without the smoothness term.
    """
    if not compiled_images_apply(x, y):
        raise ValueError(f"average_timestamp_images needs CPU float32/float64 x, y (2, N); got {tuple(x.shape)} "
                         f"{x.dtype} on {x.device}, {tuple(y.shape)} {y.dtype}")
    n = x.shape[1]
    if tau.shape != (n,) or base.shape != (n,) or base.dtype != torch.int64:
        raise ValueError(f"tau and base must be ({n},), base int64; got {tuple(tau.shape)}, {tuple(base.shape)} "
                         f"{base.dtype}")
    if int(windows) < 1 or int(size[0]) < 1 or int(size[1]) < 1:
        raise ValueError(f"windows and size must be positive, got {windows}, {tuple(size)}")
    if n and (int(base.min()) < 0 or int(base.max()) >= 2 * int(windows)):   # the kernels index images by it
        raise ValueError(f"base must lie in [0, {2 * int(windows)}) (polarity_on * B + window), got "
                         f"[{int(base.min())}, {int(base.max())}]")
    return _AverageTimestampImages.apply(x, y, tau, base, int(windows), (int(size[0]), int(size[1])),
                                         float(eps), bool(purge))
