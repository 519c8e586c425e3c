"""SO(3)/SE(3) actions in torch, closed form, batched over events (differentiable).

The same convention as :mod:`cmax.geometry` (numpy): a twist ``xi = (v, omega)``
has the translation part first; ``exp(hat(xi)) = [[R, J v], [0, 1]]`` with

    R = I + A W + B W^2,   J = I + B W + C W^2,   W = hat(omega),
    A = sin(t)/t,  B = (1 - cos t)/t^2,  C = (t - sin t)/t^3,  t = |omega|.

These functions apply the maps to vectors without forming matrices
(``W u = omega x u``), one rotation vector per row: the warp of N events costs a
few fused element-wise operations instead of N matrix exponentials. The
coefficients come from ``t^2`` with a Taylor series below ``t = 1e-2`` rad, so
the gradient is finite at ``omega = 0`` (a common starting point).
"""
from __future__ import annotations

import torch

__all__ = ["rodrigues_coefficients", "so3_rotate", "se3_transform", "so3_exp_torch", "se3_exp_torch"]

_SMALL_ANGLE_SQ = 1e-4  # (1e-2 rad)^2: the series below are exact to ~1e-14 there


def rodrigues_coefficients(theta_sq: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``A, B, C`` of the module docstring from the squared angle ``theta_sq`` (any shape).

    Smooth in ``theta_sq`` (no square root of zero), so autograd is finite everywhere.
    """
    small = theta_sq < _SMALL_ANGLE_SQ
    safe = torch.where(small, torch.ones_like(theta_sq), theta_sq)
    t = torch.sqrt(safe)
    sin, cos = torch.sin(t), torch.cos(t)
    s = theta_sq
    A = torch.where(small, 1.0 - s / 6.0 + s * s / 120.0, sin / t)
    B = torch.where(small, 0.5 - s / 24.0 + s * s / 720.0, (1.0 - cos) / safe)
    C = torch.where(small, 1.0 / 6.0 - s / 120.0 + s * s / 5040.0, (t - sin) / (safe * t))
    return A, B, C


def so3_rotate(omega: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """``so3_exp(omega) @ u`` row by row: ``u + A (w x u) + B (w x (w x u))``.

    Parameters
    ----------
    omega : Tensor, shape (..., 3)
        Rotation vectors [rad]; broadcasts against ``u``.
    u : Tensor, shape (..., 3)

    Returns
    -------
    Tensor, shape of the broadcast.

    Examples
    --------
    >>> import math
    >>> so3_rotate(torch.tensor([0.0, 0.0, math.pi / 2]), torch.tensor([1.0, 0.0, 0.0])).round(decimals=6)
    tensor([0., 1., 0.])
    """
    shape = torch.broadcast_shapes(omega.shape, u.shape)
    omega, u = omega.expand(shape), u.expand(shape)
    A, B, _ = rodrigues_coefficients((omega * omega).sum(-1, keepdim=True))
    wu = torch.linalg.cross(omega, u, dim=-1)
    wwu = torch.linalg.cross(omega, wu, dim=-1)
    return u + A * wu + B * wwu


def se3_transform(xi: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """``se3_exp(xi)`` applied to points, row by row: ``R p + J v``.

    Parameters
    ----------
    xi : Tensor, shape (..., 6)
        Twists ``(v, omega)`` [m, rad]; broadcasts against ``points``.
    points : Tensor, shape (..., 3)
        Points [m] in the frame the twist moves them from.
    """
    v, omega = xi[..., :3], xi[..., 3:]
    shape = torch.broadcast_shapes(omega.shape, points.shape)
    omega, points, v = omega.expand(shape), points.expand(shape), v.expand(shape)
    A, B, C = rodrigues_coefficients((omega * omega).sum(-1, keepdim=True))
    wp = torch.linalg.cross(omega, points, dim=-1)
    wv = torch.linalg.cross(omega, v, dim=-1)
    return (points + A * wp + B * torch.linalg.cross(omega, wp, dim=-1)
            + v + B * wv + C * torch.linalg.cross(omega, wv, dim=-1))


def _hat(omega: torch.Tensor) -> torch.Tensor:
    zero = torch.zeros_like(omega[..., 0])
    w1, w2, w3 = omega.unbind(-1)
    return torch.stack([zero, -w3, w2, w3, zero, -w1, -w2, w1, zero], -1).reshape(omega.shape[:-1] + (3, 3))


def so3_exp_torch(omega: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) (Rodrigues), differentiable."""
    A, B, _ = rodrigues_coefficients((omega * omega).sum(-1))
    W = _hat(omega)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device)
    return eye + A[..., None, None] * W + B[..., None, None] * (W @ W)


def se3_exp_torch(xi: torch.Tensor) -> torch.Tensor:
    """Poses (..., 4, 4) of twists ``(v, omega)`` (..., 6), differentiable (as :func:`cmax.geometry.se3_exp`)."""
    v, omega = xi[..., :3], xi[..., 3:]
    A, B, C = rodrigues_coefficients((omega * omega).sum(-1))
    W = _hat(omega)
    WW = W @ W
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    R = eye + A[..., None, None] * W + B[..., None, None] * WW
    J = eye + B[..., None, None] * W + C[..., None, None] * WW
    top = torch.cat([R, (J @ v[..., None])], -1)
    bottom = torch.zeros(xi.shape[:-1] + (1, 4), dtype=xi.dtype, device=xi.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], -2)
