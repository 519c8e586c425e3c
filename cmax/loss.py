"""The batched contrast loss: :func:`cmax.fit`'s se3 objective for B windows at once, for training networks.

For each window ``b`` of a batch the network gives an inverse-depth map
``rho_b`` (1, h, w) [1/m] and a twist ``xi_b = (v_b [m/s], omega_b [rad/s])``.
The loss of window ``b`` is the objective that :class:`cmax.fitting.stages.SE3Model`
minimises inside :func:`cmax.fit` (the same primitives, in the same order):

    L_b = - C_b(warped) / C_b(unwarped) + collapse_weight * deformation_b,

where ``C_b`` is the mean over reference times (fractions ``references`` of
the window) of the contrast (variance by default) of the blurred image of
warped events (:mod:`cmax.iwe`), events warped by :func:`cmax.warp.warp_se3`
with the inverse depth read at each event's pixel through
:class:`cmax.warp.DepthGrid`, and ``deformation_b`` is Shiba et al.'s guard
against event collapse (:func:`cmax.objectives.deformation`) on the 9 x 12
probe lattice that ``cmax.fit`` uses. The paper's ``L_contrast`` (EvtSlowTV
eq. 12, minus the IWE variance) is this loss with the normalisation by the
unwarped events' contrast (dimensionless, about -1 for no motion) and the
guard.

The events of a batch are concatenated with a batch index
(:class:`EventBatch`); every window has its own intrinsics and duration;
the images of all windows and reference times are built in one
``index_add`` (:func:`cmax.iwe.accumulate_bilinear_indexed`).

References
----------
G. Gallego, H. Rebecq, D. Scaramuzza, "A unifying contrast maximization
framework for event cameras", CVPR 2018, doi:10.1109/CVPR.2018.00407.
S. Shiba, Y. Aoki, G. Gallego, "Event collapse in contrast maximization
frameworks", Sensors 2022, doi:10.3390/s22145190.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch

from cmax.iwe import accumulate_bilinear_indexed, blur
from cmax.objectives import contrast_of_images, deformation
from cmax.warp import DepthGrid, WarpEvents, warp_se3

__all__ = ["EventBatch", "ContrastLoss", "contrast_loss", "contrast_loss_terms"]

#: Probe times of the deformation guard, in units of the window duration (as in ``cmax.fit``).
_PROBE_TIMES = (-1.0, -0.5, 0.5, 1.0)


@dataclass(frozen=True, eq=False)
class EventBatch:
    """Events of B windows, concatenated, each with the index of its window.

    Attributes
    ----------
    x, y : Tensor (N,)
        Pixel coordinates [px] (possibly dithered / undistorted).
    t : Tensor (N,)
        Seconds since the start of the event's window.
    polarity : Tensor (N,)
        Signed polarity -1/+1.
    batch_index : Tensor (N,) int64
        Window of each event, ``0 <= b < count``.
    duration_s : Tensor (B,)
        Duration of each window [s] (its first to its last event).
    count : int
        Number of windows B.
    width, height : int
        Sensor size shared by the windows [px].
    """

    x: torch.Tensor
    y: torch.Tensor
    t: torch.Tensor
    polarity: torch.Tensor
    batch_index: torch.Tensor
    duration_s: torch.Tensor
    count: int
    width: int
    height: int

    def __len__(self) -> int:
        return int(self.x.shape[0])

    @classmethod
    def from_windows(cls, windows: Sequence[WarpEvents]) -> "EventBatch":
        """Concatenate prepared windows (:meth:`cmax.warp.WarpEvents.from_events`) of one sensor size."""
        if not windows or not all(isinstance(w, WarpEvents) for w in windows):
            raise TypeError("windows must be a non-empty sequence of cmax.warp.WarpEvents")
        size = (windows[0].width, windows[0].height)
        for i, w in enumerate(windows):
            if (w.width, w.height) != size:
                raise ValueError(f"windows[{i}] is {w.width}x{w.height}, windows[0] is {size[0]}x{size[1]}")
        lengths = torch.tensor([len(w) for w in windows])
        index = torch.repeat_interleave(torch.arange(len(windows)), lengths)
        cat = lambda name: torch.cat([getattr(w, name) for w in windows])  # noqa: E731
        duration = torch.tensor([(w.t1_us - w.t0_us) * 1e-6 for w in windows], dtype=torch.float64)
        return cls(cat("x"), cat("y"), cat("t"), cat("polarity"), index, duration.to(windows[0].x.dtype),
                   len(windows), size[0], size[1])

    @classmethod
    def from_padded(cls, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, polarity: torch.Tensor,
                    valid: torch.Tensor, duration_s: torch.Tensor, *, width: int, height: int) -> "EventBatch":
        """From padded (B, Nmax) tensors (a collated data loader batch) and a (B, Nmax) bool mask of real events.

        ``polarity`` is signed (-1/+1); ``t`` in seconds since each window's start;
        ``duration_s`` (B,).
        """
        if x.dim() != 2 or not (x.shape == y.shape == t.shape == polarity.shape == valid.shape):
            raise ValueError(f"x, y, t, polarity, valid must share one shape (B, Nmax), got {tuple(x.shape)}, "
                             f"{tuple(y.shape)}, {tuple(t.shape)}, {tuple(polarity.shape)}, {tuple(valid.shape)}")
        if valid.dtype != torch.bool:
            raise TypeError(f"valid must be a bool tensor, got {valid.dtype}")
        if duration_s.shape != (x.shape[0],):
            raise ValueError(f"duration_s must have shape ({x.shape[0]},), got {tuple(duration_s.shape)}")
        index = torch.arange(x.shape[0], device=x.device)[:, None].expand_as(x)
        return cls(x[valid], y[valid], t[valid], polarity[valid], index[valid], duration_s.to(x.dtype),
                   int(x.shape[0]), int(width), int(height))


@dataclass(frozen=True)
class ContrastLoss:
    """Settings of :func:`contrast_loss` (the defaults are :class:`cmax.fit`'s, ``FitSettings``).

    Attributes
    ----------
    references : tuple of float
        Reference times as fractions of each window (0 = first event, 1 = last).
    sigma : float
        Gaussian blur of the IWEs [px].
    kind : {"variance", "gradient"}
        The contrast function (:data:`cmax.objectives.CONTRASTS`).
    collapse_weight : float
        Weight of the deformation guard (0 switches it off).
    """

    references: tuple[float, ...] = (0.0, 0.5, 1.0)
    sigma: float = 1.0
    kind: str = "variance"
    collapse_weight: float = 0.1

    def __call__(self, events: EventBatch, inverse_depth: torch.Tensor, twist: torch.Tensor,
                 K: torch.Tensor) -> torch.Tensor:
        return contrast_loss(events, inverse_depth, twist, K, references=self.references, sigma=self.sigma,
                             kind=self.kind, collapse_weight=self.collapse_weight)


def _check(events: EventBatch, inverse_depth: torch.Tensor, twist: torch.Tensor, K: torch.Tensor) -> None:
    if not isinstance(events, EventBatch):
        raise TypeError(f"events must be a cmax.loss.EventBatch, got {type(events).__name__}")
    B = events.count
    if inverse_depth.dim() != 4 or inverse_depth.shape[:2] != (B, 1):
        raise ValueError(f"inverse_depth must have shape ({B}, 1, h, w), got {tuple(inverse_depth.shape)}")
    if twist.shape != (B, 6):
        raise ValueError(f"twist must have shape ({B}, 6) (v m/s, omega rad/s), got {tuple(twist.shape)}")
    if K.shape != (B, 3, 3):
        raise ValueError(f"K must have shape ({B}, 3, 3), got {tuple(K.shape)}")
    if len(events) == 0:
        raise ValueError("events: the batch holds no events")


def _project_each(points_x: torch.Tensor, points_y: torch.Tensor, K: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised coordinates (R, N) to pixels with per-point K (N, 3, 3), in :func:`cmax.warp.project`'s order."""
    return (K[:, 0, 0] * points_x + K[:, 0, 1] * points_y + K[:, 0, 2], K[:, 1, 1] * points_y + K[:, 1, 2])


def _warp(rays: torch.Tensor, dt: torch.Tensor, twist: torch.Tensor, rho: torch.Tensor, K_each: torch.Tensor
          ) -> tuple[torch.Tensor, torch.Tensor]:
    """``warp_se3`` with per-point twists (N, 6) and intrinsics (N, 3, 3); dt (R, N)."""
    identity = torch.eye(3, dtype=rays.dtype, device=rays.device)
    xn, yn = warp_se3(rays, dt, twist[:, :3], twist[:, 3:], rho, identity)
    return _project_each(xn, yn, K_each)


def _contrast_per_window(x: torch.Tensor, y: torch.Tensor, batch_index: torch.Tensor, count: int,
                         height: int, width: int, sigma: float, kind: str) -> torch.Tensor:
    """Mean over the R rows of the contrast of each window's image: x, y (R, N) -> (B,)."""
    R = x.shape[0]
    image_index = (torch.arange(R, device=x.device)[:, None] * count + batch_index[None, :]).reshape(-1)
    images = blur(accumulate_bilinear_indexed(x.reshape(-1), y.reshape(-1), None, image_index, R * count,
                                              height, width), sigma)
    return contrast_of_images(images, kind).view(R, count).mean(0)


def _probe_deformation(inverse_depth: torch.Tensor, twist: torch.Tensor, K: torch.Tensor,
                       duration_s: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """The deformation guard (B,) on ``cmax.fit``'s 9 x 12 probe lattice of each window."""
    B, dtype = twist.shape[0], twist.dtype
    ys, xs = torch.meshgrid(torch.linspace(0.1, 0.9, 9, dtype=dtype) * height,
                            torch.linspace(0.1, 0.9, 12, dtype=dtype) * width, indexing="ij")
    pixels = torch.stack([xs, ys, torch.ones_like(xs)], -1).reshape(-1, 3)
    P = pixels.shape[0]
    rays = torch.einsum("pk,bjk->bpj", pixels, torch.linalg.inv(K)).reshape(-1, 3)      # (B*P, 3)
    grid = DepthGrid(tuple(inverse_depth.shape[-2:]), width, height)
    index, weight = grid.weights(xs.reshape(-1), ys.reshape(-1))
    rho = (inverse_depth.reshape(B, -1)[:, index] * weight).sum(-1).reshape(-1)        # (B*P,)
    times = torch.tensor(_PROBE_TIMES, dtype=dtype)[:, None] * duration_s.to(dtype).repeat_interleave(P)[None]
    each = torch.arange(B).repeat_interleave(P)
    x1, y1 = _warp(rays, times, twist[each], rho, K[each])
    x1, y1 = x1.view(len(_PROBE_TIMES), B, *xs.shape), y1.view(len(_PROBE_TIMES), B, *xs.shape)
    return torch.stack([deformation(xs, ys, x1[:, b], y1[:, b]) for b in range(B)])


def contrast_loss_terms(
    events: EventBatch, inverse_depth: torch.Tensor, twist: torch.Tensor, K: torch.Tensor, *,
    references: tuple[float, ...] = (0.0, 0.5, 1.0), sigma: float = 1.0, kind: str = "variance",
    collapse_weight: float = 0.1,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The two terms of :func:`contrast_loss` per window: normalised contrast (B,) and deformation (B,).

    Parameters and shapes as :func:`contrast_loss`; a window without events
    has contrast 0 and baseline 0 and gets a normalised contrast of 0.
    """
    _check(events, inverse_depth, twist, K)
    dtype = events.x.dtype
    twist, K, inverse_depth = twist.to(dtype), K.to(dtype), inverse_depth.to(dtype)
    B, H, W, b = events.count, events.height, events.width, events.batch_index
    K_each = K[b]
    ones = torch.ones_like(events.x)
    rays = torch.einsum("nij,nj->ni", torch.linalg.inv(K)[b], torch.stack([events.x, events.y, ones], -1))
    fractions = torch.tensor(references, dtype=torch.float64)
    refs = (fractions[:, None] * events.duration_s.to(torch.float64)[None, :]).to(dtype)   # (R, B)
    dt = events.t[None, :] - refs[:, b]                                                   # (R, N)
    grid = DepthGrid(tuple(inverse_depth.shape[-2:]), W, H)
    index, weight = grid.weights(events.x, events.y)
    G = inverse_depth.shape[-2] * inverse_depth.shape[-1]
    rho = DepthGrid.sample(inverse_depth.reshape(-1), index + (b * G)[:, None], weight)
    x, y = _warp(rays, dt, twist[b], rho, K_each)
    with torch.no_grad():
        baseline = _contrast_per_window(events.x[None], events.y[None], b, B, H, W, sigma, kind)
    contrast = _contrast_per_window(x, y, b, B, H, W, sigma, kind)
    normalised = torch.where(baseline > 0, contrast / torch.where(baseline > 0, baseline, 1.0), 0.0)
    if collapse_weight > 0:
        guard = _probe_deformation(inverse_depth, twist, K, events.duration_s, W, H)
    else:
        guard = torch.zeros(B, dtype=dtype)
    return normalised, guard


def contrast_loss(
    events: EventBatch, inverse_depth: torch.Tensor, twist: torch.Tensor, K: torch.Tensor, *,
    references: tuple[float, ...] = (0.0, 0.5, 1.0), sigma: float = 1.0, kind: str = "variance",
    collapse_weight: float = 0.1, reduction: str = "mean",
) -> torch.Tensor:
    """``cmax.fit``'s se3 objective (lower is better) of B windows, differentiable in depth and twist.

    Parameters
    ----------
    events : EventBatch
        N events of B windows with their batch index.
    inverse_depth : Tensor, shape (B, 1, h, w)
        Inverse z-depth [1/m] of each window at its reference time, on any grid
        up to the sensor size (read at each event's pixel by
        :class:`cmax.warp.DepthGrid`'s bilinear interpolation; ``h, w = H, W``
        is a dense map).
    twist : Tensor, shape (B, 6)
        ``(v [m/s], omega [rad/s])`` per window, camera frame.
    K : Tensor, shape (B, 3, 3)
        Intrinsics [px] per window.
    references, sigma, kind, collapse_weight
        As :class:`cmax.fitting.FitSettings` (``contrast`` is ``kind``).
    reduction : {"mean", "none"}
        The batch mean (a scalar) or the per-window losses (B,).

    Returns
    -------
    Tensor, shape () or (B,)
        ``-contrast(warped) / contrast(unwarped) + collapse_weight * deformation``.

    Examples
    --------
    >>> ev = WarpEvents.from_events(window.events, window.K)             # doctest: +SKIP
    >>> loss = contrast_loss(EventBatch.from_windows([ev]), rho, xi, K)  # doctest: +SKIP
    """
    if reduction not in ("mean", "none"):
        raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")
    normalised, guard = contrast_loss_terms(events, inverse_depth, twist, K, references=references, sigma=sigma,
                                            kind=kind, collapse_weight=collapse_weight)
    per_window = -normalised + collapse_weight * guard if collapse_weight > 0 else -normalised
    return per_window.mean() if reduction == "mean" else per_window
