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

import weakref
from dataclasses import dataclass

import numpy as np
import torch

from cmax.contrast._sweep_kernels import event_scores_compiled, node_sums, se3_terms, vote_scale_compiled
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

    On the CPU, with the events, their times, the inverse depths and the grid weights in one float dtype
    and no gradient asked, the cost is computed by the compiled kernels of
    :mod:`cmax.contrast._sweep_kernels` (the same values, to float rounding); otherwise (CUDA, autograd,
    mixed dtypes) by the torch operations of :func:`event_scores`, the reference.

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
        Candidates warped at once by the torch operations (memory against speed; no effect on the result);
        the compiled path warps one at a time.
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

    def __post_init__(self) -> None:
        n, nodes = self.rays.shape[0], self.grid_shape[0] * self.grid_shape[1]
        if tuple(self.rays.shape) != (n, 3) or self.dt.numel() != n or self.polarity.numel() != n:
            raise ValueError(f"rays must be (N, 3) with dt and polarity of N events, got {tuple(self.rays.shape)}, "
                             f"{tuple(self.dt.shape)}, {tuple(self.polarity.shape)}")
        if tuple(self.index.shape) != (n, 4) or tuple(self.weight.shape) != (n, 4):
            raise ValueError(f"index and weight must be (N, 4) = ({n}, 4), got {tuple(self.index.shape)} and "
                             f"{tuple(self.weight.shape)}")
        if n and (int(self.index.min()) < 0 or int(self.index.max()) >= nodes):
            raise ValueError(f"index must hold nodes of the {self.grid_shape} grid (0 <= index < {nodes}), got "
                             f"{int(self.index.min())}..{int(self.index.max())}")

    def __call__(self, rho_events: torch.Tensor) -> torch.Tensor:
        """Mean normalised IWE value at each node's events (C, G) for per-event inverse depths (C, N)."""
        if rho_events.dim() != 2 or rho_events.shape[1] != self.rays.shape[0]:
            raise ValueError(f"rho_events must be (C, N) with N = {self.rays.shape[0]}, got {tuple(rho_events.shape)}")
        if _use_compiled(self, rho_events):
            return self._compiled(rho_events)
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

    def _compiled(self, rho_events: torch.Tensor) -> torch.Tensor:
        """:meth:`__call__` by the compiled kernels of :mod:`cmax.contrast._sweep_kernels` (CPU, one dtype)."""
        rotated, moved = _warp_terms(self.rays, self.dt, self.v, self.omega)
        image_of = ((self.polarity <= 0) if self.polarity_split else torch.zeros_like(self.polarity, dtype=torch.bool))
        score, inside, peak, always = event_scores_compiled(
            rotated, moved, rho_events.detach().contiguous().numpy(),
            image_of.to(torch.int64).numpy(), 2 if self.polarity_split else 1, self.K.detach().cpu().numpy(),
            self.height, self.width, self.sigma, self.border_px)
        scale = vote_scale_compiled(peak, always, self.vote_scale_quantile)            # one vote per event
        sums, weights = node_sums(score, scale, inside, self.index.contiguous().numpy(),
                                  self.weight.contiguous().numpy(), self.grid_shape[0] * self.grid_shape[1])
        return torch.from_numpy(sums) / torch.from_numpy(weights).clamp(min=1e-6)


#: The compiled path of :class:`SweepNodeCost` on CPU float tensors (False: the torch reference everywhere;
#: for tests and benchmarks that compare the two).
_COMPILED = True


#: The last :func:`_warp_terms`: weak references to its rays and times, their versions, dtype, v and omega, and
#: the terms. The whole-range sweep and the refinements of one window share them.
_LAST_TERMS: list = []


def _warp_terms(rays: torch.Tensor, dt: torch.Tensor, v: np.ndarray, omega: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """The depth-independent parts of the se3 warp, (N, 3) each in the dtype of ``rays``
    (:func:`cmax.contrast._sweep_kernels.se3_terms`); the last ones are reused while the same ``rays`` and
    ``dt`` tensors, unchanged, come with the same ``v`` [m/s] and ``omega`` [rad/s] (3,)."""
    dtype = rays.dtype
    v, omega = torch.as_tensor(v, dtype=dtype).detach(), torch.as_tensor(omega, dtype=dtype).detach()
    key = (rays._version, dt._version, dtype, v.numpy().tobytes(), omega.numpy().tobytes())
    last = _LAST_TERMS[0] if _LAST_TERMS else None
    if last is not None and last[0]() is rays and last[1]() is dt and last[2] == key:
        return last[3]
    terms = tuple(part.contiguous().numpy() for part in se3_terms(rays, dt, v, omega))
    _LAST_TERMS[:] = [(weakref.ref(rays), weakref.ref(dt), key, terms)]
    return terms


def _use_compiled(cost: SweepNodeCost, rho: torch.Tensor) -> bool:
    """Whether ``cost`` runs its compiled kernels for ``rho``: CPU tensors, the rays, times, inverse depths and
    grid weights in one dtype (float32 or float64), the times one row of N, int64 node indices, and no
    gradient asked of any of them or of ``v``, ``omega``."""
    rays, dt, index, weight = cost.rays, cost.dt, cost.index, cost.weight
    tensors = (rays, dt, rho, index, weight, cost.polarity, cost.K)
    motion = [t for t in (cost.v, cost.omega) if isinstance(t, torch.Tensor)]
    return (_COMPILED and all(t.device.type == "cpu" for t in tensors + tuple(motion))
            and rays.dtype in (torch.float32, torch.float64)
            and dt.dtype == rho.dtype == weight.dtype == rays.dtype and index.dtype == torch.int64
            and dt.numel() == rays.shape[0] and rho.dim() == 2 and rho.shape[1] == rays.shape[0]
            and not (torch.is_grad_enabled() and any(t.requires_grad for t in tensors + tuple(motion))))
