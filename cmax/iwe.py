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

__all__ = [
    "accumulate_bilinear", "accumulate_bilinear_indexed", "blur", "image_of_warped_events", "iwe_numpy",
    "polarity_images", "sample_bilinear",
]


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
    batch = x.shape[0]
    index = torch.zeros_like(x, dtype=torch.long) + torch.arange(batch, device=x.device).view(-1, 1)
    image = _splat(x.reshape(-1), y.reshape(-1), None if weights is None else weights.reshape(-1),
                   index.reshape(-1), batch, height, width)
    return image if batched else image[0]


def _finite_corner(corner: torch.Tensor) -> torch.Tensor:
    """``corner`` (floored coordinates) with NaN and infinities replaced by -1, so that the integer index made
    from it stays on the padded canvas (NaN cast to int64 is its smallest value); the point's own vote or
    value stays NaN."""
    return torch.where(torch.isfinite(corner), corner, torch.full_like(corner, -1.0))


def _splat(x: torch.Tensor, y: torch.Tensor, weights: torch.Tensor | None, image_index: torch.Tensor,
           count: int, height: int, width: int) -> torch.Tensor:
    """Bilinear votes (N,) into ``count`` images (H, W), one ``index_add`` on a padded canvas.

    The canvas has one extra row and column on each side, so the four corners of
    a point are ``i, i + 1, i + Wp, i + Wp + 1``; a point whose corners leave the
    padded canvas votes nothing (its corners would all be outside the image). A
    point with a NaN or infinite coordinate makes the image NaN (its vote lands on
    pixel (0, 0)), as NaN spreads through any torch operation; it never indexes
    outside the canvas.
    """
    Hp, Wp = height + 2, width + 2
    x0 = torch.floor(x.detach())
    y0 = torch.floor(y.detach())
    fx, fy = x - x0, y - y0
    valid = (x0 >= -1) & (x0 <= width - 1) & (y0 >= -1) & (y0 <= height - 1)
    x0, y0 = _finite_corner(x0), _finite_corner(y0)
    x0 = x0.clamp(-1, width - 1).long() + 1
    y0 = y0.clamp(-1, height - 1).long() + 1
    corner = image_index * (Hp * Wp) + y0 * Wp + x0
    gx, gy = 1 - fx, 1 - fy
    votes = torch.stack([gx * gy, fx * gy, gx * fy, fx * fy])
    scale = valid.to(x.dtype) if weights is None else valid.to(x.dtype) * weights
    votes = votes * scale
    index = torch.stack([corner, corner + 1, corner + Wp, corner + Wp + 1])
    canvas = torch.zeros(count * Hp * Wp, dtype=x.dtype, device=x.device)
    canvas = canvas.index_add(0, index.reshape(-1), votes.reshape(-1))
    return canvas.view(count, Hp, Wp)[:, 1:-1, 1:-1]


def accumulate_bilinear_indexed(
    x: torch.Tensor, y: torch.Tensor, weights: torch.Tensor | None, image_index: torch.Tensor,
    count: int, height: int, width: int,
) -> torch.Tensor:
    """Bilinear votes of points into ``count`` small images, each point into its own one.

    Parameters
    ----------
    x, y : Tensor, shape (N,)
        Sub-pixel coordinates in the frame of each point's image.
    weights : Tensor (N,) or None
    image_index : Tensor, shape (N,), int64
        Which image (0 <= i < count) each point votes into.
    count, height, width : int

    Returns
    -------
    Tensor, shape (count, H, W)
        Differentiable with respect to ``x``, ``y`` and ``weights``. Used for
        the per-cell images of the local contrast (:func:`cmax.objectives.local_contrast`).
    """
    return _splat(x, y, weights, image_index, count, height, width)


