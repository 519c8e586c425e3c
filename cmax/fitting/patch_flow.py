"""Initial translation direction and rotation from patch flows and the motion-field equations.

The image is cut into patches; each patch gets a constant optical flow by
contrast maximization of its own events (all patches in one solve: the
objective is the sum of the patches' normalised IWE variances, separable).
The instantaneous motion field of a rigid scene is, at pixel ``x`` with
inverse depth ``rho``,

    u(x) = rho A(x) v + B(x) omega                    (Longuet-Higgins & Prazdny, 1980)

with ``A`` and ``B`` (2 x 3) read off the se3 warp of :mod:`cmax.warp` by
finite differences (so the sign conventions are the warp's own). For a
candidate direction ``t`` (``v = speed t``) the patch flows are linear in
``omega`` and the patches' ``rho``: one least-squares problem per direction,
solved for a few thousand directions on the sphere at once; the direction
with the smallest residual whose inverse depths are mostly positive wins.
This is the initialiser the issue asks for ("patch flows fitted to the
motion-field equations"); :func:`cmax.fitting.stages.fit_se3` refines it.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from cmax.iwe import accumulate_bilinear_indexed, blur
from cmax.objectives import variance
from cmax.warp import warp_se3

__all__ = ["patch_flows", "motion_from_flows", "fibonacci_sphere"]


def patch_flows(w, *, grid: tuple[int, int] = (4, 5), min_events: int = 200, max_events: int = 20_000
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Constant flow [px/s] of each patch with enough events.

    Returns
    -------
    centres : ndarray (P, 2)
        Mean pixel of each patch's events.
    flows : ndarray (P, 2)
    counts : ndarray (P,)
    """
    ev = w.ev
    gh, gw = grid
    n = len(ev)
    step = max(1, n // max_events)
    x, y, dt = ev.x[::step], ev.y[::step], w.dt_mid[0, ::step]
    cell = ((y * gh / ev.height).long().clamp(0, gh - 1) * gw + (x * gw / ev.width).long().clamp(0, gw - 1))
    counts = torch.bincount(cell, minlength=gh * gw)
    keep_cells = torch.nonzero(counts >= min_events).reshape(-1)
    if keep_cells.numel() == 0:
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0)
    remap = torch.full((gh * gw,), -1, dtype=torch.long)
    remap[keep_cells] = torch.arange(keep_cells.numel())
    patch = remap[cell]
    sel = patch >= 0
    x, y, dt, patch = x[sel], y[sel], dt[sel], patch[sel]
    P = keep_cells.numel()
    ph, pw = math.ceil(ev.height / gh), math.ceil(ev.width / gw)
    margin = max(8, int(0.25 * max(ph, pw)))
    ox = (keep_cells % gw).to(x.dtype) * ev.width / gw - margin
    oy = (keep_cells // gw).to(x.dtype) * ev.height / gh - margin
    H, W = ph + 2 * margin, pw + 2 * margin
    lx, ly = x - ox[patch], y - oy[patch]
    sigma = w.settings.sigma
    with torch.no_grad():
        base = variance(blur(accumulate_bilinear_indexed(lx, ly, None, patch, P, H, W), sigma)).clamp(min=1e-12)
    T = w.T

    def fun_and_grad(p: np.ndarray) -> tuple[float, np.ndarray]:
        q = torch.tensor(p.reshape(P, 2), dtype=x.dtype, requires_grad=True)
        flow = q / T
        images = blur(accumulate_bilinear_indexed(lx - flow[patch, 0] * dt, ly - flow[patch, 1] * dt,
                                                  None, patch, P, H, W), sigma)
        value = -(variance(images) / base).sum()
        (grad,) = torch.autograd.grad(value, q)
        return float(value.detach()), grad.double().numpy().reshape(-1)

    from scipy.optimize import minimize

    bound = float(margin)
    result = minimize(fun_and_grad, np.zeros(2 * P), jac=True, method="L-BFGS-B",
                      bounds=[(-bound, bound)] * (2 * P), options={"maxiter": 40})
    w.iterations += int(result.nit)
    w.evaluations += int(result.nfev)
    flows = result.x.reshape(P, 2) / T
    centres = torch.stack([torch.zeros(P, dtype=x.dtype).index_add_(0, patch, x),
                           torch.zeros(P, dtype=x.dtype).index_add_(0, patch, y)], 1) / counts[keep_cells, None]
    return centres.double().numpy(), flows, counts[keep_cells].double().numpy()


def _field_matrices(centres: np.ndarray, K: np.ndarray, dt: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """``A`` (P, 2, 3) and ``B`` (P, 2, 3) of the motion field at pixel centres, from the se3 warp."""
    Kt = torch.as_tensor(K, dtype=torch.float64)
    rays = torch.from_numpy(np.column_stack([centres, np.ones(len(centres))]) @ np.linalg.inv(K).T)
    d = torch.full((len(centres),), dt, dtype=torch.float64)
    x0, y0 = torch.from_numpy(centres[:, 0]), torch.from_numpy(centres[:, 1])
    A, B = np.zeros((len(centres), 2, 3)), np.zeros((len(centres), 2, 3))
    for j in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[j] = 1.0
        for target, v, om in ((A, e, e * 0), (B, e * 0, e)):
            x, y = warp_se3(rays, d, v, om, torch.ones(len(centres), dtype=torch.float64), Kt)
            target[:, 0, j] = ((x0 - x) / dt).numpy()  # u = (x_i - x_ref) / dt
            target[:, 1, j] = ((y0 - y) / dt).numpy()
    return A, B


def fibonacci_sphere(count: int) -> np.ndarray:
    """``count`` nearly uniform unit vectors (count, 3)."""
    i = np.arange(count) + 0.5
    z = 1 - 2 * i / count
    r = np.sqrt(1 - z * z)
    phi = i * math.pi * (3 - math.sqrt(5))
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def motion_from_flows(centres: np.ndarray, flows: np.ndarray, counts: np.ndarray, K: np.ndarray, speed: float,
                      *, directions: int = 3000) -> tuple[np.ndarray, np.ndarray, float]:
    """Best ``v`` (3,) [m/s, norm ``speed``], ``omega`` (3,) [rad/s] and the residual [px/s] from patch flows."""
    P = len(centres)
    if P < 4:
        raise ValueError(f"need at least 4 patches with events to initialise the motion, got {P}")
    A, B = _field_matrices(centres, K)
    sw = np.sqrt(counts / counts.mean())[:, None]                         # (P, 1) weights
    t = fibonacci_sphere(directions)                                       # (D, 3)
    a = np.einsum("pij,dj->dpi", A, t) * speed                             # (D, P, 2): rho_p multiplies it
    D = len(t)
    M = np.zeros((D, 2 * P, 3 + P))
    M[:, :, :3] = np.tile((B * sw[:, :, None]).reshape(2 * P, 3), (D, 1, 1))
    rows = np.arange(2 * P)
    M[:, rows, 3 + rows // 2] = (a * sw[None]).reshape(D, 2 * P)
    b = (flows * sw).reshape(2 * P)
    MtM = np.einsum("dki,dkj->dij", M, M) + 1e-9 * np.eye(3 + P)
    Mtb = np.einsum("dki,k->di", M, b)
    x = np.linalg.solve(MtM, Mtb[..., None])[..., 0]                      # (D, 3 + P)
    residual = np.sqrt(np.mean((np.einsum("dkj,dj->dk", M, x) - b) ** 2, axis=1))
    negative = (x[:, 3:] < 0).mean(1)
    score = residual * (1 + 4 * negative)
    best = int(np.argmin(score))
    return speed * t[best], x[best, :3], float(residual[best])
