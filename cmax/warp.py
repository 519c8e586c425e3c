"""Warp models of contrast maximization: constant flow, rotation, and SE(3) with inverse depth.

An event ``e_i = (x_i, y_i, t_i, p_i)`` is moved to a reference time
``t_ref`` by a warp ``W``; the image of the moved events (:mod:`cmax.iwe`) is
sharp when the warp follows the true motion (Gallego et al., CVPR 2018).
Times enter as ``dt_i = t_i - t_ref`` [s]. With the project's convention
``T_w_c(t) = T_w_c(t_ref) se3_exp(xi (t - t_ref))`` a point seen at ``t_i`` in
the camera frame is, in the camera frame of ``t_ref``,

    X_ref = se3_exp(xi dt_i) X_i = R(omega dt_i) X_i + J(omega dt_i) v dt_i.

With ``X_i = ray_i / rho_i`` (``ray = K^-1 (x, y, 1)``, ``rho`` the inverse
z-depth [1/m]) and the projection invariant to scale,

    x_ref ~ K (R(omega dt_i) ray_i + rho_i J(omega dt_i) v dt_i),     (se3, paper eqs. 8-9)
    x_ref ~ K R(omega dt_i) ray_i,                                     (rotation)
    x_ref  = x_i - u dt_i.                                             (flow)

so inverse depth 0 (infinitely far) is allowed. ``rho_i`` is read from a
coarse grid of inverse depths by bilinear interpolation at the event's own
pixel (:class:`DepthGrid`). Rotations are Rodrigues' closed form per event
(:mod:`cmax.geometry_torch`), no matrix exponential. Every function accepts
``dt`` of shape (N,) or (B, N) (B reference times at once) and returns
coordinates of the same shape; everything is differentiable.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch

from cmax.camera import check_intrinsics
from cmax.events import Events
from cmax.geometry_torch import so3_rotate, rodrigues_coefficients

__all__ = [
    "WarpEvents", "DepthGrid", "warp_flow", "warp_rotation", "warp_se3", "se3_parts", "project",
    "MIN_PROJECTED_DEPTH",
]

#: The z of a warped ray (ray z = 1 at the event) is clamped to this; a warp that
#: moves a point to 1/20 of its depth or behind the camera is not a motion of a window.
MIN_PROJECTED_DEPTH = 0.05


def project(points: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pinhole projection of points (..., 3) with K (3, 3); z clamped to :data:`MIN_PROJECTED_DEPTH`."""
    z = points[..., 2].clamp(min=MIN_PROJECTED_DEPTH)
    X, Y = points[..., 0] / z, points[..., 1] / z
    return K[0, 0] * X + K[0, 1] * Y + K[0, 2], K[1, 1] * Y + K[1, 2]