def sample_bilinear(images: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Values of images at sub-pixel points, bilinear, zero outside (the adjoint of the voting).

    Parameters
    ----------
    images : Tensor, shape (B, H, W)
    x, y : Tensor, shape (B, N)
        Coordinates (column, row) [px] of the points read from image b.

    Returns
    -------
    Tensor, shape (B, N)
        ``sum_u I_b(u) b(u - x_k)``: for a point that voted into an image with
        :func:`accumulate_bilinear`, the image it "sees" through its own kernel;
        NaN at a point with a NaN or infinite coordinate.

    Examples
    --------
    >>> import torch
    >>> image = torch.tensor([[[0.0, 2.0], [4.0, 6.0]]])
    >>> sample_bilinear(image, torch.tensor([[0.5]]), torch.tensor([[0.5]])).tolist()
    [[3.0]]
    """
    if images.dim() != 3 or x.dim() != 2 or x.shape != y.shape or x.shape[0] != images.shape[0]:
        raise ValueError(f"need images (B, H, W) and x, y (B, N), got {tuple(images.shape)}, "
                         f"{tuple(x.shape)}, {tuple(y.shape)}")
    B, H, W = images.shape
    canvas = torch.nn.functional.pad(images, (1, 1, 1, 1)).reshape(B, -1)
    Wp = W + 2
    x0, y0 = torch.floor(x.detach()), torch.floor(y.detach())
    fx, fy = x - x0, y - y0
    valid = ((x0 >= -1) & (x0 <= W - 1) & (y0 >= -1) & (y0 <= H - 1)).to(images.dtype)
    x0, y0 = _finite_corner(x0), _finite_corner(y0)
    corner = (y0.clamp(-1, H - 1).long() + 1) * Wp + x0.clamp(-1, W - 1).long() + 1
    value = ((1 - fx) * (1 - fy) * canvas.gather(1, corner) + fx * (1 - fy) * canvas.gather(1, corner + 1)
             + (1 - fx) * fy * canvas.gather(1, corner + Wp) + fx * fy * canvas.gather(1, corner + Wp + 1))
    return value * valid


def _gaussian_kernel(sigma: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    radius = max(1, math.ceil(3 * sigma))
    offsets = torch.arange(-radius, radius + 1, dtype=dtype, device=device)
    kernel = torch.exp(-offsets * offsets / (2.0 * sigma * sigma))
    return kernel / kernel.sum()


def _separable(stack: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """Zero-padded separable convolution of (B, 1, H, W) with a symmetric 1-D kernel.

    On the CPU, OpenCV's ``sepFilter2D`` (``BORDER_CONSTANT``), far faster than ``conv2d`` with one
    torch thread (``benchmarks/speed_cmax.py`` times both); the two agree to float rounding. The
    autograd of :class:`_SymmetricBlur` does not need torch ops here.
    """
    if stack.device.type == "cpu" and stack.dtype in (torch.float32, torch.float64) and stack.numel():
        import cv2

        images = stack.detach().numpy()
        taps = kernel.detach().cpu().numpy().astype(images.dtype)
        out = np.empty_like(images)
        for i in range(images.shape[0]):
            cv2.sepFilter2D(images[i, 0], -1, taps, taps, dst=out[i, 0], borderType=cv2.BORDER_CONSTANT)
        return torch.from_numpy(out)
    radius = (kernel.numel() - 1) // 2
    out = torch.nn.functional.conv2d(stack, kernel.view(1, 1, 1, -1), padding=(0, radius))
    return torch.nn.functional.conv2d(out, kernel.view(1, 1, -1, 1), padding=(radius, 0))


class _SymmetricBlur(torch.autograd.Function):
    """Gaussian blur whose backward is the same blur.

    With zero padding the adjoint of a convolution is the correlation with the
    same kernel, which equals the convolution for a symmetric kernel; this
    replaces conv2d's generic backward (several times slower on CPU).
    """

    @staticmethod
    def forward(ctx, stack: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        ctx.save_for_backward(kernel)
        return _separable(stack, kernel)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        (kernel,) = ctx.saved_tensors
        return _SymmetricBlur.apply(grad.contiguous(), kernel), None


def blur(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """Gaussian blur of (H, W) or (B, H, W) images with standard deviation ``sigma`` px.

    Separable, zero padding (mass near the border leaks out, as kornia's
    ``border_type="constant"``), kernel radius ``ceil(3 sigma)``; differentiable. ``sigma`` 0: the image
    unchanged; a negative or non-finite ``sigma`` is refused (ValueError).
    """
    if not (math.isfinite(sigma) and sigma >= 0):
        raise ValueError(f"blur: sigma must be a finite number of pixels >= 0, got {sigma!r}")
    if sigma == 0:
        return image
    kernel = _gaussian_kernel(sigma, image.dtype, image.device)
    batched = image.dim() == 3
    stack = image[:, None] if batched else image[None, None]
    out = _SymmetricBlur.apply(stack.contiguous(), kernel)
    return out[:, 0] if batched else out[0, 0]


def polarity_images(x: torch.Tensor, y: torch.Tensor, on: torch.Tensor, height: int, width: int, sigma: float,
                    weights: torch.Tensor | None = None) -> torch.Tensor:
    """Blurred IWEs of the ON and of the OFF events apart: (2B, H, W), the B ON images first.

    ``x, y`` (B, N) are warped coordinates [px] on a ``height`` x ``width`` image, blurred by ``sigma`` [px];
    ``on`` (N,) or (B, N) is 1 for
    ON events and 0 for OFF (all ones: the OFF images are empty); ``weights``
    (B, N) or None scale every vote. Differentiable like :func:`accumulate_bilinear`.
    """
    on = on.to(x.dtype).expand_as(x)
    votes = torch.cat([on, 1 - on]) if weights is None else torch.cat([on * weights, (1 - on) * weights])
    return blur(accumulate_bilinear(torch.cat([x, x]), torch.cat([y, y]), votes, height, width), sigma)


def image_of_warped_events(
    x: torch.Tensor, y: torch.Tensor, *, height: int, width: int,
    weights: torch.Tensor | None = None, sigma: float = 1.0,
) -> torch.Tensor:
    """IWE of warped coordinates: bilinear votes, then a Gaussian blur of ``sigma`` px.

    Shapes as :func:`accumulate_bilinear` (``weights`` (B, N) or None: every vote 1); ``sigma=0`` disables the blur.

    Examples
    --------
    >>> import torch
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
    """NumPy entry point of :func:`image_of_warped_events`: ``x``, ``y`` [px] and ``weights`` (N,) arrays in,
    (``height``, ``width``) float32 out, blurred by ``sigma`` [px]."""
    def tensor(values: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(values, dtype=np.float32))

    image = image_of_warped_events(
        tensor(x), tensor(y), height=height, width=width,
        weights=None if weights is None else tensor(weights), sigma=sigma,
    )
    return image.numpy()
