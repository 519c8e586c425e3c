"""Depth of a window with a known motion: a plane sweep of the contrast, aggregated on the depth grid.

For every candidate inverse depth ``rho_k`` (uniform in inverse depth over the
``depth_range`` of :class:`cmax.FitSettings`) all events are warped to the
window's middle with that one depth, and the images of warped events (one per
polarity, blurred) are read back **at each event's own warped position**
(:func:`cmax.iwe.sample_bilinear`, the adjoint of the voting). That value is
event i's share of the IWE's energy ``sum(I^2)`` at depth ``rho_k``: high when
the events that share its depth line up with it. The shares are averaged per
node of the depth grid with the grid's own bilinear weights, giving a cost
volume ``S[k, node]``, and the depth of a node is where its curve peaks. The
cost itself (warp, votes, normalisation, per-node mean) is the contrast core's
:class:`cmax.contrast.SweepNodeCost`; this module is the search over it.

What makes the sweep unbiased:

* each event is scored against the *whole* image, so no vote is lost at the
  edge of a patch, and only events whose warp stays inside the image enter a
  node's mean (an event pushed out of the image says nothing about its depth;
  counting it as 0 biased nodes near the border toward depths that keep
  events inside, i.e. far ones);
* each event's values are divided by its largest over the candidates, so every
  event has one vote: otherwise a node that straddles a depth edge follows
  the surface whose events pile up highest (a dense, fast edge), not the one
  most of its events belong to (an event that some candidates push out of the
  image is divided by the typical largest value instead, :func:`cmax.contrast.sweep.vote_scale`);
* the mean, not the sum, is taken per node, so a candidate that moves votes
  between nodes cannot win by the count of events it gathers;
* polarities are imaged apart (an ON edge and the OFF edge behind it
  blur into each other when merged).

Nodes with few events or flat curves borrow from their neighbours: each
node's curve is normalised to [0, 1] and weighted by its confidence (square
root of its events times the relative height of its peak), and the depths of
all nodes are chosen together by semi-global matching on the grid
(Hirschmüller 2008: four scan-line passes, a small penalty for a step of one
candidate between neighbouring nodes and a large one for a jump), then
refined by a parabola through the three samples around each node's minimum.

Coarse to fine: the sweep over the whole depth range runs on a grid
``coarsening`` times coarser than the depth grid (enough events per node to
see a peak), its depths are interpolated onto the depth grid, and the
relative refinements run there, so the depth grid resolves depth edges the
coarse one blends. This is the depth initialiser of every se3 fit and, with a
known pose, the depth itself.

References
----------
G. Gallego, H. Rebecq, D. Scaramuzza, "A unifying contrast maximization
framework for event cameras", CVPR 2018. H. Rebecq, G. Gallego, E. Mueggler,
D. Scaramuzza, "EMVS: Event-based multi-view stereo", IJCV 2018 (the space
sweep and its ray-density argmax). H. Hirschmüller, "Stereo processing by
semiglobal matching and mutual information", IEEE TPAMI 30(2), 2008.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from cmax.contrast.sweep import SweepNodeCost
from cmax.warp import DepthGrid

__all__ = ["DepthSweep", "sweep_inverse_depth", "sweep_candidates", "relative_sweep_cost", "node_cost_function",
           "coarse_grid_shape"]


@dataclass(frozen=True, eq=False)
class DepthSweep:
    """Result of :func:`sweep_inverse_depth`.

    Attributes
    ----------
    inverse_depth : ndarray (G,)
        Inverse depth [1/m] of each node of the depth grid (flat, row-major).
    candidates : ndarray (C,)
        The swept inverse depths [1/m].
    coarse_shape : (int, int)
        The grid the sweep over the whole range ran on.
    cost : ndarray (C, Gc)
        Mean normalised IWE value at the coarse nodes' events, per candidate.
    confidence : ndarray (Gc,)
        ``sqrt(events) * (max - min) / max`` of each coarse node's curve (0: no events).
    """

    inverse_depth: np.ndarray
    candidates: np.ndarray
    coarse_shape: tuple[int, int]
    cost: np.ndarray
    confidence: np.ndarray


def sweep_candidates(rho_range: tuple[float, float], count: int, reach: float) -> np.ndarray:
    """The inverse depths [1/m] of the whole-range sweep: ``count`` uniform over ``rho_range`` (uniform in parallax),
    and, at its far end, where the uniform ones lie further apart than the relative refinement reaches
    (a factor ``exp(reach)`` either way), a geometric sequence of ratio ``exp(reach)`` from the far end up to
    where the uniform spacing is finer; sorted, (C,) float64.

    Uniform candidates alone leave far depths unreachable over a wide range: over 0.5-200 m 36 of them jump from
    200 m to 16 m, and a relative refinement of 35% either way puts a tree at 30 m at 148 m or 22 m.

    >>> sweep_candidates((0.5, 1.0), 6, 0.3).round(3).tolist()        # a narrow range: the uniform ones alone
    [0.5, 0.6, 0.7, 0.8, 0.9, 1.0]
    >>> sweep_candidates((0.005, 2.0), 3, 0.3)[:4].round(4).tolist()  # 0.5-200 m: every 35% at the far end
    [0.005, 0.0067, 0.0091, 0.0123]
    """
    low, high = float(rho_range[0]), float(rho_range[1])
    uniform = np.linspace(low, high, int(count))
    if reach <= 0 or count < 2:
        return uniform
    ratio, step = math.exp(float(reach)), (high - low) / (int(count) - 1)
    top = min(high, step / (ratio - 1.0))                    # beyond it, uniform steps are under a factor `ratio`
    if top <= low:
        return uniform
    far = low * ratio ** np.arange(1, math.ceil(math.log(top / low) / reach) + 1)
    return np.unique(np.concatenate([uniform, far[far < high]]))


def coarse_grid_shape(grid_shape: tuple[int, int], coarsening: int) -> tuple[int, int]:
    """The grid ``coarsening`` times coarser than ``grid_shape`` (rounded up, at least 1 x 1)."""
    return tuple(max(1, math.ceil(n / coarsening)) for n in grid_shape)


def sweep_inverse_depth(
    rays: torch.Tensor, dt: torch.Tensor, polarity: torch.Tensor, v: np.ndarray, omega: np.ndarray,
    K: torch.Tensor, *, height: int, width: int, grid_shape: tuple[int, int], index: torch.Tensor,
    weight: torch.Tensor, rho_range: tuple[float, float], candidates: int = 48, sigma: float = 1.0,
    polarity_split: bool = True, smoothness: tuple[float, float] = (0.1, 1.0), coarsening: int = 2,
    refinements: tuple[float, ...] = (0.3,), refine_candidates: int = 13, chunk: int = 8, border_px: int = 1,
    vote_scale_quantile: float = 0.5,
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
        The depth grid (:class:`cmax.warp.DepthGrid`).
    index, weight : Tensor (N, 4)
        Depth-grid nodes and bilinear weights of each event (:meth:`cmax.warp.DepthGrid.weights`).
    rho_range : (float, float)
        Smallest and largest inverse depth [1/m].
    candidates : int
        Inverse depths swept uniform in ``rho_range``, with the far-end ones that :func:`sweep_candidates` adds
        over a wide range (ratio ``exp(max(refinements))``), so that the refinements reach every depth.
    sigma : float
        IWE blur [px].
    polarity_split : bool
        One image per polarity (True) or one for all events.
    smoothness : (float, float)
        Semi-global matching penalties ``(P1, P2)`` of a step of one candidate
        and of a larger jump between neighbouring nodes, in units of the
        median node confidence; ``(0, 0)``: every node on its own.
    coarsening : int
        The sweep over the whole range runs on a grid this many times coarser
        than ``grid_shape`` (:func:`coarse_grid_shape`); 1: on the depth grid.
    refinements : tuple of float
        Half-widths (log of a factor) of relative sweeps on the depth grid
        after the first: every event's inverse depth is scaled by
        ``exp(step)``, steps in ``[-span, span]``, so the events of the other
        nodes stay in focus.
    refine_candidates : int
        Steps of each relative sweep.
    chunk : int
        Candidates warped at once (memory against speed).
    border_px, vote_scale_quantile
        Of the cost (:class:`cmax.contrast.SweepNodeCost`): events warped closer than ``border_px`` to the
        edge count as outside; the quantile of the events' largest values that an event pushed out of
        the image by some candidate is divided by.

    Returns
    -------
    DepthSweep
    """
    dtype = rays.dtype
    rhos = torch.as_tensor(sweep_candidates(rho_range, candidates, max(refinements, default=0.0)), dtype=dtype)
    N = rays.shape[0]
    coarse = coarse_grid_shape(grid_shape, int(coarsening))
    pixels = rays @ K.to(dtype).T                                             # (x, y, 1) of the events
    coarse_grid = DepthGrid(coarse, width, height)
    coarse_index, coarse_weight = coarse_grid.weights(pixels[:, 0], pixels[:, 1])
    with torch.no_grad():
        common = dict(height=height, width=width, sigma=sigma, polarity_split=polarity_split, chunk=chunk,
                      border_px=border_px, vote_scale_quantile=vote_scale_quantile)
        S = node_cost_function(rays, dt, polarity, v, omega, K, grid_shape=coarse, index=coarse_index,
                               weight=coarse_weight, **common)(rhos[:, None].expand(-1, N))  # (C, Gc)
        rho, confidence = _regularised_argmax(S, rhos, _node_events(coarse_index, coarse_weight, coarse),
                                              coarse, smoothness)
        rho = coarse_grid.resample(rho, grid_shape)
        node_events = _node_events(index, weight, grid_shape)
        cost = node_cost_function(rays, dt, polarity, v, omega, K, grid_shape=grid_shape, index=index,
                                  weight=weight, **common)
        for span in refinements:  # relative sweeps around the current grid: the other events stay in focus
            steps = torch.linspace(-span, span, refine_candidates, dtype=dtype)
            base = (rho[index] * weight).sum(-1)                                  # (N,)
            S_rel = relative_sweep_cost(cost, base, steps)
            step, _ = _regularised_argmax(S_rel, steps, node_events, grid_shape, smoothness)
            rho = (rho * torch.exp(step)).clamp(float(rhos[0]), float(rhos[-1]))
    return DepthSweep(rho.numpy().astype(np.float64), rhos.numpy().astype(np.float64), coarse,
                      S.numpy(), confidence.numpy())


