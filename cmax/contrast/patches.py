"""Patch-wise contrast: a window's events cut into a grid of patches, each imaged in its own small frame.

Two objectives of the se3 fit live here, both sums over patches of each patch's IWE variance
normalised by its unwarped value, so that every patch weighs the same whatever its events (the
global contrast is ruled by the densest regions):

* :class:`PatchFlowContrast`: each patch moves with its own constant flow (the patch-flow
  initialiser, :mod:`cmax.fitting.patch_flow`); separable over patches.
* :class:`PatchMotionContrast`: the events are warped by the exact se3 warp of :mod:`cmax.warp`
  with one shared twist and any per-event inverse depth (the fit's refinement,
  :mod:`cmax.fitting.motion`, gives each patch one inverse depth).

They differ from :class:`cmax.contrast.LocalContrast` (the contrast core's per-cell objective on a
depth map): the variance, not the energy ``sum I^2``, of each patch's image; the image's own frame
(the patch plus a margin) for each patch; the events subsampled once; the sum, not the mean, over
patches; no depth smoothness.

References
----------
S. Shiba, Y. Aoki, G. Gallego, "Secrets of event-based optical flow", ECCV 2022 (patch-wise contrast
with a shared motion). T. Stoffregen, L. Kleeman, "Event cameras, contrast maximization and reward
functions: an analysis", CVPR 2019 (local contrast). G. Gallego, H. Rebecq, D. Scaramuzza, "A
unifying contrast maximization framework for event cameras", CVPR 2018 (the warps and the variance).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch

from cmax.contrast._patch_kernels import (
    _PatchVariances, _Workspace, flow_gradient_by_patch, group_by_patch, shift_by_patch,
)
from cmax.contrast._warp_kernels import (
    compiled_warp_applies, intrinsics_row, project_at_depth, se3_warp_arrays, se3_warp_gradients, warp_se3_compiled,
)
from cmax.iwe import accumulate_bilinear_indexed, blur
from cmax.objectives import variance
from cmax.warp import MIN_PROJECTED_DEPTH, project, se3_parts, warp_se3

__all__ = ["Patches", "cut_patches", "PatchFlowContrast", "PatchMotionContrast"]

#: CPU float32 / float64 events take the compiled :func:`cmax.contrast._patch_kernels.patch_variances` (and
#: :class:`PatchMotionContrast` the compiled :func:`cmax.contrast._warp_kernels.warp_se3_compiled`); False: the
#: torch operations of :meth:`Patches.images` and :func:`cmax.warp.warp_se3` everywhere (the reference; for
#: tests and benchmarks).
_COMPILED = True


@dataclass(frozen=True, eq=False)
class Patches:
    """Events of a window cut into a grid of patches, each imaged in its own small frame.

    Attributes
    ----------
    x, y : Tensor (M,)
        Pixels [px] of the kept events (a uniform subsample of the window).
    dt : Tensor (M,)
        ``t - t_mid`` [s] (the window's middle is the reference time).
    patch : Tensor (M,) int64
        The patch of each event (0 <= patch < P).
    offset : Tensor (P, 2)
        Top-left pixel ``(x, y)`` of each patch's frame (the patch plus ``margin``).
    size : (int, int)
        ``(H, W)`` of every patch frame [px].
    margin : int
        Pixels around a patch inside its frame (the largest displacement kept) [px].
    centres : ndarray (P, 2)
        Mean pixel of each patch's events.
    counts : ndarray (P,)
        Events per patch (of the subsample).
    """

    x: torch.Tensor
    y: torch.Tensor
    dt: torch.Tensor
    patch: torch.Tensor
    offset: torch.Tensor
    size: tuple[int, int]
    margin: int
    centres: np.ndarray
    counts: np.ndarray

    @property
    def count(self) -> int:
        return int(self.offset.shape[0])

    def every(self, step: int) -> "Patches":
        """The same patches with every ``step``-th event (centres and counts unchanged)."""
        if step <= 1:
            return self
        return Patches(self.x[::step], self.y[::step], self.dt[::step], self.patch[::step], self.offset, self.size,
                       self.margin, self.centres, self.counts)

    @property
    def compiled(self) -> bool:
        """Whether the compiled kernels take these events (CPU float32 / float64, ``_COMPILED``): then
        :meth:`variances` runs them under autograd, and the objectives below offer ``fun_and_grad`` /
        ``sum_and_gradients`` that run them with no autograd at all."""
        return _COMPILED and self.x.device.type == "cpu" and self.x.dtype in (torch.float32, torch.float64)

    @functools.cached_property
    def kernel_arrays(self) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """``(patch (M,) int64, offset (P, 2) in the events' dtype, (order, starts))``: what the compiled
        kernels read, computed once per event set (:func:`cmax.contrast._patch_kernels.group_by_patch`)."""
        patch = np.ascontiguousarray(self.patch.numpy(), dtype=np.int64)
        offset = np.ascontiguousarray(self.offset.numpy(), dtype=self.x.numpy().dtype)
        return patch, offset, group_by_patch(patch, self.count)

    def variance_work(self, x: np.ndarray, y: np.ndarray, sigma: float) -> _Workspace:
        """The compiled per-patch variances of events at pixels ``x, y`` (M,) (arrays of the events' dtype):
        ``.forward() -> (P,)`` float64, then ``.backward(scale (P,)) -> (dx (M,), dy (M,))`` of
        ``sum_p scale_p Var_p``; ``sigma``: the blur [px]."""
        patch, offset, grouping = self.kernel_arrays
        _check_length("x", x.shape, patch.shape)
        _check_length("y", y.shape, patch.shape)
        return _Workspace(x, y, patch, offset, self.size, sigma, grouping)

    def images(self, x: torch.Tensor, y: torch.Tensor, sigma: float) -> torch.Tensor:
        """Count images (P, H, W) of the events at full-image pixels ``x, y`` (M,), blurred by ``sigma`` [px]."""
        H, W = self.size
        ox, oy = self.offset[self.patch, 0], self.offset[self.patch, 1]
        return blur(accumulate_bilinear_indexed(x - ox, y - oy, None, self.patch, self.count, H, W), sigma)

    def variances(self, x: torch.Tensor, y: torch.Tensor, sigma: float) -> torch.Tensor:
        """``variance(self.images(x, y, sigma))`` (P,): each patch's blurred IWE variance; differentiable.

        CPU float32 / float64 events go through the compiled value and gradient of
        :mod:`cmax.contrast._patch_kernels` (equal to float rounding), anything else through the torch
        operations of :meth:`images`.
        """
        if _COMPILED and x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64) and y.dtype == x.dtype:
            _check_length("x", tuple(x.shape), tuple(self.patch.shape))
            _check_length("y", tuple(y.shape), tuple(self.patch.shape))
            return _PatchVariances.apply(x, y, self.patch, self.offset, self.size, float(sigma))
        return variance(self.images(x, y, sigma))


def _check_length(name: str, shape: tuple[int, ...], want: tuple[int, ...]) -> None:
    """Refuse an array of the wrong shape before a compiled kernel reads it (the kernels do no bounds checks)."""
    if tuple(shape) != tuple(want):
        raise ValueError(f"{name} must have shape {tuple(want)}, got {tuple(shape)}")


def cut_patches(x: torch.Tensor, y: torch.Tensor, dt: torch.Tensor, width: int, height: int, *,
                grid: tuple[int, int], min_events: int, max_events: int, margin: float,
                min_margin_px: int = 8) -> Patches | None:
    """Cut events at pixels ``x, y`` (N,) [px] with ``dt = t - t_ref`` (N,) [s] of a ``width`` x ``height``
    sensor into a ``grid`` (rows, cols) of patches; None when no patch has ``min_events``.

    Every ``N // max_events``-th event is kept (a uniform subsample). ``margin`` is a fraction of the
    patch side (at least ``min_margin_px`` px): how far an event may move inside its patch's frame.
    """
    gh, gw = grid
    step = max(1, len(x) // max_events)
    x, y, dt = x[::step], y[::step], dt[::step]
    cell = ((y * gh / height).long().clamp(0, gh - 1) * gw + (x * gw / width).long().clamp(0, gw - 1))
    counts = torch.bincount(cell, minlength=gh * gw)
    keep = torch.nonzero(counts >= min_events).reshape(-1)
    if keep.numel() == 0:
        return None
    remap = torch.full((gh * gw,), -1, dtype=torch.long)
    remap[keep] = torch.arange(keep.numel())
    patch = remap[cell]
    sel = patch >= 0
    x, y, dt, patch = x[sel], y[sel], dt[sel], patch[sel]
    P = keep.numel()
    ph, pw = math.ceil(height / gh), math.ceil(width / gw)
    pad = max(int(min_margin_px), int(margin * max(ph, pw)))
    offset = torch.stack([(keep % gw).to(x.dtype) * width / gw - pad,
                          (keep // gw).to(x.dtype) * height / gh - pad], 1)
    n = counts[keep].to(x.dtype)
    centres = torch.stack([torch.zeros(P, dtype=x.dtype).index_add_(0, patch, x),
                           torch.zeros(P, dtype=x.dtype).index_add_(0, patch, y)], 1) / n[:, None]
    return Patches(x, y, dt, patch, offset, (ph + 2 * pad, pw + 2 * pad), pad, centres.double().numpy(),
                   n.double().numpy())


@dataclass(frozen=True, eq=False)
class PatchFlowContrast:
    """Minus the summed normalised IWE variances of patches that each move with a constant flow.

    ``J(q) = -sum_p Var(I_p(q_p)) / Var(I_p(0))`` with ``q`` (2P,) each patch's displacement over the
    window [px] (flow times ``T``), the events of patch ``p`` moved by ``-q_p dt / T``
    (:func:`cmax.warp.warp_flow`'s convention). Separable: each patch's term depends on its own flow
    only. Lower is better; differentiable in ``q``.

    Attributes
    ----------
    patches : Patches
    sigma : float
        IWE blur [px].
    T : float
        Window duration [s].
    base : Tensor (P,)
        Variance of each patch's unwarped IWE (no gradient).
    """

    patches: Patches
    sigma: float
    T: float
    base: torch.Tensor

    @classmethod
    def build(cls, patches: Patches, sigma: float, T: float) -> "PatchFlowContrast":
        """The objective of ``patches`` with blur ``sigma`` [px] over a window of ``T`` [s]."""
        with torch.no_grad():
            base = patches.variances(patches.x, patches.y, sigma).clamp(min=1e-12)
        return cls(patches, sigma, T, base)

    def __call__(self, q: torch.Tensor) -> torch.Tensor:
        """``J(q)`` (scalar) of displacements ``q`` (2P,) [px over the window]."""
        patches = self.patches
        x, y, dt, patch = patches.x, patches.y, patches.dt, patches.patch
        flow = q.reshape(patches.count, 2).to(x.dtype) / self.T
        variances = patches.variances(x - flow[patch, 0] * dt, y - flow[patch, 1] * dt, self.sigma)
        return -(variances / self.base).sum()

    def fun_and_grad(self, q: np.ndarray) -> tuple[float, np.ndarray]:
        """``(J(q), dJ/dq (2P,))`` for ``q`` (2P,) float64 [px]: :meth:`__call__` and its autograd gradient,
        computed by the compiled kernels with no autograd when :attr:`Patches.compiled` (the same
        arithmetic in the events' dtype; the sums over events and patches in float64), else through torch."""
        patches = self.patches
        _check_length("q", np.shape(q), (2 * patches.count,))
        if not patches.compiled:   # the reference path: autograd of the torch operations
            params = torch.tensor(np.asarray(q, dtype=np.float64), requires_grad=True)
            value = self(params)
            (grad,) = torch.autograd.grad(value, params)
            return float(value.detach()), grad.numpy().copy()
        x, y, dt = (t.numpy() for t in (patches.x, patches.y, patches.dt))
        patch = patches.kernel_arrays[0]
        dtype = x.dtype
        flow = np.asarray(q, dtype=np.float64).reshape(patches.count, 2).astype(dtype) / dtype.type(self.T)
        moved_x, moved_y = np.empty_like(x), np.empty_like(y)
        shift_by_patch(x, y, dt, patch, flow, moved_x, moved_y)        # x_i - flow_p dt_i
        work = patches.variance_work(moved_x, moved_y, self.sigma)
        base = self.base.double().numpy()
        value = -float(np.sum(work.forward() / base))
        gx, gy = work.backward(-1.0 / base)
        grad = np.empty((patches.count, 2))
        flow_gradient_by_patch(gx, gy, dt, patch, grad)
        return value, grad.reshape(-1) / self.T


@dataclass(frozen=True, eq=False)
class PatchMotionContrast:
    """Normalised IWE variance (P,) of each patch for one se3 twist and per-event inverse depths.

    ``c_p(v, omega, rho) = Var(I_p(v, omega, rho)) / Var(I_p(0))``, the events warped to the window's
    middle by :func:`cmax.warp.warp_se3`. The se3 refinement maximises ``sum_p c_p`` with one inverse
    depth per patch (:class:`cmax.fitting.motion.LocalMotionObjective`); the verdict compares motions
    on it (:mod:`cmax.fitting.quality`). Higher is better; differentiable in ``v``, ``omega``, ``rho``.

    Attributes
    ----------
    patches : Patches
    rays : Tensor (M, 3)
        ``K^-1 (x, y, 1)`` of the patches' events.
    K : Tensor (3, 3)
    sigma : float
        IWE blur [px].
    base : Tensor (P,)
        Variance of each patch's unwarped IWE (no gradient).
    """

    patches: Patches
    rays: torch.Tensor
    K: torch.Tensor
    sigma: float
    base: torch.Tensor

    @classmethod
    def build(cls, patches: Patches, K: torch.Tensor, sigma: float) -> "PatchMotionContrast":
        """The objective of ``patches`` with intrinsics ``K`` (3, 3) [px] and blur ``sigma`` [px]."""
        rays = torch.stack([patches.x, patches.y, torch.ones_like(patches.x)], -1) @ torch.linalg.inv(K).T
        with torch.no_grad():
            base = patches.variances(patches.x, patches.y, sigma).clamp(min=1e-12)
        return cls(patches, rays, K, sigma, base)

    def __call__(self, v: torch.Tensor, omega: torch.Tensor, rho_events: torch.Tensor) -> torch.Tensor:
        """``c_p`` (P,) for ``v`` (3,) [m/s], ``omega`` (3,) [rad/s] and per-event inverse depths (M,) [1/m]."""
        dt = self.patches.dt
        if _COMPILED and compiled_warp_applies(self.rays, dt, v, omega, rho_events):
            x, y = warp_se3_compiled(self.rays, dt, v, omega, rho_events, self.K)
        else:
            x, y = warp_se3(self.rays, dt, v, omega, rho_events, self.K)
        return self.patches.variances(x, y, self.sigma) / self.base

    def sum_and_gradients(self, v: np.ndarray, omega: np.ndarray, rho_events: np.ndarray
                          ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """``sum_p c_p`` and its gradient in ``v`` (3,), ``omega`` (3,) and ``rho_events`` (M,) (float64) for
        ``v`` [m/s], ``omega`` [rad/s] and per-event inverse depths [1/m], all in the events' dtype (the
        values :meth:`__call__` takes). The compiled warp and patch kernels with no autograd (the sums
        in float64); only when :attr:`Patches.compiled`. Equal to ``__call__(...).sum()`` and its
        autograd gradient to float rounding (``tests/test_patch_kernels.py``)."""
        patches = self.patches
        if not patches.compiled:
            raise ValueError("sum_and_gradients needs CPU float32 / float64 events (Patches.compiled)")
        rays, dt, k, dt_max = self.kernel_arrays
        _check_length("rho_events", np.shape(rho_events), dt.shape)
        _check_length("v", np.shape(v), (3,))
        _check_length("omega", np.shape(omega), (3,))
        dtype = rays.dtype
        v64, omega64 = np.asarray(v, dtype).astype(np.float64), np.asarray(omega, dtype).astype(np.float64)
        rho = np.ascontiguousarray(rho_events, dtype=dtype)
        x, y = se3_warp_arrays(rays, dt, v64, omega64, rho, k, dt_max)
        work = patches.variance_work(x, y, self.sigma)
        base = self.base.double().numpy()
        value = float(np.sum(work.forward() / base))
        gx, gy = work.backward(1.0 / base)
        grad_v, grad_omega, grad_rho = se3_warp_gradients(rays, dt, v64, omega64, rho, k, gx, gy, dt_max=dt_max)
        return value, grad_v, grad_omega, grad_rho

    @functools.cached_property
    def kernel_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """``(rays (3, M), dt (M,), k (5,), dt_max)``: the rays (coordinates in rows) and times contiguous in
        the events' dtype, ``K`` as the warp kernels read it (:func:`cmax.contrast._warp_kernels.intrinsics_row`,
        float64), ``max |dt|`` [s]."""
        dt = np.ascontiguousarray(self.patches.dt.numpy())
        return (np.ascontiguousarray(self.rays.numpy().T), dt, intrinsics_row(self.K.double().numpy()),
                float(np.abs(dt).max()) if dt.size else 0.0)

    def depth_free_parts(self, v: torch.Tensor, omega: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The two parts (1, M, 3) of the warp of ``v`` (3,) [m/s], ``omega`` (3,) [rad/s] that do not depend
        on the inverse depth (:func:`cmax.warp.se3_parts`), for :meth:`at_depths`. No gradient."""
        with torch.no_grad():
            return se3_parts(self.rays, self.patches.dt, v, omega)

    def at_depths(self, v: torch.Tensor, omega: torch.Tensor, rho_rows: torch.Tensor,
                  parts: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """``c_p`` (C, P) for one motion (``v`` (3,), ``omega`` (3,) [rad/s]) and each row of per-event inverse depths ``rho_rows`` (C, M) [1/m]:
        the rows of :meth:`__call__` with the depth-free part of the warp (:meth:`depth_free_parts`, or
        ``parts`` when the caller has them for this motion) computed once (a sweep over depths). No gradient."""
        _check_length("each row of rho_rows", tuple(rho_rows.shape[1:]), (len(self.rays),))
        with torch.no_grad():
            rotated, moved = self.depth_free_parts(v, omega) if parts is None else parts
            if self.patches.compiled and rho_rows.dtype == rotated.dtype:
                return self._compiled_rows(rotated, moved, rho_rows)
            rows = []
            for rho in rho_rows:
                x, y = project(rotated + rho[:, None] * moved, self.K)
                rows.append(self.patches.variances(x, y, self.sigma) / self.base)
            return torch.stack(rows)

    def _compiled_rows(self, rotated: torch.Tensor, moved: torch.Tensor, rho_rows: torch.Tensor) -> torch.Tensor:
        """The rows of :meth:`at_depths` by the compiled projection and patch variances (the same values as
        the torch operations, bit for bit: the same operations in the same dtype)."""
        rotated, moved = np.ascontiguousarray(rotated.numpy()), np.ascontiguousarray(moved.numpy())
        dtype = rotated.dtype
        k, zmin = self.kernel_arrays[2].astype(dtype), dtype.type(MIN_PROJECTED_DEPTH)
        rows = []
        for rho in rho_rows:
            x, y = np.empty(rho.shape[0], dtype), np.empty(rho.shape[0], dtype)
            project_at_depth(rotated, moved, np.ascontiguousarray(rho.numpy()), k, zmin, x, y)
            variances = self.patches.variance_work(x, y, self.sigma).forward().astype(dtype)
            rows.append(torch.from_numpy(variances) / self.base)
        return torch.stack(rows)
