"""The depth sweep's cost: per-event normalised votes of the IWE, averaged per node of a depth grid.

For per-event inverse depths (one row per candidate) every event is warped to the reference time
with its own inverse depth, the images of warped events (one per polarity, blurred) are read back
**at each event's own warped position** (:func:`cmax.iwe.sample_bilinear`, the adjoint of the
voting: event i's share of the IWE's energy ``sum I^2``), each event's values are divided by its
largest over the candidates (one vote per event; :func:`vote_scale`), and the votes of the events
that stay inside the image are averaged per node of the depth grid with the grid's own bilinear
weights. :class:`SweepNodeCost` is what the fit's plane sweep (:mod:`cmax.fitting.depth_sweep`)
maximises per node; why each choice: that module's docstring and ``docs/fitting.md``.

It differs from :class:`cmax.contrast.SweepVote` (the same vote as a differentiable objective of a
depth map, for gradient descent): the normaliser is the largest value over the candidates passed in
the same call, not over a fixed sweep; the mean is per node, not per window; events within
``border_px`` of the edge count as outside.

References
----------
H. Rebecq, G. Gallego, E. Mueggler, D. Scaramuzza, "EMVS: Event-based multi-view stereo", IJCV 2018
(the space sweep and its ray-density argmax). G. Gallego, H. Rebecq, D. Scaramuzza, "A unifying
contrast maximization framework for event cameras", CVPR 2018 (the warp and the contrast).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from cmax.iwe import polarity_images, sample_bilinear
from cmax.warp import warp_se3

__all__ = ["SweepNodeCost", "event_scores", "vote_scale", "lower_quantile"]


def event_scores(rays: torch.Tensor, dt: torch.Tensor, on: torch.Tensor, v: torch.Tensor, omega: torch.Tensor,
                 rho: torch.Tensor, K: torch.Tensor, height: int, width: int, sigma: float, border_px: int = 1
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """IWE value (B, N) at each event's warped position for inverse depths ``rho`` (B, N) [1/m], and whether
    the warped event lies at least ``border_px`` px inside the image (B, N) (1.0 / 0.0).

    ``rays`` (N, 3), ``dt`` (1, N) [s], ``on`` (N,) 1.0 for the events imaged in the first polarity image
    (all ones: one image), ``v`` (3,) [m/s], ``omega`` (3,) [rad/s], ``K`` (3, 3), blur ``sigma`` [px].
    """
    B = rho.shape[0]
    x, y = warp_se3(rays, dt, v, omega, rho, K)
    images = polarity_images(x, y, on, height, width, sigma)
    seen = sample_bilinear(images, torch.cat([x, x]), torch.cat([y, y]))
    score = on * seen[:B] + (1.0 - on) * seen[B:]
    inside = ((x >= border_px) & (x <= width - 1 - border_px)
              & (y >= border_px) & (y <= height - 1 - border_px)).to(x.dtype)
    return score, inside


def lower_quantile(values: torch.Tensor, q: float) -> torch.Tensor:
    """The ``q``-quantile of all ``values`` with lower interpolation (the sorted value at ``floor((n - 1) q)``;
    ``q = 0.5`` is :meth:`torch.Tensor.median`'s lower median)."""
    flat = values.reshape(-1).sort().values
    return flat[int((flat.numel() - 1) * q)]


def vote_scale(score: torch.Tensor, inside: torch.Tensor, quantile: float = 0.5) -> torch.Tensor:
    """What each event's IWE values (C, N) are divided by (1, N): its largest over the candidates, or,
    for an event that some candidates push out of the image (``inside`` (C, N) is 0 there), the
    ``quantile`` (0.5: the median) of the largest values of the events that stay inside. Such an event's
    own largest value is taken over the candidates that keep it inside only, mostly far ones: the near
    events at the bottom of a driving window would vote for far depths with full weight
    (``docs/fitting.md``)."""
    peak = (score * inside).max(0, keepdim=True).values
    always = inside.min(0, keepdim=True).values > 0
    typical = lower_quantile(peak[always] if bool(always.any()) else peak, quantile)
    return torch.where(always, peak, typical).clamp(min=1e-12)


@dataclass(frozen=True, eq=False)
class SweepNodeCost:
    """The sweep's cost as a function: per-event inverse depths (C, N) [1/m] -> node costs (C, G).

    The mean, over each node's events (bilinear weights, only the events that stay inside the image),
    of the IWE value at the event divided by the event's :func:`vote_scale` over the C rows of the same
    call (one vote per event: compare candidates within one call). Higher is better.

    Attributes
    ----------
    rays : Tensor (N, 3)
        ``K^-1 (x, y, 1)`` of the events.
    dt : Tensor (1, N)
        ``t_i - t_ref`` [s].
    polarity : Tensor (N,)
        Signed polarity -1/+1.
    v, omega : ndarray (3,)
        Known linear [m/s] and angular [rad/s] velocity, camera frame.
    K : Tensor (3, 3)
    height, width : int
    grid_shape : (gh, gw)
        The depth grid (:class:`cmax.warp.DepthGrid`).
    index, weight : Tensor (N, 4)
        Depth-grid nodes and bilinear weights of each event.
    sigma : float
        IWE blur [px].
    polarity_split : bool
        One image per polarity (True) or one for all events.
    chunk : int
        Candidates warped at once (memory against speed; no effect on the result).
    border_px : int
        Events warped closer than this to the edge [px] count as outside.
    vote_scale_quantile : float
        See :func:`vote_scale`.
    """

    rays: torch.Tensor
    dt: torch.Tensor
    polarity: torch.Tensor
    v: np.ndarray
    omega: np.ndarray
    K: torch.Tensor
    height: int
    width: int
    grid_shape: tuple[int, int]
    index: torch.Tensor
    weight: torch.Tensor
    sigma: float = 1.0
    polarity_split: bool = True
    chunk: int = 8
    border_px: int = 1
    vote_scale_quantile: float = 0.5

    def __call__(self, rho_events: torch.Tensor) -> torch.Tensor:
        """Mean normalised IWE value at each node's events (C, G) for per-event inverse depths (C, N)."""
        dtype = self.rays.dtype
        polarity = self.polarity
        on = (polarity > 0).to(dtype) if self.polarity_split else torch.ones_like(polarity, dtype=dtype)
        v, omega = torch.as_tensor(self.v, dtype=dtype), torch.as_tensor(self.omega, dtype=dtype)
        parts = [event_scores(self.rays, self.dt, on, v, omega, part, self.K, self.height, self.width, self.sigma,
                              self.border_px) for part in rho_events.split(self.chunk)]
        score = torch.cat([p[0] for p in parts])                                     # (C, N)
        inside = torch.cat([p[1] for p in parts])
        score = score / vote_scale(score, inside, self.vote_scale_quantile)          # one vote per event
        C, G = score.shape[0], self.grid_shape[0] * self.grid_shape[1]
        flat_index = self.index.reshape(-1)
        w_in = inside[:, :, None] * self.weight[None]                                # (C, N, 4)
        sums = torch.zeros(C, G, dtype=dtype).index_add_(1, flat_index, (w_in * score[:, :, None]).reshape(C, -1))
        weights = torch.zeros(C, G, dtype=dtype).index_add_(1, flat_index, w_in.reshape(C, -1))
        return sums / weights.clamp(min=1e-6)
