"""Depth of a window with a known motion: a plane sweep of the contrast, aggregated on the depth grid.

For every candidate inverse depth ``rho_k`` (uniform in inverse depth over the
``depth_range`` of :class:`cmax.FitSettings`) all events are warped to the
window's middle with that one depth, and the images of warped events (one per
polarity, blurred) are read back **at each event's own warped position**
(:func:`cmax.iwe.sample_bilinear`, the adjoint of the voting). That value is
event i's share of the IWE's energy ``sum(I^2)`` at depth ``rho_k``: high when
the events that share its depth line up with it. The shares are averaged per
node of the depth grid with the grid's own bilinear weights, giving a cost
volume ``S[k, node]``, and the depth of a node is where its curve peaks.

What makes the sweep unbiased:

* each event is scored against the *whole* image, so no vote is lost at the
  edge of a patch, and only events whose warp stays inside the image enter a
  node's mean (an event pushed out of the image says nothing about its depth;
  counting it as 0 biased nodes near the border toward depths that keep
  events inside, i.e. far ones);
* the mean, not the sum, is taken per node, so a candidate that moves votes
  between nodes cannot win by the count of events it gathers;
* polarities are imaged apart (an ON edge and the OFF edge behind it
  blur into each other when merged).

Nodes with few events or flat curves borrow from their neighbours: each
node's curve is normalised to [0, 1], weighted by its confidence (square root
of its events times the relative height of its peak), and a 3x3 weighted sum
of neighbouring curves is taken before the arg-max, refined by a parabola
through the three samples around it. This is the depth initialiser of every
se3 fit and, with a known pose, the depth itself.

References
----------
G. Gallego, H. Rebecq, D. Scaramuzza, "A unifying contrast maximization
framework for event cameras", CVPR 2018. H. Rebecq, G. Gallego, E. Mueggler,
D. Scaramuzza, "EMVS: Event-based multi-view stereo", IJCV 2018 (the space
sweep and its ray-density argmax).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from cmax.iwe import polarity_images, sample_bilinear
from cmax.warp import warp_se3

__all__ = ["DepthSweep", "sweep_inverse_depth", "relative_sweep_cost", "node_cost_function"]


@dataclass(frozen=True, eq=False)
class DepthSweep:
    """Result of :func:`sweep_inverse_depth`.

    Attributes
    ----------
    inverse_depth : ndarray (G,)
        Inverse depth [1/m] of each grid node (flat, row-major).
    candidates : ndarray (C,)
        The swept inverse depths [1/m].
    cost : ndarray (C, G)
        Mean IWE value at the nodes' events, per candidate (before aggregation).
    confidence : ndarray (G,)
        ``sqrt(events) * (max - min) / max`` of each node's curve (0: no events).
    """

    inverse_depth: np.ndarray
    candidates: np.ndarray
    cost: np.ndarray
    confidence: np.ndarray


def _event_scores(rays, dt, on, v, omega, rho, K, height, width, sigma):
    """IWE value at each event's warped position for inverse depths ``rho`` (B, N): (B, N) and inside."""
    B = rho.shape[0]
    x, y = warp_se3(rays, dt, v, omega, rho, K)
    images = polarity_images(x, y, on, height, width, sigma)
    seen = sample_bilinear(images, torch.cat([x, x]), torch.cat([y, y]))
    score = on * seen[:B] + (1.0 - on) * seen[B:]
    inside = ((x >= 1) & (x <= width - 2) & (y >= 1) & (y <= height - 2)).to(x.dtype)
    return score, inside


def sweep_inverse_depth(
    rays: torch.Tensor, dt: torch.Tensor, polarity: torch.Tensor, v: np.ndarray, omega: np.ndarray,
    K: torch.Tensor, *, height: int, width: int, grid_shape: tuple[int, int], index: torch.Tensor,
    weight: torch.Tensor, rho_range: tuple[float, float], candidates: int = 48, sigma: float = 1.0,
    polarity_split: bool = True, aggregation: float = 0.5, refinements: tuple[float, ...] = (0.3,),
    refine_candidates: int = 13, chunk: int = 8,
) -> DepthSweep:
    """Per-node inverse depth of a window with known twist, by a sweep of the contrast.

    Parameters
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
    index, weight : Tensor (N, 4)
        Grid nodes and bilinear weights of each event (:meth:`cmax.warp.DepthGrid.weights`).
    rho_range : (float, float)
        Smallest and largest inverse depth [1/m].
    candidates : int
        Inverse depths swept, uniform in ``rho_range``.
    sigma : float
        IWE blur [px].
    polarity_split : bool
        One image per polarity (True) or one for all events.
    aggregation : float
        Weight of the 8 neighbours of a node in the 3x3 aggregation (0: none).
    refinements : tuple of float
        Half-widths (log of a factor) of relative sweeps after the first:
        every event's inverse depth is scaled by ``exp(step)``, steps in
        ``[-span, span]``, so the events of the other nodes stay in focus.
    refine_candidates : int
        Steps of each relative sweep.
    chunk : int
        Candidates warped at once (memory against speed).

    Returns
    -------
    DepthSweep
    """
    dtype = rays.dtype
    G = grid_shape[0] * grid_shape[1]
    rhos = torch.linspace(float(rho_range[0]), float(rho_range[1]), candidates, dtype=dtype)
    N = rays.shape[0]
    score = node_cost_function(rays, dt, polarity, v, omega, K, height=height, width=width, grid_shape=grid_shape,
                               index=index, weight=weight, sigma=sigma, polarity_split=polarity_split, chunk=chunk)
    with torch.no_grad():
        S = score(rhos[:, None].expand(-1, N))                                   # (C, G)
        node_events = torch.zeros(G, dtype=dtype).index_add_(0, index.reshape(-1), weight.reshape(-1))
        rho, confidence = _aggregate_argmax(S, rhos, node_events, grid_shape, aggregation)
        for span in refinements:  # relative sweeps around the current grid: the other events stay in focus
            steps = torch.linspace(-span, span, refine_candidates, dtype=dtype)
            base = (rho[index] * weight).sum(-1)                                  # (N,)
            S_rel = relative_sweep_cost(score, base, steps)
            step, _ = _aggregate_argmax(S_rel, steps, node_events, grid_shape, aggregation)
            rho = (rho * torch.exp(step)).clamp(float(rhos[0]), float(rhos[-1]))
    return DepthSweep(rho.numpy().astype(np.float64), rhos.numpy().astype(np.float64),
                      S.numpy(), confidence.numpy())