def _node_events(index: torch.Tensor, weight: torch.Tensor, grid_shape: tuple[int, int]) -> torch.Tensor:
    """Bilinear weight of the events at each node (G,)."""
    G = grid_shape[0] * grid_shape[1]
    return torch.zeros(G, dtype=weight.dtype).index_add_(0, index.reshape(-1), weight.reshape(-1))


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
                       chunk: int = 8, border_px: int = 1, vote_scale_quantile: float = 0.5) -> SweepNodeCost:
    """The sweep's cost as a function: per-event inverse depths (C, N) [1/m] -> node costs (C, G), the
    contrast core's :class:`cmax.contrast.SweepNodeCost` (arguments as in :func:`sweep_inverse_depth`)."""
    return SweepNodeCost(rays, dt, polarity, v, omega, K, height, width, grid_shape, index, weight, sigma,
                         polarity_split, chunk, border_px, vote_scale_quantile)


def _regularised_argmax(S: torch.Tensor, values: torch.Tensor, node_events: torch.Tensor,
                        grid_shape: tuple[int, int], smoothness: tuple[float, float]
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """The value (G,) of each node from its cost curve in ``S`` (C, G) (higher is better), chosen by
    semi-global matching over the node grid, and each node's confidence (G,).

    Each curve is normalised to [0, 1] and weighted by its confidence; the
    matching cost ``confidence (1 - normalised)`` is aggregated along four
    scan-line directions with the penalties ``smoothness * median confidence``
    (:func:`_scanline_costs`), and the minimum is refined by a parabola.
    """
    gh, gw = grid_shape
    top, bottom = S.max(0).values, S.min(0).values
    confidence = node_events.sqrt() * (top - bottom) / top.clamp(min=1e-12)
    normalised = (S - bottom) / (top - bottom).clamp(min=1e-12)
    cost = (1.0 - normalised) * confidence                                       # (C, G)
    positive = confidence[confidence > 0]
    unit = float(positive.median()) if positive.numel() else 1.0
    p1, p2 = (float(p) * unit for p in smoothness)
    C = S.shape[0]
    volume = cost.view(C, gh, gw)
    total = (_scanline_costs(volume, p1, p2)                                      # top to bottom
             + _scanline_costs(volume.flip(1), p1, p2).flip(1)                   # bottom to top
             + _scanline_costs(volume.transpose(1, 2), p1, p2).transpose(1, 2)   # left to right
             + _scanline_costs(volume.transpose(1, 2).flip(1), p1, p2).flip(1).transpose(1, 2))
    return _parabolic_argmax(-total.reshape(C, gh * gw), values), confidence


def _scanline_costs(volume: torch.Tensor, p1: float, p2: float) -> torch.Tensor:
    """Semi-global matching along dim 1 of a cost volume (C, L, M): (C, L, M).

    ``L[:, i] = cost[:, i] + min(L[:, i-1], L[:, i-1] shifted by one candidate + p1, min L[:, i-1] + p2)
    - min L[:, i-1]`` (Hirschmüller 2008). A loop over the L <= 64 grid rows or
    columns, vectorised over candidates and the other axis; no library offers
    this recursion for an arbitrary cost volume (OpenCV's is inside StereoSGBM).
    """
    out = [volume[:, 0]]
    blocked = torch.full_like(volume[:1, 0], float("inf"))
    for i in range(1, volume.shape[1]):
        previous = out[-1]
        lowest = previous.min(0, keepdim=True).values
        neighbour = torch.minimum(torch.cat([previous[1:], blocked]), torch.cat([blocked, previous[:-1]])) + p1
        best = torch.minimum(torch.minimum(previous, neighbour), lowest + p2)
        out.append(volume[:, i] + best - lowest)
    return torch.stack(out, 1)


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
    offset = offset.clamp(-0.5, 0.5)                    # in candidates
    steps = torch.diff(rhos)
    if torch.allclose(steps, steps[0].expand_as(steps), rtol=1e-9, atol=0.0):
        rho = rhos[i] + offset * (rhos[1] - rhos[0])
    else:                                               # :func:`sweep_candidates` at a wide range: each side's own
        rho = rhos[i] + offset * torch.where(offset > 0, rhos[i + 1] - rhos[i], rhos[i] - rhos[i - 1])
    rho = torch.where(k == 0, rhos[0], torch.where(k == C - 1, rhos[-1], rho))
    return rho