def warp_flow(x: torch.Tensor, y: torch.Tensor, dt: torch.Tensor, flow: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """Constant optical flow: ``x_ref = x - u dt``.

    Parameters
    ----------
    x, y : Tensor, shape (N,)
        Event pixels.
    dt : Tensor, shape (N,) or (B, N)
        ``t_i - t_ref`` [s].
    flow : Tensor, shape (2,)
        ``(u_x, u_y)`` [px/s].

    Returns
    -------
    x_ref, y_ref : Tensor, shape of ``dt`` ((N,) or (B, N))
        The events' pixels [px] at ``t_ref``.

    Examples
    --------
    >>> import torch
    >>> warp_flow(torch.tensor([10.0]), torch.tensor([5.0]), torch.tensor([0.1]), torch.tensor([20.0, -10.0]))
    (tensor([8.]), tensor([6.]))
    """
    return x - flow[0] * dt, y - flow[1] * dt


def warp_rotation(rays: torch.Tensor, dt: torch.Tensor, omega: torch.Tensor, K: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Pure rotation: ``x_ref ~ K R(omega dt) K^-1 x``.

    Parameters
    ----------
    rays : Tensor, shape (N, 3)
        ``K^-1 (x, y, 1)`` of the events.
    dt : Tensor, shape (N,) or (B, N)
        ``t_i - t_ref`` [s].
    omega : Tensor, shape (3,)
        Angular velocity [rad/s], camera frame.
    K : Tensor, shape (3, 3)

    Returns
    -------
    x_ref, y_ref : Tensor, shape of ``dt`` ((N,) or (B, N))
        The events' pixels [px] at ``t_ref``.
    """
    return project(so3_rotate(omega * dt[..., None], rays), K)


def warp_se3(rays: torch.Tensor, dt: torch.Tensor, v: torch.Tensor, omega: torch.Tensor,
             inv_depth: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rigid motion with depth: ``x_ref ~ K (R(omega dt) ray + rho J(omega dt) v dt)``.

    Parameters
    ----------
    rays : Tensor, shape (N, 3)
        ``K^-1 (x, y, 1)`` of the events.
    dt : Tensor, shape (N,) or (B, N)
        ``t_i - t_ref`` [s].
    v, omega : Tensor, shape (3,)
        Linear [m/s] and angular [rad/s] velocity, camera frame.
    inv_depth : Tensor, shape (N,)
        Inverse z-depth ``rho_i`` [1/m] of each event (>= 0).
    K : Tensor, shape (3, 3)

    Returns
    -------
    x_ref, y_ref : Tensor, shape of ``dt`` ((N,) or (B, N))
        The events' pixels [px] at ``t_ref``.
    """
    rotated, moved = se3_parts(rays, dt, v, omega)
    return project(rotated + inv_depth[..., None] * moved, K)


def se3_parts(rays: torch.Tensor, dt: torch.Tensor, v: torch.Tensor, omega: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """The two depth-free parts of :func:`warp_se3`: ``R(omega dt) ray`` and ``J(omega dt) v dt``, each
    (..., N, 3), so that ``warp_se3 = project(rotated + rho * moved, K)`` for any inverse depth ``rho``
    (a sweep over depths computes them once). ``rays`` (N, 3), ``dt`` (N,) or (B, N) [s], ``v`` (3,) [m/s],
    ``omega`` (3,) [rad/s]: shapes and units as :func:`warp_se3`."""
    w = omega * dt[..., None]
    shape = w.shape
    rays = rays.expand(shape)
    A, B, C = rodrigues_coefficients((w * w).sum(-1, keepdim=True))
    wr = torch.linalg.cross(w, rays, dim=-1)
    rotated = rays + A * wr + B * torch.linalg.cross(w, wr, dim=-1)
    u = (v * dt[..., None]).expand(shape)
    wu = torch.linalg.cross(w, u, dim=-1)
    moved = u + B * wu + C * torch.linalg.cross(w, wu, dim=-1)
    return rotated, moved


@dataclass(frozen=True, eq=False)
class DepthGrid:
    """Bilinear interpolation from a coarse (gh, gw) grid of values to pixels.

    Node ``(i, j)`` sits at the centre of cell ``(i, j)`` of a gh x gw partition
    of the image: ``x = (j + 1/2) W / gw - 1/2``, ``y = (i + 1/2) H / gh - 1/2``
    (the convention of ``cv2.resize(..., INTER_LINEAR)``); beyond the outer nodes
    the values are held constant. The interpolation weights of fixed pixels are
    computed once (:meth:`weights`), then :meth:`sample` is a gather. ``shape``: (gh, gw), at most the image's
    ``height`` x ``width`` [px].
    """

    shape: tuple[int, int]
    width: int
    height: int

    def __post_init__(self) -> None:
        gh, gw = self.shape
        if not (isinstance(gh, (int, np.integer)) and isinstance(gw, (int, np.integer)) and gh >= 1 and gw >= 1):
            raise ValueError(f"depth_grid must be two positive integers (rows, cols), got {self.shape}")
        if gh > self.height or gw > self.width:
            raise ValueError(f"depth_grid {self.shape} is finer than the image {self.height}x{self.width} (rows x "
                             "columns; cmax fit: --depth-grid ROWS,COLS)")
        object.__setattr__(self, "shape", (int(gh), int(gw)))

    def weights(self, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Flat node indices (N, 4) int64 and bilinear weights (N, 4) of pixels ``x, y`` (N,)."""
        gh, gw = self.shape
        gx = ((x + 0.5) * gw / self.width - 0.5).clamp(0, gw - 1)
        gy = ((y + 0.5) * gh / self.height - 0.5).clamp(0, gh - 1)
        x0 = gx.floor().clamp(max=max(gw - 2, 0))
        y0 = gy.floor().clamp(max=max(gh - 2, 0))
        fx, fy = gx - x0, gy - y0
        x0, y0 = x0.long(), y0.long()
        x1, y1 = (x0 + 1).clamp(max=gw - 1), (y0 + 1).clamp(max=gh - 1)
        index = torch.stack([y0 * gw + x0, y0 * gw + x1, y1 * gw + x0, y1 * gw + x1], -1)
        weight = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], -1)
        return index, weight

    @staticmethod
    def sample(values: torch.Tensor, index: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
        """Interpolated values (N,) of a grid ``values`` (gh, gw) or (gh*gw,) at the precomputed ``index`` and
        ``weight`` (N, 4) of :meth:`weights`."""
        return (values.reshape(-1)[index] * weight).sum(-1)

    def cell_of(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Flat index (N,) of the cell holding each pixel ``x, y`` (N,) (the nearest node)."""
        gh, gw = self.shape
        j = (x * gw / self.width).long().clamp(0, gw - 1)
        i = (y * gh / self.height).long().clamp(0, gh - 1)
        return i * gw + j

    def resample(self, values: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
        """Grid ``values`` (G,) or (gh, gw) interpolated at the nodes of a grid ``shape`` over the same image:
        flat (shape[0] * shape[1],), the same interpolation as :meth:`sample` (a finer grid's start from a
        coarser one's values)."""
        if tuple(shape) == tuple(self.shape):
            return values.reshape(-1)
        rows, cols = shape
        dtype = values.dtype
        ys, xs = torch.meshgrid((torch.arange(rows, dtype=dtype) + 0.5) * self.height / rows - 0.5,
                                (torch.arange(cols, dtype=dtype) + 0.5) * self.width / cols - 0.5, indexing="ij")
        index, weight = self.weights(xs.reshape(-1), ys.reshape(-1))
        return self.sample(values, index, weight)

    def upsample(self, values: np.ndarray) -> np.ndarray:
        """Dense (H, W) float64 map of grid ``values`` (gh, gw), the same interpolation as :meth:`sample`."""
        values = np.asarray(values, dtype=np.float64).reshape(self.shape)
        index, weight = _pixel_weights(self.shape, self.width, self.height)
        dense = self.sample(torch.from_numpy(values), index, weight)
        return dense.numpy().reshape(self.height, self.width)


@lru_cache(maxsize=2)
def _pixel_weights(shape: tuple[int, int], width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """:meth:`DepthGrid.weights` (H*W, 4) of every pixel of a ``width`` x ``height`` image for a grid of ``shape``,
    float64, row by row; kept for the next call (read only: :meth:`DepthGrid.sample` gathers from them), since a fit
    upsamples its depth and its depth spread on the same grid, and a run its windows of one size."""
    # Kept because the weights were most of upsample's time: at 346x260 about 8 of 10 ms (min of 9, Xeon, 2026-12-05)
    ys, xs = np.mgrid[0:height, 0:width]
    return DepthGrid(shape, width, height).weights(torch.from_numpy(xs.ravel().astype(np.float64)),
                                                   torch.from_numpy(ys.ravel().astype(np.float64)))


@dataclass(frozen=True, eq=False)
class WarpEvents:
    """Events of one window, prepared for warping (torch tensors, one dtype).

    Attributes
    ----------
    x, y : Tensor (N,)
        Pixels (undistorted where the caller undistorted them).
    t : Tensor (N,)
        Seconds since ``t0_us``.
    polarity : Tensor (N,)
        Signed polarity -1/+1.
    rays : Tensor (N, 3)
        ``K^-1 (x, y, 1)``.
    K : Tensor (3, 3)
    width, height : int
    t0_us, t1_us : int
        Window bounds [µs] (``t1_us`` = last event's time).
    """

    x: torch.Tensor
    y: torch.Tensor
    t: torch.Tensor
    polarity: torch.Tensor
    rays: torch.Tensor
    K: torch.Tensor
    width: int
    height: int
    t0_us: int
    t1_us: int

    @property
    def duration_s(self) -> float:
        return (self.t1_us - self.t0_us) * 1e-6

    def __len__(self) -> int:
        return int(self.x.shape[0])

    @classmethod
    def from_events(cls, events: Events, K: object, *, max_events: int | None = None, seed: int = 0,
                    dtype: torch.dtype = torch.float32, pixels: np.ndarray | None = None,
                    dither: bool = True,
                    lens: Callable[[np.ndarray], np.ndarray] | None = None) -> "WarpEvents":
        """Prepare ``events`` (a :class:`cmax.Events`) with intrinsics ``K`` (3, 3).

        ``max_events`` keeps a uniformly random subset (seeded, sorted) when the
        window holds more; ``pixels`` (N, 2) replaces the integer coordinates
        (e.g. undistorted ones from :meth:`cmax.Camera.undistort`). ``dither``
        adds a seeded uniform offset in [-0.5, 0.5) px to each coordinate: an
        event stands for its whole pixel, and without it every warp that keeps
        events on integer positions (zero flow along an axis) gets a spuriously
        high contrast from unsplit bilinear votes. ``seed`` seeds the subset and the dither; ``dtype`` is
        that of the tensors (float32 or float64). ``lens`` maps positions (M, 2) [px] on the sensor, after the
        dither, to the pixels of ``K``'s pinhole (M, 2) [px] (e.g. :meth:`cmax.Camera.undistort_points`, with
        ``pixels`` the events' sensor pixels): an event stands for its sensor pixel's area, dithered there and
        then mapped through the lens; a dithered position the lens cannot map (NaN) takes its pixel centre's.
        """
        K = check_intrinsics(K)
        n = len(events)
        keep = np.arange(n)
        if max_events is not None and n > max_events:
            keep = np.sort(np.random.default_rng(seed).choice(n, max_events, replace=False))
        if pixels is None:
            xy = np.column_stack([events.x[keep], events.y[keep]]).astype(np.float64)
        else:
            xy = np.asarray(pixels, dtype=np.float64)[keep]
        if dither:
            centres, xy = xy, xy + np.random.default_rng([seed, 1]).uniform(-0.5, 0.5, xy.shape)
        else:
            centres = xy
        if lens is not None:
            mapped = np.array(lens(xy), dtype=np.float64)
            unmapped = ~np.isfinite(mapped).all(axis=1)
            if unmapped.any():
                mapped[unmapped] = lens(centres[unmapped])
            xy = mapped
        t0 = int(events.t[0]) if n else 0
        t1 = int(events.t[-1]) if n else 0
        t = (events.t[keep] - t0).astype(np.float64) * 1e-6
        rays = np.column_stack([xy, np.ones(len(xy))]) @ np.linalg.inv(K).T
        as_t = lambda a: torch.from_numpy(np.ascontiguousarray(a)).to(dtype)  # noqa: E731
        return cls(as_t(xy[:, 0]), as_t(xy[:, 1]), as_t(t), as_t(2.0 * events.p[keep] - 1.0), as_t(rays),
                   as_t(K), events.width, events.height, t0, t1)

    def dt(self, reference_fractions: tuple[float, ...]) -> torch.Tensor:
        """``t_i - t_ref`` (R, N) [s] for R reference times at ``reference_fractions`` of the window (0 = start,
        1 = end)."""
        refs = torch.tensor([f * self.duration_s for f in reference_fractions], dtype=self.t.dtype)
        return self.t[None, :] - refs[:, None]