def relative_sweep_cost(node_cost, base_inverse_depth: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
    """Node cost curves (C, G) when every event's inverse depth is scaled by ``exp(step)``.

    ``node_cost`` maps per-event inverse depths (C, N) to (C, G) (the mean IWE
    value at each node's events); ``base_inverse_depth`` (N,) [1/m] is the
    current per-event inverse depth and ``steps`` (C,) the log factors. All
    events move together, so a node's neighbours stay in focus around the
    base: this is the refinement of :func:`sweep_inverse_depth`, and with the
    true per-event depth as the base it measures where the objective itself
    puts each node (``benchmarks/cmax_limits.py``).
    """
    return node_cost(base_inverse_depth[None] * torch.exp(steps)[:, None])


def node_cost_function(rays: torch.Tensor, dt: torch.Tensor, polarity: torch.Tensor, v: np.ndarray,
                       omega: np.ndarray, K: torch.Tensor, *, height: int, width: int, grid_shape: tuple[int, int],
                       index: torch.Tensor, weight: torch.Tensor, sigma: float = 1.0, polarity_split: bool = True,
                       chunk: int = 8):
    """The sweep's cost as a function: per-event inverse depths (C, N) [1/m] -> node costs (C, G).

    Arguments as in :func:`sweep_inverse_depth`; the result is the mean IWE
    value (one image per polarity, blur ``sigma``) at each node's events.
    """
    dtype = rays.dtype
    on = (polarity > 0).to(dtype) if polarity_split else torch.ones_like(polarity, dtype=dtype)
    v_t, om_t = torch.as_tensor(v, dtype=dtype), torch.as_tensor(omega, dtype=dtype)
    G = grid_shape[0] * grid_shape[1]
    return lambda rho_events: _node_cost(  # noqa: E731
        rays, dt, on, v_t, om_t, rho_events, K, height, width, sigma, index, weight, G, chunk)


def _node_cost(rays, dt, on, v, omega, rho_events, K, height, width, sigma, index, weight, G, chunk):
    """Mean IWE value at each node's events (C, G) for per-event inverse depths (C, N)."""
    flat_index = index.reshape(-1)
    sums, weights = [], []
    for part in rho_events.split(chunk):
        score, inside = _event_scores(rays, dt, on, v, omega, part, K, height, width, sigma)
        B = part.shape[0]
        w_in = inside[:, :, None] * weight[None]                                   # (B, N, 4)
        sums.append(torch.zeros(B, G, dtype=rays.dtype).index_add_(
            1, flat_index, (w_in * score[:, :, None]).reshape(B, -1)))
        weights.append(torch.zeros(B, G, dtype=rays.dtype).index_add_(1, flat_index, w_in.reshape(B, -1)))
    return torch.cat(sums) / torch.cat(weights).clamp(min=1e-6)


def _aggregate_argmax(S, values, node_events, grid_shape, aggregation):
    """Confidence-weighted 3x3 aggregation of normalised node curves, then the parabolic arg-max."""
    gh, gw = grid_shape
    top, bottom = S.max(0).values, S.min(0).values
    confidence = node_events.sqrt() * (top - bottom) / top.clamp(min=1e-12)
    normalised = (S - bottom) / (top - bottom).clamp(min=1e-12) * confidence
    kernel = torch.full((3, 3), float(aggregation), dtype=S.dtype)
    kernel[1, 1] = 1.0
    A = torch.nn.functional.conv2d(normalised.view(-1, 1, gh, gw), kernel.view(1, 1, 3, 3), padding=1)
    return _parabolic_argmax(A.view(-1, gh * gw), values), confidence


def _parabolic_argmax(A: torch.Tensor, rhos: torch.Tensor) -> torch.Tensor:
    """Arg-max along dim 0 of (C, G), refined by a parabola through its neighbours (clamped to the range)."""
    C, G = A.shape
    k = A.argmax(0)
    if C < 3:
        return rhos[k]
    i = k.clamp(1, C - 2)
    cols = torch.arange(G)
    a, b, c = A[i - 1, cols], A[i, cols], A[i + 1, cols]
    curvature = a - 2 * b + c
    offset = torch.where(curvature < 0, 0.5 * (a - c) / curvature.clamp(max=-1e-12), torch.zeros_like(b))
    rho = rhos[i] + offset.clamp(-0.5, 0.5) * (rhos[1] - rhos[0])
    rho = torch.where(k == 0, rhos[0], torch.where(k == C - 1, rhos[-1], rho))
    return rho
