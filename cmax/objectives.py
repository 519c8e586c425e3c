"""Contrast objectives of images of warped events, and the regularizers of a depth-and-motion fit.

* :func:`variance` — the IWE variance of the paper (eq. 11; Gallego et al., CVPR 2018),
  maximised, so ``fit`` minimises its negative.
* :func:`gradient_magnitude` — the mean squared image gradient (Gallego et al.,
  "Focus is all you need", CVPR 2019, doi:10.1109/CVPR.2019.01256).
* :func:`multi_reference_contrast` — the mean of a contrast over images warped to
  several reference times (start, middle, end of the window), normalised by the
  same quantity of the unwarped events. Warping to one time only rewards
  squeezing the events toward a point ("event collapse"); averaging over
  references and dividing by the identity warp's value makes the objective
  dimensionless (about 1 at the start) and far less prone to it (Shiba, Aoki,
  Gallego, "Event collapse in contrast maximization frameworks", Sensors 2022,
  doi:10.3390/s22145190).
* :func:`deformation` — Shiba et al.'s guard against collapse: the mean squared
  log area change of the warp, measured on a lattice of probe points.
* :func:`total_variation` — smoothed TV of an inverse-depth grid.
* :func:`local_contrast` — per-cell contrast of each depth cell's *own* events,
  each in a small image around its cell: a cell cannot raise it by piling its
  events onto another cell's edges, which is how a free depth grid collapses
  under the global variance.

All functions are differentiable (torch) and batched over a leading dimension.
"""
from __future__ import annotations

from typing import Callable

import torch

from cmax.iwe import accumulate_bilinear, accumulate_bilinear_indexed, blur, polarity_images

__all__ = [
    "variance", "gradient_magnitude", "CONTRASTS", "contrast_of_images", "multi_reference_contrast",
    "deformation", "total_variation", "local_contrast",
]


def _check_images(images: torch.Tensor) -> torch.Tensor:
    if images.dim() not in (2, 3):
        raise ValueError(f"images must have shape (H, W) or (B, H, W), got {tuple(images.shape)}")
    return images if images.dim() == 3 else images[None]


def variance(images: torch.Tensor) -> torch.Tensor:
    """Variance of each image over its pixels: ``mean((I - mean(I))^2)``.

    Parameters
    ----------
    images : Tensor, shape (H, W) or (B, H, W)

    Returns
    -------
    Tensor, shape () or (B,)

    Examples
    --------
    >>> import torch
    >>> float(variance(torch.tensor([[0.0, 2.0], [0.0, 2.0]])))
    1.0
    """
    batched = images.dim() == 3
    flat = _check_images(images).flatten(1)
    out = (flat * flat).mean(1) - flat.mean(1) ** 2
    return out if batched else out[0]


def gradient_magnitude(images: torch.Tensor) -> torch.Tensor:
    """Mean squared gradient ``mean(|dI/dx|^2 + |dI/dy|^2)`` (central differences) of ``images`` (H, W) or
    (B, H, W): shape () or (B,).

    Examples
    --------
    >>> import torch
    >>> float(gradient_magnitude(torch.tensor([[0.0, 2.0, 4.0]] * 3)))
    4.0
    """
    batched = images.dim() == 3
    stack = _check_images(images)
    gx = (stack[:, :, 2:] - stack[:, :, :-2]) / 2.0
    gy = (stack[:, 2:, :] - stack[:, :-2, :]) / 2.0
    out = (gx * gx).flatten(1).mean(1) + (gy * gy).flatten(1).mean(1)
    return out if batched else out[0]


#: The contrast functions by name (for keyword options of :func:`cmax.fit`).
CONTRASTS: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
    "variance": variance, "gradient": gradient_magnitude,
}


def contrast_of_images(images: torch.Tensor, kind: str = "variance") -> torch.Tensor:
    """Contrast (B,) of ``images`` (B, H, W) by the name ``kind``: ``"variance"`` or ``"gradient"``."""
    if kind not in CONTRASTS:
        raise ValueError(f"contrast must be one of {sorted(CONTRASTS)}, got {kind!r}")
    return CONTRASTS[kind](images)


