"""Image of warped events (IWE): bilinear voting, optional Gaussian blur, differentiable.

Given warped event coordinates ``x'_k, y'_k`` (sub-pixel) and weights ``w_k``
(1, or the signed polarity), the IWE is

    I(u) = sum_k w_k * b(u - x'_k)

with ``b`` the bilinear kernel: each event splits its weight among the four
pixels around it in proportion to the opposite areas (Gallego et al., "A
unifying contrast maximization framework for event cameras", CVPR 2018,
doi:10.1109/CVPR.2018.00407). The image is differentiable with respect to the
coordinates (and weights) through ``torch.Tensor.index_add_``; votes that fall
outside the image are dropped corner by corner, which keeps the image
continuous in the coordinates.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from kornia.filters import gaussian_blur2d

__all__ = ["accumulate_bilinear", "blur", "image_of_warped_events", "iwe_numpy"]


def accumulate_bilinear(
    x: torch.Tensor, y: torch.Tensor, weights: torch.Tensor | None, height: int, width: int,
) -> torch.Tensor:
    """Bilinear votes of points into images, batched.

    Parameters
    ----------
    x, y : Tensor, shape (N,) or (B, N)
        Sub-pixel coordinates (column, row) in pixels; floating point.
    weights : Tensor, shape like ``x``, or None
        Vote of each point (1 when None).
    height, width : int
        Image size in pixels.

    Returns
    -------
    Tensor, shape (H, W) or (B, H, W)
        Same dtype and device as ``x``; differentiable with respect to
        ``x``, ``y`` and ``weights``.
    """
    batched = x.dim() == 2
    if not batched:
        x, y = x[None], y[None]
        weights = None if weights is None else weights[None]
    batch, count = x.shape
    x0 = torch.floor(x.detach())
    y0 = torch.floor(y.detach())
    fx, fy = x - x0, y - y0
    x0, y0 = x0.long(), y0.long()
    base = torch.arange(batch, device=x.device).view(-1, 1) * (height * width)
    image = torch.zeros(batch * height * width, dtype=x.dtype, device=x.device)
    for dx, dy, area in (
        (0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
        (0, 1, (1 - fx) * fy), (1, 1, fx * fy),
    ):
        xi, yi = x0 + dx, y0 + dy
        inside = (xi >= 0) & (xi < width) & (yi >= 0) & (yi < height)
        vote = area if weights is None else area * weights
        index = base + yi.clamp(0, height - 1) * width + xi.clamp(0, width - 1)
        image = image.index_add(0, index.reshape(-1), (vote * inside).reshape(-1))
    image = image.view(batch, height, width)
    return image if batched else image[0]


def blur(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """Gaussian blur of (H, W) or (B, H, W) images with standard deviation ``sigma`` px (kornia)."""
    if sigma <= 0:
        return image
    radius = max(1, math.ceil(3 * sigma))
    size = 2 * radius + 1
    batched = image.dim() == 3
    stack = image[:, None] if batched else image[None, None]
    out = gaussian_blur2d(stack, (size, size), (sigma, sigma), border_type="constant")
    return out[:, 0] if batched else out[0, 0]


def image_of_warped_events(
    x: torch.Tensor, y: torch.Tensor, *, height: int, width: int,
    weights: torch.Tensor | None = None, sigma: float = 1.0,
) -> torch.Tensor:
    """IWE of warped coordinates: bilinear votes, then a Gaussian blur of ``sigma`` px.

    Shapes as :func:`accumulate_bilinear`; ``sigma=0`` disables the blur.

    Examples
    --------
    >>> x = torch.tensor([1.5]); y = torch.tensor([2.0])
    >>> image_of_warped_events(x, y, height=4, width=4, sigma=0)[2].tolist()
    [0.0, 0.5, 0.5, 0.0]
    """
    if x.shape != y.shape:
        raise ValueError(f"x and y must have the same shape, got {tuple(x.shape)} and {tuple(y.shape)}")
    if x.dim() not in (1, 2):
        raise ValueError(f"x must have shape (N,) or (B, N), got {tuple(x.shape)}")
    if not x.is_floating_point():
        raise TypeError(f"x must be a floating-point tensor, got {x.dtype}")
    if weights is not None and weights.shape != x.shape:
        raise ValueError(f"weights must have shape {tuple(x.shape)}, got {tuple(weights.shape)}")
    if height <= 0 or width <= 0:
        raise ValueError(f"height and width must be positive, got {height}, {width}")
    if sigma < 0:
        raise ValueError(f"sigma must be >= 0 pixels, got {sigma}")
    return blur(accumulate_bilinear(x, y, weights, height, width), sigma)


def iwe_numpy(
    x: np.ndarray, y: np.ndarray, *, height: int, width: int,
    weights: np.ndarray | None = None, sigma: float = 1.0,
) -> np.ndarray:
    """NumPy entry point of :func:`image_of_warped_events`: (N,) arrays in, (H, W) float32 out."""
    def tensor(values: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(values, dtype=np.float32))

    image = image_of_warped_events(
        tensor(x), tensor(y), height=height, width=width,
        weights=None if weights is None else tensor(weights), sigma=sigma,
    )
    return image.numpy()
