"""The contrast of an image split into the shares of a grid of cells.

The variance and the mean squared gradient of :mod:`cmax.objectives` are sums over pixels, so they
split exactly into the shares of the cells of a grid: :func:`contrast_by_cell` returns, for each
image, the share of every cell, and the shares sum to :func:`cmax.objectives.contrast_of_images`.
The difference of two such splits (warped against unwarped events) says where a contrast gain comes
from; its spread over the cells is the standard error of the gain that the fit's low-motion test
compares the gain with (:func:`cmax.fitting.quality.motion_within_noise`): a motion that sharpens the
whole image gains in most cells, an artefact of a few cells does not.

References
----------
G. Gallego, H. Rebecq, D. Scaramuzza, "A unifying contrast maximization framework for event cameras",
CVPR 2018 (the variance and gradient contrasts); T. Stoffregen, L. Kleeman, "Event cameras, contrast
maximization and reward functions: an analysis", CVPR 2019 (local, per-region contrast).
"""
from __future__ import annotations

import torch

__all__ = ["contrast_by_cell", "cell_index"]


def cell_index(height: int, width: int, cells: tuple[int, int]) -> torch.Tensor:
    """Cell (H * W,) int64 of every pixel, row-major, of a ``cells`` (rows, cols) grid over the image."""
    rows, cols = cells
    r = (torch.arange(height) * rows // height)[:, None]
    c = (torch.arange(width) * cols // width)[None, :]
    return (r * cols + c).reshape(-1)


def contrast_by_cell(images: torch.Tensor, kind: str, cells: tuple[int, int]) -> torch.Tensor:
    """Each cell's share (B, C) of the contrast of ``images`` (B, H, W) over a ``cells`` = (rows, cols) grid;
    ``sum(-1)`` is the contrast (B,).

    ``kind`` ``"variance"``: ``(I - mean I)^2 / (H W)`` summed over the cell's pixels (the image's own
    mean); ``"gradient"``: the central differences' squares, ``gx^2 / (H (W - 2)) + gy^2 / ((H - 2) W)``,
    each at the pixel between its two samples. ``C = rows * cols``.

    Examples
    --------
    >>> import torch
    >>> images = torch.tensor([[[0.0, 2.0], [0.0, 2.0]]])
    >>> contrast_by_cell(images, "variance", (1, 2)).tolist()
    [[0.5, 0.5]]
    """
    if images.dim() != 3:
        raise ValueError(f"images must have shape (B, H, W), got {tuple(images.shape)}")
    B, H, W = images.shape
    if kind == "variance":
        centred = images - images.mean((1, 2), keepdim=True)
        energy = centred * centred / (H * W)
    elif kind == "gradient":
        energy = torch.zeros_like(images)
        if W > 2:
            gx = (images[:, :, 2:] - images[:, :, :-2]) / 2.0
            energy[:, :, 1:-1] += gx * gx / (H * (W - 2))
        if H > 2:
            gy = (images[:, 2:, :] - images[:, :-2, :]) / 2.0
            energy[:, 1:-1, :] += gy * gy / ((H - 2) * W)
    else:
        raise ValueError(f"kind must be 'variance' or 'gradient', got {kind!r}")
    index = cell_index(H, W, cells).to(images.device)
    out = torch.zeros(B, cells[0] * cells[1], dtype=images.dtype, device=images.device)
    return out.index_add_(1, index, energy.reshape(B, -1))