def multi_reference_contrast(
    x: torch.Tensor, y: torch.Tensor, *, height: int, width: int, weights: torch.Tensor | None = None,
    sigma: float = 1.0, kind: str = "variance", baseline: torch.Tensor | float = 1.0,
    on: torch.Tensor | None = None,
) -> torch.Tensor:
    """Mean contrast of the IWEs of B sets of warped coordinates, divided by ``baseline``.

    Parameters
    ----------
    x, y : Tensor, shape (B, N)
        Coordinates warped to B reference times [px], on an image of ``height`` x ``width`` px.
    weights : Tensor (N,) or None
        Votes (signed polarity) or None for counts.
    sigma : float
        Gaussian blur of the IWEs [px].
    kind : {"variance", "gradient"}
    baseline : Tensor or float
        The same quantity for the identity warp (normalisation), or 1.
    on : Tensor (N,) or None
        1 for ON events, 0 for OFF: one IWE per polarity and the sum of
        their contrasts (an ON edge and the OFF edge that trails it stay
        apart instead of blurring into one wider edge; with one polarity
        only, the other image is empty and adds nothing).

    Returns
    -------
    Tensor, shape ()
    """
    if x.dim() != 2 or x.shape != y.shape:
        raise ValueError(f"x and y must have the same shape (B, N), got {tuple(x.shape)}, {tuple(y.shape)}")
    w = None if weights is None else weights.expand_as(x)
    if on is None:
        images = blur(accumulate_bilinear(x, y, w, height, width), sigma)
        return contrast_of_images(images, kind).mean() / baseline
    images = polarity_images(x, y, on, height, width, sigma, w)
    return contrast_of_images(images, kind).view(2, x.shape[0]).sum(0).mean() / baseline


def deformation(x0: torch.Tensor, y0: torch.Tensor, x1: torch.Tensor, y1: torch.Tensor) -> torch.Tensor:
    """Mean squared log area change of a warp, from a lattice of probe points.

    Parameters
    ----------
    x0, y0 : Tensor, shape (P, Q)
        A lattice of probe pixels before the warp.
    x1, y1 : Tensor, shape (..., P, Q)
        The same probes after the warp (any leading batch, e.g. reference times).

    Returns
    -------
    Tensor, shape ()
        ``mean(log(area1 / area0)^2)`` over the lattice cells: 0 for a
        rigid image motion, large when the warp squeezes (or blows up) the
        image, which is what event collapse does (Shiba et al., Sensors 2022,
        the "deformation" regularizer). Folded cells (negative area) count as
        a factor 1e-3.
    """
    def areas(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        ax, ay = x[..., :-1, 1:] - x[..., :-1, :-1], y[..., :-1, 1:] - y[..., :-1, :-1]
        bx, by = x[..., 1:, :-1] - x[..., :-1, :-1], y[..., 1:, :-1] - y[..., :-1, :-1]
        return ax * by - ay * bx

    a0 = areas(x0, y0)
    ratio = (areas(x1, y1) / a0).clamp(min=1e-3)
    return torch.log(ratio).pow(2).mean()


def total_variation(grid: torch.Tensor, *, epsilon: float = 1e-3) -> torch.Tensor:
    """Smoothed isotropic total variation of a (gh, gw) grid: ``mean(sqrt(dx^2 + dy^2 + eps^2))``.

    ``epsilon`` (in the grid's unit) makes it differentiable at 0.

    Examples
    --------
    >>> import torch
    >>> round(float(total_variation(torch.zeros(4, 4))), 6)
    0.001
    """
    if grid.dim() != 2:
        raise ValueError(f"grid must have shape (gh, gw), got {tuple(grid.shape)}")
    dx = torch.nn.functional.pad(grid[:, 1:] - grid[:, :-1], (0, 1))
    dy = torch.nn.functional.pad(grid[1:, :] - grid[:-1, :], (0, 0, 0, 1))
    return torch.sqrt(dx * dx + dy * dy + epsilon * epsilon).mean()


def local_contrast(
    x: torch.Tensor, y: torch.Tensor, cell: torch.Tensor, origins: torch.Tensor, *,
    count: int, patch: tuple[int, int], weights: torch.Tensor | None = None, sigma: float = 1.0,
) -> torch.Tensor:
    """Contrast of each cell's own events, each in a small image around its cell.

    Parameters
    ----------
    x, y : Tensor, shape (N,) or (B, N)
        Warped coordinates [px] in the full image (B batches, e.g. candidate depths).
    cell : Tensor, shape (N,), int64
        The cell of each event (0 <= cell < count).
    origins : Tensor, shape (count, 2)
        Top-left pixel ``(x, y)`` of each cell's image.
    count : int
        Number of cells.
    patch : (h, w)
        Size of each cell's image [px] (the cell plus a margin for the motion).
    weights : Tensor (N,) or None
    sigma : float
        Blur [px].

    Returns
    -------
    Tensor, shape (count,) or (B, count)
        ``sum(I_c^2)`` of the blurred image of cell c's events: larger when they
        are aligned (for a fixed number of events in the patch). Votes falling
        outside the patch are lost, which lowers the value.
    """
    batched = x.dim() == 2
    if not batched:
        x, y = x[None], y[None]
    B = x.shape[0]
    h, w = patch
    index = (torch.arange(B, device=x.device)[:, None] * count + cell[None, :]).reshape(-1)
    ox, oy = origins[cell, 0], origins[cell, 1]
    lx, ly = (x - ox).reshape(-1), (y - oy).reshape(-1)
    wts = None if weights is None else weights.expand(B, -1).reshape(-1)
    images = blur(accumulate_bilinear_indexed(lx, ly, wts, index, B * count, h, w), sigma)
    energy = (images * images).flatten(1).sum(1).view(B, count)
    return energy if batched else energy[0]
